"""The join tree (superlevel-set merge tree) of a volume, its branch decomposition and hypervolume pruning.

Definitions
-----------
Sweep order
    Voxels sorted from high to low value, ties broken by flat (C order) index: exactly
    ``np.argsort(-values.ravel(), kind="stable")`` (computed as one sort of 64-bit keys, which is five times
    faster).
Branch
    Every local maximum starts a branch (its *birth*). When a swept voxel touches two or more components, the
    elder rule applies: the branch whose maximum comes first in the sweep order (higher value, ties: lower
    index) lives on, every other one dies there (its *death* is that saddle value) with the elder as its
    *parent*. The branch that holds the global maximum never dies; its death is reported as the global minimum.
    Branch ids follow the birth order, so a parent's id is always smaller than its children's.
Own voxels
    Each voxel counts for the branch that owns its component when it is swept (at a saddle, the elder): a
    branch's count is the volume its component gains while it lives (the hypervolume's voxel count).
Basins
    Each voxel also joins the *basin* of its highest already-swept neighbour (ties: the lower index), so each
    maximum grows a basin and the basins tile the volume (``JoinTree.branch``). At a saddle each dying branch
    records the basin it *attaches* to: that of the saddle's highest neighbour on the elder's side.
Noise level
    The working values' noise is estimated from the data: ``sigma`` is the robust standard deviation (1.4826 x
    the median absolute value) of the residual ``values - (3 x 3 x 3 box mean)``, over the whole array
    (:attr:`JoinTree.noise`) and in the 9 x 9 x 9 windows around a branch's maximum and around its saddle. A
    branch is *noise-level* when its persistence is below ``NOISE_FACTOR x`` its local noise: the larger of the
    global sigma and the smaller of its two windows' sigmas (a specimen's maximum lies in its own quiet
    interior; the maxima of a noisy wall or plateau, and the saddles between them, lie in the noise).
Hypervolume pruning
    A branch can be pruned once all its children are pruned; its hypervolume is then ``persistence x`` its own
    voxels plus every voxel it absorbed from pruned descendants. Every noise-level branch is pruned before any
    other, whatever its hypervolume (a large structure broken only by noise-level saddles, such as a tube wall,
    becomes one feature and cannot outrank a specimen); within each of the two classes the branch with the
    smallest hypervolume is pruned first (ties: the younger first). The whole sequence, down to the root alone,
    is computed once; keeping ``k`` features keeps the last ``k - 1`` pruned branches and the root, so the
    features kept for ``k`` are those kept for ``k + 1`` minus one. Pruned hypervolumes never decrease within a
    class (a parent's persistence and volume both dominate its children's, and a noise-level branch's children
    are noise-level too: a child's persistence is at most its parent's, and the parent of a significant branch is
    made significant).
"""

from __future__ import annotations

import os
from collections.abc import Generator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit

from ..errors import InvalidInputError
from ..progress import Progress, checkpoint, run
from ._common import MAX_FEATURES
from ._features import simplify as _simplify

__all__ = ["JoinTree", "join_tree", "join_tree_iter", "MAX_FEATURES"]


#: A branch whose persistence is below this many local noise sigmas is noise-level (pruned first). Measured on
#: phantom tanks: the noise maxima of a noisy wall reach about 6 sigmas, a fish 28 or more; the aorta CT test needs
#: 7 or less (at 8 branches of the aorta and its neighbours merge, and the seeded selection loses a third).
NOISE_FACTOR = 7.0

_SWEEP_STEPS = 16  # progress records during the sweep
_SWEEP_CHUNK = 1 << 22  # voxels swept between two cancellation checks (well under a second)
_FILTER_WORK = 1 << 25  # multiply-adds of the Gaussian filter between two cancellation checks (tens of ms)


def _gaussian(values: np.ndarray, sigma: float) -> np.ndarray:
    """``ndimage.gaussian_filter(values, sigma, mode="nearest", output=np.float32)``, the same bytes, one axis at a
    time in bundles of lines of bounded work, with a cancellation check between two bundles (a large sigma makes
    the filter's kernel, and its time, grow without bound)."""
    from scipy import ndimage

    out = np.empty(values.shape, np.float32)
    if sigma <= 1e-15:  # as gaussian_filter: no axis to filter
        out[...] = values
        return out
    radius = int(4.0 * float(sigma) + 0.5)  # gaussian_filter1d's radius at truncate=4
    src = values
    for axis in range(values.ndim):
        b, c = (a for a in range(values.ndim) if a != axis)
        per_line = values.shape[axis] * (2 * radius + 1)
        lines = max(1, _FILTER_WORK // per_line)
        nc = values.shape[c]
        if lines >= nc:  # whole planes along b
            step = lines // nc
            blocks = [{b: slice(i, i + step)} for i in range(0, values.shape[b], step)]
        else:  # parts of one plane
            blocks = [{b: slice(i, i + 1), c: slice(j, j + lines)} for i in range(values.shape[b])
                      for j in range(0, nc, lines)]
        for blk in blocks:
            checkpoint()
            sl = tuple(blk.get(a, slice(None)) for a in range(values.ndim))
            ndimage.gaussian_filter1d(src[sl], sigma, axis=axis, output=out[sl], mode="nearest")
        src = out
    return out
_NPZ_VERSION = 2
_NOISE_WINDOW = 4  # half width of the local noise windows (9 x 9 x 9)


# ------------------------------------------------------------------------------------------------------------------
# numba kernels
# ------------------------------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _find(state, x):
    """Root of ``x`` in the union-find forest ``state[:, 0]``, with path halving (no write when ``x`` hangs
    directly under the root, the usual case, so the neighbours' cache lines stay clean)."""
    while True:
        p = state[x, 0]
        if p == x:
            return x
        g = state[p, 0]
        if g == p:
            return p
        state[x, 0] = g
        x = g


@njit(cache=True, nogil=True)
def _sweep(values, order, start, stop, shape, offsets, state, birth, death, parent, count, max_voxel,
           saddle_voxel, attach, nb):
    """Sweep ``order[start:stop]``; return ``(position reached, number of branches)``.

    Stops early (before touching the voxel) when a new branch would not fit in the branch arrays, so the caller
    can grow them and call again from the returned position.

    ``state[x]`` holds, side by side so that a neighbour costs one cache line: the union-find parent (-1: not
    swept yet), the basin (branch id) and the sweep position of voxel ``x``. The root of every set is the maximum
    voxel of the set's eldest branch (younger roots are always hung under the elder one), so the basin of the
    root is the set's owner, whose ``count`` grows. A voxel joins the basin of its earliest-swept (highest)
    neighbour. 6-connectivity takes an unrolled path (a third faster than the offset table).
    """
    n0 = shape[0]
    n1 = shape[1]
    n2 = shape[2]
    plane = n1 * n2
    m = offsets.shape[0]
    six = m == 6
    cap = birth.shape[0]
    roots = np.empty(m, dtype=np.int64)
    nbr = np.empty(m, dtype=np.int64)  # the swept neighbours and their roots
    nbr_root = np.empty(m, dtype=np.int64)
    lin = np.empty(m, dtype=np.int64)
    for o in range(m):
        lin[o] = offsets[o, 0] * plane + offsets[o, 1] * n2 + offsets[o, 2]
    for p in range(start, stop):
        x = np.int64(order[p])
        i = x // plane
        r = x - i * plane
        j = r // n2
        k = r - j * n2
        nr = 0
        nn = 0
        top = np.int64(-1)  # the earliest-swept neighbour, whose basin x joins
        top_pos = np.int64(-1)
        for o in range(m):
            if six:
                if o == 0:
                    if i == 0:
                        continue
                    y = x - plane
                elif o == 1:
                    if i == n0 - 1:
                        continue
                    y = x + plane
                elif o == 2:
                    if j == 0:
                        continue
                    y = x - n2
                elif o == 3:
                    if j == n1 - 1:
                        continue
                    y = x + n2
                elif o == 4:
                    if k == 0:
                        continue
                    y = x - 1
                else:
                    if k == n2 - 1:
                        continue
                    y = x + 1
            else:
                ii = i + offsets[o, 0]
                jj = j + offsets[o, 1]
                kk = k + offsets[o, 2]
                if ii < 0 or ii >= n0 or jj < 0 or jj >= n1 or kk < 0 or kk >= n2:
                    continue
                y = x + lin[o]
            if state[y, 0] < 0:
                continue
            py = np.int64(state[y, 2])
            if top < 0 or py < top_pos:
                top = y
                top_pos = py
            ry = _find(state, y)
            nbr[nn] = y
            nbr_root[nn] = ry
            nn += 1
            dup = False
            for q in range(nr):
                if roots[q] == ry:
                    dup = True
                    break
            if not dup:
                roots[nr] = ry
                nr += 1
        if nr == 0:  # a maximum: a new branch
            if nb == cap:
                return p, nb
            v = values[x]
            state[x, 0] = x
            state[x, 1] = nb
            state[x, 2] = p
            birth[nb] = v
            death[nb] = v
            parent[nb] = -1
            count[nb] = 1
            max_voxel[nb] = x
            saddle_voxel[nb] = -1
            attach[nb] = -1
            nb += 1
        elif nr == 1:
            e = roots[0]
            state[x, 0] = e
            state[x, 1] = state[top, 1]
            state[x, 2] = p
            count[state[e, 1]] += 1
        else:  # a saddle: the elder (smallest branch id) survives
            v = values[x]
            e = roots[0]
            eb = state[e, 1]
            for q in range(1, nr):
                if state[roots[q], 1] < eb:
                    e = roots[q]
                    eb = state[e, 1]
            best = np.int64(-1)  # the earliest-swept neighbour on the elder's side: the dying branches attach to it
            best_pos = np.int64(-1)
            for q in range(nn):
                y = nbr[q]
                if nbr_root[q] == e:
                    py = np.int64(state[y, 2])
                    if best < 0 or py < best_pos:
                        best = y
                        best_pos = py
            for q in range(nr):
                rq = roots[q]
                if rq != e:
                    b = state[rq, 1]
                    death[b] = v
                    parent[b] = eb
                    saddle_voxel[b] = x
                    attach[b] = state[best, 1]
                    state[rq, 0] = e
            state[x, 0] = e
            state[x, 1] = state[top, 1]
            state[x, 2] = p
            count[eb] += 1
    return stop, nb


@njit(cache=True, nogil=True)
def _heap_less(ka, ia, kb, ib):
    # smaller hypervolume first; ties: the younger (larger id) first
    return ka < kb or (ka == kb and ia > ib)


@njit(cache=True, nogil=True)
def _heap_push(keys, ids, size, key, bid):
    pos = size
    keys[pos] = key
    ids[pos] = bid
    while pos > 0:
        up = (pos - 1) // 2
        if _heap_less(keys[pos], ids[pos], keys[up], ids[up]):
            keys[pos], keys[up] = keys[up], keys[pos]
            ids[pos], ids[up] = ids[up], ids[pos]
            pos = up
        else:
            break
    return size + 1


@njit(cache=True, nogil=True)
def _heap_pop(keys, ids, size):
    key = keys[0]
    bid = ids[0]
    size -= 1
    keys[0] = keys[size]
    ids[0] = ids[size]
    pos = 0
    while True:
        left = 2 * pos + 1
        if left >= size:
            break
        best = left
        right = left + 1
        if right < size and _heap_less(keys[right], ids[right], keys[left], ids[left]):
            best = right
        if _heap_less(keys[best], ids[best], keys[pos], ids[pos]):
            keys[pos], keys[best] = keys[best], keys[pos]
            ids[pos], ids[best] = ids[best], ids[pos]
            pos = best
        else:
            break
    return key, bid, size


@njit(cache=True, nogil=True)
def _prune(parent, persistence, count, significant):
    """The full pruning sequence: ``(branch ids in pruning order, their hypervolumes)``.

    Two heaps: the noise-level branches (``significant`` False) are pruned first, by hypervolume, then the
    others by hypervolume (a significant branch becomes prunable only once its children are gone, so it waits
    in its heap while noise-level branches remain)."""
    nb = parent.shape[0]
    nchild = np.zeros(nb, dtype=np.int64)
    for b in range(nb):
        if parent[b] >= 0:
            nchild[parent[b]] += 1
    total = count.astype(np.int64).copy()
    nkeys = np.empty(nb, dtype=np.float64)
    nids = np.empty(nb, dtype=np.int64)
    skeys = np.empty(nb, dtype=np.float64)
    sids = np.empty(nb, dtype=np.int64)
    nsize = 0
    ssize = 0
    for b in range(nb):
        if parent[b] >= 0 and nchild[b] == 0:
            if significant[b]:
                ssize = _heap_push(skeys, sids, ssize, persistence[b] * total[b], b)
            else:
                nsize = _heap_push(nkeys, nids, nsize, persistence[b] * total[b], b)
    out = np.empty(max(nb - 1, 0), dtype=np.int32)
    hyp = np.empty(max(nb - 1, 0), dtype=np.float64)
    t = 0
    while nsize > 0 or ssize > 0:
        if nsize > 0:
            key, b, nsize = _heap_pop(nkeys, nids, nsize)
        else:
            key, b, ssize = _heap_pop(skeys, sids, ssize)
        out[t] = b
        hyp[t] = key
        t += 1
        p = parent[b]
        total[p] += total[b]
        nchild[p] -= 1
        if nchild[p] == 0 and parent[p] >= 0:
            if significant[p]:
                ssize = _heap_push(skeys, sids, ssize, persistence[p] * total[p], p)
            else:
                nsize = _heap_push(nkeys, nids, nsize, persistence[p] * total[p], p)
    return out[:t], hyp[:t]


def _robust_sigma(residual: np.ndarray, axis: Any = None) -> np.ndarray:
    return 1.4826 * np.median(np.abs(residual), axis=axis)


def noise_levels(values: np.ndarray, persistence: np.ndarray, parent: np.ndarray, max_voxel: np.ndarray,
                 saddle_voxel: np.ndarray) -> tuple[float, np.ndarray]:
    """The global noise sigma of ``values`` and which branches are significant (see the module docstring).

    Returns
    -------
    sigma : float
        Robust standard deviation of the box-filter residual over the whole array.
    significant : ndarray of bool, shape (B,)
        True for the root, every branch whose persistence is at least ``NOISE_FACTOR`` local sigmas, and the
        parent of a significant branch (so the noise-level branches can be pruned first, children before
        parents).
    """
    from scipy import ndimage

    residual = values - ndimage.uniform_filter(values, 3, mode="nearest")
    flat = residual.ravel()
    step = max(1, flat.size // 2_000_000)  # a large even sample is as good as all voxels
    sigma = float(_robust_sigma(flat[::step]))
    significant = persistence >= NOISE_FACTOR * sigma
    significant[0] = True
    cand = np.flatnonzero(significant[1:]) + 1  # only these can still be noise-level locally
    if len(cand):
        r = _NOISE_WINDOW
        d = np.arange(-r, r + 1)
        grid = np.stack(np.meshgrid(d, d, d, indexing="ij"), axis=-1).reshape(-1, 3)
        shape = np.asarray(values.shape)
        local = np.full(len(cand), np.inf)
        for vox in (max_voxel[cand], saddle_voxel[cand]):
            centre = np.column_stack(np.unravel_index(vox, values.shape))
            pts = np.clip(centre[:, None, :] + grid[None], 0, shape - 1)  # windows clipped at the border
            win = residual[pts[..., 0], pts[..., 1], pts[..., 2]]
            local = np.minimum(local, _robust_sigma(win, axis=1))
        significant[cand] = persistence[cand] >= NOISE_FACTOR * np.maximum(local, sigma)
        for b in cand[::-1].tolist():  # children have larger ids than their parents
            if significant[b]:
                significant[parent[b]] = True
    return sigma, significant


# ------------------------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------------------------
def _offsets(connectivity: int) -> np.ndarray:
    if connectivity == 6:
        off = [(-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)]
    else:
        off = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)]
    return np.array(off, dtype=np.int64)


def sweep_order(values: np.ndarray) -> np.ndarray:
    """Flat voxel indices from the highest value to the lowest, ties by index (int32 when it fits).

    Equal to ``np.argsort(-values.ravel(), kind="stable")``: one sort of 64-bit keys (order-preserving bits of
    the float32 value in the high word, the index in the low word).
    """
    flat = np.ascontiguousarray(values, dtype=np.float32).ravel()
    n = flat.size
    if n >= 2**32:
        return np.argsort(-flat, kind="stable")
    bits = (flat + np.float32(0.0)).view(np.uint32)  # -0.0 -> +0.0 so equal values get equal keys
    key32 = np.where(bits >> np.uint32(31), ~bits, bits | np.uint32(0x80000000))  # increases with the value
    np.invert(key32, out=key32)  # increases as the value decreases
    key = key32.astype(np.uint64)
    del key32, bits
    key <<= np.uint64(32)
    key |= np.arange(n, dtype=np.uint64)
    key.sort()
    key &= np.uint64(0xFFFFFFFF)
    return key.astype(np.int32 if n < 2**31 else np.int64)


def _check_int(name: str, value: Any, lo: int, hi: int | None = None) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InvalidInputError(f"{name} must be an integer, got {value!r}")
    value = int(value)
    if value < lo or (hi is not None and value > hi):
        rng = f">= {lo}" if hi is None else f"between {lo} and {hi}"
        raise InvalidInputError(f"{name} must be {rng}, got {value}")
    return value


def _working_array(volume_or_array: Any, level: Any) -> tuple[np.ndarray, dict[str, Any]]:
    """The working-resolution voxels (float32) and the geometry that maps them to full resolution."""
    from ..io._volume import Volume

    if isinstance(volume_or_array, Volume):
        vol = volume_or_array
        if level is None:
            level = vol.level_for(256)
        level = _check_int("level", level, 0)
        if level >= len(vol.levels):
            raise InvalidInputError(
                f"level {level} does not exist: the volume has pyramid levels 0..{len(vol.levels) - 1}"
            )
        arr = np.asarray(vol.levels[level].compute())
        full_spacing = tuple(float(s) for s in vol.spacing)
        spacing = tuple(float(s) for s in vol.level_spacings[level])
        scale = tuple(s / f for s, f in zip(spacing, full_spacing))
        geo = dict(level=level, spacing=spacing, full_spacing=full_spacing, full_shape=vol.shape,
                   scale=scale, origin=tuple(float(o) for o in vol.origin), unit=vol.unit, source=vol.source)
    else:
        if level not in (None, 0):
            raise InvalidInputError(f"an array has a single level (0), got level={level!r}; pass a Volume instead")
        arr = volume_or_array
        if hasattr(arr, "compute"):
            arr = arr.compute()
        arr = np.asarray(arr)
        if arr.ndim != 3:
            raise InvalidInputError(f"join_tree needs a 3D volume (axis0, axis1, axis2), got shape {arr.shape}")
        geo = dict(level=0, spacing=(1.0, 1.0, 1.0), full_spacing=(1.0, 1.0, 1.0),
                   full_shape=tuple(int(n) for n in arr.shape), scale=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0),
                   unit=None, source=None)
    if arr.ndim != 3:
        raise InvalidInputError(f"join_tree needs a 3D volume (axis0, axis1, axis2), got shape {arr.shape}")
    if 0 in arr.shape:
        raise InvalidInputError(f"the volume is empty (shape {arr.shape}); nothing to segment")
    if arr.dtype == bool:
        arr = arr.astype(np.uint8)
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise InvalidInputError(f"join_tree needs numbers, got voxels of type {arr.dtype}")
    if np.issubdtype(arr.dtype, np.floating):
        nan = np.isnan(arr)
        if nan.any():
            where = tuple(int(i) for i in np.argwhere(nan)[0])
            raise InvalidInputError(
                f"the volume contains NaN ({int(nan.sum())} voxels, the first at working voxel {where}); "
                "replace NaN by a number first"
            )
        if not np.isfinite(arr).all():
            raise InvalidInputError("the volume contains infinite values; clip or replace them first")
    lo, hi = arr.min(), arr.max()
    if lo == hi:
        v = lo.item()
        raise InvalidInputError(
            f"nothing to segment: every voxel is {v}" + (" (an all-zero volume)" if v == 0 else " (a constant volume)")
        )
    return arr, geo


# ------------------------------------------------------------------------------------------------------------------
# the tree
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class JoinTree:
    """The join tree of a volume at a working resolution, with its precomputed hypervolume pruning.

    Build it with :func:`join_tree`; :meth:`simplify` then gives the features for any ``k`` in milliseconds.

    Attributes
    ----------
    values : ndarray of float32, shape (M0, M1, M2)
        The working array the tree was built on (the pyramid level, smoothed).
    branch : ndarray of int32, shape (M0, M1, M2)
        The basin (branch id) of each voxel (see the module docstring).
    birth : ndarray of float64, shape (B,)
        Value of each branch's maximum.
    death : ndarray of float64, shape (B,)
        Value of the saddle where each branch merges into its parent; the global minimum for the root.
    parent : ndarray of int32, shape (B,)
        Parent branch (the elder at the saddle), -1 for the root (branch 0).
    count : ndarray of int64, shape (B,)
        Own voxel count of each branch.
    max_voxel : ndarray of int64, shape (B,)
        Flat index (C order, working array) of each branch's maximum.
    saddle_voxel : ndarray of int64, shape (B,)
        Flat index of each branch's saddle voxel, -1 for the root.
    attach : ndarray of int32, shape (B,)
        The basin each branch's basin meets at its saddle (the branch of the highest neighbour of the saddle
        voxel on the elder's side), -1 for the root. These edges form a spanning tree of the basins rooted at
        branch 0 (each joins two components that were apart), the spatial counterpart of ``parent``.
    prune_order : ndarray of int32, shape (B - 1,)
        Every non-root branch in hypervolume pruning order.
    prune_hypervolume : ndarray of float64, shape (B - 1,)
        Hypervolume of each branch when it is pruned (non-decreasing within the noise-level branches, which
        come first, and within the others).
    significant : ndarray of bool, shape (B,)
        False for the noise-level branches (see the module docstring); all True for a tree saved before
        version 2.
    noise : float
        The global noise sigma of ``values`` (NaN for a tree saved before version 2).
    level : int
        The pyramid level the tree was built on (0 for an array).
    spacing : tuple of 3 float
        Voxel size of the working level, in ``unit``.
    full_shape : tuple of 3 int
        Shape of the full-resolution volume (level 0).
    full_spacing : tuple of 3 float
        Voxel size of level 0.
    scale : tuple of 3 float
        Full-resolution voxels per working voxel along each axis (``spacing / full_spacing``).
    origin : tuple of 3 float
        Physical position of full-resolution voxel (0, 0, 0).
    unit : str or None
        Length unit.
    smooth : float
        Gaussian sigma (working voxels) applied before the sweep.
    connectivity : int
        6 or 26.
    source : str or None
        Where the volume came from.
    """

    values: np.ndarray
    branch: np.ndarray
    birth: np.ndarray
    death: np.ndarray
    parent: np.ndarray
    count: np.ndarray
    max_voxel: np.ndarray
    saddle_voxel: np.ndarray
    attach: np.ndarray
    prune_order: np.ndarray
    prune_hypervolume: np.ndarray
    significant: np.ndarray
    noise: float = float("nan")
    level: int = 0
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    full_shape: tuple[int, int, int] = (0, 0, 0)
    full_spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    unit: str | None = None
    smooth: float = 0.0
    connectivity: int = 6
    source: str | None = None
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    # -- basic properties ----------------------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int]:
        """Shape of the working array."""
        return tuple(int(n) for n in self.values.shape)  # type: ignore[return-value]

    @property
    def n_maxima(self) -> int:
        """Number of local maxima (branches) of the working array: the largest ``k`` :meth:`simplify` accepts."""
        return int(self.birth.shape[0])

    @property
    def persistence(self) -> np.ndarray:
        """``birth - death`` of every branch, shape (B,) (the root's runs down to the global minimum)."""
        return self.birth - self.death

    @property
    def rank(self) -> np.ndarray:
        """Importance of every branch, shape (B,): 0 for the root, 1 for the last pruned, ... (``k`` keeps
        ``rank < k``)."""
        if "rank" not in self._cache:
            nb = self.n_maxima
            rank = np.empty(nb, dtype=np.int64)
            rank[0] = 0
            rank[self.prune_order] = np.arange(nb - 1, 0, -1)
            self._cache["rank"] = rank
        return self._cache["rank"]

    @property
    def working_origin(self) -> tuple[float, float, float]:
        """Physical position of working voxel (0, 0, 0): the centre of the full-resolution block it covers."""
        return tuple(o + (s - f) / 2 for o, s, f in zip(self.origin, self.spacing, self.full_spacing))  # type: ignore

    def components_at(self, t: float) -> int:
        """Number of connected components of ``{values >= t}`` the tree implies (branches alive at ``t``)."""
        death = self.death.copy()
        death[0] = -np.inf
        return int(np.count_nonzero((self.birth >= t) & (death < t)))

    def simplify(self, k: int = 5):
        """Keep the ``k`` features of largest hypervolume.

        Parameters
        ----------
        k : int
            Number of features, 1..100 and at most :attr:`n_maxima`.

        Returns
        -------
        Features
            The label volume (working resolution) and the statistics of each feature.
        """
        return _simplify(self, k)

    # -- serialisation -------------------------------------------------------------------------------------------
    _ARRAYS = ("values", "branch", "birth", "death", "parent", "count", "max_voxel", "saddle_voxel", "attach",
               "prune_order", "prune_hypervolume", "significant")

    def to_dict(self) -> dict[str, Any]:
        """Every array and setting as a dict of numpy arrays (for ``np.savez`` or a service cache)."""
        d: dict[str, Any] = {name: getattr(self, name) for name in self._ARRAYS}
        d.update(
            version=np.array(_NPZ_VERSION),
            noise=np.array(self.noise, dtype=float),
            level=np.array(self.level),
            spacing=np.array(self.spacing, dtype=float),
            full_shape=np.array(self.full_shape, dtype=np.int64),
            full_spacing=np.array(self.full_spacing, dtype=float),
            scale=np.array(self.scale, dtype=float),
            origin=np.array(self.origin, dtype=float),
            unit=np.array(self.unit or ""),
            smooth=np.array(self.smooth, dtype=float),
            connectivity=np.array(self.connectivity),
            source=np.array(self.source or ""),
        )
        return d

    @classmethod
    def from_dict(cls, d: Any) -> JoinTree:
        """Rebuild a tree from :meth:`to_dict` output (or an opened ``.npz``)."""
        try:
            version = int(d["version"])
            if version not in (1, _NPZ_VERSION):
                raise InvalidInputError(
                    f"join tree format version {version} is not supported (need 1 or {_NPZ_VERSION})")
            if version == 1:  # before the noise level: pruned by hypervolume alone
                arrays = {name: np.asarray(d[name]) for name in cls._ARRAYS if name != "significant"}
                arrays["significant"] = np.ones(arrays["birth"].shape, dtype=bool)
                noise = float("nan")
            else:
                arrays = {name: np.asarray(d[name]) for name in cls._ARRAYS}
                noise = float(d["noise"])
            unit = str(d["unit"]) or None
            source = str(d["source"]) or None
            return cls(
                **arrays,
                noise=noise,
                level=int(d["level"]),
                spacing=tuple(float(v) for v in d["spacing"]),
                full_shape=tuple(int(v) for v in d["full_shape"]),
                full_spacing=tuple(float(v) for v in d["full_spacing"]),
                scale=tuple(float(v) for v in d["scale"]),
                origin=tuple(float(v) for v in d["origin"]),
                unit=unit,
                smooth=float(d["smooth"]),
                connectivity=int(d["connectivity"]),
                source=source,
            )
        except KeyError as exc:
            raise InvalidInputError(f"not a saved join tree: {exc.args[0]!r} is missing") from None

    def to_npz(self, path: str | os.PathLike, *, compress: bool = False) -> Path:
        """Save the tree to ``path`` (``.npz``); ``compress`` trades time for size."""
        path = Path(path)
        (np.savez_compressed if compress else np.savez)(path, **self.to_dict())
        return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")

    @classmethod
    def from_npz(cls, path: str | os.PathLike) -> JoinTree:
        """Load a tree saved by :meth:`to_npz`."""
        with np.load(Path(path), allow_pickle=False) as z:
            return cls.from_dict(z)

    def __repr__(self) -> str:
        return (f"JoinTree(shape={self.shape}, level={self.level}, scale={self.scale}, n_maxima={self.n_maxima}, "
                f"smooth={self.smooth}, connectivity={self.connectivity})")


def join_tree_iter(
    volume_or_array: Any, *, level: int | None = None, smooth: float = 1.0, connectivity: int = 6
) -> Generator[Progress, None, JoinTree]:
    """Generator form of :func:`join_tree`: yields :class:`~napari_unwind.progress.Progress`, returns the tree."""

    try:
        smooth = float(smooth)
    except (TypeError, ValueError):
        raise InvalidInputError(f"smooth must be a number (Gaussian sigma in working voxels), got {smooth!r}") from None
    if not np.isfinite(smooth) or smooth < 0:
        raise InvalidInputError(f"smooth must be finite and >= 0 (0: no smoothing), got {smooth}")
    if isinstance(connectivity, (bool, np.bool_)) or connectivity not in (6, 26):
        raise InvalidInputError(f"connectivity must be 6 (faces) or 26 (faces, edges, corners), got {connectivity!r}")
    connectivity = int(connectivity)
    if hasattr(volume_or_array, "ndim") and volume_or_array.ndim != 3:
        raise InvalidInputError(
            f"join_tree needs a 3D volume (axis0, axis1, axis2), got shape {tuple(volume_or_array.shape)}"
        )
    yield Progress("read", 0, 1, "working level")
    arr, geo = _working_array(volume_or_array, level)
    yield Progress("read", 1, 1, f"{arr.shape}")
    values = np.asarray(arr, dtype=np.float32)
    if smooth > 0:
        yield Progress("smooth", 0, 1, f"sigma {smooth:g}")
        values = _gaussian(values, smooth)
        yield Progress("smooth", 1, 1)
    values = np.ascontiguousarray(values)
    yield Progress("sort", 0, 1)
    order = sweep_order(values)
    yield Progress("sort", 1, 1)

    n = values.size
    flat = values.ravel()
    state = np.full((n, 3), -1, dtype=np.int32 if n < 2**31 else np.int64)
    cap = max(64, n // 256)
    arrays = _branch_arrays(cap)
    shape = np.array(values.shape, dtype=np.int64)
    offsets = _offsets(connectivity)
    nb = 0
    steps = np.linspace(0, n, _SWEEP_STEPS + 1).astype(np.int64)
    for s in range(_SWEEP_STEPS):
        pos, stop = int(steps[s]), int(steps[s + 1])
        while pos < stop:
            checkpoint()  # a cancelled job stops here (at most _SWEEP_CHUNK voxels apart); the sweep resumes at pos
            pos, nb = _sweep(flat, order, pos, min(stop, pos + _SWEEP_CHUNK), shape, offsets, state, *arrays, nb)
            if pos < stop and nb >= arrays[0].shape[0]:  # the branch arrays are full: grow them
                arrays = _grow(arrays, 2 * arrays[0].shape[0])
        yield Progress("sweep", s + 1, _SWEEP_STEPS, f"{nb} maxima")
    del order
    branch = np.ascontiguousarray(state[:, 1], dtype=np.int32)
    del state
    birth, death, parent, count, max_voxel, saddle_voxel, attach = (a[:nb].copy() for a in arrays)
    del arrays
    death[0] = float(flat.min())
    yield Progress("prune", 0, 1)
    noise, significant = noise_levels(values, birth - death, parent, max_voxel, saddle_voxel)
    prune_order, prune_hyp = _prune(parent, birth - death, count, significant)
    yield Progress("prune", 1, 1, f"{int(np.count_nonzero(significant))} above the noise")
    return JoinTree(
        values=values, branch=branch.reshape(values.shape), birth=birth, death=death, parent=parent,
        count=count, max_voxel=max_voxel, saddle_voxel=saddle_voxel, attach=attach, prune_order=prune_order,
        prune_hypervolume=prune_hyp, significant=significant, noise=noise, smooth=smooth,
        connectivity=connectivity, **geo,
    )


def _branch_arrays(cap: int) -> tuple[np.ndarray, ...]:
    """birth, death, parent, count, max_voxel, saddle_voxel, attach."""
    return (np.empty(cap, np.float64), np.empty(cap, np.float64), np.empty(cap, np.int32), np.empty(cap, np.int64),
            np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int32))


def _grow(arrays: tuple[np.ndarray, ...], cap: int) -> tuple[np.ndarray, ...]:
    new = _branch_arrays(cap)
    for a, b in zip(arrays, new):
        b[: a.shape[0]] = a
    return new


def join_tree(
    volume_or_array: Any, *, level: int | None = None, smooth: float = 1.0, connectivity: int = 6, progress=None
) -> JoinTree:
    """Build the join tree (superlevel-set merge tree) of a volume at a working resolution.

    Parameters
    ----------
    volume_or_array : Volume or array_like, shape (N0, N1, N2)
        A :class:`~napari_unwind.io.Volume` (its pyramid level ``level`` is read) or a 3D array of numbers
        (used as it is).
    level : int, optional
        Pyramid level of a Volume to work on. Default: the finest level with every side <= 256
        (``volume.level_for(256)``).
    smooth : float
        Gaussian sigma in working voxels applied before the sweep to tame noise maxima; 0 for none.
        Default 1.
    connectivity : int
        6 (faces, default) or 26 (faces, edges and corners).
    progress : callable, optional
        Called with each :class:`~napari_unwind.progress.Progress` record.

    Returns
    -------
    JoinTree
        The tree with its per-voxel branches and its precomputed pruning sequence.

    Raises
    ------
    InvalidInputError
        For a non-3D input, NaN or infinite voxels, a constant (or all-zero) volume, a missing level or a bad
        option.

    Notes
    -----
    Voxels are swept from high to low value with a union-find (path halving); memory is about four arrays of
    the working shape (float32 values, int32 order, union-find and branch ids) plus the 64-bit sort keys. See
    the module docstring for the exact definitions.
    """
    return run(join_tree_iter(volume_or_array, level=level, smooth=smooth, connectivity=connectivity), progress)
