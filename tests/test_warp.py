"""Straightening, bending back and point mapping, each checked against an independent reference.

References: scipy.ndimage.map_coordinates over the WHOLE volume with coordinates from ``Deformation.forward`` on
the output grid (computed here, not by the code under test), index arithmetic for identity frames, the phantoms'
analytic ground truth, and ``Deformation.inverse`` for the inverse map.
"""

from __future__ import annotations

import pickle
import threading
import warnings

import dask
import dask.array as da
import numpy as np
import pytest
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from napari_unwind.datasets import cylinder_phantom
from napari_unwind.deformation import Deformation
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume, open_volume
from napari_unwind.warp import (
    ORDER3_FILTER_MARGIN,
    FoldWarning,
    OutsideWarning,
    bend,
    export,
    export_iter,
    map_labels,
    map_mesh,
    map_points,
    straighten,
)

#: Order-3 tolerance against scipy on the whole volume, relative to the data range (the truncated prefilter
#: differs by about 0.268 ** ORDER3_FILTER_MARGIN of the local range; see napari_unwind.warp).
ORDER3_REL_TOL = 1e-3


# ------------------------------------------------------------------------------------------------------------------
# helpers (independent of the code under test)
# ------------------------------------------------------------------------------------------------------------------
def reference_coords(d: Deformation, ds: float, pad_slices: int = 0) -> np.ndarray:
    """Scan voxel coordinates (3, Ns, Ny, Nx) of the straight grid, from Deformation.forward."""
    lo = d.s_range[0] - pad_slices * ds
    hi = d.s_range[1] + pad_slices * ds
    ns = int(np.floor((hi - lo) / ds + 1e-9)) + 1
    rx, ry = d.max_half_extent
    ny, nx = 2 * int(np.ceil(ry / ds - 1e-9)) + 1, 2 * int(np.ceil(rx / ds - 1e-9)) + 1
    k, i, j = np.meshgrid(np.arange(ns), np.arange(ny), np.arange(nx), indexing="ij")
    xys = np.stack([(j - (nx - 1) / 2) * ds, (i - (ny - 1) / 2) * ds, lo + k * ds], axis=-1).reshape(-1, 3)
    phys = d.forward(xys)
    vox = (phys - np.asarray(d.origin)) / np.asarray(d.spacing)
    return vox.T.reshape(3, ns, ny, nx)


def smooth_volume(shape, seed=0, sigma=3.0, dtype=np.float32, lo=0.0, hi=1.0):
    rng = np.random.default_rng(seed)
    v = ndi.gaussian_filter(rng.random(shape), sigma)
    v = (v - v.min()) / np.ptp(v)
    return (lo + (hi - lo) * v).astype(dtype)


def random_deformation(seed, shape, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), cage=(6.0, 4.0)):
    """A smooth random curve through the volume (some of its cage outside it), random twist; no folds."""
    rng = np.random.default_rng(seed)
    sp = np.asarray(spacing)
    ext = np.asarray(shape) * sp
    for _ in range(50):
        start = ext * rng.uniform(0.1, 0.3, 3)
        end = ext * rng.uniform(0.7, 0.95, 3)
        t = np.linspace(0, 1, 6)[:, None]
        perp = rng.normal(size=3)
        wiggle = np.sin(np.pi * t) * perp * 0.08 * ext.min()
        pts_phys = start + t * (end - start) + wiggle
        d = Deformation.from_polyline((pts_phys - origin) / sp, spacing=spacing, cage_half_extent=cage,
                                      origin=origin, unit="micrometer")
        d = d.twist_keyframe(2, rng.uniform(-0.6, 0.6)).tilt_keyframe(3, rng.uniform(-0.2, 0.2))
        if not d.folds():
            return d
    raise AssertionError("no fold-free random deformation found")


# ------------------------------------------------------------------------------------------------------------------
# accuracy
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("order", [0, 1, 3])
def test_straight_curve_with_identity_frames_reproduces_input(order):
    vol = smooth_volume((30, 28, 50), seed=1, dtype=np.float32) if order == 3 else \
        np.random.default_rng(1).integers(0, 60000, (30, 28, 50)).astype(np.uint16)
    # centre line along axis2 at (14, 12), frames u = axis0, v = axis1, n = axis2 (the identity)
    pos = np.array([[14.0, 12.0, 5.0], [14.0, 12.0, 25.0], [14.0, 12.0, 41.0]])
    d = Deformation.from_keyframes(pos, np.repeat(np.eye(3)[None], 3, axis=0), (6.0, 5.0))
    out = straighten(vol, d, order=order, chunks=(7, 5, 6))
    assert out.shape == (37, 11, 13)
    # straight voxel (k, i, j) is scan voxel (14 - 6 + j, 12 - 5 + i, 5 + k)
    expected = vol[8:21, 7:18, 5:42].transpose(2, 1, 0)
    got = out.data.compute()
    if order == 3:
        # the interior of a cubic B-spline at the knots reproduces the data; the region prefilter is truncated
        np.testing.assert_allclose(got, expected, atol=ORDER3_REL_TOL)
    else:
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("order", [0, 1, 3])
def test_random_smooth_deformations_match_scipy_on_the_whole_volume(seed, order):
    shape = (34, 30, 40)
    spacing = [(1.0, 1.0, 1.0), (1.5, 1.0, 0.8), (0.7, 0.9, 1.1)][seed]
    origin = [(0.0, 0.0, 0.0), (-3.0, 10.0, 2.5), (5.0, -2.0, 0.0)][seed]
    vol = smooth_volume(shape, seed=seed)
    d = random_deformation(seed, shape, spacing, origin)
    ds = [None, 0.9, 0.6][seed]
    pad = [0, 2, 1][seed]
    v = Volume(da.from_array(vol, chunks=(9, 11, 13)), spacing=spacing, origin=origin, unit="um")
    out = straighten(v, d, order=order, spacing=ds, pad=pad, fill=-0.5, chunks=(6, 7, 8))
    ds_eff = min(spacing) if ds is None else ds
    coords = reference_coords(d, ds_eff, pad)
    ref = ndi.map_coordinates(vol, coords, order=order, mode="constant", cval=-0.5)
    got = out.data.compute()
    assert got.shape == ref.shape and got.dtype == vol.dtype
    outside = ref == np.float32(-0.5)
    assert 0.02 < outside.mean() < 0.9, "the test geometry should sample both inside and outside the scan"
    if order == 0:
        np.testing.assert_array_equal(got, ref)
    elif order == 1:
        np.testing.assert_allclose(got, ref, atol=1e-4, rtol=0)
    else:
        np.testing.assert_allclose(got, ref, atol=ORDER3_REL_TOL * np.ptp(vol), rtol=0)
    assert out.spacing == (ds_eff,) * 3 and out.unit == "micrometer"
    assert out.metadata["order"] == order and out.metadata["pad"] == pad
    assert Deformation.from_dict(out.metadata["deformation"]).output_shape(ds_eff) == got.shape


def test_order3_margin_is_what_the_tolerance_assumes():
    # the documented bound: the truncated prefilter differs by about 0.268 ** margin of the local range
    assert 0.268 ** ORDER3_FILTER_MARGIN < ORDER3_REL_TOL / 10


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "int16", "float32", "int32", "float64"])
@pytest.mark.parametrize("order", [0, 1, 3])
def test_voxel_type_is_kept_and_rounded_like_scipy(dtype, order):
    shape = (26, 24, 30)
    info = np.iinfo(dtype) if np.dtype(dtype).kind in "iu" else None
    lo, hi = (info.min, info.max) if info is not None and info.bits <= 16 else (-5000, 60000)
    if dtype.startswith("uint"):
        lo = 0
    vol = smooth_volume(shape, seed=3, sigma=1.5, dtype=np.float64, lo=lo, hi=hi)
    vol = np.clip(np.round(vol), lo, hi).astype(dtype) if info is not None else vol.astype(dtype)
    d = random_deformation(5, shape, cage=(5.0, 5.0))
    fill = 7
    got = straighten(vol, d, order=order, fill=fill, chunks=(5, 11, 11)).data.compute()
    ref = ndi.map_coordinates(vol, reference_coords(d, 1.0), order=order, mode="constant", cval=fill)
    assert got.dtype == np.dtype(dtype)
    diff = np.abs(got.astype(np.float64) - ref.astype(np.float64))
    if order == 0:
        np.testing.assert_array_equal(got, ref)
    elif order == 1:
        # scipy rounds half away from zero; a value within 1e-12 of a half may round the other way
        assert diff.max() <= (1 if info is not None else 1e-4 * np.abs(vol).max())
        if info is not None:
            assert (diff > 0).mean() < 1e-3
    else:
        # cubic overshoot is clipped to the type's range, as scipy does
        assert diff.max() <= ORDER3_REL_TOL * float(np.ptp(vol)) + 1


def test_fill_outside_the_scan_and_chunks_that_miss_it():
    vol = np.full((20, 20, 20), 500, dtype=np.uint16)
    # a straight curve that leaves the scan along axis0: the last slices sample nothing
    pos = np.array([[5.0, 10.0, 10.0], [45.0, 10.0, 10.0]])
    frames = np.repeat(np.array([[[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]]), 2, axis=0)
    d = Deformation.from_keyframes(pos, frames, (3.0, 3.0))
    with pytest.warns(OutsideWarning, match=r"63\.4 % of") as rec:  # 26 of the 41 slices sample nothing
        out = straighten(vol, d, fill=9, chunks=(4, 7, 7)).data.compute()
    assert [type(w.message).__name__ for w in rec] == ["OutsideWarning"]
    assert out.shape == (41, 7, 7)
    np.testing.assert_array_equal(out[:15], 500)  # s = 0..14 -> axis0 = 5..19 inside
    np.testing.assert_array_equal(out[15:], 9)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_order1_samples_on_the_scan_faces_match_scipy(axis):
    """The kernel's checked path (samples within 1e-6 voxel of a face of the scan, where the bounds-free run
    cannot go) interpolating random data, against scipy over the whole volume.

    A straight rod along ``axis`` from coordinate 0 to n - 1: its first and last slices lie exactly in the two
    faces of the scan normal to ``axis``, so every sample of theirs takes the checked path, with the two other
    fractions non-zero (u, v oblique) and, on the far face, the upper neighbour clamped. The cage is wider than
    the scan, so every slice also straddles the border.
    """
    shape = (12, 14, 16)
    vol = np.random.default_rng(axis).random(shape)
    b, c = [x for x in range(3) if x != axis]
    th = 0.3
    n = np.eye(3)[axis]
    u = np.cos(th) * np.eye(3)[b] + np.sin(th) * np.eye(3)[c]
    frame = np.stack([u, np.cross(n, u), n])
    pos = np.zeros((2, 3))
    pos[:, b], pos[:, c] = 6.3, 7.6
    pos[1, axis] = shape[axis] - 1
    d = Deformation.from_keyframes(pos, np.stack([frame, frame]), (9.0, 8.0))
    coords = reference_coords(d, 1.0)
    assert (coords[axis][0] == 0).all() and (coords[axis][-1] == shape[axis] - 1).all()
    inside = np.ones(coords.shape[1:], bool)
    near_face = np.zeros(coords.shape[1:], bool)
    for ax in range(3):
        inside &= (coords[ax] >= 0) & (coords[ax] <= shape[ax] - 1)
        near_face |= (np.abs(coords[ax]) < 1e-6) | (np.abs(coords[ax] - (shape[ax] - 1)) < 1e-6)
    assert (inside & near_face).sum() > 150 and 0.2 < inside.mean() < 0.9
    ref = ndi.map_coordinates(vol, coords, order=1, mode="constant", cval=-1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutsideWarning)
        got = straighten(vol, d, fill=-1.0, chunks=(5, 6, 7)).data.compute()
    np.testing.assert_allclose(got[inside & near_face], ref[inside & near_face], atol=1e-12, rtol=0)
    np.testing.assert_allclose(got, ref, atol=1e-12, rtol=0)


def test_cylinder_error_falls_as_keyframes_are_added():
    """The paper's synthetic experiment: keyframes on the true centreline of the sine-wave cylinder."""
    p = cylinder_phantom()
    truth = p.straight_volume.astype(np.float64)
    bg = float(np.median(truth[~p.straight_mask]))
    errors = []
    for m in (2, 3, 5, 9, 17):
        idx = np.round(np.linspace(0, len(p.arclength) - 1, m)).astype(int)
        d = Deformation.from_keyframes(p.centerline_physical[idx], p.frames[idx], p.half_extent,
                                       spacing=p.spacing, unit=p.unit)
        got = straighten(p.to_volume(), d, fill=int(bg), spacing=p.straight_spacing).data.compute().astype(float)
        n = min(len(got), len(truth))  # a coarse polyline is shorter than the curve: compare slice by slice
        full = np.full(truth.shape, bg)
        full[:n] = got[:n]
        errors.append(np.linalg.norm(full - truth) / np.linalg.norm(truth - bg))
    # 2 and 3 keyframes (ends and middle) both lie on the sine's axis, so they give nearly the same error
    assert errors[1] <= errors[0] + 1e-3
    assert all(b < a for a, b in zip(errors[1:], errors[2:], strict=False)), errors
    assert errors[-1] < 0.15 < 0.5 < errors[0], errors


@pytest.mark.parametrize("order,tol", [(1, 0.03), (3, 0.005)])
def test_bend_of_straighten_gives_back_the_scan_inside_the_cage(order, tol):
    """Tolerance: twice-interpolated smooth data; max error relative to the data range (order 1: 3 %, 3: 0.5 %)."""
    p = cylinder_phantom()
    idx = np.round(np.linspace(0, len(p.arclength) - 1, 17)).astype(int)
    d = Deformation.from_keyframes(p.centerline_physical[idx], p.frames[idx], p.half_extent, spacing=p.spacing)
    x = smooth_volume(p.shape, seed=4, sigma=4.0)
    straight = straighten(x, d, order=order)
    back = bend(straight, d, shape=p.shape, order=order, fill=-1, chunks=(32, 32, 40)).compute()
    assert back.shape == p.shape and back.dtype == x.dtype
    # reference geometry from Deformation.inverse on a random sample of the voxels near the curve
    vox = np.indices(p.shape).reshape(3, -1).T.astype(float)
    near = cKDTree(p.centerline).query(vox, distance_upper_bound=np.hypot(*p.half_extent) + 3)[0] < np.inf
    far = tuple(vox[~near].astype(int).T)
    assert np.all(back[far] == -1)
    rng = np.random.default_rng(0)
    sample = vox[near][rng.choice(int(near.sum()), 12000, replace=False)]
    inv = d.inverse(d.to_physical(sample))
    rx, ry = d.max_half_extent
    deep = inv.inside & (np.abs(inv.xys[:, 0]) <= rx - 2) & (np.abs(inv.xys[:, 1]) <= ry - 2) \
        & (inv.xys[:, 2] >= 2) & (inv.xys[:, 2] <= d.length - 2)
    assert deep.sum() > 2000
    sel = tuple(sample[deep].astype(int).T)
    err = np.abs(back[sel] - x[sel])
    assert err.max() <= tol * np.ptp(x[sel]), err.max()
    out = tuple(sample[~inv.inside].astype(int).T)
    assert len(out[0]) > 1000 and np.all(back[out] == -1)


def test_bend_checks_the_straight_grid():
    p = cylinder_phantom()
    d = Deformation.from_keyframes(p.centerline_physical[[0, -1]], p.frames[[0, -1]], p.half_extent,
                                   spacing=p.spacing)
    with pytest.raises(InvalidInputError, match="shape"):
        bend(np.zeros((5, 5, 5), np.float32), d, shape=p.shape)


def test_map_points_round_trips_and_agrees_with_deformation_inverse():
    d = random_deformation(7, (40, 40, 40), spacing=(1.2, 1.0, 0.9), origin=(2.0, -1.0, 0.5), cage=(5.0, 3.0))
    d = d.with_pad(2.0, 3.0)
    rng = np.random.default_rng(0)
    ds = 0.8
    ns, ny, nx = d.output_shape(ds)
    straight_pts = np.stack([rng.uniform(0, ns - 1, 500), rng.uniform(0, ny - 1, 500),
                             rng.uniform(0, nx - 1, 500)], axis=1)
    # keep the points inside the cage (the grid's corners may poke out of it)
    x, y = (straight_pts[:, 2] - (nx - 1) / 2) * ds, (straight_pts[:, 1] - (ny - 1) / 2) * ds
    straight_pts = straight_pts[(np.abs(x) <= 5.0) & (np.abs(y) <= 3.0)]
    scan_pts = map_points(straight_pts, d, to="scan", spacing=ds)
    # independent: forward map of the same straight coordinates
    s = d.s_range[0] + straight_pts[:, 0] * ds
    xys = np.stack([(straight_pts[:, 2] - (nx - 1) / 2) * ds, (straight_pts[:, 1] - (ny - 1) / 2) * ds, s], 1)
    np.testing.assert_allclose(scan_pts, d.to_voxels(d.forward(xys)), atol=1e-9)
    back = map_points(scan_pts, d, to="straight", spacing=ds)
    np.testing.assert_allclose(back, straight_pts, atol=1e-3)
    inv = d.inverse(d.to_physical(scan_pts))
    np.testing.assert_allclose(back[:, 0], (inv.xys[:, 2] - d.s_range[0]) / ds, atol=1e-6)
    # the other way round
    again = map_points(back, d, to="scan", spacing=ds)
    np.testing.assert_allclose(again, scan_pts, atol=1e-3)


def test_the_compiled_inverse_agrees_with_deformation_inverse():
    from napari_unwind.warp import _fast_inverse

    d = random_deformation(11, (40, 40, 40), spacing=(1.0, 0.8, 1.2), cage=(6.0, 4.0)).with_pad(3.0, 2.0)
    d = d.twist_keyframe(1, 0.5).tilt_keyframe(4, -0.15, axis="v").resize_keyframe(2, (7.0, 3.0))
    rng = np.random.default_rng(1)
    n = 3000
    xys = np.stack([rng.uniform(-9, 9, n), rng.uniform(-6, 6, n), rng.uniform(-5, d.length + 4, n)], axis=1)
    pts = np.vstack([d.forward(xys), rng.uniform(-5, 50, (500, 3))])
    ref = d.inverse(pts)
    got, inside = _fast_inverse(d, pts)
    np.testing.assert_array_equal(inside, ref.inside)
    assert 0.2 < inside.mean() < 0.9
    np.testing.assert_allclose(got[inside], ref.xys[inside], atol=1e-9)
    np.testing.assert_array_equal(np.isnan(got[:, 2]), np.isnan(ref.xys[:, 2]))


def test_map_points_outside_the_cage():
    d = random_deformation(8, (30, 30, 30))
    ok = d.to_voxels(d.forward(np.array([[0.0, 0.0, d.length / 2]])))
    far = np.array([[1000.0, 1000.0, 1000.0], [-500.0, 0.0, 0.0]])
    with pytest.warns(UserWarning, match="2 of 3 points"):
        res = map_points(np.vstack([ok, far]), d, to="straight")
    assert np.isfinite(res[0]).all() and np.isnan(res[1:]).all()
    with pytest.raises(InvalidInputError, match="outside the cage"):
        map_points(far, d, to="straight")
    with pytest.raises(InvalidInputError, match="'straight' or 'scan'"):
        map_points(ok, d, to="sideways")


def test_map_labels_and_mesh_both_ways():
    shape = (30, 32, 34)
    d = random_deformation(9, shape, cage=(5.0, 5.0))
    labels = np.zeros(shape, np.int64)  # int64 is not a Volume type, but a label image may be
    labels[8:22, 10:25, 10:25] = 3
    labels[12:16, 12:20, 14:22] = 2**40
    st = map_labels(labels, d, to="straight")
    assert st.dtype == np.int64
    ref = ndi.map_coordinates(labels, reference_coords(d, 1.0), order=0, mode="constant", cval=0)
    np.testing.assert_array_equal(st.compute(), ref)
    back = map_labels(st, d, to="scan", shape=shape).compute()
    assert back.dtype == np.int64 and set(np.unique(back)) <= {0, 3, 2**40}
    assert (back == 2**40).sum() > 0
    with pytest.raises(InvalidInputError, match="shape"):
        map_labels(st, d, to="scan")
    verts = d.to_voxels(d.forward(np.array([[0.0, 0.0, 2.0], [1.0, 1.0, 4.0], [-1.0, 2.0, 6.0]])))
    faces = np.array([[0, 1, 2]])
    v2, f2 = map_mesh(verts, faces, d, to="straight")
    np.testing.assert_array_equal(f2, faces)
    np.testing.assert_allclose(map_mesh(v2, faces, d, to="scan")[0], verts, atol=1e-6)


# ------------------------------------------------------------------------------------------------------------------
# out of core: laziness, only the needed chunks, schedulers
# ------------------------------------------------------------------------------------------------------------------
def test_only_the_chunks_near_the_curve_are_read():
    shape = (48, 48, 48)
    vol = smooth_volume(shape, seed=2)
    d = random_deformation(3, shape, cage=(4.0, 4.0))
    chunk = 6
    reads: list[tuple[int, ...]] = []
    lock = threading.Lock()

    def counting(block, block_info=None):
        with lock:
            reads.append(tuple(block_info[0]["chunk-location"]))
        return block

    data = da.from_array(vol, chunks=chunk).map_blocks(counting, dtype=vol.dtype)
    out = straighten(data, d, chunks=(4, 9, 9))
    assert reads == [], "building the graph must not read anything"
    got = out.data.compute()
    np.testing.assert_allclose(got, ndi.map_coordinates(vol, reference_coords(d, 1.0), order=1), atol=1e-4)
    read = set(reads)
    n_chunks = (shape[0] // chunk) ** 3
    # chunk boxes farther from the curve than the cage's reach plus an output block's diagonal are never read
    s = np.linspace(*d.s_range, 400)
    centres = d.to_voxels(d.sample(s)[0])
    reach = np.hypot(4, 4) + np.sqrt(4**2 + 9**2 + 9**2) + 3
    far = set()
    for idx in np.ndindex(*(n // chunk for n in shape)):
        lo = np.array(idx) * chunk
        gap = np.maximum(np.maximum(lo - centres, centres - (lo + chunk - 1)), 0)
        if np.linalg.norm(gap, axis=1).min() > reach:
            far.add(idx)
    assert far and not (read & far)
    assert len(read) < 0.5 * n_chunks, (len(read), n_chunks)


def test_threads_synchronous_and_a_distributed_cluster_agree(tmp_path):
    distributed = pytest.importorskip("distributed")
    p = cylinder_phantom()
    idx = np.round(np.linspace(0, len(p.arclength) - 1, 9)).astype(int)
    d = Deformation.from_keyframes(p.centerline_physical[idx], p.frames[idx], p.half_extent, spacing=p.spacing,
                                   unit=p.unit)
    vol = p.to_volume()
    results = {}
    for order in (0, 1, 3):
        arr = straighten(vol, d, order=order, chunks=(16, 9, 9)).data
        pickle.dumps(dict(arr.__dask_graph__()))  # every task pickles (module-level functions, plain arrays)
        with dask.config.set(scheduler="threads"):
            results["threads", order] = arr.compute()
        with dask.config.set(scheduler="synchronous"):
            results["sync", order] = arr.compute()
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) \
            as cluster, distributed.Client(cluster.scheduler_address) as client:
        for order in (0, 1, 3):
            arr = straighten(vol, d, order=order, chunks=(16, 9, 9)).data
            results["dist", order] = client.compute(arr).result()
        # export through the scheduler address (a client is made and closed by export)
        path = export(vol, d, tmp_path / "dist.zarr", scheduler=cluster.scheduler_address)
    for order in (0, 1, 3):
        np.testing.assert_array_equal(results["threads", order], results["sync", order])
        np.testing.assert_array_equal(results["threads", order], results["dist", order])
    np.testing.assert_array_equal(open_volume(path).data.compute(), results["threads", 1])


# ------------------------------------------------------------------------------------------------------------------
# export
# ------------------------------------------------------------------------------------------------------------------
def _phantom_deformation():
    p = cylinder_phantom()
    idx = np.round(np.linspace(0, len(p.arclength) - 1, 9)).astype(int)
    d = Deformation.from_keyframes(p.centerline_physical[idx], p.frames[idx], p.half_extent, spacing=p.spacing,
                                   unit=p.unit)
    return p, d


def test_export_ome_zarr_round_trip_with_the_map_and_provenance(tmp_path):
    import zarr

    p, d = _phantom_deformation()
    vol = p.to_volume()
    session = {"schema": "test-session", "source": {"path": "scan.tif"}}
    gen = export_iter(vol, d, tmp_path / "fish.zarr", order=1, pad=2, session=session, file_chunks=16)
    records = []
    while True:
        try:
            records.append(next(gen))
        except StopIteration as stop:
            path = stop.value
            break
    assert records and path.name == "fish.zarr"
    expected = straighten(vol, d, pad=2)
    back = open_volume(path)
    np.testing.assert_array_equal(back.data.compute(), expected.data.compute())
    assert back.spacing == expected.spacing and back.unit == "micrometer"
    np.testing.assert_allclose(back.origin, expected.origin)
    info = back.metadata["unwind"]["straightening"]
    d2 = Deformation.from_dict(info["deformation"])
    assert d2.pad == (2.0, 2.0) and d2.output_shape(1.0) == back.shape
    assert info["order"] == 1 and info["session"] == session and info["source"] == vol.source
    assert info["coordinateTransformations"][0]["type"] == "coordinates"
    # the stored map is exact: slice geometry, and the corner field reproduces the forward map bilinearly
    root = zarr.open_group(str(path), mode="r")
    slices = root["map/slices"][...]
    base, dv, du = d2.slice_geometry(1.0)
    np.testing.assert_allclose(slices, np.stack([base, dv, du], axis=1))
    corners = root["map/coordinates"][...]
    ns, ny, nx = back.shape
    k, i, j = 5, 3, 11
    a, b = i / (ny - 1), j / (nx - 1)
    bil = ((1 - a) * (1 - b) * corners[k, 0, 0] + (1 - a) * b * corners[k, 0, 1] + a * (1 - b) * corners[k, 1, 0]
           + a * b * corners[k, 1, 1])
    xys = np.array([[(j - (nx - 1) / 2), (i - (ny - 1) / 2), d2.s_range[0] + k]])
    np.testing.assert_allclose(bil, d2.forward(xys)[0], atol=1e-9)
    assert not any("unwind-tmp" in q.name for q in tmp_path.iterdir())
    # bending the export back reads its pad from the metadata
    bent = bend(back, d, shape=p.shape, order=0).compute()
    assert bent.shape == p.shape and bent.dtype == np.uint16
    core = ndi.binary_erosion(p.mask, iterations=2)
    close = np.abs(bent[core].astype(int) - p.volume[core].astype(int)) <= 50
    assert close.mean() > 0.9, close.mean()


def test_export_tiff_round_trip_and_refusals(tmp_path):
    p, d = _phantom_deformation()
    vol = p.to_volume()
    out = export(vol, d, tmp_path / "fish.tif", order=0)
    back = open_volume(out)
    expected = straighten(vol, d, order=0)
    np.testing.assert_array_equal(back.data.compute(), expected.data.compute())
    assert back.dtype == np.uint16 and back.spacing == (1.0, 1.0, 1.0) and back.unit == "micrometer"
    np.testing.assert_allclose(back.origin, expected.origin)
    from napari_unwind.errors import OutputError

    with pytest.raises(OutputError, match="already exists; pass overwrite=True"):
        export(vol, d, tmp_path / "fish.tif")
    with pytest.raises(InvalidInputError, match="scheduler"):
        export(vol, d, tmp_path / "other.tif", scheduler="nonsense")


# ------------------------------------------------------------------------------------------------------------------
# folds and validation
# ------------------------------------------------------------------------------------------------------------------
def test_a_folding_deformation_warns_and_names_where():
    t = np.linspace(0, np.pi / 2, 7)
    pts = np.stack([np.full_like(t, 20.0), 20 + 8 * np.sin(t), 10 + 8 * (1 - np.cos(t))], axis=1)
    tight = Deformation.from_polyline(pts, spacing=1.0, cage_half_extent=(12.0, 12.0))
    assert tight.folds()
    vol = np.zeros((40, 40, 40), np.float32)
    with pytest.warns(FoldWarning, match=r"folds at s in \[") as rec:
        straighten(vol, tight)
    a, b = tight.folds()[0]
    assert f"{a:.4g}" in str(rec[0].message)
    gentle = tight.resize_keyframe(None, (1.0, 1.0))
    assert not gentle.folds()
    with warnings.catch_warnings():
        warnings.simplefilter("error", FoldWarning)
        straighten(vol, gentle)


def test_invalid_input_is_refused_with_the_values():
    d = random_deformation(1, (20, 20, 20))
    vol = Volume(da.zeros((20, 20, 20), dtype=np.uint8), spacing=(2.0, 1.0, 1.0))
    with pytest.raises(InvalidInputError, match=r"\(2\.0, 1\.0, 1\.0\).*\(1\.0, 1\.0, 1\.0\)"):
        straighten(vol, d)
    arr = np.zeros((20, 20, 20), np.uint8)
    with pytest.raises(InvalidInputError, match="order"):
        straighten(arr, d, order=2)
    with pytest.raises(InvalidInputError, match="fill"):
        straighten(arr, d, fill=-1)
    with pytest.raises(InvalidInputError, match="pad"):
        straighten(arr, d, pad=-1)
    with pytest.raises(InvalidInputError, match="3D"):
        straighten(np.zeros((4, 4)), d)
