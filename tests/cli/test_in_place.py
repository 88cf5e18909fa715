"""An output that is, contains or lies inside an input is refused before any work starts (issue 9).

Every case once destroyed its input and exited 0. Each runs in the demo's folder with the relative names a user
types, on a copy of the demo's outputs of its own, and the inputs are checked byte for byte. The issue's seven
commands run as the installed command (all at once, to pay the interpreter's start once); every case also runs
in-process through ``main`` (the same code, quicker).
"""

import os
import time

import pytest
from cli_support import demo_copy, demo_outputs, leftovers, one_error_line, run_main, run_many, tree_hash

from napari_unwind.errors import OutputError


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return demo_outputs(tmp_path_factory)


@pytest.fixture
def here(demo, tmp_path):
    (tmp_path / "demo").mkdir()
    return demo_copy(demo, tmp_path / "demo")


CASES = {
    "straighten": ["straighten", "tank.zarr", "--session", "fish_1.unwind.json", "-o", "tank.zarr", "--overwrite"],
    "straighten-no-verify": ["straighten", "tank.zarr", "--session", "fish_1.unwind.json", "-o", "tank.zarr",
                             "--overwrite", "--no-verify"],
    "run": ["run", "tank.zarr", "--select", "{point}", "-o", "tank.zarr", "--overwrite"],
    "segment": ["segment", "tank.zarr", "-o", "tank.zarr", "--overwrite"],
    "bend": ["bend", "fish_1.zarr", "--session", "fish_1.unwind.json", "-o", "fish_1.zarr", "--overwrite"],
    "select": ["select", "feat.zarr", "--at", "{point}", "-o", "feat.zarr", "--overwrite"],
    "map-points": ["map-points", "--at", "{point}", "--session", "fish_1.unwind.json", "-o", "fish_1.unwind.json",
                   "--overwrite"],
    # the session's source is an input of straighten, bend and map-points too
    "bend-onto-source": ["bend", "fish_1.zarr", "--session", "fish_1.unwind.json", "-o", "tank.zarr",
                         "--overwrite"],
    # an output holding an input, and one inside an input
    "convert-into-parent": ["convert", "tank.zarr", ".", "--format", "ome-zarr", "--overwrite"],
    "convert-inside": ["convert", "tank.zarr", "tank.zarr/copy.zarr", "--overwrite"],
    # run writes a session too
    "run-session": ["run", "tank.zarr", "--select", "{point}", "-o", "fish.tif", "--session",
                    "tank.zarr/fish.unwind.json", "--overwrite"],
    "skeleton-inside": ["skeleton", "fish_1.zarr", "-o", "fish_1.zarr/s.unwind.json", "--overwrite"],
    "import-absolute": ["import", "{dir}/tank.zarr", "./tank.zarr", "--overwrite"],
}


ISSUE = ["straighten", "straighten-no-verify", "run", "segment", "bend", "select", "map-points"]


def _args(name, here):
    return [a.format(point=here.point, dir=here.dir) for a in CASES[name]]


@pytest.mark.parametrize("name", list(CASES))
def test_an_output_over_an_input_is_refused_at_once(here, name, capsys, monkeypatch):
    monkeypatch.chdir(here.dir)
    before = tree_hash(here.dir)
    t0 = time.perf_counter()
    code, out, err = run_main(_args(name, here), capsys)
    assert code == 1, (name, out, err)
    assert one_error_line(err) and " input " in err, err
    assert time.perf_counter() - t0 < 2  # refused before any work
    assert tree_hash(here.dir) == before
    assert leftovers(here.dir) == []


def test_the_issue_commands_as_a_user_runs_them(demo, tmp_path):
    copies = []
    for name in ISSUE:
        (tmp_path / name).mkdir()
        copies.append(demo_copy(demo, tmp_path / name))
    before = [tree_hash(h.dir) for h in copies]
    results = run_many([(_args(name, h), h.dir) for name, h in zip(ISSUE, copies)])
    for name, h, digest, (code, out, err) in zip(ISSUE, copies, before, results):
        assert code == 1, (name, out, err)
        assert one_error_line(err) and " input " in err, (name, err)
        assert tree_hash(h.dir) == digest, name
        assert leftovers(h.dir) == [], name


def test_links_are_resolved(here, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(here.dir)
    # the folder under another name: alias/tank.zarr is tank.zarr
    os.symlink(here.dir, tmp_path / "alias")
    before = tree_hash(here.dir)
    code, _, err = run_main(["convert", "tank.zarr", tmp_path / "alias" / "tank.zarr", "--overwrite"], capsys)
    assert code == 1 and one_error_line(err) and "alias/tank.zarr" in err and "is the input tank.zarr" in err, err
    # an input given through a link
    os.symlink(here.tank, tmp_path / "link.zarr")
    code, _, err = run_main(["segment", tmp_path / "link.zarr", "-o", "tank.zarr", "--overwrite"], capsys)
    assert code == 1 and one_error_line(err) and "link.zarr" in err, err
    assert tree_hash(here.dir) == before and leftovers(tmp_path) == []


def test_a_companion_file_of_the_output_is_an_input(here, capsys, monkeypatch):
    # fish.dat is written with fish.raw beside it: a .raw input would be replaced by the pair
    monkeypatch.chdir(here.dir)
    code, _, err = run_main(["convert", "tank.zarr", "fish.raw", "-q"], capsys)
    assert code == 0, err
    before = tree_hash(here.dir / "fish.raw")
    code, _, err = run_main(["convert", "fish.raw", "fish.dat", "--overwrite"], capsys)
    assert code == 1 and one_error_line(err) and "fish.raw" in err, err
    assert tree_hash(here.dir / "fish.raw") == before


def test_check_not_input_relations(tmp_path):
    from napari_unwind.io._atomic import check_not_input

    scan = tmp_path / "scan.zarr"
    scan.mkdir()
    (tmp_path / "a.nhdr").write_text("NRRD0004\ndata file: voxels.bin\n")
    check_not_input([tmp_path / "out.zarr"], [scan])  # unrelated: fine
    check_not_input([tmp_path / "scan.zarr2"], [scan])  # a name sharing a prefix is not inside
    check_not_input([None], [scan, None])
    with pytest.raises(OutputError, match="is the input"):
        check_not_input([tmp_path / "x" / ".." / "scan.zarr"], [scan])
    with pytest.raises(OutputError, match="inside the input"):
        check_not_input([scan / "0"], [scan])
    with pytest.raises(OutputError, match="contains the input"):
        check_not_input([tmp_path], [scan])
    with pytest.raises(OutputError, match="scan.raw"):  # scan.dat's voxels are scan.raw
        check_not_input([tmp_path / "scan.dat"], [tmp_path / "scan.raw"])
    with pytest.raises(OutputError, match="voxels.bin"):  # the detached header's data file, read from it
        check_not_input([tmp_path / "voxels.bin"], [tmp_path / "a.nhdr"])
    with pytest.raises(OutputError, match="is the input"):  # a slice pattern writes its folder
        check_not_input([scan / "s_{:04d}.png"], [scan])
