"""Cage half-extents and end padding (napari_unwind.skeleton._cage), checked with the Deformation's inverse map."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from napari_unwind.datasets import fish_phantom
from napari_unwind.deformation import Deformation
from napari_unwind.errors import InvalidInputError
from napari_unwind.skeleton._cage import propose_cage


@functools.cache
def _fish(curve: str, spacing=1.0, twist: float = 2.0, roll: float = 0.7):
    return fish_phantom(curve=curve, twist=twist, roll=roll, spacing=spacing, noise=0.0, tube=False)


def _true_extent(ph):
    """The specimen's own half extent: the phantom's cage minus the 2-voxel pad it adds."""
    return np.asarray(ph.half_extent) - 2.0 * max(ph.spacing)


def _all_inside(ph, pts, frames, he, pad, mask=None):
    """Fraction of the mask's voxels that the cage holds, by the Deformation's own inverse map."""
    mask = ph.mask if mask is None else mask
    d = Deformation.from_keyframes(pts, frames, he, pad=pad, spacing=ph.spacing)
    inv = d.inverse(np.argwhere(mask) * np.asarray(ph.spacing))
    return inv.inside


@pytest.mark.parametrize(("curve", "spacing"), [("s-bend", 1.0), ("c-bend", (2.0, 1.0, 1.0)), ("helix", 1.0)])
def test_cage_holds_the_whole_fish(curve, spacing):
    ph = _fish(curve, spacing)
    pts, frames = ph.centerline_physical[::2], ph.frames[::2]
    (rx, ry), (before, after) = propose_cage(ph.mask, pts, frames, spacing=ph.spacing)
    true_rx, true_ry = _true_extent(ph)
    vox = max(ph.spacing)
    # at least the true extent (fin included), at most 1.5 x it plus the default margin (10 % + 2 voxels)
    assert true_rx <= rx <= 1.5 * true_rx * 1.1 + 2 * vox
    assert true_ry <= ry <= 1.5 * true_ry * 1.1 + 2 * vox
    # the curve reaches both tips: only the end margin is padded
    assert before == pytest.approx(2 * vox, abs=0.6 * vox)
    assert after == pytest.approx(2 * vox, abs=0.6 * vox)
    inside = _all_inside(ph, pts, frames, (rx, ry), (before, after))
    assert inside.all(), f"{(~inside).sum()} mask voxels outside the cage"


def test_margins_are_applied():
    ph = _fish("s-bend")
    pts, frames = ph.centerline_physical[::2], ph.frames[::2]
    (rx0, ry0), (b0, a0) = propose_cage(ph.mask, pts, frames, spacing=ph.spacing, margin=0.0, min_margin=0.0,
                                        end_margin=0.0)
    (rx1, ry1), (b1, a1) = propose_cage(ph.mask, pts, frames, spacing=ph.spacing, margin=0.2, min_margin=1.5,
                                        end_margin=3.0)
    assert rx1 == pytest.approx(1.2 * rx0 + 1.5) and ry1 == pytest.approx(1.2 * ry0 + 1.5)
    assert (b1, a1) == pytest.approx((b0 + 3.0, a0 + 3.0))
    # without margins the cage is the voxel-centre extent: within a voxel of the true extent
    np.testing.assert_allclose([rx0, ry0], _true_extent(ph), atol=1.0)


@pytest.mark.parametrize("curve", ["s-bend", "helix"])
def test_truncated_curve_is_padded(curve):
    ph = _fish(curve)
    k = len(ph.arclength)
    cut = int(0.1 * k)
    pts, frames = ph.centerline_physical[cut:k - cut:2], ph.frames[cut:k - cut:2]
    missing_head = ph.arclength[cut]
    missing_tail = ph.length - ph.arclength[k - cut - 1]
    he, (before, after) = propose_cage(ph.mask, pts, frames, spacing=ph.spacing)
    # the body beyond each end of the curve (0.1 L each) is covered by the padding
    assert before >= 0.9 * missing_head and after >= 0.9 * missing_tail
    assert before <= missing_head + 4 and after <= missing_tail + 4
    inside = _all_inside(ph, pts, frames, he, (before, after))
    assert inside.all(), f"{(~inside).sum()} mask voxels outside the cage"


def test_sparse_keyframes():
    # keyframes 20 voxels apart: the frames between them are SLERPed, as the Deformation does
    ph = _fish("c-bend")
    idx = np.unique(np.r_[0:len(ph.arclength):40, len(ph.arclength) - 1])
    pts, frames = ph.centerline_physical[idx], ph.frames[idx]
    he, pad = propose_cage(ph.mask, pts, frames, spacing=ph.spacing)
    assert _all_inside(ph, pts, frames, he, pad).all()


def test_stray_voxels_are_ignored():
    ph = _fish("s-bend")
    pts, frames = ph.centerline_physical[::2], ph.frames[::2]
    clean = propose_cage(ph.mask, pts, frames, spacing=ph.spacing)
    noisy = ph.mask.copy()
    noisy[0, 0, 0] = noisy[-1, 3, 5] = noisy[40, 0, -1] = True  # specks in the corners
    (rx, ry), pad = propose_cage(noisy, pts, frames, spacing=ph.spacing)
    assert (rx, ry, *pad) == pytest.approx((*clean[0], *clean[1]))
    # a real part of the specimen (a detached fin of many voxels) is kept
    big = ph.mask.copy()
    big[75:85, :4, :4] = True
    (rx, ry), _ = propose_cage(big, pts, frames, spacing=ph.spacing)
    assert max(rx, ry) > max(clean[0]) + 5


def test_validation():
    ph = _fish("s-bend")
    pts, frames = ph.centerline_physical[::2], ph.frames[::2]
    with pytest.raises(InvalidInputError, match="empty"):
        propose_cage(np.zeros_like(ph.mask), pts, frames, spacing=ph.spacing)
    with pytest.raises(InvalidInputError, match="3D"):
        propose_cage(ph.mask[0], pts, frames, spacing=ph.spacing)
    with pytest.raises(InvalidInputError, match="frames must have shape"):
        propose_cage(ph.mask, pts, frames[1:], spacing=ph.spacing)
    with pytest.raises(InvalidInputError, match=r"shape \(K, 3\)"):
        propose_cage(ph.mask, pts[:1], frames[:1], spacing=ph.spacing)
    with pytest.raises(InvalidInputError, match="margin"):
        propose_cage(ph.mask, pts, frames, spacing=ph.spacing, margin=-0.1)
    with pytest.raises(InvalidInputError, match="end_margin"):
        propose_cage(ph.mask, pts, frames, spacing=ph.spacing, end_margin=float("nan"))
    with pytest.raises(InvalidInputError, match="spacing"):
        propose_cage(ph.mask, pts, frames, spacing=(1.0, 1.0))


def test_another_specimen_in_the_mask_does_not_widen_the_cage():
    """Issue 10: the cage holds the body the curve runs through, not a neighbouring specimen the mask also holds
    (its voxels are nearest to this curve's points all the same)."""
    ph = _fish("s-bend")
    pts, frames = ph.centerline_physical[::2], ph.frames[::2]
    clean = propose_cage(ph.mask, pts, frames, spacing=ph.spacing)
    # a second specimen: the fish's own body, 40 % of it, moved beside it along axis2, touching nothing
    other = np.zeros_like(ph.mask)
    body = np.argwhere(ph.mask)
    part = body[body[:, 0] < np.percentile(body[:, 0], 40)]
    shift = int(part[:, 2].max() - body[:, 2].min()) + 3
    pad = np.zeros((ph.mask.shape[0], ph.mask.shape[1], shift + 3), dtype=bool)
    both = np.concatenate([ph.mask, pad], axis=2)
    other = np.zeros_like(both)
    other[part[:, 0], part[:, 1], part[:, 2] + shift] = True
    assert not (other & both).any() and other.sum() > 0.1 * ph.mask.sum()
    with_other = propose_cage(both | other, pts, frames, spacing=ph.spacing)
    assert (*with_other[0], *with_other[1]) == pytest.approx((*clean[0], *clean[1]))


@pytest.mark.parametrize("seed", range(6))
def test_nearest_labels_matches_the_distance_transform(seed):
    """The part nearest to a point outside the mask: KD-tree of the surface against scipy's exact EDT."""
    from scipy import ndimage

    from napari_unwind.skeleton._cage import _nearest_labels

    rng = np.random.default_rng(seed)
    blobs = ndimage.gaussian_filter(rng.random((40, 36, 30)), 2.5)
    labels, n = ndimage.label(blobs > np.quantile(blobs, 0.85))
    assert n >= 2
    outside = np.argwhere(labels == 0)
    pts = outside[rng.choice(len(outside), 200, replace=False)]
    dist, near = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    expected = labels[tuple(near[:, pts[:, 0], pts[:, 1], pts[:, 2]])]
    got = _nearest_labels(labels, pts)
    # ties (two parts at the same distance) may go either way: then the chosen part must be as near
    same = got == expected
    if not same.all():
        for p, g in zip(pts[~same], got[~same]):
            d_g = np.sqrt(((np.argwhere(labels == g) - p) ** 2).sum(1)).min()
            assert abs(d_g - dist[tuple(p)]) < 1e-9
    assert same.mean() > 0.9
