"""Straighten a scan along a :class:`~napari_unwind.deformation.Deformation`, bend it back, and map points.

The straight volume has axis0 = ``s`` (arclength), axis1 = ``y`` (along v) and axis2 = ``x`` (along u), on an
isotropic grid of spacing ``ds``: straight voxel ``(k, i, j)`` is ``s = s_lo + k ds``, ``y = (i - i0) ds``,
``x = (j - j0) ds`` with ``(i0, j0)`` = :meth:`Deformation.grid_centre` (``((Ny - 1) / 2, (Nx - 1) / 2)`` for
centred cages; see :meth:`Deformation.output_shape` and :meth:`Deformation.slice_geometry`).

How straightening scales (docs/design.md section 7)
---------------------------------------------------
Each output slice is an affine image of the scan: straight voxel ``(k, i, j)`` samples the scan at voxel
coordinate ``base_k + i dv_k + j du_k``. Nine numbers per slice are the whole map. So, per output chunk:

1. the bounding box of the scan coordinates it needs is exact and cheap: the four corners of the chunk's
   ``(i, j)`` range on each of its slices;
2. that box plus the interpolation margin, clipped to the scan, is what the block reads: its task depends on the
   whole input chunks that hold the box (so each input chunk is read and decompressed once per computation,
   however many blocks need it) and copies the box out of them; only those chunks are ever read, and a block
   whose box misses the scan is filled without reading anything;
3. the task resamples the block: a numba kernel (orders 0 and 1) walks the block's voxels row by row, generating
   each row's coordinates from ``base``, ``dv`` and ``du`` on the fly, with no coordinate array beyond one row.
   Per row it solves for the run of columns whose samples lie safely inside the region (the map is linear along
   a row) and interpolates that run without any bounds test, in three passes over row buffers (cells and
   fractions, vectorised; the eight neighbours by unsigned flat indices; the weights, vectorised); rows that
   miss the scan are filled at once, and only the few samples near the scan's edge take the checked path.
   Order 3 prefilters the region and calls :func:`scipy.ndimage.map_coordinates` one slice at a time.

The tasks are plain module-level functions of numpy arrays, so the same graph runs on the threaded or
synchronous scheduler or on a ``dask.distributed`` cluster, with identical results. Peak memory depends on the
chunk sizes, not on the scan (default chunks tile cross-sections wider than 256 voxels).

Bending back inverts the map voxel by voxel with a compiled version of :meth:`Deformation.inverse` (same seeds,
Newton steps and inside rule; agreement to 1e-9 is tested), skipping blocks and voxels beyond the cage's reach.

Inputs, units and limits
------------------------
The scan may be a :class:`~napari_unwind.io.Volume`, a path (opened with :func:`~napari_unwind.io.open_volume`),
an array or a nested list (whole numbers become int32). A Volume in another length unit than the deformation
(mm against micrometres...) is converted to the deformation's unit before its geometry is compared; the output,
``spacing=`` and the padding are in the deformation's unit. Before anything proportional to the output exists
(slice tables, graph, voxels) the output's size is checked against ``max_output`` (default
:data:`DEFAULT_MAX_OUTPUT`, 64 GiB), padding that runs far beyond the scan is refused, a straight grid with no
sample in the scan is refused and one mostly outside warns (:class:`OutsideWarning`), both computed from the slice
geometry; :func:`export` also compares the size with the free space at its target.

Sampling semantics (the reference the tests compare against)
------------------------------------------------------------
The result equals ``scipy.ndimage.map_coordinates(volume, coords, order=order, mode="constant", cval=fill)``
of the whole volume, ``coords`` being the scan voxel coordinates of the output grid:

- a sample is valid iff ``0 <= c <= n - 1`` on every axis (scipy's ``"constant"`` mode: no interpolation
  beyond the edge, unlike ``"grid-constant"``); invalid samples get ``fill``;
- order 0 takes voxel ``floor(c + 0.5)`` (halves round up);
- integer outputs are rounded half away from zero and clipped to the type's range, as scipy does.

Orders 0 and 1 match scipy to floating-point rounding (order 0 exactly; order 1 to ~1e-12 relative, so an
integer result can differ by one grey value where scipy's value is within 1e-12 of a half). Order 3 prefilters
each region with a margin of :data:`ORDER3_FILTER_MARGIN` voxels beyond the cubic support; the truncated
B-spline prefilter then differs from the whole-volume one by about ``0.268 ** margin`` (3e-5 of the local
data range for margin 8) inside the volume, and exactly nothing where the region reaches the volume's edge.
"""

from __future__ import annotations

import math
import operator
import os
import reprlib
import shutil
import uuid
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import dask
import dask.array as da
import numpy as np
from dask.highlevelgraph import HighLevelGraph
from numba import njit
from scipy import ndimage

from .deformation import Deformation
from .errors import InvalidInputError, OutputError
from .io._api import _size, open_volume, write_volume_iter
from .io._atomic import atomic_output, check_writable
from .io._formats import output_format
from .io._volume import SUPPORTED_DTYPES, Volume, normalise_unit, unit_label
from .progress import Progress, checkpoint, run
from .scheduler import use_scheduler

__all__ = [
    "DEFAULT_MAX_OUTPUT",
    "DiskSpaceWarning",
    "FoldWarning",
    "ORDER3_FILTER_MARGIN",
    "OutsideWarning",
    "bend",
    "export",
    "export_iter",
    "export_channels_iter",
    "map_labels",
    "map_mesh",
    "map_points",
    "straighten",
]

#: Extra voxels read around an order-3 region so that its B-spline prefilter matches the whole volume's
#: (error about 0.268 ** margin of the local data range).
ORDER3_FILTER_MARGIN = 8

#: Default depth (output slices) of a straightening chunk.
DEFAULT_CHUNK_DEPTH = 64
#: Default chunks hold whole cross-sections up to this side; larger ones are split into near-equal tiles.
DEFAULT_TILE = 256

#: Default limit of an output's size (bytes, uncompressed): 64 GiB. Larger outputs of :func:`straighten`,
#: :func:`export`, :func:`bend` and :func:`map_labels` are refused before anything proportional to them is
#: allocated, unless the call passes a larger ``max_output`` (CLI: ``--max-output``) or ``max_output=None`` (no
#: limit). It is above the largest scans the project targets (docs/design.md: 45 GB) and a straightened specimen is
#: usually smaller than its scan, so an output this large is nearly always a wrong spacing, pad or unit
#: (the demo fish at ``--spacing 0.01`` would be 120 GiB; with ``--pad 100000000``, 86 GiB).
DEFAULT_MAX_OUTPUT = 64 * 2**30
#: Points :func:`map_points` maps between two cancellation checks (tens of milliseconds).
_MAP_BATCH = 16384

#: Largest ``pad`` (output slices at each end) accepted at all, whatever ``max_output``.
MAX_PAD = 10**9

#: Straightening warns (:class:`OutsideWarning`) when more than this fraction of the output samples outside the scan.
OUTSIDE_WARN_FRACTION = 0.5

#: Samples this close (voxels) to an edge of the region take the checked path in the kernels.
_EDGE_EPS = 1e-6


class FoldWarning(UserWarning):
    """The deformation folds: its cage is larger than the local radius of curvature somewhere.

    There the straight box maps onto itself twice and the straightened volume repeats (mirrors) tissue.
    """


class OutsideWarning(UserWarning):
    """Most of the straight volume (more than :data:`OUTSIDE_WARN_FRACTION`) samples outside the scan.

    Those voxels get ``fill``. The message gives the fraction.
    """


class DiskSpaceWarning(UserWarning):
    """A compressed export may not fit the free space at its target (its uncompressed size does not)."""


# ------------------------------------------------------------------------------------------------------------------
# validation helpers
# ------------------------------------------------------------------------------------------------------------------
def _check_order(order: Any) -> int:
    if isinstance(order, bool) or order not in (0, 1, 3):
        raise InvalidInputError(f"interpolation order must be 0 (nearest), 1 (linear) or 3 (cubic), got {order!r}")
    return int(order)


def _check_pad(pad: Any) -> int:
    """``pad``: a whole number of output slices, 0..MAX_PAD (an integral float such as 2.0 is accepted)."""
    ok = not isinstance(pad, bool) and isinstance(pad, (int, np.integer, float, np.floating))
    if ok and isinstance(pad, (float, np.floating)):
        ok = math.isfinite(pad) and float(pad).is_integer()
    if not ok or pad < 0:
        raise InvalidInputError(f"pad must be a whole number of output slices >= 0, got {pad!r}")
    if pad > MAX_PAD:
        raise InvalidInputError(f"pad {pad!r} is absurd: at most {MAX_PAD:,} output slices at each end")
    return int(pad)


def _check_max_output(max_output: Any) -> int | None:
    """``max_output``: None (no limit) or a positive number of bytes."""
    if max_output is None:
        return None
    ok = not isinstance(max_output, bool) and isinstance(max_output, (int, np.integer, float, np.floating))
    if not ok or not (max_output >= 1 and math.isfinite(max_output)):
        raise InvalidInputError(f"max_output must be a number of bytes >= 1, or None for no limit, got {max_output!r}")
    return int(max_output)


def _check_output_size(what: str, shape: Sequence[int], dtype: Any, max_output: int | None, hint: str) -> int:
    """Bytes of an output of ``shape`` and ``dtype``; refuses one larger than ``max_output`` (None: no limit).

    Called before anything proportional to the output (tables, graph, voxels) exists.
    """
    shape = tuple(int(n) for n in shape)
    dtype = np.dtype(dtype)
    voxels = math.prod(shape)
    nbytes = voxels * dtype.itemsize
    if max_output is not None and nbytes > max_output:
        raise InvalidInputError(
            f"the {what} would have shape {shape}: {voxels:,} voxels of {dtype}, {nbytes:,} bytes "
            f"({_size(nbytes)}), more than the limit max_output={max_output:,} bytes ({_size(max_output)}); "
            f"{hint}, or pass max_output=... (CLI: --max-output) to raise the limit (max_output=None: no limit)"
        )
    return nbytes


def _check_fill(fill: Any, dtype: np.dtype) -> Any:
    """``fill`` as a value of ``dtype``; raises when the type cannot hold it exactly."""
    try:
        value = float(fill)
    except (TypeError, ValueError):
        raise InvalidInputError(f"fill must be a number, got {fill!r}") from None
    if dtype == np.bool_:
        if value not in (0.0, 1.0):
            raise InvalidInputError(f"fill for a boolean volume must be 0 or 1, got {fill!r}")
        return bool(value)
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        if not (np.isfinite(value) and value == math.floor(value) and info.min <= value <= info.max):
            raise InvalidInputError(
                f"fill {fill!r} cannot be stored in the volume's type {dtype} (whole numbers {info.min}..{info.max})"
            )
        return dtype.type(int(value))
    if not np.isfinite(value):
        raise InvalidInputError(f"fill must be finite, got {fill!r}")
    return dtype.type(value)


def _close(a: Sequence[float], b: Sequence[float], rel: float = 1e-6) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return bool(np.all(np.abs(a - b) <= rel * np.maximum(np.abs(a), np.abs(b))))


#: Powers of ten of the length units :func:`~napari_unwind.io._volume.normalise_unit` knows.
_UNIT_EXPONENT = {"meter": 0, "centimeter": -2, "millimeter": -3, "micrometer": -6, "nanometer": -9}


def _unit_scale(unit: str | None, to: str | None) -> float:
    """Factor taking lengths in ``unit`` to lengths in ``to`` (1 when either is unknown or they agree)."""
    unit, to = normalise_unit(unit), normalise_unit(to)
    if unit is None or to is None or unit == to:
        return 1.0
    return 10.0 ** (_UNIT_EXPONENT[unit] - _UNIT_EXPONENT[to])


def _fmt_triple(values: Sequence[float]) -> str:
    return "(" + ", ".join(f"{v:.6g}" for v in values) + ")"


def _check_geometry(volume: Volume, deformation: Deformation) -> str | None:
    """Check a Volume's spacing and origin against the deformation's, converting the unit; returns the unit.

    When both units are known length units the volume's geometry is converted to the deformation's unit first, so
    a scan in millimetres matches a deformation in micrometres of the same grid; the result is then in the
    deformation's unit. When one unit is unknown the numbers are compared as they are.
    """
    f = _unit_scale(volume.unit, deformation.unit)
    spacing = tuple(v * f for v in volume.spacing)
    origin = tuple(v * f for v in volume.origin)
    sp_ok = _close(spacing, deformation.spacing)
    scale = max(max(abs(o) for o in origin), max(deformation.spacing))
    org_ok = all(abs(a - b) <= 1e-6 * scale for a, b in zip(origin, deformation.origin, strict=True))
    if not (sp_ok and org_ok):
        v_unit, d_unit = volume.unit or "unit not recorded", deformation.unit or "unit not recorded"
        converted = (f", i.e. spacing {_fmt_triple(spacing)}, origin {_fmt_triple(origin)} {deformation.unit}"
                     if f != 1.0 else "")
        raise InvalidInputError(
            f"the volume's geometry (spacing {volume.spacing}, origin {volume.origin} {v_unit}{converted}) differs "
            f"from the deformation's (spacing {deformation.spacing}, origin {deformation.origin} {d_unit}); the "
            "deformation belongs to another scan or to another pyramid level, or one of the units is wrong"
        )
    return deformation.unit or volume.unit


def _nested(values: Any, *, keep_int64: bool) -> np.ndarray:
    """A nested list (or anything without a dtype) as an array.

    Python integers become int64 in numpy, a type a Volume cannot hold: unless ``keep_int64`` (label images),
    they become int32 when every value fits, else the error says so.
    """
    try:
        arr = np.asarray(values)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(
            f"the volume must be an array, or a nested list of numbers of shape (N0, N1, N2); this nested list "
            f"cannot be one ({exc})"
        ) from None
    if not keep_int64 and arr.dtype == np.int64:
        lo, hi = (int(arr.min()), int(arr.max())) if arr.size else (0, 0)
        if lo < -(2**31) or hi >= 2**31:
            raise InvalidInputError(
                f"a nested list of whole numbers becomes int32 (numpy would make int64, which a volume cannot "
                f"hold), but this one holds values {lo}..{hi}, beyond int32 (-2**31..2**31-1); pass an array of "
                "float64 instead"
            )
        arr = arr.astype(np.int32)
    return arr


def _in_place(values: np.ndarray) -> da.Array:
    """A numpy array as a dask array of one chunk that is the array itself: no copy, no hash of its voxels.

    ``da.from_array`` would copy the array and hash all of it for the name (0.1 s for 65 MB, more than a small
    straightening takes); the tasks read their regions as views of it instead. The name is random, so two inputs
    never share one.
    """
    name = f"ndarray-{uuid.uuid4().hex}"
    return da.Array({(name,) + (0,) * values.ndim: values}, name, chunks=tuple((int(n),) for n in values.shape),
                    dtype=values.dtype, meta=np.empty((0,) * values.ndim, dtype=values.dtype))


def _as_dask(values: Any, *, keep_int64: bool) -> da.Array:
    """Any array-like (dask, numpy, zarr, nested lists) as a dask array; numpy arrays are used in place."""
    if isinstance(values, da.Array):
        return values
    if isinstance(values, np.ndarray):
        return _in_place(values)
    if hasattr(values, "shape") and hasattr(values, "dtype") and hasattr(values, "__getitem__"):
        return da.from_array(values, chunks=tuple(max(1, min(int(s), 128)) for s in values.shape), name=False)
    return _in_place(_nested(values, keep_int64=keep_int64))


def _input_array(volume: Any, deformation: Deformation, *, any_dtype: bool = False
                 ) -> tuple[da.Array, str | None, str | None]:
    """The scan as a dask array, checked against the deformation's geometry; also its unit and source.

    ``volume`` is a Volume, a path (opened with :func:`~napari_unwind.io.open_volume`), an array or a nested list.
    Without ``any_dtype`` the voxel type must be one a Volume holds (the straight volume keeps it).
    """
    if not isinstance(deformation, Deformation):
        raise InvalidInputError(f"deformation must be a napari_unwind.Deformation, got {type(deformation).__name__}")
    if isinstance(volume, (str, os.PathLike)):
        volume = open_volume(volume)
    if isinstance(volume, Volume):
        unit = _check_geometry(volume, deformation)
        return volume.data, unit, volume.source
    data = _as_dask(volume, keep_int64=any_dtype)
    if data.ndim != 3:
        raise InvalidInputError(f"the volume must be 3D (axis0, axis1, axis2), got shape {data.shape}")
    if 0 in data.shape:
        raise InvalidInputError(f"the volume must not have a dimension of size 0, got shape {data.shape}")
    dt = np.dtype(data.dtype)
    if not any_dtype and not (np.issubdtype(dt, np.integer) or np.issubdtype(dt, np.floating)):
        raise InvalidInputError(f"cannot interpolate voxels of type {dt}; use integers or floats")
    if not (np.issubdtype(dt, np.integer) or np.issubdtype(dt, np.floating) or dt == np.bool_):
        raise InvalidInputError(f"unsupported voxel type {dt}")
    if not any_dtype and dt not in SUPPORTED_DTYPES:
        raise InvalidInputError(
            f"cannot straighten voxels of type {dt}: the straight volume keeps the scan's type, and a volume holds "
            f"only {', '.join(str(t) for t in SUPPORTED_DTYPES)}; convert first, e.g. volume.astype(np.float32) "
            "(or np.int32 when the values fit)"
        )
    return data, deformation.unit, None


def _warn_folds(deformation: Deformation, what: str) -> None:
    folds = deformation.folds()
    if folds:
        unit = unit_label(deformation.unit)
        where = ", ".join(f"[{a:.4g}, {b:.4g}]" for a, b in folds)
        warnings.warn(
            f"the deformation folds at s in {where} ({unit}): the cage is larger than the local radius of "
            f"curvature there, so the {what} maps tissue twice; shrink the cage or add keyframes to smooth the bend",
            FoldWarning,
            stacklevel=3,
        )


def _normalise_out_chunks(chunks: Any, shape: tuple[int, int, int]) -> tuple[tuple[int, ...], ...]:
    if chunks is None:
        # whole cross-sections, tiled when a side exceeds DEFAULT_TILE: an oblique tile's input box grows with
        # its area, so large cross-sections in one piece would need large input regions per task
        chunks = (DEFAULT_CHUNK_DEPTH,) + tuple(math.ceil(n / math.ceil(n / DEFAULT_TILE)) for n in shape[1:])
    try:
        return da.core.normalize_chunks(chunks, shape)
    except (ValueError, TypeError) as exc:
        raise InvalidInputError(f"invalid chunks {chunks!r} for an output of shape {shape}: {exc}") from None


def _padded(deformation: Deformation, pad: int, ds: float) -> Deformation:
    if pad == 0:
        return deformation
    return deformation.with_pad(deformation.pad[0] + pad * ds, deformation.pad[1] + pad * ds)


# ------------------------------------------------------------------------------------------------------------------
# the kernels
# ------------------------------------------------------------------------------------------------------------------
@njit(nogil=True, cache=True)
def _restrict(q: float, d: float, lo: float, hi: float, ta: float, tb: float) -> tuple[float, float]:
    """Restrict the interval ``[ta, tb]`` of t to where ``lo <= q + t d <= hi``."""
    if d > 0.0:
        ta = max(ta, (lo - q) / d)
        tb = min(tb, (hi - q) / d)
    elif d < 0.0:
        ta = max(ta, (hi - q) / d)
        tb = min(tb, (lo - q) / d)
    elif q < lo or q > hi:
        ta = 1.0
        tb = 0.0
    return ta, tb


@njit(nogil=True, cache=True)
def _runs(p0: float, p1: float, p2: float, u0: float, u1: float, u2: float, nj: int,
          o0: int, o1: int, o2: int, r0: int, r1: int, r2: int, n0: int, n1: int, n2: int,
          fast_hi_off: float) -> tuple[int, int, int, int]:
    """Column runs of one output row whose samples ``p + t u`` are (loosely) valid / safely inside the region.

    Returns ``(la, lb, fa, fb)``: columns outside ``[la, lb]`` are certainly outside the volume; columns in
    ``[fa, fb]`` have every axis in ``[o + eps, o + r - 1 - fast_hi_off - eps]`` (the kernel's bounds-free fast
    path). ``fa > fb`` when there is no fast run.
    """
    eps = 1e-6
    ta, tb = 0.0, nj - 1.0
    ta, tb = _restrict(p0, u0, -eps, n0 - 1.0 + eps, ta, tb)
    ta, tb = _restrict(p1, u1, -eps, n1 - 1.0 + eps, ta, tb)
    ta, tb = _restrict(p2, u2, -eps, n2 - 1.0 + eps, ta, tb)
    if ta > tb:
        return 0, -1, 0, -1
    la = max(0, int(math.ceil(ta)))
    lb = min(nj - 1, int(math.floor(tb)))
    fa_f, fb_f = float(la), float(lb)
    fa_f, fb_f = _restrict(p0, u0, o0 + eps, o0 + r0 - 1.0 - fast_hi_off - eps, fa_f, fb_f)
    fa_f, fb_f = _restrict(p1, u1, o1 + eps, o1 + r1 - 1.0 - fast_hi_off - eps, fa_f, fb_f)
    fa_f, fb_f = _restrict(p2, u2, o2 + eps, o2 + r2 - 1.0 - fast_hi_off - eps, fa_f, fb_f)
    if fa_f > fb_f:
        return la, lb, lb + 1, lb
    fa = max(la, int(math.ceil(fa_f)))
    fb = min(lb, int(math.floor(fb_f)))
    if fa > fb:
        return la, lb, lb + 1, lb
    return la, lb, fa, fb


@njit(nogil=True, cache=True)
def _samples_inside(base, dv, du, ny, nx, n0, n1, n2):
    """How many samples ``base_k + i dv_k + j du_k`` (all k, i < ny, j < nx) lie in the scan ``[0, n - 1]``.

    To the kernels' tolerance (1e-6 voxel, as in :func:`_runs`). A slice is a parallelogram: when its four
    corners are inside, all of it is; when they all lie beyond one face, none of it is; only slices across the
    scan's border are counted row by row, each row's run of inside columns solved as in :func:`_runs`.
    """
    eps = 1e-6
    hi = np.array([n0 - 1.0, n1 - 1.0, n2 - 1.0])
    total = 0
    for k in range(base.shape[0]):
        inside = True
        missed = False
        for a in range(3):
            c00 = base[k, a]
            c01 = c00 + (nx - 1) * du[k, a]
            c10 = c00 + (ny - 1) * dv[k, a]
            c11 = c10 + (nx - 1) * du[k, a]
            lo_c = min(min(c00, c01), min(c10, c11))
            hi_c = max(max(c00, c01), max(c10, c11))
            if lo_c < -eps or hi_c > hi[a] + eps:
                inside = False
            if hi_c < -eps or lo_c > hi[a] + eps:
                missed = True
        if missed:
            continue
        if inside:
            total += ny * nx
            continue
        for i in range(ny):
            ta, tb = 0.0, nx - 1.0
            for a in range(3):
                ta, tb = _restrict(base[k, a] + i * dv[k, a], du[k, a], -eps, hi[a] + eps, ta, tb)
            if ta <= tb:
                la = max(0, int(math.ceil(ta)))
                lb = min(nx - 1, int(math.floor(tb)))
                if lb >= la:
                    total += lb - la + 1
    return total


@njit(nogil=True, cache=True, inline="always")
def _rounded(v: float) -> float:
    """Round half away from zero (scipy's conversion to an integer output)."""
    if v >= 0.0:
        return math.floor(v + 0.5)
    return -math.floor(0.5 - v)


# Conversion of a computed value to the output type: 0 float, 1 unsigned integer, 2 signed integer.
_KIND_FLOAT, _KIND_UNSIGNED, _KIND_SIGNED = 0, 1, 2


@njit(nogil=True, cache=True)
def _store_run(row, tmp, a, b, kind):
    """``row[a:b+1] = tmp[a:b+1]`` converted as scipy converts (round half away from zero for integers)."""
    if kind == 0:
        for t in range(a, b + 1):
            row[t] = tmp[t]
    elif kind == 1:
        for t in range(a, b + 1):
            row[t] = tmp[t] + 0.5  # values are >= 0: truncation is floor
    else:
        for t in range(a, b + 1):
            row[t] = _rounded(tmp[t])


@njit(nogil=True, cache=True)
def _nearest_block(flat, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2, base, dv, du, i0, j0, out, fill):
    """Order 0 into ``out`` (nk, ni, nj).

    The region holds scan voxels ``[o, o + r)`` per axis: voxel ``(a, b, c)`` of it is ``flat[a s0 + b s1 + c s2]``
    (element strides). The scan has shape ``(n0, n1, n2)``; ``base``/``dv``/``du`` (nk, 3) give each output
    slice's scan voxel coordinates; ``i0``/``j0`` are the block's first output row and column.
    """
    nk, ni, nj = out.shape
    us0, us1, us2 = np.uint64(s0), np.uint64(s1), np.uint64(s2)
    for k in range(nk):
        b0, b1, b2 = base[k, 0], base[k, 1], base[k, 2]
        v0, v1, v2 = dv[k, 0], dv[k, 1], dv[k, 2]
        u0, u1, u2 = du[k, 0], du[k, 1], du[k, 2]
        for ii in range(ni):
            fi = float(i0 + ii)
            fj = float(j0)
            p0 = b0 + fi * v0 + fj * u0
            p1 = b1 + fi * v1 + fj * u1
            p2 = b2 + fi * v2 + fj * u2
            la, lb, fa, fb = _runs(p0, p1, p2, u0, u1, u2, nj, o0, o1, o2, r0, r1, r2, n0, n1, n2, 0.0)
            row = out[k, ii]
            for t in range(0, la):
                row[t] = fill
            for t in range(max(lb + 1, 0), nj):
                row[t] = fill
            # the fast run: every axis in [o + eps, o + r - 1 - eps], so floor(c + 0.5) is a region voxel
            q0 = p0 - o0 + 0.5
            q1 = p1 - o1 + 0.5
            q2 = p2 - o2 + 0.5
            for t in range(fa, fb + 1):
                ft = float(t)
                a = np.uint64(q0 + ft * u0)
                b = np.uint64(q1 + ft * u1)
                c = np.uint64(q2 + ft * u2)
                row[t] = flat[a * us0 + b * us1 + c * us2]
            for t in range(la, lb + 1):
                if fa <= t <= fb:
                    continue
                ft = float(t)
                c0 = p0 + ft * u0
                c1 = p1 + ft * u1
                c2 = p2 + ft * u2
                if c0 < 0.0 or c0 > n0 - 1.0 or c1 < 0.0 or c1 > n1 - 1.0 or c2 < 0.0 or c2 > n2 - 1.0:
                    row[t] = fill
                else:
                    a = min(max(int(math.floor(c0 + 0.5)) - o0, 0), r0 - 1)
                    b = min(max(int(math.floor(c1 + 0.5)) - o1, 0), r1 - 1)
                    c = min(max(int(math.floor(c2 + 0.5)) - o2, 0), r2 - 1)
                    row[t] = flat[a * s0 + b * s1 + c * s2]


@njit(nogil=True, cache=True)
def _linear_checked(flat, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2, c0, c1, c2, fill):
    """Trilinear value at scan voxel coordinate (c0, c1, c2), scipy ``mode="constant"`` semantics."""
    if c0 < 0.0 or c0 > n0 - 1.0 or c1 < 0.0 or c1 > n1 - 1.0 or c2 < 0.0 or c2 > n2 - 1.0:
        return fill
    a = int(math.floor(c0))
    b = int(math.floor(c1))
    c = int(math.floor(c2))
    f0 = c0 - a
    f1 = c1 - b
    f2 = c2 - c
    # neighbours: the upper one is clamped to the scan (its weight is 0 there), both to the region (safety)
    a0 = min(max(a - o0, 0), r0 - 1) * s0
    a1 = min(max(min(a + 1, n0 - 1) - o0, 0), r0 - 1) * s0
    b0 = min(max(b - o1, 0), r1 - 1) * s1
    b1 = min(max(min(b + 1, n1 - 1) - o1, 0), r1 - 1) * s1
    d0 = min(max(c - o2, 0), r2 - 1) * s2
    d1 = min(max(min(c + 1, n2 - 1) - o2, 0), r2 - 1) * s2
    v000 = float(flat[a0 + b0 + d0])
    v001 = float(flat[a0 + b0 + d1])
    v010 = float(flat[a0 + b1 + d0])
    v011 = float(flat[a0 + b1 + d1])
    v100 = float(flat[a1 + b0 + d0])
    v101 = float(flat[a1 + b0 + d1])
    v110 = float(flat[a1 + b1 + d0])
    v111 = float(flat[a1 + b1 + d1])
    c00 = v000 + f2 * (v001 - v000)
    c01 = v010 + f2 * (v011 - v010)
    c10 = v100 + f2 * (v101 - v100)
    c11 = v110 + f2 * (v111 - v110)
    e0 = c00 + f1 * (c01 - c00)
    e1 = c10 + f1 * (c11 - c10)
    return e0 + f0 * (e1 - e0)


@njit(nogil=True, cache=True, inline="always", fastmath={"contract"})
def _cells(q0, q1, q2, u0, u1, u2, fa, n, us0, us1, us2, idx, fr):
    """For ``t < n``: the cell of region voxel ``q + (fa + t) u`` as a flat index ``idx[t]`` and its fractions
    ``fr[:, t]`` (the first of the three passes of :func:`_linear_run`; vectorises)."""
    for t in range(n):
        ft = float(t + fa)
        x0 = q0 + ft * u0
        x1 = q1 + ft * u1
        x2 = q2 + ft * u2
        a = math.floor(x0)
        b = math.floor(x1)
        c = math.floor(x2)
        fr[0, t] = x0 - a
        fr[1, t] = x1 - b
        fr[2, t] = x2 - c
        idx[t] = np.uint64(a) * us0 + np.uint64(b) * us1 + np.uint64(c) * us2


@njit(nogil=True, cache=True, inline="always", fastmath={"contract"})
def _gather_weigh(flat, off, us0, us1, us2, idx, fr, vals, row, fa, n):
    """``row[fa + t]`` = the trilinear value of cell ``idx[t] + off`` with fractions ``fr[:, t]``, t < n: the eight
    neighbours gathered (unsigned flat indices: no wraparound tests), then weighted; both loops vectorise."""
    for t in range(n):
        i000 = idx[t] + off
        i010 = i000 + us1
        i100 = i000 + us0
        i110 = i100 + us1
        vals[0, t] = flat[i000]
        vals[1, t] = flat[i000 + us2]
        vals[2, t] = flat[i010]
        vals[3, t] = flat[i010 + us2]
        vals[4, t] = flat[i100]
        vals[5, t] = flat[i100 + us2]
        vals[6, t] = flat[i110]
        vals[7, t] = flat[i110 + us2]
    for t in range(n):
        f0 = fr[0, t]
        f1 = fr[1, t]
        f2 = fr[2, t]
        v000 = float(vals[0, t])
        v001 = float(vals[1, t])
        v010 = float(vals[2, t])
        v011 = float(vals[3, t])
        v100 = float(vals[4, t])
        v101 = float(vals[5, t])
        v110 = float(vals[6, t])
        v111 = float(vals[7, t])
        c00 = v000 + f2 * (v001 - v000)
        c01 = v010 + f2 * (v011 - v010)
        c10 = v100 + f2 * (v101 - v100)
        c11 = v110 + f2 * (v111 - v110)
        e0 = c00 + f1 * (c01 - c00)
        e1 = c10 + f1 * (c11 - c10)
        row[t + fa] = e0 + f0 * (e1 - e0)


@njit(nogil=True, cache=True, fastmath={"contract"})
def _linear_run(flat, s0, s1, s2, q0, q1, q2, u0, u1, u2, fa, fb, tmp, idx, fr, vals):
    """The bounds-free run ``t = fa..fb`` of a line: ``tmp[t]`` = trilinear value at region voxel ``q + t u``.

    Three passes over small buffers so that the first and the last vectorise: cells and fractions; the eight
    neighbours (gathers, with unsigned flat indices: no wraparound tests); the weights.
    """
    n = fb + 1 - fa
    us0, us1, us2 = np.uint64(s0), np.uint64(s1), np.uint64(s2)
    _cells(q0, q1, q2, u0, u1, u2, fa, n, us0, us1, us2, idx, fr)
    _gather_weigh(flat, np.uint64(0), us0, us1, us2, idx, fr, vals, tmp, fa, n)


@njit(nogil=True, cache=True)
def _linear_line(flat, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2, p0, p1, p2, u0, u1, u2, line, tmp, idx, fr,
                 vals, fill, kind):
    """Order 1 along one line of the output: ``line[t]`` samples the scan at voxel ``p + t u``."""
    count = line.shape[0]
    la, lb, fa, fb = _runs(p0, p1, p2, u0, u1, u2, count, o0, o1, o2, r0, r1, r2, n0, n1, n2, 0.0)
    for t in range(0, la):
        line[t] = fill
    for t in range(max(lb + 1, 0), count):
        line[t] = fill
    # the fast run: floor(c) in [o, o + r - 2] on every axis, so no bounds tests
    if fb >= fa:
        _linear_run(flat, s0, s1, s2, p0 - o0, p1 - o1, p2 - o2, u0, u1, u2, fa, fb, tmp, idx, fr, vals)
    # checked samples before and after the fast run (near the scan's edges)
    fillf = float(fill)
    for t in range(la, lb + 1):
        if fa <= t <= fb:
            continue
        ft = float(t)
        tmp[t] = _linear_checked(flat, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2,
                                 p0 + ft * u0, p1 + ft * u1, p2 + ft * u2, fillf)
    _store_run(line, tmp, la, lb, kind)


@njit(nogil=True, cache=True)
def _linear_block(flat, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2, base, dv, du, i0, j0, out, fill, kind):
    """Order 1 into ``out`` (nk, ni, nj), row by row; see :func:`_nearest_block` for the arguments, ``kind`` in
    :func:`_store_run`."""
    nk, ni, nj = out.shape
    tmp = np.empty(nj, dtype=np.float64)
    idx = np.empty(nj, dtype=np.uint64)
    fr = np.empty((3, nj), dtype=np.float64)
    vals = np.empty((8, nj), dtype=flat.dtype)
    fj = float(j0)
    for k in range(nk):
        b0, b1, b2 = base[k, 0], base[k, 1], base[k, 2]
        v0, v1, v2 = dv[k, 0], dv[k, 1], dv[k, 2]
        u0, u1, u2 = du[k, 0], du[k, 1], du[k, 2]
        for ii in range(ni):
            fi = float(i0 + ii)
            _linear_line(flat, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2,
                         b0 + fi * v0 + fj * u0, b1 + fi * v1 + fj * u1, b2 + fi * v2 + fj * u2,
                         u0, u1, u2, out[k, ii], tmp, idx, fr, vals, fill, kind)


@njit(nogil=True, cache=True, fastmath={"contract"})
def _linear_run_channels(flat, sc, nc, s0, s1, s2, q0, q1, q2, u0, u1, u2, fa, fb, tmp, idx, fr, vals):
    """:func:`_linear_run` for ``nc`` channels ``sc`` elements apart in ``flat``: the cells and fractions are
    computed once, then gathered and weighted per channel into ``tmp[ch]``."""
    n = fb + 1 - fa
    us0, us1, us2 = np.uint64(s0), np.uint64(s1), np.uint64(s2)
    _cells(q0, q1, q2, u0, u1, u2, fa, n, us0, us1, us2, idx, fr)
    for ch in range(nc):
        _gather_weigh(flat, np.uint64(ch * sc), us0, us1, us2, idx, fr, vals, tmp[ch], fa, n)


@njit(nogil=True, cache=True)
def _linear_block_channels(flat, sc, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2, base, dv, du, i0, j0, out,
                           fill, kind):
    """Order 1 into ``out`` (nc, nk, ni, nj) from ``nc`` channels of one region (channel ``ch`` starts at element
    ``ch * sc`` of ``flat``); each line's runs, cells and fractions are computed once for every channel."""
    nc, nk, ni, nj = out.shape
    tmp = np.empty((nc, nj), dtype=np.float64)
    idx = np.empty(nj, dtype=np.uint64)
    fr = np.empty((3, nj), dtype=np.float64)
    vals = np.empty((8, nj), dtype=flat.dtype)
    fj = float(j0)
    fillf = float(fill)
    for k in range(nk):
        b0, b1, b2 = base[k, 0], base[k, 1], base[k, 2]
        v0, v1, v2 = dv[k, 0], dv[k, 1], dv[k, 2]
        u0, u1, u2 = du[k, 0], du[k, 1], du[k, 2]
        for ii in range(ni):
            fi = float(i0 + ii)
            p0 = b0 + fi * v0 + fj * u0
            p1 = b1 + fi * v1 + fj * u1
            p2 = b2 + fi * v2 + fj * u2
            la, lb, fa, fb = _runs(p0, p1, p2, u0, u1, u2, nj, o0, o1, o2, r0, r1, r2, n0, n1, n2, 0.0)
            for ch in range(nc):
                line = out[ch, k, ii]
                for t in range(0, la):
                    line[t] = fill
                for t in range(max(lb + 1, 0), nj):
                    line[t] = fill
            if fb >= fa:
                _linear_run_channels(flat, sc, nc, s0, s1, s2, p0 - o0, p1 - o1, p2 - o2, u0, u1, u2, fa, fb, tmp,
                                     idx, fr, vals)
            for ch in range(nc):
                part = flat[ch * sc:]
                for t in range(la, lb + 1):
                    if fa <= t <= fb:
                        continue
                    ft = float(t)
                    tmp[ch, t] = _linear_checked(part, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2,
                                                 p0 + ft * u0, p1 + ft * u1, p2 + ft * u2, fillf)
                _store_run(out[ch, k, ii], tmp[ch], la, lb, kind)


def _flat_view(region: np.ndarray) -> tuple[np.ndarray, int, int, int]:
    """A 1D view of ``region``'s memory and its element strides (a C-contiguous copy when that is impossible)."""
    region = np.asarray(region)
    item = region.dtype.itemsize
    st = region.strides
    if region.size == 0 or any(s < 0 or s % item for s in st):
        region = np.ascontiguousarray(region)
        st = region.strides
    if region.flags.c_contiguous:
        return region.reshape(-1), *(int(s // item) for s in st)
    span = 1 + sum((n - 1) * (s // item) for n, s in zip(region.shape, st, strict=True))
    flat = np.lib.stride_tricks.as_strided(region, shape=(span,), strides=(item,), writeable=False)
    return flat, *(int(s // item) for s in st)


def _cubic_block(region: np.ndarray, offset: np.ndarray, base: np.ndarray, dv: np.ndarray, du: np.ndarray,
                 i0: int, j0: int, out: np.ndarray, fill: Any) -> None:
    """Order 3: prefilter the region once, then scipy's map_coordinates one output slice at a time."""
    filtered = ndimage.spline_filter(np.asarray(region), 3, output=np.float64, mode="constant")
    nk, ni, nj = out.shape
    ii = np.arange(i0, i0 + ni, dtype=np.float64)[:, None]
    jj = np.arange(j0, j0 + nj, dtype=np.float64)[None, :]
    coords = np.empty((3, ni, nj))
    for k in range(nk):
        for a in range(3):
            np.add(base[k, a] - offset[a] + ii * dv[k, a], jj * du[k, a], out=coords[a])
        ndimage.map_coordinates(filtered, coords, output=out[k], order=3, mode="constant", cval=float(fill),
                                prefilter=False)


def _warp_block(region: np.ndarray, offset: tuple[int, int, int], scan_shape: tuple[int, int, int],
                base: np.ndarray, dv: np.ndarray, du: np.ndarray, i0: int, j0: int,
                block_shape: tuple[int, int, int], order: int, fill: Any, dtype: str) -> np.ndarray:
    """Resample one output block from ``region`` (the scan's voxels from ``offset`` on).

    ``base``/``dv``/``du`` are the slice geometry of the block's slices in scan voxel coordinates; ``i0``, ``j0``
    the block's first row and column in the output.
    """
    dt = np.dtype(dtype)
    out = np.empty(block_shape, dtype=dt)
    region = np.asarray(region)
    o0, o1, o2 = (int(v) for v in offset)
    n0, n1, n2 = (int(v) for v in scan_shape)
    r0, r1, r2 = region.shape
    fill = dt.type(fill)
    base = np.ascontiguousarray(base, dtype=np.float64)
    dv = np.ascontiguousarray(dv, dtype=np.float64)
    du = np.ascontiguousarray(du, dtype=np.float64)
    if order == 3:
        _cubic_block(region, np.array([o0, o1, o2], dtype=np.float64), base, dv, du, int(i0), int(j0), out, fill)
        return out
    flat, s0, s1, s2 = _flat_view(region)
    if order == 0:
        _nearest_block(flat, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2, base, dv, du, int(i0), int(j0), out,
                       fill)
    else:
        kind = (_KIND_FLOAT if not np.issubdtype(dt, np.integer)
                else _KIND_SIGNED if np.issubdtype(dt, np.signedinteger) else _KIND_UNSIGNED)
        _linear_block(flat, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2, base, dv, du, int(i0), int(j0), out,
                      fill, kind)
    return out


def _warp_block_channels(region: np.ndarray, offset: tuple[int, int, int], scan_shape: tuple[int, int, int],
                         base: np.ndarray, dv: np.ndarray, du: np.ndarray, i0: int, j0: int,
                         block_shape: tuple[int, int, int], order: int, fill: Any, dtype: str) -> np.ndarray:
    """:func:`_warp_block` for every channel of ``region`` (nc, r0, r1, r2): an (nc, nk, ni, nj) block. Order 1
    computes each sample's cell and weights once for all channels; orders 0 and 3 resample channel by channel."""
    nc = region.shape[0]
    if order != 1:
        out = np.empty((nc, *block_shape), dtype=np.dtype(dtype))
        for ch in range(nc):
            out[ch] = _warp_block(region[ch], offset, scan_shape, base, dv, du, i0, j0, block_shape, order, fill,
                                  dtype)
        return out
    dt = np.dtype(dtype)
    out = np.empty((nc, *block_shape), dtype=dt)
    o0, o1, o2 = (int(v) for v in offset)
    n0, n1, n2 = (int(v) for v in scan_shape)
    _, r0, r1, r2 = region.shape
    flat, sc, s0, s1, s2 = _flat_view(region)
    kind = (_KIND_FLOAT if not np.issubdtype(dt, np.integer)
            else _KIND_SIGNED if np.issubdtype(dt, np.signedinteger) else _KIND_UNSIGNED)
    _linear_block_channels(flat, sc, s0, s1, s2, r0, r1, r2, o0, o1, o2, n0, n1, n2,
                           np.ascontiguousarray(base, dtype=np.float64), np.ascontiguousarray(dv, dtype=np.float64),
                           np.ascontiguousarray(du, dtype=np.float64), int(i0), int(j0), out, dt.type(fill), kind)
    return out


def _fill_block(block_shape: tuple[int, int, int], fill: Any, dtype: str) -> np.ndarray:
    return np.full(block_shape, fill, dtype=np.dtype(dtype))


# ------------------------------------------------------------------------------------------------------------------
# the graph
# ------------------------------------------------------------------------------------------------------------------
def _margins(order: int) -> tuple[int, int]:
    """Voxels to read below floor(min c) and above floor(max c) (one more than strictly needed, for safety)."""
    if order == 0:
        return 1, 2
    if order == 1:
        return 1, 3
    return 2 + ORDER3_FILTER_MARGIN, 4 + ORDER3_FILTER_MARGIN


def _block_boxes(base: np.ndarray, dv: np.ndarray, du: np.ndarray, ks: tuple[int, int], is_: tuple[int, int],
                 js: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Exact min and max (3,) of the scan coordinates of the output block (corners of every slice)."""
    k0, k1 = ks
    ii = np.array([is_[0], is_[1] - 1], dtype=float)
    jj = np.array([js[0], js[1] - 1], dtype=float)
    pts = (base[k0:k1, None, None, :] + ii[None, :, None, None] * dv[k0:k1, None, None, :]
           + jj[None, None, :, None] * du[k0:k1, None, None, :])
    pts = pts.reshape(-1, 3)
    return pts.min(axis=0), pts.max(axis=0)


def _chunk_edges(data: da.Array) -> list[np.ndarray]:
    return [np.concatenate([[0], np.cumsum(c)]).astype(np.int64) for c in data.chunks]


def _region_refs(data: da.Array, edges: list[np.ndarray], lo: np.ndarray, hi: np.ndarray
                 ) -> tuple[list, tuple[tuple[int, ...], ...]]:
    """The keys of ``data``'s chunks that hold the box ``[lo, hi)`` (nested lists) and their boundaries.

    Tasks depend on whole input chunks rather than on slices of them, so each input chunk is read (and
    decompressed) once per computation however many output blocks need it.
    """
    ranges = []
    for ax in range(3):
        c0 = int(np.searchsorted(edges[ax], lo[ax], side="right")) - 1
        c1 = int(np.searchsorted(edges[ax], hi[ax], side="left"))
        ranges.append((c0, c1))
    # the keys of a dask array are (name, i, j, k): made directly, never by listing all the input's keys
    name = data.name
    refs = [[[(name, a, b, c) for c in range(*ranges[2])] for b in range(*ranges[1])] for a in range(*ranges[0])]
    bounds = tuple(tuple(int(v) for v in edges[ax][r0:r1 + 1]) for ax, (r0, r1) in enumerate(ranges))
    return refs, bounds


def _one_chunk(bounds: tuple[tuple[int, ...], ...]) -> bool:
    return len(bounds[0]) == 2 and len(bounds[1]) == 2 and len(bounds[2]) == 2


def _assemble(blocks: list, bounds: tuple[tuple[int, ...], ...], lo: tuple[int, int, int],
              hi: tuple[int, int, int], out: np.ndarray | None = None) -> np.ndarray:
    """The box ``[lo, hi)`` of the scan from the chunks that hold it (a view when one chunk holds it all and no
    ``out`` is given; else copied into ``out``, or a new array)."""
    if out is None and _one_chunk(bounds):
        chunk = np.asarray(blocks[0][0][0])
        return chunk[tuple(slice(lo[ax] - bounds[ax][0], hi[ax] - bounds[ax][0]) for ax in range(3))]
    if out is None:
        first = np.asarray(blocks[0][0][0])
        out = np.empty(tuple(h - low for low, h in zip(lo, hi, strict=True)), dtype=first.dtype)
    for a, plane in enumerate(blocks):
        for b, row in enumerate(plane):
            for c, chunk in enumerate(row):
                idx = (a, b, c)
                src, dst = [], []
                for ax in range(3):
                    c_lo, c_hi = bounds[ax][idx[ax]], bounds[ax][idx[ax] + 1]
                    x0, x1 = max(c_lo, lo[ax]), min(c_hi, hi[ax])
                    src.append(slice(x0 - c_lo, x1 - c_lo))
                    dst.append(slice(x0 - lo[ax], x1 - lo[ax]))
                out[tuple(dst)] = np.asarray(chunk)[tuple(src)]
    return out


def _warp_chunks(blocks: list, bounds: tuple, lo: tuple[int, int, int], hi: tuple[int, int, int],
                 *args: Any) -> np.ndarray:
    """Task: assemble the region from its input chunks, then :func:`_warp_block`."""
    return _warp_block(_assemble(blocks, bounds, lo, hi), lo, *args)


def _warp_chunks_channels(blocks: list, bounds: list, lo: tuple[int, int, int], hi: tuple[int, int, int],
                          *args: Any) -> np.ndarray:
    """Task: every channel of one output block.

    When one input chunk of every channel holds the region, each channel is resampled from a view of its chunk
    (copying the regions into one array costs more than sharing each sample's cell and weights saves); otherwise
    the regions are assembled straight into one (nc, ...) array for :func:`_warp_block_channels`.
    """
    if all(_one_chunk(b) for b in bounds):
        regions = [_assemble(blk, b, lo, hi) for blk, b in zip(blocks, bounds, strict=True)]
        first = _warp_block(regions[0], lo, *args)
        out = np.empty((len(regions), *first.shape), dtype=first.dtype)
        out[0] = first
        for ch in range(1, len(regions)):
            out[ch] = _warp_block(regions[ch], lo, *args)
        return out
    dtype = np.asarray(blocks[0][0][0][0]).dtype
    region = np.empty((len(blocks), *(h - low for low, h in zip(lo, hi, strict=True))), dtype=dtype)
    for ch in range(len(blocks)):
        _assemble(blocks[ch], bounds[ch], lo, hi, out=region[ch])
    return _warp_block_channels(region, lo, *args)


def _fill_channels(nc: int, block_shape: tuple[int, int, int], fill: Any, dtype: str) -> np.ndarray:
    return np.full((nc, *block_shape), fill, dtype=np.dtype(dtype))


def _output_array(name: str, layer: dict, data: da.Array, chunks: tuple, dtype: np.dtype) -> da.Array:
    graph = HighLevelGraph.from_collections(name, layer, dependencies=[data])
    return da.Array(graph, name, chunks=chunks, dtype=dtype, meta=np.empty((0, 0, 0), dtype=dtype))


def _check_padding(deformation: Deformation, padded: Deformation, pad: int, ds: float,
                   scan_shape: Sequence[int]) -> None:
    """Refuse padding that runs absurdly far beyond the scan.

    Past ``R`` = (the farthest scan corner from the curve's end) + (the cage's reach), every padded slice provably
    samples outside the scan (the padding is straight, along the end normal). A few such slices are harmless, so
    only padding longer than ``R`` plus the scan's diagonal is refused: it would add that many slices of pure
    fill (a session's pad of 1e7, or ``pad=100000000``).
    """
    sp = np.asarray(padded.spacing)
    corners = (np.array(np.meshgrid(*[[0, int(n) - 1] for n in scan_shape], indexing="ij")).reshape(3, -1).T
               * sp + np.asarray(padded.origin))
    diagonal = float(np.linalg.norm((np.asarray(scan_shape) - 1) * sp))
    reach = float(np.hypot(*padded.max_half_extent))
    unit = unit_label(padded.unit)
    for end, name, centre in ((0, "head", padded.positions[0]), (1, "tail", padded.positions[-1])):
        useful = float(np.linalg.norm(corners - centre, axis=1).max()) + reach
        if padded.pad[end] > useful + diagonal:
            raise InvalidInputError(
                f"the padding at the {name} ({padded.pad[end]:.6g} {unit}: pad={pad} slices of {ds:g} plus the "
                f"deformation's own {deformation.pad[end]:.6g}) is absurd: past {useful:.6g} {unit} from the curve's "
                f"end every padded slice samples outside the scan (its diagonal is {diagonal:.6g} {unit}); use a "
                "padding of at most a few slices beyond the scan"
            )


def _check_coverage(deformation: Deformation, ds: float, scan_shape: Sequence[int], what: str
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refuse a straight grid with no sample inside the scan; warn when most of it is outside.

    Computed from the slice geometry (each output slice is an affine image of the scan), not from the output;
    returns that geometry ``(base, dv, du)`` in scan voxels for the graph.
    """
    _, ny, nx = deformation.output_shape(ds)
    base, dv, du = deformation.slice_geometry(ds, voxels=True)
    n0, n1, n2 = (int(n) for n in scan_shape)
    inside = _samples_inside(base, dv, du, ny, nx, n0, n1, n2)
    total = len(base) * ny * nx
    if inside == 0:
        corners = np.concatenate([base, base + (ny - 1) * dv, base + (nx - 1) * du,
                                  base + (ny - 1) * dv + (nx - 1) * du])
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        box = ", ".join(f"{a:.6g}..{b:.6g}" for a, b in zip(lo, hi, strict=True))
        raise InvalidInputError(
            f"the {what} lies entirely outside the scan: its samples span scan voxels {box} (axis0, axis1, axis2) "
            f"but the scan spans 0..{n0 - 1}, 0..{n1 - 1}, 0..{n2 - 1}; the deformation belongs to another scan "
            "(or its spacing, origin or unit are wrong)"
        )
    outside = 1.0 - inside / total
    if outside > OUTSIDE_WARN_FRACTION:
        warnings.warn(
            f"{100 * outside:.1f} % of the {what}'s voxels sample outside the scan and get the fill value; check "
            "that the deformation belongs to this scan, or shrink its cage or padding",
            OutsideWarning,
            stacklevel=3,
        )
    return base, dv, du


def _straighten_array(data: da.Array, deformation: Deformation, ds: float, order: int, chunks: Any,
                      fill: Any, geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> da.Array:
    """The lazy straight array of ``data`` (any dask array on the deformation's scan grid).

    ``geometry``: the deformation's ``slice_geometry(ds, voxels=True)`` when the caller has it already.
    """
    dtype = np.dtype(data.dtype)
    fill = _check_fill(fill, dtype)
    shape = deformation.output_shape(ds)
    base, dv, du = deformation.slice_geometry(ds, voxels=True) if geometry is None else geometry
    out_chunks = _normalise_out_chunks(chunks, shape)
    scan_shape = tuple(int(n) for n in data.shape)
    scan_hi = np.asarray(scan_shape)
    lo_m, hi_m = _margins(order)
    edges = _chunk_edges(data)
    # the slice geometry, the scan's shape and the options determine every output voxel: a cheap, exact token
    name = "straighten-" + dask.base.tokenize(data.name, base, dv, du, scan_shape, order, fill, dtype.str, out_chunks)
    starts = [np.concatenate([[0], np.cumsum(c)[:-1]]).astype(int) for c in out_chunks]
    layer: dict = {}
    for a, (k0, nk) in enumerate(zip(starts[0], out_chunks[0], strict=True)):
        for b, (i0, ni) in enumerate(zip(starts[1], out_chunks[1], strict=True)):
            for c, (j0, nj) in enumerate(zip(starts[2], out_chunks[2], strict=True)):
                bshape = (int(nk), int(ni), int(nj))
                cmin, cmax = _block_boxes(base, dv, du, (k0, k0 + nk), (i0, i0 + ni), (j0, j0 + nj))
                if np.any(cmax < -_EDGE_EPS) or np.any(cmin > scan_hi - 1 + _EDGE_EPS):
                    layer[(name, a, b, c)] = (_fill_block, bshape, fill, dtype.str)  # misses the scan: no read
                    continue
                lo = np.clip(np.floor(cmin).astype(int) - lo_m, 0, scan_hi)
                hi = np.clip(np.floor(cmax).astype(int) + hi_m, 0, scan_hi)
                refs, bounds = _region_refs(data, edges, lo, hi)
                layer[(name, a, b, c)] = (
                    _warp_chunks, refs, bounds, tuple(int(v) for v in lo), tuple(int(v) for v in hi), scan_shape,
                    base[k0:k0 + nk].copy(), dv[k0:k0 + nk].copy(), du[k0:k0 + nk].copy(), int(i0), int(j0),
                    bshape, order, fill, dtype.str,
                )
    return _output_array(name, layer, data, out_chunks, dtype)


def _straighten_channels_array(datas: list[da.Array], deformation: Deformation, ds: float, order: int, chunks: Any,
                               fill: Any, geometry: tuple[np.ndarray, np.ndarray, np.ndarray]) -> da.Array:
    """The lazy (nc, Ns, Ny, Nx) straight array of channels ``datas`` (dask arrays of one shape and dtype on the
    deformation's scan grid): one task per output block resamples every channel from one region."""
    dtype = np.dtype(datas[0].dtype)
    fill = _check_fill(fill, dtype)
    nc = len(datas)
    shape = deformation.output_shape(ds)
    base, dv, du = geometry
    out_chunks = _normalise_out_chunks(chunks, shape)
    scan_shape = tuple(int(n) for n in datas[0].shape)
    scan_hi = np.asarray(scan_shape)
    lo_m, hi_m = _margins(order)
    edges = [_chunk_edges(d) for d in datas]
    name = "straighten-channels-" + dask.base.tokenize([d.name for d in datas], base, dv, du, scan_shape, order, fill,
                                                       dtype.str, out_chunks)
    starts = [np.concatenate([[0], np.cumsum(c)[:-1]]).astype(int) for c in out_chunks]
    layer: dict = {}
    for a, (k0, nk) in enumerate(zip(starts[0], out_chunks[0], strict=True)):
        for b, (i0, ni) in enumerate(zip(starts[1], out_chunks[1], strict=True)):
            for c, (j0, nj) in enumerate(zip(starts[2], out_chunks[2], strict=True)):
                bshape = (int(nk), int(ni), int(nj))
                cmin, cmax = _block_boxes(base, dv, du, (k0, k0 + nk), (i0, i0 + ni), (j0, j0 + nj))
                if np.any(cmax < -_EDGE_EPS) or np.any(cmin > scan_hi - 1 + _EDGE_EPS):
                    layer[(name, 0, a, b, c)] = (_fill_channels, nc, bshape, fill, dtype.str)
                    continue
                lo = np.clip(np.floor(cmin).astype(int) - lo_m, 0, scan_hi)
                hi = np.clip(np.floor(cmax).astype(int) + hi_m, 0, scan_hi)
                refs, bounds = zip(*[_region_refs(d, e, lo, hi) for d, e in zip(datas, edges, strict=True)],
                                   strict=True)
                layer[(name, 0, a, b, c)] = (
                    _warp_chunks_channels, list(refs), list(bounds), tuple(int(v) for v in lo),
                    tuple(int(v) for v in hi), scan_shape, base[k0:k0 + nk].copy(), dv[k0:k0 + nk].copy(),
                    du[k0:k0 + nk].copy(), int(i0), int(j0), bshape, order, fill, dtype.str,
                )
    graph = HighLevelGraph.from_collections(name, layer, dependencies=list(datas))
    return da.Array(graph, name, chunks=((nc,), *out_chunks), dtype=dtype, meta=np.empty((0, 0, 0, 0), dtype=dtype))


# ------------------------------------------------------------------------------------------------------------------
# straighten
# ------------------------------------------------------------------------------------------------------------------
def straighten(
    volume: Any,
    deformation: Deformation,
    *,
    order: int = 1,
    spacing: float | None = None,
    pad: int = 0,
    chunks: Any = None,
    fill: float = 0,
    max_output: float | None = DEFAULT_MAX_OUTPUT,
) -> Volume:
    """Resample a bent scan into the straight box of a deformation, lazily and chunk by chunk.

    Parameters
    ----------
    volume : Volume, path or array-like, shape (N0, N1, N2)
        The bent scan. A :class:`~napari_unwind.io.Volume` must have the deformation's spacing and origin
        (relative 1e-6); when both name a length unit, the volume's geometry is converted to the deformation's
        unit first (a scan in mm matches a deformation in micrometres of the same grid), and the result is in the
        deformation's unit; different numbers are refused with both units named. A path (str or path-like) is
        opened with :func:`~napari_unwind.io.open_volume`. A bare array is taken to be on the deformation's grid;
        a nested list of whole numbers becomes int32 (numpy's int64 is not a voxel type a Volume holds).
    deformation : Deformation
        The map from the straight box into the scan.
    order : {0, 1, 3}
        Interpolation order: 0 nearest (labels), 1 trilinear (default), 3 cubic B-spline.
    spacing : float, optional
        Isotropic output spacing ``ds`` (physical units); default the finest scan spacing.
    pad : int
        Extra output slices at each end, beyond the deformation's own padding (extended along the end normals).
    chunks : int or tuple, optional
        Output chunks (dask notation); default ``(64, Ny, Nx)``: whole cross-sections, split into near-equal
        tiles along a side longer than 256 (which bounds the input region each task reads).
    fill : float
        Value of output voxels that sample outside the scan; must fit the voxel type.
    max_output : float or None
        Largest output accepted, in bytes (default :data:`DEFAULT_MAX_OUTPUT`, 256 GiB; None: no limit). The size
        is checked before anything proportional to the output is built.

    Returns
    -------
    Volume
        ``data`` is a lazy dask array of shape ``deformation.output_shape(ds)`` (padding included), axis0 = s,
        axis1 = y, axis2 = x, dtype of the input; ``spacing`` ``(ds, ds, ds)``; ``origin`` the straight
        coordinates ``(s, y, x)`` of voxel (0, 0, 0); ``metadata`` holds ``"deformation"`` (the padded
        deformation that defines the output grid, as a dict), ``"order"``, ``"output_spacing"``, ``"pad"``,
        ``"fill"`` and ``"source"``.

    Raises
    ------
    InvalidInputError
        For malformed options; for an output larger than ``max_output`` (the message gives its shape, voxels and
        bytes); when no output voxel samples the scan (the message gives both boxes).

    Warns
    -----
    FoldWarning
        When the deformation folds (``deformation.folds()`` is not empty).
    OutsideWarning
        When more than half of the output's voxels sample outside the scan (computed from the slice geometry).

    Notes
    -----
    Equals ``scipy.ndimage.map_coordinates(volume, coords, order=order, mode="constant", cval=fill)`` with
    ``coords`` the scan voxel coordinates of the output grid (see the module docstring for the tolerances).
    """
    order = _check_order(order)
    pad = _check_pad(pad)
    max_output = _check_max_output(max_output)
    data, unit, source = _input_array(volume, deformation)
    ds = deformation._ds(spacing)
    d2 = _padded(deformation, pad, ds)
    _check_output_size("straight volume", d2.output_shape(ds), data.dtype, max_output,
                       f"check the output spacing ({ds:g}) and the padding (pad {pad} slices; the deformation's own "
                       f"{deformation.pad[0]:g} / {deformation.pad[1]:g} {unit_label(deformation.unit)})")
    _check_padding(deformation, d2, pad, ds, data.shape)
    _warn_folds(deformation, "straight volume")
    geometry = _check_coverage(d2, ds, data.shape, "straight volume")
    out = _straighten_array(data, d2, ds, order, chunks, fill, geometry)
    i0, j0 = d2.grid_centre(ds)
    origin = (d2.s_range[0], -i0 * ds, -j0 * ds)
    meta = {
        "deformation": d2.to_dict(),
        "order": order,
        "output_spacing": ds,
        "pad": pad,
        "fill": float(fill),
        "source": source,
    }
    return Volume(out, spacing=(ds, ds, ds), unit=unit, origin=origin, source=source, format=None,
                  metadata=meta)


def straighten_channels(
    volumes: Sequence[Any],
    deformation: Deformation,
    *,
    order: int = 1,
    spacing: float | None = None,
    pad: int = 0,
    chunks: Any = None,
    fill: float = 0,
    max_output: float | None = DEFAULT_MAX_OUTPUT,
) -> list[Volume]:
    """Straighten several channels of one scan grid with one deformation, in one pass over the output's blocks.

    Parameters
    ----------
    volumes : sequence of Volume, path or array-like, each shape (N0, N1, N2)
        The channels (:func:`napari_unwind.io.open_channels` opens them), each as for :func:`straighten`; they
        must share a shape (a :class:`~napari_unwind.io.Volume` also its geometry, checked against the
        deformation's). Channels of different voxel types are resampled in their common type (numpy's
        ``result_type``: uint8 and uint16 give uint16).
    deformation, order, spacing, pad, chunks, fill, max_output
        As for :func:`straighten`; ``max_output`` bounds the channels' output together.

    Returns
    -------
    list of Volume
        One per channel, as :func:`straighten` returns it (``metadata["channel"]`` keeps the input's name). Their
        ``data`` are slices of one lazy (nc, Ns, Ny, Nx) array: each output block is one task that reads the
        region it needs from every channel and resamples them together (order 1 computes each sample's cell and
        weights once for every channel), so computing the channels together, as
        :func:`napari_unwind.io.write_channels_iter` does, costs one pass.

    Raises
    ------
    InvalidInputError
        No channels; channels of different shapes or voxel types; as :func:`straighten`.
    """
    vols = list(volumes)
    if not vols:
        raise InvalidInputError("straighten_channels needs at least one channel, got none")
    order = _check_order(order)
    pad = _check_pad(pad)
    max_output = _check_max_output(max_output)
    inputs = [_input_array(v, deformation) for v in vols]
    datas = [x[0] for x in inputs]
    for k, d in enumerate(datas[1:], start=1):
        if tuple(d.shape) != tuple(datas[0].shape):
            raise InvalidInputError(f"channel {k} has shape {tuple(d.shape)} but channel 0 has "
                                    f"{tuple(datas[0].shape)}: channels must share one scan grid")
    common = np.result_type(*[d.dtype for d in datas])  # one block holds every channel: their common type
    if common not in SUPPORTED_DTYPES:
        raise InvalidInputError(f"channels of types {sorted({str(d.dtype) for d in datas})} have no common voxel type "
                                "napari-unwind writes; convert them to one type first (unwind convert)")
    datas = [d if d.dtype == common else d.astype(common) for d in datas]
    unit = inputs[0][1]
    ds = deformation._ds(spacing)
    d2 = _padded(deformation, pad, ds)
    out_shape = d2.output_shape(ds)
    _check_output_size(f"straight volume of {len(vols)} channels", (len(vols), *out_shape), datas[0].dtype,
                       max_output, f"check the output spacing ({ds:g}) and the padding (pad {pad} slices)")
    _check_padding(deformation, d2, pad, ds, datas[0].shape)
    _warn_folds(deformation, "straight volume")
    geometry = _check_coverage(d2, ds, datas[0].shape, "straight volume")
    stack = _straighten_channels_array(datas, d2, ds, order, chunks, fill, geometry)
    i0, j0 = d2.grid_centre(ds)
    origin = (d2.s_range[0], -i0 * ds, -j0 * ds)
    out = []
    for k, (v, (_, _, source)) in enumerate(zip(vols, inputs, strict=True)):
        name = (v.metadata.get("channel") if isinstance(v, Volume) else None) or f"c{k}"
        meta = {"deformation": d2.to_dict(), "order": order, "output_spacing": ds, "pad": pad, "fill": float(fill),
                "source": source, "channel": name}
        out.append(Volume(stack[k], spacing=(ds, ds, ds), unit=unit, origin=origin, source=source, format=None,
                          metadata=meta))
    return out


# ------------------------------------------------------------------------------------------------------------------
# export
# ------------------------------------------------------------------------------------------------------------------
def _session_dict(session: Any) -> dict | None:
    if session is None:
        return None
    if isinstance(session, dict):
        return session
    if hasattr(session, "to_dict"):
        return session.to_dict()
    raise InvalidInputError(f"session must be a dict or have a to_dict() method, got {type(session).__name__}")


def _check_disk(path: str | os.PathLike, straight: Volume, fmt: str, write_options: dict[str, Any]) -> None:
    """Compare the output's uncompressed size with the free space of the target's folder, before writing.

    Refused (OutputError) for an uncompressed format that cannot fit; a :class:`DiskSpaceWarning` for a
    compressed one, which may.
    """
    folder = Path(path).expanduser().absolute().parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent  # a folder the writer will create: the space is that of its nearest ancestor
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return  # nothing to compare with; a full disk is still reported when writing
    nbytes = straight.nbytes
    if nbytes <= free:
        return
    what = (f"{path} needs {nbytes:,} bytes ({_size(nbytes)}) for a straight volume of shape {straight.shape} "
            f"({straight.dtype}, uncompressed) but {folder} has only {free:,} bytes free ({_size(free)})")
    from .io._formats import compresses

    if compresses(fmt, path, write_options):
        warnings.warn(f"{what}; {fmt} is compressed and may fit, but the export may stop with a full disk",
                      DiskSpaceWarning, stacklevel=4)
        return
    raise OutputError(f"{what}; free some space, write to another disk, or choose a compressed format "
                      "(OME-Zarr, .nii.gz, gzip NRRD)")


def _straight_map(straight: Volume, d: Deformation, ds: float) -> dict[str, np.ndarray]:
    """The map arrays stored beside an OME-Zarr export.

    ``slices`` (Ns, 3, 3): per slice ``(base, dv, du)`` in scan voxel coordinates (exact);
    ``coordinates`` (Ns, 2, 2, 3): the scan's physical position of the four corner voxels of each slice, an
    NGFF "coordinates" field that bilinear interpolation over each slice reproduces exactly.
    """
    base, dv, du = d.slice_geometry(ds, voxels=True)
    slices = np.stack([base, dv, du], axis=1)
    pb, pv, pu = d.slice_geometry(ds, voxels=False)
    _, ny, nx = straight.shape
    corners = np.empty((len(pb), 2, 2, 3))
    for a, i in enumerate((0, ny - 1)):
        for b, j in enumerate((0, nx - 1)):
            corners[:, a, b] = pb + i * pv + j * pu
    return {"slices": slices, "coordinates": corners}


def _map_attributes(straight: Volume, d: Deformation, ds: float) -> dict[str, Any]:
    """NGFF 0.6-style coordinate systems and the transformation from the straight image into the scan."""
    _, ny, nx = straight.shape
    unit = straight.unit
    ax = lambda names: [{"name": n, "type": "space", **({"unit": unit} if unit else {})} for n in names]  # noqa: E731
    return {
        "coordinateSystems": [
            {"name": "straight", "axes": ax(["s", "y", "x"])},
            {"name": "scan", "axes": ax(["z", "y", "x"])},
        ],
        "coordinateTransformations": [
            {
                "type": "coordinates",
                "path": "map/coordinates",
                "input": "straight",
                "output": "scan",
                "interpolation": "linear",
                "description": "scan position of the 4 corner voxels of every straight slice; each slice is "
                               "an affine plane, so linear interpolation is exact",
            },
        ],
        "map": {
            "slices": "map/slices",
            "slices_description": "(Ns, 3, 3) float64: per straight slice k, rows base, dv, du in scan voxel "
                                  "coordinates; straight voxel (k, i, j) samples scan voxel base + i dv + j du",
            "coordinates": "map/coordinates",
            "coordinates_grid": {
                "scale": [ds, (ny - 1) * ds, (nx - 1) * ds],
                "translation": list(straight.origin),
            },
            "scan_spacing": list(d.spacing),
            "scan_origin": list(d.origin),
        },
    }


def _write_map_arrays(path: Path, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> None:
    import zarr

    root = zarr.open_group(store=str(path), mode="r+")
    grp = root.require_group("map")
    for name, arr in arrays.items():
        z = grp.create_array(name, shape=arr.shape, dtype=arr.dtype, chunks=arr.shape, compressors=None,
                             fill_value=0, overwrite=True)
        z[...] = arr
    grp.attrs["unwind"] = attrs


def export_iter(
    volume: Any,
    deformation: Deformation,
    path: str | os.PathLike,
    *,
    order: int = 1,
    spacing: float | None = None,
    pad: int = 0,
    chunks: Any = None,
    fill: float = 0,
    overwrite: bool = False,
    session: Any = None,
    scheduler: str | None = None,
    max_output: float | None = DEFAULT_MAX_OUTPUT,
    **write_options: Any,
) -> Iterator[Progress]:
    """Generator form of :func:`export`: yields :class:`~napari_unwind.progress.Progress`, returns the path."""
    fmt = output_format(path, write_options.get("format"))
    straight = straighten(volume, deformation, order=order, spacing=spacing, pad=pad, chunks=chunks, fill=fill,
                          max_output=max_output)
    _check_disk(path, straight, fmt, write_options)
    return (yield from _write_straight([straight], path, fmt, order=order, pad=pad, fill=fill, overwrite=overwrite,
                                       session=session, scheduler=scheduler, write_options=write_options))


def _write_straight(straight: list[Volume], path: str | os.PathLike, fmt: str, *, order: int, pad: int, fill: float,
                    overwrite: bool, session: Any, scheduler: str | None,
                    write_options: dict[str, Any]) -> Iterator[Progress]:
    """Write straight volumes of one deformation (one, or the channels of :func:`straighten_channels`) in ``fmt``:
    OME-Zarr with the straightening record and the map arrays beside the image, in one atomic folder; any other
    format as its writer writes it. Returns the path."""
    from .io.channels import write_channels_iter

    first = straight[0]

    def write(target: Any, **options: Any) -> Iterator[Progress]:
        if len(straight) == 1:
            return (yield from write_volume_iter(first, target, overwrite=overwrite, **options))
        return (yield from write_channels_iter(straight, target, overwrite=overwrite, **options))

    d2 = Deformation.from_dict(first.metadata["deformation"])
    ds = first.metadata["output_spacing"]
    with use_scheduler(scheduler):
        if fmt != "ome-zarr":
            if "file_chunks" in write_options:
                raise InvalidInputError(f"file_chunks is an option of OME-Zarr outputs, not of {fmt}")
            if len(straight) > 1:
                write_options = {**write_options, "format": fmt}
            written = yield from write(path, **write_options)
            return written
        info = {
            "deformation": d2.to_dict(),
            "order": order,
            "output_spacing": ds,
            "pad": pad,
            "fill": float(fill),
            "source": first.source,
            **({"sources": [v.source for v in straight], "channels": [v.metadata["channel"] for v in straight]}
               if len(straight) > 1 else {}),
            "session": _session_dict(session),
            **_map_attributes(first, d2, ds),
        }
        attributes = dict(write_options.pop("attributes", None) or {})
        attributes["straightening"] = info
        write_options.pop("format", None)
        if "file_chunks" in write_options:
            write_options["chunks"] = write_options.pop("file_chunks")
        target = check_writable(path, overwrite=overwrite)
        # the image and the map arrays appear together: write both into a temporary folder, then rename
        with atomic_output(target, overwrite=overwrite) as tmp:
            yield from write(tmp, format="ome-zarr", attributes=attributes, **write_options)
            yield Progress("map", 0, 1, "writing the straightening map")
            _write_map_arrays(tmp, _straight_map(first, d2, ds), {"description": "straightening map"})
            yield Progress("map", 1, 1, "map written")
        return target


def export_channels_iter(
    volumes: Sequence[Any],
    deformation: Deformation,
    path: str | os.PathLike,
    *,
    order: int = 1,
    spacing: float | None = None,
    pad: int = 0,
    chunks: Any = None,
    fill: float = 0,
    overwrite: bool = False,
    session: Any = None,
    scheduler: str | None = None,
    max_output: float | None = DEFAULT_MAX_OUTPUT,
    **write_options: Any,
) -> Iterator[Progress]:
    """Straighten several channels with one deformation into one multi-channel image; yields progress, returns
    the path.

    ``volumes`` as for :func:`straighten_channels`; ``path`` a ``.zarr`` (OME-Zarr, axes ``c, z, y, x``, the
    channel names in ``omero.channels``, the straightening record and map as :func:`export` stores them) or a
    ``.tif`` (ImageJ hyperstack ``ZCYX``). Each slab of output planes is computed for every channel in one pass.
    Other options as for :func:`export` (``file_chunks``: the OME-Zarr chunk of one channel).
    """
    from .io.channels import CHANNEL_FORMATS

    fmt = output_format(path, write_options.get("format"))
    if fmt not in CHANNEL_FORMATS:
        raise InvalidInputError(f"{Path(path).name}: {fmt} holds one channel; write {len(volumes)} channels as "
                                "OME-Zarr (.zarr) or an ImageJ hyperstack (.tif)")
    straight = straighten_channels(volumes, deformation, order=order, spacing=spacing, pad=pad, chunks=chunks,
                                   fill=fill, max_output=max_output)
    first = straight[0]
    whole = Volume(da.stack([v.data for v in straight]).reshape((-1, *first.shape[1:])), spacing=first.spacing,
                   unit=first.unit, origin=first.origin)
    _check_disk(path, whole, fmt, write_options)
    write_options.pop("format", None)
    return (yield from _write_straight(straight, path, fmt, order=order, pad=pad, fill=fill, overwrite=overwrite,
                                       session=session, scheduler=scheduler, write_options=write_options))


def export(
    volume: Any,
    deformation: Deformation,
    path: str | os.PathLike,
    *,
    order: int = 1,
    spacing: float | None = None,
    pad: int = 0,
    chunks: Any = None,
    fill: float = 0,
    overwrite: bool = False,
    session: Any = None,
    scheduler: str | None = None,
    progress: Callable[[Progress], Any] | None = None,
    max_output: float | None = DEFAULT_MAX_OUTPUT,
    **write_options: Any,
) -> Path:
    """Straighten ``volume`` and write the result, chunk by chunk, in the format ``path`` names.

    Parameters
    ----------
    volume, deformation, order, spacing, pad, chunks, fill
        As for :func:`straighten`.
    path : str or path-like
        Output; every format of :func:`napari_unwind.io.write_volume`. An OME-Zarr export (``.zarr``) also
        stores the map and its provenance: ``attrs["unwind"]["straightening"]`` holds the deformation, order,
        output spacing, source, session and NGFF 0.6-style ``coordinateSystems``/``coordinateTransformations``
        (a ``"coordinates"`` transform from ``"straight"`` to ``"scan"``); the arrays ``map/slices``
        (Ns, 3, 3: base, dv, du per slice in scan voxels) and ``map/coordinates`` (Ns, 2, 2, 3) hold it exactly.
    overwrite : bool
        Replace an existing output once the new one is complete.
    session : dict or object with ``to_dict()``, optional
        The session the deformation comes from (stored in an OME-Zarr export).
    scheduler : str, optional
        None (threads), ``"synchronous"``, or a dask.distributed scheduler address ``"tcp://host:port"`` (a
        client is connected for the duration of the export and closed afterwards, unless an enclosing
        :func:`napari_unwind.scheduler.use_scheduler` of the same address already holds one).
    progress : callable, optional
        Called with each progress record.
    max_output : float or None
        Largest output accepted, in bytes (default :data:`DEFAULT_MAX_OUTPUT`, 256 GiB; None: no limit), as for
        :func:`straighten`. Besides, the output's uncompressed size is compared with the free space of the target's
        folder before anything is written: an uncompressed format that cannot fit is refused
        (:class:`~napari_unwind.errors.OutputError`); for a compressed one (OME-Zarr, gzip NRRD, ``.nii.gz``,
        compressed TIFF, PNG/JPEG slices) a :class:`DiskSpaceWarning` is issued and the export goes ahead.
    **write_options
        Passed to the writer (``chunks=``... note: ``chunks`` above are the dask chunks of the computation;
        pass the file's chunking as ``file_chunks`` for OME-Zarr, which is renamed to the writer's ``chunks``).

    Returns
    -------
    Path
        The written path.
    """
    return run(export_iter(volume, deformation, path, order=order, spacing=spacing, pad=pad, chunks=chunks,
                           fill=fill, overwrite=overwrite, session=session, scheduler=scheduler,
                           max_output=max_output, **write_options),
               progress)


# ------------------------------------------------------------------------------------------------------------------
# bending back
# ------------------------------------------------------------------------------------------------------------------
def _map_tables(d: Deformation) -> tuple[np.ndarray, ...]:
    """The deformation as plain arrays for the numba inverse map.

    ``knots`` (m,), ``pos`` (m, 3), ``rot`` (m, 3, 3) world matrices with columns u, v, n, ``rates`` (m-1, 3) the
    SLERP angular velocity of each segment in its start frame (so ``R(s) = R_k exp([rates_k] (s - d_k))``),
    ``bounds`` (m, 4) the cage sides ``(x_lo, x_hi, y_lo, y_hi)`` and ``pad`` (2,).
    """
    from scipy.spatial.transform import Rotation

    frames = d.frames
    rot = np.ascontiguousarray(frames.transpose(0, 2, 1))
    knots = np.asarray(d.knots, dtype=float)
    rs = Rotation.from_matrix(rot)
    rates = np.array([(rs[k].inv() * rs[k + 1]).as_rotvec() / (knots[k + 1] - knots[k])
                      for k in range(len(knots) - 1)])
    return (knots, np.ascontiguousarray(d.positions, dtype=float), rot, rates,
            np.ascontiguousarray(d.bounds, dtype=float), np.asarray(d.pad, dtype=float))


@njit(nogil=True, cache=True)
def _frame_at(s, knots, pos, rot, rates):
    """Centre, frame columns and SLERP rate at arclength ``s``: (c, R (3x3 world, columns u v n), w (3), pad)."""
    m = knots.shape[0]
    length = knots[m - 1]
    c = np.empty(3)
    r = np.empty((3, 3))
    w = np.zeros(3)
    if s < 0.0 or s > length:
        e = 0 if s < 0.0 else m - 1
        ds_ = s if s < 0.0 else s - length
        for a in range(3):
            c[a] = pos[e, a] + ds_ * rot[e, a, 2]
            for b in range(3):
                r[a, b] = rot[e, a, b]
        return c, r, w, True
    k = 0
    lo, hi = 0, m - 1
    while hi - lo > 1:  # knots[lo] <= s < knots[hi]
        mid = (lo + hi) // 2
        if knots[mid] <= s:
            lo = mid
        else:
            hi = mid
    k = min(lo, m - 2)
    t = s - knots[k]
    lam = t / (knots[k + 1] - knots[k])
    for a in range(3):
        c[a] = (1.0 - lam) * pos[k, a] + lam * pos[k + 1, a]
        w[a] = rates[k, a]
    wx, wy, wz = rates[k, 0] * t, rates[k, 1] * t, rates[k, 2] * t
    th = math.sqrt(wx * wx + wy * wy + wz * wz)
    mloc = np.eye(3)
    if th > 1e-15:
        ax, ay, az = wx / th, wy / th, wz / th
        cs, sn = math.cos(th), math.sin(th)
        oc = 1.0 - cs
        mloc[0, 0] = cs + ax * ax * oc
        mloc[0, 1] = ax * ay * oc - az * sn
        mloc[0, 2] = ax * az * oc + ay * sn
        mloc[1, 0] = ay * ax * oc + az * sn
        mloc[1, 1] = cs + ay * ay * oc
        mloc[1, 2] = ay * az * oc - ax * sn
        mloc[2, 0] = az * ax * oc - ay * sn
        mloc[2, 1] = az * ay * oc + ax * sn
        mloc[2, 2] = cs + az * az * oc
    for a in range(3):
        for b in range(3):
            acc = 0.0
            for q in range(3):
                acc += rot[k, a, q] * mloc[q, b]
            r[a, b] = acc
    return c, r, w, False


@njit(nogil=True, cache=True)
def _newton_s(p0, p1, p2, s, lo, hi, knots, pos, rot, rates, max_iter, tol):
    """Solve ``(p - c(s)) . n(s) = 0`` from ``s``; returns (x, y, s, residual)."""
    m = knots.shape[0]
    for _ in range(max_iter):
        c, r, w, padded = _frame_at(s, knots, pos, rot, rates)
        d0, d1, d2 = p0 - c[0], p1 - c[1], p2 - c[2]
        g = d0 * r[0, 2] + d1 * r[1, 2] + d2 * r[2, 2]
        if abs(g) < tol:
            break
        if padded:
            dg = -1.0
        else:
            k = 0
            for q in range(m - 1):
                if knots[q] <= s:
                    k = q
            k = min(k, m - 2)
            inv_len = 1.0 / (knots[k + 1] - knots[k])
            dc0 = (pos[k + 1, 0] - pos[k, 0]) * inv_len
            dc1 = (pos[k + 1, 1] - pos[k, 1]) * inv_len
            dc2 = (pos[k + 1, 2] - pos[k, 2]) * inv_len
            # n'(s) = R(s) (w x e_z) = R(s) (w_y, -w_x, 0)
            l0, l1 = w[1], -w[0]
            dn0 = r[0, 0] * l0 + r[0, 1] * l1
            dn1 = r[1, 0] * l0 + r[1, 1] * l1
            dn2 = r[2, 0] * l0 + r[2, 1] * l1
            dg = -(dc0 * r[0, 2] + dc1 * r[1, 2] + dc2 * r[2, 2]) + d0 * dn0 + d1 * dn1 + d2 * dn2
        step = g / dg if abs(dg) > 1e-12 else 0.0
        s = min(max(s - step, lo), hi)
    c, r, w, padded = _frame_at(s, knots, pos, rot, rates)
    d0, d1, d2 = p0 - c[0], p1 - c[1], p2 - c[2]
    x = d0 * r[0, 0] + d1 * r[1, 0] + d2 * r[2, 0]
    y = d0 * r[0, 1] + d1 * r[1, 1] + d2 * r[2, 1]
    e0 = c[0] + x * r[0, 0] + y * r[0, 1] - p0
    e1 = c[1] + x * r[1, 0] + y * r[1, 1] - p1
    e2 = c[2] + x * r[2, 0] + y * r[2, 1] - p2
    return x, y, s, math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)


@njit(nogil=True, cache=True)
def _inverse_points(pts, knots, pos, rot, rates, bounds, pad, reach, out, inside):
    """The inverse map of :meth:`Deformation.inverse`, point by point, for physical points ``pts`` (N, 3).

    Same method (seeds on the three nearest pieces of the centre polyline and its padded ends, Newton on
    ``(p - c(s)) . n(s) = 0``, the candidate nearest the curve wins) and the same ``inside`` rule. Points farther
    than ``reach`` from every piece are skipped (``inside`` False, ``out`` NaN).
    """
    m = knots.shape[0]
    length = knots[m - 1]
    lo, hi = -pad[0], length + pad[1]
    nseg = m + 1
    sa = np.empty((nseg, 3))
    sb = np.empty((nseg, 3))
    s0 = np.empty(nseg)
    s1 = np.empty(nseg)
    for a in range(3):
        sa[0, a] = pos[0, a] - pad[0] * rot[0, a, 2]
        sb[0, a] = pos[0, a]
        sa[nseg - 1, a] = pos[m - 1, a]
        sb[nseg - 1, a] = pos[m - 1, a] + pad[1] * rot[m - 1, a, 2]
    s0[0], s1[0] = lo, 0.0
    s0[nseg - 1], s1[nseg - 1] = length, hi
    for q in range(m - 1):
        for a in range(3):
            sa[q + 1, a] = pos[q, a]
            sb[q + 1, a] = pos[q + 1, a]
        s0[q + 1], s1[q + 1] = knots[q], knots[q + 1]
    dist = np.empty(nseg)
    tpar = np.empty(nseg)
    res_tol = 1e-6 * max(1.0, length)
    for n in range(pts.shape[0]):
        p0, p1, p2 = pts[n, 0], pts[n, 1], pts[n, 2]
        out[n, 0] = np.nan
        out[n, 1] = np.nan
        out[n, 2] = np.nan
        inside[n] = False
        dmin = np.inf
        for q in range(nseg):
            e0, e1, e2 = sb[q, 0] - sa[q, 0], sb[q, 1] - sa[q, 1], sb[q, 2] - sa[q, 2]
            l2 = e0 * e0 + e1 * e1 + e2 * e2
            if s1[q] - s0[q] <= 1e-12 or l2 <= 0.0:
                dist[q] = np.inf
                tpar[q] = 0.0
                continue
            t = ((p0 - sa[q, 0]) * e0 + (p1 - sa[q, 1]) * e1 + (p2 - sa[q, 2]) * e2) / l2
            t = min(max(t, 0.0), 1.0)
            f0, f1, f2 = sa[q, 0] + t * e0 - p0, sa[q, 1] + t * e1 - p1, sa[q, 2] + t * e2 - p2
            dist[q] = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
            tpar[q] = t
            dmin = min(dmin, dist[q])
        if dmin > reach:
            continue
        best_r = np.inf
        for _ in range(min(3, nseg)):
            q = int(np.argmin(dist))
            if not np.isfinite(dist[q]):
                break
            s_init = s0[q] + tpar[q] * (s1[q] - s0[q])
            dist[q] = np.inf
            x, y, s, res = _newton_s(p0, p1, p2, s_init, lo, hi, knots, pos, rot, rates, 20, 1e-9)
            rr = math.hypot(x, y)
            if np.isfinite(rr) and res < res_tol and rr < best_r:
                best_r = rr
                out[n, 0] = x
                out[n, 1] = y
                out[n, 2] = s
        s = out[n, 2]
        if not np.isfinite(s):
            continue
        sc = min(max(s, 0.0), length)
        k = 0
        for q in range(m - 1):
            if knots[q] <= sc:
                k = q
        k = min(k, m - 2)
        lam = (sc - knots[k]) / (knots[k + 1] - knots[k])
        x_lo = (1.0 - lam) * bounds[k, 0] + lam * bounds[k + 1, 0]
        x_hi = (1.0 - lam) * bounds[k, 1] + lam * bounds[k + 1, 1]
        y_lo = (1.0 - lam) * bounds[k, 2] + lam * bounds[k + 1, 2]
        y_hi = (1.0 - lam) * bounds[k, 3] + lam * bounds[k + 1, 3]
        inside[n] = (lo - 1e-9 <= s <= hi + 1e-9 and x_lo - 1e-9 <= out[n, 0] <= x_hi + 1e-9
                     and y_lo - 1e-9 <= out[n, 1] <= y_hi + 1e-9)


def _fast_inverse(d: Deformation, points: np.ndarray, reach: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`Deformation.inverse` in compiled code: ``(xys (N, 3), inside (N,))`` for physical points."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.empty((len(pts), 3))
    inside = np.zeros(len(pts), dtype=np.bool_)
    knots, pos, rot, rates, bounds, pad = _map_tables(d)
    _inverse_points(pts, knots, pos, rot, rates, bounds, pad, float(reach), out, inside)
    return out, inside


def _bend_block(region: np.ndarray, k_offset: int, block_offset: tuple[int, int, int],
                block_shape: tuple[int, int, int], deformation: dict, ds: float, order: int, fill: Any,
                dtype: str) -> np.ndarray:
    """One block of the bent volume: scan voxel centres -> inverse map -> straight voxels -> interpolation."""
    d = Deformation.from_dict(deformation)
    dt = np.dtype(dtype)
    out = np.full(block_shape, fill, dtype=dt)
    region = np.asarray(region)
    if order == 3:
        region = ndimage.spline_filter(region, 3, output=np.float64, mode="constant")
    i0, j0 = d.grid_centre(ds)
    s_lo = d.s_range[0]
    reach = float(np.hypot(*d.max_half_extent)) + ds
    tables = _map_tables(d)
    sp = np.asarray(d.spacing)
    org = np.asarray(d.origin)
    g1, g2 = np.meshgrid(np.arange(block_shape[1]) + block_offset[1], np.arange(block_shape[2]) + block_offset[2],
                         indexing="ij")
    phys = np.empty((g1.size, 3))
    xys = np.empty((g1.size, 3))
    inside = np.empty(g1.size, dtype=np.bool_)
    phys[:, 1] = g1.ravel() * sp[1] + org[1]
    phys[:, 2] = g2.ravel() * sp[2] + org[2]
    for a in range(block_shape[0]):  # a plane at a time: memory stays a few arrays of one plane
        phys[:, 0] = (a + block_offset[0]) * sp[0] + org[0]
        _inverse_points(phys, *tables, reach, xys, inside)
        if not inside.any():
            continue
        idx = np.flatnonzero(inside)
        sel = xys[idx]
        coords = np.stack([(sel[:, 2] - s_lo) / ds - k_offset, sel[:, 1] / ds + i0, sel[:, 0] / ds + j0])
        vals = ndimage.map_coordinates(region, coords, order=order, mode="constant", cval=float(fill), output=dt,
                                       prefilter=False)
        out[a].reshape(-1)[idx] = vals
    return out


def _bend_chunks(blocks: list, bounds: tuple, lo: tuple[int, int, int], hi: tuple[int, int, int],
                 *args: Any) -> np.ndarray:
    """Task: assemble the straight slab from its chunks, then :func:`_bend_block`."""
    return _bend_block(_assemble(blocks, bounds, lo, hi), lo[0], *args)


def _recorded(straight: Any) -> dict[str, Any]:
    """The straightening record of a straight Volume ({} when it has none): straighten's own metadata, or what a
    reader returned from a straight file of any format (:mod:`napari_unwind.io._straight_record`)."""
    from .io._straight_record import straightening_record

    return (straightening_record(straight) or {}) if isinstance(straight, Volume) else {}


def _recorded_pad(straight: Any) -> int:
    """The ``pad`` a straight Volume was made with, from its metadata (0 when it does not say)."""
    return int(_recorded(straight).get("pad", 0))


def _recorded_ds(straight: Volume, deformation: Deformation) -> float:
    """``ds`` of a straight Volume in the deformation's unit: the output spacing straighten recorded (exact, where
    a format keeps the spacing as float32) when the Volume's spacing agrees with it, else the Volume's spacing."""
    ds = float(straight.spacing[0]) * _unit_scale(straight.unit, deformation.unit)
    record = _recorded(straight)
    if "output_spacing" in record:
        exact = record["output_spacing"] * _unit_scale(record.get("unit") or straight.unit, deformation.unit)
        if _close((exact,), (ds,)):
            return exact
    return ds


def _check_shape(shape: Any) -> tuple[int, int, int]:
    """The bent output's shape: 3 whole numbers >= 1."""
    def whole(n: Any) -> int:
        if isinstance(n, (float, np.floating)) and float(n).is_integer():
            return int(n)
        return operator.index(n)  # TypeError for anything else

    try:
        values = tuple(whole(n) for n in shape)
    except TypeError:
        raise InvalidInputError(f"shape must be 3 positive integers, got {shape!r}") from None
    if len(values) != 3 or min(values) < 1:
        raise InvalidInputError(f"shape must be 3 positive integers, got {shape!r}")
    return values  # type: ignore[return-value]


def bend(
    straight: Any,
    deformation: Deformation,
    *,
    shape: Sequence[int] | None = None,
    scan: Any = None,
    order: int = 1,
    fill: float = 0,
    spacing: float | None = None,
    pad: int | None = None,
    chunks: Any = None,
    max_output: float | None = DEFAULT_MAX_OUTPUT,
) -> da.Array:
    """Put a straight specimen back into the bent pose of ``deformation`` (the inverse of :func:`straighten`).

    Parameters
    ----------
    straight : Volume, path or array-like, shape (Ns, Ny, Nx)
        A volume on the straight grid of ``deformation`` at spacing ``ds`` (axis0 = s, axis1 = y, axis2 = x),
        e.g. the output of :func:`straighten` or a straight model to pose. A path is opened with
        :func:`~napari_unwind.io.open_volume`; a Volume's spacing is converted to the deformation's unit when
        both are known length units.
    deformation : Deformation
        The pose to bend into.
    shape : tuple of 3 int, optional
        Shape of the bent output (the scan's grid: the deformation's spacing and origin). Required unless ``scan``
        is given.
    scan : Volume or path, optional
        The scan the deformation belongs to: its shape is the output's, and its spacing and origin are checked
        against the deformation's as :func:`straighten` checks them (a deformation of another scan or pyramid level
        would give a volume that does not overlay it).
    order : {0, 1, 3}
        Interpolation order in the straight volume.
    fill : float
        Value of voxels outside the cage.
    spacing : float, optional
        ``ds`` of the straight volume; default the straight Volume's spacing (the output spacing its metadata
        records when the two agree to 1e-6, which a float32 header rounds), else the finest scan spacing.
    pad : int, optional
        Extra straight slices at each end, as given to :func:`straighten`; default: what a straight Volume's
        metadata records (the output of :func:`straighten`, or a straight file of any format written by
        :func:`~napari_unwind.io.write_volume` or :func:`export` and read back), else 0.
    chunks : int or tuple, optional
        Chunks of the output (default 64^3).
    max_output : float or None
        Largest output accepted, in bytes (default :data:`DEFAULT_MAX_OUTPUT`; None: no limit).

    Returns
    -------
    dask.array.Array, shape ``shape``
        Lazy; dtype of ``straight``. Every scan voxel inside the cage takes the straight volume's value at its
        inverse-mapped position; the others get ``fill``. Chunks that cannot reach the cage are filled without
        reading anything.
    """
    order = _check_order(order)
    max_output = _check_max_output(max_output)
    if not isinstance(deformation, Deformation):
        raise InvalidInputError(f"deformation must be a napari_unwind.Deformation, got {type(deformation).__name__}")
    if isinstance(straight, (str, os.PathLike)):
        straight = open_volume(straight)
    auto_pad = pad is None
    if auto_pad:
        pad = _recorded_pad(straight)
    pad = _check_pad(pad)
    if isinstance(straight, Volume):
        sp = straight.spacing
        if not np.allclose(sp, sp[0], rtol=1e-6):
            raise InvalidInputError(f"a straight volume has isotropic spacing; this one has {sp}")
        ds = _recorded_ds(straight, deformation) if spacing is None else deformation._ds(spacing)
        data = straight.data
    else:
        ds = deformation._ds(spacing)
        data = _as_dask(straight, keep_int64=True)
    if data.ndim != 3:
        raise InvalidInputError(f"the straight volume must be 3D (s, y, x), got shape {data.shape}")
    if scan is not None:
        if isinstance(scan, (str, os.PathLike)):
            scan = open_volume(scan)
        if not isinstance(scan, Volume):
            raise InvalidInputError(f"scan must be a napari_unwind Volume or a path, got {type(scan).__name__}")
        _check_geometry(scan, deformation)
        if shape is not None and tuple(_check_shape(shape)) != tuple(scan.shape):
            raise InvalidInputError(f"shape={tuple(shape)} differs from the scan's shape {tuple(scan.shape)}; give "
                                    "one of them")
        shape = tuple(scan.shape)
    if shape is None:
        raise InvalidInputError("bend needs the bent output's shape=(N0, N1, N2) or the scan=: the shape of the "
                                "scan the deformation belongs to (a session's source.shape)")
    shape = _check_shape(shape)
    dtype = np.dtype(data.dtype)
    if not (np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating) or dtype == np.bool_):
        raise InvalidInputError(f"cannot bend voxels of type {dtype}; use integers or floats")
    _check_output_size("bent volume", shape, dtype, max_output,
                       "check shape= (the shape of the scan the deformation belongs to)")
    fill = _check_fill(fill, dtype)
    d2 = _padded(deformation, pad, ds)
    expected = d2.output_shape(ds)
    if tuple(data.shape) != expected and auto_pad and pad and deformation.output_shape(ds) == tuple(data.shape):
        d2, pad, expected = deformation, 0, tuple(data.shape)  # the deformation given already holds the padding
    if tuple(data.shape) != expected:
        raise InvalidInputError(
            f"the straight volume has shape {tuple(data.shape)} but the deformation's straight grid at spacing "
            f"{ds:g} (pad {pad}) has shape {expected}; pass the spacing and pad it was straightened with"
        )
    _warn_folds(deformation, "bent volume")
    out_chunks = _normalise_out_chunks(64 if chunks is None else chunks, shape)
    ns = expected[0]
    s_lo = d2.s_range[0]
    curve_s = s_lo + ds * np.arange(ns)
    centres, _ = d2.sample(curve_s)
    reach = float(np.hypot(*d2.max_half_extent)) + ds
    sp = np.asarray(d2.spacing)
    org = np.asarray(d2.origin)
    margin = 2 + (ORDER3_FILTER_MARGIN if order == 3 else 0)
    starts = [np.concatenate([[0], np.cumsum(c)[:-1]]).astype(int) for c in out_chunks]
    d_dict = d2.to_dict()
    edges = _chunk_edges(data)
    name = "bend-" + dask.base.tokenize(data.name, d_dict, ds, order, fill, shape, out_chunks)
    layer: dict = {}
    for a, (a0, n0) in enumerate(zip(starts[0], out_chunks[0], strict=True)):
        for b, (a1, n1) in enumerate(zip(starts[1], out_chunks[1], strict=True)):
            for c, (a2, n2) in enumerate(zip(starts[2], out_chunks[2], strict=True)):
                bshape = (int(n0), int(n1), int(n2))
                box_lo = np.array([a0, a1, a2], dtype=float) * sp + org
                box_hi = (np.array([a0 + n0, a1 + n1, a2 + n2], dtype=float) - 1) * sp + org
                # straight slices whose centre is within the cage's reach of the block's box
                gap = np.maximum(np.maximum(box_lo - centres, centres - box_hi), 0.0)
                close = np.flatnonzero(np.linalg.norm(gap, axis=1) <= reach)
                if close.size == 0:
                    layer[(name, a, b, c)] = (_fill_block, bshape, fill, dtype.str)  # cannot touch the cage
                    continue
                lo = np.array([max(0, int(close[0]) - margin), 0, 0])
                hi = np.array([min(ns, int(close[-1]) + 1 + margin), expected[1], expected[2]])
                refs, bounds = _region_refs(data, edges, lo, hi)
                layer[(name, a, b, c)] = (_bend_chunks, refs, bounds, tuple(int(v) for v in lo),
                                          tuple(int(v) for v in hi), (int(a0), int(a1), int(a2)), bshape, d_dict,
                                          ds, order, fill, dtype.str)
    return _output_array(name, layer, data, out_chunks, dtype)


# ------------------------------------------------------------------------------------------------------------------
# points, labels, meshes
# ------------------------------------------------------------------------------------------------------------------
def _points(values: Any, what: str) -> np.ndarray:
    """``values`` as finite float points of shape (N, 3); the error shows what was received."""
    try:
        if isinstance(values, (str, bytes)):
            raise ValueError
        pts = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{what} must be numbers of shape (N, 3), got {reprlib.repr(values)}") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInputError(f"{what} must have shape (N, 3), got shape {pts.shape}: {reprlib.repr(values)}")
    if not np.isfinite(pts).all():
        row = int(np.argmax(~np.isfinite(pts).all(axis=1)))
        raise InvalidInputError(f"{what} must be finite numbers; row {row} is {reprlib.repr(values[row])}")
    return pts


def map_points(
    points: Any,
    deformation: Deformation,
    *,
    to: str = "straight",
    spacing: float | None = None,
    pad: int = 0,
    strict: bool = True,
) -> np.ndarray:
    """Carry points between the scan and the straight volume.

    Parameters
    ----------
    points : array-like, shape (N, 3)
        ``to="straight"``: scan voxel coordinates (axis0, axis1, axis2). ``to="scan"``: straight voxel
        coordinates ``(k, i, j)`` on the grid of :func:`straighten` with spacing ``ds`` and ``pad``.
    deformation : Deformation
    to : {"straight", "scan"}
        The direction.
    spacing : float, optional
        ``ds`` of the straight grid (default: the finest scan spacing).
    pad : int
        Extra straight slices at each end, as given to :func:`straighten`.
    strict : bool
        True: a warning counts the points outside the cage, and an error says when all are. False: neither (one
        batch of a longer stream of points, whose caller judges the whole).

    Returns
    -------
    ndarray, shape (N, 3)
        The mapped voxel coordinates; NaN for points outside the cage (a warning counts them).

    Raises
    ------
    InvalidInputError
        When every point is outside the cage, or for malformed input.
    """
    if not isinstance(deformation, Deformation):
        raise InvalidInputError(f"deformation must be a napari_unwind.Deformation, got {type(deformation).__name__}")
    if to not in ("straight", "scan"):
        raise InvalidInputError(f"to must be 'straight' or 'scan', got {to!r}")
    pts = _points(points, "points")
    pad = _check_pad(pad)
    ds = deformation._ds(spacing)
    d = _padded(deformation, pad, ds)
    i0, j0 = d.grid_centre(ds)
    s_lo, s_hi = d.s_range
    out = np.full(pts.shape, np.nan)
    if len(pts) == 0:
        return out
    inside = np.zeros(len(pts), dtype=bool)
    tol = 1e-9 * max(1.0, d.length)
    for a in range(0, len(pts), _MAP_BATCH):  # each point on its own: batches only bound the time between checks
        checkpoint()
        p, o = pts[a:a + _MAP_BATCH], out[a:a + _MAP_BATCH]
        if to == "straight":
            xys, ins = _fast_inverse(d, d.to_physical(p))  # Deformation.inverse, compiled
            xys = xys[ins]
            o[ins] = np.stack([(xys[:, 2] - s_lo) / ds, xys[:, 1] / ds + i0, xys[:, 0] / ds + j0], axis=1)
        else:
            s = s_lo + p[:, 0] * ds
            y = (p[:, 1] - i0) * ds
            x = (p[:, 2] - j0) * ds
            b = d.bounds_at(s)
            ins = ((s >= s_lo - tol) & (s <= s_hi + tol) & (x >= b[:, 0] - tol) & (x <= b[:, 1] + tol)
                   & (y >= b[:, 2] - tol) & (y <= b[:, 3] + tol))
            if ins.any():
                phys = d.forward(np.stack([x[ins], y[ins], s[ins]], axis=1))
                o[ins] = d.to_voxels(phys)
        inside[a:a + _MAP_BATCH] = ins
    n_out = int((~inside).sum())
    if not strict:
        return out
    if n_out == len(pts):
        raise InvalidInputError(
            f"all {len(pts)} points are outside the cage of the deformation (mapping to {to!r}); check that they "
            "are voxel coordinates of the right volume"
        )
    if n_out:
        warnings.warn(f"{n_out} of {len(pts)} points lie outside the cage and map to NaN", UserWarning,
                      stacklevel=2)
    return out


def map_labels(
    labels: Any,
    deformation: Deformation,
    *,
    to: str = "straight",
    shape: Sequence[int] | None = None,
    spacing: float | None = None,
    pad: int = 0,
    chunks: Any = None,
    max_output: float | None = DEFAULT_MAX_OUTPUT,
) -> da.Array:
    """Carry a label image between the scan and the straight volume (nearest neighbour, fill 0, dtype kept).

    Parameters
    ----------
    labels : array-like or Volume
        ``to="straight"``: labels on the scan grid; ``to="scan"``: labels on the straight grid.
    deformation : Deformation
    to : {"straight", "scan"}
    shape : tuple of 3 int
        Shape of the scan (needed for ``to="scan"``).
    spacing, pad, chunks, max_output
        As for :func:`straighten` / :func:`bend` (a straight grid with no sample in the scan is refused).

    Returns
    -------
    dask.array.Array
        Lazy labels on the target grid; any integer or boolean type is kept (also int64 and uint64).
    """
    if to == "straight":
        pad = _check_pad(pad)
        max_output = _check_max_output(max_output)
        data, _, _ = _input_array(labels, deformation, any_dtype=True)
        ds = deformation._ds(spacing)
        d2 = _padded(deformation, pad, ds)
        _check_output_size("straight labels", d2.output_shape(ds), data.dtype, max_output,
                           f"check the output spacing ({ds:g}) and pad ({pad})")
        _check_padding(deformation, d2, pad, ds, data.shape)
        _warn_folds(deformation, "straight labels")
        geometry = _check_coverage(d2, ds, data.shape, "straight labels")
        return _straighten_array(data, d2, ds, 0, chunks, 0, geometry)
    if to == "scan":
        if shape is None:
            raise InvalidInputError("map_labels(..., to='scan') needs the scan's shape=")
        return bend(labels, deformation, shape=shape, order=0, fill=0, spacing=spacing, pad=pad, chunks=chunks,
                    max_output=max_output)
    raise InvalidInputError(f"to must be 'straight' or 'scan', got {to!r}")


def map_mesh(
    vertices: Any,
    faces: Any,
    deformation: Deformation,
    *,
    to: str = "straight",
    spacing: float | None = None,
    pad: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Carry a surface mesh between the scan and the straight volume: vertices are mapped, faces kept.

    Parameters
    ----------
    vertices : array-like, shape (N, 3)
        Voxel coordinates (see :func:`map_points`).
    faces : array-like of int, shape (M, K)
        Vertex indices per face (triangles: K = 3).
    deformation, to, spacing, pad
        As for :func:`map_points`.

    Returns
    -------
    vertices : ndarray, shape (N, 3)
        Mapped vertices; NaN for those outside the cage (a warning counts them).
    faces : ndarray, shape (M, K)
        Unchanged.
    """
    try:
        f = np.asarray(faces)
    except (TypeError, ValueError):
        f = np.asarray([], dtype=object)
    if f.ndim != 2 or (f.size and not np.issubdtype(f.dtype, np.integer)):
        raise InvalidInputError(
            f"faces must be whole numbers of shape (M, K) (vertex indices), got {reprlib.repr(faces)}"
        )
    v = _points(vertices, "vertices")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise InvalidInputError(f"faces refer to vertices outside 0..{len(v) - 1}")
    return map_points(v, deformation, to=to, spacing=spacing, pad=pad), f
