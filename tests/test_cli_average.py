"""``unwind average`` as a user runs it: a folder of straight volumes of one family (tests/test_average.py) in, the
mean, median, std and the residual table out, beside the given name; inputs kept, bad inputs one line."""

import csv

import numpy as np
from test_average import member

from conftest import no_leftovers
from conftest import run_unwind as _run
from napari_unwind.io import open_volume, write_volume


def test_a_folder_of_straight_fish_gives_mean_median_std_and_residuals(tmp_path):
    rng = np.random.default_rng(5)
    batch = tmp_path / "straight"
    batch.mkdir()
    for i, (z, th) in enumerate([(0.9, -20.0), (1.0, 0.0), (1.1, 15.0), (0.95, 30.0)]):
        v = member(z, th, rng.uniform(-2, 2, 2), rng.uniform(0.5, 2), rng.uniform(0, 200), rng)
        write_volume(v, batch / f"fish{i}.nrrd")
    odd = member(1.0, 0.0, (0.0, 0.0), 1.0, 0.0, rng, flip=True)
    write_volume(odd, batch / "fish9.nrrd")
    before = sorted((p.name, p.stat().st_mtime_ns) for p in batch.iterdir())
    out = tmp_path / "avg" / "mean.ome.zarr"
    out.parent.mkdir()
    code, stdout, err = _run("average", batch, "-o", out)
    assert code == 0, err
    assert "fish9.nrrd" in stdout                                   # named as least like the mean
    for name in ("mean.ome.zarr", "mean.median.ome.zarr", "mean.std.ome.zarr", "mean.residuals.csv"):
        assert (out.parent / name).exists(), name
    mean = open_volume(out)
    assert mean.unit == open_volume(batch / "fish0.nrrd").unit and mean.shape[0] > 100
    rows = list(csv.DictReader(open(out.parent / "mean.residuals.csv")))
    assert [r["name"] for r in rows] == [f"fish{i}.nrrd" for i in (0, 1, 2, 3, 9)]
    corr = {r["name"]: float(r["correlation"]) for r in rows}
    assert corr["fish9.nrrd"] < min(v for k, v in corr.items() if k != "fish9.nrrd")
    assert sorted((p.name, p.stat().st_mtime_ns) for p in batch.iterdir()) == before   # inputs untouched
    # again without --overwrite: refused before any work, the outputs kept
    stamp = (out.parent / "mean.residuals.csv").stat().st_mtime_ns
    code, _, err = _run("average", batch, "-o", out, "-q")
    assert code != 0 and "Traceback" not in err and (out.parent / "mean.residuals.csv").stat().st_mtime_ns == stamp
    assert no_leftovers(out.parent) == []


def test_what_cannot_be_averaged_is_one_line(tmp_path):
    session = tmp_path / "fish.unwind.json"
    session.write_text("{}")
    code, _, err = _run("average", session, tmp_path, "-o", tmp_path / "m.zarr")
    assert code != 0 and "straighten it first" in err and len(err.strip().splitlines()) == 1
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = _run("average", empty, "-o", tmp_path / "m.zarr")
    assert code != 0 and "no straight volume" in err and len(err.strip().splitlines()) == 1


def test_landmarks_from_a_csv_sharpen_the_ring_and_bad_rows_are_one_line(tmp_path):
    from test_average_landmarks import SPACING, centre_profile, tube

    batch = tmp_path / "straight"
    batch.mkdir()
    rows = []
    for i, (ns, c) in enumerate([(81, 30), (101, 60), (91, 41)]):
        write_volume(tube(ns, c), batch / f"tube{i}.nrrd")
        rows.append(f"tube{i}.nrrd,{c * SPACING}")
    lm = tmp_path / "landmarks.csv"
    lm.write_text("specimen,ring\n" + "\n".join(rows) + "\n")
    out = tmp_path / "mean.nrrd"
    code, _, err = _run("average", batch, "-o", out, "--landmarks", lm, "--normalise", "none", "--max-roll", "0", "-q")
    assert code == 0, err
    prof = centre_profile(np.asarray(open_volume(out).data))
    assert prof.max() > 2.8, prof.max()                        # the three rings on one station range: full height
    lm.write_text("\n".join(rows[:2]) + "\n")
    code, _, err = _run("average", batch, "-o", out, "--landmarks", lm, "--overwrite", "-q")
    assert code != 0 and "no landmarks for tube2.nrrd" in err and len(err.strip().splitlines()) == 1
