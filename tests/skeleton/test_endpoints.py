"""Suggested head and tail, and clicks snapped into the mask (napari_unwind.skeleton._endpoints)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from napari_unwind.datasets import fish_phantom, hard_fish_phantom, tank_phantom
from napari_unwind.errors import InvalidInputError
from napari_unwind.skeleton._endpoints import snap_to_mask, suggest_endpoints

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
BODY_RADIUS = 8.0


def _check_ends(mask, spacing, head, tail, true_head, true_tail, *, slack=3.0):
    """Both points inside the mask, each near its true end (body radius + 3 voxels), and not swapped."""
    sp = np.asarray(spacing, dtype=float)
    for p in (head, tail):
        assert p.shape == (3,)
        assert mask[tuple(np.round(p).astype(int))], f"{p} is not in the mask"
    d_head = np.linalg.norm((head - true_head) * sp)
    d_tail = np.linalg.norm((tail - true_tail) * sp)
    bound = BODY_RADIUS + slack * sp.max()
    assert d_head <= bound, f"head {head} is {d_head:.3g} from the true head {true_head}"
    assert d_tail <= bound, f"tail {tail} is {d_tail:.3g} from the true tail {true_tail}"
    assert np.linalg.norm((head - true_tail) * sp) > 5 * bound  # not swapped


@pytest.mark.parametrize(
    ("curve", "roll", "spacing"),
    [
        ("s-bend", 0.0, 1.0),
        ("c-bend", 2.0, 1.0),
        ("helix", 1.0, 1.0),
        ("s-bend", 2.0, (2.0, 1.0, 1.0)),
        ("c-bend", 0.5, (1.0, 1.5, 1.0)),
        ("helix", 3.0, (1.0, 1.0, 2.0)),
    ],
)
def test_fish_phantom_ends(curve, roll, spacing):
    ph = fish_phantom(curve=curve, roll=roll, twist=1.0, spacing=spacing, body_radius=BODY_RADIUS)
    # the tips of the mask are where the truth says: c(0) and c(L) lie on the mask's flat end caps
    for end in (ph.head, ph.tail):
        inside = np.argwhere(ph.mask)
        assert np.linalg.norm((inside - end) * ph.spacing, axis=1).min() <= 1.5 * max(ph.spacing)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clear fish: no warning
        head, tail = suggest_endpoints(ph.mask, spacing=ph.spacing)
    _check_ends(ph.mask, ph.spacing, head, tail, ph.head, ph.tail)
    # the same fish facing the other way along axis0: the head is still found at the thick end
    flip = ph.mask[::-1]
    n0 = ph.mask.shape[0] - 1
    head_r, tail_r = suggest_endpoints(flip, spacing=ph.spacing)
    mirror = np.array([-1.0, 1.0, 1.0])
    offset = np.array([n0, 0.0, 0.0])
    _check_ends(flip, ph.spacing, head_r, tail_r, ph.head * mirror + offset, ph.tail * mirror + offset)


def test_tank_fish():
    tank = tank_phantom(n_fish=3, seed=5, body_radius=BODY_RADIUS)
    for i, ph in enumerate(tank.fish):
        mask = tank.labels == i + 1
        head, tail = suggest_endpoints(mask, spacing=tank.spacing, volume=tank.volume)
        _check_ends(mask, tank.spacing, head, tail, ph.head, ph.tail)


def _shortfall(ph, mask, spacing, point, end):
    """How far (in voxels of the coarsest axis) a suggested end stops short of the specimen's end in the scan,
    along its true centreline: the phantom's arclength of the point against that of the mask's extreme voxels."""
    sp = np.asarray(spacing, dtype=float) * np.ones(3)
    tree = cKDTree(ph.centerline_physical)
    s_mask = ph.arclength[tree.query(np.argwhere(mask) * sp)[1]]
    s = ph.arclength[tree.query(point * sp)[1]]
    return float((s - s_mask.min()) if end == "head" else (s_mask.max() - s)) / sp.max()


@pytest.mark.parametrize("source", ["dense tank 0", "dense tank 1", "dense tank 2", "hard 0", "hard 21", "hard 5"])
def test_the_ends_reach_the_tips_of_a_thin_tail(source):
    """A fish's tail tapers to 1 voxel of half width in a dense tank: the suggested tail is at its tip, not where
    the body is still 2 voxels thick (19 voxels short, the old rule), so the centreline spans the whole fish."""
    kind, seed = source.rsplit(" ", 1)
    if kind == "dense tank":
        tank = tank_phantom(n_fish=3, seed=int(seed), wall_value=3000, wall_thickness=6, wall_noise=600)
        cases = [(ph, tank.labels == i + 1, tank.volume) for i, ph in enumerate(tank.fish)]
        spacing = tank.spacing
    else:
        ph = hard_fish_phantom(int(seed))
        cases, spacing = [(ph, ph.mask, ph.volume)], ph.spacing
    for ph, mask, volume in cases:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            head, tail = suggest_endpoints(mask, spacing=spacing, volume=volume)
        short_head = _shortfall(ph, mask, spacing, head, "head")
        short_tail = _shortfall(ph, mask, spacing, tail, "tail")
        assert short_tail <= 2.0, f"{ph.name}: the tail stops {short_tail:.1f} voxels short of the tip"
        assert short_head <= 4.0, f"{ph.name}: the head stops {short_head:.1f} voxels short of the tip"


def test_several_parts_use_the_largest_and_warn():
    ph = fish_phantom(curve="s-bend", body_radius=BODY_RADIUS, noise=0.0, tube=False)
    mask = ph.mask.copy()
    mask[2:6, 2:6, 2:6] = True  # a speck far from the fish
    with pytest.warns(UserWarning, match="2 separate parts"):
        head, tail = suggest_endpoints(mask, spacing=ph.spacing)
    _check_ends(ph.mask, ph.spacing, head, tail, ph.head, ph.tail)


def _rod(length=60, radius=5, pad=6):
    g = np.mgrid[: length + 2 * pad, : 2 * radius + 2 * pad + 1, : 2 * radius + 2 * pad + 1]
    c = radius + pad
    mask = ((g[1] - c) ** 2 + (g[2] - c) ** 2 <= radius**2) & (g[0] >= pad) & (g[0] < pad + length)
    return mask


def test_equal_ends_tie_broken_by_density():
    mask = _rod()
    with pytest.warns(UserWarning, match="may be swapped"):
        suggest_endpoints(mask, spacing=1.0)
    for dense_end in ("low", "high"):
        volume = np.full(mask.shape, 1000, dtype=np.uint16)
        if dense_end == "low":
            volume[:20] = 2500  # a "skull" at small axis0
        else:
            volume[-20:] = 2500
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            head, tail = suggest_endpoints(mask, spacing=1.0, volume=volume)
        assert (head[0] < tail[0]) == (dense_end == "low")


def test_thin_specimen_stays_connected():
    # a rod one voxel thick and 300 long: the coarse copy must keep it in one piece
    mask = np.zeros((310, 5, 5), dtype=bool)
    mask[5:305, 2, 2] = True
    with pytest.warns(UserWarning, match="may be swapped"):  # a symmetric rod
        head, tail = suggest_endpoints(mask, spacing=1.0, max_side=32)
    assert sorted([head[0], tail[0]]) == pytest.approx([5, 304], abs=3)
    assert mask[tuple(head.astype(int))] and mask[tuple(tail.astype(int))]


def test_sphere_and_blobs_have_no_axis():
    g = np.mgrid[:50, :50, :50]
    sphere = ((g - 25) ** 2).sum(0) <= 20**2
    with pytest.raises(InvalidInputError, match="no head-tail axis"):
        suggest_endpoints(sphere, spacing=1.0)
    # anisotropic voxels: a ball in physical units is not a ball in index units
    g = np.mgrid[:26, :50, :50]
    ball = ((g[0] - 13) * 2.0) ** 2 + (g[1] - 25) ** 2 + (g[2] - 25) ** 2 <= 20**2
    with pytest.raises(InvalidInputError, match="nearly spherical"):
        suggest_endpoints(ball, spacing=(2.0, 1.0, 1.0))
    # ... while a 2:1 ellipsoid is elongated enough
    ell = ((g[0] - 13) * 2.0 / 24) ** 2 + ((g[1] - 25) / 12) ** 2 + ((g[2] - 25) / 12) ** 2 <= 1
    with pytest.warns(UserWarning, match="may be swapped"):  # symmetric
        head, tail = suggest_endpoints(ell, spacing=(2.0, 1.0, 1.0))
    assert abs(head[0] - tail[0]) * 2.0 > 30


def test_empty_and_malformed_masks():
    with pytest.raises(InvalidInputError, match="empty"):
        suggest_endpoints(np.zeros((10, 10, 10), bool), spacing=1.0)
    with pytest.raises(InvalidInputError, match="3D"):
        suggest_endpoints(np.ones((10, 10), bool), spacing=1.0)
    with pytest.raises(InvalidInputError, match="spacing"):
        suggest_endpoints(_rod(), spacing=(1.0, -1.0, 1.0))
    with pytest.raises(InvalidInputError, match="max_side"):
        suggest_endpoints(_rod(), spacing=1.0, max_side=4)
    with pytest.raises(InvalidInputError, match="volume"):
        suggest_endpoints(_rod(), spacing=1.0, volume=np.zeros((3, 3, 3)))


def test_real_spinal_cord():
    if not DATA.is_dir():
        pytest.skip(f"real scans not available ({DATA} is absent)")
    nrrd = pytest.importorskip("nrrd")
    mask, header = nrrd.read(str(DATA / "spine_t2_cord_mask.nrrd"), index_order="C")
    spacing = np.abs(np.diag(np.asarray(header["space directions"], dtype=float)))
    line = np.loadtxt(DATA / "spine_t2_centerline_manual.csv", delimiter=",", skiprows=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the cord is about as thick at both ends
        ends = suggest_endpoints(mask, spacing=spacing)
    # the two suggestions are near the two ends of the manual centreline (in either order)
    d = [[np.linalg.norm((e - ref) * spacing) for ref in (line[0], line[-1])] for e in ends]
    assert min(d[0][0] + d[1][1], d[0][1] + d[1][0]) <= 2 * 6.0
    for e in ends:
        assert mask[tuple(np.round(e).astype(int))]


# ------------------------------------------------------------------------------------------------------------------
# snapping
# ------------------------------------------------------------------------------------------------------------------
def test_snap_inside_is_unchanged():
    mask = _rod()
    p = np.array([30.2, 11.4, 10.6])
    assert mask[tuple(np.round(p).astype(int))]
    q, d = snap_to_mask(p, mask, spacing=1.0, tolerance=0.0)
    np.testing.assert_array_equal(q, p)
    assert d == 0.0


@pytest.mark.parametrize("spacing", [1.0, (1.0, 3.0, 0.5)])
def test_snap_outside_moves_to_the_nearest_voxel(spacing):
    mask = _rod()
    sp = np.broadcast_to(np.asarray(spacing, float), (3,))
    rng = np.random.default_rng(0)
    voxels = np.argwhere(mask)
    for p in rng.uniform([0, 0, 0], np.asarray(mask.shape) - 1, size=(30, 3)):
        if mask[tuple(np.round(p).astype(int))]:
            continue
        dist = np.linalg.norm((voxels - p) * sp, axis=1)  # brute force reference
        q, d = snap_to_mask(p, mask, spacing=spacing, tolerance=float(dist.min()) + 1e-9)
        assert d == pytest.approx(dist.min())
        assert mask[tuple(q.astype(int))]
        assert np.linalg.norm((q - p) * sp) == pytest.approx(dist.min())


def test_snap_too_far_and_outside_the_volume():
    mask = _rod()
    p = (30.0, 0.0, 0.0)
    with pytest.raises(InvalidInputError, match=r"is (\d|\.)+ away from the mask, more than the tolerance 2") as err:
        snap_to_mask(p, mask, spacing=1.0, tolerance=2.0)
    assert "[30.0, 0.0, 0.0]" in str(err.value)
    with pytest.raises(InvalidInputError, match=r"outside the volume of shape \(72, 23, 23\)"):
        snap_to_mask((30.0, -3.0, 5.0), mask, spacing=1.0, tolerance=100.0)
    with pytest.raises(InvalidInputError, match="3 finite"):
        snap_to_mask((30.0, np.nan, 5.0), mask, spacing=1.0, tolerance=1.0)
    with pytest.raises(InvalidInputError, match="tolerance"):
        snap_to_mask((30.0, 1.0, 5.0), mask, spacing=1.0, tolerance=-1.0)
    with pytest.raises(InvalidInputError, match="empty"):
        snap_to_mask((3.0, 1.0, 5.0), np.zeros_like(mask), spacing=1.0, tolerance=1.0)
