"""Python client of the napari-unwind services: the in-process API, run on a server.

>>> from napari_unwind.client import Client                       # doctest: +SKIP
>>> with Client("unwind.facility.org:50051", token="...", tls=True) as c:
...     scan = c.upload("tank_042.tif", spacing=(35.7, 35.7, 35.7), unit="um")
...     job = c.pipeline(scan.volume_id, select=[(120, 80, 400)], output_name="fish1.zarr")
...     c.download(job.result.volume_id, "fish1.nrrd")

Every call has a deadline and is retried with exponential backoff while the server is UNAVAILABLE (restarting);
``wait`` and ``watch`` reconnect and resume the progress stream where it stopped. Long operations are jobs:
with ``wait=True`` (the default) the call follows the job with a tqdm bar and returns it finished, or raises
:class:`RemoteError` with the server's status code and message. :meth:`Client.run_batch` straightens a whole
collection and ends with a CSV summary.

Needs the ``server`` extra (grpcio); the core does not import this module.
"""

from __future__ import annotations

import collections
import csv
import itertools
import math
import os
import random
import re
import shutil
import tarfile
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InvalidInputError, UnwindError
from .progress import Progress, progress_bar

__all__ = ["Client", "RemoteError", "BatchItem", "DEFAULT_ADDRESS"]

DEFAULT_ADDRESS = "127.0.0.1:50051"
#: Bytes of voxels per upload message: within the 4 MiB default message limit of servers; larger messages are not
#: faster (benchmarks/bench_services.py).
_CHUNK = 2 * 1024 * 1024
_RAW_PIECE_MIN = 64 * 1024  # the smallest raw message the client sends to a server whose message limit is low
_SLAB_BYTES = 32 * 1024 * 1024  # voxels read from the source per step (ahead of the messages being sent)



def _batch_item(item: Any, k: int) -> BatchItem:
    """A :class:`BatchItem` from itself or a dict of its fields; one line naming the item otherwise."""
    if isinstance(item, BatchItem):
        return item
    if not isinstance(item, dict):
        raise InvalidInputError(f"batch item {k} must be a BatchItem or a dict of its fields, got "
                                f"{type(item).__name__}")
    try:
        return BatchItem(**item)
    except TypeError as exc:
        raise InvalidInputError(f"batch item {k}: {exc}; its fields are scan, select, name, features, register, "
                                "options") from None


def _server_json(text: str, what: str) -> Any:
    """JSON the server sent (a session, the features) read under the rules of every JSON input
    (:mod:`napari_unwind._json`): a damaged or hostile answer is one line, never a RecursionError."""
    from ._json import loads

    try:
        return loads(text)
    except InvalidInputError as exc:
        raise InvalidInputError(f"{what} the server sent {exc}; is the server a napari-unwind server of this "
                                "version?") from None

class _Held:
    """An ndarray dask sees without the full copy (and hash) ``dask.array.from_array`` makes of arrays."""

    def __init__(self, a: np.ndarray):
        self.a, self.shape, self.dtype, self.ndim = a, a.shape, a.dtype, a.ndim

    def __getitem__(self, key: Any) -> np.ndarray:
        return self.a[key]


def _message_limit(exc: Exception) -> int | None:
    """The server's message limit in gRPC's refusal of a message over it ("Received message larger than max
    (2097171 vs. 1048576)"), or None for any other error."""
    m = re.search(r"larger than max \((\d+) vs\. (\d+)\)", str(exc))
    if m is None or getattr(exc, "code", None) != "RESOURCE_EXHAUSTED":
        return None
    return int(m.group(2))


def _piece_within(exc: Exception, piece: int) -> int | None:
    """Bytes of raw voxels a message, under the server's message limit named in ``exc``, when that is below
    ``piece`` (and at least ``_RAW_PIECE_MIN``); None otherwise."""
    limit = _message_limit(exc)
    if limit is None or not _RAW_PIECE_MIN <= limit - 64 < piece:
        return None
    return (limit - 64) // 4096 * 4096


def _lazy(a: np.ndarray) -> Any:
    import dask.array as da

    return da.from_array(_Held(a), chunks=tuple(min(int(n), 128) for n in a.shape), name=f"array-{uuid.uuid4().hex}")


def _slabs(source: Any, dtype: np.dtype, step: int) -> Iterator[np.ndarray]:
    """C-contiguous slabs of ``step`` planes of ``source`` (an ndarray, or a dask array computed slab by slab),
    in ``dtype``; the next slab is read in a background thread while the caller sends this one."""
    from .io._lazy import read_ahead

    starts = range(0, source.shape[0], step)

    def read(z0: int) -> np.ndarray:
        block = source[z0:z0 + step]
        if not isinstance(block, np.ndarray):
            block = block.compute()
        return np.ascontiguousarray(block, dtype=dtype)  # a view when it already is (no copy)

    yield from read_ahead(read, starts, name="unwind-upload-read")


#: Seconds the raw upload that follows a refused chunked one waits for the refused one's slot (see Client.upload).
_SLOT_GRACE = 3.0

#: What a server that takes raw uploads only answers to an upload of format "chunks" (it ignores the format and
#: counts the chunks' bytes as voxels), or one whose message limit is below a chunk's: the client then uploads raw.
_RAW_ONLY_SERVER = ("but the chunks held", "the chunks hold more bytes than the header's shape",
                    "; upload it raw")  # (the last: a server whose message limit is below a chunk's size)


def _encoded_chunks(source: Any, dtype: np.dtype, codec: Any) -> Iterator[bytes]:
    """Upload messages of format "chunks": each chunk of ``source`` encoded as the store holds it (a few chunks
    ahead, on two threads: blosc releases the GIL), in C order of the grid, one message each."""
    from unwind_services.ingest import encode_chunk

    def encode(part: np.ndarray) -> bytes:
        return encode_chunk(*codec.encode(codec.chunk(part)))  # the message made with one copy

    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="unwind-upload-encode") as pool:
        inflight: collections.deque = collections.deque()
        for cz, slab in enumerate(_slabs(source, dtype, codec.grid[0])):
            for c in itertools.product([cz], *[range(n) for n in codec.counts[1:]]):
                where = codec.bounds(c)
                inflight.append(pool.submit(encode, slab[(slice(None), *where[1:])]))
                while len(inflight) > 6:
                    yield inflight.popleft().result()
        while inflight:
            yield inflight.popleft().result()


class RemoteError(UnwindError):
    """A call or a job failed on the server: ``code`` is the gRPC status code name, the message the server's."""

    def __init__(self, message: str, code: str = "UNKNOWN", job: Any = None):
        super().__init__(message)
        self.code = code
        self.job = job


class RemoteInvalidInputError(RemoteError, InvalidInputError):
    """The server refused the input (INVALID_ARGUMENT)."""


def _remote_error(exc: Any, what: str = "") -> RemoteError:
    import grpc

    code = exc.code() if hasattr(exc, "code") else grpc.StatusCode.UNKNOWN
    details = exc.details() if hasattr(exc, "details") else str(exc)
    if code == grpc.StatusCode.UNAVAILABLE:
        details = f"the server is unavailable ({details})"
    cls = RemoteInvalidInputError if code == grpc.StatusCode.INVALID_ARGUMENT else RemoteError
    return cls(f"{what}{details}", code.name)


#: Points per MapPoints call or MapPointsStream message (the server takes up to 100000; 1.2 MB a message).
MAP_BATCH = 50_000


def _points(points: Any, what: str) -> list:
    from unwind_services._proto.unwind.v1 import common_pb2 as pb

    if points is None:
        return []
    arr = np.asarray(points, dtype=float).reshape(-1, 3)
    return [pb.Point(axis0=a, axis1=b, axis2=c) for a, b, c in arr]


def _progress(p: Any) -> Progress:
    return Progress(p.stage, int(p.done), int(p.total), p.message)


#: The summary of a profile in :meth:`Client.run_batch` (``measure=True``), in column order; each column's name
#: carries its unit (``"length [mm]"``).
SUMMARY_MEASURES = ("curvature_mean", "curvature_max", "area_mean", "area_max", "radius_max", "volume")


def profile_summary(table_csv: str) -> dict[str, float]:
    """The figures of a profile (the CSV of ``unwind measure`` or of a Measure job) that are compared across
    specimens, each named with its unit: ``curvature_mean`` and ``curvature_max`` (1/length), and with a mask
    ``area_mean``, ``area_max`` (the cross-section), ``radius_max`` (the largest equivalent radius,
    sqrt(area / pi)) and ``volume`` (the area integrated along s, trapezoids). Columns the profile lacks are left
    out. (The length is the deformation's, a column of the pipeline's summary already: the profile's stations stop
    within one spacing of the tail.)"""
    import re

    rows = list(csv.reader(table_csv.splitlines()))
    if not rows or not rows[0] or rows[0][0].split(" [")[0] != "s":
        raise InvalidInputError("not a profile: its first column is not the arc length s")
    names, units = [], {}
    for h in rows[0]:
        m = re.fullmatch(r"(.*) \[(.*)\]", h)
        names.append(m.group(1) if m else h)
        units[names[-1]] = m.group(2) if m else ""
    values = np.array([[float(x) if x else np.nan for x in r] for r in rows[1:]], dtype=float).reshape(-1, len(names))
    col = {n: values[:, i] for i, n in enumerate(names)}
    L = units["s"]

    def named(measure: str, unit: str) -> str:
        return f"{measure} [{unit}]" if unit else measure

    out: dict[str, float] = {}
    if "curvature" in col and np.isfinite(col["curvature"]).any():
        out[named("curvature_mean", units["curvature"])] = float(np.nanmean(col["curvature"]))
        out[named("curvature_max", units["curvature"])] = float(np.nanmax(col["curvature"]))
    if "area" in col and np.isfinite(col["area"]).any():
        area = col["area"]
        out[named("area_mean", units["area"])] = float(np.nanmean(area))
        out[named("area_max", units["area"])] = float(np.nanmax(area))
        if "radius" in col:
            out[named("radius_max", units["radius"])] = float(np.nanmax(col["radius"]))
        a = np.nan_to_num(area)
        out[named("volume", f"{L}^3" if L else "")] = float(np.sum((a[1:] + a[:-1]) / 2 * np.diff(col["s"])))
    return out


@dataclass
class BatchItem:
    """One scan of a collection for :meth:`Client.run_batch`.

    Attributes
    ----------
    scan : str
        A local file or folder to upload, a volume id on the server (``vol-...``), or with ``register`` a path
        relative to the server's data root.
    select : sequence of points, or "all"
        Points inside the specimen (full-resolution voxels), or ``"all"``: every feature of the segmentation is a
        specimen (a tank of fish).
    name : str, optional
        The specimen's name in the summary and its output's file name (default: the scan's).
    features : int
        Features the segmentation keeps (default 5).
    register : bool
        ``scan`` is a path under the server's data root: register it instead of uploading.
    """

    scan: str
    select: Any = "all"
    name: str | None = None
    features: int = 5
    register: bool = False
    options: dict[str, Any] = field(default_factory=dict)


try:
    import google_crc32c as _CRC32C
except ImportError:  # pragma: no cover - a dependency of zarr's crc32c codec; without it downloads come raw
    _CRC32C = None


def _receive_chunks(header: Any, chunks: Iterator[Any], shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """A download of format "chunks" decoded into one array: each message one stored chunk (a blosc stream and its
    crc32c), in C order of the grid, checked and decoded on two threads (blosc releases the GIL) while the next
    ones arrive. A chunk whose checksum or size does not match is DATA_LOSS."""
    from numcodecs import blosc

    grid = tuple(int(g) for g in header.chunk_shape)
    if len(grid) != len(shape) or min(grid, default=0) < 1:
        raise RemoteError(f"download: the server sent chunks of shape {grid} for a {shape} volume", "DATA_LOSS")
    counts = [-(-n // g) for n, g in zip(shape, grid, strict=True)]
    coords = itertools.product(*[range(c) for c in counts])
    expected = math.prod(counts)
    nbytes = math.prod(grid) * dtype.itemsize
    arr = np.empty(shape, dtype=dtype)

    def place(c: tuple[int, ...], blob: Any) -> None:
        where = tuple(slice(i * g, min(n, (i + 1) * g)) for i, g, n in zip(c, grid, shape, strict=True))
        if not len(blob):
            arr[where] = header.fill_value
            return
        data = np.frombuffer(blob, dtype=np.uint8)
        if header.chunk_crc32c:
            if data.size < 4 or _CRC32C.value(data[:-4]) != int.from_bytes(bytes(data[-4:]), "little"):
                raise RemoteError(f"download: chunk {c} does not match its checksum", "DATA_LOSS")
            data = data[:-4]
        if data.size < 16 or int.from_bytes(bytes(data[4:8]), "little") != nbytes:
            raise RemoteError(f"download: chunk {c} is not a blosc stream of the chunk's size", "DATA_LOSS")
        out = np.empty(grid, dtype=dtype)
        try:
            blosc.decompress(data, out)
        except Exception as exc:  # noqa: BLE001 - numcodecs raises RuntimeError, ValueError...
            raise RemoteError(f"download: chunk {c} cannot be decoded ({exc})", "DATA_LOSS") from None
        arr[where] = out[tuple(slice(0, s.stop - s.start) for s in where)]

    got = 0
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="unwind-download-decode") as pool:
        pending: list[Any] = []
        for blob in chunks:
            c = next(coords, None)
            if c is None:
                raise RemoteError(f"download: the server sent more than the {expected} chunks of the volume",
                                  "DATA_LOSS")
            pending.append(pool.submit(place, c, blob))
            got += 1
            if len(pending) >= 8:  # a few chunks in flight at most
                pending.pop(0).result()
        for f in pending:
            f.result()
    if got != expected:
        raise RemoteError(f"download: the server sent {got} chunks of {expected}", "DATA_LOSS")
    return arr


class Client:
    """A connection to an ``unwind serve`` server.

    Parameters
    ----------
    address : str
        ``host:port`` (default ``127.0.0.1:50051``).
    token : str, optional
        The bearer token the server's administrator gave you (default: ``$UNWIND_TOKEN``, else the one in the
        file ``$UNWIND_TOKEN_FILE`` names; see :func:`napari_unwind._tokenfile.read_token_file`).
    tls : bool or path-like
        Use TLS: True with the system's root certificates, or the path of a CA certificate (PEM).
    timeout : float
        Deadline of each unary call, seconds.
    retry_seconds : float
        How long to keep retrying while the server is UNAVAILABLE (restarting), seconds.
    progress : bool
        Show tqdm bars while waiting for jobs.
    max_message_bytes : int
        Message size limit of the channel (both ways).
    """

    def __init__(self, address: str = DEFAULT_ADDRESS, *, token: str | None = None,
                 tls: bool | str | os.PathLike = False, timeout: float = 60.0, retry_seconds: float = 60.0,
                 progress: bool = True, max_message_bytes: int = 64 * 1024**2):
        import grpc

        from unwind_services._proto.unwind.v1 import (
            jobs_pb2_grpc,
            segmentation_pb2_grpc,
            skeleton_pb2_grpc,
            volume_pb2_grpc,
            warp_pb2_grpc,
        )

        self.address, self._max_message = address, int(max_message_bytes)
        self.timeout, self.retry_seconds, self.progress = float(timeout), float(retry_seconds), bool(progress)
        if token is None:
            token = os.environ.get("UNWIND_TOKEN") or None
        if token is None and os.environ.get("UNWIND_TOKEN_FILE"):
            from ._tokenfile import read_token_file

            token = read_token_file(os.environ["UNWIND_TOKEN_FILE"])
        self._metadata = (("authorization", f"Bearer {token}"),) if token else ()
        options = [("grpc.max_receive_message_length", max_message_bytes),
                   ("grpc.max_send_message_length", max_message_bytes)]
        if tls:
            roots = None if tls is True else Path(tls).read_bytes()
            self._channel = grpc.secure_channel(address, grpc.ssl_channel_credentials(root_certificates=roots), options)
        else:
            self._channel = grpc.insecure_channel(address, options)
        self.volumes_stub = volume_pb2_grpc.VolumeServiceStub(self._channel)
        self.segmentation_stub = segmentation_pb2_grpc.SegmentationServiceStub(self._channel)
        self.skeleton_stub = skeleton_pb2_grpc.SkeletonServiceStub(self._channel)
        self.warp_stub = warp_pb2_grpc.WarpServiceStub(self._channel)
        self.jobs_stub = jobs_pb2_grpc.JobServiceStub(self._channel)

    # -- plumbing ----------------------------------------------------------------------------------------------------
    def close(self) -> None:
        self._channel.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _retrying(self, fn: Callable[[], Any], what: str, until: float | None = None) -> Any:
        """Call ``fn``; on UNAVAILABLE retry with exponential backoff (and jitter) for up to ``retry_seconds``, and
        never past ``until`` (a ``time.monotonic()`` deadline: the call's own)."""
        import grpc

        deadline = time.monotonic() + self.retry_seconds
        if until is not None:
            deadline = min(deadline, until)
        delay = 0.1
        while True:
            try:
                return fn()
            except grpc.RpcError as exc:
                if exc.code() != grpc.StatusCode.UNAVAILABLE or time.monotonic() + delay > deadline:
                    raise _remote_error(exc, what) from None
            time.sleep(delay * (0.5 + random.random()))
            delay = min(delay * 2, 5.0)

    def _unary(self, method: Callable, request: Any, what: str = "", timeout: float | None = None) -> Any:
        """One call within ``timeout`` (default the client's) in all: waiting for an unreachable or restarting
        server counts against it, so an unreachable server is reported after ``timeout`` seconds, not after
        ``retry_seconds``."""
        end = time.monotonic() + (timeout or self.timeout)

        def call() -> Any:
            return method(request, timeout=max(0.05, end - time.monotonic()), metadata=self._metadata)

        return self._retrying(call, what, until=end)

    def health(self, service: str = "") -> str:
        """The server's health status name (``SERVING``...) for the whole server or one service."""
        from grpc_health.v1 import health_pb2, health_pb2_grpc

        stub = health_pb2_grpc.HealthStub(self._channel)
        r = self._unary(stub.Check, health_pb2.HealthCheckRequest(service=service))
        return health_pb2.HealthCheckResponse.ServingStatus.Name(r.status)

    # -- volumes -----------------------------------------------------------------------------------------------------
    def upload(self, data: Any, *, name: str | None = None, spacing: Any = None, unit: str | None = None,
               origin: Any = None, labels: bool = False, timeout: float = 3600.0, format: str = "chunks",
               **reader_options: Any):
        """Upload a scan (a path any reader opens, a Volume, or an array); it lands as an OME-Zarr pyramid.

        ``format``: "chunks" (default) encodes the store's chunks here (blosc lz4 and their crc32c, on two threads
        while they are sent: fewer bytes cross, and the server checks and stores them instead of encoding them);
        "raw" sends the voxels' bytes. A server of an earlier version, which takes raw voxels only, is sent them
        raw. Returns the server's ``VolumeInfo`` (``.volume_id`` names it in later calls).
        """
        from unwind_services._proto.unwind.v1 import volume_pb2
        from unwind_services.convert import dtype_enum
        from unwind_services.ingest import encode_chunk, encoder

        from .io import Volume, as_volume, open_volume

        source = None  # an in-memory array is sent slab by slab as it is, without a dask copy of it
        if isinstance(data, (str, os.PathLike)):
            path = Path(data)
            volume = open_volume(path, **reader_options)
            name = name or path.name.split(".")[0]
        elif isinstance(data, np.ndarray):
            source = data
            volume = Volume(_lazy(source).astype(source.dtype.newbyteorder("=")))  # checks shape and dtype
            name = name or "upload"
        else:  # a Volume, a dask, zarr... array: read slab by slab
            volume = as_volume(data)
            name = name or "upload"
        volume = as_volume(volume, spacing=spacing, unit=unit, origin=origin)
        header = volume_pb2.UploadHeader(
            name=name, shape=list(volume.shape), dtype=dtype_enum(volume.dtype), spacing=list(volume.spacing),
            unit=volume.unit or "", origin=list(volume.origin),
            labels=labels)
        le = volume.dtype.newbyteorder("<")
        plane = int(np.prod(volume.shape[1:])) * le.itemsize
        if source is None:
            source = volume.data
            step = max(1, int(source.chunks[0][0]))
        else:
            step = max(1, _SLAB_BYTES // plane)

        if format not in ("chunks", "raw"):
            raise InvalidInputError(f"format must be \"chunks\" or \"raw\", got {format!r}")
        codec = None
        if format == "chunks" and _CRC32C is not None and self._max_message >= 64 * 1024**2:
            from .io.ome_zarr import ChunkCodec

            codec = ChunkCodec(volume.shape, le)
            if codec.max_bytes + 16 > self._max_message:
                codec = None

        piece = _CHUNK  # bytes of voxels a raw message: less for a server whose message limit is below it

        def raw_messages() -> Iterator[Any]:
            yield volume_pb2.UploadRequest(header=header)
            for block in _slabs(source, le, step):
                mv = memoryview(block).cast("B")
                for a in range(0, len(mv), piece):
                    yield encode_chunk(mv[a:a + piece])  # encoded here: one copy, not protobuf's three

        def chunk_messages() -> Iterator[Any]:
            chunked = volume_pb2.UploadHeader()
            chunked.CopyFrom(header)
            chunked.format, chunked.chunk_shape[:] = "chunks", codec.grid
            yield volume_pb2.UploadRequest(header=chunked)
            yield from _encoded_chunks(source, le, codec)

        upload = self._channel.stream_unary("/unwind.v1.VolumeService/Upload",
                                            request_serializer=encoder(volume_pb2.UploadRequest),
                                            response_deserializer=volume_pb2.VolumeInfo.FromString)
        slot_grace = 0.0
        if codec is not None:
            try:
                return self._retrying(lambda: upload(chunk_messages(), timeout=timeout, metadata=self._metadata),
                                      "upload: ")
            except RemoteError as exc:
                too_large = exc.code == "RESOURCE_EXHAUSTED" and "larger than max" in str(exc)  # gRPC's own limit
                if not (too_large or (exc.code == "INVALID_ARGUMENT" and any(m in str(exc) for m in _RAW_ONLY_SERVER))):
                    raise
                # a server of an earlier version took the chunks for raw voxels and refused their count, or a
                # chunk is over the server's message limit: send raw. The refused upload may still hold this
                # user's upload slot for a moment on a server that counts it until its handler ends (gRPC itself
                # cut the call, and the handler, late on a busy server, has yet to notice): a refusal for that is
                # retried for a few seconds, every other error is raised as it is.
                slot_grace = _SLOT_GRACE
                piece = _piece_within(exc, piece) or piece  # raw messages within the limit gRPC named, if it did
        end = time.monotonic() + slot_grace
        while True:
            try:
                return self._retrying(lambda: upload(raw_messages(), timeout=timeout, metadata=self._metadata),
                                      "upload: ")
            except RemoteError as exc:
                if smaller := _piece_within(exc, piece):
                    # gRPC refused a raw message over the server's limit, and said the limit: send smaller
                    # messages (raw voxels may be cut anywhere); the refused call may hold the slot a moment
                    piece, end = smaller, time.monotonic() + _SLOT_GRACE
                    continue
                if not (exc.code == "RESOURCE_EXHAUSTED" and "uploads in progress" in str(exc)
                        and time.monotonic() < end):
                    raise
            time.sleep(0.2)

    def register(self, path: str, *, name: str = ""):
        """Register a scan already under the server's data root (``path`` relative to it)."""
        from unwind_services._proto.unwind.v1 import volume_pb2

        return self._unary(self.volumes_stub.Register, volume_pb2.RegisterRequest(path=str(path), name=name))

    def volumes(self, limit: int = 100) -> list:
        from unwind_services._proto.unwind.v1 import volume_pb2

        return list(self._unary(self.volumes_stub.List, volume_pb2.ListVolumesRequest(limit=limit)).volumes)

    def info(self, volume_id: str):
        from unwind_services._proto.unwind.v1 import volume_pb2

        return self._unary(self.volumes_stub.Info, volume_pb2.VolumeRef(volume_id=volume_id))

    def _download_stream(self, volume_id: str, fmt: str, level: int, timeout: float) -> tuple[Any, Iterator[Any]]:
        """The download's header, and its chunks as bytes-like objects (memoryviews, not copied out of messages)."""
        from unwind_services._proto.unwind.v1 import volume_pb2
        from unwind_services.ingest import decoder

        request = volume_pb2.DownloadRequest(volume_id=volume_id, format=fmt, level=level)
        download = self._channel.unary_stream("/unwind.v1.VolumeService/Download",
                                              request_serializer=volume_pb2.DownloadRequest.SerializeToString,
                                              response_deserializer=decoder(volume_pb2.DownloadResponse))

        def start():
            stream = download(request, timeout=timeout, metadata=self._metadata)
            first = next(stream)
            return first, stream

        first, stream = self._retrying(start, "download: ")
        if isinstance(first, memoryview) or first.WhichOneof("part") != "header":
            stream.cancel()
            raise RemoteError("download: the server's stream did not start with a header", "DATA_LOSS")

        def chunks() -> Iterator[Any]:
            import grpc

            try:
                for msg in stream:
                    yield msg if isinstance(msg, memoryview) else msg.chunk
            except grpc.RpcError as exc:
                raise _remote_error(exc, "download: ") from None

        return first.header, chunks()

    def open(self, volume_id: str, *, level: int = 0, timeout: float = 3600.0):
        """Download a volume's voxels into memory: a :class:`~napari_unwind.io.Volume` with its geometry."""
        from unwind_services.convert import dtype_of

        from .io import Volume

        # the stored chunks when they can come (the server sends raw otherwise): one blosc stream a message
        fmt = "chunks" if _CRC32C is not None and self._max_message >= 64 * 1024**2 else "raw"
        header, chunks = self._download_stream(volume_id, fmt, level, timeout)
        dtype = dtype_of(header.dtype).newbyteorder("<")
        shape = tuple(int(n) for n in header.shape)
        total = int(np.prod(shape)) * dtype.itemsize
        if header.total_bytes != total:
            raise RemoteError(f"download: the server announced {header.total_bytes} bytes for a {shape} "
                              f"{dtype.name} volume ({total} bytes)", "DATA_LOSS")
        if header.format == "chunks":
            arr = _receive_chunks(header, chunks, shape, dtype)
        else:
            arr = np.empty(shape, dtype=dtype)
            buf = memoryview(arr).cast("B")  # every chunk is copied once, into its place
            pos = 0
            for c in chunks:
                n = len(c)
                if pos + n > total:
                    raise RemoteError(f"download: the server sent more than the {total} bytes it announced",
                                      "DATA_LOSS")
                buf[pos:pos + n] = c
                pos += n
            if pos != total:
                raise RemoteError(f"download: the server sent {pos} bytes of {total}", "DATA_LOSS")
        arr = arr.astype(dtype.newbyteorder("="), copy=False)
        return Volume(_lazy(arr), spacing=tuple(header.spacing), unit=header.unit or None,
                      origin=tuple(header.origin))

    def download(self, volume_id: str, path: str | os.PathLike, *, level: int = 0, overwrite: bool = False,
                 timeout: float = 3600.0) -> Path:
        """Download a volume into ``path``; its suffix chooses the format, written on the server by the core.

        The file (or folder) appears atomically.
        """
        from .io._atomic import atomic_output, check_writable
        from .io._formats import output_format

        path = Path(path)
        output_format(path)
        check_writable(path, overwrite=overwrite)
        suffix = "".join(path.suffixes[-2:]) if path.name.lower().endswith(".nii.gz") else path.suffix
        header, chunks = self._download_stream(volume_id, suffix, level, timeout)
        with atomic_output(path, overwrite=overwrite) as tmp:
            blob = tmp.with_name(tmp.name + ".part")
            try:
                with open(blob, "wb") as f:
                    for c in chunks:
                        f.write(c)
                if blob.stat().st_size != header.total_bytes:
                    raise RemoteError(f"download: the server sent {blob.stat().st_size} bytes of "
                                      f"{header.total_bytes}", "DATA_LOSS")
                if header.tar:
                    unpack = tmp.with_name(tmp.name + ".d")
                    with tarfile.open(blob) as tar:
                        tar.extractall(unpack, filter="data")
                    inner = unpack / header.file_name
                    os.replace(inner if inner.exists() else unpack, tmp)
                    shutil.rmtree(unpack, ignore_errors=True)
                else:
                    os.replace(blob, tmp)
            finally:
                blob.unlink(missing_ok=True)
        return path

    # -- jobs --------------------------------------------------------------------------------------------------------
    def submit(self, request: Any, *, wait: bool = True, name: str = "", timeout_seconds: float = 0.0):
        """Submit a ``SubmitRequest`` (safe to retry: it carries a request id); with ``wait``, follow it."""
        if not request.request_id:
            request.request_id = uuid.uuid4().hex
        if name:
            request.name = name
        if timeout_seconds:
            request.timeout_seconds = timeout_seconds
        job = self._unary(self.jobs_stub.Submit, request, "submit: ")
        return self.wait(job.id) if wait else job

    def job(self, job_id: str):
        from unwind_services._proto.unwind.v1 import jobs_pb2

        return self._unary(self.jobs_stub.Get, jobs_pb2.JobRef(job_id=job_id))

    def jobs(self, state: int = 0, limit: int = 100) -> list:
        from unwind_services._proto.unwind.v1 import jobs_pb2

        return list(self._unary(self.jobs_stub.List, jobs_pb2.ListJobsRequest(state=state, limit=limit)).jobs)

    def cancel(self, job_id: str):
        from unwind_services._proto.unwind.v1 import jobs_pb2

        return self._unary(self.jobs_stub.Cancel, jobs_pb2.JobRef(job_id=job_id))

    def resubmit(self, job_id: str, *, wait: bool = False):
        from unwind_services._proto.unwind.v1 import jobs_pb2

        job = self._unary(self.jobs_stub.Resubmit, jobs_pb2.JobRef(job_id=job_id))
        return self.wait(job.id) if wait else job

    def watch(self, job_id: str, *, timeout: float | None = None) -> Iterator[Any]:
        """The job's events (``JobEvent``: progress records, then the final job), reconnecting after a server restart
        and resuming after the last record received. Ends with the finished job."""
        import grpc

        from unwind_services._proto.unwind.v1 import common_pb2 as pb
        from unwind_services._proto.unwind.v1 import jobs_pb2

        after = 0
        end = None if timeout is None else time.monotonic() + timeout
        outage: float | None = None
        delay = 0.2
        while True:
            left = None if end is None else max(0.01, end - time.monotonic())
            try:
                stream = self.jobs_stub.Watch(jobs_pb2.WatchRequest(job_id=job_id, after_seq=after),
                                              timeout=left or 86400, metadata=self._metadata)
                for event in stream:
                    outage, delay = None, 0.2
                    if event.HasField("progress"):
                        after = event.progress.seq
                    yield event
                    if event.HasField("job") and event.job.state in (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED,
                                                                     pb.JOB_STATE_CANCELLED):
                        return
            except grpc.RpcError as exc:
                if exc.code() != grpc.StatusCode.UNAVAILABLE:
                    raise _remote_error(exc, f"watch {job_id}: ") from None
                outage = outage or time.monotonic()
                if time.monotonic() - outage > self.retry_seconds:
                    raise _remote_error(exc, f"watch {job_id}: ") from None
                time.sleep(delay * (0.5 + random.random()))
                delay = min(delay * 2, 5.0)

    def wait(self, job_id: str, *, progress: bool | None = None, timeout: float | None = None, check: bool = True):
        """Follow a job to its end (tqdm bars from its progress); returns it, or raises :class:`RemoteError` when it
        failed or was cancelled (with ``check``)."""
        from unwind_services._proto.unwind.v1 import common_pb2 as pb

        callback, close = progress_bar(not (self.progress if progress is None else progress))
        job = None
        try:
            for event in self.watch(job_id, timeout=timeout):
                if event.HasField("progress"):
                    callback(_progress(event.progress))
                else:
                    job = event.job
        finally:
            close()
        if check and job.state != pb.JOB_STATE_SUCCEEDED:
            raise RemoteError(f"job {job.id} {pb.JobState.Name(job.state)[10:].lower()}: {job.error.message}",
                              job.error.code or "UNKNOWN", job)
        return job

    @staticmethod
    def session(job: Any):
        """The :class:`~napari_unwind.session.Session` a skeleton or pipeline job produced."""
        from .session import Session

        if not job.result.session_json:
            raise InvalidInputError(f"job {job.id} produced no session")
        return Session.from_dict(_server_json(job.result.session_json, "the session"))

    @staticmethod
    def specimen(job: Any, **fields_: Any):
        """The pipeline's verdict on the specimen of a skeleton or pipeline job: a
        :class:`~napari_unwind.pipeline.SpecimenResult` with its status (``ok`` or ``partial``, judged on the server by
        :func:`napari_unwind.pipeline.judge` as on this computer), reason, figures (coverage, folded, lost,
        length...) and warnings; ``fields_`` set the others (session, output...). A result without a verdict raises
        :class:`~napari_unwind.errors.InvalidInputError`: it is never read as ok."""
        from unwind_services.convert import specimen_result

        try:
            return specimen_result(job.result, **fields_)
        except InvalidInputError as exc:
            raise InvalidInputError(f"job {job.id}: {exc}") from None

    # -- the pipeline's steps ----------------------------------------------------------------------------------------
    def segment(self, volume_id: str, *, features: int = 5, level: int | None = None, smooth: float | None = None,
                wait: bool = True):
        """Join tree + simplification (a job); its result names the segmentation (``result.segmentation_id``)."""
        from unwind_services._proto.unwind.v1 import jobs_pb2, segmentation_pb2

        req = segmentation_pb2.SegmentRequest(volume_id=volume_id, features=features, level=level or 0,
                                              has_level=level is not None, smooth=smooth or 0.0,
                                              has_smooth=smooth is not None)
        return self.submit(jobs_pb2.SubmitRequest(segment=req), wait=wait)

    def segmentation(self, segmentation_id: str):
        """The segmentation's ``SegmentationInfo``: its current features, their statistics, their label volume."""
        from unwind_services._proto.unwind.v1 import segmentation_pb2

        return self._unary(self.segmentation_stub.Info,
                           segmentation_pb2.SegmentationRef(segmentation_id=segmentation_id))

    def simplify(self, segmentation_id: str, features: int):
        """Keep another number of features, from the server's cached join tree (no rebuild); returns the
        ``SegmentationInfo`` (its ``labels_volume_id`` is their label volume; :meth:`features` downloads them)."""
        from unwind_services._proto.unwind.v1 import segmentation_pb2

        return self._unary(self.segmentation_stub.Simplify,
                           segmentation_pb2.SimplifyRequest(segmentation_id=segmentation_id, features=features))

    def features(self, segmentation_id: str, k: int | None = None, *, timeout: float = 3600.0):
        """The features of a segmentation on this computer: :class:`~napari_unwind.segmentation.Features` (the
        label volume at working resolution and every feature's statistics, without the join tree).

        ``k`` features are kept on the server first (:meth:`simplify`; it becomes the segmentation's current
        number); ``None`` takes the current ones (:meth:`segmentation`). The label volume is written once per
        ``k`` on the server and downloaded here; the result is what
        :func:`napari_unwind.segmentation.load_features` gives for the same segmentation saved locally, so
        ``select``, ``refine_mask``, ``ids_at`` and ``nearest_feature`` work on it (an isovalue at working
        resolution needs the tree: refine at full resolution instead).
        """
        from .segmentation import Features

        info = self.segmentation(segmentation_id) if k is None else self.simplify(segmentation_id, k)
        labels = self.open(info.labels_volume_id, timeout=timeout)
        return Features.from_labels(np.asarray(labels.data), _server_json(info.features_json, "the features"))

    def select(self, segmentation_id: str, *, seeds: Any = None, ids: Sequence[int] | None = None,
               fill_holes: bool = False, isovalue: float | None = None, output_name: str = "",
               features: int | None = None, wait: bool = True):
        """The chosen features refined to a full-resolution mask (a job; ``result.volume_id`` is the mask).

        ``features``: the number of features the ids and seeds refer to (one :meth:`simplify` made; default: the
        segmentation's current one). Without ``isovalue`` the mask is cut at
        :func:`napari_unwind.segmentation.default_isovalue` of the features it covers, read from the scan, as
        :func:`napari_unwind.segmentation.refine_mask` does on this computer.
        """
        from unwind_services._proto.unwind.v1 import jobs_pb2, segmentation_pb2

        req = segmentation_pb2.SelectRequest(segmentation_id=segmentation_id, seeds=_points(seeds, "seed"),
                                             ids=list(ids or ()), fill_holes=fill_holes, isovalue=isovalue or 0.0,
                                             has_isovalue=isovalue is not None, output_name=output_name,
                                             features=features or 0)
        return self.submit(jobs_pb2.SubmitRequest(select=req), wait=wait)

    def suggest_ends(self, mask_volume_id: str, volume_id: str = "") -> tuple[np.ndarray, np.ndarray]:
        from unwind_services._proto.unwind.v1 import skeleton_pb2

        e = self._unary(self.skeleton_stub.SuggestEnds,
                        skeleton_pb2.SuggestEndsRequest(mask_volume_id=mask_volume_id, volume_id=volume_id))
        return (np.array([e.head.axis0, e.head.axis1, e.head.axis2]),
                np.array([e.tail.axis0, e.tail.axis1, e.tail.axis2]))

    @staticmethod
    def _ends(head: Any, tail: Any, chain: Any = None):
        from unwind_services._proto.unwind.v1 import skeleton_pb2

        if head is None and tail is None:
            return None
        if head is None or tail is None:
            raise InvalidInputError("give both head and tail, or neither to use the suggested ones")
        msg = skeleton_pb2.Ends(head=_points([head], "head")[0], tail=_points([tail], "tail")[0])
        for a, b in chain or ():
            msg.chain.add(start=_points([a], "chain")[0], end=_points([b], "chain")[0])
        return msg

    @staticmethod
    def _skeleton_options(options: Any = None, **given: Any):
        """The SkeletonOptions message of a :class:`~napari_unwind.pipeline.SkeletonOptions` or of its fields
        (``no_twist`` and ``levels`` are accepted for ``estimate_twist`` and ``n_levels``; the rest default)."""
        from unwind_services import convert

        from .pipeline import SkeletonOptions

        if options is None:
            if "no_twist" in given:
                given["estimate_twist"] = not given.pop("no_twist")
            if "levels" in given:
                given["n_levels"] = given.pop("levels")
            options = SkeletonOptions(**{k: v for k, v in given.items() if v is not None})
        elif given:
            raise InvalidInputError("give either SkeletonOptions or its fields, not both")
        return convert.skeleton_options_msg(options)

    @staticmethod
    def _export_options(output_name: str = "", options: Any = None, **given: Any):
        """The ExportOptions message of a :class:`~napari_unwind.pipeline.ExportOptions` or of its fields."""
        from unwind_services import convert

        from .pipeline import ExportOptions

        if options is None:
            options = ExportOptions(**{k: v for k, v in given.items() if v is not None})
        elif given:
            raise InvalidInputError("give either ExportOptions or its fields, not both")
        return convert.export_options_msg(options, output_name)

    def skeleton(self, mask_volume_id: str, *, volume_id: str = "", head: Any = None, tail: Any = None,
                 chain: Any = None, wait: bool = True, **options: Any):
        """Skeleton solve (a job); ``Client.session(job)`` is the resulting session, ``Client.specimen(job)`` the
        pipeline's verdict on it (status ok or partial, reason, coverage, folds)."""
        from unwind_services._proto.unwind.v1 import jobs_pb2, skeleton_pb2

        req = skeleton_pb2.EstimateDeformationRequest(mask_volume_id=mask_volume_id, volume_id=volume_id,
                                                      ends=self._ends(head, tail, chain),
                                                      options=self._skeleton_options(**options))
        return self.submit(jobs_pb2.SubmitRequest(estimate_deformation=req), wait=wait)

    def straighten(self, volume_id: str, session_id: str, *, channels: dict[str, str] | None = None,
                   scan_name: str = "", wait: bool = True, **export: Any):
        """Export the straight volume (a job; ``result.volume_id``). ``channels`` maps a name to the volume id of
        another image of the scan's grid: all are straightened in one pass into one multi-channel output
        (OME-Zarr with a ``c`` axis; the scan is channel 0, named ``scan_name`` or "scan")."""
        from unwind_services._proto.unwind.v1 import jobs_pb2, warp_pb2

        req = warp_pb2.StraightenRequest(volume_id=volume_id, session_id=session_id,
                                         options=self._export_options(**export), scan_name=scan_name,
                                         channels=[warp_pb2.MeasureChannel(name=n, volume_id=v)
                                                   for n, v in (channels or {}).items()])
        return self.submit(jobs_pb2.SubmitRequest(straighten=req), wait=wait)

    def measure(self, session_id: str, *, mask_volume_id: str = "", labels_volume_id: str = "",
                channels: dict[str, str] | None = None, spacing: float | None = None, wait: bool = True):
        """Measure along the session's centreline (a job; ``result.table_csv``: the CSV ``unwind measure``
        writes). ``channels`` maps a column name to a volume id; every volume on the session's scan grid."""
        from unwind_services._proto.unwind.v1 import jobs_pb2, warp_pb2

        req = warp_pb2.MeasureRequest(session_id=session_id, mask_volume_id=mask_volume_id,
                                      labels_volume_id=labels_volume_id, spacing=float(spacing or 0.0),
                                      channels=[warp_pb2.MeasureChannel(name=n, volume_id=v)
                                                for n, v in (channels or {}).items()])
        return self.submit(jobs_pb2.SubmitRequest(measure=req), wait=wait)

    def average(self, volume_ids: Sequence[str], *, landmarks: Sequence[Sequence[float]] | None = None,
                stations: int | None = None, scale: str = "length", normalise: str = "robust",
                max_roll: float = 90.0, output_name: str = "", wait: bool = True):
        """The average straight specimen of a batch of straight volumes (a job, :func:`napari_unwind.average.average`
        on the server): ``result.volumes`` maps "mean", "median" and "std" to stored volumes (the mean is also
        ``result.volume_id``), ``result.table_csv`` holds the residual per specimen. ``landmarks``: per volume, in
        order, its K positions along s (arc length, the volumes' unit)."""
        from unwind_services._proto.unwind.v1 import jobs_pb2, warp_pb2

        from .average import NORMALISATIONS, SCALES

        if scale not in SCALES or normalise not in NORMALISATIONS:
            raise InvalidInputError(f"scale must be one of {', '.join(SCALES)} and normalise one of "
                                    f"{', '.join(NORMALISATIONS)}, got {scale!r}, {normalise!r}")
        if landmarks is not None and len(landmarks) != len(volume_ids):
            raise InvalidInputError(f"landmarks has {len(landmarks)} rows for {len(volume_ids)} volumes: one row "
                                    "per volume, in order")
        req = warp_pb2.AverageRequest(
            specimens=[warp_pb2.AverageSpecimen(volume_id=v, landmarks=list(landmarks[i]) if landmarks else [])
                       for i, v in enumerate(volume_ids)],
            stations=int(stations or 0), keep_size=scale == "none", keep_grey_values=normalise == "none",
            max_roll=float(max_roll), has_max_roll=True, output_name=output_name)
        return self.submit(jobs_pb2.SubmitRequest(average=req), wait=wait)

    def bend(self, volume_id: str, session_id: str, *, order: int = 1, output_name: str = "", wait: bool = True):
        """Bend a straight volume into the session's pose (a job; ``result.volume_id``)."""
        from unwind_services._proto.unwind.v1 import jobs_pb2, warp_pb2

        req = warp_pb2.BendRequest(volume_id=volume_id, session_id=session_id, order=order, has_order=True,
                                   output_name=output_name)
        return self.submit(jobs_pb2.SubmitRequest(bend=req), wait=wait)

    def map_points(self, session_id: str, points: Any, *, to: str = "straight", spacing: float | None = None,
                   pad: int = 0, timeout: float | None = None) -> np.ndarray:
        """Carry points between the scan and the straight volume on the server (``napari_unwind.warp.map_points``).

        Up to :data:`MAP_BATCH` points go in one MapPoints call; more stream through MapPointsStream in batches of
        that many, so neither side holds more than a batch of messages (``timeout``: for the whole call, default
        the client's timeout per batch). A server whose message limit is below a batch gets batches within it.
        """
        from unwind_services._proto.unwind.v1 import warp_pb2

        if to not in ("straight", "scan"):
            raise InvalidInputError(f"to must be 'straight' or 'scan', got {to!r}")
        direction = warp_pb2.MAP_DIRECTION_TO_SCAN if to == "scan" else warp_pb2.MAP_DIRECTION_TO_STRAIGHT
        arr = np.asarray(points, dtype=float).reshape(-1, 3)
        options = dict(session_id=session_id, direction=direction, spacing=spacing or 0.0, pad=pad)
        batch = MAP_BATCH
        while True:
            try:
                return self._map_batches(arr, options, batch, timeout)
            except RemoteError as exc:
                # gRPC refused a message over the server's limit, and said the limit: batches that fit it
                limit = _message_limit(exc)
                smaller = None if limit is None else (limit - 1024) // 24  # 3 doubles a point
                if smaller is None or not 1000 <= smaller < batch:
                    raise
                batch = smaller

    def _map_batches(self, arr: np.ndarray, options: dict, batch: int, timeout: float | None) -> np.ndarray:
        from unwind_services._proto.unwind.v1 import warp_pb2

        batches = max(1, -(-len(arr) // batch))
        timeout = timeout or self.timeout * batches
        if batches == 1:
            r = self._unary(self.warp_stub.MapPoints, warp_pb2.MapPointsRequest(
                coords=arr.ravel().tolist(), **options), timeout=timeout)
            return np.asarray(r.coords, dtype=float).reshape(-1, 3)

        def requests() -> Iterator[Any]:
            for a in range(0, len(arr), batch):
                yield warp_pb2.MapPointsRequest(coords=arr[a:a + batch].ravel().tolist(),
                                                **(options if a == 0 else {}))

        def stream() -> np.ndarray:
            out = np.empty_like(arr)
            at = 0
            for r in self.warp_stub.MapPointsStream(requests(), timeout=timeout, metadata=self._metadata):
                got = np.asarray(r.coords, dtype=float).reshape(-1, 3)
                out[at:at + len(got)] = got
                at += len(got)
            if at != len(arr):
                raise RemoteError(f"map points: the server answered {at} of {len(arr)} points", "INTERNAL")
            return out

        return self._retrying(stream, "map points: ")

    def pipeline_request(self, volume_id: str, *, select: Any = None, ids: Sequence[int] | None = None,
                         segmentation_id: str = "", mask_volume_id: str = "", features: int | None = None,
                         level: int | None = None, isovalue: float | None = None, fill_holes: bool = False,
                         head: Any = None, tail: Any = None, chain: Any = None, skeleton: dict | None = None,
                         options: Any = None, output_name: str = "", **export: Any):
        """The ``SubmitRequest`` of :meth:`pipeline` (for :meth:`submit` with other options).

        ``options`` (a :class:`~napari_unwind.pipeline.PipelineOptions`) gives every option at once, instead of
        ``features``, ``level``, ``isovalue``, ``fill_holes``, ``skeleton`` (a dict of SkeletonOptions fields) and
        the export keywords (``order``, ``spacing``, ``pad``, ``chunks``, ``allow_folds``).
        """
        from unwind_services._proto.unwind.v1 import jobs_pb2

        from .pipeline import PipelineOptions, SegmentOptions

        if options is None:
            options = PipelineOptions(SegmentOptions(features=features, level=level, isovalue=isovalue,
                                                     fill_holes=bool(fill_holes)))
            skel, exp = self._skeleton_options(**(skeleton or {})), self._export_options(output_name, **export)
        elif not isinstance(options, PipelineOptions):
            raise InvalidInputError(f"options must be PipelineOptions, got {type(options).__name__}")
        elif skeleton or export or features is not None or level is not None or isovalue is not None or fill_holes:
            raise InvalidInputError("give either options=PipelineOptions(...) or the options one by one, not both")
        else:
            skel, exp = self._skeleton_options(options.skeleton), self._export_options(output_name, options.export)
        seg = options.segment
        req = jobs_pb2.PipelineRequest(
            volume_id=volume_id, select=_points(select, "select point"), ids=list(ids or ()),
            segmentation_id=segmentation_id, mask_volume_id=mask_volume_id, features=seg.features or 0,
            level=seg.level or 0, has_level=seg.level is not None, isovalue=seg.isovalue or 0.0,
            has_isovalue=seg.isovalue is not None, fill_holes=seg.fill_holes, ends=self._ends(head, tail, chain),
            skeleton=skel, export=exp)
        return jobs_pb2.SubmitRequest(pipeline=req)

    def pipeline(self, volume_id: str, *, wait: bool = True, name: str = "", **options: Any):
        """``unwind run`` on the server: segment (or a mask), select, skeleton, straighten (a job).

        Its result holds the straight volume (``result.volume_id``), the session (``Client.session(job)``), the
        pipeline's verdict (``result.verdict``; decoded by ``Client.specimen(job)``: status ``ok`` or ``partial``, see
        :mod:`napari_unwind.pipeline`, reason, coverage, folds...) and figures as text (length, keyframes,
        seconds...). Options: see :meth:`pipeline_request`.
        """
        return self.submit(self.pipeline_request(volume_id, **options), wait=wait, name=name)

    # -- collections -------------------------------------------------------------------------------------------------
    def run_batch(self, items: Iterable[BatchItem | dict], *, max_parallel: int = 4, out_dir: str | os.PathLike | None
                  = None, suffix: str = ".zarr", summary: str | os.PathLike | None = None, retries: int = 1,
                  progress: bool = False, measure: bool = False) -> list[dict[str, str]]:
        """Straighten a collection: every item is a scan plus a selection (or ``"all"`` for a tank).

        Up to ``max_parallel`` pipelines run at once. The batch outlives a server restart: every call is retried
        while the server is UNAVAILABLE (for ``retry_seconds``), watching resumes where it stopped, a job that the
        restart interrupted (or whose dask cluster lost its work: UNAVAILABLE) is resubmitted, up to ``retries``
        times, and a job that had finished is never run again (its output is fetched). With ``out_dir`` every
        straight volume (``suffix`` format) and its session are downloaded. Returns one summary row per specimen
        and writes them as CSV to ``summary`` (default ``out_dir/summary.csv`` when ``out_dir`` is given): name,
        scan, job, state, the specimen's status and reason (``ok`` or ``partial``: the pipeline's verdict; a
        ``partial`` specimen is not a success), figures, the ids of jobs that were interrupted and resubmitted
        (``resubmitted``), error.

        With ``measure``, each straightened specimen is also measured along its centreline (a Select job makes its
        full-resolution mask, as the pipeline refined it, then a Measure job), and the row gains the summary
        columns of :func:`profile_summary` (curvature, area, equivalent radius, volume; names with units);
        with ``out_dir`` the profile is saved as ``<name>.profile.csv``. A measurement that fails leaves the
        specimen's row as it was, with ``measure_error``.
        """
        from unwind_services._proto.unwind.v1 import common_pb2 as pb

        items = [_batch_item(i, k) for k, i in enumerate(items)]
        out = Path(out_dir) if out_dir is not None else None
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
        rows: list[dict[str, str]] = []
        lock = threading.Lock()

        def record(row: dict[str, Any]) -> None:
            with lock:
                rows.append({k: str(v) for k, v in row.items()})

        def again(fn: Callable[[], Any], what: str) -> Any:
            """``fn()`` again while the server is UNAVAILABLE (a stream cut by a restart is not retried inside)."""
            deadline = time.monotonic() + self.retry_seconds
            delay = 0.2
            while True:
                try:
                    return fn()
                except RemoteError as exc:
                    if exc.code != "UNAVAILABLE" or time.monotonic() + delay > deadline:
                        raise
                time.sleep(delay * (0.5 + random.random()))
                delay = min(delay * 2, 5.0)

        def follow(job: Any, resubmitted: list[str]) -> Any:
            """Wait for ``job``; resubmit it while a restart interrupts it (or the cluster loses it)."""
            for attempt in range(retries + 1):
                job = self.wait(job.id, progress=progress, check=False)
                lost = job.state == pb.JOB_STATE_FAILED and (job.interrupted or job.error.code == "UNAVAILABLE")
                if not lost or attempt == retries:
                    break
                resubmitted.append(job.id)
                job = self.resubmit(job.id)
            return job

        def volume_of(item: BatchItem) -> str:
            if item.register:
                return self.register(item.scan).volume_id
            if item.scan.startswith("vol-") and not Path(item.scan).exists():
                return item.scan
            return again(lambda: self.upload(item.scan, name=Path(item.scan).name.split(".")[0]).volume_id,
                         f"upload {item.scan}")

        def measured(item: BatchItem, name: str, job: Any, selection: dict[str, Any]) -> dict[str, Any]:
            """The specimen's mask (a Select job at the pipeline's isovalue), its profile (a Measure job), and the
            profile's summary columns."""
            figures = dict(job.result.figures)
            seg = selection.get("segmentation_id")
            if not seg:
                sj = follow(self.segment(selection["volume_id"], features=item.features, wait=False), [])
                if sj.state != pb.JOB_STATE_SUCCEEDED:
                    raise RemoteError(f"segmenting for the mask: {sj.error.message}", sj.error.code, sj)
                seg = sj.result.segmentation_id
            iso = float(figures["isovalue"]) if figures.get("isovalue") else None
            mj = follow(self.select(seg, seeds=selection.get("select"), ids=selection.get("ids"), isovalue=iso,
                                    features=item.features, output_name=f"{name}_mask.zarr", wait=False), [])
            if mj.state != pb.JOB_STATE_SUCCEEDED:
                raise RemoteError(f"the mask: {mj.error.message}", mj.error.code, mj)
            pj = follow(self.measure(job.result.session_id, mask_volume_id=mj.result.volume_id, wait=False), [])
            if pj.state != pb.JOB_STATE_SUCCEEDED:
                raise RemoteError(f"measuring: {pj.error.message}", pj.error.code, pj)
            if out is not None:
                (out / f"{name}.profile.csv").write_text(pj.result.table_csv)
            return {**profile_summary(pj.result.table_csv), "mask_volume_id": mj.result.volume_id}

        def one(item: BatchItem, name: str, scan_label: str, **selection: Any) -> None:
            row: dict[str, Any] = {"name": name, "scan": scan_label, "job": "", "state": "", "error": ""}
            resubmitted: list[str] = []
            try:
                request = self.pipeline_request(output_name=f"{name}{suffix}", **selection, **item.options)
                job = follow(self.submit(request, wait=False, name=name), resubmitted)
                row.update(job=job.id, state=pb.JobState.Name(job.state)[10:].lower(),
                           resubmitted=" ".join(resubmitted))
                if job.state != pb.JOB_STATE_SUCCEEDED:
                    row["error"] = f"{job.error.code}: {job.error.message}"
                else:
                    row.update(dict(job.result.figures))
                    verdict = self.specimen(job)  # the status a row reports is the pipeline's verdict
                    row.update(status=verdict.status, reason=verdict.reason)
                    row["volume_id"] = job.result.volume_id
                    if out is not None:
                        row["output"] = str(again(lambda: self.download(
                            job.result.volume_id, out / f"{name}{suffix}", overwrite=True), f"download {name}"))
                        (out / f"{name}.unwind.json").write_text(job.result.session_json)
                    if measure:
                        try:
                            row.update(measured(item, name, job, selection))
                        except (UnwindError, OSError) as exc:
                            row["measure_error"] = f"{getattr(exc, 'code', 'ERROR')}: {exc}"
            except (UnwindError, OSError) as exc:
                row.update(state="failed", error=f"{getattr(exc, 'code', 'ERROR')}: {exc}",
                           resubmitted=" ".join(resubmitted))
                row.pop("output", None)  # a download that failed left nothing behind: no output to name
            record(row)

        def prepare(item: BatchItem) -> list[tuple]:
            name = item.name or Path(item.scan).name.split(".")[0]
            vid = volume_of(item)
            if isinstance(item.select, str):
                if item.select != "all":
                    raise InvalidInputError(f"select must be points or 'all', got {item.select!r}")
                job = follow(self.segment(vid, features=item.features, wait=False), [])
                if job.state != pb.JOB_STATE_SUCCEEDED:
                    raise RemoteError(f"segmenting {item.scan}: {job.error.message}", job.error.code, job)
                seg = job.result.segmentation_id
                info = self.segmentation(seg)
                return [(item, f"{name}_f{f.id}", item.scan, dict(volume_id=vid, ids=[f.id], segmentation_id=seg))
                        for f in info.feature]
            return [(item, name, item.scan, dict(volume_id=vid, select=item.select, features=item.features))]

        with ThreadPoolExecutor(max_workers=max(1, max_parallel)) as pool:
            tasks: list[tuple] = []
            for item, fut in [(i, pool.submit(prepare, i)) for i in items]:
                try:
                    tasks += fut.result()
                except (UnwindError, OSError) as exc:
                    record({"name": item.name or Path(item.scan).name, "scan": item.scan, "job": "", "state": "failed",
                            "error": f"{getattr(exc, 'code', 'ERROR')}: {exc}"})
            for f in [pool.submit(one, it, n, s, **sel) for it, n, s, sel in tasks]:
                f.result()
        rows.sort(key=lambda r: r["name"])
        target = Path(summary) if summary is not None else (out / "summary.csv" if out is not None else None)
        if target is not None:
            columns = ["name", "scan", "job", "state", "status", "reason", "volume_id", "length", "unit", "keyframes",
                       "ids", "isovalue", "seconds", "skeleton_seconds", "export_seconds", "output", "resubmitted",
                       "error"]
            columns += list(dict.fromkeys(c for m in SUMMARY_MEASURES for r in rows for c in r
                                          if c.split(" [")[0] == m and c not in columns))
            columns += sorted({k for r in rows for k in r} - set(columns))
            with open(target, "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=columns, restval="")
                w.writeheader()
                w.writerows(rows)
        return rows
