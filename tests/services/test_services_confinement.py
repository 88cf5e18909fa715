"""Confinement through file contents (issue 22 item 1): a scan registered inside the data root may not make the
server read outside it, nor its own folder, through a header's file name or a symbolic link at any depth. Each
attempt is PERMISSION_DENIED with a message that names no outside path; the same scans without the trick register
and read back (the check refuses only what it should). Reference: the bytes of the files themselves."""

from __future__ import annotations

import os
import re
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
