"""import_slabs_iter: an OME-Zarr import fed by blocks of planes as they arrive (uploads) writes the same store."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from napari_unwind.errors import InvalidInputError
from napari_unwind.io import as_volume, import_slabs_iter, import_volume, open_volume
from napari_unwind.progress import run


def _blocks(a: np.ndarray, sizes: list[int]):
    z = 0
    i = 0
    while z < a.shape[0]:
        k = sizes[i % len(sizes)]
        yield a[z:z + k]
        z += k
        i += 1


def _files(store: Path) -> dict[str, bytes]:
    return {str(p.relative_to(store)): p.read_bytes() for p in sorted(store.rglob("*")) if p.is_file()}


def _phantom(shape, dtype, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if np.dtype(dtype).kind == "f":
        return rng.normal(100, 30, shape).astype(dtype)
    hi = min(np.iinfo(dtype).max, 60000)
    return rng.integers(0, hi, shape).astype(dtype)


@pytest.mark.parametrize("shape, dtype, labels, sizes", [
    ((37, 21, 19), np.uint16, False, [8]),        # exact slabs; not a multiple of the chunk on any axis
    ((37, 21, 19), np.uint8, False, [3, 11, 1]),  # blocks cut and joined into slabs
    ((29, 17, 23), np.float32, False, [40]),      # one block larger than the volume's slab
    ((33, 18, 20), np.uint16, True, [5, 8]),      # labels: nearest-neighbour pyramid
])
def test_streamed_import_writes_the_store_import_volume_writes(tmp_path, shape, dtype, labels, sizes):
    a = _phantom(shape, dtype)
    if labels:
        a = (a % 7).astype(dtype)
    opts = dict(chunks=8, max_side=8, labels=labels)
    ref = import_volume(as_volume(a, spacing=(3, 2, 1), unit="mm", origin=(1, 2, 3)), tmp_path / "ref.zarr", **opts)
    got = run(import_slabs_iter(_blocks(a, sizes), tmp_path / "got.zarr", shape=shape, dtype=dtype,
                                spacing=(3, 2, 1), unit="mm", origin=(1, 2, 3), **opts))
    assert Path(got) == (tmp_path / "got.zarr").absolute()
    # the same files, byte for byte: every level's chunks, codecs and metadata
    assert len(ref.levels) >= 3
    ref_files, got_files = _files(tmp_path / "ref.zarr"), _files(tmp_path / "got.zarr")
    assert ref_files.keys() == got_files.keys()
    for name in ref_files:
        if name == "zarr.json":  # the root's attributes name the store (its folder)
            r, g = json.loads(ref_files[name]), json.loads(got_files[name])
            r["attributes"]["ome"]["multiscales"][0].pop("name")
            g["attributes"]["ome"]["multiscales"][0].pop("name")
            assert r == g
            assert g["attributes"]["unwind"]["all_chunks_written"] is True
        else:
            assert ref_files[name] == got_files[name], name
    v = open_volume(got)
    np.testing.assert_array_equal(v.data.compute(), a)  # against the array itself, too
    assert v.spacing == (3, 2, 1) and v.origin == (1, 2, 3) and v.unit == "millimeter"


def _nothing_left(tmp_path: Path) -> None:
    assert not [p.name for p in tmp_path.iterdir()], "a partial output was left behind"


@pytest.mark.parametrize("sizes, total, words", [
    ([8], 30, "must have shape"),      # too few planes: the last slab is short
    ([8], 24, "got nothing"),          # too few planes: a whole slab missing
    ([8], 40, "more planes"),           # too many planes
    ([5], 36, "more planes"),      # too many planes, in blocks that do not match the slabs
])
def test_a_stream_with_other_than_its_planes_is_refused_and_leaves_nothing(tmp_path, sizes, total, words):
    a = _phantom((total, 9, 10), np.uint16)
    with pytest.raises(InvalidInputError, match=words):
        run(import_slabs_iter(_blocks(a, sizes), tmp_path / "x.zarr", shape=(32, 9, 10), dtype=np.uint16, chunks=8))
    _nothing_left(tmp_path)


def test_blocks_of_another_plane_shape_or_dtype_are_refused(tmp_path):
    a = _phantom((16, 9, 10), np.uint16)
    with pytest.raises(InvalidInputError, match=r"shape \(k, 9, 11\)"):
        run(import_slabs_iter([a], tmp_path / "x.zarr", shape=(16, 9, 11), dtype=np.uint16, chunks=8))
    with pytest.raises(InvalidInputError, match="dtype uint8"):
        run(import_slabs_iter([a], tmp_path / "x.zarr", shape=(16, 9, 10), dtype=np.uint8, chunks=8))
    _nothing_left(tmp_path)


def test_nan_in_a_streamed_float_volume_is_refused_with_its_voxel_or_replaced(tmp_path):
    a = _phantom((20, 6, 7), np.float32)
    a[13, 2, 5] = np.nan
    with pytest.raises(InvalidInputError, match=r"NaN at voxel \(13, 2, 5\)"):
        run(import_slabs_iter(_blocks(a, [4]), tmp_path / "x.zarr", shape=a.shape, dtype=a.dtype, chunks=8))
    _nothing_left(tmp_path)
    run(import_slabs_iter(_blocks(a, [4]), tmp_path / "y.zarr", shape=a.shape, dtype=a.dtype, chunks=8,
                          nan_value=-1))
    want = np.where(np.isnan(a), np.float32(-1), a)
    np.testing.assert_array_equal(open_volume(tmp_path / "y.zarr").data.compute(), want)


def test_read_ahead_gives_every_read_in_order_the_next_one_already_under_way():
    import threading

    from napari_unwind.io._lazy import read_ahead

    started = []
    cond = threading.Condition()

    def read(z0):
        with cond:
            started.append(z0)
            cond.notify_all()
        return z0 * 10

    out = []
    for value in read_ahead(read, range(0, 50, 10)):
        z0 = value // 10
        if z0 + 10 < 50:  # while the caller holds this block, the next read starts without it asking
            with cond:
                assert cond.wait_for(lambda nxt=z0 + 10: nxt in started, timeout=5)
        out.append(value)
    assert out == [0, 100, 200, 300, 400] and started == [0, 10, 20, 30, 40]
    assert list(read_ahead(read, range(0))) == []
