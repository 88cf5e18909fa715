"""The three ways out of a fold (docs/design.md section 3) each switched off in turn, on hard phantoms: the end
padding that ignores another turn beyond the end plane, the tilt, the shrink (margins at min_jacobian, the tissue
only under a quarter of it, the corner's deficit off the side that loses the least area).

The Jacobian is measured by central differences of ``Deformation.forward`` at the cage's four corners (not with
``jacobian_min``), the coverage with ``Deformation.inverse`` against the phantom's true arclength
(tests/test_fold_free.py's ``_held_at_own_place``).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import napari_unwind.skeleton._api as api
import napari_unwind.skeleton._foldfree as ff
from napari_unwind.datasets import hard_fish_phantom
from napari_unwind.deformation import Deformation, parallel_transport_frames
from napari_unwind.progress import run
from napari_unwind.skeleton import estimate_deformation_iter
from napari_unwind.skeleton._cage import fit_cages, propose_cage

try:
    from test_fold_free import _held_at_own_place
except ImportError:  # pragma: no cover - run from the repository's root
    from tests.test_fold_free import _held_at_own_place


def corner_jacobian(d: Deformation, step: float = 0.25) -> float:
    """The smallest det J over the cage's corners along s, by central differences of ``forward``."""
    s = np.arange(step / 2, d.length, step)
    b = d.bounds_at(s)
    h = 1e-4
    worst = np.inf
    for ix, iy in ((0, 2), (0, 3), (1, 2), (1, 3)):
        q = np.column_stack([b[:, ix], b[:, iy], s])
        jac = np.stack([(d.forward(q + h * e) - d.forward(q - h * e)) / (2 * h) for e in np.eye(3)], axis=2)
        worst = min(worst, float(np.linalg.det(jac).min()))
    return worst


def _solve(ph):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run(estimate_deformation_iter(ph.mask, (ph.head, ph.tail), spacing=ph.spacing, volume=ph.volume))


# ------------------------------------------------------------------------------------------------------------------
# the padding: another turn beyond the end plane is not the tip
# ------------------------------------------------------------------------------------------------------------------
def _rod_and_blob(blob: bool):
    """A rod of radius 3 along axis0 from voxel 5 to 40 (the curve ends at its tip, 40), and a separate blob beyond
    the end plane, 6-8 voxels past it and 5-7 voxels off the axis (a piece of another turn of a coil passing there,
    small enough not to be taken for another specimen)."""
    mask = np.zeros((60, 40, 40), dtype=bool)
    z, y, x = np.mgrid[:60, :40, :40]
    mask |= ((y - 20) ** 2 + (x - 20) ** 2 <= 9) & (z >= 5) & (z <= 40)
    if blob:
        mask |= (z >= 46) & (z <= 48) & (y >= 25) & (y <= 27) & (x >= 19) & (x <= 21)
    pts = np.stack([np.arange(5.0, 41.0), np.full(36, 20.0), np.full(36, 20.0)], axis=1)
    return mask, pts, parallel_transport_frames(pts, up=(0, 1, 0))


def test_the_padding_and_the_end_cage_ignore_another_turn_beyond_the_end():
    mask, pts, frames = _rod_and_blob(True)
    plain, _, _ = _rod_and_blob(False)
    he, pad = propose_cage(mask, pts, frames, spacing=1.0, margin=0.0, min_margin=0.0, end_margin=0.0)
    he0, pad0 = propose_cage(plain, pts, frames, spacing=1.0, margin=0.0, min_margin=0.0, end_margin=0.0)
    # the rod's own figures (by hand: radius 3 about the axis, the tip on the end plane) with or without the blob
    assert pad == pad0 == (0.0, 0.0)
    assert he == he0 == (3.0, 3.0)
    keys = [0, 17, 35]
    np.testing.assert_allclose(fit_cages(mask, pts, frames, keys, spacing=1.0, margin=0.0, min_margin=0.0),
                               np.tile([-3.0, 3.0, -3.0, 3.0], (3, 1)))
    # a curve stopping 3 voxels short of the tip keeps the tip beyond its end (joined to it)
    short = slice(0, 33)
    _, pad_s = propose_cage(mask, pts[short], frames[short], spacing=1.0, margin=0.0, min_margin=0.0,
                            end_margin=0.0)
    assert pad_s[1] == pytest.approx(3.0)


# ------------------------------------------------------------------------------------------------------------------
# the tilt and the shrink, switched off
# ------------------------------------------------------------------------------------------------------------------
def test_the_tilt_keeps_the_jacobian_above_min_jacobian_on_a_tight_s_bend(monkeypatch):
    """S-bend 1003: with the tilt the map keeps det J >= 0.2 (the default min_jacobian) at every cage corner and
    holds the mask; with every window 0 the same tissue is held only by letting det J fall to a quarter of it."""
    ph = hard_fish_phantom(1003, kind="s-bend")
    r = _solve(ph)
    tilted = corner_jacobian(r.deformation)
    assert tilted >= 0.2 - 1e-3 and _held_at_own_place(r.deformation, ph) >= 0.99
    tilt = ff.tilted_frames
    monkeypatch.setattr(ff, "tilted_frames", lambda f, a, k, sigma, **kw: tilt(f, a, k, np.zeros_like(sigma), **kw))
    r0 = _solve(ph)
    flat = corner_jacobian(r0.deformation)
    assert 0.0 < flat < 0.1, (tilted, flat)


@pytest.fixture(scope="module")
def helix_1011():
    return hard_fish_phantom(1011, kind="helix")  # the tightest helix of the 30: radius 1.33 half-heights


def test_the_shrink_unfolds_a_tight_helix_and_keeps_its_tissue(helix_1011):
    r = _solve(helix_1011)
    assert corner_jacobian(r.deformation) > 0.04
    assert _held_at_own_place(r.deformation, helix_1011) >= 0.99


def test_without_the_shrink_the_tight_helix_folds(helix_1011, monkeypatch):
    monkeypatch.setattr(api, "unfold", lambda d, **_: d)
    r = _solve(helix_1011)
    assert corner_jacobian(r.deformation) < 0.0


@pytest.mark.parametrize("planted", ["tissue cut at min_jacobian", "least length"])
def test_the_tissue_is_lost_when_the_shrink_cuts_it_like_a_margin(helix_1011, monkeypatch, planted):
    """Before: the tissue's sides were shrunk like the margins (det J >= 0.2), or with the corner's deficit off
    the faster side. Held of this helix, the method / the planted variant: 0.9955 / 0.988 and 0.992 (0.968 and
    0.988 before the twist read its sections up to the crop's faces). The second variant now stays above the 0.99
    goal, so both are judged against the method itself on the same helix: each must lose at least 0.2 % more."""
    held = _held_at_own_place(_solve(helix_1011).deformation, helix_1011)
    if planted == "tissue cut at min_jacobian":
        monkeypatch.setattr(api, "_TISSUE_JACOBIAN", 1.0)
    else:
        shrink = ff.unfold
        monkeypatch.setattr(api, "unfold", lambda d, **kw: shrink(d, **{**kw, "least": "length"}))
    r = _solve(helix_1011)
    assert corner_jacobian(r.deformation) > 0.04
    assert _held_at_own_place(r.deformation, helix_1011) < held - 0.002, held


def test_same_mask_same_keyframes(helix_1011):
    a, b = _solve(helix_1011).deformation, _solve(helix_1011).deformation
    assert a.to_dict() == b.to_dict()


def test_unfold_by_least_area_cuts_the_tall_side_of_a_tall_cage():
    """The arc of tests/test_fold_free.py turned by 30 degrees about n (det J = cos(h) - x kx + y ky at the inner
    corner x_hi, y_lo; x turns faster, kx = k cos 30 > ky = k sin 30) with a tall cage, x in [-3, 8], y in
    [-30, 3]. By length the faster x side goes first, onto the curve, and y_lo takes the rest; by area (rate over
    the other side's length: kx / 33 < ky / 11) y_lo alone is cut, to where det J = eps with x_hi = 8 kept."""
    from test_fold_free import _turned_arc

    radius, eps, cage = 10.0, 0.2, (-3.0, 8.0, -30.0, 3.0)
    d, base, k = _turned_arc(radius, np.radians(30.0), cage)
    assert d.folds()
    kx, ky = k * np.cos(np.radians(30.0)), k * np.sin(np.radians(30.0))
    m = base - eps
    by_area = ff.unfold(d, eps=eps, least="area").bounds
    np.testing.assert_allclose(by_area, np.tile([-3.0, 8.0, -(m - 8.0 * kx) / ky, 3.0], (len(d), 1)), rtol=1e-9,
                               atol=1e-9)
    by_length = ff.unfold(d, eps=eps).bounds
    np.testing.assert_allclose(by_length[:, 1], 0.0, atol=1e-4)  # x_hi onto the curve (a sliver)
    np.testing.assert_allclose(by_length[:, 2], -m / ky, rtol=1e-9)
    with pytest.raises(ValueError, match="least"):
        ff.unfold(d, eps=eps, least="volume")


def test_the_loss_on_the_inside_of_a_tight_bend_is_told_from_a_cage_too_small():
    """A lost interval is the bend's when it meets the two segments of a keyframe whose cage the fold-free
    construction shrank to within half a voxel of the tissue or into it (the fitted cage lies two voxels beyond
    it at least): figures by hand."""
    knots = np.array([0.0, 10.0, 20.0, 30.0, 40.0])
    tissue = np.tile([-5.0, 5.0, -4.0, 4.0], (5, 1))
    fitted = tissue + np.array([-2.0, 2.0, -2.0, 2.0])  # two voxels of margin
    lost = ((12.0, 14.0, 0.01), (29.0, 31.0, 0.005), (35.0, 38.0, 0.02))
    assert api._bend_lost(fitted, tissue, knots, lost, 1.0) == (0.0, ())  # no bend shrank a cage
    shrunk = fitted.copy()
    shrunk[2, 3] = 4.3  # the third keyframe's upper v side: its margin given up
    share, at = api._bend_lost(shrunk, tissue, knots, lost, 1.0)
    assert at == lost[:2] and share == pytest.approx(0.015)  # its two segments, s = 10..30, not s = 35..38
    shrunk[2, 3] = 3.0  # into the tissue
    assert api._bend_lost(shrunk, tissue, knots, lost, 1.0) == (pytest.approx(0.015), lost[:2])
    shrunk[2, 3] = 4.6  # a margin of more than half a voxel kept
    assert api._bend_lost(shrunk, tissue, knots, lost, 1.0) == (0.0, ())
    shrunk[0, 0] = -5.2  # the first keyframe's lower u side: its one segment, s = 0..10
    assert api._bend_lost(shrunk, tissue, knots, lost, 1.0) == (0.0, ())
    assert api._bend_lost(shrunk, tissue, knots, ((9.0, 11.0, 0.01),), 1.0) == (0.01, ((9.0, 11.0, 0.01),))
    assert api._bend_lost(shrunk, tissue, knots, lost, 2.0) == (pytest.approx(0.015), lost[:2])  # 0.6 < a voxel's half
    assert api._bend_lost(shrunk, None, knots, lost, 1.0) == (0.0, ())  # a cage given: no tissue to compare
