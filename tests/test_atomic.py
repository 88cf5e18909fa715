import os
import subprocess
import sys
import threading
import time

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
    (target / "old").write_text("x")
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
def test_overwrite_replaces_folders_and_files_either_way(tmp_path, monkeypatch, portable):
    if portable:
        monkeypatch.setattr(_atomic, "_renameat2_fn", None)
    target = tmp_path / "out"
    target.write_text("a file")
    with atomic_output(target, overwrite=True) as tmp:  # a folder over a file
        tmp.mkdir()
        (tmp / "x").write_text("folder")
    assert (target / "x").read_text() == "folder"
    with atomic_output(target, overwrite=True) as tmp:  # a file over a folder
        tmp.write_text("file again")
    assert target.read_text() == "file again"
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
