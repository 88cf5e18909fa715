"""``unwind skeleton``, ``unwind run`` and ``unwind demo`` as a user runs them, on phantoms with known truth.

References come from the phantoms (their dense true centreline, ends, masks and straight masks), never from the
code under test. The main flows run the installed command in a subprocess; quick refusals of bad arguments call
``napari_unwind.cli.main`` in-process (same code path, without paying the interpreter start each time).
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from conftest import no_leftovers, write_segment_crop
from conftest import run_unwind as _run
from napari_unwind.cli import main
from napari_unwind.datasets import fish_phantom, tank_phantom
from napari_unwind.io import open_volume, write_volume
from napari_unwind.session import load_session


def _arg(p):
    return ",".join(f"{float(v):.3f}" for v in p)


def _centreline_distances(deformation, fish, step=0.5):
    """Distances (voxels) from the deformation's centre curve to the phantom's dense true centreline."""
    s = np.linspace(0, deformation.length, int(deformation.length / step) + 2)
    centres, _ = deformation.sample(s)
    vox = (centres - np.asarray(deformation.origin)) / np.asarray(fish.spacing)
    d, _ = cKDTree(fish.centerline).query(vox)
    return d


def _one_error_line(err):
    lines = [line for line in err.splitlines() if line.strip()]
    return len(lines) == 1 and lines[0].startswith("unwind: error: ") and "Traceback" not in err


@pytest.fixture(scope="module")
def fish(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("skeleton_cli")
    f = fish_phantom(length=100, seed=3, tube=False)
    mask = write_volume(f.mask.astype(np.uint8), tmp / "mask.nrrd", spacing=f.spacing, unit=f.unit)
    scan = write_volume(f.volume, tmp / "scan.nrrd", spacing=f.spacing, unit=f.unit)
    return tmp, f, mask, scan


@pytest.fixture(scope="module")
def given_ends(fish):
    """``unwind skeleton MASK --head --tail --volume SCAN``: the session and the command's output."""
    tmp, f, mask, scan = fish
    session = tmp / "given.unwind.json"
    code, out, err = _run("skeleton", mask, "--head", _arg(f.head), "--tail", _arg(f.tail), "--volume", scan,
                          "-o", session)
    assert code == 0, err
    return session, out, err


def test_skeleton_with_given_ends_follows_the_true_centreline(fish, given_ends):
    tmp, f, mask, scan = fish
    session_path, out, _ = given_ends
    session = load_session(session_path)
    d = session.deformation
    dist = _centreline_distances(d, f)
    assert np.sqrt(np.mean(dist ** 2)) < 1.0
    # the ends used are the given ones (moved into the mask by at most a few voxels)
    assert np.linalg.norm(np.subtract(session.endpoints.head, f.head)) < 3
    assert np.linalg.norm(np.subtract(session.endpoints.tail, f.tail)) < 3
    assert abs(d.length - f.length) < 0.05 * f.length
    assert session.source.path == str(scan.absolute()) and session.source.shape == f.shape
    assert d.unit == "micrometer" and np.allclose(d.spacing, f.spacing)
    # the summary
    assert f"{len(d)} keyframes" in out and "length" in out and "twist" in out and "times:" in out
    assert "padding" in out and "cage half extents" in out and "suggested" not in out
    # the session records the twist profile and where it was estimated (the body, not the tips)
    tw = session.twist
    assert tw.source == "estimated" and len(tw.s) == len(tw.angle) == len(tw.confidence) > 50
    assert abs(tw.s[-1] - f.length) < 0.05 * f.length
    conf = np.asarray(tw.confidence)
    assert conf[len(conf) // 2] == 1.0 and conf[0] == 0.0 and 0.6 < conf.mean() < 1.0


def test_straighten_accepts_the_session_made_with_volume(fish, given_ends, tmp_path):
    _, f, _, scan = fish
    session_path, _, _ = given_ends
    out = tmp_path / "straight.nrrd"
    # the checksum of the scan is verified (no --no-verify)
    code, _, err = _run("straighten", scan, "--session", session_path, "-o", out, "-q")
    assert code == 0, err
    straight = open_volume(out)
    d = load_session(session_path).deformation
    assert straight.shape == d.output_shape()
    # the fish lies along the middle of the straight volume: its centre column is body (flesh or spine)
    ns, ny, nx = straight.shape
    p0 = int(round(d.pad[0] / min(f.spacing)))
    centre = straight.data[p0 + 5: ns - p0 - 5, ny // 2, nx // 2].compute()
    assert np.mean(centre > 550) > 0.9


def test_the_skeleton_of_a_fish_does_not_fold(given_ends):
    assert load_session(given_ends[0]).deformation.folds() == []


def test_suggested_ends_are_printed_and_the_mask_is_the_source(fish, tmp_path):
    tmp, f, mask, scan = fish
    session_path = tmp_path / "suggested.unwind.json"
    code, out, err = _run("skeleton", mask, "-o", session_path)
    assert code == 0, err
    line = next(li for li in out.splitlines() if li.startswith("suggested head:"))
    session = load_session(session_path)
    head, tail = np.array(session.endpoints.head), np.array(session.endpoints.tail)
    assert f"{head[0]:.1f}" in line and f"{tail[0]:.1f}" in line and f"--head {head[0]:.4g}," in line
    # the suggestion is near the true ends, the right way round
    assert np.linalg.norm((head - f.head) * f.spacing) < 8 and np.linalg.norm((tail - f.tail) * f.spacing) < 8
    assert session.source.path == str(mask.absolute())
    assert "source is the mask" in out and "--volume" in out
    # straightening the scan with it is refused: the session belongs to the mask, as the summary said
    code, _, err = _run("straighten", scan, "--session", session_path, "-o", tmp_path / "x.nrrd", "-q")
    assert code == 1 and "changed" in err and "Traceback" not in err
    assert not (tmp_path / "x.nrrd").exists()


def test_a_mask_cropped_to_its_box_gives_the_same_skeleton(fish, given_ends, tmp_path):
    """A mask saved cropped to the specimen's box with its origin (as 3D Slicer saves a segment; header written here
    with pynrrd) is placed on the scan: the same deformation as the full mask's, and the placement is said."""
    tmp, f, _, scan = fish
    path, lo, crop = write_segment_crop(f.mask, f.spacing, tmp_path / "fish.seg.nrrd")
    session = tmp_path / "crop.unwind.json"
    code, out, err = _run("skeleton", path, "--head", _arg(f.head), "--tail", _arg(f.tail), "--volume", scan,
                          "-o", session)
    assert code == 0, err
    at = " x ".join(str(int(v)) for v in lo)
    assert f"the mask fish.seg.nrrd (shape {' x '.join(map(str, crop.shape))}) is a box of the scan's grid: " \
           f"placed at voxel {at} by its origin" in err
    ours, full = load_session(session).deformation, load_session(given_ends[0]).deformation
    assert ours.to_dict() == full.to_dict()


@pytest.fixture(scope="module")
def cut(fish):
    """The fish mask with a slab of 10 voxels removed across the body: two parts."""
    tmp, f, _, _ = fish
    m = f.mask.copy()
    a = int(f.centerline[len(f.centerline) // 2, 0])
    m[a: a + 10] = False
    path = write_volume(m.astype(np.uint8), tmp / "cut.nrrd", spacing=f.spacing, unit=f.unit)
    before = f.centerline[np.flatnonzero(f.centerline[:, 0] < a - 2)[-1]]
    after = f.centerline[np.flatnonzero(f.centerline[:, 0] > a + 12)[0]]
    return path, before, after


def test_a_mask_in_two_parts_needs_a_chain(fish, cut, tmp_path):
    _, f, _, _ = fish
    path, before, after = cut
    session_path = tmp_path / "cut.unwind.json"
    code, _, err = _run("skeleton", path, "--head", _arg(f.head), "--tail", _arg(f.tail), "-o", session_path, "-q")
    assert code == 1 and _one_error_line(err)
    assert "different parts" in err and "part 1" in err and "part 2" in err and "--chain" in err
    assert not session_path.exists() and no_leftovers(tmp_path) == []

    code, out, err = _run("skeleton", path, "--chain", _arg(f.head), _arg(before), "--chain", _arg(after),
                          _arg(f.tail), "-o", session_path)
    assert code == 0, err
    session = load_session(session_path)
    assert len(session.endpoints.chain) == 2 and "2 parts chained" in out
    assert np.linalg.norm(np.subtract(session.endpoints.head, f.head)) < 3
    dist = _centreline_distances(session.deformation, f)
    assert np.sqrt(np.mean(dist ** 2)) < 1.5


def test_bad_ends_and_masks_are_refused_in_one_line(fish, tmp_path, capsys):
    tmp, f, mask, _ = fish
    out = tmp_path / "s.unwind.json"
    empty = write_volume(np.zeros((20, 20, 20), np.uint8), tmp_path / "empty.nrrd")
    corner = np.array([1.0, 1.0, 1.0])
    assert not f.mask[1, 1, 1]
    cases = [
        (["skeleton", mask, "--head", _arg(f.head), "--tail", _arg(f.head)], "same point"),
        (["skeleton", mask, "--head", _arg(corner), "--tail", _arg(f.tail)], "--snap-tolerance"),
        (["skeleton", mask, "--head=-40,0,0", "--tail", _arg(f.tail)], "outside the volume"),
        (["skeleton", mask, "--head", _arg(f.head)], "both --head and --tail"),
        (["skeleton", mask, "--head", _arg(f.tail), "--chain", _arg(f.head), _arg(f.tail)], "--head"),
        (["skeleton", empty], "empty"),
    ]
    for args, words in cases:
        code = main([str(a) for a in [*args, "-o", out, "-q"]])
        err = capsys.readouterr().err
        assert code == 1 and _one_error_line(err) and words in err, (args, err)
        assert not out.exists() and no_leftovers(tmp_path) == []
    code = main([str(a) for a in ["skeleton", mask, "-o", tmp_path / "s.json", "-q"]])
    err = capsys.readouterr().err
    assert code == 1 and ".unwind.json" in err and _one_error_line(err)


# ------------------------------------------------------------------------------------------------------------------
# unwind run
# ------------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tank(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("run_cli")
    t = tank_phantom(n_fish=2, seed=1, length=90)
    scan = write_volume(t.volume, tmp / "tank.zarr", spacing=t.spacing, unit=t.unit)
    return tmp, t, scan


def _check_straight(path, session, fish):
    straight = open_volume(path)
    d = session.deformation
    assert straight.shape == d.output_shape()
    ns, ny, nx = straight.shape
    p0 = int(round(d.pad[0] / min(fish.spacing)))
    centre = straight.data[p0 + 5: ns - p0 - 5, ny // 2, nx // 2].compute()
    assert np.mean(centre > 550) > 0.9
    assert np.sqrt(np.mean(_centreline_distances(d, fish) ** 2)) < 1.0


def test_run_segments_selects_and_straightens(tank):
    tmp, t, scan = tank
    fish = t.fish[0]
    click = fish.centerline[len(fish.centerline) // 2]
    out = tmp / "fish0.nrrd"
    code, stdout, err = _run("run", scan, "--select", _arg(click), "-o", out)
    assert code == 0, err
    session = load_session(tmp / "fish0.unwind.json")  # the default: beside the output, named after it
    assert session.source.path == str(scan.absolute())
    assert session.segmentation.k == 5 and len(session.segmentation.selected) == 1
    np.testing.assert_allclose(session.segmentation.seeds[0], click, atol=1e-3)
    assert "suggested head:" in stdout and "segmented" in stdout and "straightened" in stdout
    _check_straight(out, session, fish)


def test_run_with_a_mask_and_given_ends(tank):
    tmp, t, scan = tank
    fish = t.fish[1]
    mask = write_volume(fish.mask.astype(np.uint8), tmp / "fish1_mask.tif", spacing=t.spacing, unit=t.unit)
    out, session_path = tmp / "fish1.zarr", tmp / "sessions_fish1.unwind.json"
    code, stdout, err = _run("run", scan, "--mask", mask, "--head", _arg(fish.head), "--tail", _arg(fish.tail),
                             "-o", out, "--session", session_path, "-q")
    assert code == 0, err
    assert stdout == "" and not (tmp / "fish1.unwind.json").exists()
    session = load_session(session_path)
    # the selection was the mask file: the session records it (unwind measure and the dock find it again)
    assert session.segmentation.mask == str(mask.absolute()) and session.segmentation.k is None
    assert session.source.path == str(scan.absolute())
    assert np.linalg.norm(np.subtract(session.endpoints.head, fish.head)) < 3
    _check_straight(out, session, fish)


def test_run_needs_a_mask_or_a_click(tank, tmp_path, capsys):
    _, _, scan = tank
    out = tmp_path / "x.nrrd"
    for extra, words in (([], "--select"), (["--mask", scan, "--select", "1,2,3"], "not both"),
                         (["--mask", scan, "--features", "3"], "do not apply with --mask")):
        code = main([str(a) for a in ["run", scan, "-o", out, "-q", *extra]])
        err = capsys.readouterr().err
        assert code == 1 and _one_error_line(err) and words in err, err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_run_refuses_a_click_in_the_background(tank, tmp_path):
    _, _, scan = tank
    code, _, err = _run("run", scan, "--select", "0,0,0", "-o", tmp_path / "x.nrrd", "-q")
    assert code == 1 and _one_error_line(err) and "background" in err
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------------------------
# the demo and its accuracy measure
# ------------------------------------------------------------------------------------------------------------------
def test_accuracy_against_known_perturbations():
    from napari_unwind.deformation import Deformation
    from napari_unwind.demo import accuracy, true_deformation

    f = fish_phantom(length=100, seed=3, tube=False, noise=0.0)
    d = true_deformation(f, step=2.0)  # keyframes every 2 voxels: chords within 0.02 voxels of the bends
    exact = accuracy(f, d)
    assert exact["centreline_rms"] < 0.05 and exact["twist_max"] < 1.0 and abs(exact["arclength_error"]) < 0.5
    assert exact["start_offset"] < 0.01 and exact["end_offset"] < 0.01 and exact["dice"] > 0.9
    # turned by 30 degrees about the curve everywhere
    turned = d
    for i in range(len(d)):
        turned = turned.twist_keyframe(i, np.radians(30))
    acc = accuracy(f, turned)
    assert abs(acc["twist_median"] - 30) < 1 and abs(acc["twist_max"] - 30) < 2
    assert acc["centreline_rms"] < 0.05 and acc["dice"] < exact["dice"] - 0.05
    # moved sideways by 2 voxels along u
    moved = Deformation.from_keyframes(d.positions + 2.0 * d.frames[:, 0] * min(f.spacing), d.frames,
                                       d.half_extents, spacing=d.spacing, unit=d.unit)
    acc = accuracy(f, moved)
    assert abs(acc["centreline_rms"] - 2.0) < 0.1 and acc["dice"] < exact["dice"] - 0.05
    # starting 10 voxels down the fish: the s axes are aligned, the offset is reported
    k = np.searchsorted(d.knots, 10.0)
    shorter = Deformation.from_keyframes(d.positions[k:], d.frames[k:], d.half_extents[k:], spacing=d.spacing,
                                         unit=d.unit, pad=(d.knots[k], 0.0))
    acc = accuracy(f, shorter)
    assert abs(acc["start_offset"] - d.knots[k]) < 0.05 and acc["dice"] > exact["dice"] - 0.01


def test_demo_runs_end_to_end(tmp_path):
    code, out, err = _run("demo", "--fish", "1", "-o", tmp_path / "demo")
    assert code == 0, err + out
    for name in ("tank.tif", "tank.zarr", "tank_mip.png", "fish_1.zarr", "fish_1.unwind.json", "fish_1_mip.png"):
        assert (tmp_path / "demo" / name).exists(), name
    assert "suggested head" in out and "from the true head" in out and "Dice" in out
    session = load_session(tmp_path / "demo" / "fish_1.unwind.json")
    assert session.segmentation.seeds and session.deformation is not None
    straight = open_volume(tmp_path / "demo" / "fish_1.zarr")
    assert straight.shape == session.deformation.output_shape()


def test_cage_option_sets_every_keyframe_and_the_report_has_the_fold_figures(fish, tmp_path):
    tmp, f, mask, scan = fish
    session = tmp_path / "cage.unwind.json"
    code, out, err = _run("skeleton", mask, "--head", _arg(f.head), "--tail", _arg(f.tail), "--cage", "4,5",
                          "--no-twist", "-o", session)
    # a 4 x 5 cage round a body wider than that leaves part of the mask out: the session is written, and the
    # command says it is partial (exit 3) in one line
    assert code == 3 and sum(line.startswith("unwind: partial: coverage") for line in err.splitlines()) == 1, err
    d = load_session(session).deformation
    # the given half extents everywhere; a side is only ever shrunk where a bend would fold it
    he = d.half_extents
    assert np.all(he <= np.array([4.0, 5.0]) + 1e-9) and np.isclose(he[:, 0].max(), 4.0) and np.isclose(
        he[:, 1].max(), 5.0)
    assert "cage: min Jacobian" in out and "coverage" in out and "max tilt" in out


@pytest.mark.parametrize("bad", ["4,-1", "a,b", "1,2,3", "nan,1"])
def test_bad_cage_is_refused_in_one_line(fish, tmp_path, capsys, bad):
    tmp, f, mask, scan = fish
    assert main(["skeleton", str(mask), "--cage", bad, "-o", str(tmp_path / "x.unwind.json")]) == 1
    err = capsys.readouterr().err
    assert _one_error_line(err) and "--cage" in err and bad in err


def test_a_fold_over_no_specimen_voxel_is_a_warning_and_one_over_the_specimen_is_refused():
    """The one fold rule (pipeline.fold_rule, which export_step applies for every face)."""
    from napari_unwind.deformation import Deformation
    from napari_unwind.pipeline import fold_rule

    t = np.linspace(0, np.pi / 2, 40)
    pos = np.stack([np.zeros_like(t), 10 * np.sin(t), 10 * (1 - np.cos(t))], axis=1)
    n = np.stack([np.zeros_like(t), np.cos(t), np.sin(t)], axis=1)
    v = np.tile([1.0, 0.0, 0.0], (len(t), 1))
    folding = Deformation.from_keyframes(pos, np.stack([np.cross(v, n), v, n], axis=1), 12.0)
    assert folding.folds()
    verdict = fold_rule(folding, folded=0.0, allow_folds=False)
    assert not verdict.refused and len(verdict.message.splitlines()) == 1
    assert "no voxel of the specimen" in verdict.message and "--cage" in verdict.message
    for folded in (0.01, None):
        verdict = fold_rule(folding, folded=folded, allow_folds=False)
        assert verdict.refused and "--allow-folds" in verdict.message
    verdict = fold_rule(folding, folded=0.01, allow_folds=True)
    assert not verdict.refused and "1 % of the specimen" in verdict.message


def test_run_with_fill_holes_refines_at_the_lowest_threshold_the_mask_covers(tmp_path):
    """One isovalue rule everywhere (dock, unwind select, the server's jobs, unwind run): a closed shell selected
    with --fill-holes covers the dimmer rod inside it, so the mask is cut at the rod's contrast midpoint (the lowest
    of the covered features' specimen isovalues), not the shell's."""
    from scipy import ndimage

    from napari_unwind.segmentation import segment

    z, y, x = np.mgrid[:96, :40, :40].astype(float)
    along = np.clip(z, 20, 76)
    d = np.sqrt((z - along) ** 2 + (y - 19.5) ** 2 + (x - 19.5) ** 2)  # distance to the capsule's axis segment
    v = np.full(d.shape, 100.0)
    v[(d > 10) & (d < 13)] = 1000.0  # the shell
    v[d < 4] = 400.0  # the rod inside
    v = (v + np.random.default_rng(1).normal(0, 5, v.shape)).astype(np.uint16)
    scan = write_volume(v, tmp_path / "capsule.nrrd", spacing=(1.0, 1.0, 1.0), unit="um")
    click = (48.0, 19.5 + 11.5, 19.5)  # in the shell's wall
    out = tmp_path / "capsule_straight.nrrd"
    code, _, err = _run("run", scan, "--select", _arg(click), "--features", "2", "--fill-holes", "-o", out, "-q")
    assert code == 0, err
    seg = load_session(tmp_path / "capsule_straight.unwind.json").segmentation
    # the reference: the same segmentation, the shell filled by scipy, the lowest threshold of what it covers
    features = segment(open_volume(scan), features=2)
    shell = features.labels[tuple(np.floor(np.asarray(click) + 0.5).astype(int))]
    covered = np.unique(features.labels[ndimage.binary_fill_holes(features.labels == shell)])
    thresholds = {int(i): features.stat(int(i)).threshold for i in covered if i > 0}
    assert len(thresholds) == 2 and min(thresholds.values()) < thresholds[int(shell)]  # the rod is covered, dimmer
    assert seg.selected == (int(shell),) and seg.fill_holes
    # the phantom's values: the rod (400) in the medium (100) is the dimmer body; its midpoint within 10 % of the
    # contrast, so the rod is in the mask
    assert abs(seg.isovalue - 250.0) <= 0.1 * 300.0, seg.isovalue


def test_dorsal_points_set_the_twist_through_them(fish, tmp_path):
    tmp, f, mask, scan = fish
    session = tmp_path / "dorsal.unwind.json"
    at = np.linspace(0, len(f.arclength) - 1, 6).astype(int)[1:-1]   # four landmarks along the body
    # on the fish's side (its u), 5 units off the centreline: where the estimate would never put v
    side = f.frames[at, 0]
    marks = f.centerline[at] + 5.0 * side / np.asarray(f.spacing)
    code, out, err = _run("skeleton", mask, "--head", _arg(f.head), "--tail", _arg(f.tail),
                          *[a for p in marks for a in ("--dorsal", _arg(p))], "-o", session)
    assert code == 0, err
    assert "set by the dorsal landmarks" in out
    assert load_session(session).twist.source == "landmarks"
    d = load_session(session).deformation
    s_true = f.arclength[at]
    _, frames = d.sample(s_true * d.length / f.length)
    angle = np.degrees(np.arccos(np.clip(np.sum(frames[:, 1] * side, axis=1), -1, 1)))
    assert angle.max() <= 8.0, angle  # v at each landmark points at it (the curve and the keyframes within a voxel)


def test_dorsal_landmarks_and_no_twist_are_refused_together(fish, tmp_path, capsys):
    tmp, f, mask, scan = fish
    assert main(["skeleton", str(mask), "--dorsal", "1,2,3", "--no-twist", "-o", str(tmp_path / "x.unwind.json")]) == 1
    err = capsys.readouterr().err
    assert _one_error_line(err) and "--no-twist" in err
