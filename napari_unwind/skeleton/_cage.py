"""Cage half-extents and end padding proposed from the mask around a curve.

Every boundary voxel of the mask (the extremes of any coordinate are reached on the boundary) is given the
straight coordinates of the curve point nearest to it: ``x = (p - c_j) . u_j``, ``y = (p - c_j) . v_j`` and the
offset ``z = (p - c_j) . n_j`` along the curve. Voxels nearest the first point with ``z < 0`` lie beyond the head;
voxels nearest the last point with ``z > 0`` lie beyond the tail.

- ``(rx, ry)``: the largest ``|x|`` and ``|y|`` over all those voxels (beyond-end voxels included, seen in the
  end frames, which is how the padded straight box sees them), enlarged by ``margin`` (relative) plus
  ``min_margin`` (absolute) so that fins and partial-volume edges are not cut.
- ``(before, after)``: how far the mask reaches beyond the first point along ``-n_0`` and beyond the last one
  along ``+n_K``, plus ``end_margin``, so that fleshy ends the curve does not reach are kept.

Per keyframe and per side (:func:`fit_cages`): the same voxels, grouped by the curve point they are nearest to,
give each curve point its cross-section's extent on each side (``x_lo, x_hi, y_lo, y_hi``: a bend's inner half
can be thinner than its outer half). A keyframe's cage holds the sections of the two curve stretches it bounds
(the cage is linear between keyframes), with the same margins. A voxel counts for a curve point only when it is
nearest to it, so other turns of a coil and other parts of the body that cross the section plane far from the
centre are left to their own curve points.

Stray voxels: parts of the mask smaller than 0.1 % of it (specks left by a segmentation) are ignored. Curves
with points farther apart than a voxel are first densified (positions linear, frames by quaternion SLERP, as
:class:`napari_unwind.deformation.Deformation` interpolates them).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp

from ..errors import InvalidInputError
from ..io._volume import check_spacing
from ._twist import _check_frames, _check_points

__all__ = ["propose_cage", "fit_cages"]

_STRUCT26 = np.ones((3, 3, 3), dtype=bool)
_SPECK_FRACTION = 1e-3  # parts smaller than this fraction of the mask are ignored
_OTHER_FRACTION = 0.1  # a separate part the curve misses, this large against the specimen, is another specimen


def _nonneg(name: str, value: Any) -> float:
    if isinstance(value, (bool, np.bool_)) or not (np.isscalar(value) and np.isfinite(value) and float(value) >= 0):
        raise InvalidInputError(f"{name} must be a number >= 0, got {value!r}")
    return float(value)


def propose_cage(
    mask: Any,
    points: np.ndarray,
    frames: np.ndarray,
    *,
    spacing: Sequence[float] | float,
    margin: float = 0.1,
    min_margin: float | None = None,
    end_margin: float | None = None,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """Propose the cage half-extents and the end padding that hold the whole mask.

    See the module docstring for the method.

    Parameters
    ----------
    mask : ndarray of bool, shape (N0, N1, N2)
        The specimen (non-zero = inside).
    points : ndarray, shape (K, 3)
        Curve points, physical units (voxel index x spacing, origin 0), head first, consecutive points distinct.
    frames : ndarray, shape (K, 3, 3)
        Rows ``u, v, n`` at each point, orthonormal and right-handed (the twisted frames if the twist is known:
        ``rx`` is measured along ``u`` and ``ry`` along ``v``).
    spacing : float or sequence of 3 float
        Voxel size of ``mask`` along axis0, axis1, axis2.
    margin : float
        Relative enlargement of the half-extents (0.1: 10 %).
    min_margin : float, optional
        Absolute enlargement added to the half-extents, physical units. Default: 2 voxels (the largest spacing).
    end_margin : float, optional
        Added to each end's padding, physical units. Default: 2 voxels (the largest spacing).

    Returns
    -------
    half_extent : tuple of 2 float
        ``(rx, ry)``, physical units.
    pad : tuple of 2 float
        ``(before, after)``: padding before the first point and after the last one, physical units.

    Raises
    ------
    InvalidInputError
        For malformed inputs or an empty mask.
    """
    arr = np.asarray(mask)
    if arr.ndim != 3:
        raise InvalidInputError(f"mask must be a 3D array (axis0, axis1, axis2), got shape {arr.shape}")
    if arr.dtype != bool:
        if not np.issubdtype(arr.dtype, np.number):
            raise InvalidInputError(f"mask must hold booleans or numbers (non-zero = inside), got dtype {arr.dtype}")
        arr = arr != 0
    pts = _check_points(points)
    fr = _check_frames(frames, len(pts))
    sp = np.asarray(check_spacing(spacing))
    margin = _nonneg("margin", margin)
    vox = float(sp.max())
    min_margin = 2.0 * vox if min_margin is None else _nonneg("min_margin", min_margin)
    end_margin = 2.0 * vox if end_margin is None else _nonneg("end_margin", end_margin)

    _, j, x, y, z, last = _sections(arr, pts, fr, sp)
    rx = float(np.abs(x).max()) * (1.0 + margin) + min_margin
    ry = float(np.abs(y).max()) * (1.0 + margin) + min_margin
    ahead = (j == 0) & (z < 0)
    behind = (j == last) & (z > 0)
    before = (float(-z[ahead].min()) if ahead.any() else 0.0) + end_margin
    after = (float(z[behind].max()) if behind.any() else 0.0) + end_margin
    return (rx, ry), (before, after)


def _sections(arr: np.ndarray, pts: np.ndarray, fr: np.ndarray, sp: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Boundary voxels in the coordinates of their nearest (densified) curve point.

    Returns ``t`` (the curve parameter of each dense point: original index, fractional between points), ``j``
    (each voxel's dense point), ``x, y, z`` and the index of the last dense point.
    """
    vox_idx = _boundary_voxels(arr, pts / sp)
    if len(vox_idx) == 0:
        raise InvalidInputError("the mask is empty: there is no specimen to fit a cage around; check the segmentation")
    p = vox_idx * sp
    pts, fr, t = _densify(pts, fr, float(sp.min()))
    _, j = cKDTree(pts).query(p, workers=-1)
    d = p - pts[j]
    x = np.einsum("ij,ij->i", d, fr[j, 0])
    y = np.einsum("ij,ij->i", d, fr[j, 1])
    z = np.einsum("ij,ij->i", d, fr[j, 2])
    last = len(pts) - 1
    # beyond an end, only the tissue joined to that end's tip: another turn of a tight coil passing beyond the
    # end plane (nearest to the end point because the body is tall there) would stretch the padding through it
    keep = np.ones(len(j), dtype=bool)
    for end, out in ((0, -1.0), (last, 1.0)):
        sel = (j == end) & (out * z > 0)
        if sel.any():
            keep[np.flatnonzero(sel)[_detached_beyond(arr, sp, pts[end], out * fr[end, 2], vox_idx[sel])]] = False
    return t, j[keep], x[keep], y[keep], z[keep], last


def _detached_beyond(arr: np.ndarray, sp: np.ndarray, end: np.ndarray, normal: np.ndarray, idx: np.ndarray
                     ) -> np.ndarray:
    """Which voxels ``idx`` (index coordinates, beyond the plane through ``end`` (physical) facing ``normal``) are
    not joined to the end's tip: the mask beyond the plane, 26-connected within a box around them and the end, split
    into parts; the parts within two voxels of ``end`` are the tip (there may be none: the body ends before the
    plane). None is detached when no mask voxel lies within two voxels of ``end`` (a curve that stops off the mask
    keeps every voxel, as before)."""
    e = end / sp
    lo = np.maximum(np.floor(np.minimum(idx.min(axis=0), e)).astype(int) - 3, 0)
    hi = np.minimum(np.ceil(np.maximum(idx.max(axis=0), e)).astype(int) + 4, np.asarray(arr.shape))
    sub = arr[tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))]
    g = np.indices(sub.shape, dtype=float).reshape(3, -1).T + lo
    beyond = sub & (((g * sp - end) @ normal) > 0).reshape(sub.shape)
    near = (np.linalg.norm((g - e) * sp, axis=1) <= 2.0 * float(sp.max())).reshape(sub.shape)
    if not (sub & near).any():
        return np.zeros(len(idx), dtype=bool)
    labels, _ = ndimage.label(beyond, _STRUCT26)
    tip = np.unique(labels[near & beyond])
    return ~np.isin(labels[tuple((idx - lo).T)], tip[tip > 0])


def fit_cages(
    mask: Any,
    points: np.ndarray,
    frames: np.ndarray,
    keyframes: Sequence[int],
    *,
    spacing: Sequence[float] | float,
    margin: float = 0.1,
    min_margin: float | None = None,
) -> np.ndarray:
    """Per keyframe, the cage sides ``(x_lo, x_hi, y_lo, y_hi)`` that hold the body's cross-sections there.

    See the module docstring for the method.

    Parameters
    ----------
    mask, points, frames, spacing, margin, min_margin
        As for :func:`propose_cage` (the points and frames of the dense curve).
    keyframes : sequence of int
        Sorted indices into ``points`` of the keyframes, the first and last points included.

    Returns
    -------
    ndarray, shape (m, 4)
        Sides per keyframe, physical units; each side is enlarged by ``margin`` (relative) and ``min_margin``
        (absolute) and lies at least ``min_margin`` from the curve, so every cage holds its curve point.
    """
    arr = np.asarray(mask)
    if arr.ndim != 3:
        raise InvalidInputError(f"mask must be a 3D array (axis0, axis1, axis2), got shape {arr.shape}")
    arr = arr != 0 if arr.dtype != bool else arr
    pts = _check_points(points)
    fr = _check_frames(frames, len(pts))
    sp = np.asarray(check_spacing(spacing))
    margin = _nonneg("margin", margin)
    min_margin = 2.0 * float(sp.max()) if min_margin is None else _nonneg("min_margin", min_margin)
    key = np.asarray(keyframes, dtype=np.int64).reshape(-1)
    if len(key) < 2 or key[0] != 0 or key[-1] != len(pts) - 1 or (np.diff(key) <= 0).any():
        raise InvalidInputError(f"keyframes must be sorted indices into the curve from 0 to {len(pts) - 1}, got "
                                f"{key.tolist()}")
    t, j, x, y, z, _ = _sections(arr, pts, fr, sp)
    # each dense point's section extent, per side
    n_dense = len(t)
    ext = np.zeros((n_dense, 4))
    np.minimum.at(ext[:, 0], j, x)
    np.maximum.at(ext[:, 1], j, x)
    np.minimum.at(ext[:, 2], j, y)
    np.maximum.at(ext[:, 3], j, y)
    # a keyframe's cage holds the sections of the two stretches of curve it bounds
    seg = np.clip(np.searchsorted(key, t, side="right") - 1, 0, len(key) - 2)
    out = np.zeros((len(key), 4))
    for k in range(len(key) - 1):
        e = ext[seg == k]
        if len(e) == 0:
            continue
        env = np.array([e[:, 0].min(), e[:, 1].max(), e[:, 2].min(), e[:, 3].max()])
        for i in (k, k + 1):
            out[i] = [min(out[i, 0], env[0]), max(out[i, 1], env[1]), min(out[i, 2], env[2]), max(out[i, 3], env[3])]
    sign = np.array([-1.0, 1.0, -1.0, 1.0])
    return out * (1.0 + margin) + sign * min_margin


def _nearest_labels(labels: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The label of the labelled voxel nearest to each point (voxel indices, shape (P, 3)), shape (P,).

    The nearest labelled voxel of a point outside every part is on a part's surface, so a KD-tree of the surface
    voxels answers it: cost grows with the surface and the number of points, not with the crop's volume (a full
    distance transform of the crop did the same before).
    """
    solid = labels > 0
    surface = solid & ~ndimage.binary_erosion(solid, border_value=0)
    where = np.argwhere(surface)
    _, nearest = cKDTree(where).query(np.asarray(points, dtype=float))
    return labels[tuple(where[nearest].T)]


def _boundary_voxels(mask: np.ndarray, curve_vox: np.ndarray | None = None) -> np.ndarray:
    """Index coordinates (N, 3) of the mask voxels with a face neighbour outside, specks removed.

    With ``curve_vox`` (curve points, voxel indices), a separate part of the mask that the curve does not run through
    (nor, for a stretch of curve outside the mask, lies nearest to) is dropped when it holds at least 10 % as many
    voxels as the parts the curve runs through: that is another specimen, not this one's cross-section, whichever
    curve point it is nearest to. Smaller separate parts (a fin the segmentation broke off) are kept.
    """
    sl = []
    for ax in range(3):
        other = tuple(a for a in range(3) if a != ax)
        nz = np.flatnonzero(np.any(mask, axis=other))
        if len(nz) == 0:
            return np.empty((0, 3), dtype=np.int64)
        sl.append(slice(int(nz[0]), int(nz[-1]) + 1))
    crop = mask[tuple(sl)]
    labels, n = ndimage.label(crop, _STRUCT26)
    if n > 1:
        sizes = np.bincount(labels.reshape(-1), minlength=n + 1)
        sizes[0] = 0
        drop = sizes < _SPECK_FRACTION * sizes.sum()
        if curve_vox is not None and len(curve_vox):
            lo = np.array([x.start for x in sl])
            idx = np.round(np.asarray(curve_vox, dtype=float)).astype(int) - lo
            ok = ((idx >= 0) & (idx < np.asarray(crop.shape))).all(axis=1)
            on = labels[tuple(idx[ok].T)] if ok.any() else np.zeros(0, dtype=labels.dtype)
            touched = np.unique(on[on > 0])
            if len(touched) == 0 or (~ok).any() or (on == 0).any():
                # parts of the curve outside the mask (a gap, an end snapped beside it): the part nearest them
                off = idx[ok][on == 0] if ok.any() else np.zeros((0, 3), dtype=int)
                clipped = np.clip(idx[~ok], 0, np.asarray(crop.shape) - 1)
                pts = np.concatenate([off, clipped]) if len(clipped) else off
                if len(pts):
                    touched = np.union1d(touched, _nearest_labels(labels, pts))
            keep = np.zeros(n + 1, dtype=bool)
            keep[touched] = True
            # a detached part much smaller than the specimen (a fin the segmentation broke off) is kept; one of
            # comparable size is another specimen
            keep |= sizes < _OTHER_FRACTION * sizes[touched].sum()
            drop |= ~keep
        drop[0] = True
        crop = ~drop[labels]
    inner = ndimage.binary_erosion(np.pad(crop, 1))[1:-1, 1:-1, 1:-1]
    edge = crop & ~inner
    return np.argwhere(edge) + np.array([s.start for s in sl])


def _densify(pts: np.ndarray, fr: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Insert points (linear) and frames (SLERP) so that consecutive points are at most ``step`` apart; also
    returns each new point's parameter (original index, fractional between points)."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    m = np.maximum(1, np.ceil(seg / step).astype(int))
    if (m == 1).all():
        return pts, fr, np.arange(len(pts), dtype=float)
    rots = Rotation.from_matrix(np.transpose(fr, (0, 2, 1)))  # columns u, v, n
    knots = np.arange(len(pts), dtype=float)
    t = np.concatenate([i + np.arange(k) / k for i, k in enumerate(m)] + [[len(pts) - 1.0]])
    i0 = np.minimum(np.floor(t).astype(int), len(pts) - 2)
    lam = (t - i0)[:, None]
    new_pts = (1 - lam) * pts[i0] + lam * pts[i0 + 1]
    new_fr = np.transpose(Slerp(knots, rots)(t).as_matrix(), (0, 2, 1))
    return new_pts, new_fr, t
