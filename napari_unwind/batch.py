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
    (``ok``, ``partial``, ``failed`` or ``rejected``, see :mod:`napari_unwind.pipeline`), ``voxels`` (labelled
    working-resolution voxels), ``length`` (centreline, physical units), ``unit``, ``keyframes``,
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

__all__ = ["BatchResult", "CSV_NAME", "CSV_COLUMNS", "straighten_all_iter", "straighten_all"]

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
