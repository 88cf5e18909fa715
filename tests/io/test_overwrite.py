"""--overwrite replaces only what this program could have written (issue 20, item 1): a file by a file, a store of
ours by a store; never a folder of other files, never a folder by a file or a file by a folder. The API refuses the
same paths as the CLI, and what is refused is left as it was, byte for byte, with no temporary beside it."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import pytest

from napari_unwind.errors import OutputError
from napari_unwind.io import write_volume


def _tree(path: Path) -> dict[str, str]:
    """Every file under ``path`` with the hash of its bytes (a file alone: one entry)."""
    if path.is_file():
        return {path.name: hashlib.sha256(path.read_bytes()).hexdigest()}
    return {str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


def _no_temps(folder: Path) -> None:
    assert not [p.name for p in folder.iterdir() if "unwind-tmp" in p.name]


@pytest.fixture
def small(tmp_path):
    data = np.arange(4 * 5 * 6, dtype=np.uint16).reshape(4, 5, 6)
    return data, write_volume(data, tmp_path / "small.zarr", spacing=(1.0, 2.0, 3.0))


def _thesis(folder: Path) -> Path:
    folder.mkdir()
    (folder / "thesis.docx").write_bytes(b"PK\x03\x04 years of work")
    (folder / "figures").mkdir()
    (folder / "figures" / "fig1.svg").write_text("<svg/>")
    return folder


@pytest.mark.parametrize("name", ["out.tif", "out.nrrd", "out.zarr", "out.nii.gz"])
def test_a_folder_of_other_files_is_never_replaced(small, tmp_path, name):
    from conftest import run_unwind

    data, scan = small
    target = _thesis(tmp_path / name)
    before = _tree(target)
    code, out, err = run_unwind("convert", scan, target, "--overwrite")
    assert code == 1 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "cannot replace" in err and ("thesis.docx" in err or "figures" in err), err
    assert _tree(target) == before and target.is_dir()
    with pytest.raises(OutputError, match=r"cannot replace .* not an output of napari-unwind"):
        write_volume(data, target, overwrite=True)  # the API refuses it too
    assert _tree(target) == before
    _no_temps(tmp_path)


def test_a_file_is_not_replaced_by_a_folder_nor_a_folder_by_a_file(small, tmp_path):
    data, _ = small
    notes = tmp_path / "notes.zarr"  # a file that happens to have a store's name
    notes.write_text("not a store")
    with pytest.raises(OutputError, match="it is a file and the output is a folder"):
        write_volume(data, notes, overwrite=True)
    assert notes.read_text() == "not a store"
    store = write_volume(data, tmp_path / "store.tif.zarr", spacing=1.0)  # one of ours, under a file's name
    target = tmp_path / "as.tif"
    os.rename(store, target)
    before = _tree(target)
    with pytest.raises(OutputError, match="it is a folder and the output is a file"):
        write_volume(data, target, overwrite=True)
    assert _tree(target) == before
    _no_temps(tmp_path)


def test_what_this_program_wrote_is_replaced(small, tmp_path):
    from napari_unwind.io import open_volume

    data, _ = small
    for name in ("again.zarr", "again.tif", "again.nrrd"):
        write_volume(data, tmp_path / name, spacing=1.0)
        write_volume(data + 1, tmp_path / name, spacing=1.0, overwrite=True)
        assert np.array_equal(np.asarray(open_volume(tmp_path / name).data), data + 1)
    empty = tmp_path / "empty.zarr"
    empty.mkdir()
    write_volume(data, empty, spacing=1.0, overwrite=True)  # an empty folder holds nothing to lose
    assert np.array_equal(np.asarray(open_volume(empty).data), data)
    _no_temps(tmp_path)


def test_a_folder_of_slices_is_ours_to_replace_but_not_with_a_stranger_among_them(small, tmp_path):
    data, _ = small
    stack = tmp_path / "slices"
    stack.mkdir()
    for i in range(3):
        (stack / f"slice_{i:04d}.png").write_bytes(b"\x89PNG fake")
    from napari_unwind.io._atomic import _foreign

    assert _foreign(stack) == ""
    (stack / "README.txt").write_text("my notes")
    assert "README.txt" in _foreign(stack)
    with pytest.raises(OutputError, match="README.txt"):
        write_volume(data, stack / "slice_{:04d}.png", overwrite=True)
    assert (stack / "README.txt").read_text() == "my notes"
    (stack / "README.txt").unlink()
    write_volume(data, stack / "slice_{:04d}.png", overwrite=True)  # a stack of slices: ours to replace
    assert sorted(p.name for p in stack.iterdir()) == [f"slice_{i:04d}.png" for i in range(4)]


def test_the_api_refuses_to_write_into_its_own_input(small, tmp_path):
    """import_volume("X.zarr", "X.zarr/inner.zarr") wrote into its own input from Python; the CLI refused it."""
    from napari_unwind.io import import_volume, open_volume

    data, scan = small
    before = _tree(scan)
    for target in (scan / "inner.zarr", scan):
        with pytest.raises(OutputError, match="input"):
            import_volume(scan, target, overwrite=True)
        with pytest.raises(OutputError, match="input"):
            write_volume(open_volume(scan), target, overwrite=True)
    assert _tree(scan) == before
    _no_temps(tmp_path)


# ------------------------------------------------------------------------------------------------------------------
# seeded: folders of other files, stores with a stranger inside, and our own outputs (issue 20, item 7)
# ------------------------------------------------------------------------------------------------------------------
_STRANGERS = ["thesis.docx", "notes.txt", "fig 1.svg", "data.xlsx", "README", "raw_scan.tif", "session.json",
              "Ærø.csv", ".hidden.pdf", "0.0.0.bak"]


def _stranger_tree(folder: Path, rng) -> None:
    """Random files (some with our suffixes), maybe nested, maybe with a link."""
    folder.mkdir(exist_ok=True)
    for _ in range(int(rng.integers(1, 5))):
        sub = folder
        for _ in range(int(rng.integers(0, 3))):
            sub = sub / str(rng.choice(["figures", "c", "0", "old"]))
        sub.mkdir(parents=True, exist_ok=True)
        (sub / str(rng.choice(_STRANGERS))).write_bytes(rng.bytes(int(rng.integers(1, 300))))
    if rng.random() < 0.2:
        (folder / "link").symlink_to(folder.parent)


@pytest.mark.parametrize("seed", range(40))
def test_seeded_folders_not_ours_are_never_replaced(small, tmp_path, seed):
    rng = np.random.default_rng(seed)
    data, src = small
    name = "out" + str(rng.choice([".zarr", ".tif", ".nrrd", ".nii.gz", ".dcm"]))
    target = tmp_path / name
    if rng.random() < 0.5:
        _stranger_tree(target, rng)  # a folder of someone's files under the output's name
        if rng.random() < 0.5 and not any(target.glob("*.docx")):
            (target / "thesis.docx").write_bytes(b"PK years of work")
    else:  # a store of ours into which someone saved a file (at random depth)
        write_volume(data, target, spacing=(1.0, 2.0, 3.0), format="ome-zarr", chunks=2, max_side=2)
        deep = target / "0" / "c" if rng.random() < 0.5 else target
        (deep / str(rng.choice(["thesis.docx", "notes.txt", "fig 1.svg", ".hidden.pdf", "0.0.0.bak"]))).write_bytes(
            b"years of work")
    before = _tree(target)
    with pytest.raises(OutputError, match=r"cannot replace .* (holds|is a folder)"):
        write_volume(data, target, overwrite=True, format="ome-zarr" if name.endswith(".zarr") else None)
    assert _tree(target) == before
    _no_temps(tmp_path)


@pytest.mark.parametrize("seed", range(10))
def test_seeded_stores_of_ours_are_replaced(small, tmp_path, seed):
    rng = np.random.default_rng(seed)
    data, _ = small
    target = tmp_path / "out.zarr"
    old = rng.integers(0, 9, (int(rng.integers(2, 9)),) * 3).astype(np.uint8)
    write_volume(old, target, chunks=int(rng.integers(1, 4)), max_side=int(rng.integers(1, 4)),
                 labels=bool(rng.random() < 0.5))
    write_volume(data, target, overwrite=True)
    from napari_unwind.io import open_volume

    np.testing.assert_array_equal(open_volume(target).data.compute(), data)
    _no_temps(tmp_path)
