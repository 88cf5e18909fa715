"""estimate_deformation against phantoms with ground truth, the spine MRI's manual centreline, and bad input.

The references are the phantoms' analytic centrelines, frames and straight masks (napari_unwind.datasets, made
without any skeleton code) and an expert's centreline of a real MRI; the straightened mask is sampled here with
scipy's map_coordinates at the phantom's own straight grid.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import dask.array as da
import numpy as np
import pytest
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from napari_unwind.datasets import fish_phantom
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume
from napari_unwind.progress import Progress
from napari_unwind.session import Endpoints
from napari_unwind.skeleton import SkeletonResult, estimate_deformation, estimate_deformation_iter

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


def _solve(mask, endpoints, **kw) -> tuple[SkeletonResult, list[str]]:
    """The result and the stages the generator reported."""
    gen = estimate_deformation_iter(mask, endpoints, **kw)
    stages = []
    while True:
        try:
            p = next(gen)
        except StopIteration as stop:
            return stop.value, stages
        assert isinstance(p, Progress)
        stages.append(p.stage)


def _solve_quiet(mask, endpoints, **kw) -> SkeletonResult:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gen = estimate_deformation_iter(mask, endpoints, **kw)
        while True:
            try:
                next(gen)
            except StopIteration as stop:
                return stop.value


def centreline_errors(ph, dfm) -> tuple[float, float]:
    """RMS distance (in voxels of the finest spacing) of the deformation's centre from the true centreline, and the
    relative arclength error."""
    c, _ = dfm.sample(np.linspace(0.0, dfm.length, 2000))
    dist, _ = cKDTree(ph.centerline_physical).query(c - np.asarray(dfm.origin))
    return float(np.sqrt((dist**2).mean()) / min(ph.spacing)), dfm.length / ph.length - 1.0


def residual_twist_deg(ph, dfm) -> np.ndarray:
    """Angle (degrees) between the deformation's v and the true v, along the curve (true v at the closest true
    centreline point, our v projected onto the plane normal to the true n)."""
    s = np.linspace(0.0, dfm.length, 400)
    c, frames = dfm.sample(s)
    _, k = cKDTree(ph.centerline_physical).query(c - np.asarray(dfm.origin))
    v_true, n_true = ph.frames[k, 1], ph.frames[k, 2]
    v = frames[:, 1] - np.sum(frames[:, 1] * n_true, axis=1, keepdims=True) * n_true
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(v * v_true, axis=1), -1, 1)))


def straight_dice(ph, dfm) -> float:
    """Dice of the phantom's mask sampled through the deformation at the straight ground truth's grid."""
    s, y, x = ph.straight_grid()
    ss, yy, xx = np.meshgrid(s, y, x, indexing="ij")
    xys = np.stack([xx.ravel(), yy.ravel(), ss.ravel()], axis=1)
    pts = (dfm.forward(xys) - np.asarray(dfm.origin)) / np.asarray(ph.spacing)
    got = ndi.map_coordinates(ph.mask.astype(np.float32), pts.T, order=1, cval=0.0).reshape(ss.shape) >= 0.5
    truth = ph.straight_mask
    return 2.0 * (got & truth).sum() / (got.sum() + truth.sum())


CASES = {
    "s-bend": dict(curve="s-bend", twist=np.pi / 2),
    "c-bend": dict(curve="c-bend", twist=np.pi / 2, roll=1.0),
    "helix": dict(curve="helix", twist=-3 * np.pi / 4, roll=np.pi),
    "anisotropic": dict(curve="s-bend", twist=np.pi / 2, spacing=(1.6, 1.0, 1.0)),
}


@pytest.fixture(scope="module", params=list(CASES))
def solved(request):
    ph = fish_phantom(seed=7, **CASES[request.param])
    res = _solve_quiet(ph.mask, (ph.head, ph.tail), spacing=ph.spacing, volume=ph.volume)
    return ph, res


def test_centreline_and_length_match_the_truth(solved):
    ph, res = solved
    rms, length_err = centreline_errors(ph, res.deformation)
    assert rms <= 1.0, f"centreline RMS {rms:.2f} voxels"
    assert abs(length_err) <= 0.02, f"arclength error {100 * length_err:.2f} %"


def test_twist_is_undone(solved):
    ph, res = solved
    err = residual_twist_deg(ph, res.deformation)
    # the tips are a few voxels across: their cross-sections carry no orientation
    body = slice(int(0.03 * len(err)), int(0.97 * len(err)))
    assert err[body].max() <= 10.0, f"residual twist up to {err[body].max():.1f} degrees"
    assert np.median(err) <= 5.0


def test_straightened_mask_matches_the_straight_truth(solved):
    ph, res = solved
    assert straight_dice(ph, res.deformation) >= 0.9


def test_the_deformation_does_not_fold(solved):
    ph, res = solved
    assert res.deformation.folds() == []
    assert not any("folds" in w for w in res.warnings)


def test_cage_and_padding_hold_the_whole_specimen(solved):
    ph, res = solved
    dfm = res.deformation
    pts = np.argwhere(ph.mask)[::7] * np.asarray(ph.spacing) + np.asarray(dfm.origin)
    inv = dfm.inverse(pts)
    assert inv.inside.mean() >= 0.995


def test_result_describes_the_run(solved):
    ph, res = solved
    dfm = res.deformation
    assert dfm.spacing == tuple(float(s) for s in ph.spacing)
    assert res.keyframe_indices[0] == 0 and res.keyframe_indices[-1] == len(res.curve) - 1
    np.testing.assert_allclose(res.curve[res.keyframe_indices] * ph.spacing, dfm.positions, atol=1e-9)
    assert 2 <= len(dfm.keyframes) <= 60
    assert {"tet mesh", "harmonic", "level sets", "smoothing", "frames", "twist", "keyframes"} <= set(
        res.timings)
    # the true ends c(0) and c(L) are the tips of the body; the used ends are snapped into the working mask
    np.testing.assert_allclose(res.endpoints.head, ph.head, atol=2.5)
    np.testing.assert_allclose(res.endpoints.tail, ph.tail, atol=2.5)


def test_twist_off_keeps_parallel_transport():
    ph = fish_phantom(seed=1, curve="c-bend", twist=np.pi / 2, noise=0, tube=False)
    res = _solve_quiet(ph.mask, (ph.head, ph.tail), spacing=ph.spacing, estimate_twist=False)
    assert np.all(res.twist == 0)
    # without the estimate the residual equals the phantom's own twist (90 degrees at the tail)
    err = residual_twist_deg(ph, res.deformation)
    assert err[-20:].mean() > 45


def test_generator_reports_stages_in_order_and_plain_function_agrees():
    ph = fish_phantom(seed=2, curve="c-bend", noise=0, tube=False)
    res, stages = _solve(ph.mask, (ph.head, ph.tail), spacing=ph.spacing, estimate_twist=False)
    order = [s for i, s in enumerate(stages) if i == 0 or stages[i - 1] != s]
    expected = ["working mask", "tet mesh", "harmonic", "level sets", "smoothing", "frames", "cage",
                "keyframes"]
    assert [s for s in order if s in expected] == expected
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dfm = estimate_deformation(ph.mask, (ph.head, ph.tail), spacing=ph.spacing, estimate_twist=False)
    assert centreline_errors(ph, dfm)[0] <= 1.0


def test_dask_and_volume_inputs_and_origin():
    ph = fish_phantom(seed=3, curve="s-bend", noise=0, tube=False)
    vol = Volume(da.from_array(ph.mask.astype(np.uint8), chunks=32), spacing=ph.spacing, unit="micrometer",
                 origin=(100.0, -5.0, 2.0))
    res = _solve_quiet(vol, Endpoints(head=tuple(ph.head), tail=tuple(ph.tail)), estimate_twist=False)
    dfm = res.deformation
    assert dfm.origin == (100.0, -5.0, 2.0) and dfm.unit == "micrometer"
    assert centreline_errors(ph, dfm)[0] <= 1.0


def test_a_specimen_in_two_parts_needs_a_chain():
    ph = fish_phantom(seed=4, curve="c-bend", noise=0, tube=False)
    mask = ph.mask.copy()
    k = len(ph.centerline) // 2
    cut = int(round(ph.centerline[k, 0]))
    mask[cut - 8: cut + 8] = False  # a gap of 16 voxels: more than dilation by 3 working voxels (x2) closes
    with pytest.raises(InvalidInputError, match=r"different parts.*part 1.*part 2.*chain"):
        _solve_quiet(mask, (ph.head, ph.tail), spacing=ph.spacing, estimate_twist=False)
    # the user clicks the ends of each part: here the middle of each cut face, 1.5 voxels inside
    a = ph.centerline[np.argmin(np.abs(ph.centerline[:, 0] - (cut - 9.5)))]
    b = ph.centerline[np.argmin(np.abs(ph.centerline[:, 0] - (cut + 9.5)))]
    ends = Endpoints(head=tuple(ph.head), tail=tuple(ph.tail), chain=((tuple(ph.head), tuple(a)),
                                                                      (tuple(b), tuple(ph.tail))))
    res = _solve_quiet(mask, ends, spacing=ph.spacing, estimate_twist=False)
    rms, length_err = centreline_errors(ph, res.deformation)
    assert rms <= 1.0 and abs(length_err) <= 0.02
    assert len(res.endpoints.chain) == 2


def test_a_small_gap_is_bridged_by_dilation():
    ph = fish_phantom(seed=4, curve="c-bend", noise=0, tube=False)
    mask = ph.mask.copy()
    cut = int(round(ph.centerline[len(ph.centerline) // 2, 0]))
    mask[cut: cut + 4] = False  # 4 voxels: two working voxels at the factor 2 of this phantom
    with pytest.warns(UserWarning, match="dilation"):
        res, _ = _solve(mask, (ph.head, ph.tail), spacing=ph.spacing, estimate_twist=False)
    assert centreline_errors(ph, res.deformation)[0] <= 1.0


def test_endpoints_are_snapped_into_the_mask_or_refused():
    ph = fish_phantom(seed=5, curve="c-bend", noise=0, tube=False)
    head_out = ph.head - 3 * ph.frames[0, 2]  # 3 voxels beyond the head's tip, along the body
    res = _solve_quiet(ph.mask, (head_out, ph.tail), spacing=ph.spacing, estimate_twist=False)
    hi = np.round(res.endpoints.head).astype(int)
    assert ph.mask[tuple(hi)] or ndi.binary_dilation(ph.mask)[tuple(hi)]
    assert np.linalg.norm(np.subtract(res.endpoints.head, head_out)) <= 5.0
    dist = ndi.distance_transform_edt(~ph.mask)
    far = np.argwhere((dist > 8) & (dist < 12))[0]  # 8-12 voxels from the mask; the tolerance is 5
    with pytest.raises(InvalidInputError, match="from the mask.*snapping tolerance"):
        _solve_quiet(ph.mask, (far, ph.tail), spacing=ph.spacing, estimate_twist=False)
    with pytest.raises(InvalidInputError, match="outside the volume"):
        _solve_quiet(ph.mask, ((-50, 3, 3), ph.tail), spacing=ph.spacing, estimate_twist=False)


def test_bad_input_is_refused_clearly():
    ph = fish_phantom(seed=6, curve="c-bend", noise=0, tube=False)
    with pytest.raises(InvalidInputError, match="empty"):
        estimate_deformation(np.zeros((20, 20, 20), bool), ((5, 5, 5), (15, 15, 15)), spacing=1.0)
    with pytest.raises(InvalidInputError, match="same point"):
        estimate_deformation(ph.mask, (ph.head, ph.head), spacing=ph.spacing)
    near = ph.centerline[3]
    with pytest.raises(InvalidInputError, match="same point"):
        estimate_deformation(ph.mask, (ph.centerline[1], near), spacing=ph.spacing)
    with pytest.raises(InvalidInputError, match="spacing is required"):
        estimate_deformation(ph.mask, (ph.head, ph.tail))
    with pytest.raises(InvalidInputError, match="3-dimensional"):
        estimate_deformation(ph.mask[0], (ph.head, ph.tail), spacing=1.0)
    with pytest.raises(InvalidInputError, match="n_levels"):
        estimate_deformation(ph.mask, (ph.head, ph.tail), spacing=1.0, n_levels=1)
    with pytest.raises(InvalidInputError, match="volume's shape"):
        estimate_deformation(ph.mask, (ph.head, ph.tail), spacing=1.0, volume=np.zeros((3, 3, 3)))
    with pytest.raises(InvalidInputError, match="end_window_factor"):
        estimate_deformation(ph.mask, (ph.head, ph.tail), spacing=1.0, end_window_factor=-1)
    with pytest.raises(InvalidInputError, match="tolerance must be"):
        estimate_deformation(ph.mask, (ph.head, ph.tail), spacing=1.0, tolerance=0)
    with pytest.raises(InvalidInputError, match="endpoints must be"):
        estimate_deformation(ph.mask, 5, spacing=1.0)


def test_a_mask_filling_the_scan_is_refused_as_no_specimens_and_a_tight_crop_is_not():
    """An inverted mask (the background non-zero) fills nearly the whole scan: refused in one line saying so. A
    straight body cropped to its own box fills pi / 4 of it (a cylinder in its box), and is solved."""
    ph = fish_phantom(seed=6, curve="c-bend", noise=0, tube=False)
    with pytest.raises(InvalidInputError) as err:
        estimate_deformation(~ph.mask, (ph.head, ph.tail), spacing=ph.spacing)
    fill = 100 * (~ph.mask).mean()
    assert str(err.value) == (f"the mask's non-zero voxels fill {fill:.3g} % of the scan: that is no specimen's mask "
                              "(a body fills at most about 79 % of its own box); is it inverted (the background "
                              "non-zero)? give a mask whose non-zero voxels are the specimen alone")
    z, y, x = np.mgrid[:60, :16, :16]
    rod = (y - 7.5) ** 2 + (x - 7.5) ** 2 <= 8.0**2  # touches its box's four long faces
    assert 0.75 < rod.mean() < 0.9
    res, _ = _solve(rod, ((2, 7.5, 7.5), (57, 7.5, 7.5)), spacing=1.0, estimate_twist=False)
    assert res.deformation.length == pytest.approx(55, abs=3)


def test_mask_touching_the_border_is_handled_with_a_warning():
    ph = fish_phantom(seed=8, curve="c-bend", noise=0, tube=False)
    cut = int(ph.centerline[int(0.9 * len(ph.centerline)), 0])
    mask = ph.mask[:cut]  # the scan ends inside the fish
    tail = ph.centerline[np.argmin(np.abs(ph.centerline[:, 0] - (cut - 1.5)))]
    with pytest.warns(UserWarning, match=r"touches the volume's border \(axis0 end\)"):
        res, _ = _solve(mask, (ph.head, tail), spacing=ph.spacing, estimate_twist=False)
    c, _ = res.deformation.sample(np.linspace(0, res.deformation.length, 500))
    assert cKDTree(ph.centerline_physical).query(c)[0].max() <= 2.0


def test_nearly_spherical_specimen_is_handled_with_a_warning():
    z, y, x = np.mgrid[:40, :40, :40]
    ball = (z - 20) ** 2 + (y - 20) ** 2 + (x - 20) ** 2 <= 15**2
    with pytest.warns(UserWarning, match="nearly spherical"):
        res, _ = _solve(ball, ((7, 20, 20), (33, 20, 20)), spacing=1.0)
    c, _ = res.deformation.sample(np.linspace(0, res.deformation.length, 50))
    np.testing.assert_allclose(c[:, 1:], 20, atol=1.5)  # by symmetry the curve runs straight between the clicks


@pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data is not present")
def test_spine_mri_follows_the_manual_centreline():
    import nrrd

    mask, header = nrrd.read(str(DATA / "spine_t2_cord_mask.nrrd"), index_order="C")
    scan, _ = nrrd.read(str(DATA / "spine_t2.nrrd"), index_order="C")
    spacing = np.abs(np.diag(header["space directions"])).astype(float)
    manual = np.loadtxt(DATA / "spine_t2_centerline_manual.csv", delimiter=",", skiprows=1)
    res = _solve_quiet(mask, (manual[0], manual[-1]), spacing=spacing, volume=scan)
    c, _ = res.deformation.sample(np.linspace(0, res.deformation.length, 2000))
    dist, _ = cKDTree(c).query(manual * spacing)  # mm from every manual point to our curve
    assert dist.mean() <= 1.5, f"mean distance {dist.mean():.2f} mm"
    assert dist.max() <= 3.0


def test_an_end_where_the_mask_runs_off_the_scan_is_the_centre_of_the_cut_face():
    # a bent tube of radius 5 that leaves the scan through the face axis1 = 0, centred there at (20, 0, 22)
    g = np.indices((44, 70, 60), dtype=float)
    t = np.linspace(0, 1, 400)
    curve = np.stack([20 + 0 * t, 60 * t, 22 + 25 * t ** 2], axis=1)  # leaves the face axis1 = 0 at right angles
    d, _ = cKDTree(curve).query(g.reshape(3, -1).T)
    mask = (d <= 5.0).reshape(g.shape[1:])
    res = _solve_quiet(mask, None, spacing=1.0)
    ends = np.array([res.endpoints.head, res.endpoints.tail])
    at_face = ends[np.argmin(ends[:, 1])]
    # the rim of the face is 5 voxels from its centre; the geodesic's own tip lies on the rim
    assert np.linalg.norm(at_face - [20.0, 0.0, 22.0]) <= 1.0, at_face


def test_a_long_thin_body_keeps_six_working_voxels_across():
    # an eel: 9 voxels across, 560 long; max_side 128 alone would average it by 5 (under 2 voxels across)
    t = np.linspace(0, 1, 800)
    curve = np.stack([20 + 560 * t, 16 + 6 * np.sin(2 * np.pi * t), 16 + 0 * t], axis=1)
    g = np.indices((600, 32, 32), dtype=float)
    d, _ = cKDTree(curve).query(g.reshape(3, -1).T)
    mask = (d <= 4.5).reshape(g.shape[1:])
    res = _solve_quiet(mask, (curve[0], curve[-1]), spacing=1.0)
    assert 9 / res.factor >= 6
    c, _ = res.deformation.sample(np.linspace(0, res.deformation.length, 2000))
    dist, _ = cKDTree(c).query(curve[20:-20])
    true_length = float(np.linalg.norm(np.diff(curve, axis=0), axis=1).sum())
    assert dist.mean() < 1.0 and abs(res.deformation.length - true_length) / true_length < 0.02


def _line_mask(spacing=(1.0, 1.0, 1.0)):
    """A bent cylinder phantom's centreline drawn one voxel thick (26-connected), with the phantom."""
    from napari_unwind.datasets import cylinder_phantom

    cyl = cylinder_phantom(spacing=spacing)
    mask = np.zeros(cyl.shape, dtype=bool)
    idx = np.unique(np.round(cyl.centerline).astype(int), axis=0)
    idx = idx[np.all((idx >= 0) & (idx < cyl.shape), axis=1)]
    mask[tuple(idx.T)] = True
    return mask, cyl


def test_a_line_mask_is_refused_in_one_line_naming_its_thickness_and_the_cage():
    mask, cyl = _line_mask()
    with pytest.raises(InvalidInputError, match=r"the mask is a line, at most [0-9.]+ voxels thick.*--cage") as info:
        estimate_deformation(mask, spacing=cyl.spacing)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (1.5, 1.0, 1.0)])
def test_a_line_mask_with_a_cage_is_straightened_along_it(spacing):
    mask, cyl = _line_mask(spacing)
    result = _solve_quiet(mask, None, spacing=spacing, half_extent=(5.0, 5.0))
    assert any("is a line" in m for m in result.warnings)
    d = result.deformation
    curve, _ = d.sample(np.linspace(0, d.length, 400))
    dist, _ = cKDTree(cyl.centerline_physical).query(curve)
    assert dist.max() <= 1.5 * max(spacing), dist.max()  # along the true line (its voxels within half a voxel)
    assert abs(d.length - cyl.length) <= 0.05 * cyl.length
    assert np.allclose(d.half_extents, 5.0) and not d.folds()


def test_a_thin_body_is_not_taken_for_a_line():
    from napari_unwind.datasets import cylinder_phantom

    cyl = cylinder_phantom(radius=2.5)  # 5 voxels across
    result = _solve_quiet(cyl.mask, None, spacing=cyl.spacing)
    assert not any("is a line" in m for m in result.warnings)
    assert result.coverage >= 0.99


def _gaps(mask, deformation):
    """The least distance (physical) from the straightened mask to the straight volume's sides, over its slices, and
    from its ends to the volume's ends (the warp resamples the mask; the skeleton's own figures are not used)."""
    from napari_unwind.warp import straighten

    out = np.asarray(straighten(mask.astype(np.float32), deformation, order=1).data) > 0.5
    ds = float(min(deformation.spacing))
    rows = np.flatnonzero(out.any(axis=(1, 2)))
    side = np.inf
    for k in rows:
        yy, xx = np.nonzero(out[k])
        side = min(side, yy.min(), out.shape[1] - 1 - yy.max(), xx.min(), out.shape[2] - 1 - xx.max())
    return side * ds, min(rows[0], len(out) - 1 - rows[-1]) * ds


def test_context_keeps_the_distance_asked_around_the_specimen():
    from napari_unwind.datasets import cylinder_phantom

    cyl = cylinder_phantom(amplitude=4.0, wavelength=400.0, radius=5.0)  # nearly straight: nothing to give up
    base = _solve_quiet(cyl.mask, None, spacing=cyl.spacing)
    wide = _solve_quiet(cyl.mask, None, spacing=cyl.spacing, context=6.0)
    side0, end0 = _gaps(cyl.mask, base.deformation)
    side, end = _gaps(cyl.mask, wide.deformation)
    assert side0 < 5.0 and side >= 6.0 - 1.0, (side0, side)  # one voxel for the resampling
    assert end >= end0 + 6.0 - 1.0, (end0, end)
    # the figure reported is a lower bound of what the straight volume shows, and a shortfall is said
    assert 0 < wide.context <= side + 1.0 and base.context is None
    noted = any(m.startswith("context:") for m in wide.warnings)
    assert noted == (wide.context < 6.0 - 0.5)


def test_context_is_given_up_on_the_inner_side_of_a_tight_bend_and_reported():
    from napari_unwind.datasets import hard_fish_phantom

    ph = hard_fish_phantom(1000, kind="s-bend")
    result = _solve_quiet(ph.mask, (ph.head, ph.tail), spacing=ph.spacing, context=12.0)
    assert not result.deformation.folds()
    assert result.context < 12.0
    notes = [m for m in result.warnings if m.startswith("context:")]
    assert len(notes) == 1 and "12 " in notes[0] and "inner side of bends" in notes[0]


def test_context_and_a_given_cage_are_refused_together():
    mask, cyl = _line_mask()
    with pytest.raises(InvalidInputError, match="context"):
        estimate_deformation(mask, spacing=1.0, half_extent=(5.0, 5.0), context=2.0)
    with pytest.raises(InvalidInputError, match="context"):
        estimate_deformation(mask, spacing=1.0, context=-1.0)
