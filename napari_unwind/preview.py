"""The straight preview, CPU path: the straight volume resampled from a coarse pyramid level, fast enough to
recompute after every edit.

Qt-free (the plugin runs it in a ``thread_worker``; issue 12's GLSL view falls back to it when GL lacks what the
shader needs). The level is the coarsest one that keeps the body at least ``min_across`` voxels across, where the
body is the cage's smallest full width (over the keyframes and both sides; the sides are linear between keyframes,
so their extremes are at keyframes) and a level's voxel is its coarsest spacing.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import Any

import numpy as np

from .deformation import Deformation
from .errors import InvalidInputError
from .io import Volume
from .warp import FoldWarning, OutsideWarning, straighten

__all__ = ["preview_level", "preview_volume", "level_deformation"]


def _levels(volume: Any) -> tuple[list[Any], list[tuple[float, ...]], list[tuple[float, ...]], tuple[float, ...],
                                  tuple[float, ...]]:
    if isinstance(volume, Volume):
        return (list(volume.levels), list(volume.level_spacings), list(volume.level_origins), volume.spacing,
                volume.origin)
    shape = getattr(volume, "shape", None)
    if shape is None or len(shape) != 3:
        raise InvalidInputError(f"the scan must be a Volume or a 3D array, got {type(volume).__name__} "
                                f"with shape {shape}")
    return [volume], [(1.0, 1.0, 1.0)], [(0.0, 0.0, 0.0)], (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)


def _check(deformation: Any, min_across: Any) -> float:
    if not isinstance(deformation, Deformation):
        raise InvalidInputError(f"deformation must be a Deformation, got {type(deformation).__name__}")
    if isinstance(min_across, bool) or not isinstance(min_across, (int, float, np.integer, np.floating)) or not (
            np.isfinite(min_across) and min_across > 0):
        raise InvalidInputError(f"min_across must be a positive number of voxels, got {min_across!r}")
    return float(min_across)


def preview_level(volume: Volume | Any, deformation: Deformation, *, min_across: float = 64) -> int:
    """Index of the coarsest pyramid level on which the body is at least ``min_across`` voxels across.

    Parameters
    ----------
    volume : Volume or array_like
        The scan (a bare array is a single level).
    deformation : Deformation
        Its cage gives the body's width: the smallest full side ``x_hi - x_lo`` or ``y_hi - y_lo`` of any keyframe.
    min_across : float
        Voxels across the body the preview keeps, on the level's coarsest axis.

    Returns
    -------
    int
        The level (0 when even the finest level has fewer than ``min_across`` voxels across the body).
    """
    min_across = _check(deformation, min_across)
    levels, level_spacings, _, base, _ = _levels(volume)
    b = deformation.bounds
    width = float(min((b[:, 1] - b[:, 0]).min(), (b[:, 3] - b[:, 2]).min()))
    # a level's spacing in the deformation's unit: the same factor over the base spacing
    dsp = np.asarray(deformation.spacing, dtype=float)
    for i in range(len(levels) - 1, 0, -1):
        factor = np.asarray(level_spacings[i], dtype=float) / np.asarray(base, dtype=float)
        if width / float((dsp * factor).max()) >= min_across:
            return i
    return 0


def level_deformation(volume: Volume | Any, deformation: Deformation, level: int) -> Deformation:
    """The same deformation (same physical curve and cages) expressed on pyramid level ``level``'s voxel grid.

    The level's spacing is the deformation's times the level's factor over the base spacing, and its origin is
    moved by the level's origin shift measured in base voxels, so the scan's unit need not be the deformation's.
    """
    levels, level_spacings, level_origins, base, base_origin = _levels(volume)
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)) or not 0 <= int(level) < len(levels):
        raise InvalidInputError(f"level must be a whole number in [0, {len(levels) - 1}], got {level!r}")
    sp0 = np.asarray(base, dtype=float)
    factor = np.asarray(level_spacings[level], dtype=float) / sp0
    shift = (np.asarray(level_origins[level], dtype=float) - np.asarray(base_origin, dtype=float)) / sp0
    dsp = np.asarray(deformation.spacing, dtype=float)
    return replace(deformation, spacing=tuple(dsp * factor), origin=tuple(np.asarray(deformation.origin) + shift * dsp))


def preview_volume(volume: Volume | Any, deformation: Deformation, *, min_across: float = 64,
                   level: int | None = None) -> tuple[np.ndarray, float]:
    """The straight volume of ``deformation`` resampled (trilinear) from the preview level of the scan.

    Parameters
    ----------
    volume : Volume or array_like, shape (N0, N1, N2)
        The scan (a bare array: on the deformation's grid, one level).
    deformation : Deformation
    min_across : float
        See :func:`preview_level`.
    level : int, optional
        Use this level instead of the one :func:`preview_level` chooses.

    Returns
    -------
    array : ndarray, shape (Ns, Ny, Nx)
        ``straighten(level_volume, level_deformation, spacing=ds)`` computed, in the scan's voxel type.
    spacing : float
        The output spacing ``ds``: the level's finest spacing in the deformation's unit (the layer's scale).

    Raises
    ------
    InvalidInputError
        For a bad scan or deformation, or when no voxel of the straight box samples the scan. Folds and a box
        mostly outside the scan do not warn here (the editor shows folds on its slider).
    """
    _check(deformation, min_across)
    if level is None:
        level = preview_level(volume, deformation, min_across=min_across)
    levels = _levels(volume)[0]
    d = level_deformation(volume, deformation, level)
    ds = float(min(d.spacing))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FoldWarning)
        warnings.simplefilter("ignore", OutsideWarning)
        straight = straighten(levels[level], d, spacing=ds, order=1)
    return np.asarray(straight.data.compute()), ds
