"""Protobuf <-> core values: the only translation layer (no domain logic)."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from napari_unwind.errors import InvalidInputError

from ._proto.unwind.v1 import common_pb2 as pb
from ._proto.unwind.v1 import segmentation_pb2, skeleton_pb2, volume_pb2, warp_pb2
from .errors import LimitError

__all__ = ["Bound", "bounds", "check_request",
           "DTYPES", "dtype_of", "dtype_enum", "points", "point_msg", "endpoints", "volume_info", "feature_msg",
           "skeleton_options", "skeleton_options_msg", "export_options", "export_options_msg", "segment_options",
           "pipeline_options", "order",
           "result_figures", "verdict_msg", "specimen_result", "STATUSES"]

DTYPES = {
    pb.DTYPE_UINT8: np.dtype("uint8"), pb.DTYPE_INT8: np.dtype("int8"),
    pb.DTYPE_UINT16: np.dtype("uint16"), pb.DTYPE_INT16: np.dtype("int16"),
    pb.DTYPE_UINT32: np.dtype("uint32"), pb.DTYPE_INT32: np.dtype("int32"),
    pb.DTYPE_FLOAT32: np.dtype("float32"), pb.DTYPE_FLOAT64: np.dtype("float64"),
}
_ENUMS = {v: k for k, v in DTYPES.items()}


# ------------------------------------------------------------------------------------------------------------------
# the bounds of every field of every request (the protos' comments list them; a test holds the two equal)
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Bound:
    """What a field accepts: numbers in ``lo..hi`` (doubles finite), text of at most ``max_bytes`` UTF-8 bytes
    without NUL (a ``path``: each folder or file name at most 255 bytes), a repeated field of at most ``max_items``
    items (or exactly one of the counts ``counts``), each item within ``lo..hi``."""

    lo: float = -math.inf
    hi: float = math.inf
    max_bytes: int = 0
    path: bool = False
    max_items: int | None = None
    counts: tuple[int, ...] = ()
    say: str = ""  # what the field holds, in the refusal (default: its bounds)


#: Longest id of an object or a job (the server's are 16 characters).
MAX_ID_BYTES = 64
#: Longest file name of an output or a volume (paths.check_file_name: 128 characters).
MAX_NAME_BYTES = 128
#: Longest path of a Register request, and its longest folder or file name (Linux PATH_MAX and NAME_MAX).
MAX_PATH_BYTES, MAX_COMPONENT_BYTES = 4096, 255
#: Longest job time limit: 30 days.
MAX_TIMEOUT_SECONDS = 30 * 24 * 3600.0
#: Largest coordinate of a point, voxels.
MAX_COORDINATE = 1e9
#: Most points of a selection, of one MapPoints message on the wire, and most parts of a chain. (MapPoints itself
#: maps at most ``servicers.MAX_MAP_POINTS`` a call or a stream message: more is RESOURCE_EXHAUSTED naming the stream.)
MAX_POINTS, MAX_WIRE_POINTS, MAX_CHAIN = 10_000, 1_000_000, 1_000
#: Largest `limit` of a listing (the server sends at most 1000) and `after_seq` of a watch.
MAX_LIMIT, MAX_SEQ = 1_000_000, 2**53
#: Most channels of a Measure job.
MAX_CHANNELS = 16
#: Most specimens of an Average job, landmarks of one specimen, and stations of the average.
MAX_SPECIMENS, MAX_LANDMARKS, MAX_STATIONS = 1000, 64, 1_000_000
#: Largest side of an upload, voxels (the server's --max-voxels bounds the product).
MAX_SIDE = 2**31 - 1


@functools.lru_cache(maxsize=1)
def bounds() -> dict[str, Bound]:
    """``"Message.field"`` -> its :class:`Bound`, for every field of every request message (booleans, enums,
    messages and the upload's bytes: :data:`ANY`). The options' bounds are the core's
    (:mod:`napari_unwind.pipeline`), so the command line, the dock and the server refuse the same values."""
    from napari_unwind import pipeline as P
    from napari_unwind.segmentation._common import MAX_FEATURES

    ident, name, anything = Bound(max_bytes=MAX_ID_BYTES), Bound(max_bytes=MAX_NAME_BYTES), Bound()
    coordinate = Bound(-MAX_COORDINATE, MAX_COORDINATE)
    finite = Bound()
    table = {
        "Point": dict(axis0=coordinate, axis1=coordinate, axis2=coordinate),
        "SubmitRequest": dict(segment=anything, select=anything, estimate_deformation=anything, straighten=anything,
                              bend=anything, pipeline=anything, measure=anything, average=anything,
                              request_id=name,
                              timeout_seconds=Bound(0, MAX_TIMEOUT_SECONDS), name=Bound(max_bytes=255)),
        "PipelineRequest": dict(volume_id=ident, select=Bound(max_items=MAX_POINTS),
                                ids=Bound(1, MAX_FEATURES, max_items=MAX_FEATURES), segmentation_id=ident,
                                mask_volume_id=ident, features=Bound(0, MAX_FEATURES), level=Bound(0, P.MAX_LEVEL),
                                has_level=anything, isovalue=finite, has_isovalue=anything, fill_holes=anything,
                                ends=anything, skeleton=anything, export=anything),
        "JobRef": dict(job_id=ident),
        "WatchRequest": dict(job_id=ident, after_seq=Bound(0, MAX_SEQ)),
        "ListJobsRequest": dict(state=anything, limit=Bound(0, MAX_LIMIT)),
        "SegmentRequest": dict(volume_id=ident, features=Bound(0, MAX_FEATURES), level=Bound(-1, P.MAX_LEVEL),
                               has_level=anything, smooth=Bound(0, P.MAX_SMOOTH), has_smooth=anything),
        "SegmentationRef": dict(segmentation_id=ident),
        "SimplifyRequest": dict(segmentation_id=ident, features=Bound(1, MAX_FEATURES)),
        "SelectRequest": dict(segmentation_id=ident, seeds=Bound(max_items=MAX_POINTS),
                              ids=Bound(1, MAX_FEATURES, max_items=MAX_FEATURES), fill_holes=anything,
                              isovalue=finite, has_isovalue=anything, output_name=name,
                              features=Bound(0, MAX_FEATURES)),
        "SuggestEndsRequest": dict(mask_volume_id=ident, volume_id=ident),
        "PointPair": dict(start=anything, end=anything),
        "Ends": dict(head=anything, tail=anything, chain=Bound(max_items=MAX_CHAIN)),
        "SkeletonOptions": dict(no_twist=anything, levels=Bound(0, P.MAX_N_LEVELS),
                                smoothing_iterations=Bound(0, P.MAX_SMOOTHING_ITERATIONS),
                                has_smoothing_iterations=anything, cage_radius=Bound(0, P.MAX_VOXELS_DISTANCE),
                                tolerance=Bound(0, P.MAX_VOXELS_DISTANCE),
                                snap_tolerance=Bound(0, P.MAX_VOXELS_DISTANCE),
                                half_extent=Bound(0, P.MAX_LENGTH, counts=(0, 2)),
                                cage_margin=Bound(0, P.MAX_CAGE_MARGIN), has_cage_margin=anything,
                                dorsal_points=Bound(max_items=P.MAX_DORSAL_POINTS),
                                dorsal_direction=Bound(-P.MAX_LENGTH, P.MAX_LENGTH, counts=(0, 3)),
                                context=Bound(0, P.MAX_LENGTH)),
        "EstimateDeformationRequest": dict(mask_volume_id=ident, volume_id=ident, ends=anything, options=anything),
        "UploadHeader": dict(name=name, shape=Bound(1, MAX_SIDE, counts=(3,),
                                                    say="3 positive sizes (axis0, axis1, axis2)"), dtype=anything,
                             spacing=Bound(0, P.MAX_LENGTH, counts=(0, 3)), unit=Bound(max_bytes=32),
                             origin=Bound(-P.MAX_LENGTH, P.MAX_LENGTH, counts=(0, 3)), labels=anything,
                             format=Bound(max_bytes=16), chunk_shape=Bound(1, MAX_SIDE, counts=(0, 3))),
        "UploadRequest": dict(header=anything, chunk=anything),
        "RegisterRequest": dict(path=Bound(max_bytes=MAX_PATH_BYTES, path=True), name=name),
        "VolumeRef": dict(volume_id=ident),
        "ListVolumesRequest": dict(limit=Bound(0, MAX_LIMIT)),
        "DownloadRequest": dict(volume_id=ident, format=Bound(max_bytes=16), level=Bound(0, P.MAX_LEVEL)),
        "ExportOptions": dict(order=Bound(0, 3), has_order=anything, spacing=Bound(0, P.MAX_LENGTH),
                              pad=Bound(0, P.MAX_PAD), chunks=Bound(1, P.MAX_CHUNK, counts=(0, 3)),
                              allow_folds=anything, output_name=name),
        "StraightenRequest": dict(volume_id=ident, session_id=ident, options=anything,
                                  channels=Bound(max_items=MAX_CHANNELS), scan_name=Bound(max_bytes=64)),
        "MeasureRequest": dict(session_id=ident, mask_volume_id=ident, labels_volume_id=ident,
                               channels=Bound(max_items=MAX_CHANNELS), spacing=Bound(0, P.MAX_LENGTH)),
        "MeasureChannel": dict(name=Bound(max_bytes=64), volume_id=ident),
        "AverageRequest": dict(specimens=Bound(max_items=MAX_SPECIMENS), stations=Bound(0, MAX_STATIONS),
                               keep_size=anything, keep_grey_values=anything, max_roll=Bound(0, 180),
                               has_max_roll=anything, output_name=name),
        "AverageSpecimen": dict(volume_id=ident, landmarks=Bound(0, P.MAX_LENGTH, max_items=MAX_LANDMARKS)),
        "BendRequest": dict(volume_id=ident, session_id=ident, order=Bound(0, 3), has_order=anything,
                            output_name=name),
        "MapPointsRequest": dict(session_id=ident, points=Bound(max_items=MAX_WIRE_POINTS), direction=anything,
                                 spacing=Bound(0, P.MAX_LENGTH), pad=Bound(0, P.MAX_PAD),
                                 coords=Bound(max_items=3 * MAX_WIRE_POINTS)),
    }
    return {f"{m}.{f}": b for m, fs in table.items() for f, b in fs.items()}


def _text_of(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def _range(b: Bound, fd: Any) -> str:
    from google.protobuf.descriptor import FieldDescriptor as F

    if b.say:
        return b.say
    finite = "a finite number" if fd.type in (F.TYPE_DOUBLE, F.TYPE_FLOAT) else "a whole number"
    return f"{finite} in {_text_of(b.lo)}..{_text_of(b.hi)}" if math.isfinite(b.lo) else finite


def _check_value(where: str, fd: Any, b: Bound, v: Any) -> None:
    from google.protobuf.descriptor import FieldDescriptor as F

    if fd.type == F.TYPE_STRING:
        size = len(v.encode("utf-8", "surrogatepass"))
        if b.max_bytes and size > b.max_bytes:
            raise InvalidInputError(f"{where} is {size} bytes long; at most {b.max_bytes}")
        if "\x00" in v:
            raise InvalidInputError(f"{where} holds a NUL character")
        if b.path:
            longest = max((len(p.encode("utf-8", "surrogatepass")) for p in v.replace("\\", "/").split("/")),
                          default=0)
            if longest > MAX_COMPONENT_BYTES:
                raise InvalidInputError(f"{where} holds a folder or file name of {longest} bytes; at most "
                                        f"{MAX_COMPONENT_BYTES} each")
    elif fd.type == F.TYPE_ENUM:
        if fd.enum_type.values_by_number.get(v) is None:
            raise InvalidInputError(f"{where} must be one of {', '.join(fd.enum_type.values_by_name)}, got {v}")
    elif fd.type in (F.TYPE_DOUBLE, F.TYPE_FLOAT):
        if not math.isfinite(v) or not b.lo <= v <= b.hi:
            raise InvalidInputError(f"{where} must be {_range(b, fd)}, got {v!r}")
    elif fd.type not in (F.TYPE_BOOL, F.TYPE_BYTES, F.TYPE_MESSAGE) and not b.lo <= v <= b.hi:
        raise InvalidInputError(f"{where} must be {_range(b, fd)}, got {v}")


def check_request(msg: Any, where: str = "") -> None:
    """Refuse (:class:`InvalidInputError` naming the field) a request with a field out of its :func:`bounds`:
    numbers out of range, NaN or infinity, text too long or holding NUL, too many items. Walks nested messages."""
    from google.protobuf.descriptor import FieldDescriptor as F

    table, name = bounds(), msg.DESCRIPTOR.name
    where = where or name
    for fd in msg.DESCRIPTOR.fields:
        b = table.get(f"{name}.{fd.name}", Bound(max_bytes=MAX_PATH_BYTES))
        here = f"{where}.{fd.name}"
        value = getattr(msg, fd.name)
        if fd.is_repeated:
            n = len(value)
            if b.counts and n not in b.counts:
                raise InvalidInputError(f"{here} must hold {b.say or ' or '.join(map(str, b.counts)) + ' values'}, "
                                        f"got {n} values")
            if b.max_items is not None and n > b.max_items:
                raise InvalidInputError(f"{here} holds {n} items; at most {b.max_items}")
            if n and _check_in_bulk(here, fd, b, value):
                continue
            for i, item in enumerate(value):
                if fd.type == F.TYPE_MESSAGE:
                    check_request(item, f"{here}[{i}]")
                else:
                    _check_value(f"{here}[{i}]", fd, b, item)
        elif fd.type == F.TYPE_MESSAGE:
            if msg.HasField(fd.name):
                check_request(value, here)
        else:
            _check_value(here, fd, b, value)


def _floats(desc: Any) -> tuple[str, ...] | None:
    """The field names of a message of floating-point scalars only (a Point), else None."""
    from google.protobuf.descriptor import FieldDescriptor as F

    fields = desc.fields
    if fields and all(f.type in (F.TYPE_DOUBLE, F.TYPE_FLOAT) and not f.is_repeated for f in fields):
        return tuple(f.name for f in fields)
    return None


def _check_in_bulk(here: str, fd: Any, b: Bound, value: Any) -> bool:
    """Check a repeated field of floating-point numbers, or of messages of them (points), with numpy: a million
    points take milliseconds, not seconds. False: not such a field (check item by item). The first bad item is
    reported as the item-by-item check words it."""
    from google.protobuf.descriptor import FieldDescriptor as F

    if fd.type in (F.TYPE_DOUBLE, F.TYPE_FLOAT):
        arr = np.asarray(value, dtype=float)
        bad = ~(np.isfinite(arr) & (arr >= b.lo) & (arr <= b.hi))
        if bad.any():
            i = int(np.argmax(bad))
            _check_value(f"{here}[{i}]", fd, b, value[i])
        return True
    names = _floats(fd.message_type) if fd.type == F.TYPE_MESSAGE else None
    if names is None:
        return False
    table, kind = bounds(), fd.message_type.name
    arr = np.array([[getattr(item, f) for f in names] for item in value], dtype=float).reshape(len(value), -1)
    for j, f in enumerate(names):
        fb = table.get(f"{kind}.{f}", Bound())
        bad = ~(np.isfinite(arr[:, j]) & (arr[:, j] >= fb.lo) & (arr[:, j] <= fb.hi))
        if bad.any():
            i = int(np.argmax(bad))
            _check_value(f"{here}[{i}].{f}", fd.message_type.fields_by_name[f], fb, arr[i, j])
    return True


def dtype_of(value: int) -> np.dtype:
    if value not in DTYPES:
        raise InvalidInputError(f"dtype must be one of {', '.join(pb.DType.Name(k) for k in DTYPES)}, got "
                                f"{pb.DType.Name(value) if value in pb.DType.values() else value}")
    return DTYPES[value]


def dtype_enum(dtype: Any) -> int:
    return _ENUMS.get(np.dtype(dtype), pb.DTYPE_UNSPECIFIED)


def points(msgs: Sequence[pb.Point], what: str) -> np.ndarray:
    """(N, 3) array of points; refuses NaN and infinity."""
    return _finite(np.array([(p.axis0, p.axis1, p.axis2) for p in msgs], dtype=float).reshape(-1, 3), what)


def _finite(arr: np.ndarray, what: str) -> np.ndarray:
    """``arr`` ((N, 3) points), or InvalidInputError naming the first point with NaN or infinity."""
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise InvalidInputError(f"{what} {i} is not a finite point: {tuple(arr[i])}; give three finite numbers "
                                "(axis0, axis1, axis2)")
    return arr


def map_points_in(msg: warp_pb2.MapPointsRequest, most: int, what: str, hint: str) -> np.ndarray:
    """The (N, 3) points of a MapPointsRequest (``points`` or the flat ``coords``), at most ``most`` of them."""
    if msg.points and msg.coords:
        raise InvalidInputError("give the points either as points or as coords, not both")
    n = len(msg.points) if msg.points else len(msg.coords) // 3
    if n > most:
        raise LimitError(f"{what} carries at most {most} points, got {n}; {hint}")
    if not msg.coords:
        return points(msg.points, "point")
    if len(msg.coords) % 3:
        raise InvalidInputError(f"coords holds (axis0, axis1, axis2) triples: its length must be a multiple of 3, "
                                f"got {len(msg.coords)}")
    return _finite(np.asarray(msg.coords, dtype=float).reshape(-1, 3), "point")


def map_points_out(mapped: np.ndarray, flat: bool) -> warp_pb2.MapPointsResponse:
    """The response to a MapPointsRequest: flat ``coords`` when the request gave coords, else ``points``."""
    if flat:
        out = warp_pb2.MapPointsResponse()
        out.coords.extend(np.ascontiguousarray(mapped, dtype=float).ravel().tolist())
        return out
    return warp_pb2.MapPointsResponse(points=[pb.Point(axis0=a, axis1=b, axis2=c) for a, b, c in mapped])


def map_options(msg: warp_pb2.MapPointsRequest) -> dict[str, Any]:
    """The keywords of ``napari_unwind.warp.map_points`` a MapPointsRequest gives."""
    to = "scan" if msg.direction == warp_pb2.MAP_DIRECTION_TO_SCAN else "straight"
    return {"to": to, "spacing": msg.spacing or None, "pad": msg.pad}


def check_same_map(first: warp_pb2.MapPointsRequest, msg: warp_pb2.MapPointsRequest) -> None:
    """A later message of MapPointsStream leaves the first one's session and options unset, or repeats them."""
    for name in ("session_id", "direction", "spacing", "pad"):
        value = getattr(msg, name)
        if value and value != getattr(first, name):
            raise InvalidInputError(f"every message of a MapPointsStream maps with the first one's {name} "
                                    f"({getattr(first, name)!r}); a later message gave {value!r}")


def point_msg(p: Sequence[float]) -> pb.Point:
    return pb.Point(axis0=float(p[0]), axis1=float(p[1]), axis2=float(p[2]))


def endpoints(msg: skeleton_pb2.Ends | None, present: bool):
    """A session Endpoints from an Ends message, or None when not given."""
    from napari_unwind.session import Endpoints

    if not present:
        return None
    head, tail = points([msg.head], "head")[0], points([msg.tail], "tail")[0]
    chain = tuple((tuple(points([c.start], "chain start")[0]), tuple(points([c.end], "chain end")[0]))
                  for c in msg.chain)
    return Endpoints(head=tuple(head), tail=tuple(tail), chain=chain)


def ends_msg(e: Any) -> skeleton_pb2.Ends:
    msg = skeleton_pb2.Ends(head=point_msg(e.head), tail=point_msg(e.tail))
    for a, b in getattr(e, "chain", ()):
        msg.chain.add(start=point_msg(a), end=point_msg(b))
    return msg


def volume_info(row: Any, volume: Any) -> volume_pb2.VolumeInfo:
    return volume_pb2.VolumeInfo(
        volume_id=row.id, name=row.name, shape=list(volume.shape), dtype=dtype_enum(volume.dtype),
        spacing=list(volume.spacing), unit=volume.unit or "", origin=list(volume.origin), levels=len(volume.levels),
        format=volume.format or "", origin_kind=row.meta.get("origin", ""), created=row.created, job_id=row.job_id)


def _number(v: Any) -> float:
    """A statistic as a double: NaN for None (a saved NaN: JSON has none)."""
    return float("nan") if v is None else float(v)


def feature_msg(st: Any) -> segmentation_pb2.Feature:
    return segmentation_pb2.Feature(
        id=int(st.id), voxel_count=int(st.voxel_count), bbox_full=[int(b) for b in st.bbox_full],
        value_min=_number(st.value_min), value_max=_number(st.value_max), threshold=_number(st.threshold),
        max_position_full=point_msg(st.max_position_full))


# ------------------------------------------------------------------------------------------------------------------
# the pipeline's options (their defaults live in napari_unwind.pipeline; zero or unset in a message means default)
# ------------------------------------------------------------------------------------------------------------------
def skeleton_options(msg: skeleton_pb2.SkeletonOptions):
    """A :class:`napari_unwind.pipeline.SkeletonOptions` from its message (unset fields: the defaults)."""
    from napari_unwind.pipeline import SkeletonOptions

    given: dict[str, Any] = {}
    if msg.no_twist:
        given["estimate_twist"] = False
    if msg.levels:
        given["n_levels"] = int(msg.levels)
    if msg.has_smoothing_iterations:
        given["smoothing_iterations"] = int(msg.smoothing_iterations)
    for name in ("cage_radius", "tolerance", "snap_tolerance"):
        if getattr(msg, name):
            given[name] = float(getattr(msg, name))
    if len(msg.half_extent):
        given["half_extent"] = tuple(msg.half_extent)
    if msg.has_cage_margin:
        given["cage_margin"] = float(msg.cage_margin)
    if len(msg.dorsal_points):
        given["dorsal_points"] = tuple(map(tuple, points(msg.dorsal_points, "options.dorsal_points")))
    if len(msg.dorsal_direction):
        given["dorsal_direction"] = tuple(msg.dorsal_direction)
    if msg.context:
        given["context"] = float(msg.context)
    return SkeletonOptions(**given)


def skeleton_options_msg(opt: Any) -> skeleton_pb2.SkeletonOptions:
    """The message of a :class:`napari_unwind.pipeline.SkeletonOptions` (every field given)."""
    return skeleton_pb2.SkeletonOptions(
        no_twist=not opt.estimate_twist, levels=opt.n_levels, smoothing_iterations=opt.smoothing_iterations,
        has_smoothing_iterations=True, cage_radius=opt.cage_radius, tolerance=opt.tolerance,
        snap_tolerance=opt.snap_tolerance, half_extent=list(opt.half_extent or ()), cage_margin=opt.cage_margin,
        has_cage_margin=True, dorsal_points=[point_msg(p) for p in opt.dorsal_points or ()],
        dorsal_direction=list(opt.dorsal_direction or ()), context=opt.context)


def export_options(msg: warp_pb2.ExportOptions):
    """A :class:`napari_unwind.pipeline.ExportOptions` from its message (unset fields: the defaults)."""
    from napari_unwind.pipeline import ExportOptions

    given: dict[str, Any] = dict(pad=int(msg.pad), allow_folds=bool(msg.allow_folds))
    if msg.has_order:
        given["order"] = int(msg.order)
    if msg.spacing:
        given["spacing"] = float(msg.spacing)
    if len(msg.chunks):
        given["chunks"] = tuple(int(c) for c in msg.chunks)
    return ExportOptions(**given)


def segment_options(msg: Any):
    """A :class:`napari_unwind.pipeline.SegmentOptions` from a SegmentRequest, SelectRequest or PipelineRequest
    (unset fields: the defaults)."""
    from napari_unwind.pipeline import SegmentOptions

    given: dict[str, Any] = {}
    if msg.features:
        given["features"] = int(msg.features)
    if getattr(msg, "has_level", False) and msg.level >= 0:  # a SegmentRequest's -1: the default
        given["level"] = int(msg.level)
    if getattr(msg, "has_smooth", False):
        given["smooth"] = float(msg.smooth)
    if getattr(msg, "has_isovalue", False):
        given["isovalue"] = float(msg.isovalue)
    if hasattr(msg, "fill_holes"):
        given["fill_holes"] = bool(msg.fill_holes)
    return SegmentOptions(**given)


def pipeline_options(msg: Any):
    """The :class:`napari_unwind.pipeline.PipelineOptions` of a PipelineRequest."""
    from napari_unwind.pipeline import PipelineOptions

    return PipelineOptions(segment_options(msg), skeleton_options(msg.skeleton), export_options(msg.export))


def order(msg: Any) -> int:
    """The interpolation order of a BendRequest (unset: 1), checked by the export's options (0, 1 or 3)."""
    from napari_unwind.pipeline import ExportOptions

    return ExportOptions(order=int(msg.order) if msg.has_order else 1).order


def average_options(req: Any) -> dict[str, Any]:
    """The keyword options of :func:`napari_unwind.average.average` from an AverageRequest: at least two
    specimens, each named once, landmarks for all of them (the same count) or none. Whether the landmarks increase
    and lie inside each specimen's length is checked as the job runs (it needs the volumes)."""
    ids = [sp.volume_id for sp in req.specimens]
    if len(ids) < 2:
        raise InvalidInputError(f"an average needs at least 2 straight specimens, got {len(ids)}")
    if any(not i for i in ids):
        raise InvalidInputError("every specimen of an average needs a volume_id")
    if len(set(ids)) != len(ids):
        dup = next(i for i in ids if ids.count(i) > 1)
        raise InvalidInputError(f"volume {dup} is given twice: give each specimen once")
    counts = {len(sp.landmarks) for sp in req.specimens}
    if len(counts) > 1:
        raise InvalidInputError(f"the specimens have {' and '.join(map(str, sorted(counts)))} landmarks: give every "
                                "specimen the same landmarks, or none")
    return dict(stations=int(req.stations) or None,
                landmarks=[list(sp.landmarks) for sp in req.specimens] if counts != {0} else None,
                scale="none" if req.keep_size else "length", normalise="none" if req.keep_grey_values else "robust",
                max_roll=float(req.max_roll) if req.has_max_roll else 90.0)


def export_options_msg(opt: Any, output_name: str = "") -> warp_pb2.ExportOptions:
    """The message of a :class:`napari_unwind.pipeline.ExportOptions` (``max_output`` is the server's)."""
    return warp_pb2.ExportOptions(order=opt.order, has_order=True, spacing=opt.spacing or 0.0, pad=opt.pad,
                                  chunks=list(opt.chunks or ()), allow_folds=opt.allow_folds,
                                  output_name=output_name)


def result_figures(r: Any) -> dict[str, Any]:
    """The figures of a :class:`napari_unwind.pipeline.SpecimenResult` for a JobResult: ``status``, ``reason``
    and the skeleton's figures (absent ones left out)."""
    from napari_unwind.io._volume import unit_label
    from napari_unwind.skeleton._foldfree import format_lost

    values = dict(status=r.status, reason=r.reason, length=r.length, unit=r.unit or "", keyframes=r.keyframes,
                  min_jacobian=r.min_jacobian, max_tilt=r.max_tilt, coverage=r.coverage, folded=r.folded,
                  lost=format_lost(r.lost, unit_label(r.unit)) if r.lost else "")
    return {k: v for k, v in values.items() if v is not None}


# ------------------------------------------------------------------------------------------------------------------
# the pipeline's verdict on a specimen (napari_unwind.pipeline.SpecimenResult <-> SpecimenVerdict)
# ------------------------------------------------------------------------------------------------------------------
#: SpecimenStatus values and the pipeline's status names (napari_unwind.pipeline.STATUSES).
STATUSES = {pb.SPECIMEN_STATUS_OK: "ok", pb.SPECIMEN_STATUS_PARTIAL: "partial", pb.SPECIMEN_STATUS_FAILED: "failed",
            pb.SPECIMEN_STATUS_REJECTED: "rejected", pb.SPECIMEN_STATUS_UNRESOLVED: "unresolved"}
_STATUS_ENUMS = {v: k for k, v in STATUSES.items()}
_OPTIONAL = ("length", "keyframes", "min_jacobian", "max_tilt", "coverage", "folded", "voxels")


def verdict_msg(r: Any) -> pb.SpecimenVerdict:
    """The message of a :class:`napari_unwind.pipeline.SpecimenResult`: its status, reason and figures as the
    pipeline judged them (None figures left unset)."""
    msg = pb.SpecimenVerdict(status=_STATUS_ENUMS[r.status], reason=r.reason, unit=r.unit or "",
                             ids=[int(i) for i in r.ids])
    for name in _OPTIONAL:
        v = getattr(r, name)
        if v is not None:
            setattr(msg, name, int(v) if name in ("keyframes", "voxels") else float(v))
    for a, b, f in r.lost:
        msg.lost.add(s_start=float(a), s_end=float(b), fraction=float(f))
    return msg


def specimen_result(result: pb.JobResult, **fields_: Any):
    """The :class:`napari_unwind.pipeline.SpecimenResult` a skeleton or pipeline job's result carries (status,
    reason, figures, warnings); ``fields_`` set the others (session, output...). Raises
    :class:`~napari_unwind.errors.InvalidInputError` when the result holds no verdict (it is never read as ok)."""
    from napari_unwind.pipeline import SpecimenResult

    if not result.HasField("verdict") or result.verdict.status not in STATUSES:
        raise InvalidInputError("the job's result carries no verdict (status, reason, coverage): a skeleton or "
                                "pipeline job of a server of this version has one")
    v = result.verdict
    values: dict[str, Any] = dict(status=STATUSES[v.status], reason=v.reason, unit=v.unit or None,
                                  ids=tuple(int(i) for i in v.ids),
                                  lost=tuple((x.s_start, x.s_end, x.fraction) for x in v.lost),
                                  warnings=tuple(result.warnings))
    for name in _OPTIONAL:
        values[name] = getattr(v, name) if v.HasField(name) else None
    values.update(fields_)
    return SpecimenResult(**values)
