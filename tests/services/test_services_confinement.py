"""Confinement through file contents (issue 22 item 1): a scan registered inside the data root may not make the
server read outside it, nor its own folder, through a header's file name or a symbolic link at any depth. Each
attempt is PERMISSION_DENIED with a message that names no outside path; the same scans without the trick register
and read back (the check refuses only what it should). Reference: the bytes of the files themselves."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from napari_unwind.client import Client, RemoteError
from napari_unwind.io import open_volume, write_volume

SHAPE = (4, 4, 4)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from unwind_services.server import ServerConfig, UnwindServer

    tmp = tmp_path_factory.mktemp("confine")
    data, outside = tmp / "data", tmp / "outside"
    (data / "scans").mkdir(parents=True)
    outside.mkdir()
    (outside / "secret.raw").write_bytes(b"S" * int(np.prod(SHAPE)))  # as many bytes as the headers promise
    srv = UnwindServer(ServerConfig(data_root=data, port=0, scheduler="threads"))
    srv.start()
    yield srv, data, outside
    srv.stop(0)


def _header(path: Path, key: str, value: str) -> None:
    """Point the header's data-file line at ``value``."""
    text = path.read_text()
    text, n = re.subn(rf"(?im)^({key}\s*[:=]\s*).*$", lambda m: m.group(1) + value, text)
    assert n == 1, text
    path.write_text(text)


def _scan(folder: Path, name: str) -> Path:
    return write_volume(np.arange(np.prod(SHAPE), dtype=np.uint8).reshape(SHAPE), folder / name,
                        spacing=(1, 1, 1))


def _refused(srv, rel: str) -> str:
    with Client(srv.address, progress=False) as c, pytest.raises(RemoteError) as err:
        c.register(rel)
    assert err.value.code == "PERMISSION_DENIED", (err.value.code, str(err.value))
    message = str(err.value)
    assert "secret" not in message and "outside/" not in message and "sqlite" not in message, message
    return message


def _fine(srv, rel: str, expected: np.ndarray) -> None:
    with Client(srv.address, progress=False) as c:
        info = c.register(rel)
        np.testing.assert_array_equal(np.asarray(c.open(info.volume_id).data), expected)


@pytest.mark.parametrize("target", ["absolute", "relative", "own database"])
def test_an_nrrd_header_naming_a_file_elsewhere_is_refused(server, tmp_path, target):
    srv, data, outside = server
    folder = data / "scans" / f"nhdr-{target.replace(' ', '-')}"
    folder.mkdir()
    header = _scan(folder, "fish.nhdr")
    _fine(srv, os.path.relpath(header, data), np.asarray(open_volume(header).data))
    value = {"absolute": str(outside / "secret.raw"), "relative": os.path.relpath(outside / "secret.raw", folder),
             "own database": os.path.relpath(data / ".unwind" / "unwind.sqlite", folder)}[target]
    _header(header, "data file", value)
    _refused(srv, os.path.relpath(header, data))


@pytest.mark.parametrize("target", ["relative", "own database"])
def test_a_dat_header_naming_a_file_elsewhere_is_refused(server, target):
    srv, data, outside = server
    folder = data / "scans" / f"dat-{target.replace(' ', '-')}"
    folder.mkdir()
    raw = _scan(folder, "fish.raw")
    dat = raw.with_suffix(".dat") if raw.suffix != ".dat" else raw
    _fine(srv, os.path.relpath(dat, data), np.asarray(open_volume(dat).data))
    value = {"relative": os.path.relpath(outside / "secret.raw", folder),
             "own database": os.path.relpath(data / ".unwind" / "unwind.sqlite", folder)}[target]
    _header(dat, "RawFile", value)  # the key our writer uses; ObjectFileName is its alias
    _refused(srv, os.path.relpath(dat, data))


@pytest.mark.parametrize("where", ["chunk", "folder at depth"])
def test_a_store_with_a_link_out_is_refused_and_one_inside_is_not(server, where):
    srv, data, outside = server
    store = _scan(data / "scans", f"store-{where.replace(' ', '-')}.ome.zarr")
    expected = np.asarray(open_volume(store).data)
    chunks = sorted(p for p in store.rglob("*") if p.is_file() and not p.name.endswith(".json"))
    assert chunks, sorted(store.rglob("*"))
    victim = chunks[0]
    # a link that stays inside the root (the same bytes elsewhere in it) is fine
    twin = data / "scans" / f"twin-{where.replace(' ', '-')}"
    twin.write_bytes(victim.read_bytes())
    victim.unlink()
    os.symlink(twin, victim)
    _fine(srv, os.path.relpath(store, data), expected)
    victim.unlink()
    if where == "chunk":
        os.symlink(outside / "secret.raw", victim)
    else:  # the chunk's folder replaced by a link to a folder outside that holds the same file names
        folder = victim.parent
        copy = outside / f"copy-{folder.name}"
        copy.mkdir()
        (copy / victim.name).write_bytes(twin.read_bytes())
        for other in folder.iterdir():
            (copy / other.name).write_bytes(other.read_bytes()) if other.is_file() else None
        for other in list(folder.iterdir()):
            other.unlink()
        folder.rmdir()
        os.symlink(copy, folder)
    _refused(srv, os.path.relpath(store, data))


def test_a_registered_store_changed_afterwards_is_refused_at_each_open(server):
    srv, data, outside = server
    store = _scan(data / "scans", "later.ome.zarr")
    with Client(srv.address, progress=False) as c:
        vid = c.register(os.path.relpath(store, data)).volume_id
        c.info(vid)
        chunk = sorted(p for p in store.rglob("*") if p.is_file() and not p.name.endswith(".json"))[0]
        chunk.unlink()
        os.symlink(outside / "secret.raw", chunk)
        for call in (lambda: c.info(vid), lambda: c.open(vid)):
            with pytest.raises(RemoteError) as err:
                call()
            assert err.value.code == "PERMISSION_DENIED" and "secret" not in str(err.value)


# ------------------------------------------------------------------------------------------------------------------
# zarr v2 stores (.zarray / .zgroup / .zattrs; chunks "0.0.0" or nested "0/0/0"), and links swapped in after an open
# ------------------------------------------------------------------------------------------------------------------
V2_CHUNKS = (2, 2, 2)


def _v2_store(folder: Path, name: str, *, nested: bool, group: bool) -> tuple[Path, np.ndarray]:
    """A zarr v2 store of 8 chunks, written by zarr itself: a plain array, or an NGFF 0.4 group holding level "0"."""
    import zarr

    values = np.arange(np.prod(SHAPE), dtype=np.uint8).reshape(SHAPE)
    store = folder / name
    where = store / "0" if group else store
    arr = zarr.open_array(str(where), mode="w", zarr_format=2, shape=SHAPE, chunks=V2_CHUNKS, dtype="u1",
                          compressor=None, fill_value=0, dimension_separator="/" if nested else ".")
    arr[:] = values
    if group:
        (store / ".zgroup").write_text('{"zarr_format": 2}')
        axes = [{"name": a, "type": "space", "unit": "micrometer"} for a in "zyx"]
        (store / ".zattrs").write_text(json.dumps({"multiscales": [{
            "version": "0.4", "axes": axes,
            "datasets": [{"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [1.0, 1.0, 1.0]}]}]}]}))
    return store, values


def _v2_files(store: Path) -> list[Path]:
    return sorted(p for p in store.rglob("*") if p.is_file() and not p.name.startswith("."))


def _link_out(path: Path, outside: Path, tag: str) -> None:
    """Replace ``path`` (a file or a folder) by a symbolic link to a copy of it outside the data root."""
    copy = outside / f"{tag}-{path.name}"
    if path.is_dir():
        shutil.copytree(path, copy)
        shutil.rmtree(path)
    else:
        shutil.copyfile(path, copy)
        path.unlink()
    os.symlink(copy, path)


V2_CASES = [  # (name, nested chunk keys, NGFF group, what is replaced by a link out)
    ("flat-chunk", False, False, "chunk"),
    ("flat-zarray", False, False, ".zarray"),
    ("nested-chunk", True, False, "chunk"),
    ("nested-folder", True, False, "folder at depth 2"),
    ("group-zarray", False, True, ".zarray"),
    ("group-level", True, True, "level folder"),
    ("group-folder", True, True, "folder at depth 3"),
]


@pytest.mark.parametrize("name,nested,group,what", V2_CASES, ids=[c[0] for c in V2_CASES])
def test_a_zarr_v2_store_with_a_link_out_is_refused(server, name, nested, group, what):
    srv, data, outside = server
    store, values = _v2_store(data / "scans", f"v2-{name}.zarr", nested=nested, group=group)
    assert not (store / "zarr.json").exists() and open_volume(store).format == "ome-zarr"
    _fine(srv, os.path.relpath(store, data), values)  # the store itself reads back
    array = store / "0" if group else store
    chunk = _v2_files(array)[0]
    victim = {"chunk": chunk, ".zarray": array / ".zarray", "level folder": array,
              "folder at depth 2": array / "0" / "0", "folder at depth 3": array / "0" / "0"}[what]
    if what.startswith("folder"):
        assert victim.is_dir() and chunk.is_relative_to(victim), (victim, chunk)
    _link_out(victim, outside, name)
    _refused(srv, os.path.relpath(store, data))


def _catalog_volume(srv, data: Path, store: Path):
    """Register ``store`` through the server, then open it as the server's servicers and jobs do."""
    from unwind_services.auth import LOCAL_USER

    with Client(srv.address, progress=False) as c:
        vid = c.register(os.path.relpath(store, data)).volume_id
    return srv.catalog.volume(LOCAL_USER, vid)[1]


@pytest.mark.parametrize("what,nested", [("chunk", False), ("chunk", True), ("folder", True)],
                         ids=["chunk-flat", "chunk-nested", "folder-nested"])
def test_a_link_swapped_in_after_the_open_is_not_followed_at_chunk_read(server, nested, what):
    """The window the checks at Register and at each open leave: a volume opened (checked) whose chunk, or a
    folder of chunks, becomes a link out before the chunk is read. The read refuses; the bytes never come back."""
    srv, data, outside = server
    store, values = _v2_store(data / "scans", f"swap-{what}-{'nested' if nested else 'flat'}.zarr", nested=nested,
                              group=False)
    volume = _catalog_volume(srv, data, store)
    chunk = _v2_files(store)[-1]  # chunk (1, 1, 1): the last 2x2x2 corner
    victim = chunk if what == "chunk" else chunk.parent
    copy = outside / f"swap-{what}-{nested}"
    if victim.is_dir():
        shutil.copytree(victim, copy)
        for f in copy.iterdir():
            f.write_bytes(b"S" * f.stat().st_size)  # the outside copy holds other bytes
        shutil.rmtree(victim)
    else:
        copy.write_bytes(b"S" * chunk.stat().st_size)
        victim.unlink()
    os.symlink(copy, victim)
    with pytest.raises(PermissionError) as err:
        np.asarray(volume.data[2:, 2:, 2:])
    assert "secret" not in str(err.value) and str(outside) not in str(err.value), str(err.value)
    # the chunks that are still inside read as before
    np.testing.assert_array_equal(np.asarray(volume.data[:2, :2, :2]), values[:2, :2, :2])


def test_a_link_swapped_into_a_v3_store_after_the_open_is_not_followed(server):
    """The same for the stores the server writes (zarr v3, whole chunks read directly, without zarr)."""
    srv, data, outside = server
    store = _scan(data / "scans", "swap-v3.ome.zarr")
    volume = _catalog_volume(srv, data, store)
    chunk = sorted(p for p in store.rglob("*") if p.is_file() and not p.name.endswith(".json"))[0]
    (outside / "swap-v3").write_bytes(chunk.read_bytes())  # the same bytes: only where they lie is wrong
    chunk.unlink()
    os.symlink(outside / "swap-v3", chunk)
    with pytest.raises(PermissionError):
        np.asarray(volume.data)


def test_a_raw_data_file_swapped_after_the_open_is_not_followed(server):
    """The same for a header's raw data file (a ``.dat``'s raw), memory-mapped anew at each read."""
    srv, data, outside = server
    folder = data / "scans" / "swap-dat"
    folder.mkdir()
    raw = _scan(folder, "fish.raw")
    volume = _catalog_volume(srv, data, raw.with_suffix(".dat"))
    np.testing.assert_array_equal(np.asarray(volume.data), np.asarray(open_volume(raw).data))
    raw.unlink()
    os.symlink(outside / "secret.raw", raw)  # as many bytes as the header promises
    with pytest.raises(PermissionError) as err:
        np.asarray(volume.data)
    assert "secret" not in str(err.value) and str(outside) not in str(err.value), str(err.value)


# ------------------------------------------------------------------------------------------------------------------
# the readers that open their files again at each read: compressed TIFF pages, slice files, DICOM slices, NIfTI
# (a file swapped for a symbolic link out after the open is refused at the read; the files left alone still read)
# ------------------------------------------------------------------------------------------------------------------
VALUES = (np.arange(np.prod(SHAPE), dtype=np.uint16).reshape(SHAPE) * 7 + 3)
OTHER = (VALUES + 1000).astype(np.uint16)  # what the outside copies hold: a leak would show as these values


def _swap_out(victim: Path, impostor: Path, outside: Path, tag: str) -> Path:
    """Replace ``victim`` by a symbolic link to ``impostor`` (a file of the same kind with other voxels) moved
    outside the data root; returns where the link points."""
    target = outside / f"{tag}-{impostor.name}"
    shutil.move(impostor, target)
    victim.unlink()
    os.symlink(target, victim)
    return target


def _read_refused(array, outside: Path) -> None:
    with pytest.raises(PermissionError) as err:
        np.asarray(array)
    message = str(err.value)
    assert str(outside) not in message and "impostor" not in message and "/" not in message, message


@pytest.mark.parametrize("name,options", [("zlib.tif", {"compression": "zlib"}), ("scan.nii.gz", {}),
                                          ("scan.nii", {}), ("raw.nhdr", {"encoding": "raw"})],
                         ids=["tiff-zlib", "nifti-gz", "nifti", "nhdr-raw-data"])
def test_a_single_file_scan_swapped_after_the_open_is_not_followed(server, name, options):
    """A compressed TIFF (decoded page by page), a NIfTI (gzip or not) and a detached NRRD's raw data file, each
    opened at each read: the read after a swap refuses; a link that stays inside the data root still reads."""
    srv, data, outside = server
    folder = data / "scans" / f"swap-{name.replace('.', '-')}"
    folder.mkdir()
    scan = write_volume(VALUES, folder / name, spacing=(1, 1, 1), **options)
    volume = _catalog_volume(srv, data, scan)
    if name.endswith(".tif"):
        assert volume.format == "tiff" and not volume.metadata["memmap"], volume.metadata  # the pages reader
    np.testing.assert_array_equal(np.asarray(volume.data), VALUES)
    victim = folder / "raw.raw" if name.endswith(".nhdr") else scan
    assert victim.is_file(), sorted(folder.iterdir())
    impostor = write_volume(OTHER, outside / f"impostor-{name}", spacing=(1, 1, 1), **options)
    if name.endswith(".nhdr"):
        impostor = outside / "impostor-raw.raw"
    twin = folder.parent / f"twin-{name}"
    shutil.copyfile(victim, twin)
    _swap_out(victim, impostor, outside, "swap")
    _read_refused(volume.data, outside)
    victim.unlink()
    os.symlink(twin, victim)  # the same bytes elsewhere inside the data root: read as before
    np.testing.assert_array_equal(np.asarray(volume.data), VALUES)


@pytest.mark.parametrize("kind", ["png stack", "tif stack", "dicom"])
def test_one_slice_swapped_after_the_open_is_not_followed(server, kind):
    """Numbered 2D slices and a DICOM series read each slice file when its plane is computed: the swapped slice
    refuses, the others read as before."""
    srv, data, outside = server
    tag = kind.replace(" ", "-")
    values, other = (VALUES, OTHER) if kind == "dicom" else (VALUES.astype(np.uint8), OTHER.astype(np.uint8) + 1)
    fmt, options = {"png stack": ("stack", {}), "tif stack": ("stack", {"pattern": "z_{:03d}.tif"}),
                    "dicom": ("dicom", {"unit": "millimeter"})}[kind]
    scan = write_volume(values, data / "scans" / f"swap-{tag}", spacing=(1, 1, 1), format=fmt, **options)
    volume = _catalog_volume(srv, data, scan)
    assert volume.format == fmt and volume.data.chunks[0] == (1,) * SHAPE[0], (volume.format, volume.data.chunks)
    np.testing.assert_array_equal(np.asarray(volume.data), values)
    impostors = write_volume(other, outside / f"impostor-{tag}", spacing=(1, 1, 1), format=fmt, **options)
    slices, theirs = sorted(p for p in scan.iterdir()), sorted(p for p in impostors.iterdir())
    assert len(slices) == len(theirs) == SHAPE[0], (slices, theirs)
    _swap_out(slices[2], theirs[2], outside, tag)
    _read_refused(volume.data, outside)
    _read_refused(volume.data[2], outside)
    for z in (0, 1, 3):
        np.testing.assert_array_equal(np.asarray(volume.data[z]), values[z])


def test_a_multi_file_ome_tiff_naming_a_file_outside_is_refused(server):
    """An OME-TIFF whose metadata spreads its planes over files (``TiffData``/``UUID FileName``): tifffile opens
    the files it names, so one named outside the data root is refused at Register; the same files side by side
    in the root register and read back."""
    import uuid

    import tifffile

    srv, data, outside = server
    planes = SHAPE[0] // 2

    def xml(own: str, first: str, second: str, ids: tuple[str, str]) -> str:
        entries = "".join(f'<TiffData FirstZ="{k * planes}" IFD="0" PlaneCount="{planes}"><UUID FileName="{name}">'
                          f"{i}</UUID></TiffData>" for k, (name, i) in enumerate(zip((first, second), ids)))
        return ('<?xml version="1.0" encoding="UTF-8"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/'
                f'2016-06" UUID="{own}"><Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYZCT" '
                f'Type="uint16" SizeX="{SHAPE[2]}" SizeY="{SHAPE[1]}" SizeZ="{SHAPE[0]}" SizeC="1" SizeT="1">'
                f'<Channel ID="Channel:0:0" SamplesPerPixel="1"/>{entries}</Pixels></Image></OME>')

    for case, second_dir in (("inside", data / "scans"), ("outside", outside)):
        ids = (f"urn:uuid:{uuid.uuid4()}", f"urn:uuid:{uuid.uuid4()}")
        first = data / "scans" / f"ome-{case}-a.ome.tif"
        second = second_dir / f"ome-{case}-b.ome.tif"
        named = os.path.relpath(second, first.parent)
        for path, part, own in ((first, VALUES[:planes], ids[0]), (second, VALUES[planes:], ids[1])):
            tifffile.imwrite(path, part, description=xml(own, first.name, named, ids), metadata=None,
                             photometric="minisblack")
        assert open_volume(first).shape == SHAPE  # tifffile follows the file name wherever it leads
        if case == "inside":
            _fine(srv, os.path.relpath(first, data), VALUES)
        else:
            message = _refused(srv, os.path.relpath(first, data))
            assert "OME-TIFF" in message, message
