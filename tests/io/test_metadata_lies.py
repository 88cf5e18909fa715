"""Metadata that lies, checked before anything is read or allocated (issue 20, item 2), over seeded families:

- a scan, a header's data file, a ``.dat``'s raw file or a zarr chunk that is a named pipe (it would block the
  reader for ever): one line naming it, through the API, the CLI and napari's reader;
- a ``line skip`` of up to 10^12 lines in an NRRD header: refused at once, without reading;
- sizes that claim far more voxels than the file holds (NRRD, NIfTI, ``.dat``): one line, at once;
- a store that claims 10^15 voxels (a sparse zarr with no chunk written) converted to any format: refused before
  anything is written, naming the size and the free space, with no temporary output left.

Every case runs under a watchdog: a reader still blocked after a few seconds is released (the test opens the
pipe's other end) and the case fails as "blocked", never hanging the suite.
"""

from __future__ import annotations

import os
import struct
import subprocess
import threading
import time

import nibabel as nib
import numpy as np
import pytest
import zarr

from conftest import UNWIND, no_leftovers
from napari_unwind.cli import main
from napari_unwind.errors import InvalidInputError, OutputError
from napari_unwind.io import open_volume, write_volume

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")

#: Seconds a refused case may take (each is refused from its metadata alone: milliseconds in practice).
_QUICK = 5.0


def _run_guarded(fn, pipes=()):
    """Run ``fn()`` in a thread; if it is still running after _QUICK s, release any reader blocked on ``pipes``
    (by opening their write end) and fail. Returns (result, exception, seconds)."""
    box: dict = {}

    def target():
        t0 = time.perf_counter()
        try:
            box["result"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box["exc"] = exc
        box["seconds"] = time.perf_counter() - t0

    th = threading.Thread(target=target, daemon=True)
    th.start()
    th.join(_QUICK)
    if th.is_alive():
        for p in pipes:
            try:
                os.close(os.open(p, os.O_WRONLY | os.O_NONBLOCK))  # a blocked open for reading now sees EOF
            except OSError:
                pass
        th.join(_QUICK)
        pytest.fail(f"blocked for more than {_QUICK} s (a named pipe or a runaway read)")
    return box.get("result"), box.get("exc"), box["seconds"]


def _refused(fn, pattern, pipes=(), error=InvalidInputError):
    _, exc, seconds = _run_guarded(fn, pipes)
    assert isinstance(exc, error), f"expected {error.__name__}, got {exc!r}"
    msg = str(exc)
    assert "\n" not in msg and pattern in msg, msg
    assert seconds < _QUICK


# ------------------------------------------------------------------------------------------------------------------
# files that are named pipes
# ------------------------------------------------------------------------------------------------------------------
def _nhdr(folder, data_name, sizes=(6, 5, 4), extra=""):
    h = folder / "scan.nhdr"
    h.write_text(f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: {' '.join(map(str, sizes))}\nencoding: raw\n"
                 f"{extra}data file: {data_name}\n\n")
    return h


def _dat(folder, raw_name, resolution=(4, 5, 6)):
    d = folder / "scan.dat"
    d.write_text(f"ObjectFileName: {raw_name}\nResolution: {' '.join(map(str, resolution))}\n"
                 "SliceThickness: 1 1 1\nFormat: UCHAR\n")
    return d


_PIPE_CASES = ["scan.nrrd", "scan.tif", "scan.nii", "scan.dat", "nhdr-data", "dat-raw", "zarr-chunk-direct",
               "zarr-chunk-zarr", "zarr-metadata"]


def _pipe_case(kind, folder):
    """(path to open, the named pipe in it, what the message names)."""
    if kind in ("scan.nrrd", "scan.tif", "scan.nii", "scan.dat"):
        p = folder / kind
        os.mkfifo(p)
        return p, p, "named pipe"
    if kind == "nhdr-data":
        pipe = folder / "voxels.raw"
        os.mkfifo(pipe)
        return _nhdr(folder, pipe.name), pipe, "data file is a named pipe"
    if kind == "dat-raw":
        pipe = folder / "voxels.raw"
        os.mkfifo(pipe)
        return _dat(folder, pipe.name), pipe, "raw file is a named pipe"
    if kind == "zarr-chunk-direct":  # a store we wrote: chunks read without zarr (blosc + crc32c)
        out = write_volume(np.ones((8, 8, 8), np.uint8), folder / "v.zarr", chunks=8, max_side=8)
        chunk = out / "0" / "c" / "0" / "0" / "0"
        chunk.unlink()
        os.mkfifo(chunk)
        return out, chunk, "chunk file is a named pipe"
    if kind == "zarr-chunk-zarr":  # a plain zarr array: chunks read through zarr's store
        store = folder / "plain.zarr"
        zarr.open(str(store), mode="w", shape=(8, 8, 8), chunks=(8, 8, 8), dtype="u1")
        chunk = store / "c" / "0" / "0" / "0"
        chunk.parent.mkdir(parents=True)
        os.mkfifo(chunk)
        return store, chunk, "chunk file is a named pipe"
    if kind == "zarr-metadata":
        store = folder / "meta.zarr"
        store.mkdir()
        os.mkfifo(store / "zarr.json")
        return store, store / "zarr.json", "named pipe"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", _PIPE_CASES)
def test_a_named_pipe_is_refused_in_one_line_and_never_blocks(tmp_path, kind):
    path, pipe, says = _pipe_case(kind, tmp_path)
    _refused(lambda: open_volume(path).data[:].compute(), says, [pipe])


@pytest.mark.parametrize("kind", ["nhdr-data", "zarr-chunk-direct", "scan.nrrd"])
def test_the_cli_refuses_a_named_pipe_with_exit_1_and_leaves_no_temp(tmp_path, kind, capsys):
    path, pipe, says = _pipe_case(kind, tmp_path)
    out = tmp_path / "out.tif"
    result, exc, _ = _run_guarded(lambda: main(["convert", str(path), str(out), "-q"]), [pipe])
    assert exc is None and result == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("unwind: error:") and says in err[0], err
    assert not out.exists() and no_leftovers(tmp_path) == []


def test_napari_s_reader_says_why_a_named_pipe_cannot_be_read(tmp_path):
    from napari_unwind._napari._reader import get_reader

    path, pipe, says = _pipe_case("scan.nrrd", tmp_path)
    reader = get_reader(str(path))
    assert reader is not None  # ours: reading it gives the one-line reason instead of "no reader"
    _refused(lambda: reader(str(path)), says, [pipe])


# ------------------------------------------------------------------------------------------------------------------
# line skip and sizes that no file holds, seeded
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(6))
def test_a_line_skip_past_the_end_of_the_file_is_refused_at_once(tmp_path, seed):
    rng = np.random.default_rng(seed)
    data = tmp_path / "voxels.raw"
    lines = int(rng.integers(0, 5))
    data.write_bytes(b"\n" * lines + bytes(6 * 5 * 4))
    # more lines than the file has: from just past its end (it has `lines` newlines + 1 partial) up to 10^12
    skip = int(rng.choice([lines + 2, 10 ** int(rng.integers(3, 13))]))
    header = _nhdr(tmp_path, data.name, extra=f"line skip: {skip}\n")
    _refused(lambda: open_volume(header).data[:].compute(), "line skip", [])


def test_a_line_skip_inside_the_file_still_reads_the_voxels(tmp_path):
    voxels = np.arange(120, dtype=np.uint8).reshape(4, 5, 6)
    data = tmp_path / "voxels.raw"
    data.write_bytes(b"comment one\ncomment two\n" + voxels.tobytes())
    header = _nhdr(tmp_path, data.name, extra="line skip: 2\n")
    np.testing.assert_array_equal(open_volume(header).data.compute(), voxels)


def _claims(kind, folder, rng):
    """A file whose header claims about 10^9-10^12 voxels and holds a few bytes."""
    sizes = tuple(int(n) for n in rng.integers(1000, 10000, 3))
    if kind == "nhdr":
        (folder / "v.raw").write_bytes(bytes(64))
        return _nhdr(folder, "v.raw", sizes=sizes)
    if kind == "nrrd":
        p = folder / "v.nrrd"
        p.write_bytes(f"NRRD0004\ntype: uint16\ndimension: 3\nsizes: {' '.join(map(str, sizes))}\n"
                      "encoding: raw\nendian: little\n\n".encode() + bytes(64))
        return p
    if kind == "dat":
        (folder / "v.raw").write_bytes(bytes(64))
        return _dat(folder, "v.raw", resolution=sizes)
    if kind == "nii":
        small = folder / "small.nii"
        nib.save(nib.Nifti1Image(np.zeros((2, 2, 2), np.uint8), np.eye(4)), small)
        b = bytearray(small.read_bytes())
        struct.pack_into("<4h", b, 40, 3, *sizes)
        p = folder / "v.nii"
        p.write_bytes(bytes(b))
        return p
    raise AssertionError(kind)


@pytest.mark.parametrize("seed", range(8))
def test_sizes_no_file_holds_are_refused_at_once_by_info_and_convert(tmp_path, seed, capsys):
    rng = np.random.default_rng(100 + seed)
    kind = ["nhdr", "nrrd", "dat", "nii"][seed % 4]
    path = _claims(kind, tmp_path, rng)
    _refused(lambda: open_volume(path).data[:1, :1, :1].compute(), "truncated", [])
    out = tmp_path / "out.nrrd"
    for argv in (["info", str(path)], ["convert", str(path), str(out), "-q"]):
        result, exc, seconds = _run_guarded(lambda argv=argv: main(argv))
        err = capsys.readouterr().err.strip().splitlines()
        assert exc is None and result == 1 and seconds < _QUICK
        assert len(err) == 1 and "truncated" in err[0], err
    assert not out.exists() and no_leftovers(tmp_path) == []


# ------------------------------------------------------------------------------------------------------------------
# outputs that no disk holds
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix,how", [(".tif", "uncompressed"), (".nrrd", "compressed"), (".nii", "uncompressed"),
                                        (".dat", "uncompressed"), (".zarr", "compressed")])
def test_a_store_claiming_10_15_voxels_is_refused_before_anything_is_written(tmp_path, suffix, how):
    store = tmp_path / "sparse.zarr"  # valid zarr: a chunk never written reads as the fill value
    zarr.open(str(store), mode="w", shape=(10 ** 5,) * 3, chunks=(64, 64, 64), dtype="u1")
    before = sorted(p.name for p in tmp_path.iterdir())
    out = tmp_path / f"out{suffix}"
    # a process of its own: were the output not refused, the runaway is killed at the timeout, not left running
    try:
        done = subprocess.run([str(UNWIND), "convert", str(store), str(out), "-q"], capture_output=True, text=True,
                              timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("the convert ran for 60 s instead of being refused at once")
    err = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(err) == 1, done.stderr
    assert "1,000,000,000,000,000 bytes" in err[0] and "free in" in err[0], err
    assert ("even compressed" in err[0]) == (how == "compressed"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == before and no_leftovers(tmp_path) == []


def test_the_api_refuses_an_output_larger_than_the_free_space(tmp_path, monkeypatch):
    import shutil

    real = shutil.disk_usage

    def tiny(path):  # a disk with 1 MB free: 2 MB of voxels do not fit uncompressed
        return real(path)._replace(free=10 ** 6)

    monkeypatch.setattr(shutil, "disk_usage", tiny)
    a = np.zeros((20, 100, 1000), np.uint8)
    with pytest.raises(OutputError, match=r"2,000,000 bytes .* uncompressed .* free in"):
        write_volume(a, tmp_path / "a.nii")
    write_volume(a, tmp_path / "a.nii.gz")  # compressed: it may fit (all zeros: it does)
    assert no_leftovers(tmp_path) == []
