"""Morphology shared by segmentation and skeleton (below both)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage

__all__ = ["depth_map"]


def depth_map(region: np.ndarray, spacing: Sequence[float] | np.ndarray) -> np.ndarray:
    """The Euclidean distance (physical) of each voxel of ``region`` to the nearest voxel outside it.

    Parameters
    ----------
    region : ndarray of bool, shape (N0, N1, N2)
    spacing : sequence of 3 float
        Voxel size along each axis.

    Returns
    -------
    ndarray of float64, shape (N0, N1, N2)
        0 outside ``region``; the array's border counts as outside (a region touching it is not infinitely deep).
    """
    pad = np.pad(region, 1)
    return ndimage.distance_transform_edt(pad, sampling=spacing)[(slice(1, -1),) * region.ndim]
