"""Lazy, streamed access shared by the format modules: raw voxels in a file, slabs of planes."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InvalidInputError
from ._files import ConfinementError, current_confinement, open_regular
from ._volume import LazyArray, Volume

if TYPE_CHECKING:
    import dask.array as da

__all__ = ["SLAB_BYTES", "RawFileArray", "iter_slabs", "read_ahead", "slab_depth", "write_slab_depth"]

SLAB_BYTES = 64 * 2**20



def slab_depth(plane_shape: tuple[int, ...], dtype: Any, target_bytes: int = SLAB_BYTES) -> int:
    """Number of planes of ``plane_shape`` and ``dtype`` that fit in about ``target_bytes`` (at least 1)."""
    plane = int(np.prod(plane_shape)) * np.dtype(dtype).itemsize
    return max(1, int(target_bytes) // max(1, plane))


class RawFileArray:
    """A read-only, picklable array-like over C-ordered voxels stored at ``offset`` in a file.

    Indexing memory-maps the file, copies the requested region out and closes the map again, so a dask array
    built on it (``da.from_array(RawFileArray(...), chunks=...)``) reads only the chunks it computes and holds
    no open file between computations. Values come back in native byte order.

    Parameters
    ----------
    path : path-like
        The file holding the voxels.
    dtype : numpy dtype
        The stored type, including its byte order (``">u2"`` for big-endian 16-bit).
    shape : tuple of int
        The array shape, C order (last axis fastest).
    offset : int
        Byte position of the first voxel.
    """

    def __init__(self, path: str | os.PathLike, dtype: Any, shape: tuple[int, ...], offset: int = 0):
        self.path = str(path)
        self.stored_dtype = np.dtype(dtype)
        self.dtype = self.stored_dtype.newbyteorder("=")
        self.shape = tuple(int(s) for s in shape)
        self.ndim = len(self.shape)
        self.offset = int(offset)
        self.confine = current_confinement()  # opened confined: every read is (see _files.confined_reads)

    def _map(self) -> np.memmap:
        if self.confine is None:
            return np.memmap(self.path, dtype=self.stored_dtype, mode="r", offset=self.offset, shape=self.shape)
        with open_regular(self.path, "data", confine=self.confine) as fh:  # checked where the opened file lies
            return np.memmap(fh, dtype=self.stored_dtype, mode="r", offset=self.offset, shape=self.shape)

    def __getitem__(self, key: Any) -> np.ndarray:
        try:
            mm = self._map()
        except ConfinementError:
            raise
        except (OSError, ValueError) as exc:  # gone, or cut short since it was opened
            need = self.offset + int(np.prod(self.shape)) * self.stored_dtype.itemsize
            try:
                have = f"{os.path.getsize(self.path)} bytes"
            except OSError:
                have = "no file"
            raise InvalidInputError(
                f"{self.path}: cannot read its voxels ({getattr(exc, 'strerror', None) or exc}; {need} bytes needed, "
                f"{have} found); the file was moved, truncated or replaced since it was opened"
            ) from None
        try:
            return np.array(mm[key], dtype=self.dtype)  # copy out (and swap bytes when needed)
        finally:
            del mm

    def to_dask(self, *, depth: int | None = None, name: str = "raw") -> da.Array:
        """A dask array over this file with one chunk per slab of ``depth`` planes along axis 0."""
        return self.to_lazy(depth=depth, name=name).build()

    def to_lazy(self, *, depth: int | None = None, name: str = "raw") -> LazyArray:
        """:meth:`to_dask` as a :class:`LazyArray`: the file's identity is taken now, dask imported when built."""
        if depth is None:
            depth = slab_depth(self.shape[1:], self.dtype)
        stat = os.stat(self.path)
        chunks = (min(int(depth), self.shape[0]),) + self.shape[1:]

        def build() -> da.Array:
            import dask.array as da
            from dask.base import tokenize

            token = tokenize(self.path, stat.st_mtime_ns, stat.st_size, self.offset, self.stored_dtype.str,
                             self.shape)
            return da.from_array(self, chunks=chunks, name=f"{name}-{token}", asarray=False, fancy=False,
                                 meta=np.empty((0,) * self.ndim, dtype=self.dtype))

        return LazyArray(build, self.shape, self.dtype, chunks)

    def __repr__(self) -> str:
        return f"RawFileArray({self.path!r}, dtype={self.stored_dtype.str}, shape={self.shape}, offset={self.offset})"




def write_slab_depth(volume: Volume, target: int = 256 * 2**20) -> int:
    """Planes per slab when streaming ``volume`` out: whole input chunks along axis0 when they fit ``target``."""
    plane = volume.shape[1] * volume.shape[2] * volume.dtype.itemsize
    c = int(volume.data.chunksize[0])
    if c * plane <= target:
        return max(c, c * (target // (c * plane)))
    return max(1, target // plane)


def iter_slabs(volume: Volume, depth: int) -> Iterator[tuple[int, int, np.ndarray]]:
    """``(z0, z1, planes)`` of ``volume`` in slabs of ``depth`` planes, each computed when reached."""
    n0 = volume.shape[0]
    for z0 in range(0, n0, depth):
        z1 = min(n0, z0 + depth)
        yield z0, z1, np.ascontiguousarray(np.asarray(volume.data[z0:z1].compute()))


def read_ahead(read: Callable[[int], Any], starts: Sequence[int], *, name: str = "unwind-read-ahead") -> Iterator[Any]:
    """``read(start)`` for each of ``starts`` in order, the next one read in a background thread while the caller
    works on this one (sending it, writing it)."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix=name) as pool:
        pending = pool.submit(read, starts[0]) if len(starts) else None
        for n in range(len(starts)):
            block = pending.result()
            if n + 1 < len(starts):
                pending = pool.submit(read, starts[n + 1])
            yield block
