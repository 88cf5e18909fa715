"""Containers, specimens and ``run --all`` (issue 10, item 4): a tank splits into its specimens.

References are independent of the code under test: hand-built volumes whose containers and specimens follow
from their construction, numpy's covariance for the elongation, and the phantom tanks' true masks.
"""

from __future__ import annotations

import ast
import csv
from pathlib import Path

import dask.array as da
import numpy as np
import pytest
from _scenes import rods_in_tube

from napari_unwind.datasets import tank_phantom
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume, open_volume, write_volume
from napari_unwind.segmentation import join_tree, refine_mask, segment, select, specimens
from napari_unwind.warp import straighten

PKG = Path(__file__).resolve().parents[1] / "napari_unwind"


def dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))


# ------------------------------------------------------------------------------------------------------------------
# the import circle of item 8
# ------------------------------------------------------------------------------------------------------------------
def _imports(path: Path, package: str) -> set[str]:
    """Modules of ``package`` that ``path`` imports anywhere (functions included), by relative or absolute name."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level == 1 and node.module:
                out.add(f"{package}.{node.module}")
            elif node.level == 1:
                out.update(f"{package}.{a.name}" for a in node.names)
            elif node.module and node.module.startswith(package + "."):
                out.add(node.module)
    return out


def test_the_segmentation_modules_import_no_circle():
    package = "napari_unwind.segmentation"
    files = {f"{package}.{p.stem}": p for p in (PKG / "segmentation").glob("_*.py")}
    graph = {m: _imports(p, package) & set(files) for m, p in files.items()}
    state: dict[str, int] = {}

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            assert state.get(n) != 1, f"import circle: {' -> '.join(path + [m, n])}"
            if n not in state:
                visit(n, path + [m])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])
    assert f"{package}._features" in graph[f"{package}._jointree"]  # the tree simplifies with the features module


# ------------------------------------------------------------------------------------------------------------------
# containers and specimens by construction
# ------------------------------------------------------------------------------------------------------------------
def _scene() -> tuple[np.ndarray, dict[str, np.ndarray]]:
    return rods_in_tube(ball_on_border=True)


def test_containers_and_specimens_follow_from_the_construction():
    vol, parts = _scene()
    features = segment(vol, features=5, smooth=0)
    which = {}
    for name, m in parts.items():
        ids, counts = np.unique(features.labels[m], return_counts=True)
        which[name] = int(ids[np.argmax(counts)])
        assert dice(features.labels == which[name], m) > 0.9, name
    st = {name: features.stat(fid) for name, fid in which.items()}
    assert st["tube"].container and not st["tube"].touches_border  # it encloses the rods
    assert st["ball"].container and st["ball"].touches_border
    for name in ("rod_a", "rod_b", "rod_out"):
        assert not st[name].container and not st[name].touches_border, name
    assert {s.id for s in specimens(features)} == {which["rod_a"], which["rod_b"], which["rod_out"]}
    assert specimens(features, min_elongation=100) == ()


def test_elongation_is_the_principal_axis_ratio():
    vol, _ = _scene()
    spacing = (1.0, 0.5, 2.0)
    features = segment(Volume(data=vol, spacing=spacing), features=5, smooth=0)
    for s in features.stats:
        pts = np.argwhere(features.labels == s.id) * np.asarray(spacing)
        cov = np.cov(pts.T, bias=True) + np.diag(np.asarray(spacing) ** 2 / 12.0)
        ev = np.sort(np.linalg.eigvalsh(cov))[::-1]
        assert s.elongation == pytest.approx(np.sqrt(ev[0] / ev[1]), rel=1e-6)


def test_specimens_refuses_bad_input():
    vol, _ = _scene()
    features = segment(vol, features=3, smooth=0)
    with pytest.raises(InvalidInputError, match="needs Features"):
        specimens(vol)
    with pytest.raises(InvalidInputError, match="min_elongation"):
        specimens(features, min_elongation=0.5)
    with pytest.raises(InvalidInputError, match="min_voxels"):
        specimens(features, min_voxels=0)


def test_a_dense_wall_tank_gives_its_fish_and_nothing_else():
    tank = tank_phantom(n_fish=3, seed=0, wall_value=3000, wall_thickness=6, wall_noise=600, gap=1)
    features = join_tree(tank.volume).simplify(8)  # more than enough: the wall's pieces are containers or round
    found = specimens(features)
    assert len(found) == len(tank.fish)
    matched = set()
    for fish in tank.fish:
        best = max(found, key=lambda s: dice(features.labels == s.id, fish.mask))
        assert dice(features.labels == best.id, fish.mask) >= 0.8
        matched.add(best.id)
    assert len(matched) == len(tank.fish)
    wall = [s for s in features.stats if s.id not in matched and s.voxel_count > 0.5 * features.labels.size / 100]
    assert all(s.container or s.elongation < 3 for s in wall)


# ------------------------------------------------------------------------------------------------------------------
# run --all
# ------------------------------------------------------------------------------------------------------------------
def _dense_tank(n_fish: int, seed: int, gap: float = 1.0):
    return tank_phantom(n_fish=n_fish, seed=seed, wall_value=3000, wall_thickness=6, wall_noise=600, gap=gap)


def _check_batch(tank, result, outdir: Path) -> dict[str, float]:
    """Every fish found once and straightened, nothing else; returns the Dice of each fish's mask."""
    from napari_unwind.session import load_session

    vol = tank.to_volume()
    assert [r["status"] for r in result.rows] == ["ok"] * len(tank.fish), result.failed
    rows = {r["specimen"]: r for r in result.rows}
    with open(outdir / "specimens.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    # the table has a row for every candidate; the rejected ones (the tube) each say why
    assert all(r["reason"] for r in table if r["status"] == "rejected")
    assert [r["specimen"] for r in table if r["status"] != "rejected"] == [str(k) for k in rows]
    out: dict[str, float] = {}
    for fish in tank.fish:
        best_id, best = None, 0.0
        for fid in rows:  # one feature per fish here: the specimen's name is its feature id
            st = result.features.stat(int(fid))
            mask = np.asarray(refine_mask(vol, select(result.features, ids=[int(fid)]), features=result.features,
                                          isovalue=st.threshold))
            d = dice(mask, fish.mask)
            if d > best:
                best_id, best = fid, d
        assert best >= 0.9, (fish.name, best_id, best)
        out[fish.name] = best
        row = rows.pop(best_id)  # one specimen per fish
        straight = open_volume(outdir / row["output"])
        assert straight.shape[0] * straight.spacing[0] >= row["length"]  # the body, and the cage's end padding
        session = load_session(outdir / row["session"])
        assert session.segmentation.selected == (int(best_id),)
        # straightened: the true fish, carried by the session's deformation, lies in the straight box (its volume
        # is kept to within 10 %: nothing of the body is lost off the cage)
        true_mask = Volume(data=da.from_array(fish.mask.astype(np.float32)), spacing=tank.spacing)
        moved = straighten(true_mask, session.deformation, order=1)
        kept = float(moved.data.sum().compute()) * float(np.prod(moved.spacing))
        whole = float(np.count_nonzero(fish.mask)) * float(np.prod(tank.spacing))
        assert 0.9 <= kept / whole <= 1.1, (fish.name, kept / whole)
        print(f"{fish.name}: Dice {best:.3f}, body kept {kept / whole:.3f}, length {row['length']:.1f} (true "
              f"{fish.length:.1f})")
    assert not rows  # nothing else was straightened
    return out


def _check_rows_against_the_fish(tank, table, outdir: Path) -> None:
    """Each row's specimen against the phantom's truth, one fish per row (the skeleton's goals of
    tests/skeleton/test_skeleton.py, and the coverage goal):

    - its centre within 1 voxel RMS of the fish's centreline (the phantom's own dense samples of c(s));
    - its length within 2 % of the fish's arclength s (the phantom's) between the points its two ends fall on;
    - its span, padding included, reaching the fish's ends in the scan (the s of the fish's labelled voxels; a
      fish cut by a face ends there), and its centreline within 3 voxels of each of them;
    - its cage holding at least 99 % of the fish's labelled voxels unfolded, by tests/cage_reference.py's inverse.
    """
    from cage_reference import coverage
    from scipy.spatial import cKDTree

    from napari_unwind.session import load_session

    matched = set()
    for r in table:
        assert r["reason"] == "" and (outdir / r["output"]).is_dir()
        d = load_session(outdir / r["session"]).deformation
        # the row is the session's deformation (the csv keeps 6 digits)
        assert int(r["keyframes"]) == len(d.keyframes) and float(r["length"]) == pytest.approx(d.length, rel=1e-5)
        c, _ = d.sample(np.linspace(0.0, d.length, 2000))
        c = c - np.asarray(d.origin)
        rms = [float(np.sqrt(np.mean(cKDTree(f.centerline_physical).query(c)[0] ** 2))) / min(tank.spacing)
               for f in tank.fish]
        i = int(np.argmin(rms))
        fish = tank.fish[i]
        assert i not in matched, (r["specimen"], fish.name)
        matched.add(i)
        tree = cKDTree(fish.centerline_physical)
        s_ends = fish.arclength[tree.query(c[[0, -1]])[1]]
        head_first = s_ends[0] <= s_ends[1]
        spanned = abs(s_ends[1] - s_ends[0])
        fish_vox = np.argwhere(tank.labels == i + 1) * np.asarray(tank.spacing)
        s_fish = fish.arclength[tree.query(fish_vox)[1]]
        pads = d.pad if head_first else d.pad[::-1]
        reach = (min(s_ends) - pads[0], max(s_ends) + pads[1])
        held = coverage(d, tank.labels == i + 1, tank.spacing)
        print(f"specimen {r['specimen']} -> {fish.name}: RMS {rms[i]:.2f} voxels, length {d.length:.2f} over true "
              f"s {min(s_ends):.2f}..{max(s_ends):.2f} ({spanned:.2f}); with its padding {reach[0]:.2f}..{reach[1]:.2f}"
              f", the fish in the scan {s_fish.min():.2f}..{s_fish.max():.2f} of {fish.length:.2f}; coverage "
              f"{held:.4f}")
        assert rms[i] <= 1.0, (fish.name, rms[i])
        assert abs(d.length / spanned - 1) <= 0.02, (fish.name, d.length, spanned)
        assert reach[0] <= s_fish.min() and reach[1] >= s_fish.max(), (fish.name, reach, s_fish.min(), s_fish.max())
        # the centreline itself spans the fish to within 3 voxels at each end (the padding holds no body: a
        # centreline that stopped 19.5 voxels short of a thin tail reported a length 16 % short)
        vox = max(tank.spacing)
        assert min(s_ends) - s_fish.min() <= 3 * vox and s_fish.max() - max(s_ends) <= 3 * vox, \
            (fish.name, s_ends, s_fish.min(), s_fish.max())
        assert held >= 0.99, (fish.name, held)
    assert len(matched) == len(tank.fish)


def test_run_all_on_a_small_dense_tank(tmp_path):
    """The CLI as a user runs it: one straight volume and session per fish, the table, exit 0."""
    from conftest import run_unwind

    tank = _dense_tank(3, 0)
    scan = write_volume(tank.volume, tmp_path / "tank.zarr", spacing=tank.spacing, unit=tank.unit)
    code, out, err = run_unwind("run", scan, "--all", "-o", tmp_path / "out", "-q")
    assert code == 0, err
    with open(tmp_path / "out" / "specimens.csv", newline="") as fh:
        table = [r for r in csv.DictReader(fh) if r["status"] != "rejected"]  # rejected candidates are rows too
    assert len(table) == 3 and {r["status"] for r in table} == {"ok"}
    _check_rows_against_the_fish(tank, table, tmp_path / "out")
    # a second run into the same folder needs --overwrite; --all takes no click options
    code, _, err = run_unwind("run", scan, "--all", "-o", tmp_path / "out", "-q")
    assert code == 1 and "--overwrite" in err and "Traceback" not in err
    code, _, err = run_unwind("run", scan, "--all", "-o", tmp_path / "o2", "--select", "1,2,3")
    assert code == 1 and "--select" in err and not (tmp_path / "o2").exists()


def test_a_failing_specimen_is_reported_and_the_others_go_on(tmp_path, monkeypatch, capsys):
    import napari_unwind.skeleton as skeleton
    from napari_unwind.cli import main

    tank = _dense_tank(3, 0)
    scan = write_volume(tank.volume, tmp_path / "tank.zarr", spacing=tank.spacing, unit=tank.unit)
    real = skeleton.estimate_deformation_iter
    calls = []

    def flaky(mask, *a, **kw):  # the second specimen's skeleton fails
        calls.append(1)
        if len(calls) == 2:
            raise InvalidInputError("the mask has no interior (planted failure)")
        return (yield from real(mask, *a, **kw))

    monkeypatch.setattr(skeleton, "estimate_deformation_iter", flaky)
    code = main(["run", str(scan), "--all", "-o", str(tmp_path / "out"), "-q"])
    err = capsys.readouterr().err
    assert code == 1 and "planted failure" in err and err.count("failed") == 1
    with open(tmp_path / "out" / "specimens.csv", newline="") as fh:
        table = [r for r in csv.DictReader(fh) if r["status"] != "rejected"]  # rejected candidates are rows too
    assert [r["status"] for r in table] == ["ok", "failed", "ok"]
    assert "planted failure" in table[1]["reason"] and table[1]["output"] == ""
    assert all((tmp_path / "out" / r["output"]).is_dir() for r in (table[0], table[2]))


@pytest.mark.slow
@pytest.mark.parametrize("n_fish, seed, gap", [(3, 21, 1.0), (5, 22, 3.0), (8, 23, 1.0), (12, 24, 1.0)])
def test_every_fish_of_a_dense_tank_is_found_and_straightened(tmp_path, n_fish, seed, gap):
    from napari_unwind.batch import straighten_all

    tank = _dense_tank(n_fish, seed, gap)
    scan = write_volume(tank.volume, tmp_path / "tank.zarr", spacing=tank.spacing, unit=tank.unit)
    result = straighten_all(scan, tmp_path / "out")
    dices = _check_batch(tank, result, tmp_path / "out")
    print(f"{n_fish} fish (seed {seed}, gap {gap}): {result.seconds:.1f} s, Dice "
          + " ".join(f"{d:.3f}" for d in dices.values()))


def test_run_all_checks_its_output_folder_first(tmp_path):
    from napari_unwind.batch import straighten_all
    from napari_unwind.errors import OutputError

    missing_scan = tmp_path / "no-such-scan.zarr"  # never opened: the folder is checked first
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="is a file"):
        straighten_all(missing_scan, tmp_path / "file")
    with pytest.raises(OutputError, match="does not exist"):
        straighten_all(missing_scan, tmp_path / "a" / "b")
    (tmp_path / "done").mkdir()
    (tmp_path / "done" / "specimens.csv").write_text("")
    with pytest.raises(OutputError, match="--overwrite"):
        straighten_all(missing_scan, tmp_path / "done")


def test_tank_wall_and_touching_options():
    t = tank_phantom(n_fish=2, seed=3, length=60, body_radius=5, wall_value=3000, wall_thickness=5, wall_noise=300,
                     gap=0)
    r_in, r_out = t.tube_radii
    assert r_out - r_in == pytest.approx(5.0)
    c = np.asarray(t.tube_center)
    jj, kk = np.mgrid[: t.shape[1], : t.shape[2]]
    rho = np.hypot(jj - c[0], kk - c[1])
    wall = np.broadcast_to(((rho > r_in + 1) & (rho < r_out - 1))[None], t.shape)
    outside = np.broadcast_to((rho > r_out + 2)[None], t.shape)
    assert np.median(t.volume[wall]) == pytest.approx(3000, abs=60)
    assert t.volume[wall].std() > 4 * t.volume[outside].std()  # the wall's own noise
    assert t.min_distance <= 2.0  # gap 0: the fish touch (masks about one voxel apart)
    with pytest.raises(InvalidInputError, match="wall_thickness"):
        tank_phantom(n_fish=1, wall_thickness=0.5)
    with pytest.raises(InvalidInputError, match="wall_noise"):
        tank_phantom(n_fish=1, wall_noise=-1)
