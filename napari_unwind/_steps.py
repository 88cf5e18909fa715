"""The dock's steps as calls of the one pipeline (:mod:`napari_unwind.pipeline`); no Qt here.

The dock takes its options from the pipeline's option objects and runs these in its workers:

- :func:`skeleton` runs in the dock's child process, by name (``"napari_unwind._steps:skeleton"``): the
  pipeline's :func:`~napari_unwind.pipeline.skeleton_step`, judged by :func:`~napari_unwind.pipeline.judge`
  (a :class:`~napari_unwind.pipeline.SpecimenResult`: ``ok``, or ``partial`` with its reason). The spare child
  imports this module while idle (:func:`napari_unwind._napari._workers.prewarm`), so the solver's imports
  (scipy, numba, the mesher) are done before the click: they are imported here at the top on purpose;
- :func:`export` is :func:`~napari_unwind.pipeline.export_step` (the one fold rule, then the writer), returning
  the written path and the warnings the rule let through;
- :func:`check_folds` is the fold rule alone, for an export done on a server.

The UI thread never imports this module (only the workers do), so the solver's imports never block it.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Generator, Sequence
from pathlib import Path
from typing import Any

from . import pipeline
from . import skeleton as _skeleton  # noqa: F401 - imported while the spare child waits (see the docstring)
from .errors import FoldError
from .progress import Progress

__all__ = ["SKELETON", "check_folds", "export", "skeleton"]

#: The skeleton step's name for :func:`napari_unwind._napari._workers.start_process_job` and ``prewarm``.
SKELETON = f"{__name__}:skeleton"


def skeleton(mask: Any, endpoints: Any, *, spacing: Any, origin: Any = None, unit: str | None = None,
             volume: Any = None, options: pipeline.SkeletonOptions | None = None
             ) -> Generator[Progress, None, pipeline.SpecimenResult]:
    """:func:`~napari_unwind.pipeline.skeleton_step` with ``options`` (None: the pipeline's defaults); returns its
    :class:`~napari_unwind.pipeline.SpecimenResult` (status, reason, figures; ``.skeleton`` the full result)."""
    if options is None:
        options = pipeline.SkeletonOptions()
    result = yield from pipeline.skeleton_step(mask, endpoints, spacing=spacing, origin=origin, unit=unit,
                                               volume=volume, options=options)
    return pipeline.SpecimenResult.of(result)


def check_folds(deformation: Any, *, folded: float | None, options: pipeline.ExportOptions) -> str | None:
    """The one fold rule (:func:`~napari_unwind.pipeline.fold_rule`): raises
    :class:`~napari_unwind.errors.FoldError` with the command line's message when it refuses; returns the
    warning line of a fold it lets through (None: no fold)."""
    verdict = pipeline.fold_rule(deformation, folded=folded, allow_folds=options.allow_folds)
    if verdict is None:
        return None
    if verdict.refused:
        raise FoldError(verdict.message)
    return verdict.message


def export(volume: Any, deformation: Any, target: str | os.PathLike, *, options: pipeline.ExportOptions,
           folded: float | None = None, session: Any = None, overwrite: bool = False,
           channels: Sequence[Any] | None = None) -> Generator[Progress, None, tuple[Path, tuple[str, ...]]]:
    """:func:`~napari_unwind.pipeline.export_step` (``channels``: other images of the scan's grid, written with it
    as one multi-channel image); returns (the written path, its warnings, one line each)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        written = yield from pipeline.export_step(volume, deformation, target, options=options, folded=folded,
                                                  session=session, overwrite=overwrite, channels=channels)
    lines = [" ".join(str(w.message).split()) for w in caught if issubclass(w.category, UserWarning)]
    return Path(written), tuple(dict.fromkeys(lines))

