"""The job kinds: each is a generator that drives core generators, yields their Progress and returns a JobResult.

Thin glue only: protobuf in, core calls, protobuf out. The pipeline and skeleton jobs call
:mod:`napari_unwind.pipeline` (the same run, options, defaults and fold rule as ``unwind run``), so the local and
the remote pipeline write the same voxels; their results carry the pipeline's verdict on the specimen (``verdict``:
status, reason, coverage, folds; :func:`napari_unwind.pipeline.judge`), and the same in the figures as text.
"""

from __future__ import annotations

import time
from collections.abc import Generator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from napari_unwind.errors import InvalidInputError
from napari_unwind.progress import Progress

from . import convert
from ._proto.unwind.v1 import common_pb2 as pb
from ._proto.unwind.v1 import jobs_pb2
from .catalog import Catalog
from .errors import StateError
from .paths import check_file_name

__all__ = ["TaskContext", "KINDS", "kind_of", "precheck", "run_task"]

TaskGen = Generator[Progress, None, pb.JobResult]


@dataclass
class TaskContext:
    """What a running job may touch: its owner's objects and its own work folder."""

    catalog: Catalog
    owner: str
    job_id: str
    workdir: Path
    scheduler: str | None = None

    def output(self, name: str, default: str) -> Path:
        from napari_unwind.io._formats import output_format

        name = check_file_name(name or default, "output_name")
        output_format(name)  # an unknown suffix fails now, before any work
        return self.workdir / name

    def register(self, path: Path, name: str) -> str:
        row, _ = self.catalog.add_volume(self.owner, Path(path), name, "output", self.job_id)
        return row.id


KINDS = {
    "segment": pb.JOB_KIND_SEGMENT,
    "select": pb.JOB_KIND_SELECT,
    "estimate_deformation": pb.JOB_KIND_ESTIMATE_DEFORMATION,
    "straighten": pb.JOB_KIND_STRAIGHTEN,
    "bend": pb.JOB_KIND_BEND,
    "pipeline": pb.JOB_KIND_PIPELINE,
    "measure": pb.JOB_KIND_MEASURE,
    "average": pb.JOB_KIND_AVERAGE,
}


def kind_of(spec: jobs_pb2.SubmitRequest) -> str:
    which = spec.WhichOneof("spec")
    if which is None:
        raise InvalidInputError("a job needs a spec: one of " + ", ".join(KINDS))
    return which


def _figures(**values: Any) -> dict[str, str]:
    out = {}
    for k, v in values.items():
        if isinstance(v, float):
            out[k] = f"{v:.6g}"
        elif isinstance(v, (list, tuple)):
            out[k] = " ".join(f"{x:.6g}" if isinstance(x, float) else str(x) for x in v)
        else:
            out[k] = str(v)
    return out


def _save_session(ctx: TaskContext, session: Any, name: str) -> tuple[str, str]:
    from napari_unwind.session import save_session

    path = save_session(session, ctx.workdir / name, overwrite=False)
    return _register_session(ctx, path)


def _portable(source: Any, row: Any) -> Any:
    """The session's source as a client can use it: the scan named by its volume's name (a plain file name), never
    the server's absolute path. Next to the session file, ``load_session`` resolves it to the scan downloaded or
    copied there; its checksum, size and shape are the server's file's, so ``verify_source`` still proves it is the
    same scan."""
    from dataclasses import replace

    return replace(source, path=row.name)


def _named(volume: Any, row: Any) -> Any:
    """A stored volume as a job's output may describe it: its ``source`` the name the user gave it, not the
    server's path (written into outputs as their source, e.g. a straight volume's ``straightening.source``)."""
    from dataclasses import replace

    return replace(volume, source=row.name)


def _register_session(ctx: TaskContext, path: Path) -> tuple[str, str]:
    name = Path(path).name
    row = ctx.catalog.store.add_object(ctx.owner, "session", name, ctx.catalog.root.relative(path), {}, ctx.job_id)
    return row.id, Path(path).read_text()


# ------------------------------------------------------------------------------------------------------------------
def segment(ctx: TaskContext, req: Any) -> TaskGen:
    from napari_unwind.segmentation import join_tree_iter, save_features_iter

    vrow, volume = ctx.catalog.volume(ctx.owner, req.volume_id)
    volume = _named(volume, vrow)
    k = req.features or 5
    t0 = time.perf_counter()
    tree = yield from join_tree_iter(volume, level=req.level if req.has_level else None,
                                     smooth=req.smooth if req.has_smooth else 1.0)
    yield Progress("simplify", 0, 1, f"{k} features")
    features = tree.simplify(k)
    yield Progress("simplify", 1, 1)
    tree_path = tree.to_npz(ctx.workdir / "tree.npz")
    features_path = yield from save_features_iter(features, ctx.workdir / "features.zarr")
    root = ctx.catalog.root
    row = ctx.catalog.store.add_object(
        ctx.owner, "segmentation", f"{vrow.name} k={k}", root.relative(ctx.workdir),
        {"volume_id": vrow.id, "k": k, "level": int(features.level), "tree": root.relative(Path(tree_path)),
         "features": root.relative(Path(features_path)), "maxima": int(tree.n_maxima)}, ctx.job_id)
    return pb.JobResult(segmentation_id=row.id, figures=_figures(
        features=features.k, level=int(features.level), seconds=time.perf_counter() - t0))


def select(ctx: TaskContext, req: Any) -> TaskGen:
    from napari_unwind.segmentation import default_isovalue, load_features, refine_mask_iter, select, selected_ids

    seg = ctx.catalog.segmentation(ctx.owner, req.segmentation_id)
    vrow, volume = ctx.catalog.volume(ctx.owner, seg.meta["volume_id"])
    volume = _named(volume, vrow)
    out = ctx.output(req.output_name, "mask.zarr")
    seeds = convert.points(req.seeds, "seed")
    k = req.features or int(seg.meta["k"])
    if k == int(seg.meta["k"]):
        path = ctx.catalog.root.absolute(seg.meta["features"])
    elif str(k) in seg.meta.get("labels", {}):
        path = ctx.catalog.path(ctx.catalog.store.get_object(ctx.owner, seg.meta["labels"][str(k)], "volume"))
    else:
        raise StateError(f"segmentation {seg.id} has no simplification to {k} features; call Simplify with "
                         f"features={k} first")
    features = load_features(path)
    ids = selected_ids(features, seeds=seeds if len(seeds) else None, ids=list(req.ids) or None)
    working = select(features, ids=ids, fill_holes=req.fill_holes)
    iso = req.isovalue if req.has_isovalue else default_isovalue(features, working, volume=volume)  # every face
    written = yield from refine_mask_iter(volume, working, features=features, isovalue=iso, output=out)
    return pb.JobResult(volume_id=ctx.register(written, out.name),
                        figures=_figures(ids=ids, features=k, isovalue=float(iso)))


def estimate_deformation(ctx: TaskContext, req: Any) -> TaskGen:
    from napari_unwind.pipeline import SpecimenResult, skeleton_step
    from napari_unwind.session import Session, SourceInfo

    mrow, mask = ctx.catalog.volume(ctx.owner, req.mask_volume_id)
    srow, scan = ctx.catalog.volume(ctx.owner, req.volume_id) if req.volume_id else (mrow, mask)
    notes = []
    if scan is not mask:  # the scan's shape, or a box of its grid placed by its origin (named as the user named it)
        from napari_unwind.io._grid import place_on_grid

        mask, note = place_on_grid(_named(mask, mrow), scan)
        notes = [note] if note else []
    endpoints = convert.endpoints(req.ends, req.HasField("ends"))
    options = convert.skeleton_options(req.options)
    t0 = time.perf_counter()
    result = yield from skeleton_step(mask.data, endpoints, spacing=scan.spacing, origin=scan.origin, unit=scan.unit,
                                      volume=None if scan is mask else scan.data, options=options)
    dt = time.perf_counter() - t0
    yield Progress("checksum", 0, 1, "describing the source")
    source = _portable(SourceInfo.from_path(ctx.catalog.path(srow), volume=scan), srow)
    session = Session(source=source, deformation=result.deformation, endpoints=result.endpoints,
                      twist=result.twist_profile(), notes=f"unwind server job {ctx.job_id}: mask {mrow.name}"
                            + ("; suggested endpoints" if result.suggested else ""))
    sid, text = _save_session(ctx, session, "session.unwind.json")
    yield Progress("checksum", 1, 1)
    r = SpecimenResult.of(result)
    return pb.JobResult(session_id=sid, session_json=text, warnings=notes + list(result.warnings), figures=_figures(
        **convert.result_figures(r), seconds=dt, suggested=bool(result.suggested)), verdict=convert.verdict_msg(r))


def straighten(ctx: TaskContext, req: Any) -> TaskGen:
    from dataclasses import replace

    from napari_unwind.pipeline import export_step
    from napari_unwind.session import SourceInfo

    vrow, volume = ctx.catalog.volume(ctx.owner, req.volume_id)
    volume = _named(volume, vrow)
    _, session = ctx.catalog.session(ctx.owner, req.session_id)
    # the session embedded in the output names its scan as the session file does (a name beside it), not by the
    # server's path that loading it resolved
    session = replace(session, source=replace(session.source, path=Path(session.source.path).name))
    out = ctx.output(req.options.output_name, "straight.zarr")
    if tuple(session.source.shape) != tuple(volume.shape):
        raise InvalidInputError(f"the session was made on a scan of shape {tuple(session.source.shape)} but the "
                                f"volume has shape {volume.shape}")
    channels = []
    if req.channels:
        names = [req.scan_name or "scan", *_channel_names(req)]
        if len(set(names)) != len(names):
            raise InvalidInputError(f"the scan's channel name {names[0]!r} is also another channel's: name each "
                                    "channel once")
        volume = volume.with_data(volume.data, metadata={**volume.metadata, "channel": names[0]})
        records = []
        for c in req.channels:
            crow, v = ctx.catalog.volume(ctx.owner, c.volume_id)
            if tuple(v.shape) != tuple(volume.shape):
                raise InvalidInputError(f"channel {c.name!r} has shape {tuple(v.shape)} but the scan has "
                                        f"{tuple(volume.shape)}: channels must share the scan's grid")
            yield Progress("checksum", len(records), len(req.channels), f"describing channel {c.name}")
            # the session of the output records each other channel, as `unwind straighten A B` does: by its
            # volume's name and content checksum (never the server's path)
            records.append(replace(_portable(SourceInfo.from_path(ctx.catalog.path(crow), volume=v), crow),
                                   channel=c.name, dtype=str(v.dtype), shape=tuple(v.shape)))
            channels.append(_named(v, crow).with_data(v.data, metadata={**v.metadata, "channel": c.name}))
        session = replace(session, channels=(*session.channels, *records))
    t0 = time.perf_counter()
    written = yield from export_step(volume, session.deformation, out, options=convert.export_options(req.options),
                                     session=session, scheduler=ctx.scheduler, channels=channels)
    return pb.JobResult(volume_id=ctx.register(written, out.name),
                        figures=_figures(seconds=time.perf_counter() - t0))


def bend(ctx: TaskContext, req: Any) -> TaskGen:
    from napari_unwind.io import write_volume_iter
    from napari_unwind.warp import bend

    _, straight = ctx.catalog.volume(ctx.owner, req.volume_id)
    _, session = ctx.catalog.session(ctx.owner, req.session_id)
    out = ctx.output(req.output_name, "bent.zarr")
    d = session.deformation
    data = bend(straight, d, shape=tuple(session.source.shape), order=convert.order(req))
    written = yield from write_volume_iter(data, out, spacing=d.spacing, origin=d.origin, unit=session.source.unit)
    return pb.JobResult(volume_id=ctx.register(written, out.name))


def _channel_names(req: Any) -> list[str]:
    """The measure request's channel names (each given, distinct)."""
    names = [c.name for c in req.channels]
    if any(not n for n in names):
        raise InvalidInputError("every channel needs a name (the columns are <name>_mean, ...)")
    if len(set(names)) != len(names):
        raise InvalidInputError("two channels have the same name: name each channel once")
    return names


def measure(ctx: TaskContext, req: Any) -> TaskGen:
    """``unwind measure`` as a job: :func:`napari_unwind.measure.measure_iter`; the CSV in the result."""
    from napari_unwind.measure import measure_iter

    _, session = ctx.catalog.session(ctx.owner, req.session_id)

    def volume(volume_id: str) -> Any:
        return ctx.catalog.volume(ctx.owner, volume_id)[1] if volume_id else None

    channels = {n: volume(c.volume_id) for n, c in zip(_channel_names(req), req.channels, strict=True)}
    # a mask and a label image of the scan's shape are on its grid voxel for voxel, as the pipeline takes a mask
    mask, mask_note = session.on_scan_grid(volume(req.mask_volume_id), "mask")
    soft = None
    if mask is not None:  # a float map of fractional values, thresholded as measure_iter would (said in the result)
        from napari_unwind.pipeline import specimen_mask

        mask, soft = specimen_mask(mask)
    labels, labels_note = session.on_scan_grid(volume(req.labels_volume_id), "label image")
    t0 = time.perf_counter()
    profile = yield from measure_iter(session.deformation, mask=mask, labels=labels, channels=channels or None,
                                      spacing=req.spacing or None)
    return pb.JobResult(table_csv=profile.csv_text(), warnings=[n for n in (mask_note, soft, labels_note) if n],
                        figures=_figures(stations=len(profile), seconds=time.perf_counter() - t0))


def average(ctx: TaskContext, req: Any) -> TaskGen:
    """``unwind average`` as a job: :func:`napari_unwind.average.average_iter` on the server's scheduler; the
    mean, median and std stored as volumes, the residuals' CSV in the result."""
    from napari_unwind.average import average_iter
    from napari_unwind.io import write_volume_iter

    options = convert.average_options(req)
    rows = [ctx.catalog.volume(ctx.owner, sp.volume_id) for sp in req.specimens]
    out = ctx.output(req.output_name, "mean.ome.zarr")
    stem, _, suffix = out.name.partition(".")
    paths = {"mean": out, "median": out.with_name(f"{stem}.median.{suffix}"),
             "std": out.with_name(f"{stem}.std.{suffix}")}
    t0 = time.perf_counter()
    res = yield from average_iter([v for _, v in rows], names=[r.name for r, _ in rows], scheduler=ctx.scheduler,
                                  **options)
    ids = {}
    for what, path in paths.items():
        written = yield from write_volume_iter(getattr(res, what), path, spacing=(res.spacing,) * 3, unit=res.unit)
        ids[what] = ctx.register(written, path.name)
    worst = int(np.argmin(res.correlation))
    return pb.JobResult(volume_id=ids["mean"], volumes=ids, table_csv=res.csv_text(),
                        figures=_figures(specimens=len(rows), shape=list(res.mean.shape), spacing=res.spacing,
                                         least_like_the_mean=res.names[worst], seconds=time.perf_counter() - t0))


def _one_specimen(req: Any) -> None:
    """A pipeline request says which specimen in exactly one way."""
    ways = sum((len(req.select) > 0, bool(req.mask_volume_id), len(req.ids) > 0))
    if ways != 1:
        raise InvalidInputError("say which specimen to straighten with exactly one of: select points (the scan is "
                                "segmented first), ids of a segmentation, or a mask volume")
    if req.ids and not req.segmentation_id:
        raise InvalidInputError("feature ids need the segmentation they refer to (segmentation_id)")


def pipeline(ctx: TaskContext, req: Any) -> TaskGen:
    """``unwind run`` as a job: :func:`napari_unwind.pipeline.run_iter` (segment or a mask, select, refine,
    skeleton, session, straighten); the figures carry the specimen's status and reason."""
    from napari_unwind.pipeline import run_iter
    from napari_unwind.segmentation import load_features
    from napari_unwind.session import SourceInfo

    vrow, volume = ctx.catalog.volume(ctx.owner, req.volume_id)
    path, volume = ctx.catalog.path(vrow), _named(volume, vrow)
    out = ctx.output(req.export.output_name, "straight.zarr")
    seeds = convert.points(req.select, "select point")
    _one_specimen(req)
    options = convert.pipeline_options(req)
    endpoints = convert.endpoints(req.ends, req.HasField("ends"))
    t_all = time.perf_counter()
    chosen: dict[str, Any] = {}
    if req.mask_volume_id:
        from napari_unwind.io._grid import place_on_grid

        mrow, mask_vol = ctx.catalog.volume(ctx.owner, req.mask_volume_id)
        chosen["mask"] = place_on_grid(_named(mask_vol, mrow), volume)[0].data
    elif req.ids:
        seg = ctx.catalog.segmentation(ctx.owner, req.segmentation_id)
        if seg.meta["volume_id"] != vrow.id:
            raise InvalidInputError(f"segmentation {seg.id} was made on another volume than {vrow.id}")
        chosen.update(features=load_features(ctx.catalog.root.absolute(seg.meta["features"])), ids=list(req.ids))
    else:
        chosen["seeds"] = seeds
    stem = out.name.split(".")[0] or "straight"
    session_path = ctx.workdir / f"{stem}.unwind.json"
    # the session (its file and the copy inside the straight volume) names the scan by its volume's name, never by
    # the server's path (see _portable)
    yield Progress("checksum", 0, 1, "describing the source")
    source = _portable(SourceInfo.from_path(path, volume=volume), vrow)
    yield Progress("checksum", 1, 1)
    r = yield from run_iter(volume, endpoints=endpoints, options=options, output=out, session_path=session_path,
                            source=source, notes=f"unwind run (server job {ctx.job_id})",
                            scheduler=ctx.scheduler, **chosen)
    sid, text = _register_session(ctx, session_path)
    figures: dict[str, Any] = convert.result_figures(r)
    seg_record = r.session.segmentation
    if seg_record is not None:
        figures.update(ids=list(seg_record.selected), isovalue=float(seg_record.isovalue))
    e = r.session.endpoints
    figures.update(seconds=time.perf_counter() - t_all, head=list(np.round(e.head, 3)), tail=list(np.round(e.tail, 3)))
    return pb.JobResult(volume_id=ctx.register(r.output, out.name), session_id=sid, session_json=text,
                        warnings=list(r.warnings), figures=_figures(**figures), verdict=convert.verdict_msg(r))


_REFS = (("volume_id", "volume"), ("mask_volume_id", "volume"), ("labels_volume_id", "volume"),
         ("segmentation_id", "segmentation"), ("session_id", "session"))
_REQUIRED = {"segment": ("volume_id",), "select": ("segmentation_id",), "estimate_deformation": ("mask_volume_id",),
             "straighten": ("volume_id", "session_id"), "bend": ("volume_id", "session_id"),
             "pipeline": ("volume_id",), "measure": ("session_id",), "average": ()}


#: The core's options of each kind of job, built from its request (a bad value is refused as the job runs would).
_OPTIONS = {"segment": convert.segment_options, "select": convert.segment_options,
            "estimate_deformation": lambda r: convert.skeleton_options(r.options),
            "straighten": lambda r: convert.export_options(r.options), "bend": convert.order,
            "pipeline": convert.pipeline_options, "measure": _channel_names, "average": convert.average_options}


def precheck(catalog: Catalog, owner: str, spec: jobs_pb2.SubmitRequest) -> None:
    """Refuse at Submit, not minutes later when the job runs: a field out of its bounds
    (:func:`unwind_services.convert.check_request`), options the core refuses (the same
    :mod:`napari_unwind.pipeline` options the job builds), malformed points (NaN, infinity), bad output names,
    and ids the owner does not have."""
    which = kind_of(spec)
    convert.check_request(spec)
    req = getattr(spec, which)
    _OPTIONS[which](req)
    if which == "pipeline":
        _one_specimen(req)
    required = _REQUIRED[which]
    for field_name, what in (("seeds", "seed"), ("select", "select point")):
        if hasattr(req, field_name):
            convert.points(getattr(req, field_name), what)
    if hasattr(req, "ends") and req.HasField("ends"):
        convert.endpoints(req.ends, True)
    if hasattr(req, "options") and hasattr(req.options, "output_name") and req.options.output_name:
        check_file_name(req.options.output_name, "output_name")
    if getattr(req, "output_name", ""):
        check_file_name(req.output_name, "output_name")
    if hasattr(req, "export") and req.export.output_name:
        check_file_name(req.export.output_name, "output_name")
    for field_name, kind in _REFS:
        if hasattr(req, field_name) and (getattr(req, field_name) or field_name in required):
            catalog.store.get_object(owner, getattr(req, field_name), kind)
    for channel in getattr(req, "channels", ()):
        catalog.store.get_object(owner, channel.volume_id, "volume")
    for specimen in getattr(req, "specimens", ()):
        catalog.store.get_object(owner, specimen.volume_id, "volume")


_TASKS = {"segment": segment, "select": select, "estimate_deformation": estimate_deformation,
          "straighten": straighten, "bend": bend, "pipeline": pipeline, "measure": measure, "average": average}


def run_task(ctx: TaskContext, spec: jobs_pb2.SubmitRequest) -> TaskGen:
    kind = kind_of(spec)
    return _TASKS[kind](ctx, getattr(spec, kind))
