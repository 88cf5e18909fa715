"""Segmentation in one call: build the join tree and simplify it (above both modules)."""

from __future__ import annotations

from collections.abc import Generator
from typing import Any

from ..progress import Progress, run
from ._common import check_features_count
from ._features import Features
from ._jointree import join_tree_iter

__all__ = ["segment", "segment_iter"]


def segment_iter(
    volume: Any, *, features: int = 5, level: int | None = None, smooth: float = 1.0, connectivity: int = 6
) -> Generator[Progress, None, Features]:
    """Generator form of :func:`segment`: yields progress, returns the :class:`Features`."""
    k = check_features_count(features)
    tree = yield from join_tree_iter(volume, level=level, smooth=smooth, connectivity=connectivity)
    yield Progress("simplify", 0, 1, f"{k} features")
    result = tree.simplify(k)
    yield Progress("simplify", 1, 1)
    return result


def segment(
    volume: Any,
    *,
    features: int = 5,
    level: int | None = None,
    smooth: float = 1.0,
    connectivity: int = 6,
    progress=None,
) -> Features:
    """Segment a volume into its ``features`` most important bright objects (join tree + hypervolume).

    Parameters
    ----------
    volume : Volume or array_like, shape (N0, N1, N2)
        The scan (a Volume's pyramid level ``level`` is used) or a 3D array.
    features : int
        Number of features to keep, 1..100 (default 5).
    level : int, optional
        Pyramid level; default the finest with every side <= 256.
    smooth : float
        Gaussian sigma in working voxels before the sweep (default 1; 0 for none).
    connectivity : int
        6 (default) or 26.
    progress : callable, optional
        Called with each :class:`~napari_unwind.progress.Progress` record.

    Returns
    -------
    Features
        Labels (working resolution, 0 = background), statistics, and the tree for re-simplifying.

    Raises
    ------
    InvalidInputError
        As :func:`join_tree`, and when ``features`` is not in 1..100 or exceeds the number of maxima.
    """
    return run(segment_iter(volume, features=features, level=level, smooth=smooth, connectivity=connectivity),
               progress)
