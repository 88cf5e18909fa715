"""Straighten every specimen of a scan with no click: the batch face of :mod:`napari_unwind.pipeline`.

:func:`straighten_all_iter` is :func:`napari_unwind.pipeline.run_all_iter` with flat keyword options (the driver
of ``unwind run SCAN --all -o OUTDIR``); this module keeps the output folder's helpers. A specimen that fails (no
skeleton, a fold over it, an output that cannot be written) is reported in the table with its reason and the
others go on.

Output folder
-------------
``specimen-<id>.zarr``
    The straightened volume of feature ``<id>`` (OME-Zarr, the session embedded).
``specimen-<id>.unwind.json``
    Its session (scan, segmentation, ends, deformation), for ``unwind straighten --session`` or the plugin.
``specimens.csv``
    One row per candidate of the segmentation, rejected ones included: ``specimen`` (feature id), ``status``
    (``ok``, ``partial``, ``failed``, ``rejected`` or ``unresolved``, see :mod:`napari_unwind.pipeline`), ``voxels``
    (labelled working-resolution voxels), ``length`` (centreline, physical units), ``unit``, ``keyframes``,
    ``min_jacobian``, ``max_tilt`` (degrees), ``coverage`` (fraction of the mask inside the cage), ``lost``
    (arclength intervals whose mask is left out of the cage), ``output``, ``session`` (file names in the folder)
    and ``reason`` (why it is not ok).
"""

from __future__ import annotations

import os
from collections.abc import Generator
from typing import Any

from .pipeline import CSV_COLUMNS, CSV_NAME, BatchResult
from .progress import Progress

__all__ = ["BatchResult", "CSV_NAME", "CSV_COLUMNS", "straighten_all_iter", "straighten_all", "read_batch"]

#: Largest collection file read (a row is a scan path and a few points: a million rows is far below this).
MAX_BATCH_BYTES = 64 * 2**20

def straighten_all_iter(
    scan: str | os.PathLike,
    outdir: str | os.PathLike,
    *,
    features: int | None = None,
    level: int | None = None,
    smooth: float | None = None,
    min_elongation: float | None = None,
    allow_folds: bool | None = None,
    order: int | None = None,
    overwrite: bool = False,
    reader_options: dict[str, Any] | None = None,
    skeleton: dict[str, Any] | None = None,
    options: Any = None,
) -> Generator[Progress, None, BatchResult]:
    """Straighten every specimen of a scan (generator: yields progress, returns a
    :class:`~napari_unwind.pipeline.BatchResult`): :func:`napari_unwind.pipeline.run_all_iter`.

    Parameters
    ----------
    scan : str or path-like
        The scan (any format :func:`~napari_unwind.io.open_volume` reads).
    outdir : str or path-like
        The folder for the results (created; see the module docstring).
    features, level, smooth, min_elongation
        Fields of :class:`~napari_unwind.pipeline.SegmentOptions` (None: its default).
    allow_folds, order
        Fields of :class:`~napari_unwind.pipeline.ExportOptions` (None: its default).
    overwrite : bool
        Replace results already in ``outdir``.
    reader_options : dict, optional
        Options of :func:`~napari_unwind.io.open_volume` (``format``, ``series``).
    skeleton : dict, optional
        Fields of :class:`~napari_unwind.pipeline.SkeletonOptions`.
    options : PipelineOptions, optional
        All the options at once (instead of the keywords above).

    Returns
    -------
    BatchResult
        Every candidate (``specimens``); ``rows`` are the specimens' rows of the table.
    """
    from .errors import InvalidInputError
    from .pipeline import PipelineOptions, run_all_iter

    flat = dict(features=features, level=level, smooth=smooth, min_elongation=min_elongation,
                allow_folds=allow_folds, order=order, **(skeleton or {}))
    if options is not None:
        if any(v is not None for v in flat.values()):
            raise InvalidInputError("give either options=PipelineOptions(...) or keyword options, not both")
    else:
        options = PipelineOptions.from_values(**flat)
    return (yield from run_all_iter(scan, outdir, options=options, overwrite=overwrite,
                                    reader_options=reader_options))


def straighten_all(scan: str | os.PathLike, outdir: str | os.PathLike, *, progress=None, **options: Any
                   ) -> BatchResult:
    """Straighten every specimen of a scan: :func:`straighten_all_iter` run to the end (``progress`` is called
    with each :class:`~napari_unwind.progress.Progress`)."""
    from .progress import run

    return run(straighten_all_iter(scan, outdir, **options), progress)


# ------------------------------------------------------------------------------------------------------------------
# collection files (unwind submit --batch FILE)
# ------------------------------------------------------------------------------------------------------------------
def read_batch(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The items of a collection file for :meth:`napari_unwind.client.Client.run_batch`.

    Two layouts, both checked against ``napari_unwind/schemas/batch.schema.json`` (:mod:`napari_unwind._json`):

    - ``*.json``: a list of objects ``{"scan": ..., "select": "all" or [[a0, a1, a2], ...], "name": ...}``;
    - anything else is CSV with a header: columns ``scan``, ``select`` (``all``, or points ``10 20 30; 1 2 3``)
      and ``name`` (optional); empty ``select`` is ``all``.

    Returns
    -------
    list of dict
        ``{"scan": str, "select": "all" or list of [a0, a1, a2], "name": str or None}`` per item.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    InvalidInputError
        Anything else wrong, in one line naming the file and the line (CSV) or JSON path of the bad value.
    """
    from pathlib import Path

    from . import _json
    from .errors import InvalidInputError

    path = Path(path).expanduser()
    hint = "correct it in the file (see unwind submit --help)"
    if path.name.lower().endswith(".json"):
        items = _json.load_file(path, what="a collection", max_bytes=MAX_BATCH_BYTES, hint=hint)
        try:
            items = _json.validate(items, "batch", hint=hint)
        except InvalidInputError as exc:
            raise InvalidInputError(f"{path}: {exc}") from None
        if not items:
            raise InvalidInputError(f"{path} lists no scan; give at least one item {{\"scan\": ...}}")
        return [{"scan": i["scan"].strip(), "select": i.get("select", "all"), "name": i.get("name") or None}
                for i in items]
    return _read_batch_csv(path, hint)


def _read_batch_csv(path: Any, hint: str) -> list[dict[str, Any]]:
    import csv
    import io

    from . import _json
    from .errors import InvalidInputError
    from .io._files import read_small

    raw = read_small(path, what="a collection", max_bytes=MAX_BATCH_BYTES,
                     hint=" (CSV with columns scan, select, name)")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InvalidInputError(f"{path} is not a collection file: it is not UTF-8 text (invalid byte at offset "
                                f"{exc.start}); give a CSV with columns scan, select, name") from None
    if "\0" in text:
        raise InvalidInputError(f"{path} is not a collection file: it holds NUL characters (a binary file?); give a "
                                "CSV with columns scan, select, name")
    reader = csv.DictReader(io.StringIO(text, newline=""))
    items = []
    n = 1
    try:
        for n, row in enumerate(reader, start=2):
            if None in row:
                raise InvalidInputError(f"{path} line {n}: more values than the header's columns "
                                        f"({', '.join(reader.fieldnames or [])})")
            scan = (row.get("scan") or "").strip()
            if not scan:
                raise InvalidInputError(f"{path} line {n}: the scan column is empty")
            sel: Any = (row.get("select") or "all").strip()
            if sel != "all":
                points = []
                for p in sel.split(";"):
                    if not p.strip():
                        continue
                    words = p.replace(",", " ").split()
                    if any(len(w) > _json.MAX_NUMBER_CHARS for w in words):
                        raise InvalidInputError(f"{path} line {n}: select holds a number of more than "
                                                f"{_json.MAX_NUMBER_CHARS} characters: {_json.short(p)}; {hint}")
                    try:
                        points.append([float(w) for w in words])
                    except ValueError:
                        raise InvalidInputError(f"{path} line {n}: select must be 'all' or points like '10 20 30; 1 "
                                                f"2 3', got {_json.short(row.get('select'))}") from None
                if not points or any(len(p) != 3 for p in points):
                    raise InvalidInputError(f"{path} line {n}: every select point needs 3 numbers, got "
                                            f"{_json.short(points)}")
                sel = points
            item = {"scan": scan, "select": sel, "name": (row.get("name") or "").strip() or None}
            try:
                items.append(_json.validate(item, "batch", part="item", root=f"line {n}: ", hint=hint))
            except InvalidInputError as exc:
                raise InvalidInputError(f"{path} {exc}") from None
    except csv.Error as exc:
        raise InvalidInputError(f"{path} line {max(reader.line_num, n)}: not a CSV row ({exc}); {hint}") from None
    if reader.fieldnames is None or "scan" not in reader.fieldnames:
        raise InvalidInputError(f"{path} has no column 'scan' in its first line (got "
                                f"{_json.short(reader.fieldnames or [])}); give a CSV with columns scan, select, name")
    return items
