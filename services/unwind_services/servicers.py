"""The five servicers: protobuf in, one core call (or a job), protobuf out."""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
import tarfile
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from napari_unwind.errors import InvalidInputError
from napari_unwind.io._atomic import remove_path
from napari_unwind.progress import cancellation

from . import convert
from ._proto.unwind.v1 import (
    jobs_pb2,
    jobs_pb2_grpc,
    segmentation_pb2,
    segmentation_pb2_grpc,
    skeleton_pb2,
    skeleton_pb2_grpc,
    volume_pb2,
    volume_pb2_grpc,
    warp_pb2_grpc,
)
from .catalog import Catalog
from .errors import CancelledError, DeadlineError, LimitError
from .fairness import UserSlots, idle_limited, idle_sends
from .ingest import (
    UploadPipe,
    decoder,
    encode_chunk,
    encoder,
    import_stream,
    level_slabs,
    stored_chunks,
    upload_framing,
)
from .interceptor import current_user
from .jobs import JobManager
from .paths import check_file_name

log = logging.getLogger("unwind_services")

__all__ = ["VolumeServicer", "SegmentationServicer", "SkeletonServicer", "WarpServicer", "JobServicer", "SERVICES"]

#: Bytes per message of a download (well under the 4 MiB default limit of clients).
DOWNLOAD_CHUNK = 2 * 1024 * 1024
#: Formats whose stored file (or folder) holds everything: a download in the same format sends it as it is.
_SELF_CONTAINED = (".zarr", ".tif", ".tiff", ".nrrd", ".nii", ".nii.gz")


#: Most points a MapPoints call (or one message of MapPointsStream) carries.
MAX_MAP_POINTS = 100_000


def _limit(value: int, default: int = 100, most: int = 1000) -> int:
    return min(most, value) if value > 0 else default


def _while_wanted(context) -> contextlib.AbstractContextManager:
    """The core's long loops within a unary call stop (``progress.checkpoint``) once its deadline has passed or its
    client has cancelled: the call ends DEADLINE_EXCEEDED or CANCELLED instead of working on for nobody."""
    def check() -> None:
        left = context.time_remaining()
        if left is not None and left <= 0:
            raise DeadlineError("the call's deadline passed; the server stopped its work")
        if not context.is_active():
            raise CancelledError("the call was cancelled by its client; the server stopped its work")

    return cancellation(check, 0.05)


class VolumeServicer(volume_pb2_grpc.VolumeServiceServicer):
    def __init__(self, catalog: Catalog, jobs: JobManager):
        self.catalog, self.jobs = catalog, jobs
        self.uploads = UserSlots(catalog.limits.max_uploads_per_user, "uploads",
                                 "wait for it to end before starting another")

    def Upload(self, request_iterator, context):
        owner, idle = current_user(), self.catalog.limits.upload_idle_seconds
        abandoned: list[UploadPipe] = []
        try:
            # the transfer holds the user's slot while its call is alive: not the clean-up after a failure, nor a
            # call gRPC ended itself (e.g. a message over its limit) that this thread has yet to notice
            with self.uploads.hold(owner, context.is_active):
                return self._upload(owner, idle_limited(
                    request_iterator, idle, f"the upload sent nothing for {idle:g} s and was aborted (this "
                    "server's idle limit); upload again", context.is_active), context, abandoned)
        finally:
            for pipe in abandoned:
                pipe.abandon()  # the import sees the stream end short and removes its partial store; waits for that
            self.catalog.forget_stored_bytes(owner)

    def _upload(self, owner, request_iterator, context, abandoned: list):
        limits, root = self.catalog.limits, self.catalog.root
        first = next(request_iterator, None)
        if first is None or isinstance(first, memoryview) or first.WhichOneof("part") != "header":
            raise InvalidInputError("an upload starts with a header message (name, shape, dtype, spacing, unit), "
                                    "then the voxels in chunks")
        h = first.header
        name = check_file_name(h.name or "upload", "the volume's name")
        if len(h.shape) != 3 or any(s < 1 for s in h.shape):
            raise InvalidInputError(f"shape must be 3 positive sizes (axis0, axis1, axis2), got {list(h.shape)}")
        dtype = convert.dtype_of(h.dtype)
        for what, values in (("spacing", h.spacing), ("origin", h.origin)):
            if len(values) not in (0, 3):
                raise InvalidInputError(f"{what} must be 3 numbers (axis0, axis1, axis2) or empty, got {list(values)}")
        limits.check_voxels(h.shape, "the upload")
        expected = int(np.prod(h.shape)) * dtype.itemsize
        if limits.max_upload_bytes and expected > limits.max_upload_bytes:
            raise LimitError(f"the upload would be {expected} bytes, more than this server's limit of "
                             f"{limits.max_upload_bytes}")
        self.catalog.check_quota(owner, expected, "this upload")
        framing = upload_framing(h, dtype, limits.message_bytes)  # "raw" or "chunks"
        vid = f"vol-{uuid.uuid4().hex[:12]}"
        dst = root.user_dir(owner) / "volumes" / f"{vid}.zarr"
        dst.parent.mkdir(parents=True, exist_ok=True)
        # a process of the import pool imports the voxels while they arrive (ingest.py); this thread checks, forwards
        pipe = UploadPipe(root.tmp, vid, lambda fifo: self.jobs.start_import(
            import_stream, fifo, tuple(h.shape), dtype.newbyteorder("<").str, tuple(h.spacing) or None,
            h.unit or None, tuple(h.origin) or None, h.labels, str(dst), framing.format))
        try:
            t0 = time.perf_counter()
            pipe.open(context.is_active)
            stopped = False
            for msg in request_iterator:
                if isinstance(msg, memoryview):  # a chunk, not copied out of its message (ingest.decoder)
                    chunk = msg
                elif msg.WhichOneof("part") != "chunk":
                    raise InvalidInputError("only the first message of an upload is a header; the rest are chunks")
                else:
                    chunk = msg.chunk
                if not pipe.write(*framing.parts(chunk)):  # counted and bounded against the header first
                    stopped = True  # the import stopped (e.g. NaN voxels, a bad chunk): finish() raises its error
                    break
            t1 = time.perf_counter()
            if not stopped:
                framing.check_complete()
            pipe.finish()
            log.info("upload %s of %s: %.1f MiB received in %.2f s, imported %.2f s after the last byte", vid,
                     owner, expected / 2**20, t1 - t0, time.perf_counter() - t1)
        except BaseException:
            abandoned.append(pipe)
            raise
        row, vol = self.catalog.add_volume(owner, dst, name, "upload", object_id=vid)
        return convert.volume_info(row, vol)

    def Register(self, request, context):
        owner = current_user()
        path = self.catalog.root.resolve_client_path(request.path)
        if not path.exists():
            raise FileNotFoundError(f"{request.path} does not exist under the server's data root")
        self.catalog.root.check_scan(path)  # every file it reads, not only the path given
        name = check_file_name(request.name or path.name, "the volume's name")
        row, vol = self.catalog.add_volume(owner, path, name, "register")
        return convert.volume_info(row, vol)

    def List(self, request, context):
        owner = current_user()
        out = volume_pb2.ListVolumesResponse()
        for row in self.catalog.store.list_objects(owner, "volume", _limit(request.limit)):
            try:
                _, vol = self.catalog.volume(owner, row.id)
            except Exception:  # noqa: BLE001 - a registered file removed by an admin: list it without its geometry
                out.volumes.add(volume_id=row.id, name=row.name, origin_kind=row.meta.get("origin", ""),
                                created=row.created, job_id=row.job_id)
                continue
            out.volumes.append(convert.volume_info(row, vol))
        return out

    def Info(self, request, context):
        row, vol = self.catalog.volume(current_user(), request.volume_id)
        return convert.volume_info(row, vol)

    def Download(self, request, context) -> Iterator[volume_pb2.DownloadResponse]:
        idle = self.catalog.limits.download_idle_seconds
        return idle_sends(context, self._download(request, context), idle, f"download of {request.volume_id}")

    def _download(self, request, context) -> Iterator[volume_pb2.DownloadResponse]:
        from napari_unwind.io import write_volume

        row, vol = self.catalog.volume(current_user(), request.volume_id)
        if not 0 <= request.level < len(vol.levels):
            raise InvalidInputError(f"level must be 0..{len(vol.levels) - 1} for this volume, got {request.level}")
        level = vol.levels[request.level]
        spacing = vol.level_spacings[request.level]
        fmt = (request.format or "raw").lower()
        header = volume_pb2.DownloadHeader(name=row.name, shape=list(level.shape), dtype=convert.dtype_enum(vol.dtype),
                                           spacing=list(spacing), unit=vol.unit or "", origin=list(vol.origin))
        max_message = self.catalog.limits.message_bytes
        piece = min(DOWNLOAD_CHUNK, (max_message - 64) // 4096 * 4096)  # within this server's limit (>= 256 KiB)
        as_stored = stored_chunks(vol, request.level, max_message - 64) if fmt == "chunks" else None
        if as_stored is not None:
            # the chunks as they are on disk: no decoding here, the client decodes and checks them
            reader, blobs = as_stored
            header.format, header.total_bytes = "chunks", int(np.prod(level.shape)) * vol.dtype.itemsize
            header.chunk_shape[:], header.chunk_crc32c = reader.grid, bool(reader.direct[1])
            header.fill_value = float(reader.fill or 0)
            header.file_name = f"{row.name.split('.')[0]}.raw"
            yield volume_pb2.DownloadResponse(header=header)
            for blob in blobs:
                yield encode_chunk(blob or b"")
            return
        if fmt in ("raw", "chunks"):
            dtype = vol.dtype.newbyteorder("<")
            header.format, header.total_bytes = "raw", int(np.prod(level.shape)) * dtype.itemsize
            header.file_name = f"{row.name.split('.')[0]}.raw"
            yield volume_pb2.DownloadResponse(header=header)
            for block in level_slabs(vol, request.level, dtype):  # the next slab is read while this one is sent
                mv = memoryview(block).cast("B")
                for a in range(0, len(mv), piece):
                    yield encode_chunk(mv[a:a + piece])  # one copy; sent as is (ingest.encoder)
            return
        suffix = fmt if fmt.startswith(".") else "." + fmt
        stem = row.name.split(".")[0] or "volume"
        stored = self.catalog.path(row)
        work = Path(tempfile.mkdtemp(prefix="download-", dir=self.catalog.root.tmp))
        try:
            target = work / "out" / f"{stem}{suffix}"
            target.parent.mkdir()
            if (request.level == 0 and suffix in _SELF_CONTAINED and stored.name.lower().endswith(suffix)
                    and not stored.is_symlink()):
                # the stored file itself (e.g. an export with its straightening map): the exact bytes
                if stored.is_dir():
                    shutil.copytree(stored, target)
                else:
                    shutil.copyfile(stored, target)
            else:
                write_volume(vol.with_data(level, spacing=spacing), target)
            files = [p for p in target.parent.rglob("*") if p.is_file()]
            if target.is_file() and len(files) == 1:
                send, header.tar, header.file_name = target, False, target.name
            else:
                send = work / "out.tar"
                with tarfile.open(send, "w") as tar:
                    for p in sorted(target.parent.iterdir()):
                        tar.add(p, arcname=p.name)
                header.tar, header.file_name = True, target.name
            header.format = suffix.lstrip(".")
            header.total_bytes = send.stat().st_size
            yield volume_pb2.DownloadResponse(header=header)
            with open(send, "rb") as f:
                while block := f.read(piece):
                    yield encode_chunk(block)
        finally:
            remove_path(work)


class JobServicer(jobs_pb2_grpc.JobServiceServicer):
    def __init__(self, jobs: JobManager):
        self.jobs = jobs

    def Submit(self, request, context):
        return self.jobs.submit(current_user(), request)

    def Resubmit(self, request, context):
        return self.jobs.resubmit(current_user(), request.job_id)

    def Get(self, request, context):
        return self.jobs.store.get_job(current_user(), request.job_id)

    def Watch(self, request, context):
        yield from self.jobs.watch(current_user(), request.job_id, request.after_seq, context.is_active)

    def Cancel(self, request, context):
        return self.jobs.cancel(current_user(), request.job_id)

    def List(self, request, context):
        return jobs_pb2.ListJobsResponse(jobs=self.jobs.store.list_jobs(current_user(), request.state,
                                                                        _limit(request.limit)))


class SegmentationServicer(segmentation_pb2_grpc.SegmentationServiceServicer):
    def __init__(self, jobs: JobManager):
        self.jobs, self.catalog = jobs, jobs.catalog

    def Segment(self, request, context):
        return self.jobs.submit(current_user(), jobs_pb2.SubmitRequest(segment=request))

    def Select(self, request, context):
        return self.jobs.submit(current_user(), jobs_pb2.SubmitRequest(select=request))

    def _labels(self, owner: str, row, k: int):
        """The label volume of ``k`` features as (its volume row, its Volume); under the segmentation's lock.

        Written once per (segmentation, k) (atomically, by the core's save_features) and registered as a volume of
        the owner; ``meta["labels"]`` maps k to its id. The segment job's own file (``meta["features"]``, which
        holds ``meta["k"]`` features) is registered the first time any k is asked for.
        """
        from napari_unwind.segmentation import JoinTree, save_features

        row = self.catalog.segmentation(owner, row.id)  # the meta as it is now (another call may have added a k)
        root, known = self.catalog.root, row.meta.get("labels")
        stem = row.name.split(" k=")[0]

        def register(path: Path, n: int) -> None:
            nonlocal known
            vrow, _ = self.catalog.add_volume(owner, path, f"{stem} features k={n}", "output", row.job_id)
            known = {**(known or {}), str(n): vrow.id}
            self.catalog.store.update_meta(owner, row.id, dict(row.meta, labels=known))

        if known is None:
            register(root.absolute(row.meta["features"]), int(row.meta["k"]))
        if str(k) not in known:
            tree = JoinTree.from_npz(root.absolute(row.meta["tree"]))
            register(save_features(tree.simplify(k), root.absolute(row.path) / f"features-k{k}.zarr", overwrite=True),
                     k)
        return self.catalog.volume(owner, known[str(k)])

    def _info(self, row, k: int, vrow, vol) -> segmentation_pb2.SegmentationInfo:
        from napari_unwind.segmentation import Features

        attrs = vol.metadata["unwind"]["segmentation"]
        features = Features.from_labels(np.zeros((1, 1, 1), np.uint16), attrs)  # the statistics, not the voxels
        return segmentation_pb2.SegmentationInfo(
            segmentation_id=row.id, volume_id=row.meta["volume_id"], features=k, level=int(attrs["level"]),
            shape=list(vol.shape), feature=[convert.feature_msg(s) for s in features.stats],
            labels_volume_id=vrow.id, features_json=json.dumps(attrs), maxima=int(row.meta.get("maxima", 0)))

    def Info(self, request, context):
        owner = current_user()
        row = self.catalog.segmentation(owner, request.segmentation_id)
        k = int(row.meta["k"])
        with self.catalog.lock(row.id), _while_wanted(context):
            vrow, vol = self._labels(owner, row, k)
        return self._info(row, k, vrow, vol)

    def Simplify(self, request, context):
        from napari_unwind.segmentation._common import check_features_count

        owner = current_user()
        row = self.catalog.segmentation(owner, request.segmentation_id)
        k = check_features_count(request.features)
        with self.catalog.lock(row.id):
            with _while_wanted(context):
                vrow, vol = self._labels(owner, row, k)
            row = self.catalog.segmentation(owner, row.id)
            self.catalog.store.update_meta(owner, row.id, dict(row.meta, k=k, features=self.catalog.root.relative(
                self.catalog.path(vrow))))
        return self._info(row, k, vrow, vol)


class SkeletonServicer(skeleton_pb2_grpc.SkeletonServiceServicer):
    def __init__(self, jobs: JobManager):
        self.jobs, self.catalog = jobs, jobs.catalog

    def SuggestEnds(self, request, context):
        from napari_unwind.skeleton import suggest_endpoints

        owner = current_user()
        _, mask = self.catalog.volume(owner, request.mask_volume_id)
        scan = self.catalog.volume(owner, request.volume_id)[1] if request.volume_id else None
        if scan is not None and tuple(scan.shape) != tuple(mask.shape):
            raise InvalidInputError(f"the mask has shape {mask.shape} but the scan has {scan.shape}")
        with _while_wanted(context):
            head, tail = suggest_endpoints(mask.data, spacing=mask.spacing,
                                           volume=None if scan is None else scan.data)
        return skeleton_pb2.Ends(head=convert.point_msg(head), tail=convert.point_msg(tail))

    def EstimateDeformation(self, request, context):
        return self.jobs.submit(current_user(), jobs_pb2.SubmitRequest(estimate_deformation=request))


class WarpServicer(warp_pb2_grpc.WarpServiceServicer):
    def __init__(self, jobs: JobManager):
        self.jobs, self.catalog = jobs, jobs.catalog

    def Straighten(self, request, context):
        return self.jobs.submit(current_user(), jobs_pb2.SubmitRequest(straighten=request))

    def Bend(self, request, context):
        return self.jobs.submit(current_user(), jobs_pb2.SubmitRequest(bend=request))

    def Measure(self, request, context):
        return self.jobs.submit(current_user(), jobs_pb2.SubmitRequest(measure=request))

    def Average(self, request, context):
        return self.jobs.submit(current_user(), jobs_pb2.SubmitRequest(average=request))

    def MapPoints(self, request, context):
        from napari_unwind.warp import map_points

        pts = convert.map_points_in(request, MAX_MAP_POINTS, "MapPoints", "use MapPointsStream for more")
        _, session = self.catalog.session(current_user(), request.session_id)
        with _while_wanted(context):
            mapped = map_points(pts, session.deformation, **convert.map_options(request)) if len(pts) \
                else np.zeros((0, 3))
        return convert.map_points_out(mapped, bool(request.coords))

    def MapPointsStream(self, request_iterator, context):
        from napari_unwind.warp import map_points

        first, deformation, total, inside = None, None, 0, 0
        for request in request_iterator:
            if first is None:
                first = request
                _, session = self.catalog.session(current_user(), request.session_id)
                deformation, options = session.deformation, convert.map_options(request)
            else:
                convert.check_same_map(first, request)
            pts = convert.map_points_in(request, MAX_MAP_POINTS, "a message of MapPointsStream",
                                        "send them in several messages")
            with _while_wanted(context):
                mapped = map_points(pts, deformation, strict=False, **options) if len(pts) else np.zeros((0, 3))
            total += len(pts)
            inside += int(np.isfinite(mapped[:, 0]).sum())
            yield convert.map_points_out(mapped, bool(request.coords))
        if total and not inside:
            raise InvalidInputError(f"all {total} points are outside the cage of the deformation; check that they "
                                    "are voxel coordinates of the right volume")


def add_volume_service(servicer: VolumeServicer, server) -> None:
    """``volume_pb2_grpc.add_VolumeServiceServicer_to_server``, with the chunks of Upload and Download encoded and
    decoded by :mod:`.ingest` (a chunk arrives as a memoryview of its bytes and leaves pre-encoded)."""
    import grpc

    v = volume_pb2
    handlers = {
        "Upload": grpc.stream_unary_rpc_method_handler(
            servicer.Upload, request_deserializer=decoder(v.UploadRequest),
            response_serializer=v.VolumeInfo.SerializeToString),
        "Register": grpc.unary_unary_rpc_method_handler(
            servicer.Register, request_deserializer=v.RegisterRequest.FromString,
            response_serializer=v.VolumeInfo.SerializeToString),
        "List": grpc.unary_unary_rpc_method_handler(
            servicer.List, request_deserializer=v.ListVolumesRequest.FromString,
            response_serializer=v.ListVolumesResponse.SerializeToString),
        "Info": grpc.unary_unary_rpc_method_handler(
            servicer.Info, request_deserializer=v.VolumeRef.FromString,
            response_serializer=v.VolumeInfo.SerializeToString),
        "Download": grpc.unary_stream_rpc_method_handler(
            servicer.Download, request_deserializer=v.DownloadRequest.FromString,
            response_serializer=encoder(v.DownloadResponse)),
    }
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler("unwind.v1.VolumeService", handlers),))
    server.add_registered_method_handlers("unwind.v1.VolumeService", handlers)


#: service name (for --service) -> (full proto name, servicer factory taking (catalog, jobs))
SERVICES = {
    "volume": ("unwind.v1.VolumeService", lambda c, j: VolumeServicer(c, j), add_volume_service),
    "segmentation": ("unwind.v1.SegmentationService", lambda c, j: SegmentationServicer(j),
                     segmentation_pb2_grpc.add_SegmentationServiceServicer_to_server),
    "skeleton": ("unwind.v1.SkeletonService", lambda c, j: SkeletonServicer(j),
                 skeleton_pb2_grpc.add_SkeletonServiceServicer_to_server),
    "warp": ("unwind.v1.WarpService", lambda c, j: WarpServicer(j), warp_pb2_grpc.add_WarpServiceServicer_to_server),
    "jobs": ("unwind.v1.JobService", lambda c, j: JobServicer(j), jobs_pb2_grpc.add_JobServiceServicer_to_server),
}
