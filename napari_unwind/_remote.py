"""The dock's "server" backend: progress generators that drive :class:`napari_unwind.client.Client`.

Each function is a generator of core :class:`~napari_unwind.progress.Progress` records that returns its result,
the shape :func:`._workers.start_job` runs in a worker (same progress bar, same Cancel); :func:`simplify` (the
feature slider) is a plain call the dock runs in its own worker. A server job is followed through
``Client.watch``; when the generator is closed before the job ended (Cancel), the job is cancelled on the server.
No Qt here; the client (grpcio, the ``server`` extra) is imported only when a server is used.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InvalidInputError
from .progress import Progress

__all__ = ["Server", "check_server", "upload_iter", "register_iter", "segment_iter", "simplify", "select_iter",
           "mask_volume", "suggest_ends_iter", "skeleton_iter", "export_iter"]


@dataclass(frozen=True)
class Server:
    """Where the dock's jobs run: ``host:port``, the bearer token, and the CA certificate for TLS (or None)."""

    address: str
    token: str | None = None
    ca: str | None = None

    def client(self, *, timeout: float = 60.0, retry_seconds: float = 10.0) -> Any:
        try:
            from .client import Client
        except ImportError as exc:
            raise InvalidInputError(f"the server backend needs the 'server' extra (grpcio): {exc}; install "
                                    "napari-unwind[server] or use 'this computer'") from None
        return Client(self.address, token=self.token or None, tls=self.ca or False, timeout=timeout,
                      retry_seconds=retry_seconds, progress=False)


def parse_server(address: str, token: str = "", ca: str = "") -> Server:
    """Check the dock's fields and build a :class:`Server`; ``token`` may be the path of a file holding it."""
    address = address.strip()
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise InvalidInputError(f"the server address must be host:port, got {address!r}; e.g. 127.0.0.1:50051")
    token = token.strip()
    if token and Path(token).expanduser().is_file():
        token = Path(token).expanduser().read_text().strip()
    ca = ca.strip()
    if ca and not Path(ca).expanduser().is_file():
        raise InvalidInputError(f"the CA certificate file does not exist: {ca!r}; give a PEM file or leave it empty "
                                "for a plain connection")
    return Server(address, token or None, str(Path(ca).expanduser()) if ca else None)


def check_server(server: Server, *, deadline: float = 5.0) -> Generator[Progress, None, str]:
    """Health and authentication of ``server`` within ``deadline`` seconds; returns the health status name.

    Raises :class:`~napari_unwind.client.RemoteError` (code UNAVAILABLE, UNAUTHENTICATED, ...) with one line.
    """
    from .client import RemoteError

    yield Progress("connect", 0, 1, server.address)
    with server.client(timeout=deadline, retry_seconds=0.0) as c:
        try:
            status = c.health()
            c.jobs(limit=1)  # health needs no token; this call checks it
        except RemoteError as exc:
            raise RemoteError(f"{exc.code}: {server.address}: {exc}", exc.code) from None
    yield Progress("connect", 1, 1)
    return status


def _follow(client: Any, job: Any, *, poll: float = 0.25) -> Generator[Progress, None, Any]:
    """Yield the job's progress until it ends; cancel it on the server when closed early (Cancel).

    The job's events are read in a thread; while none arrives (a queued job, a long step) the last record is
    yielded again every ``poll`` seconds, so the dock's Cancel (seen at a yield) acts within ``poll`` seconds.
    """
    import queue
    import threading

    from unwind_services._proto.unwind.v1 import common_pb2 as pb

    from .client import RemoteError, _progress

    _FINAL = (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED, pb.JOB_STATE_CANCELLED)
    events: queue.Queue = queue.Queue()

    def pump() -> None:
        try:
            for event in client.watch(job.id):
                events.put(("event", event))
            events.put(("end", None))
        except Exception as exc:  # noqa: BLE001 - handed to the generator (or dropped once it was closed)
            events.put(("error", exc))

    threading.Thread(target=pump, daemon=True, name=f"watch {job.id}").start()
    final, last = None, None
    try:
        while True:
            try:
                kind, item = events.get(timeout=poll)
            except queue.Empty:
                if last is not None:
                    yield last  # nothing new: a point where Cancel is seen
                continue
            if kind == "error":
                raise item
            if kind == "end":
                break
            if item.HasField("progress"):
                last = _progress(item.progress)
                yield last
            else:
                final = item.job
                if final.state not in _FINAL:  # the job as it stands (queued): a point where Cancel is seen
                    last = Progress("server job", 0, 0, pb.JobState.Name(final.state)[10:].lower())
                    yield last
    finally:
        if final is None or final.state not in _FINAL:
            try:
                client.cancel(job.id)
            except RemoteError:
                pass
    if final is None or final.state != pb.JOB_STATE_SUCCEEDED:
        state = pb.JobState.Name(final.state)[10:].lower() if final is not None else "lost"
        message = final.error.message if final is not None else "the server ended the job's stream"
        raise RemoteError(f"server job {job.id} {state}: {message}",
                          (final.error.code if final is not None else "") or "UNKNOWN", final)
    return final


def upload_iter(server: Server, volume: Any, *, labels: bool = False, name: str = "scan"
                ) -> Generator[Progress, None, str]:
    """Upload a :class:`~napari_unwind.io.Volume` (or a mask with its geometry); returns the server's volume id."""
    yield Progress("upload", 0, 1, f"{name} to {server.address}")
    with server.client(timeout=3600.0) as c:
        info = c.upload(volume, name=name, labels=labels)
    yield Progress("upload", 1, 1)
    return info.volume_id


def register_iter(server: Server, path: str, volume: Any, *, name: str = "scan") -> Generator[Progress, None, str]:
    """Register the scan at ``path`` (relative to the server's data root) instead of uploading it; it must be the
    dock's scan (same shape and spacing). Returns the server's volume id."""
    yield Progress("register", 0, 1, f"{path} on {server.address}")
    with server.client() as c:
        info = c.register(path, name=name)
    shape, spacing = tuple(info.shape), tuple(info.spacing)
    if shape != tuple(volume.shape) or not np.allclose(spacing, volume.spacing, rtol=1e-6):
        raise InvalidInputError(f"the server's {path} holds {shape} voxels of spacing {spacing}, the scan here "
                                f"{tuple(volume.shape)} of spacing {tuple(volume.spacing)}: give the server's path of "
                                "this scan, or leave 'path on server' empty to upload it")
    yield Progress("register", 1, 1)
    return info.volume_id


def segment_iter(server: Server, volume_id: str, *, features: int, level: int | None = None
                 ) -> Generator[Progress, None, tuple[str, int, Any]]:
    """The Segment job on the server (join tree + ``features`` features), then its features downloaded.

    Returns (the segmentation's id, the maxima of its tree (0: unknown), the
    :class:`~napari_unwind.segmentation.Features` without the tree).
    """
    with server.client() as c:
        job = c.segment(volume_id, features=features, level=level, wait=False)
        done = yield from _follow(c, job)
        seg = done.result.segmentation_id
        yield Progress("download", 0, 1, "the features' labels")
        maxima = int(c.segmentation(seg).maxima)
        result = c.features(seg)
    yield Progress("download", 1, 1)
    return seg, maxima, result


def simplify(server: Server, segmentation_id: str, k: int) -> Any:
    """``k`` features of the server's segmentation (Simplify there, its label volume downloaded): Features."""
    with server.client() as c:
        return c.features(segmentation_id, k)


def select_iter(server: Server, segmentation_id: str, ids: Any, k: int) -> Generator[Progress, None, str]:
    """The Select job on the server: features ``ids`` of its ``k`` features refined into a full-resolution mask
    (refine_mask's default isovalue, as on this computer); returns the mask's volume id."""
    with server.client() as c:
        job = c.select(segmentation_id, ids=[int(i) for i in ids], features=int(k), wait=False,
                       output_name="selection.zarr")
        done = yield from _follow(c, job)
    return done.result.volume_id


def mask_volume(mask: Any, volume: Any) -> Any:
    """A mask computed on this computer as a Volume with the scan's geometry (to upload it)."""
    from .io import as_volume

    return as_volume(mask.astype(np.uint8), spacing=volume.spacing, unit=volume.unit, origin=volume.origin)


def suggest_ends_iter(server: Server, volume_id: str, mask_id: str) -> Generator[Progress, None, tuple]:
    """Suggest head and tail of the server's mask ``mask_id`` on the server; returns (head, tail)."""
    yield Progress("ends", 0, 1, "longest geodesic (server)")
    with server.client() as c:
        head, tail = c.suggest_ends(mask_id, volume_id)
    yield Progress("ends", 1, 1)
    return tuple(head), tuple(tail)


def skeleton_iter(server: Server, volume_id: str, mask_id: str, ends: Any, *, options: Any = None
                  ) -> Generator[Progress, None, Any]:
    """The skeleton job on the server with ``options`` (a :class:`~napari_unwind.pipeline.SkeletonOptions`; None:
    its defaults); returns (its Session, the stored session's id, the pipeline's verdict: a
    :class:`~napari_unwind.pipeline.SpecimenResult` with the status, reason, figures and warnings the server's
    pipeline judged)."""
    from .client import Client

    kw: dict[str, Any] = {}
    if ends is not None:
        kw = dict(head=ends.head, tail=ends.tail, chain=ends.chain or None)
    with server.client() as c:
        job = c.skeleton(mask_id, volume_id=volume_id, wait=False, options=options, **kw)
        done = yield from _follow(c, job)
    session = Client.session(done)
    return session, done.result.session_id, Client.specimen(done, session=session)


def export_iter(server: Server, volume_id: str, session_id: str, target: Path, *, options: Any = None,
                overwrite: bool = False, channels: dict[str, str] | None = None,
                scan_name: str = "") -> Generator[Progress, None, Path]:
    """Straighten on the server (a job) with ``options`` (a :class:`~napari_unwind.pipeline.ExportOptions`; None:
    its defaults), then download the result to ``target`` (atomically); returns ``target``. ``channels`` (name to
    volume id of other images of the scan's grid) make it one multi-channel image, the scan named ``scan_name``."""
    from .io._atomic import check_writable
    from .io._formats import output_format

    output_format(target)
    check_writable(target, overwrite=overwrite)
    with server.client() as c:
        job = c.straighten(volume_id, session_id, wait=False, output_name=target.name, options=options,
                           channels=channels, scan_name=scan_name)
        done = yield from _follow(c, job)
        yield Progress("download", 0, 1, str(target))
        c.download(done.result.volume_id, target, overwrite=overwrite)
    yield Progress("download", 1, 1)
    return target
