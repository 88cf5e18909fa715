"""Straighten every specimen of a scan with no click: segment, keep the specimen-like features, and for each one
select -> suggested ends -> skeleton -> export, with a summary table.

:func:`straighten_all_iter` is the driver of ``unwind run SCAN --all -o OUTDIR``. A specimen that fails (no
skeleton, a fold over it, an output that cannot be written) is reported in the table with its reason and the
others go on.

Output folder
-------------
``specimen-<id>.zarr``
    The straightened volume of feature ``<id>`` (OME-Zarr, the session embedded).
``specimen-<id>.unwind.json``
    Its session (scan, segmentation, ends, deformation), for ``unwind straighten --session`` or the plugin.
``specimens.csv``
    One row per specimen: ``specimen`` (feature id), ``status`` (``ok`` or ``failed``), ``voxels`` (labelled
    working-resolution voxels), ``length`` (centreline, physical units), ``unit``, ``keyframes``,
    ``min_jacobian``, ``max_tilt`` (degrees), ``coverage`` (fraction of the mask inside the cage; empty when the
    skeleton does not report it), ``output``, ``session`` (file names in the folder) and ``reason`` (why it
    failed).
"""

from __future__ import annotations

import csv
import io
import math
import os
import time
import warnings
from collections.abc import Generator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import InvalidInputError, OutputError
from .io._volume import unit_label
from .progress import Progress

__all__ = ["BatchResult", "CSV_NAME", "CSV_COLUMNS", "straighten_all_iter", "straighten_all"]

CSV_NAME = "specimens.csv"
CSV_COLUMNS = ("specimen", "status", "voxels", "length", "unit", "keyframes", "min_jacobian", "max_tilt",
               "coverage", "output", "session", "reason")


@dataclass
class BatchResult:
    """What :func:`straighten_all_iter` did.

    Attributes
    ----------
    rows : list of dict
        One per specimen, the columns of :data:`CSV_COLUMNS` (numbers as numbers, None when absent).
    table : Path
        The summary CSV.
    features : Features
        The segmentation the specimens came from.
    seconds : float
        Wall time of the whole run.
    """

    rows: list[dict[str, Any]] = field(default_factory=list)
    table: Path | None = None
    features: Any = None
    seconds: float = 0.0

    @property
    def failed(self) -> list[dict[str, Any]]:
        """The rows of the specimens that failed."""
        return [r for r in self.rows if r["status"] != "ok"]


def _check_outdir(outdir: Path, overwrite: bool) -> None:
    if outdir.exists() and not outdir.is_dir():
        raise OutputError(f"the output folder {outdir} is a file; give a folder for --all (it is created)")
    if outdir.is_dir() and not overwrite:
        taken = sorted(p.name for p in outdir.iterdir() if p.name == CSV_NAME or p.name.startswith("specimen-"))
        if taken:
            raise OutputError(f"{outdir} already holds results of a batch ({', '.join(taken[:3])}"
                              f"{', ...' if len(taken) > 3 else ''}); choose another folder or pass --overwrite")
    if not outdir.is_dir():
        parent = outdir.absolute().parent
        if not parent.is_dir():
            raise OutputError(f"cannot create the output folder {outdir}: {parent} does not exist")
        if not os.access(parent, os.W_OK):
            raise OutputError(f"cannot create the output folder {outdir}: {parent} is not writable")


def _num(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _write_table(rows: list[dict[str, Any]], path: Path) -> Path:
    from .io._atomic import atomic_output

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]))
                    for k in CSV_COLUMNS})
    with atomic_output(path, overwrite=True) as tmp:
        Path(tmp).write_text(buf.getvalue(), encoding="utf-8")
    return path


def _one(volume: Any, features: Any, st: Any, source: Any, outdir: Path, *, allow_folds: bool, order: int,
         overwrite: bool, skeleton: dict[str, Any]) -> Generator[Progress, None, dict[str, Any]]:
    """Straighten one specimen; returns its row (raises on failure)."""
    from .segmentation import refine_mask_iter, select
    from .session import Segmentation, Session, save_session
    from .skeleton import estimate_deformation_iter
    from .warp import FoldWarning, export_iter

    working = select(features, ids=[st.id])
    mask = yield from refine_mask_iter(volume, working, features=features, isovalue=st.threshold)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the row and the reason say what matters
        result = yield from estimate_deformation_iter(mask, None, spacing=volume.spacing, origin=volume.origin,
                                                      unit=volume.unit, volume=volume.data, **skeleton)
    d = result.deformation
    row = dict(length=_num(d.length), unit=d.unit, keyframes=len(d),
               min_jacobian=_num(getattr(result, "min_jacobian", None)),
               max_tilt=_num(getattr(result, "max_tilt", None)),
               coverage=_num(getattr(result, "coverage", None)))
    seg = Segmentation(k=features.k, level=features.level, selected=(st.id,),
                       seeds=(tuple(float(c) for c in st.max_position_full),), isovalue=float(st.threshold))
    session = Session(source=source, deformation=d, segmentation=seg, endpoints=result.endpoints,
                      notes=f"unwind run --all: feature {st.id} of {features.k}, suggested endpoints")
    session_path = save_session(session, outdir / f"specimen-{st.id}.unwind.json", overwrite=overwrite)
    row["session"] = session_path.name
    folds = d.folds()
    folded = _num(getattr(result, "folded", None))  # fraction of the mask in the folds, when the skeleton says
    if folds and not allow_folds and folded != 0:  # a fold over empty cage corners only is no reason to stop
        where = ", ".join(f"s = {a:.4g}..{b:.4g}" for a, b in folds)
        over = "" if folded is None else f", over {100 * folded:.2g} % of the specimen's mask"
        raise InvalidInputError(f"the deformation folds ({where} {unit_label(d.unit)}{over}); the session was saved: "
                                f"edit it (--cage, --cage-margin), or export it with unwind straighten --session "
                                f"{session_path.name} --allow-folds")
    out = outdir / f"specimen-{st.id}.zarr"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FoldWarning)
        written = yield from export_iter(volume, d, out, order=order, overwrite=overwrite,
                                         session=session.to_dict())
    row["output"] = Path(written).name
    return row


def straighten_all_iter(
    scan: str | os.PathLike,
    outdir: str | os.PathLike,
    *,
    features: int | None = None,
    level: int | None = None,
    smooth: float = 1.0,
    min_elongation: float = 3.0,
    allow_folds: bool = False,
    order: int = 1,
    overwrite: bool = False,
    reader_options: dict[str, Any] | None = None,
    skeleton: dict[str, Any] | None = None,
) -> Generator[Progress, None, BatchResult]:
    """Straighten every specimen of a scan (generator: yields progress, returns a :class:`BatchResult`).

    Parameters
    ----------
    scan : str or path-like
        The scan (any format :func:`~napari_unwind.io.open_volume` reads).
    outdir : str or path-like
        The folder for the results (created; see the module docstring). Without ``overwrite`` it must not hold
        results of an earlier batch.
    features : int, optional
        Features the segmentation keeps, 1..100. Default: every feature above the noise level (at most 100).
    level, smooth
        As :func:`~napari_unwind.segmentation.segment`.
    min_elongation : float
        As :func:`~napari_unwind.segmentation.specimens`.
    allow_folds : bool
        Export a specimen whose deformation folds over its mask instead of reporting it as failed (a fold over
        no voxel of the mask, only empty cage corners, never stops the export).
    order : int
        Interpolation order of the export (0, 1 or 3).
    overwrite : bool
        Replace results already in ``outdir``.
    reader_options : dict, optional
        Options of :func:`~napari_unwind.io.open_volume` (``format``, ``series``).
    skeleton : dict, optional
        Options of :func:`~napari_unwind.skeleton.estimate_deformation` for every specimen.

    Returns
    -------
    BatchResult
        Its ``rows`` hold every specimen, the failed ones with ``status`` ``"failed"`` and a ``reason``.

    Raises
    ------
    UnwindError
        When the scan cannot be read or segmented, or ``outdir`` cannot be used; a specimen's failure is a row.
    """
    from .io import open_volume
    from .segmentation import join_tree_iter, specimens
    from .segmentation._common import MAX_FEATURES, check_features_count
    from .session import SourceInfo

    t_all = time.perf_counter()
    outdir = Path(outdir)
    _check_outdir(outdir, overwrite)
    if features is not None:
        features = check_features_count(features)
    volume = open_volume(scan, **(reader_options or {}))
    tree = yield from join_tree_iter(volume, level=level, smooth=smooth)
    k = features if features is not None else int(min(MAX_FEATURES, max(1, int(tree.significant.sum()))))
    k = min(k, tree.n_maxima)
    yield Progress("simplify", 0, 1, f"{k} features")
    feats = tree.simplify(k)
    yield Progress("simplify", 1, 1)
    found = specimens(feats, min_elongation=min_elongation)
    source = SourceInfo.from_path(scan, volume=volume)
    outdir.mkdir(exist_ok=True)
    result = BatchResult(features=feats)
    for i, st in enumerate(found):
        yield Progress("specimens", i, len(found), f"feature {st.id}")
        row: dict[str, Any] = dict(specimen=st.id, status="ok", voxels=st.voxel_count)
        gen = _one(volume, feats, st, source, outdir, allow_folds=allow_folds, order=order, overwrite=overwrite,
                   skeleton=dict(skeleton or {}))
        try:
            row.update((yield from gen))
        except Exception as exc:  # noqa: BLE001 - one specimen's failure must not stop the others
            msg = " ".join(str(exc).split()) or type(exc).__name__
            row.update(status="failed", reason=msg if hasattr(exc, "__module__") and
                       type(exc).__module__.startswith("napari_unwind") else f"{type(exc).__name__}: {msg}")
            if (outdir / f"specimen-{st.id}.unwind.json").exists():
                row.setdefault("session", f"specimen-{st.id}.unwind.json")
        result.rows.append(row)
    yield Progress("specimens", len(found), len(found))
    result.table = _write_table(result.rows, outdir / CSV_NAME)
    result.seconds = time.perf_counter() - t_all
    return result


def straighten_all(scan: str | os.PathLike, outdir: str | os.PathLike, *, progress=None, **options: Any
                   ) -> BatchResult:
    """Straighten every specimen of a scan: :func:`straighten_all_iter` run to the end (``progress`` is called
    with each :class:`~napari_unwind.progress.Progress`)."""
    from .progress import run

    return run(straighten_all_iter(scan, outdir, **options), progress)
