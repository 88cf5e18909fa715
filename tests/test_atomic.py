import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import no_leftovers
from napari_unwind.errors import OutputError
from napari_unwind.io import _atomic, open_volume, write_volume
from napari_unwind.io._atomic import atomic_output, final_name


def test_success_renames_into_place(tmp_path):
    target = tmp_path / "out.bin"
    with atomic_output(target) as tmp:
        assert tmp.parent == tmp_path and tmp != target
        tmp.write_bytes(b"abc")
        assert not target.exists()  # nothing visible until done
    assert target.read_bytes() == b"abc"
    assert no_leftovers(tmp_path) == []


def test_crash_leaves_nothing_and_keeps_old_output(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="crash while writing"):
        with atomic_output(target, overwrite=True) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("crash while writing")
    assert target.read_bytes() == b"old"
    assert no_leftovers(tmp_path) == []


def test_folder_outputs_replace_existing_folder(tmp_path):
    target = tmp_path / "store.zarr"
    target.mkdir()
    (target / ".zgroup").write_text('{"zarr_format": 2}')  # a store: metadata, a chunk key
    (target / "0.0.0").write_text("x")
    with atomic_output(target, overwrite=True) as tmp:
        tmp.mkdir()
        (tmp / "new").write_text("y")
    assert sorted(p.name for p in target.iterdir()) == ["new"]
    assert no_leftovers(tmp_path) == []


def test_refuses_to_overwrite_by_default(tmp_path):
    target = tmp_path / "a.zarr"
    target.write_bytes(b"keep")
    with pytest.raises(OutputError, match="already exists"):
        write_volume(np.zeros((2, 3, 4), np.uint8), target)
    assert target.read_bytes() == b"keep"


def test_missing_folder_is_a_clear_error(tmp_path):
    with pytest.raises(OutputError, match="does not exist"):
        write_volume(np.zeros((2, 3, 4), np.uint8), tmp_path / "nope" / "a.zarr")


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere; permission bits do not apply")
def test_unwritable_folder_is_a_clear_error(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(OutputError, match="not writable"):
            write_volume(np.zeros((2, 3, 4), np.uint8), ro / "a.zarr")
    finally:
        ro.chmod(0o700)


def test_unwritable_path_under_a_file_is_a_clear_error(tmp_path):
    # works for root too: a regular file cannot hold children
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError, match="does not exist; create it first"):
        write_volume(np.zeros((2, 3, 4), np.uint8), blocker / "a.zarr")


def test_error_midway_through_a_chunked_write_leaves_nothing(tmp_path):
    """A NaN in the last chunk is found only while streaming: the half-written zarr must vanish."""
    data = np.ones((40, 8, 8), np.float32)
    data[-1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_volume(data, tmp_path / "a.zarr", chunks=8)
    assert list(tmp_path.iterdir()) == []
    # replacing NaN by a value is the documented way out
    out = write_volume(data, tmp_path / "a.zarr", chunks=8, nan_value=0.0)
    back = open_volume(out).data.compute()
    assert back[-1, 0, 0] == 0 and np.isfinite(back).all()


# ------------------------------------------------------------------------------------------------------------------
# two writers of one new path: the second fails with "already exists" (issue 9)
# ------------------------------------------------------------------------------------------------------------------
def _race(target, kind):
    """Two threads write ``target`` without overwrite, both past the up-front check before either renames."""
    barrier = threading.Barrier(2)
    results = {}

    def writer(name):
        try:
            with atomic_output(target, overwrite=False) as tmp:
                if kind == "folder":
                    tmp.mkdir()
                    (tmp / "who").write_text(name)
                else:
                    tmp.write_text(name)
                barrier.wait(timeout=10)
                if name == "second":
                    time.sleep(0.2)  # let the first rename first
            results[name] = "ok"
        except OutputError as exc:
            results[name] = str(exc)

    threads = [threading.Thread(target=writer, args=(n,)) for n in ("first", "second")]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=20)
    return results


@pytest.mark.parametrize("kind", ["file", "folder"])
@pytest.mark.parametrize("portable", [False, True], ids=["renameat2", "portable"])
def test_the_second_of_two_writers_fails(tmp_path, monkeypatch, kind, portable):
    if portable:
        monkeypatch.setattr(_atomic, "_renameat2_fn", None)
    target = tmp_path / ("out.zarr" if kind == "folder" else "out.csv")
    results = _race(target, kind)
    assert results["first"] == "ok"
    assert "already exists" in results["second"] and str(target) in results["second"]
    written = (target / "who") if kind == "folder" else target
    assert written.read_text() == "first"
    assert no_leftovers(tmp_path) == []


@pytest.mark.parametrize("portable", [False, True], ids=["renameat2", "portable"])
def test_an_empty_folder_made_meanwhile_is_not_replaced(tmp_path, monkeypatch, portable):
    # rename() replaces an empty folder: without overwrite, that must not happen either
    if portable:
        monkeypatch.setattr(_atomic, "_renameat2_fn", None)
    target = tmp_path / "out.zarr"
    with pytest.raises(OutputError, match="already exists"):
        with atomic_output(target, overwrite=False) as tmp:
            tmp.mkdir()
            (tmp / "data").write_text("x")
            target.mkdir()  # someone else's, after our check
    assert target.is_dir() and list(target.iterdir()) == []
    assert no_leftovers(tmp_path) == []


@pytest.mark.parametrize("portable", [False, True], ids=["renameat2", "portable"])
def test_overwrite_never_swaps_a_folder_and_a_file(tmp_path, monkeypatch, portable):
    """A folder over a file or a file over a folder is refused, both left as they were (issue 20: --overwrite
    replaced a folder of a user's files with a TIFF); a store of ours over a store of ours is replaced."""
    if portable:
        monkeypatch.setattr(_atomic, "_renameat2_fn", None)
    target = tmp_path / "out"
    target.write_text("a file")
    with pytest.raises(OutputError, match="it is a file and the output is a folder"):
        with atomic_output(target, overwrite=True) as tmp:
            tmp.mkdir()
            (tmp / "x").write_text("folder")
    assert target.read_text() == "a file"
    target.unlink()
    target.mkdir()
    (target / ".zgroup").write_text("{}")  # a store of ours
    with pytest.raises(OutputError, match="it is a folder and the output is a file"):
        with atomic_output(target, overwrite=True) as tmp:
            tmp.write_text("file again")
    assert (target / ".zgroup").read_text() == "{}"
    with atomic_output(target, overwrite=True) as tmp:  # a store over a store
        tmp.mkdir()
        (tmp / "zarr.json").write_text("{}")
    assert sorted(p.name for p in target.iterdir()) == ["zarr.json"]
    assert no_leftovers(tmp_path) == []


# ------------------------------------------------------------------------------------------------------------------
# temporary outputs of killed processes are removed by the next writer, and only those (issue 9)
# ------------------------------------------------------------------------------------------------------------------
def _dead_pid():
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _tmp_name(target, pid, start, host, old=False):
    return target.with_name(f".{target.name}.0123abcd.p{pid}.s{start}.h{host}{'.old' if old else ''}{_atomic.TMP_MARK}")


def test_temp_names_record_the_writer(tmp_path):
    target = tmp_path / "fish.zarr"
    with atomic_output(target) as tmp:
        m = _atomic._TMP_RE.match(tmp.name)
        assert m and m.group("name") == "fish.zarr" and int(m.group("pid")) == os.getpid()
        assert m.group("host") == _atomic._host_tag() and final_name(tmp) == "fish.zarr"
        tmp.write_text("x")


def test_stale_temps_of_dead_writers_are_removed(tmp_path):
    target = tmp_path / "fish.zarr"
    host = _atomic._host_tag()
    me, my_start = os.getpid(), _atomic._start_time(os.getpid())
    dead = _dead_pid()
    stale_dir = _tmp_name(target, dead, 12345, host)
    stale_dir.mkdir()
    (stale_dir / "chunk").write_bytes(b"x" * 100)
    reused = _tmp_name(target, me, my_start + 1, host)  # our pid, but another process's start: it is gone
    reused.write_text("old")
    keep = {
        "live": _tmp_name(target, me, my_start, host),  # a writer that is running (this one)
        "other host": _tmp_name(target, dead, 12345, "ffffffff" if host != "ffffffff" else "eeeeeeee"),
        "older version": target.with_name(f".{target.name}.0123abcd{_atomic.TMP_MARK}"),
        "other target": _tmp_name(tmp_path / "fish.zarr2", dead, 12345, host),
        "other target 2": _tmp_name(tmp_path / "ish.zarr", dead, 12345, host),
        "not ours": tmp_path / f".fish.zarr.p{dead}.unwind-tmp",
    }
    for p in keep.values():
        p.write_text("keep")
    with atomic_output(target) as tmp:
        tmp.mkdir()
    assert not stale_dir.exists() and not reused.exists()
    assert all(p.exists() for p in keep.values())


def test_a_moved_aside_output_is_kept_while_the_target_is_missing(tmp_path):
    # a writer killed between moving the old output aside and renaming the new one: the aside is the only copy
    target = tmp_path / "fish.zarr"
    aside = _tmp_name(target, _dead_pid(), 1, _atomic._host_tag(), old=True)
    aside.write_text("the only copy")
    assert _atomic.remove_stale_temps(target) == []
    target.write_text("new")
    assert _atomic.remove_stale_temps(target) == [aside] and not aside.exists()


def test_a_stale_temp_of_a_temp_is_removed(tmp_path):
    # a writer that writes its temporary output atomically too: .(.fish.zarr.<id>.unwind-tmp).<id>.unwind-tmp
    target = tmp_path / "fish.zarr"
    outer = _tmp_name(target, _dead_pid(), 1, _atomic._host_tag())
    inner = _tmp_name(outer, _dead_pid(), 2, _atomic._host_tag())
    inner.mkdir()
    assert final_name(final_name(inner)) == "fish.zarr"
    assert final_name(inner) == "fish.zarr"     # a temporary inside a temporary names the outermost final output
    assert _atomic.remove_stale_temps(target) == [inner] and not inner.exists()


def test_special_files_and_nameless_paths_are_no_outputs(tmp_path):
    # renaming over /dev/null (as root) would replace the device: a FIFO stands in for it here
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(OutputError, match="device, pipe or socket"):
        with atomic_output(fifo, overwrite=True) as tmp:
            tmp.write_text("x")
    assert fifo.is_fifo()
    for bad in ("/", tmp_path / "sub" / ".."):
        with pytest.raises(OutputError, match="name the file or folder"):
            with atomic_output(bad, overwrite=True) as tmp:
                tmp.write_text("x")
    assert no_leftovers(tmp_path) == []


def test_the_current_folder_is_no_output(tmp_path, monkeypatch):
    # "unwind convert scan.zarr . --format ome-zarr --overwrite" would replace the folder one stands in
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "keep").write_text("mine")
    monkeypatch.chdir(tmp_path / "sub")
    for bad in (".", tmp_path, tmp_path / "sub"):
        with pytest.raises(OutputError, match="current folder"):
            with atomic_output(bad, overwrite=True) as tmp:
                tmp.mkdir()
    assert (tmp_path / "sub" / "keep").read_text() == "mine"


def test_remove_path_outlasts_a_writer_that_finishes_its_chunk(tmp_path):
    """After an interrupt, a computation's threads may still write a chunk into the folder being removed: the
    folder must stay gone (seen as a temp left by SIGINT mid-export under load)."""
    import threading
    import time

    from napari_unwind.io._atomic import remove_path

    folder = tmp_path / ".out.zarr.tmp"
    (folder / "c").mkdir(parents=True)
    stop = time.monotonic() + 0.4

    def writer():
        i = 0
        while time.monotonic() < stop:
            try:
                (folder / "c").mkdir(parents=True, exist_ok=True)
                (folder / "c" / f"{i}").write_bytes(b"x" * 100)
            except OSError:
                pass
            i += 1
            time.sleep(0.01)

    t = threading.Thread(target=writer)
    t.start()
    time.sleep(0.05)
    remove_path(folder, settle=5.0)
    t.join()
    assert not folder.exists()


def test_a_new_output_inside_an_input_folder_through_a_symlink_is_refused(tmp_path):
    """The output does not exist yet, so only resolving the link shows that it lies inside the input (issue 19:
    the symlink tests used outputs that existed, which ``samefile`` catches without resolving)."""
    from napari_unwind.io._atomic import check_not_input

    data = tmp_path / "data" / "scan.zarr"
    data.mkdir(parents=True)
    (tmp_path / "alias").symlink_to(tmp_path / "data", target_is_directory=True)
    new = tmp_path / "alias" / "scan.zarr" / "straight.tif"
    assert not new.exists() and os.path.realpath(new.parent) == str(data)  # the filesystem's own answer
    with pytest.raises(OutputError, match=r"lies inside the input .*scan\.zarr"):
        check_not_input([new], [data])
    # and the other way: the input named through the link, the output by its real path
    with pytest.raises(OutputError, match=r"lies inside the input .*alias.*scan\.zarr"):
        check_not_input([data / "new.tif"], [tmp_path / "alias" / "scan.zarr"])
    # a sibling of the input through the same link is fine
    check_not_input([tmp_path / "alias" / "other.tif"], [data])


# ------------------------------------------------------------------------------------------------------------------
# planted-bug pass (docs/testing-mutation.md, issue 19): companions, messages, the fault branches of the renames
# ------------------------------------------------------------------------------------------------------------------
def _nhdr(path, data_line):
    path.write_text(f"NRRD0004\ntype: uint8\ndimension: 1\nsizes: 4\nencoding: raw\n{data_line}\n")
    return path


def test_companions_of_an_output_against_a_headers_data_file(tmp_path):
    """Each companion rule alone: the input is a detached header whose data file (read from the header) is the
    output's companion, so only the output's .dat/.raw pairing can see the clash."""
    from napari_unwind.io._atomic import check_not_input

    tmp_path = tmp_path.resolve()
    on_raw = _nhdr(tmp_path / "a.nhdr", "data file: x.raw")
    with pytest.raises(OutputError) as info:
        check_not_input([tmp_path / "x.dat"], [on_raw])
    assert str(info.value) == (f"{tmp_path}/x.raw, written with the output {tmp_path}/x.dat, is {tmp_path}/x.raw, "
                               f"part of the input {on_raw} (both resolve to {tmp_path}/x.raw); inputs are never "
                               "modified: choose another output path")
    on_dat = _nhdr(tmp_path / "b.nhdr", "data file: y.dat")
    with pytest.raises(OutputError, match="y.dat, written with the output"):
        check_not_input([tmp_path / "y.raw"], [on_dat])
    # the same path twice, nothing resolved differently: no "(both resolve to ...)"
    with pytest.raises(OutputError) as info:
        check_not_input([tmp_path / "s.tif"], [tmp_path / "s.tif"])
    assert str(info.value) == (f"the output {tmp_path}/s.tif is the input {tmp_path}/s.tif; inputs are never "
                               "modified: choose another output path")


def test_a_headers_default_data_names_and_the_data_lines_it_does_not_follow(tmp_path):
    """A header that names no usable data file (none, LIST, a pattern with spaces), or does not exist yet, stands
    for STEM.raw, STEM.raw.gz and STEM.raw.bz2 (STEM = the name without ".nhdr"); an output header is an output
    (our writer names its data STEM.raw whatever an old header there says)."""
    from napari_unwind.io._atomic import check_not_input

    tmp_path = tmp_path.resolve()
    for name, line in (("abcdef.nhdr", None), ("b.nhdr", "datafile: LIST"), ("c.nhdr", "data file: c%03d.raw 0 3 1"),
                       ("d.nhdr", "encoding: raw")):
        header = tmp_path / name
        if line is not None:
            _nhdr(header, line)
        stem = name[: -len(".nhdr")]
        for suffix in (".raw", ".raw.gz", ".raw.bz2"):
            with pytest.raises(OutputError, match=f"the output .*/{stem}{suffix} is "):
                check_not_input([tmp_path / f"{stem}{suffix}"], [header])
        check_not_input([tmp_path / f"{stem}.raw.xz"], [header])  # not one of the three
    old = _nhdr(tmp_path / "o.nhdr", "data file: elsewhere.bin")
    with pytest.raises(OutputError, match=r"o\.raw, written with the output .*o\.nhdr"):
        check_not_input([old], [tmp_path / "o.raw"])
    check_not_input([old], [tmp_path / "elsewhere.bin"])


def test_a_symlinked_output_that_is_the_input_says_both_resolve(tmp_path):
    from napari_unwind.io._atomic import check_not_input

    tmp_path = tmp_path.resolve()
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "scan.tif").write_bytes(b"x")
    (tmp_path / "alias").symlink_to(tmp_path / "data", target_is_directory=True)
    with pytest.raises(OutputError) as info:
        check_not_input([tmp_path / "alias" / "scan.tif"], [tmp_path / "data" / "scan.tif"])
    assert str(info.value).endswith(f"(both resolve to {tmp_path}/data/scan.tif); inputs are never modified: "
                                    "choose another output path")


def test_a_dead_pid_has_no_start_time_and_a_live_writer_is_not_signalled(tmp_path):
    """Asking whether a writer lives must not send it a signal (signal 0 only checks): a live process whose SIGHUP
    kills it (its default) is still running after its temporary output was judged; /proc has no start time for
    a dead pid (0: unknown)."""
    assert _atomic._start_time(_dead_pid()) == 0
    child = subprocess.Popen([sys.executable, "-c", "import signal, time; signal.signal(signal.SIGHUP, "
                              "signal.SIG_DFL); print('ready', flush=True); time.sleep(30)"], stdout=subprocess.PIPE)
    try:
        assert child.stdout.readline().strip() == b"ready"
        target = tmp_path / "fish.zarr"
        live = _tmp_name(target, child.pid, _atomic._start_time(child.pid), _atomic._host_tag())
        live.write_text("being written")
        assert _atomic.remove_stale_temps(target) == [] and live.exists()
        time.sleep(0.2)
        assert child.poll() is None
    finally:
        child.kill()
        child.wait()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="renameat2 is Linux's")
def test_renameat2_is_found_on_linux_and_a_refusing_filesystem_falls_back(tmp_path, monkeypatch):
    """glibc has renameat2 (2.28+); a filesystem that answers EINVAL (no RENAME_NOREPLACE there) falls back to the
    portable rename, which still moves the output into place."""
    import ctypes
    import errno

    assert _atomic._load_renameat2() is not None

    def refuse(*args):
        ctypes.set_errno(errno.EINVAL)
        return -1

    monkeypatch.setattr(_atomic, "_renameat2_fn", refuse)
    target = tmp_path / "out.csv"
    with atomic_output(target, overwrite=False) as tmp:
        tmp.write_text("written")
    assert target.read_text() == "written" and no_leftovers(tmp_path) == []


def test_a_target_that_vanishes_during_the_swap_still_gets_the_output(tmp_path, monkeypatch):
    target = tmp_path / "out.zarr"
    target.mkdir()
    (target / ".zgroup").write_text("{}")  # a store of ours: replaceable
    (target / "0.0.0").write_text("x")
    real = _atomic._renameat2

    def vanish(src, dst, flags):
        if flags == _atomic._RENAME_EXCHANGE:
            _atomic.remove_path(dst)
            raise FileNotFoundError(2, "gone", str(dst))
        return real(src, dst, flags)

    monkeypatch.setattr(_atomic, "_renameat2", vanish)
    with atomic_output(target) as tmp:
        tmp.mkdir()
        (tmp / "new").write_text("y")
    assert sorted(p.name for p in target.iterdir()) == ["new"] and no_leftovers(tmp_path) == []


def test_a_failed_portable_swap_puts_the_old_output_back(tmp_path, monkeypatch):
    monkeypatch.setattr(_atomic, "_renameat2_fn", None)
    target = tmp_path / "out.zarr"
    target.mkdir()
    (target / ".zgroup").write_text("{}")  # a store of ours: replaceable
    (target / "0.0.0").write_text("keep me")
    real = os.replace

    def failing(src, dst):
        if Path(dst) == target and ".old" not in Path(src).name:
            raise OSError(5, "Input/output error")
        return real(src, dst)

    monkeypatch.setattr(_atomic.os, "replace", failing)
    with pytest.raises(OSError, match="Input/output error"):
        with atomic_output(target) as tmp:
            tmp.mkdir()
            (tmp / "new").write_text("y")
    monkeypatch.undo()
    assert (target / "0.0.0").read_text() == "keep me" and no_leftovers(tmp_path) == []


def test_remove_path_of_nothing_is_quiet_and_check_writable_says_what_to_do(tmp_path, monkeypatch):
    _atomic.remove_path(tmp_path / "missing.bin")
    with pytest.raises(OutputError, match=re.escape(f"e.g. {tmp_path}/sub/../out.zarr") + "$"):
        _atomic.check_writable(tmp_path / "sub" / "..")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(OutputError, match="not a file or folder; choose another output path$"):
        _atomic.check_writable(fifo)
    monkeypatch.setattr(_atomic.os, "access", lambda *a, **k: False)  # as root, permission bits do not apply
    with pytest.raises(OutputError, match="^" + re.escape(f"cannot write {tmp_path}/x: the folder {tmp_path} is not "
                                                          "writable; choose another output path") + "$"):
        _atomic.check_writable(tmp_path / "x")


def test_sweep_removes_what_a_write_in_flight_made_again(tmp_path):
    """An interrupted command sweeps its temporary outputs once its work has unwound: a chunk still in flight in a
    library's IO thread (here 0.2 s after the removal began) makes the folder again; it must be gone at the end."""
    import threading

    from napari_unwind.io._atomic import sweep, temp_path

    tmp = temp_path(tmp_path / "out.zarr")
    tmp.mkdir()
    (tmp / "c0").write_bytes(b"x")

    def late_chunk():
        tmp.mkdir(exist_ok=True)
        (tmp / "c1").write_bytes(b"y")

    late = threading.Timer(0.2, late_chunk)
    late.start()
    left = sweep(settle=3.0, quiet=0.5)
    late.join()
    assert tmp.absolute() in left and not tmp.exists()
    assert sweep() == []                       # nothing left to sweep, and the record is forgotten
