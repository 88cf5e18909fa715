"""Suggested head and tail of a specimen, and user clicks moved into the mask.

Suggestion (:func:`suggest_endpoints`)
    1. The mask is cropped to its bounding box and reduced by blocks ("any" pooling: a coarse voxel is in when
       any of its voxels is) to about ``max_side`` voxels along its longest physical side. Pooling by "any" keeps
       thin parts (fins, tails, a specimen a few voxels thick) connected.
    2. The largest 26-connected part is kept (with a warning when there are several).
    3. The longest geodesic through it is found by a double sweep of Dijkstra's algorithm over the 26-neighbour
       graph with physical edge lengths (scipy.sparse.csgraph): the farthest voxel A from an arbitrary one, then
       the farthest voxel B from A. A and B are the two tips.
    4. A specimen with no head-tail axis (longest geodesic < 1.5 x its largest inscribed diameter: a ball, a
       blob) is refused: the user must click both ends.
    5. Head or tail: the head is the THICKER end. The mask volume within a quarter of the geodesic length of each
       tip is compared (the head and trunk of a fish against its tapering tail); when the two are within 10 %
       and a volume is given, the end with the denser tissue (the skull) is the head; otherwise a warning says
       that the order is a guess.
    6. The returned points are the tips themselves: of the coarse voxel at each tip, its mask voxel deepest
       inside the mask (on the axis of a thin tail that crosses it). A point set back from the tip leaves the end
       of the specimen to the cage's straight padding and shortens its centreline: a rule "at least 2 voxels
       from the boundary" stopped 19.5 voxels (14 %) short of a fish's 1-voxel-thin tail in a dense tank.

Snapping (:func:`snap_to_mask`)
    A click inside the mask is kept; a click outside moves to the nearest mask voxel centre if that is within
    ``tolerance`` (physical units), otherwise it is refused with the distance in the message.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from .._morphology import depth_map
from ..errors import InvalidInputError
from ..io._volume import check_spacing

__all__ = ["suggest_endpoints", "snap_to_mask"]

_STRUCT26 = np.ones((3, 3, 3), dtype=bool)
_MIN_ELONGATION = 1.5  # longest geodesic / largest inscribed diameter below which there is no head-tail axis
_END_FRACTION = 0.25  # the end regions compared for thickness, as a fraction of the geodesic length
_AMBIGUOUS = 1.1  # thickness ratio below which the head/tail decision is uncertain
# the 13 "forward" offsets of the 26-neighbourhood
_OFFSETS = np.array([o for o in np.ndindex(3, 3, 3) if o > (1, 1, 1)]) - 1


def _check_mask(mask: Any) -> np.ndarray:
    arr = np.asarray(mask)
    if arr.ndim != 3:
        raise InvalidInputError(f"mask must be a 3D array (axis0, axis1, axis2), got shape {arr.shape}")
    if arr.dtype != bool:
        if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
            raise InvalidInputError(f"mask must hold booleans or numbers (non-zero = inside), got dtype {arr.dtype}")
        arr = arr != 0
    return arr


def _bbox(mask: np.ndarray) -> tuple[slice, ...] | None:
    sl = []
    for ax in range(3):
        other = tuple(a for a in range(3) if a != ax)
        nz = np.flatnonzero(np.any(mask, axis=other))
        if len(nz) == 0:
            return None
        sl.append(slice(int(nz[0]), int(nz[-1]) + 1))
    return tuple(sl)


def _pool(block: np.ndarray, f: Sequence[int], how: str) -> np.ndarray:
    """Reduce ``block`` by factors ``f`` (zero-padded to multiples): ``"any"``, ``"max"`` or ``"sum"`` over each
    block."""
    f = tuple(int(x) for x in f)
    if f == (1, 1, 1):
        return block.copy() if how in ("any", "max") else block.astype(np.float64)
    shape = tuple(int(math.ceil(n / k)) * k for n, k in zip(block.shape, f))
    if shape != block.shape:
        padded = np.zeros(shape, dtype=block.dtype)
        padded[tuple(slice(0, n) for n in block.shape)] = block
        block = padded
    r = block.reshape(shape[0] // f[0], f[0], shape[1] // f[1], f[1], shape[2] // f[2], f[2])
    if how == "any":
        return r.any(axis=(1, 3, 5))
    if how == "max":
        return r.max(axis=(1, 3, 5))
    return r.sum(axis=(1, 3, 5), dtype=np.float64)


def _graph(coarse: np.ndarray, csp: np.ndarray) -> tuple[sparse.csr_matrix, np.ndarray]:
    """The 26-neighbour graph of the true voxels of ``coarse`` with physical edge lengths."""
    nodes = np.flatnonzero(coarse.reshape(-1))
    index = np.full(coarse.size, -1, dtype=np.int64)
    index[nodes] = np.arange(len(nodes))
    index = index.reshape(coarse.shape)
    coords = np.unravel_index(nodes, coarse.shape)
    rows, cols, vals = [], [], []
    for off in _OFFSETS:
        nb = [c + o for c, o in zip(coords, off)]
        ok = np.ones(len(nodes), dtype=bool)
        for d in range(3):
            ok &= (nb[d] >= 0) & (nb[d] < coarse.shape[d])
        src = np.flatnonzero(ok)
        dst = index[nb[0][ok], nb[1][ok], nb[2][ok]]
        hit = dst >= 0
        rows.append(src[hit])
        cols.append(dst[hit])
        vals.append(np.full(int(hit.sum()), float(np.linalg.norm(off * csp))))
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    g = sparse.csr_matrix((v, (r, c)), shape=(len(nodes), len(nodes)))
    return g, np.stack(coords, axis=1)


def _longest_geodesic(graph: sparse.csr_matrix) -> tuple[int, int, np.ndarray]:
    """The ends ``a``, ``b`` of a graph's longest geodesic by a double sweep of Dijkstra (the node farthest from node
    0, then the node farthest from it), and the distances from ``a`` (``inf`` off its component): ``da[b]`` is the
    length."""
    d0 = csgraph.dijkstra(graph, directed=False, indices=0)
    a = int(np.argmax(np.where(np.isfinite(d0), d0, -1)))
    da = csgraph.dijkstra(graph, directed=False, indices=a)
    return a, int(np.argmax(np.where(np.isfinite(da), da, -1))), da


def suggest_endpoints(
    mask: Any,
    *,
    spacing: Sequence[float] | float,
    volume: Any = None,
    max_side: int = 80,
) -> tuple[np.ndarray, np.ndarray]:
    """Suggest the head and the tail of a specimen: the ends of the longest geodesic through its mask.

    See the module docstring for the method.

    Parameters
    ----------
    mask : ndarray of bool, shape (N0, N1, N2)
        The specimen (non-zero = inside).
    spacing : float or sequence of 3 float
        Voxel size along axis0, axis1, axis2 (physical units).
    volume : ndarray, shape (N0, N1, N2), optional
        Intensities; only used to break a tie between two ends of the same thickness (the denser end, with the
        skull, is the head). Only the mask's bounding box is read, and only in that case.
    max_side : int
        The geodesic is computed on a copy reduced to about this many voxels along the mask's longest physical
        side (>= 16).

    Returns
    -------
    head, tail : ndarray, shape (3,)
        Voxel index coordinates (full resolution, array axis order) of two mask voxels near the tips, the head
        first.

    Raises
    ------
    InvalidInputError
        For an empty mask, a malformed mask, volume, spacing or ``max_side``, or a specimen without a head-tail
        axis (nearly spherical): then the head and the tail must be clicked.

    Warns
    -----
    UserWarning
        When the mask has several parts (the largest is used), or when the head and the tail look alike.
    """
    m = _check_mask(mask)
    sp = np.asarray(check_spacing(spacing))
    if volume is not None:
        if not hasattr(volume, "shape") or not hasattr(volume, "__getitem__"):
            volume = np.asarray(volume)
        if tuple(volume.shape) != m.shape:
            raise InvalidInputError(f"volume must have the mask's shape {m.shape}, got {tuple(volume.shape)}")
    if isinstance(max_side, (bool, np.bool_)) or not isinstance(max_side, (int, np.integer)) or max_side < 16:
        raise InvalidInputError(f"max_side must be an integer >= 16, got {max_side!r}")
    box = _bbox(m)
    if box is None:
        raise InvalidInputError("the mask is empty: there is no specimen to find the ends of; check the segmentation")
    lo = np.array([s.start for s in box])
    crop = m[box]

    # -- coarse copy
    ext = np.asarray(crop.shape) * sp
    h = max(float(ext.max()) / int(max_side), float(sp.min()))
    f = np.maximum(1, np.round(h / sp)).astype(int)
    csp = f * sp
    coarse = _pool(crop, f, "any")
    counts = _pool(crop, f, "sum")  # fine voxels per coarse voxel

    # -- the largest part
    labels, n_parts = ndimage.label(coarse, _STRUCT26)
    if n_parts > 1:
        sizes = ndimage.sum_labels(counts, labels, index=np.arange(1, n_parts + 1))
        keep = int(np.argmax(sizes)) + 1
        warnings.warn(
            f"the mask has {n_parts} separate parts; the ends are suggested for the largest one "
            f"({100.0 * sizes[keep - 1] / sizes.sum():.0f} % of the mask); click the ends yourself to use another",
            UserWarning,
            stacklevel=2,
        )
        coarse = labels == keep
        counts = np.where(coarse, counts, 0.0)

    # -- double sweep
    graph, coords = _graph(coarse, csp)
    if len(coords) < 2:
        raise InvalidInputError(
            "the specimen is a single voxel at this resolution: there is no head-tail axis to suggest; click the "
            "head and the tail"
        )
    a, b, da = _longest_geodesic(graph)
    db = csgraph.dijkstra(graph, directed=False, indices=b)
    length = float(da[b])

    # -- is there an axis at all?
    solid = (counts >= 0.5 * np.prod(f)) & coarse
    if not solid.any():
        solid = coarse
    r_in = float(depth_map(solid, csp).max())
    elongation = length / (2.0 * r_in)
    if elongation < _MIN_ELONGATION:
        raise InvalidInputError(
            f"the specimen is nearly spherical (longest path through it {length:.3g}, largest inscribed diameter "
            f"{2 * r_in:.3g}, ratio {elongation:.2f} < {_MIN_ELONGATION}): there is no head-tail axis to suggest; "
            "click the head and the tail yourself"
        )

    # -- which end is the head: the thicker one
    node_counts = counts[tuple(coords.T)]
    vol_a = float(node_counts[da <= _END_FRACTION * length].sum())
    vol_b = float(node_counts[db <= _END_FRACTION * length].sum())
    ratio = max(vol_a, vol_b) / max(min(vol_a, vol_b), 1e-12)
    a_is_head = vol_a >= vol_b
    if ratio < _AMBIGUOUS:
        decided = False
        if volume is not None:
            dens_a = _end_density(volume, box, f, coords[da <= _END_FRACTION * length], crop)
            dens_b = _end_density(volume, box, f, coords[db <= _END_FRACTION * length], crop)
            if np.isfinite(dens_a) and np.isfinite(dens_b) and dens_a != dens_b:
                a_is_head, decided = dens_a > dens_b, True
        if not decided:
            warnings.warn(
                f"the two ends of the specimen are about as thick (volume ratio {ratio:.2f} within a quarter of "
                "its length from each tip): the head and the tail may be swapped; check them",
                UserWarning,
                stacklevel=2,
            )

    # -- a point at each tip
    end_a = _tip_point(crop, coarse, f, sp, coords, da)
    end_b = _tip_point(crop, coarse, f, sp, coords, db)
    end_a, end_b = end_a + lo, end_b + lo
    return (end_a, end_b) if a_is_head else (end_b, end_a)


def _end_density(volume: Any, box: tuple[slice, ...], f: np.ndarray, nodes: np.ndarray, crop: np.ndarray) -> float:
    """Mean intensity of the mask voxels in the coarse ``nodes`` (blocks of ``f`` voxels of the crop)."""
    lo = nodes.min(axis=0) * f
    hi = np.minimum((nodes.max(axis=0) + 1) * f, crop.shape)
    sub = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    vals = np.asarray(volume[tuple(slice(s.start + a.start, s.start + a.stop) for s, a in zip(box, sub))])
    sel = np.zeros(tuple(int(b - a) for a, b in zip(lo, hi)), dtype=bool)
    for node in nodes:
        q = node * f - lo
        sel[q[0]:q[0] + f[0], q[1]:q[1] + f[1], q[2]:q[2] + f[2]] = True
    sel &= crop[sub]
    if not sel.any():
        return float("nan")
    return float(np.mean(vals[sel], dtype=np.float64))


def _tip_point(
    crop: np.ndarray,
    coarse: np.ndarray,
    f: np.ndarray,
    sp: np.ndarray,
    coords: np.ndarray,
    dist: np.ndarray,
) -> np.ndarray:
    """The deepest mask voxel of the tip's coarse node (index coordinates of ``crop``).

    ``coords`` are the coarse nodes of the part, ``dist`` their geodesic distance from the tip (0 at the tip).
    Only the part's own voxels count (another part in the same block does not), and the depth is the distance to
    the mask's boundary, so of a tip block that a thin tail crosses, the voxel on the tail's axis is returned.
    """
    node = coords[int(np.argmin(dist))]
    lo_c = np.maximum(node - 1, 0)
    hi_c = np.minimum(node + 2, coarse.shape)
    lo, hi = lo_c * f, np.minimum(hi_c * f, crop.shape)
    sub = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    part = coarse[tuple(slice(int(a), int(b)) for a, b in zip(lo_c, hi_c))]
    for ax in range(3):
        part = np.repeat(part, f[ax], axis=ax)
    local = crop[sub] & part[: hi[0] - lo[0], : hi[1] - lo[1], : hi[2] - lo[2]]
    edt = depth_map(local, sp)
    q = node * f - lo
    blk = edt[q[0]:q[0] + f[0], q[1]:q[1] + f[1], q[2]:q[2] + f[2]]
    k = np.asarray(np.unravel_index(int(np.argmax(blk)), blk.shape))
    return (k + q + lo).astype(float)


def snap_to_mask(
    point: Sequence[float] | np.ndarray,
    mask: Any,
    *,
    spacing: Sequence[float] | float,
    tolerance: float,
) -> tuple[np.ndarray, float]:
    """Move a point that lies just outside the mask onto its nearest mask voxel.

    Parameters
    ----------
    point : sequence of 3 float
        Voxel index coordinates (array axis order) of a click. It is inside when its nearest voxel is.
    mask : ndarray of bool, shape (N0, N1, N2)
        The specimen (non-zero = inside).
    spacing : float or sequence of 3 float
        Voxel size along axis0, axis1, axis2.
    tolerance : float
        Largest distance (physical units) a point may be moved, >= 0.

    Returns
    -------
    snapped : ndarray, shape (3,)
        ``point`` itself when inside, else the index coordinates of the nearest mask voxel centre.
    distance : float
        How far the point moved, physical units (0 when inside).

    Raises
    ------
    InvalidInputError
        When the point is outside the array, the mask is empty, or the nearest mask voxel is farther than
        ``tolerance``.
    """
    m = _check_mask(mask)
    sp = np.asarray(check_spacing(spacing))
    try:
        p = np.asarray(point, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        p = None
    if p is None or p.shape != (3,) or not np.isfinite(p).all():
        raise InvalidInputError(f"a point must be 3 finite voxel coordinates (axis0, axis1, axis2), got {point!r}")
    if not (np.isscalar(tolerance) and np.isfinite(tolerance) and float(tolerance) >= 0):
        raise InvalidInputError(f"tolerance must be a number >= 0 (physical units), got {tolerance!r}")
    tol = float(tolerance)
    shape = np.asarray(m.shape)
    if np.any(p < -0.5) or np.any(p >= shape - 0.5):
        raise InvalidInputError(
            f"the point {np.round(p, 2).tolist()} lies outside the volume of shape {tuple(int(n) for n in shape)} "
            "(voxel coordinates in array axis order); click inside the volume"
        )
    q = np.clip(np.round(p).astype(int), 0, shape - 1)
    if m[tuple(q)]:
        return p.copy(), 0.0
    r = np.ceil(tol / sp).astype(int) + 1
    lo = np.maximum(q - r, 0)
    hi = np.minimum(q + r + 1, shape)
    idx = np.argwhere(m[tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))]) + lo
    if len(idx):
        d = np.linalg.norm((idx - p) * sp, axis=1)
        k = int(np.argmin(d))
        if d[k] <= tol:
            return idx[k].astype(float), float(d[k])
    # farther than the tolerance: say how far the mask is
    everything = np.argwhere(m)
    if len(everything) == 0:
        raise InvalidInputError("the mask is empty: there is nothing to snap the point to; check the segmentation")
    dmin = float(np.min(np.linalg.norm((everything - p) * sp, axis=1)))
    raise InvalidInputError(
        f"the point {np.round(p, 2).tolist()} is {dmin:.3g} away from the mask, more than the tolerance "
        f"{tol:.3g} (physical units); click on the specimen or raise the tolerance"
    )
