"""The contrast limits the scan reader gives a scan's layer (no viewer, no napari).

Expected values are numpy's percentiles of the whole array, computed here; a huge lazy array must be sampled, not
read: its voxels come from a counting source (the dask chunks a reader builds) that records every read.
"""

import threading

import numpy as np
import pytest

from napari_unwind._napari._reader import contrast_limits

da = pytest.importorskip("dask.array")

P_LOW, P_HIGH = 0.5, 99.5


def _ct(shape=(48, 40, 36), seed=0, dtype=np.int16):
    """A CT-like scan: air (-1000) around a water body (0 +- 30) holding bone (1000..3000)."""
    rng = np.random.default_rng(seed)
    a = rng.normal(-1000, 20, shape)
    z, y, x = np.ogrid[tuple(slice(0, n) for n in shape)]
    body = ((z - shape[0] / 2) / (shape[0] * 0.45)) ** 2 + ((y - shape[1] / 2) / (shape[1] * 0.4)) ** 2 + \
        ((x - shape[2] / 2) / (shape[2] * 0.4)) ** 2 < 1
    a[body] = rng.normal(0, 30, int(body.sum()))
    bone = body & (np.abs(y - shape[1] / 2) < 3) & (np.abs(x - shape[2] / 2) < 3)
    a[bone] = rng.uniform(1000, 3000, int(bone.sum()))
    return np.clip(a, -1000, 3000).astype(dtype)


def _near(got, expected, span):
    np.testing.assert_allclose(got, expected, atol=0.02 * span)


@pytest.mark.parametrize("dtype", [np.int16, np.float32])
def test_small_scan_gets_the_percentiles_of_its_voxels(dtype):
    a = _ct(dtype=dtype)
    expected = np.percentile(a.astype(np.float64), [P_LOW, P_HIGH])
    for data in (a, da.from_array(a, chunks=(10, 40, 36)), [da.from_array(a), da.from_array(a[::2, ::2, ::2])]):
        low, high = contrast_limits(data)
        assert isinstance(low, float) and isinstance(high, float)
        _near((low, high), expected, 4000)
        assert (low, high) != (0.0, 1.0) and low < high


@pytest.mark.parametrize("value, dtype", [(7, np.int16), (-1000, np.int16), (0, np.uint8), (2.5, np.float32),
                                          (1e20, np.float64)])
def test_constant_data_gets_a_range_that_is_not_empty(value, dtype):
    low, high = contrast_limits(np.full((5, 6, 7), value, dtype))
    assert low == pytest.approx(float(np.asarray(value, dtype))) and high > low
    if abs(value) < 2**40:
        assert high == low + 1


def test_nan_and_infinities_are_ignored():
    a = _ct(dtype=np.float32)
    nan = np.random.default_rng(1).random(a.shape) < 0.3
    a[nan] = np.nan
    a[0, 0, :3] = [np.inf, -np.inf, np.inf]
    finite = a[np.isfinite(a)].astype(np.float64)
    _near(contrast_limits(a), np.percentile(finite, [P_LOW, P_HIGH]), 4000)
    _near(contrast_limits(da.from_array(a, chunks=(7, 40, 36))), np.percentile(finite, [P_LOW, P_HIGH]), 4000)
    assert contrast_limits(np.full((4, 4, 4), np.nan, np.float32)) == (0.0, 1.0)
    b = np.full((4, 4, 4), np.nan, np.float32)
    b[1, 2, 3] = 5
    assert contrast_limits(b) == (5.0, 6.0)


def test_a_few_bright_voxels_are_not_lost_when_the_percentiles_meet():
    a = np.zeros((40, 40, 40), np.uint16)
    a[1, 2, 3], a[4, 5, 6] = 900, 1200  # far under 0.5 % of the voxels: both percentiles are 0
    assert np.percentile(a, P_HIGH) == 0
    assert contrast_limits(a) == (0.0, 1200.0)


def _voxels(z, y, x):
    """A hash of the voxel's indices in [-1000, 3000]: uniform noise, the same wherever it is read from."""
    h = (z.astype(np.int64) * 73856093) ^ (y.astype(np.int64) * 19349663) ^ (x.astype(np.int64) * 83492791)
    return (h % 4001 - 1000).astype(np.int16)


class _CountingSource:
    """A huge virtual scan read like a reader's memory-mapped file: counts the voxels and chunks asked for.

    Voxel (i, j, k) holds :func:`_voxels`: evenly spread over [-1000, 3000] in every chunk.
    """

    def __init__(self, shape, chunks):
        self.shape, self.ndim, self.dtype = tuple(shape), len(shape), np.dtype(np.int16)
        self.chunks = tuple(chunks)
        self.voxels = 0
        self.touched: set[tuple[int, ...]] = set()
        self._lock = threading.Lock()

    def __getitem__(self, key):
        key = key if isinstance(key, tuple) else (key,)
        idx = [np.arange(n)[k] for n, k in zip(self.shape, key)]
        out = _voxels(idx[0][:, None, None], idx[1][None, :, None], idx[2][None, None, :])
        with self._lock:
            self.voxels += out.size
            for i0 in set(idx[0] // self.chunks[0]):
                for i1 in set(idx[1] // self.chunks[1]):
                    for i2 in set(idx[2] // self.chunks[2]):
                        self.touched.add((int(i0), int(i1), int(i2)))
        return out


def test_huge_lazy_scan_is_sampled_not_read():
    # 2000 x 1000 x 1000 int16 (4 GB) in slabs of 8 planes, as the NRRD reader chunks a raw file: dask reads a slab
    # whole however little of it is asked for, so the slabs read are bounded
    src = _CountingSource((2000, 1000, 1000), (8, 1000, 1000))
    data = da.from_array(src, chunks=src.chunks, asarray=False, fancy=False)
    low, high = contrast_limits(data, max_voxels=2**20, max_read=2**25, max_chunks=64)
    assert 0 < src.voxels <= 2**25, src.voxels
    assert 0 < len(src.touched) <= 4, len(src.touched)
    # the values spread evenly over [-1000, 3000]: their percentiles are 0.5 % of the way in from either end
    _near((low, high), (-1000 + 0.005 * 4000, 3000 - 0.005 * 4000), 4000)
    # one chunk larger than the budget is still read (the least dask can), and only one
    src = _CountingSource((400, 1000, 1000), (100, 1000, 1000))
    contrast_limits(da.from_array(src, chunks=src.chunks, asarray=False, fancy=False), max_read=2**20)
    assert src.voxels == 100 * 1000 * 1000 and len(src.touched) == 1


def test_huge_lazy_scan_in_small_chunks_reads_few_of_them():
    computed = []

    def chunk(block, block_info=None):
        (z0, _), (y0, _), (x0, _) = block_info[None]["array-location"]
        computed.append(block.size)
        z, y, x = np.ogrid[z0:z0 + block.shape[0], y0:y0 + block.shape[1], x0:x0 + block.shape[2]]
        return _voxels(z, y, x)

    # 2048^3 int16 (16 GB) in 32768 chunks of 64^3, as a compressed store without a pyramid
    data = da.zeros((2048, 2048, 2048), dtype=np.int16, chunks=64).map_blocks(chunk, dtype=np.int16)
    low, high = contrast_limits(data)
    assert 0 < len(computed) <= 64, len(computed)
    assert sum(computed) <= 2**25
    _near((low, high), (-1000 + 0.005 * 4000, 3000 - 0.005 * 4000), 4000)


def test_a_pyramid_is_read_at_its_finest_level_within_the_budget():
    a = _ct(shape=(64, 64, 64))
    src = _CountingSource((4000, 4000, 4000), (16, 4000, 4000))  # level 0: never read
    full = da.from_array(src, chunks=src.chunks, asarray=False, fancy=False)
    levels = [full, da.from_array(a), da.from_array(a[::4, ::4, ::4])]
    _near(contrast_limits(levels), np.percentile(a, [P_LOW, P_HIGH]), 4000)
    assert src.voxels == 0
    # every level too large: the coarsest is sampled
    src2 = _CountingSource((800, 800, 800), (16, 800, 800))
    small = da.from_array(src2, chunks=src2.chunks, asarray=False, fancy=False)
    contrast_limits([full, small], max_voxels=2**16, max_read=2**24)
    assert src.voxels == 0 and 0 < src2.voxels <= 2**24
