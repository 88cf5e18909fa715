"""The pyramid's 2x2x2 box mean (the compiled kernel of ``_downsample2``) against a plain reference written here:
edge-padded blocks of 2x2x2, summed in the order o0, o1, o2 in the accumulator numpy's sums use, integers rounded
half up; the same bytes for every voxel type and odd sides."""

from __future__ import annotations

import numpy as np
import pytest

from napari_unwind.io.ome_zarr import _downsample2


def _reference(block: np.ndarray) -> np.ndarray:
    pad = np.pad(block, [(0, s % 2) for s in block.shape], mode="edge")
    integer = np.issubdtype(block.dtype, np.integer)
    acc_t = (np.int32 if block.dtype.itemsize < 4 else np.int64) if integer else \
        (np.float64 if block.dtype == np.float64 else np.float32)
    m = [s // 2 for s in pad.shape]
    acc = np.zeros(m, acc_t)
    for o0 in (0, 1):
        for o1 in (0, 1):
            for o2 in (0, 1):
                acc = (acc + pad[o0::2, o1::2, o2::2].astype(acc_t)).astype(acc_t)
    if integer:
        return ((acc + 4) // 8).astype(block.dtype)
    return (acc / acc_t(8)).astype(block.dtype)


@pytest.mark.parametrize("dtype", ["u1", "i1", "u2", "i2", "u4", "i4", "f4", "f8"])
@pytest.mark.parametrize("shape", [(6, 8, 10), (5, 7, 9), (2, 3, 2), (129, 33, 17)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_box_mean_is_the_reference_byte_for_byte(dtype, shape, seed):
    rng = np.random.default_rng(seed)
    if dtype[0] == "f":
        a = rng.normal(0, 1e3, shape).astype(dtype)
        a.flat[::7] = -0.0
    else:
        info = np.iinfo(dtype)
        a = rng.integers(info.min, info.max, shape, endpoint=True).astype(dtype)
    got, want = _downsample2(a, labels=False), _reference(a)
    assert got.shape == want.shape and got.dtype == want.dtype
    assert got.tobytes() == want.tobytes()


def test_non_contiguous_and_thin_blocks_take_the_same_values():
    a = np.random.default_rng(3).integers(0, 60000, (9, 40, 30), dtype=np.uint16)
    view = a[:, ::2, 1:]  # strided
    assert _downsample2(view, labels=False).tobytes() == _reference(view).tobytes()
    thin = a[:1]  # an axis of length 1 stays (numpy's path)
    assert _downsample2(thin, labels=False).shape == (1, 20, 15)
