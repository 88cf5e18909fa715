"""Bulk voxels in and out: uploads imported while they arrive, and the chunk messages' bytes kept out of protobuf.

Uploads: the gRPC thread feeds a pipe, a process of the import pool imports from it.

The server's Upload handler only moves bytes: it checks each chunk against the header and writes it into a named pipe
(FIFO) under the data root's ``tmp``. A process of the import pool (off the server's GIL, apart from the job workers, so
a slow client holds no job worker) reads the pipe plane by plane and writes the OME-Zarr pyramid with the core's
streaming import (:func:`napari_unwind.io.import_slabs_iter`), so the import overlaps the transfer and neither process
ever holds the whole scan. The store is written atomically: when the stream ends early (the client went away, the chunks
disagree with the header) the worker sees the pipe close short, the core removes its temporary output, and no volume
appears.

An upload of format "chunks" (the store's own chunks, encoded by the client) is stored differently: the import process
checks each chunk and stores it as it came, level 0 alone (:func:`_store_chunks`), and the upload returns once level 0
is in place; the pyramid's other levels are built afterwards by another task of the import pool
(:class:`PyramidBuilds`, :func:`build_pyramid`), resumed at the next start if the server stopped meanwhile.

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
import logging
import os
import select
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from napari_unwind.errors import InvalidInputError

__all__ = ["UploadPipe", "import_stream", "build_pyramid", "PyramidBuilds", "upload_framing",
           "encode_chunk", "chunk_payload", "encoder", "decoder",
           "level_slabs"]

log = logging.getLogger("unwind_services")

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

    def finish(self) -> Any:
        """The last byte is sent: close the pipe and wait for the import (its error, if any, is raised); its
        result."""
        self._close()
        return self.future.result()

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


def _store_chunks(fd: int, shape: tuple[int, int, int], dtype: np.dtype, writer: Any) -> None:
    """Level 0 of an upload of format "chunks", from the pipe (each chunk after its length), into ``writer`` (a
    :class:`~napari_unwind.io.ome_zarr.Level0Writer`) chunk by chunk, without assembling slabs: each chunk is checked
    and decoded (:meth:`ChunkCodec.decode`: its crc32c, a blosc stream of the store's codec holding the chunk's size,
    zeros beyond the volume's edge; float voxels also for NaN and infinities) on two threads while the next ones
    arrive, then stored as it came. The pyramid's other levels are built afterwards (:func:`build_pyramid`)."""
    from napari_unwind.io._api import _reject_nonfinite
    from napari_unwind.io.ome_zarr import ChunkCodec

    codec = ChunkCodec(shape, dtype)
    total, got = int(np.prod(codec.counts)), 0
    floating = np.issubdtype(codec.dtype, np.floating)
    # The bytes are stored as the client made them only when this server's codec makes the same bytes of the same
    # voxels (a client's other blosc build or settings may encode a valid stream differently, and the store would
    # then depend on who uploaded it): every chunk is encoded again here and compared until one that is not
    # constant matched; after a mismatch the server encodes every chunk itself (the store is then import_volume's).
    state = {"trusted": False, "own": writer.signature != codec.signature}

    def store(c: tuple[int, ...], blob: bytearray) -> None:
        voxels = codec.decode(blob, c)
        if floating and not np.isfinite(voxels).all():
            _reject_nonfinite(voxels, {None: {"array-location": [(b.start, b.stop) for b in codec.bounds(c)]}})
        if state["own"]:
            writer.put(c, *codec.encode(codec.chunk(voxels)))
            return
        if not state["trusted"]:
            mine = codec.encode(codec.chunk(voxels))
            if b"".join(mine) != bytes(blob):
                state["own"] = True
                writer.put(c, *mine)
                return
            if voxels.min() != voxels.max():
                state["trusted"] = True
        writer.put(c, blob)

    with open(fd, "rb", buffering=0, closefd=False) as f, \
            ThreadPoolExecutor(max_workers=2, thread_name_prefix="unwind-upload-check") as pool:

        def exact(n: int) -> bytearray:
            buf = bytearray(n)
            view, pos = memoryview(buf), 0
            while pos < n:
                k = f.readinto(view[pos:])
                if not k:
                    raise InvalidInputError(f"the upload ended after {got} of its {total} chunks")
                pos += k
            return buf

        inflight: list[Future] = []
        for c in codec.coords():
            n = int.from_bytes(exact(4), "little")
            if n > codec.max_bytes:
                raise InvalidInputError(f"chunk {got} is {n} bytes, more than a stored chunk")
            blob = exact(n)
            got += 1
            inflight.append(pool.submit(store, c, blob))
            while len(inflight) > 8 or (inflight and inflight[0].done()):  # at most a few chunks held at once
                inflight.pop(0).result()
        for d in inflight:
            d.result()
        if f.read(1):
            raise InvalidInputError(f"more than the {total} chunks of the volume arrived")


def import_stream(fifo: str, shape: tuple, dtype: str, spacing: tuple | None, unit: str | None,
                  origin: tuple | None, labels: bool, dst: str, fmt: str = "raw") -> bool:
    """Import the voxels arriving through ``fifo`` into the OME-Zarr pyramid ``dst`` (runs in a worker process);
    ``fmt``: the upload's format ("raw" voxels or the store's "chunks", see :func:`upload_framing`).

    Format "raw" writes the whole pyramid. Format "chunks" stores level 0 alone (checked chunk by chunk, each stored
    as it came), its other levels marked pending: the store appears (renamed into place) as soon as level 0 is
    written, and :func:`build_pyramid` adds the other levels later. Returns whether levels are pending."""
    from napari_unwind.io import import_slabs_iter
    from napari_unwind.progress import run

    shape = tuple(int(n) for n in shape)
    fd = _open_reader(fifo)
    try:
        if fmt == "chunks":
            import dask.array as da

            from napari_unwind.io import as_volume
            from napari_unwind.io._atomic import atomic_output, check_writable
            from napari_unwind.io._files import check_room
            from napari_unwind.io.ome_zarr import Level0Writer

            placeholder = as_volume(da.empty(shape, dtype=np.dtype(dtype), chunks=shape), spacing=spacing, unit=unit,
                                    origin=origin)
            target = check_writable(dst, overwrite=False)
            check_room(target, placeholder.nbytes, compressed=True)  # as import_slabs_iter
            with atomic_output(target, overwrite=False) as tmp:
                writer = Level0Writer(placeholder, tmp, labels=labels)
                _store_chunks(fd, shape, np.dtype(dtype), writer)
                writer.finish()
            return True
        blocks = _planes(fd, shape, np.dtype(dtype))
        run(import_slabs_iter(blocks, dst, shape=shape, dtype=dtype, spacing=spacing, unit=unit, origin=origin,
                              labels=labels))
        return False
    finally:
        os.close(fd)


#: Tests only: while this environment variable names a file that does not exist, :func:`build_pyramid` waits
#: before it starts (so that a test sees a volume whose pyramid is pending, and kills the server meanwhile).
PYRAMID_GATE = "UNWIND_TEST_PYRAMID_GATE"


def build_pyramid(dst: str) -> None:
    """Build the pending levels of the store ``dst`` (runs in a process of the import pool; see
    :func:`napari_unwind.io.ome_zarr.complete_pyramid`). A store gone meanwhile (deleted) is no error."""
    from napari_unwind.io.ome_zarr import complete_pyramid
    from napari_unwind.progress import run

    gate = os.environ.get(PYRAMID_GATE)
    while gate and not os.path.exists(gate):
        time.sleep(0.05)
    if not os.path.exists(os.path.join(dst, "zarr.json")):
        return
    run(complete_pyramid(dst))


class PyramidBuilds:
    """The pyramids of uploads built after the upload returned, one task of the import pool each.

    The catalog row of such a volume holds ``"pyramid": "pending"`` in its metadata until its build ended; a build
    that did not end (the server stopped or was killed meanwhile, the build failed) is started again by
    :meth:`resume` at the next start. Until then readers see level 0 alone (the store's metadata lists it only)."""

    def __init__(self, catalog: Any, jobs: Any):
        self.catalog, self.jobs = catalog, jobs
        self._lock = threading.Lock()
        self._building: dict[str, Future] = {}

    def start(self, owner: str, volume_id: str, path: Path) -> None:
        with self._lock:
            if volume_id in self._building:
                return
            fut = self.jobs.start_import(build_pyramid, str(path))
            self._building[volume_id] = fut
        fut.add_done_callback(lambda f: self._done(owner, volume_id, f))

    def _done(self, owner: str, volume_id: str, fut: Future) -> None:
        with self._lock:
            self._building.pop(volume_id, None)
        error = None if fut.cancelled() else fut.exception()
        failed = fut.cancelled() or error is not None
        if failed and not self.jobs.closing:
            log.error("the pyramid of volume %s was not built (%s); it is built again at the next start",
                      volume_id, "cancelled" if error is None else _one_line(error))
        if failed and self.jobs.closing:
            return  # stopped by the shutdown: still pending, built at the next start
        try:
            row = self.catalog.store.get_object(owner, volume_id, "volume")
            meta = dict(row.meta)
            if failed:
                meta["pyramid"] = "failed"  # jobs waiting for it fail now, not after their wait; resumed at start
            else:
                meta.pop("pyramid", None)
            self.catalog.store.update_meta(owner, volume_id, meta)
            self.catalog.forget_stored_bytes(owner)
        except Exception as exc:  # noqa: BLE001 - deleted meanwhile, or the store closed at shutdown
            log.warning("volume %s: its record not updated after its pyramid's build (%s)", volume_id,
                        _one_line(exc))

    def resume(self) -> None:
        """At start: build the pyramids that a stopped server left pending."""
        for row in self.catalog.store.pending_pyramids():
            path = self.catalog.path(row)
            log.warning("volume %s: building its pyramid, left %s when the server stopped", row.id,
                        row.meta["pyramid"])
            if row.meta["pyramid"] != "pending":
                self.catalog.store.update_meta(row.owner, row.id, {**row.meta, "pyramid": "pending"})
            self.start(row.owner, row.id, path)


def _one_line(exc: BaseException) -> str:
    return (str(exc).splitlines() or [type(exc).__name__])[0][:300]
