"""napari_unwind.pipeline: its options' defaults and checks, the fold rule, the status rule, and the command
line's exit statuses (partial -> 3, nothing specimen-like -> 1).

References: the skeleton solver's own signature (for the defaults), phantoms whose fish is known to fit a cage,
and a cage given far too small (so part of the fish is left out of it, whatever the solver does).
"""

from __future__ import annotations

import csv
import inspect
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import run_unwind
from napari_unwind.datasets import fish_phantom
from napari_unwind.errors import FoldError, InvalidInputError
from napari_unwind.io import write_volume
from napari_unwind.pipeline import (
    EXIT_PARTIAL,
    ExportOptions,
    PipelineOptions,
    SegmentOptions,
    SkeletonOptions,
    SpecimenResult,
    exit_status,
    fold_rule,
    judge,
)


def _arg(p):
    return ",".join(f"{float(v):.3f}" for v in p)


@pytest.fixture(scope="module")
def fish(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pipeline")
    f = fish_phantom(length=80, seed=3, tube=False)
    mask = write_volume(f.mask.astype(np.uint8), tmp / "mask.nrrd", spacing=f.spacing, unit=f.unit)
    scan = write_volume(f.volume, tmp / "scan.nrrd", spacing=f.spacing, unit=f.unit)
    return tmp, f, mask, scan


@pytest.fixture(scope="module")
def mask_run(fish):
    """``unwind run`` on the fish with its own binary mask, once for the tests that compare other masks with it:
    (its straight volume's path, its session's path, its stderr)."""
    tmp, f, mask, scan = fish
    code, _, err = run_unwind("run", scan, "--mask", mask, "--head", _arg(f.head), "--tail", _arg(f.tail), "-o",
                              tmp / "m.nrrd", "-q")
    assert code == 0, err
    return tmp / "m.nrrd", tmp / "m.unwind.json", err


def _folding():
    from napari_unwind.deformation import Deformation

    t = np.linspace(0, np.pi / 2, 40)
    pos = np.stack([np.zeros_like(t), 10 * np.sin(t), 10 * (1 - np.cos(t))], axis=1)
    n = np.stack([np.zeros_like(t), np.cos(t), np.sin(t)], axis=1)
    v = np.tile([1.0, 0.0, 0.0], (len(t), 1))
    return Deformation.from_keyframes(pos, np.stack([np.cross(v, n), v, n], axis=1), 12.0)


# ------------------------------------------------------------------------------------------------------------------
# options
# ------------------------------------------------------------------------------------------------------------------
def test_skeleton_defaults_are_the_solvers_own():
    """One source: every SkeletonOptions default equals estimate_deformation_iter's."""
    from napari_unwind.skeleton import estimate_deformation_iter

    sig = inspect.signature(estimate_deformation_iter).parameters
    for name, f in SkeletonOptions.__dataclass_fields__.items():
        assert f.default == sig[name].default, name
    assert set(SkeletonOptions().kwargs()) <= set(sig)


def test_export_defaults_are_the_warps_own(tmp_path):
    from napari_unwind.warp import export_iter

    sig = inspect.signature(export_iter).parameters
    kw = ExportOptions().kwargs(tmp_path / "x.zarr")
    assert "max_output" not in kw  # the warp's DEFAULT_MAX_OUTPUT applies
    for name in ("order", "spacing", "pad", "chunks"):
        assert kw[name] == sig[name].default, name
    assert ExportOptions(chunks=(8, 16, 16)).kwargs(tmp_path / "x.zarr")["file_chunks"] == (8, 16, 16)
    assert "file_chunks" not in ExportOptions(chunks=(8, 16, 16)).kwargs(tmp_path / "x.tif")


@pytest.mark.parametrize("make, words", [
    (lambda: SegmentOptions(features=0), "features must be a whole number 1..100, got 0"),
    (lambda: SegmentOptions(isovalue=float("nan")), "isovalue must be a finite number, got nan"),
    (lambda: SkeletonOptions(n_levels=1), "n_levels must be a whole number 2..10000, got 1"),
    (lambda: SkeletonOptions(tolerance=-1), "tolerance must be a positive number, got -1"),
    (lambda: SkeletonOptions(cage_margin="a"), "cage_margin must be a number, got 'a'"),
    (lambda: SkeletonOptions(half_extent=(1, 2, 3)), "half_extent must be two positive numbers"),
    (lambda: ExportOptions(order=2), "order must be 0, 1 or 3, got 2"),
    (lambda: ExportOptions(chunks=(1, 2)), "chunks must be 3 sizes"),
    (lambda: PipelineOptions.from_values(cage=3), "unknown pipeline option 'cage'"),
])
def test_bad_options_are_refused_up_front_with_the_value(make, words):
    with pytest.raises(InvalidInputError) as info:
        make()
    assert words in str(info.value) and "\n" not in str(info.value)


def test_options_from_flat_values():
    o = PipelineOptions.from_values(features=8, cage_margin=0.2, order=3, level=None)
    assert o.segment.features == 8 and o.segment.level is None and o.skeleton.cage_margin == 0.2
    assert o.export.order == 3 and o.skeleton.n_levels == SkeletonOptions().n_levels
    assert SegmentOptions().k == 5 and SegmentOptions(features=7).k == 7


# ------------------------------------------------------------------------------------------------------------------
# the fold rule and the status rule
# ------------------------------------------------------------------------------------------------------------------
def test_fold_rule():
    d = _folding()
    assert d.folds()
    corners = fold_rule(d, folded=0.0)
    assert not corners.refused and "no voxel of the specimen" in corners.message and "--cage" in corners.message
    for folded in (0.01, None, float("nan")):
        v = fold_rule(d, folded=folded)
        assert v.refused and "--allow-folds" in v.message, folded
    allowed = fold_rule(d, folded=0.01, allow_folds=True)
    assert not allowed.refused and "1 % of the specimen" in allowed.message
    from napari_unwind.deformation import Deformation

    straight = Deformation.from_polyline(np.stack([np.arange(20.0), np.zeros(20), np.zeros(20)], 1), spacing=1.0,
                                         cage_half_extent=2.0)
    assert fold_rule(straight) is None


def test_export_step_applies_the_fold_rule(tmp_path):
    from napari_unwind.io import as_volume
    from napari_unwind.pipeline import export_step
    from napari_unwind.progress import run

    vol = as_volume(np.zeros((30, 30, 30), np.float32), spacing=1.0)
    with pytest.raises(FoldError, match="--allow-folds"):
        run(export_step(vol, _folding(), tmp_path / "x.nrrd"))
    assert not (tmp_path / "x.nrrd").exists()
    with pytest.warns(UserWarning, match="no voxel of the specimen"):
        run(export_step(vol, _folding(), tmp_path / "x.nrrd", folded=0.0))
    assert (tmp_path / "x.nrrd").exists()


def _skel(coverage=1.0, lost=(), folded=0.0, folds=(), bend=0.0):
    d = SimpleNamespace(unit="micrometer", folds=lambda: list(folds))
    return SimpleNamespace(coverage=coverage, lost=lost, folded=folded, deformation=d, bend=bend)


def test_status_rule():
    assert judge(_skel()) == ("ok", "")
    assert judge(_skel(coverage=0.99)) == ("ok", "")
    assert judge(_skel(coverage=float("nan"))) == ("ok", "")  # not measured: no verdict on it
    status, reason = judge(_skel(coverage=0.985))
    assert status == "partial" and "coverage 98.5 %" in reason
    # lost stretches under the coverage goal are figures of an ok specimen (the inner wall of a tight bend)
    assert judge(_skel(coverage=0.996, lost=((10.0, 20.0, 0.004),))) == ("ok", "")
    status, reason = judge(_skel(coverage=0.985, lost=((10.0, 20.0, 0.015),)))
    assert status == "partial" and "coverage 98.5 %" in reason and "lost: s = 10..20" in reason
    status, reason = judge(_skel(folded=0.02, folds=[(1.0, 2.0)]))
    assert status == "partial" and "folds over 2 %" in reason
    assert judge(_skel(folded=0.0, folds=[(1.0, 2.0)])) == ("ok", "")  # only empty cage corners
    # lost on the inside of bends tighter than the body: said as such, and a larger cage is not advised for it
    status, reason = judge(_skel(coverage=0.97, lost=((10.0, 20.0, 0.03),), bend=0.03))
    assert status == "partial" and "3 % of the mask lies on the inside of bends tighter" in reason, reason
    assert "a larger or fitted cage" not in reason, reason
    status, reason = judge(_skel(coverage=0.97, lost=((10.0, 20.0, 0.01), (30.0, 40.0, 0.02)), bend=0.01))
    assert "1 % of the mask lies on the inside of bends" in reason and "a larger or fitted cage" in reason, reason


def test_exit_status():
    ok, part = SpecimenResult("ok"), SpecimenResult("partial", "coverage")
    failed, rejected = SpecimenResult("failed", "x"), SpecimenResult("rejected", "a container")
    assert exit_status([ok, rejected]) == 0
    assert exit_status([ok, part, rejected]) == EXIT_PARTIAL == 3
    assert exit_status([ok, part, failed]) == 1
    assert exit_status([rejected]) == 1 and exit_status([]) == 1
    # a candidate only a click can take is not passed over in silence: the run is not a success
    unresolved = SpecimenResult("unresolved", "a curved body among elongated ones")
    assert exit_status([ok, unresolved, rejected]) == EXIT_PARTIAL
    assert exit_status([ok, unresolved, failed]) == 1
    with pytest.raises(InvalidInputError, match="status must be one of"):
        SpecimenResult("fine")


# ------------------------------------------------------------------------------------------------------------------
# the command line's statuses
# ------------------------------------------------------------------------------------------------------------------
def test_run_with_a_fitting_cage_is_ok_and_a_too_small_cage_is_partial(fish, tmp_path):
    tmp, f, mask, scan = fish
    ends = ["--head", _arg(f.head), "--tail", _arg(f.tail)]
    code, out, err = run_unwind("run", scan, "--mask", mask, *ends, "-o", tmp_path / "ok.nrrd", "-q")
    assert code == 0, err
    # half extents of 1 voxel on a body several voxels thick: much of the mask lies outside the cage
    code, out, err = run_unwind("run", scan, "--mask", mask, *ends, "--cage", "1,1", "-o", tmp_path / "small.nrrd")
    assert code == EXIT_PARTIAL, err
    partial = [line for line in err.splitlines() if line.startswith("unwind: partial: ")]
    assert len(partial) == 1 and "coverage" in partial[0] and "Traceback" not in err, err
    assert (tmp_path / "small.nrrd").exists() and (tmp_path / "small.unwind.json").exists()  # written, not success
    assert "--cage" in run_unwind("run", "--help")[1] and "3 when one is partial" in run_unwind("run", "--help")[1]
    # unwind skeleton writes the session and says the same, with the same exit status
    code, out, err = run_unwind("skeleton", mask, "--volume", scan, *ends, "--cage", "1,1", "-o",
                                tmp_path / "s.unwind.json")
    assert code == EXIT_PARTIAL and (tmp_path / "s.unwind.json").exists(), err
    assert sum(line.startswith("unwind: partial: coverage") for line in err.splitlines()) == 1, err
    code, out, err = run_unwind("skeleton", mask, "--volume", scan, *ends, "-o", tmp_path / "t.unwind.json", "-q")
    assert code == 0, err


def test_run_all_on_a_scan_with_nothing_specimen_like_says_so_and_exits_1(tmp_path):
    z, y, x = np.mgrid[:40, :40, :40]
    ball = ((z - 20) ** 2 + (y - 20) ** 2 + (x - 20) ** 2 <= 8 ** 2).astype(np.float32) * 1000
    scan = write_volume(ball, tmp_path / "ball.nrrd", spacing=1.0)
    code, out, err = run_unwind("run", scan, "--all", "-o", tmp_path / "out")
    assert code == 1 and "nothing specimen-like" in err and "Traceback" not in err, err
    with open(tmp_path / "out" / "specimens.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    assert table and all(r["status"] == "rejected" and r["reason"] for r in table)
    assert "not elongated" in table[0]["reason"]
    assert "rejected" in out  # a summary line per candidate


def beside_a_fish(ph, seed: int) -> tuple[np.ndarray, int]:
    """A phantom's scan beside an S-bend fish's in one scan (benchmarks/bench_curled.py --among): ``(volume uint16,
    split)``, the phantom on axis 2 below ``split``, the fish above, in noise (104 +- 40)."""
    f = fish_phantom(seed=seed, curve="s-bend", length=110, body_radius=7)
    rng = np.random.default_rng(seed)
    n0 = max(ph.volume.shape[0], f.volume.shape[0]) + 4
    n1 = max(ph.volume.shape[1], f.volume.shape[1]) + 4
    split = ph.volume.shape[2] + 6
    vol = rng.normal(104, 40, (n0, n1, split + f.volume.shape[2] + 6)).clip(0).astype(np.uint16)
    for v, x0 in ((np.asarray(ph.volume), 4), (np.asarray(f.volume), split + 2)):
        a0, a1 = (n0 - v.shape[0]) // 2, (n1 - v.shape[1]) // 2
        box = (slice(a0, a0 + v.shape[0]), slice(a1, a1 + v.shape[1]), slice(x0, x0 + v.shape[2]))
        vol[box] = np.maximum(vol[box], v)
    return vol, split


def test_a_candidate_the_full_resolution_scan_does_not_bear_out_is_rejected_not_failed(tmp_path):
    # a coiled phantom's S-bend beside a fish (bench_curled --among, seed 1000), no click: the working level offered
    # a body that no feature holds where the full-resolution scan shows none above the medium. It was a "failed"
    # row advising the API's isovalue=, and the run exited 1 with both specimens straightened ok.
    from napari_unwind.datasets import hard_fish_phantom
    from napari_unwind.pipeline import run_all_iter
    from napari_unwind.progress import run

    ph = hard_fish_phantom(1000, kind="s-bend")
    vol, _ = beside_a_fish(ph, 1000)
    scan = write_volume(vol, tmp_path / "scan.nrrd", spacing=ph.spacing)
    res = run(run_all_iter(scan, tmp_path / "out"))
    rows = {r.label: r for r in res.specimens}
    assert not [r for r in res.specimens if r.status == "failed"], [(r.label, r.reason) for r in res.specimens]
    nobody = [r for r in res.specimens if r.reason.startswith("no body at full resolution")]
    assert nobody and all(r.status == "rejected" for r in nobody)
    assert not any((tmp_path / "out" / f"specimen-{r.label}.unwind.json").exists() for r in nobody)
    assert sum(r.status == "ok" for r in rows.values()) == 2 and exit_status(res.specimens) == 0


# ------------------------------------------------------------------------------------------------------------------
# a label map given as the mask
# ------------------------------------------------------------------------------------------------------------------
def test_label_counts_and_one_label_against_numpy():
    from napari_unwind.pipeline import mask_label_counts, pick_mask_label

    rng = np.random.default_rng(5)
    for dtype in (np.uint8, np.uint16, np.int16, np.int32, np.uint64):
        lab = rng.integers(0, 4, size=(7, 8, 9)).astype(dtype)
        if np.dtype(dtype).kind == "i":
            lab[0, 0, :3] = -2
        values, counts = np.unique(lab, return_counts=True)
        assert mask_label_counts(lab) == {int(v): int(c) for v, c in zip(values, counts) if v != 0}, dtype
        np.testing.assert_array_equal(pick_mask_label(lab, 3), lab == 3)
    assert mask_label_counts(np.ones((3, 3, 3), bool)) == {} and mask_label_counts(np.full((2, 2, 2), 0.5)) == {}
    assert mask_label_counts(np.ones((2, 2, 2))) == {1: 8}  # a float map of whole values is a label map
    with pytest.raises(InvalidInputError, match="no voxel of the mask holds label 7; its labels are 1, 2, 3"):
        pick_mask_label(rng.integers(0, 4, size=(5, 5, 5)).astype(np.uint8), 7)
    with pytest.raises(InvalidInputError, match="must be an integer, got 1.5"):
        pick_mask_label(np.ones((2, 2, 2), np.uint8), 1.5)
    # a label of what is no label map, even where a voxel equals it: a bool mask, a float map of fractional values
    with pytest.raises(InvalidInputError, match=r"no label map of integers \(dtype bool\): give it without a label"):
        pick_mask_label(np.ones((2, 2, 2), bool), 1)
    frac = np.ones((2, 2, 2), np.float32)
    frac[0, 0, 0] = 0.5
    with pytest.raises(InvalidInputError, match=r"\(dtype float32 with fractional values\)"):
        pick_mask_label(frac, 1)
    # a label map saved as float (whole values, as NIfTI tools often save one): its labels, as the integers'
    lab = rng.integers(0, 4, size=(7, 8, 9))
    for dtype in (np.float32, np.float64):
        values, counts = np.unique(lab, return_counts=True)
        assert mask_label_counts(lab.astype(dtype)) == {int(v): int(c) for v, c in zip(values, counts) if v != 0}
        np.testing.assert_array_equal(pick_mask_label(lab.astype(dtype), 2), lab == 2)
    with pytest.raises(InvalidInputError, match="holds label 2: it is empty"):
        pick_mask_label(np.zeros((2, 2, 2), np.uint8), 2)


def test_a_label_map_as_the_mask_is_named_and_one_label_is_straightened_as_its_own_mask(fish, mask_run, tmp_path):
    from napari_unwind.io import open_volume
    from napari_unwind.session import load_session

    tmp, f, mask, scan = fish
    straight, _, one_label_err = mask_run
    ends = ["--head", _arg(f.head), "--tail", _arg(f.tail)]
    lab = f.mask.astype(np.uint8)
    far = np.zeros(f.mask.shape, bool)
    far[:6, :6, :6] = True  # a block of another structure, away from the fish
    assert not (far & f.mask).any()
    lab[far] = 2
    labels = write_volume(lab, tmp_path / "labels.nrrd", spacing=f.spacing, unit=f.unit)
    # the label of the fish: the same straight volume as the fish's own mask, and the session records the label
    code, out, err = run_unwind("run", scan, "--mask", labels, "--mask-label", "1", *ends, "-o", tmp_path / "l.nrrd",
                                "-q")
    assert code == 0, err
    np.testing.assert_array_equal(open_volume(tmp_path / "l.nrrd").data, open_volume(straight).data)
    assert load_session(tmp_path / "l.unwind.json").segmentation.mask_label == 1
    # the same label map saved as float32 (as NIfTI tools often save one): the same
    flt = write_volume(lab.astype(np.float32), tmp_path / "labels_float.nrrd", spacing=f.spacing, unit=f.unit)
    code, out, err = run_unwind("run", scan, "--mask", flt, "--mask-label", "1", *ends, "-o", tmp_path / "lf.nrrd",
                                "-q")
    assert code == 0, err
    np.testing.assert_array_equal(open_volume(tmp_path / "lf.nrrd").data, open_volume(straight).data)
    code, out, err = run_unwind("skeleton", labels, "--mask-label", "1", "--volume", scan, *ends, "-o",
                                tmp_path / "s.unwind.json", "-q")
    assert code == 0 and load_session(tmp_path / "s.unwind.json").segmentation.mask_label == 1, err
    # every label at once: said, with each label's share of the mask's voxels
    code, out, err = run_unwind("run", scan, "--mask", labels, *ends, "-o", tmp_path / "all.nrrd", "-q")
    share = 100 * f.mask.sum() / (f.mask.sum() + far.sum())
    assert (f"the mask holds 2 labels (label 1: {share:.3g} %, label 2: {100 - share:.3g} % of its voxels): all are "
            "taken as one specimen") in err, err
    assert "--mask-label N" in err
    assert "labels" not in one_label_err, one_label_err  # a mask of one label says nothing
    # a label the map does not hold, or a label without a mask: one line, exit 1
    code, out, err = run_unwind("run", scan, "--mask", labels, "--mask-label", "3", *ends, "-o", tmp_path / "x.nrrd")
    assert code == 1 and err.strip() == "unwind: error: no voxel of the mask holds label 3; its labels are 1, 2: " \
                                        "give one of them", err
    assert not (tmp_path / "x.nrrd").exists()
    code, out, err = run_unwind("run", scan, "--select", "1,1,1", "--mask-label", "1", "-o", tmp_path / "y.nrrd")
    assert code == 1 and "--mask-label picks a label of --mask MASK" in err, err


def test_the_specimen_of_a_float_mask_against_numpy():
    """Whole-valued float masks (0.0 / 1.0, as NIfTI masks often are) are taken as they are; a map of fractional values
    (a probability or partial-volume map) at 0.5, or half its maximum beyond 1; NaN never; numpy and dask alike."""
    import dask.array as da

    from napari_unwind.io import Volume
    from napari_unwind.pipeline import specimen_mask

    rng = np.random.default_rng(11)
    body = rng.random((9, 10, 11)) < 0.3
    for whole in (body, body.astype(np.uint8) * 7, body.astype(np.float32)):
        got, note = specimen_mask(whole)
        assert got is whole and note is None
    prob = np.where(body, rng.uniform(0.55, 1.0, body.shape), rng.uniform(0.0, 0.45, body.shape)).astype(np.float32)
    scaled = (prob * 255).astype(np.float64)  # a 0/255 mask resampled linearly
    nan = body.astype(np.float32)
    nan[0, 0, :4] = np.nan
    for soft, level in ((prob, 0.5), (scaled, 0.5 * scaled.max())):
        for arr in (soft, da.from_array(soft, chunks=4)):
            got, note = specimen_mask(arr)
            np.testing.assert_array_equal(np.asarray(got), soft >= level)
            share = 100 * (soft >= level).sum() / (soft != 0).sum()
            assert note == (f"the mask holds fractional values ({soft.min():.3g} to {soft.max():.3g}, {soft.dtype}): "
                            f"a probability or partial-volume map; its voxels >= {level:.3g} are the specimen "
                            f"({share:.3g} % of its non-zero voxels); threshold it yourself to choose another level")
    got, note = specimen_mask(nan)
    np.testing.assert_array_equal(np.asarray(got), np.nan_to_num(nan) != 0)
    assert note is None
    vol, _ = specimen_mask(Volume(prob, spacing=(2.0, 1.0, 1.0), origin=(1.0, 2.0, 3.0)))
    assert vol.spacing == (2.0, 1.0, 1.0) and vol.origin == (1.0, 2.0, 3.0)
    np.testing.assert_array_equal(np.asarray(vol.data), prob >= 0.5)


def test_a_probability_map_as_the_mask_straightens_as_its_binary_mask(fish, mask_run, tmp_path):
    """The fish's mask as a map of fractional values (each voxel of the fish 0.6-1, the rest 0.001-0.4): the same
    straight volume as the binary mask, and said; the same profile from `unwind measure` as a 0.0 / 1.0 float mask."""
    from napari_unwind.io import open_volume

    tmp, f, mask, scan = fish
    ends = ["--head", _arg(f.head), "--tail", _arg(f.tail)]
    rng = np.random.default_rng(2)
    prob = np.where(f.mask, rng.uniform(0.6, 1.0, f.mask.shape), rng.uniform(0.001, 0.4, f.mask.shape))
    soft = write_volume(prob.astype(np.float32), tmp_path / "prob.nrrd", spacing=f.spacing, unit=f.unit)
    code, _, err = run_unwind("run", scan, "--mask", soft, *ends, "-o", tmp_path / "p.nrrd", "-q")
    assert code == 0, err
    assert "the mask holds fractional values" in err and "its voxels >= 0.5 are the specimen" in err, err
    straight, session, _ = mask_run
    np.testing.assert_array_equal(open_volume(tmp_path / "p.nrrd").data, open_volume(straight).data)
    flt = write_volume(f.mask.astype(np.float32), tmp_path / "float.nrrd", spacing=f.spacing, unit=f.unit)
    profiles = {}
    for name, m in (("uint8", mask), ("float", flt), ("prob", soft)):
        code, _, err = run_unwind("measure", "--session", session, "--mask", m, "-o",
                                  tmp_path / f"{name}.csv", "-q")
        assert code == 0, (name, err)
        profiles[name] = (tmp_path / f"{name}.csv").read_bytes()
    assert profiles["float"] == profiles["uint8"] and profiles["prob"] == profiles["uint8"]


def test_a_separate_part_off_the_path_is_named_as_such_not_as_a_cage_too_small(fish):
    """A second body in the mask (another specimen, or a piece cut off by the scan's face): the result is partial and
    its reason names the share in separate parts (scipy's labelling of the mask is the reference), not a larger
    cage; a fragment beside the body inside the cage counts nothing."""
    from scipy import ndimage

    from napari_unwind.pipeline import skeleton_step
    from napari_unwind.progress import run as drive
    from napari_unwind.session import Endpoints

    tmp, f, mask, scan = fish
    m = np.pad(f.mask, ((0, 0), (0, 0), (0, 40)))
    other = np.zeros_like(m)
    c = (m.shape[0] // 2, m.shape[1] // 2, m.shape[2] - 18)
    z, y, x = np.ogrid[: m.shape[0], : m.shape[1], : m.shape[2]]
    other[(z - c[0]) ** 2 / 30.0**2 + (y - c[1]) ** 2 / 8.0**2 + (x - c[2]) ** 2 / 8.0**2 <= 1] = True
    assert not ndimage.binary_dilation(other, iterations=3)[m].any()  # well apart from the fish
    both = m | other
    ends = Endpoints(head=tuple(f.head), tail=tuple(f.tail))
    res = drive(skeleton_step(both, ends, spacing=f.spacing))
    labels, n = ndimage.label(both, np.ones((3, 3, 3)))
    assert n == 2
    share = other.sum() / both.sum()
    assert res.apart == pytest.approx(share, rel=0.1), (res.apart, share)
    status, reason = judge(res)
    assert status == "partial" and f"{100 * res.apart:.2g} % of the mask lies in separate parts off the path" in reason
    assert "a larger or fitted cage" not in reason, reason
    assert any("separate part(s) of the mask" in w for w in res.warnings), res.warnings
    assert not any(w.startswith("the cage leaves") for w in res.warnings), res.warnings
    # the fish with a fragment two voxels off its side (a fin the segmentation broke off): in the cage, nothing apart
    cube = np.ones((3, 3, 3), bool)
    shell = ndimage.binary_dilation(m, cube, iterations=3) & ~ndimage.binary_dilation(m, cube, iterations=1)
    mid = f.centerline[len(f.centerline) // 2]
    on = np.argwhere(shell)
    p = on[np.argmin(np.linalg.norm(on - mid, axis=1))]
    frag = shell & ((z - p[0]) ** 2 + (y - p[1]) ** 2 + (x - p[2]) ** 2 <= 4)
    with_frag = m | frag
    assert ndimage.label(with_frag, np.ones((3, 3, 3)))[1] == 2 and frag.sum() >= 5
    alone = drive(skeleton_step(with_frag, ends, spacing=f.spacing))
    assert alone.apart == 0.0 and judge(alone)[0] == "ok", (alone.apart, judge(alone))
