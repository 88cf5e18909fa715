"""Protobuf <-> core values: the only translation layer (no domain logic)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from napari_unwind.errors import InvalidInputError

from ._proto.unwind.v1 import common_pb2 as pb
from ._proto.unwind.v1 import segmentation_pb2, skeleton_pb2, volume_pb2, warp_pb2
from .errors import LimitError

__all__ = ["DTYPES", "dtype_of", "dtype_enum", "points", "point_msg", "endpoints", "volume_info", "feature_msg",
           "skeleton_options", "skeleton_options_msg", "export_options", "export_options_msg",
           "result_figures", "verdict_msg", "specimen_result", "STATUSES"]

DTYPES = {
    pb.DTYPE_UINT8: np.dtype("uint8"), pb.DTYPE_INT8: np.dtype("int8"),
    pb.DTYPE_UINT16: np.dtype("uint16"), pb.DTYPE_INT16: np.dtype("int16"),
    pb.DTYPE_UINT32: np.dtype("uint32"), pb.DTYPE_INT32: np.dtype("int32"),
    pb.DTYPE_FLOAT32: np.dtype("float32"), pb.DTYPE_FLOAT64: np.dtype("float64"),
}
_ENUMS = {v: k for k, v in DTYPES.items()}


def dtype_of(value: int) -> np.dtype:
    if value not in DTYPES:
        raise InvalidInputError(f"dtype must be one of {', '.join(pb.DType.Name(k) for k in DTYPES)}, got "
                                f"{pb.DType.Name(value) if value in pb.DType.values() else value}")
    return DTYPES[value]


def dtype_enum(dtype: Any) -> int:
    return _ENUMS.get(np.dtype(dtype), pb.DTYPE_UNSPECIFIED)


def points(msgs: Sequence[pb.Point], what: str) -> np.ndarray:
    """(N, 3) array of points; refuses NaN and infinity."""
    arr = np.array([(p.axis0, p.axis1, p.axis2) for p in msgs], dtype=float).reshape(-1, 3)
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
    arr = np.asarray(msg.coords, dtype=float).reshape(-1, 3)
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise InvalidInputError(f"point {i} is not a finite point: {tuple(arr[i])}; give three finite numbers "
                                "(axis0, axis1, axis2)")
    return arr


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
    return SkeletonOptions(**given)


def skeleton_options_msg(opt: Any) -> skeleton_pb2.SkeletonOptions:
    """The message of a :class:`napari_unwind.pipeline.SkeletonOptions` (every field given)."""
    return skeleton_pb2.SkeletonOptions(
        no_twist=not opt.estimate_twist, levels=opt.n_levels, smoothing_iterations=opt.smoothing_iterations,
        has_smoothing_iterations=True, cage_radius=opt.cage_radius, tolerance=opt.tolerance,
        snap_tolerance=opt.snap_tolerance, half_extent=list(opt.half_extent or ()), cage_margin=opt.cage_margin,
        has_cage_margin=True)


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
            pb.SPECIMEN_STATUS_REJECTED: "rejected"}
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
