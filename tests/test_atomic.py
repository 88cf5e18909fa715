import os

import numpy as np
import pytest

from conftest import no_leftovers
from napari_unwind.errors import OutputError
from napari_unwind.io import open_volume, write_volume
from napari_unwind.io._atomic import atomic_output


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
    with pytest.raises(RuntimeError):
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
    with pytest.raises(OutputError):
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
