"""Bulk voxels in and out: uploads imported while they arrive, and the chunk messages' bytes kept out of protobuf.

Uploads: the gRPC thread feeds a pipe, a process of the import pool imports from it.

The server's Upload handler only moves bytes: it checks each chunk against the header and writes it into a named pipe
(FIFO) under the data root's ``tmp``. A process of the import pool (off the server's GIL, apart from the job workers, so
a slow client holds no job worker) reads the pipe plane by plane and writes the OME-Zarr pyramid with the core's
streaming import (:func:`napari_unwind.io.import_slabs_iter`), so the import overlaps the transfer and neither process
ever holds the whole scan. The store is written atomically: when the stream ends early (the client went away, the chunks
disagree with the header) the worker sees the pipe close short, the core removes its temporary output, and no volume
appears.

Chunk messages (``UploadRequest.chunk`` and ``DownloadResponse.chunk``, field 2 of both) are encoded and decoded
here by hand, on both sides: a chunk is its tag, its length and its bytes, so encoding is one copy and decoding
is a memoryview of the received bytes, where protobuf would copy each 2 MiB chunk two or three times. Every
other message (headers, and anything that does not look like a bare chunk) goes through protobuf.

Downloads: :func:`level_slabs` reads a pyramid level slab by slab, one slab ahead of the one being sent; a level of
the stores the core writes is read chunk by chunk with the core's checked chunk reader, each chunk decoded straight
into its place, which is about twice as fast as dask's scheduler here (and five times on a first read).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import itertools
import os
import select
import sys
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from napari_unwind.errors import InvalidInputError

__all__ = ["UploadPipe", "import_stream", "upload_framing", "encode_chunk", "chunk_payload", "encoder", "decoder",
           "level_slabs"]

CHUNK_TAG = b"\x12"  # field 2, wire type 2 (length-delimited): ``chunk`` of UploadRequest and DownloadResponse

_F_SETPIPE_SZ = 1031  # linux/fcntl.h: a larger pipe buffer means fewer wake-ups per MiB
_PIPE_BYTES = 1 << 20


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        out.append((n & 0x7F) | (0x80 if n > 0x7F else 0))
        n >>= 7
        if not n:
            return bytes(out)


def encode_chunk(*parts: Any) -> bytes:
    """The encoded message ``{chunk: the parts' bytes one after the other}`` (an UploadRequest or a
    DownloadResponse), made with one copy."""
    return b"".join((CHUNK_TAG, _varint(sum(len(p) for p in parts)), *parts))


def chunk_payload(data: bytes) -> memoryview | None:
    """The bytes of an encoded message that is exactly ``{chunk: ...}``, as a memoryview; else None."""
    if data[:1] != CHUNK_TAG:
        return None
    n, shift, i = 0, 0, 1
    while i < min(len(data), 11):
        b = data[i]
        n |= (b & 0x7F) << shift
        i += 1
        if b < 0x80:
            return memoryview(data)[i:] if i + n == len(data) else None
        shift += 7
    return None


def encoder(message_type: Any) -> Callable[[Any], bytes]:
    """A serializer for messages of ``message_type`` that passes chunks already encoded (bytes) as they are."""
    def encode(message: Any) -> bytes:
        return message if isinstance(message, bytes) else message_type.SerializeToString(message)

    return encode


def decoder(message_type: Any) -> Callable[[bytes], Any]:
    """A deserializer giving a chunk message as a memoryview of its bytes, any other as ``message_type``."""
    def decode(data: bytes) -> Any:
        payload = chunk_payload(data)
        return payload if payload is not None else message_type.FromString(data)

    return decode


class UploadPipe:
    """The server's end of one streamed import: a FIFO the worker reads, written chunk by chunk.

    ``start(fifo)`` must submit the worker's :func:`import_stream` reading that path and return its Future.
    """

    def __init__(self, tmp_dir: Path, name: str, start: Callable[[str], Future]):
        self.path = Path(tmp_dir) / f"{name}.fifo"
        os.mkfifo(self.path, 0o600)
        self.fd: int | None = None
        self.future: Future | None = None
        try:
            self.future = start(str(self.path))
        except BaseException:
            self.path.unlink(missing_ok=True)
            raise

    def open(self, alive: Callable[[], bool] = lambda: True) -> None:
        """Wait until the worker opens its end (it may wait for a free worker), then own the writing end."""
        delay = 0.001
        while True:
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_NONBLOCK)
                break
            except OSError as exc:
                if exc.errno != errno.ENXIO:  # ENXIO: no reader yet
                    raise
            if self.future.done():
                self.future.result()  # the worker failed before reading: its error
                raise InvalidInputError("the import ended before the upload started")
            if not alive():
                raise InvalidInputError("the client went away before the upload started")
            time.sleep(delay)
            delay = min(0.05, delay * 2)
        os.set_blocking(fd, True)
        with contextlib.suppress(OSError):
            fcntl.fcntl(fd, _F_SETPIPE_SZ, _PIPE_BYTES)
        self.fd = fd

    def write(self, *parts: Any) -> bool:
        """Send ``parts`` (bytes-like) to the worker; False when the worker stopped reading (its error is in the
        Future)."""
        try:
            for data in parts:
                view = memoryview(data)
                while view:
                    view = view[os.write(self.fd, view):]
        except BrokenPipeError:
            return False
        return True

    def finish(self) -> None:
        """The last byte is sent: close the pipe and wait for the import (its error, if any, is raised)."""
        self._close()
        self.future.result()

    def abandon(self) -> None:
        """Stop early: the worker sees the stream end short and removes its partial output; wait for that."""
        self._close()
        if self.future is not None and not self.future.cancel():
            with contextlib.suppress(Exception):
                self.future.result()

    def _close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
        self.path.unlink(missing_ok=True)


class _RawFraming:
    """Upload format "raw": the voxels' bytes, cut anywhere; they go down the pipe as they came."""

    format = "raw"

    def __init__(self, shape: tuple[int, ...], dtype: np.dtype):
        self.shape, self.dtype = shape, dtype
        self.expected, self.received = int(np.prod(shape)) * dtype.itemsize, 0

    def parts(self, chunk: Any) -> tuple:
        self.received += len(chunk)
        if self.received > self.expected:
            raise InvalidInputError(f"the chunks hold more bytes than the header's shape {list(self.shape)} and "
                                    f"dtype {self.dtype.name} ({self.expected} bytes)")
        return (chunk,)

    def check_complete(self) -> None:
        if self.received != self.expected:
            raise InvalidInputError(f"the header promises {self.expected} bytes (shape {list(self.shape)}, "
                                    f"{self.dtype.name}) but the chunks held {self.received}")


class _ChunkFraming:
    """Upload format "chunks": one stored chunk a message; each goes down the pipe after its length (4 bytes,
    little-endian). The worker checks and decodes it (:func:`_chunk_slabs`); here only the count and the size."""

    format = "chunks"

    def __init__(self, shape: tuple[int, ...], dtype: np.dtype, chunk_shape: tuple[int, ...], max_message: int):
        from napari_unwind.io.ome_zarr import ChunkCodec

        self.codec = ChunkCodec(shape, dtype)
        if tuple(chunk_shape) != self.codec.grid:
            raise InvalidInputError(f"chunk_shape must be {list(self.codec.grid)} for a volume of shape "
                                    f"{list(shape)} (the server's chunks), got {list(chunk_shape)}")
        if self.codec.max_bytes + 16 > max_message:
            raise InvalidInputError(f"format \"chunks\" of this volume needs messages of up to "
                                    f"{self.codec.max_bytes + 16} bytes, more than this server's limit of "
                                    f"{max_message}; upload it raw")
        self.expected, self.received = int(np.prod(self.codec.counts)), 0

    def parts(self, chunk: Any) -> tuple:
        if self.received >= self.expected:
            raise InvalidInputError(f"more chunks than the {self.expected} of the volume arrived")
        if not 4 < len(chunk) <= self.codec.max_bytes:
            raise InvalidInputError(f"chunk {self.received} is {len(chunk)} bytes: not a stored chunk of "
                                    f"{self.codec.nbytes} bytes of voxels and its checksum")
        self.received += 1
        return len(chunk).to_bytes(4, "little"), chunk

    def check_complete(self) -> None:
        if self.received != self.expected:
            raise InvalidInputError(f"the volume has {self.expected} chunks but {self.received} arrived")


def upload_framing(header: Any, dtype: np.dtype, max_message: int) -> _RawFraming | _ChunkFraming:
    """How an upload's messages go down the pipe, from its header (format "raw" or "chunks"); a header asking for
    anything else is an :class:`InvalidInputError`."""
    shape = tuple(int(n) for n in header.shape)
    fmt = (header.format or "raw").lower()
    if fmt == "raw":
        return _RawFraming(shape, dtype)
    if fmt == "chunks":
        return _ChunkFraming(shape, dtype, tuple(int(n) for n in header.chunk_shape), max_message)
    raise InvalidInputError(f"format must be \"raw\" or \"chunks\", got {header.format!r}")


def _chunk_reader(vol: Any, index: int) -> Any:
    """The core's chunk reader of pyramid level ``index`` of an OME-Zarr volume, or None (read through dask)."""
    if vol.format != "ome-zarr" or not vol.source:
        return None
    try:
        import zarr

        from napari_unwind.io.ome_zarr import _multiscales, _ZarrChunks

        node = zarr.open_group(vol.source, mode="r")
        multiscales, _ = _multiscales(dict(node.attrs))
        array = node[multiscales[0]["datasets"][index]["path"]]
    except Exception:  # noqa: BLE001 - anything unusual (a bare array, v2 layouts...) is read through dask
        return None
    if array.ndim != 3 or tuple(array.shape) != tuple(vol.levels[index].shape):
        return None  # e.g. length-1 t/c axes that the reader drops
    complete = (vol.metadata.get("unwind") or {}).get("all_chunks_written") is True
    return _ZarrChunks(array, vol.source, complete=complete)


def level_slabs(vol: Any, index: int, dtype: np.dtype) -> Iterator[np.ndarray]:
    """Pyramid level ``index`` of ``vol`` as C-contiguous slabs (of its chunk depth) in ``dtype``, read ahead."""
    from napari_unwind.io._lazy import read_ahead

    level = vol.levels[index]
    shape = tuple(int(n) for n in level.shape)
    chunks = _chunk_reader(vol, index)
    step = max(1, chunks.grid[0] if chunks is not None else int(level.chunks[0][0]))
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:

        def read(z0: int) -> np.ndarray:
            z1 = min(shape[0], z0 + step)
            if chunks is None:
                return np.ascontiguousarray(level[z0:z1].compute(), dtype=dtype)
            slab = np.empty((z1 - z0, *shape[1:]), dtype=dtype)
            g1, g2 = chunks.grid[1:]

            def one(yx: tuple[int, int]) -> None:
                y, x = yx
                slab[:, y:y + g1, x:x + g2] = chunks[z0:z1, y:y + g1, x:x + g2]

            list(pool.map(one, itertools.product(range(0, shape[1], g1), range(0, shape[2], g2))))
            return slab

        yield from read_ahead(read, range(0, shape[0], step), name="unwind-download-read")


def stored_chunks(vol: Any, index: int, max_message: int) -> tuple[Any, Iterator[bytes | None]] | None:
    """Pyramid level ``index`` of ``vol`` as its stored chunks, when they are blosc streams of little-endian voxels
    the client can decode itself (what the core's OME-Zarr writer stores) and a chunk fits in a message of
    ``max_message`` bytes even uncompressed: (the chunk reader, the chunks' bytes in C order of the grid, None for a
    chunk never written, read ahead); None otherwise (send the level raw)."""
    from napari_unwind.io._lazy import read_ahead

    reader = _chunk_reader(vol, index)
    if reader is None or reader.direct is None or not reader.direct[0] or sys.byteorder != "little":
        return None
    if int(np.prod(reader.grid)) * reader.dtype.itemsize * 1.01 + 1024 > max_message:  # blosc's worst case
        return None
    grid = [range(-(-n // g)) for n, g in zip(reader.shape, reader.grid, strict=True)]
    coords = list(itertools.product(*grid))
    return reader, read_ahead(lambda k: reader.stored_chunk(coords[k]), range(len(coords)),
                              name="unwind-download-read")


def _open_reader(fifo: str) -> int:
    """Open the reading end without blocking on a writer that may never come, then wait for the first bytes."""
    fd = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    poll = select.poll()
    poll.register(fd, select.POLLIN | select.POLLHUP)
    while not poll.poll(200):  # data, or a writer came and went (the stream ended)
        if not os.path.exists(fifo):  # the server gave up before writing
            os.close(fd)
            raise InvalidInputError("the upload was abandoned before its first byte")
    os.set_blocking(fd, True)
    return fd


def _planes(fd: int, shape: tuple[int, int, int], dtype: np.dtype) -> Iterator[np.ndarray]:
    """The voxels from the pipe, slab by slab, each read straight into a new array."""
    from napari_unwind.io.ome_zarr import DEFAULT_CHUNKS

    expected = int(np.prod(shape)) * dtype.itemsize
    got = 0
    with open(fd, "rb", buffering=0, closefd=False) as f:
        for z0 in range(0, shape[0], DEFAULT_CHUNKS[0]):  # planes per read: the store's chunk depth
            slab = np.empty((min(DEFAULT_CHUNKS[0], shape[0] - z0), *shape[1:]), dtype=dtype)
            view = memoryview(slab).cast("B")
            pos = 0
            while pos < len(view):
                n = f.readinto(view[pos:])
                if not n:
                    raise InvalidInputError(f"the upload ended after {got + pos} of its {expected} bytes")
                pos += n
            got += pos
            yield slab


def _chunk_slabs(fd: int, shape: tuple[int, int, int], dtype: np.dtype) -> Iterator[Any]:
    """The stored chunks from the pipe (format "chunks", each after its length), a row of the grid at a time: each
    chunk checked and decoded (:meth:`ChunkCodec.decode`, on two threads while the next ones arrive) into the row's
    slab; yields the slabs with their chunks' bytes (:class:`EncodedSlab`), which the writer stores as they are."""
    from napari_unwind.io.ome_zarr import ChunkCodec, EncodedSlab

    codec = ChunkCodec(shape, dtype)
    total, got = int(np.prod(codec.counts)), 0
    # The bytes are stored as the client made them only when this server's codec makes the same bytes of the same
    # voxels (a client's other blosc build or settings may encode a valid stream differently, and the store would
    # then depend on who uploaded it): every chunk is encoded again here and compared until one that is not
    # constant matched; a mismatch makes the server encode the rest itself (the store is then import_volume's).
    trusted, own = False, False

    with open(fd, "rb", buffering=0, closefd=False) as f, \
            ThreadPoolExecutor(max_workers=2, thread_name_prefix="unwind-upload-decode") as pool:

        def exact(n: int) -> bytearray:
            buf = bytearray(n)
            view, pos = memoryview(buf), 0
            while pos < n:
                k = f.readinto(view[pos:])
                if not k:
                    raise InvalidInputError(f"the upload ended after {got} of its {total} chunks")
                pos += k
            return buf

        for cz in range(codec.counts[0]):
            z0 = cz * codec.grid[0]
            slab = np.empty((min(codec.grid[0], shape[0] - z0), *shape[1:]), dtype=codec.dtype)
            chunks: dict = {}
            decoding = []

            def place(c: tuple[int, ...], blob: bytearray, slab: np.ndarray = slab) -> None:
                where = codec.bounds(c)
                slab[(slice(None), *where[1:])] = codec.decode(blob, c)

            for c in itertools.product([cz], *[range(n) for n in codec.counts[1:]]):
                n = int.from_bytes(exact(4), "little")
                if n > codec.max_bytes:
                    raise InvalidInputError(f"chunk {got} is {n} bytes, more than a stored chunk")
                blob = exact(n)
                got += 1
                chunks[c] = blob
                decoding.append(pool.submit(place, c, blob))
            for d in decoding:
                d.result()
            if not trusted and not own:
                for c, blob in chunks.items():
                    whole = codec.chunk(slab[(slice(None), *codec.bounds(c)[1:])])
                    if b"".join(codec.encode(whole)) != bytes(blob):
                        own = True
                        break
                    if whole.min() != whole.max():
                        trusted = True
                        break
            yield slab if own else EncodedSlab(slab, chunks, codec)
        if f.read(1):
            raise InvalidInputError(f"more than the {total} chunks of the volume arrived")


def import_stream(fifo: str, shape: tuple, dtype: str, spacing: tuple | None, unit: str | None,
                  origin: tuple | None, labels: bool, dst: str, fmt: str = "raw") -> None:
    """Import the voxels arriving through ``fifo`` into the OME-Zarr pyramid ``dst`` (runs in a worker process);
    ``fmt``: the upload's format ("raw" voxels or the store's "chunks", see :func:`upload_framing`)."""
    from napari_unwind.io import import_slabs_iter
    from napari_unwind.progress import run

    shape = tuple(int(n) for n in shape)
    fd = _open_reader(fifo)
    try:
        blocks = _chunk_slabs(fd, shape, np.dtype(dtype)) if fmt == "chunks" else _planes(fd, shape, np.dtype(dtype))
        run(import_slabs_iter(blocks, dst, shape=shape, dtype=dtype, spacing=spacing, unit=unit, origin=origin,
                              labels=labels))
    finally:
        os.close(fd)
