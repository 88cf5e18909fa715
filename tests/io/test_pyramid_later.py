"""A store of level 0 alone written chunk by chunk (Level0Writer, an upload's), completed later (complete_pyramid):
usable with one level meanwhile, then byte for byte what import_volume writes."""

from __future__ import annotations

import dask.array as da
import numpy as np
import pytest

from napari_unwind.io import as_volume, import_volume, open_volume
from napari_unwind.io.ome_zarr import ChunkCodec, Level0Writer, complete_pyramid, pyramid_pending
from napari_unwind.progress import run


def _files(store):
    return {str(p.relative_to(store)): p.read_bytes() for p in sorted(store.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("dtype, shape, labels", [
    ("u2", (300, 261, 140), False),  # partial chunks on every axis, three levels
    ("f4", (130, 300, 290), False),
    ("u1", (257, 129, 300), True),   # labels: the pyramid by nearest
])
def test_level_0_first_then_the_pyramid_is_import_volumes_store(tmp_path, dtype, shape, labels):
    a = (np.random.default_rng(1).random(shape) * 200).astype(dtype)
    geometry = dict(spacing=(3, 2, 1), unit="um", origin=(1.5, -2, 0))
    (tmp_path / "ref").mkdir()
    import_volume(as_volume(a, **geometry), tmp_path / "ref" / "s.zarr", labels=labels)
    got = tmp_path / "got" / "s.zarr"
    writer = Level0Writer(as_volume(da.empty(shape, dtype=dtype, chunks=shape), **geometry), got, labels=labels)
    codec = ChunkCodec(shape, dtype)
    for c in codec.coords():
        writer.put(c, *codec.encode(codec.chunk(a[codec.bounds(c)])))
    writer.finish()

    vol = open_volume(got)  # usable at once: level 0 alone, marked pending
    assert len(vol.levels) == 1 and pyramid_pending(got)
    np.testing.assert_array_equal(np.asarray(vol.data), a)

    (got / "1" / "c" / "9" / "9").mkdir(parents=True)  # what a stopped earlier attempt left
    (got / "1" / "zarr.json").write_text("{}")
    (got / "1" / "c" / "9" / "9" / "9").write_bytes(b"stale")
    run(complete_pyramid(got))
    assert not pyramid_pending(got)
    assert _files(got) == _files(tmp_path / "ref" / "s.zarr")
    before = _files(got)
    run(complete_pyramid(got))  # a complete store is left as it is
    assert _files(got) == before
