"""Small straightenings have no fixed cost proportional to the input (issue 10, item 5).

Checked by what the work touches, not only by the clock: a numpy input is neither hashed nor copied, building the
graph does not grow with the input's chunk count, and the in-place input still gives scipy's values for every
memory layout. One test bounds the fixed cost of a tiny output from a large scan in wall time, with a wide margin.
"""

from __future__ import annotations

import time
import tracemalloc

import dask
import dask.array as da
import numpy as np
import pytest
from scipy import ndimage as ndi

from napari_unwind.deformation import Deformation
from napari_unwind.warp import straighten


def _line_deformation(n: int, length: float, half: float = 4.0) -> Deformation:
    """A gently bent curve of about ``length`` voxels through the middle of an ``n``^3 scan."""
    t = np.linspace(0.0, 1.0, 7)[:, None]
    c = np.full(3, n / 2.0)
    e = np.array([0.8, 0.5, 0.33])
    e /= np.linalg.norm(e)
    bend = np.array([-0.5, 0.8, 0.0]) * 0.1 * length * np.sin(np.pi * t)
    pts = c + (t - 0.5) * length * e + bend
    d = Deformation.from_polyline(pts, spacing=1.0, cage_half_extent=(half, half), unit="micrometer")
    assert not d.folds()
    return d


def _reference(vol: np.ndarray, d: Deformation, order: int) -> np.ndarray:
    """scipy on the whole volume at the grid's scan coordinates (from Deformation.forward, not the code tested)."""
    ns, ny, nx = d.output_shape(1.0)
    k, i, j = np.meshgrid(np.arange(ns), np.arange(ny), np.arange(nx), indexing="ij")
    xys = np.stack([j - (nx - 1) / 2, i - (ny - 1) / 2, d.s_range[0] + k], axis=-1).reshape(-1, 3).astype(float)
    coords = d.to_voxels(d.forward(xys)).T.reshape(3, ns, ny, nx)
    return ndi.map_coordinates(np.ascontiguousarray(vol), coords, order=order, mode="constant", cval=0.0)


def test_a_numpy_input_is_neither_hashed_nor_copied(monkeypatch):
    vol = np.random.default_rng(0).random((200, 200, 200), dtype=np.float32)  # 32 MB
    d = _line_deformation(200, 40.0)
    straighten(vol[:120, :120, :120].copy(), d).data.compute()  # load the kernels (numba allocates doing so)
    hashed: list[int] = []
    real = dask.tokenize.hash_buffer_hex

    def recording(buf, *args, **kwargs):
        hashed.append(memoryview(buf).nbytes)
        return real(buf, *args, **kwargs)

    monkeypatch.setattr(dask.tokenize, "hash_buffer_hex", recording)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        out = straighten(vol, d)
        with dask.config.set(scheduler="synchronous"):
            got = out.data.compute()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert max(hashed, default=0) < vol.nbytes // 100, f"hashed {max(hashed):,} bytes of a {vol.nbytes:,}-byte input"
    # the output and the kernels' row buffers, but no copy of the 32 MB input (nor of a chunk of it)
    assert peak < 4 * got.nbytes + 2**20, f"peak {peak:,} bytes for an output of {got.nbytes:,}"
    np.testing.assert_allclose(got, _reference(vol, d, 1), rtol=1e-6, atol=1e-6)


def test_building_the_graph_does_not_grow_with_the_input_chunk_count():
    n = 256
    d = _line_deformation(n, 120.0, half=10.0)
    straighten(da.zeros((n, n, n), dtype=np.float32, chunks=128), d, chunks=(8, 7, 7))  # load the kernels

    def build_memory(chunk):
        data = da.zeros((n, n, n), dtype=np.float32, chunks=chunk)  # a new array: nothing cached from before
        tracemalloc.start()
        try:
            out = straighten(data, d, chunks=(8, 7, 7))  # 16 x 3 x 3 output blocks
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        return out, peak

    (fine, m_fine), (_, m_coarse) = build_memory(4), build_memory(128)  # 262144 and 8 input chunks
    # each block depends on the few input chunks around it: nothing may list all the input's keys
    assert m_fine < 2 * m_coarse + 2**20, (m_fine, m_coarse)
    inputs = fine.data.dask.dependencies[fine.data.name]
    (input_name,) = inputs
    deps = [str(task).count(repr(input_name)) for task in fine.data.dask.layers[fine.data.name].values()]
    assert 0 < max(deps) <= 6**3, max(deps)


@pytest.mark.parametrize("layout", ["C", "F", "reversed", "strided", "memmap"])
@pytest.mark.parametrize("order", [0, 1, 3])
def test_any_memory_layout_of_a_numpy_input_gives_scipys_values(layout, order, tmp_path):
    base = np.random.default_rng(1).integers(0, 60000, size=(70, 66, 68), dtype=np.uint16)
    if layout == "C":
        vol = base
    elif layout == "F":
        vol = np.asfortranarray(base)
    elif layout == "reversed":
        vol = base[::-1, :, ::-1]
    elif layout == "strided":
        vol = np.random.default_rng(2).integers(0, 60000, size=(140, 66, 136), dtype=np.uint16)[::2, :, ::2]
    else:
        vol = np.lib.format.open_memmap(tmp_path / "v.npy", mode="w+", dtype=np.uint16, shape=base.shape)
        vol[...] = base
        vol.flush()
    d = _line_deformation(66, 40.0, half=6.0)
    got = straighten(vol, d, order=order, chunks=(16, 7, 13)).data.compute()
    ref = _reference(vol, d, order)
    if order == 3:
        np.testing.assert_allclose(got.astype(float), ref.astype(float), atol=1e-3 * 60000)
    else:
        assert np.abs(got.astype(int) - ref.astype(int)).max() <= (0 if order == 0 else 1)


def test_a_tiny_output_from_a_large_numpy_scan_has_no_large_fixed_cost():
    vol = np.zeros((320, 320, 320), dtype=np.uint16)  # 65 MB: hashing or copying it costs tens of ms
    vol[150:170, 150:170, 150:170] = 1000
    d = _line_deformation(320, 8.0, half=4.0)
    straighten(vol, d).data.compute()  # compile / load the kernels
    best = np.inf
    for _ in range(7):
        t0 = time.perf_counter()
        straighten(vol, d).data.compute()
        best = min(best, time.perf_counter() - t0)
    assert best < 0.04, f"a {d.output_shape(1.0)} output took {1e3 * best:.1f} ms"
