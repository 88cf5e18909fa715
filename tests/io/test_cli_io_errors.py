"""The volume I/O errors of issue 9 as a user meets them: ``unwind`` run as a subprocess on damaged inputs, a full
disk, a relative path on a dask.distributed cluster, a pyramid level's geometry."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import uuid
import warnings
from pathlib import Path

import nrrd
import numpy as np
import pytest

from conftest import no_leftovers
from conftest import run_unwind as _run
from napari_unwind.io import open_volume, write_volume


def _one_error_line(err: str) -> str:
    """The single ``unwind: error:`` line of stderr (progress bars aside); fails on a traceback or several."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip() and "step/s" not in ln
             and not ln.lstrip().startswith(("write", "read", "straighten", "checking"))]
    assert len(lines) == 1 and lines[0].startswith("unwind: error: "), err
    return lines[0]


def _scan(tmp_path, name="scan.zarr", **options):
    a = np.random.default_rng(1).integers(1, 250, (40, 30, 30)).astype(np.uint8)
    return a, write_volume(a, tmp_path / name, spacing=(2.0, 0.5, 0.5), unit="um", chunks=16, max_side=16, **options)


# ------------------------------------------------------------------------------------------------------------------
# missing and corrupt chunks
# ------------------------------------------------------------------------------------------------------------------
def test_convert_refuses_a_store_with_a_missing_chunk(tmp_path):
    _, scan = _scan(tmp_path)
    chunk = scan / "0" / "c" / "0" / "0" / "0"
    chunk.unlink()
    code, _, err = _run("convert", scan, tmp_path / "out.nrrd", "-q")
    line = _one_error_line(err)
    assert code == 1 and str(chunk) in line and "missing" in line
    assert not (tmp_path / "out.nrrd").exists() and no_leftovers(tmp_path) == []


def test_convert_names_a_corrupt_chunk(tmp_path):
    _, scan = _scan(tmp_path)
    chunk = scan / "0" / "c" / "1" / "0" / "1"
    chunk.write_bytes(b"garbage" * 30)
    code, _, err = _run("convert", scan, tmp_path / "out.tif", "-q")
    line = _one_error_line(err)
    assert code == 1 and str(chunk) in line and "corrupt" in line and "re-import" in line
    assert not (tmp_path / "out.tif").exists() and no_leftovers(tmp_path) == []


@pytest.fixture(scope="module")
def straight_case(tmp_path_factory):
    """A phantom fish scan (OME-Zarr) and the session holding its true deformation."""
    from napari_unwind.datasets import fish_phantom
    from napari_unwind.demo import true_deformation
    from napari_unwind.session import Session, SourceInfo, save_session

    tmp = tmp_path_factory.mktemp("straight")
    fish = fish_phantom(seed=2, noise=0.0, tube=False, length=70.0, body_radius=5.0)
    scan = write_volume(fish.volume, tmp / "fish.zarr", spacing=fish.spacing, unit=fish.unit, chunks=32)
    session = save_session(Session(source=SourceInfo.from_path(scan), deformation=true_deformation(fish)),
                           tmp / "fish.unwind.json")
    return tmp, scan, session


def test_straighten_names_a_corrupt_chunk(straight_case, tmp_path):
    import shutil

    src, scan, session = straight_case
    copy = tmp_path / "fish.zarr"
    shutil.copytree(scan, copy)
    chunks = sorted(p for p in (copy / "0" / "c").rglob("*") if p.is_file())
    victim = chunks[len(chunks) // 2]
    victim.write_bytes(b"\x00not blosc" * 40)
    code, _, err = _run("straighten", copy, "--session", session, "-o", tmp_path / "s.zarr", "--no-verify", "-q")
    line = _one_error_line(err)
    assert code == 1 and str(victim) in line and "corrupt" in line
    assert not (tmp_path / "s.zarr").exists() and no_leftovers(tmp_path) == []


# ------------------------------------------------------------------------------------------------------------------
# a relative input path on a dask.distributed cluster started in another folder
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_straighten_a_relative_path_on_a_cluster_started_elsewhere(straight_case, tmp_path):
    distributed = pytest.importorskip("distributed")
    src, scan, session = straight_case
    reference = tmp_path / "local.nrrd"
    code, _, err = _run("straighten", scan, "--session", session, "-o", reference, "-q")
    assert code == 0, err
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=40)
    try:
        assert Path.cwd() != src  # the worker runs in this test's folder, not in the scan's
        out = tmp_path / "cluster.nrrd"
        r = subprocess.run([str(Path(sys.executable).with_name("unwind")), "straighten", scan.name, "--session",
                            session.name, "-o", str(out), "--scheduler", cluster.scheduler_address, "-q"],
                           cwd=src, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
    finally:
        cluster.close()
    got, expect = open_volume(out).data.compute(), open_volume(reference).data.compute()
    assert np.count_nonzero(expect) > 0.05 * expect.size
    np.testing.assert_array_equal(got, expect)


# ------------------------------------------------------------------------------------------------------------------
# a full disk (a real, tiny tmpfs)
# ------------------------------------------------------------------------------------------------------------------
@pytest.fixture
def tiny_disk(tmp_path):
    """A 256 KiB tmpfs (root only; skipped where mounting is not allowed)."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    mnt = tmp_path / f"tiny-{uuid.uuid4().hex[:6]}"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {r.stderr.decode(errors='replace').strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


@pytest.mark.parametrize("target", ["x.dcm", "x.dicom", "x.tif", "x.zarr", "x.nii", "x.nrrd"])
def test_convert_to_a_full_disk_is_one_line(tmp_path, tiny_disk, target):
    a = np.random.default_rng(0).integers(0, 60000, (40, 64, 64)).astype(np.uint16)  # 320 KiB > 256 KiB
    src = write_volume(a, tmp_path / "src.nrrd", spacing=(1, 1, 1), unit="mm", encoding="raw")
    args = ["convert", src, tiny_disk / target, "-q"]
    if target == "x.dcm":
        args += ["--format", "dicom"]
    code, _, err = _run(*args)
    line = _one_error_line(err)
    assert code == 1 and str(tiny_disk / target) in line, line
    if target in ("x.zarr", "x.nrrd"):  # compressed: it might fit, so it is tried and the full disk reported
        assert "no space left" in line, line
    else:  # 320 KiB uncompressed in 256 KiB: refused before a byte is written
        assert "uncompressed in the" in line and "free in" in line, line
    assert os.listdir(tiny_disk) == []  # the partial output is gone


@pytest.mark.parametrize("target", ["x.dcm", "x.dicom", "x.tif", "x.nii"])
def test_a_disk_that_fills_while_an_uncompressed_output_is_written_is_one_line(tmp_path, tiny_disk, target,
                                                                                  monkeypatch, capsys):
    """The up-front room check passed (the disk filled afterwards, e.g. by another program): the writer's own
    full-disk report, in process with the check switched off."""
    import napari_unwind.io._api as api
    from napari_unwind.cli import main

    monkeypatch.setattr(api, "check_room", lambda *a, **k: None)
    a = np.random.default_rng(0).integers(0, 60000, (40, 64, 64)).astype(np.uint16)
    src = write_volume(a, tmp_path / "src.nrrd", spacing=(1, 1, 1), unit="mm", encoding="raw")
    args = ["convert", str(src), str(tiny_disk / target), "-q"]
    if target == "x.dcm":
        args += ["--format", "dicom"]
    assert main(args) == 1
    line = _one_error_line(capsys.readouterr().err)
    assert str(tiny_disk / target) in line and "no space left" in line, line
    assert os.listdir(tiny_disk) == []


# ------------------------------------------------------------------------------------------------------------------
# messages that said something else
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["info", "import"])
def test_a_truncated_tiff_is_called_truncated(tmp_path, command):
    a = np.random.default_rng(0).integers(0, 255, (20, 73, 73)).astype(np.uint8)
    full = write_volume(a, tmp_path / "full.tif", spacing=(2, 1, 1), unit="um")
    whole = full.read_bytes()
    (tmp_path / "trunc.tif").write_bytes(whole[: len(whole) // 2])
    args = ["info", tmp_path / "trunc.tif"] if command == "info" else \
        ["import", tmp_path / "trunc.tif", tmp_path / "t.zarr", "-q"]
    code, _, err = _run(*args)
    line = _one_error_line(err)
    assert code == 1 and "truncated" in line and "single 2D image" not in line and "trunc.tif" in line


@pytest.mark.parametrize("value, word", [(np.inf, "+inf"), (-np.inf, "-inf")])
def test_infinity_is_called_by_its_name(tmp_path, value, word):
    a = np.ones((10, 20, 20), np.float32)
    a[3, 4, 5] = value
    src = tmp_path / "inf.nrrd"
    nrrd.write(str(src), a.transpose(2, 1, 0))  # pynrrd: x fastest; our writer refuses infinities
    code, _, err = _run("convert", src, tmp_path / "out.zarr", "-q")
    line = _one_error_line(err)
    assert code == 1 and word in line and "NaN" not in line and "(3, 4, 5)" in line and "--nan-value" in line
    # the option the message suggests exists and works
    code, _, err = _run("convert", src, tmp_path / "out.zarr", "--nan-value", "7", "-q")
    assert code == 0, err
    assert open_volume(tmp_path / "out.zarr").data.compute()[3, 4, 5] == 7


# ------------------------------------------------------------------------------------------------------------------
# the geometry of a pyramid level
# ------------------------------------------------------------------------------------------------------------------
def test_convert_a_level_keeps_that_levels_origin(tmp_path):
    _, scan = _scan(tmp_path)
    ms = json.loads((scan / "zarr.json").read_text())["attributes"]["ome"]["multiscales"][0]
    t = {c["type"]: c[c["type"]] for c in ms["datasets"][1]["coordinateTransformations"]}
    code, _, err = _run("convert", scan, tmp_path / "l1.nrrd", "--level", "1", "-q")
    assert code == 0, err
    data, header = nrrd.read(str(tmp_path / "l1.nrrd"))  # pynrrd: file axis order x, y, z
    assert list(header["space origin"][::-1]) == pytest.approx(t["translation"]) == [1.0, 0.25, 0.25]
    assert list(np.diag(header["space directions"])[::-1]) == pytest.approx(t["scale"])
