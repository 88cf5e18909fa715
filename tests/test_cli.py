"""The ``unwind`` command as a user runs it: exit codes, messages, files."""

import subprocess

import numpy as np
import pytest

from conftest import UNWIND, no_leftovers
from conftest import run_unwind as _run
from napari_unwind.cli import main
from napari_unwind.io import open_volume, write_volume


@pytest.fixture
def scan(tmp_path):
    a = (np.random.default_rng(0).random((40, 30, 20)) * 4000).astype(np.uint16)
    return a, write_volume(a, tmp_path / "scan.zarr", spacing=(2.0, 0.5, 0.5), unit="um", max_side=16)


def test_entry_point_is_installed_and_prints_version():
    r = subprocess.run([str(UNWIND), "--version"], capture_output=True, text=True)
    assert r.returncode == 0
    assert "napari-unwind" in r.stdout


def test_info_reports_geometry(scan, capsys):
    a, path = scan
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "40 x 30 x 20" in out and "uint16" in out
    assert "2 x 0.5 x 0.5 um" in out
    assert "levels:    3" in out and "on disk:" in out


def test_import_then_convert_round_trip(scan, tmp_path, capsys):
    a, path = scan
    out = tmp_path / "copy.zarr"
    assert main(["import", str(path), str(out), "--quiet", "--chunks", "8", "--max-side", "10"]) == 0
    v = open_volume(out)
    np.testing.assert_array_equal(v.data.compute(), a)
    assert v.spacing == (2.0, 0.5, 0.5) and v.levels[-1].shape == (10, 8, 5)
    assert v.data.chunksize == (8, 8, 8)
    # convert a lower level, overriding spacing
    low = tmp_path / "low.zarr"
    assert main(["convert", str(out), str(low), "--level", "1", "--quiet"]) == 0
    lv = open_volume(low)
    assert lv.shape == (20, 15, 10) and lv.spacing == (4.0, 1.0, 1.0)
    assert main(["convert", str(out), str(tmp_path / "sp.zarr"), "--spacing", "3", "--unit", "mm", "-q"]) == 0
    sv = open_volume(tmp_path / "sp.zarr")
    assert sv.spacing == (3.0, 3.0, 3.0) and sv.unit == "millimeter"




@pytest.mark.parametrize(
    "args, message",
    [
        (["info", "{tmp}/missing.nrrd"], "does not exist"),
        (["info", "{tmp}/unknown.xyz"], "unknown format"),
        (["import", "{scan}", "{tmp}/out.tif"], "name the output *.zarr"),
        (["convert", "{scan}", "{tmp}/out.xyz"], "cannot choose an output format"),
        (["convert", "{scan}", "{tmp}/no/such/folder/out.zarr"], "does not exist"),
        (["convert", "{scan}", "{scan}"], "is the input"),
        (["convert", "{scan}", "{tmp}/x.zarr", "--level", "9"], "levels 0..2"),
        (["import", "{scan}", "{tmp}/x.zarr", "--unit", "furlong"], "unknown length unit"),
    ],
)
def test_user_mistakes_give_one_clear_line_and_no_traceback(scan, tmp_path, args, message):
    _, path = scan
    (tmp_path / "unknown.xyz").write_text("hello")
    args = [a.format(tmp=tmp_path, scan=path) for a in args]
    code, out, err = _run(*args)
    assert code == 1
    assert message in err
    assert "Traceback" not in err and err.startswith("unwind: error:")
    assert no_leftovers(tmp_path) == []


def test_bad_option_values_are_usage_errors(scan, capsys):
    # exit status 1 and one line, like every other error (README); in-process: the same parser
    _, path = scan
    assert main(["import", str(path), "x.zarr", "--chunks", "0"]) == 1
    err = capsys.readouterr().err
    assert "positive whole numbers" in err and err.count("\n") == 1
    assert main(["convert", str(path), "x.zarr", "--spacing", "1,2"]) == 1
    err = capsys.readouterr().err
    assert "axis0,axis1,axis2" in err and err.startswith("unwind: error: ") and err.count("\n") == 1


def test_nan_needs_a_decision(tmp_path):
    a = np.zeros((10, 10, 10), np.float32)
    a[5, 5, 5] = np.nan
    src = write_volume(a, tmp_path / "f.zarr", nan_value=-1)  # stored without NaN...
    import zarr
    zarr.open_array(str(src / "0"), mode="r+")[5, 5, 5] = np.nan  # ...then corrupted behind our back
    code, _, err = _run("import", src, tmp_path / "g.zarr", "-q")
    assert code == 1 and "NaN at voxel (5, 5, 5)" in err
    assert not (tmp_path / "g.zarr").exists() and no_leftovers(tmp_path) == []
    code, _, err = _run("import", src, tmp_path / "g.zarr", "-q", "--nan-value", "7")
    assert code == 0, err
    assert open_volume(tmp_path / "g.zarr").data[5, 5, 5].compute() == 7


def test_progress_bar_shows_and_quiet_silences(scan, tmp_path):
    _, path = scan
    code, out, err = _run("import", path, tmp_path / "a.zarr", "--chunks", "8")
    assert code == 0 and "write" in err and "100%" in err and "imported" in out
    code, out, err = _run("import", path, tmp_path / "b.zarr", "--chunks", "8", "--quiet")
    assert code == 0 and out == "" and err == ""
