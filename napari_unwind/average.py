"""An average straight specimen from a batch of straight volumes (issue 24 item 3).

Every specimen is a straight volume (axis0 = s, axis1 = y, axis2 = x, as :func:`napari_unwind.warp.straighten`
writes it). They are brought onto one grid and averaged:

1. **length**: each is resampled along s to the common number of stations (the median of the batch, or
   ``stations=``), linearly by arc length, head to head and tail to tail; with ``landmarks=`` (the same K positions
   along s in every specimen: the gill, the dorsal fin's start, the anus) piecewise linearly, each specimen's
   landmark k onto the batch's mean position of landmark k (as a fraction of the length);
2. **size**: with ``scale="length"`` (default) the cross-section is scaled by the same factor, so a fish twice as
   long is also halved across (shape is compared, not size); ``scale="none"`` keeps the physical cross-section;
3. **centre and roll**: each specimen's cross-section centre is its intensity-weighted centroid (after
   normalisation, averaged along s); its roll about s is the angle that best correlates its mean cross-section with
   the batch's (a grid search every 4 degrees, then 1 and 0.25 around the best; two rounds against the batch mean,
   the first against the specimen of median length);
4. **intensity**: ``normalise="robust"`` (default) maps each specimen's median to 0 and its 99th percentile to 1;
   ``"none"`` keeps the grey values.

It runs on dask in two passes, on the threads of this process or on a ``dask.distributed`` cluster
(``scheduler=``, as :func:`napari_unwind.warp.export`): the first reads each specimen block by block (its sum
along s and a subsample for the percentiles), the second is one task per chunk of output stations that resamples
every specimen's slab (linear in s, and the cross-section map as four bilinear taps, the same at every station)
and computes the mean, median, standard deviation and the residual sums in one numba loop. Locally the batch is
read once: it is held in memory between the passes while it fits in :data:`HOLD_BYTES`; on a cluster the workers
read it twice. Per specimen the residual: the RMS difference to the mean and the correlation with it. The result
does not depend on where it ran (the tasks are the same functions of the same blocks).
"""

from __future__ import annotations

import os
from collections.abc import Generator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from .errors import InvalidInputError
from .progress import Progress
from .progress import run as _run

__all__ = ["AverageResult", "average", "average_iter", "read_landmarks", "SCALES", "NORMALISATIONS", "HOLD_BYTES"]

SCALES = ("length", "none")
NORMALISATIONS = ("robust", "none")
#: The batch (in its stored dtype) is read once and held in memory between the two passes up to this size.
HOLD_BYTES = 4 * 2**30


@dataclass(frozen=True)
class AverageResult:
    """The average specimen and how each specimen fits it.

    Attributes
    ----------
    mean, median, std : ndarray of float32, shape (n, ny, nx)
        Voxel-wise statistics of the aligned specimens.
    spacing : float
        The average's voxel size (the median spacing of the batch, in its unit).
    unit : str or None
    names : tuple of str
        One per specimen (its file name, or ``specimen<i>``).
    roll : ndarray, shape (N,)
        Roll (degrees) applied to each specimen about s.
    shift : ndarray, shape (N, 2)
        Its cross-section centre (y, x) relative to its straight grid's centre, physical units.
    scale : ndarray, shape (N,)
        The factor its physical length was multiplied by.
    rms, correlation : ndarray, shape (N,)
        Residual: RMS difference to the mean (normalised grey values) and Pearson correlation with the mean.
    landmarks : ndarray, shape (K,), or None
        With ``landmarks=``: where each landmark lies along the average's s (its unit), the batch's mean position.
    """

    mean: np.ndarray
    median: np.ndarray
    std: np.ndarray
    spacing: float
    unit: str | None
    names: tuple[str, ...]
    roll: np.ndarray
    shift: np.ndarray
    scale: np.ndarray
    rms: np.ndarray
    correlation: np.ndarray
    landmarks: np.ndarray | None = None

    def table(self) -> list[dict[str, Any]]:
        """One row per specimen: name, scale, roll, shift, rms, correlation."""
        return [{"name": n, "scale": float(self.scale[i]), "roll_deg": float(self.roll[i]),
                 "shift_y": float(self.shift[i, 0]), "shift_x": float(self.shift[i, 1]),
                 "rms": float(self.rms[i]), "correlation": float(self.correlation[i])}
                for i, n in enumerate(self.names)]

    def csv_text(self) -> str:
        """:meth:`table` as CSV text: the bytes ``unwind average`` writes to ``<mean>.residuals.csv`` (the
        pipeline's table writer: floats to 6 significant digits, ``\\n`` line ends)."""
        import csv
        import io

        rows = self.table()
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: f"{v:.6g}" if isinstance(v, float) else v for k, v in r.items()})
        return buf.getvalue()


def _as_volume(item: Any, i: int) -> tuple[Any, str]:
    from .io import Volume, open_volume

    if isinstance(item, (str, os.PathLike)):
        vol = open_volume(item)
        name = os.path.basename(os.fspath(item).rstrip("/\\"))
        return vol, name
    if isinstance(item, Volume):
        return item, os.path.basename(item.source) if item.source else f"specimen{i}"
    arr = np.asarray(item)
    if arr.ndim != 3:
        raise InvalidInputError(f"specimen {i} must be a 3D straight volume (s, y, x), got shape {arr.shape}")
    return Volume(arr), f"specimen{i}"


@njit(nogil=True, cache=True, inline="always")
def _tap(cy: float, cx: float, c: float, s: float, zoom: float, yy: int, xx: int, ocy: float, ocx: float, Ny: int,
         Nx: int) -> tuple:  # pragma: no cover - numba
    """The cross-section map at output pixel (yy, xx): it shows input pixel ``centre + R(-angle) ((yy, xx) -
    out_centre) / zoom`` (c, s: cos and sin of the angle), sampled bilinearly: 4 flat indices into the (Ny, Nx)
    section and their weights, all 0 beyond the edge as scipy's ``map_coordinates(mode="constant")`` (a sample is
    valid iff 0 <= c <= n - 1 on both axes)."""
    dy, dx = (yy - ocy) / zoom, (xx - ocx) / zoom
    iy = cy + c * dy - s * dx
    ix = cx + s * dy + c * dx
    y0 = min(max(int(np.floor(max(min(iy, 1e9), -1e9))), 0), max(Ny - 2, 0))
    x0 = min(max(int(np.floor(max(min(ix, 1e9), -1e9))), 0), max(Nx - 2, 0))
    fy = min(max(iy - y0, 0.0), 1.0)
    fx = min(max(ix - x0, 0.0), 1.0)
    y1, x1 = min(y0 + 1, Ny - 1), min(x0 + 1, Nx - 1)
    v = 1.0 if (0.0 <= iy <= Ny - 1 and 0.0 <= ix <= Nx - 1) else 0.0
    return (y0 * Nx + x0, y0 * Nx + x1, y1 * Nx + x0, y1 * Nx + x1,
            v * (1 - fy) * (1 - fx), v * (1 - fy) * fx, v * fy * (1 - fx), v * fy * fx)


@njit(nogil=True, cache=True)
def _bilinear_taps(cy: float, cx: float, angle: float, zoom: float, ny: int, nx: int, ocy: float, ocx: float,
                   Ny: int, Nx: int) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - numba
    """The cross-section map of one specimen (:func:`_tap`, angle in degrees) for every pixel of a (ny, nx) output
    section: flat indices (P, 4) into the (Ny, Nx) input section and weights (P, 4), P = ny * nx. The map is the
    same at every station, so the resampling computes it once per specimen; the roll search uses the same
    :func:`_tap` pixel by pixel."""
    P = ny * nx
    idx = np.empty((P, 4), np.int64)
    wt = np.empty((P, 4), np.float64)
    c, s = np.cos(angle * np.pi / 180.0), np.sin(angle * np.pi / 180.0)
    for yy in range(ny):
        for xx in range(nx):
            p = yy * nx + xx
            i0, i1, i2, i3, w0, w1, w2, w3 = _tap(cy, cx, c, s, zoom, yy, xx, ocy, ocx, Ny, Nx)
            idx[p, 0], idx[p, 1], idx[p, 2], idx[p, 3] = i0, i1, i2, i3
            wt[p, 0], wt[p, 1], wt[p, 2], wt[p, 3] = w0, w1, w2, w3
    return idx, wt


@njit(nogil=True, cache=True)
def _roll_score(img: np.ndarray, cy: float, cx: float, angle: float, zoom: float, ref: np.ndarray, ocy: float,
                ocx: float, stride: int) -> float:  # pragma: no cover - numba
    """Pearson correlation of ``ref`` (ny, nx) with the (Ny, Nx) section ``img`` mapped by :func:`_tap`, over every
    ``stride``-th pixel on both axes (no arrays of taps: the search tries some 80 angles per specimen)."""
    ny, nx = ref.shape
    Ny, Nx = img.shape
    flat = img.ravel()
    c, s = np.cos(angle * np.pi / 180.0), np.sin(angle * np.pi / 180.0)
    sa = sb = sab = saa = sbb = 0.0
    P = 0
    for yy in range(0, ny, stride):
        for xx in range(0, nx, stride):
            P += 1
            i0, i1, i2, i3, w0, w1, w2, w3 = _tap(cy, cx, c, s, zoom, yy, xx, ocy, ocx, Ny, Nx)
            a = w0 * flat[i0] + w1 * flat[i1] + w2 * flat[i2] + w3 * flat[i3]
            b = ref[yy, xx]
            sa += a
            sb += b
            sab += a * b
            saa += a * a
            sbb += b * b
    cov = sab - sa * sb / P
    den = np.sqrt(max(saa - sa * sa / P, 0.0) * max(sbb - sb * sb / P, 0.0))
    return cov / den if den > 0 else 0.0


@njit(nogil=True, cache=True)
def _sample_section(img: np.ndarray, idx: np.ndarray, wt: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    flat, o = img.ravel(), out.ravel()
    for p in range(o.size):
        o[p] = wt[p, 0] * flat[idx[p, 0]] + wt[p, 1] * flat[idx[p, 1]] + wt[p, 2] * flat[idx[p, 2]] \
            + wt[p, 3] * flat[idx[p, 3]]


@njit(nogil=True, cache=True, fastmath={"reassoc", "contract"})
def _resample(slab: np.ndarray, k0: np.ndarray, w: np.ndarray, idx: np.ndarray, wt: np.ndarray, lo: float,
              inv: float, out: np.ndarray) -> None:  # pragma: no cover - numba
    """Stations of one specimen on the average's grid: linear in s between input stations ``k0[j]`` and
    ``k0[j] + 1`` of ``slab`` (m_in, Ny * Nx, raw grey values) with weight ``w[j]`` (one row of the input section),
    then bilinear across by the taps, normalised ``(v - lo) * inv`` (0 outside the specimen: the taps' weights there
    are 0). ``out`` (m, P)."""
    m, P = out.shape
    row = np.empty(slab.shape[1], np.float32)
    taps = np.empty(P)
    for p in range(P):
        taps[p] = wt[p, 0] + wt[p, 1] + wt[p, 2] + wt[p, 3]
    for j in range(m):
        r0 = k0[j]
        wj = np.float32(w[j])
        a, b = slab[r0], slab[r0 + 1]
        for q in range(row.size):
            row[q] = a[q] + wj * (np.float32(b[q]) - np.float32(a[q]))
        for p in range(P):
            if taps[p] == 0.0:
                out[j, p] = 0.0
                continue
            acc = wt[p, 0] * row[idx[p, 0]] + wt[p, 1] * row[idx[p, 1]] + wt[p, 2] * row[idx[p, 2]] \
                + wt[p, 3] * row[idx[p, 3]]
            out[j, p] = (acc - lo * taps[p]) * inv


def _sorting_network(n: int) -> np.ndarray:
    """Comparators (i, j), i < j, of Batcher's odd-even merge sort of ``n`` values (the network of the next power
    of two with the pairs beyond ``n`` dropped: those would compare with +inf and change nothing), shape (C, 2)."""
    p2 = 1 << max(0, (n - 1).bit_length())
    comps = []
    p = 1
    while p < p2:
        k = p
        while k >= 1:
            for j in range(k % p, p2 - k, 2 * k):
                for i in range(min(k, p2 - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p) and i + j + k < n:
                        comps.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return np.array(comps, np.int64).reshape(-1, 2)


@njit(nogil=True, cache=True, fastmath={"reassoc", "contract"})
def _voxel_stats(stack: np.ndarray, comps: np.ndarray, mean: np.ndarray, median: np.ndarray, std: np.ndarray,
                 sums: np.ndarray, msums: np.ndarray) -> None:  # pragma: no cover - numba
    """Per voxel over the N specimens of ``stack`` (N, m, P): mean, median (numpy's: the middle two averaged for
    even N) and standard deviation (population) into (m, P); per specimen the sums of (x - mean)^2, x, x^2 and
    x * mean into ``sums`` (N, 4), and of mean, mean^2 into ``msums`` (2,).

    Station by station, each loop runs along a row of P pixels (vectorised); the median sorts the N rows with the
    sorting network ``comps`` (:func:`_sorting_network`), min and max pixel by pixel.
    """
    N, m, P = stack.shape
    buf = np.empty((N, P), np.float32)
    acc = np.empty(P)
    mm = np.empty(P)
    sq = np.empty(P)
    half = N // 2
    for j in range(m):
        acc[:] = 0.0
        for i in range(N):
            for p in range(P):
                acc[p] += stack[i, j, p]
        for p in range(P):
            mean[j, p] = np.float32(acc[p] / N)
            mm[p] = np.float64(mean[j, p])
            acc[p] = acc[p] / N
        sq[:] = 0.0
        for i in range(N):
            for p in range(P):
                d = stack[i, j, p] - acc[p]
                sq[p] += d * d
        for p in range(P):
            std[j, p] = np.sqrt(sq[p] / N)
        for i in range(N):
            s0 = s1 = s2 = s3 = 0.0
            for p in range(P):
                x = np.float64(stack[i, j, p])
                d = x - mm[p]
                s0 += d * d
                s1 += x
                s2 += x * x
                s3 += x * mm[p]
            sums[i, 0] += s0
            sums[i, 1] += s1
            sums[i, 2] += s2
            sums[i, 3] += s3
        t0 = t1 = 0.0
        for p in range(P):
            t0 += mm[p]
            t1 += mm[p] * mm[p]
        msums[0] += t0
        msums[1] += t1
        for i in range(N):
            for p in range(P):
                buf[i, p] = stack[i, j, p]
        for c in range(comps.shape[0]):
            lo, hi = buf[comps[c, 0]], buf[comps[c, 1]]
            for p in range(P):
                x, y = lo[p], hi[p]
                lo[p], hi[p] = min(x, y), max(x, y)
        if N % 2:
            for p in range(P):
                median[j, p] = buf[half, p]
        else:
            for p in range(P):
                median[j, p] = np.float32((np.float64(buf[half - 1, p]) + buf[half, p]) / 2)


def _block_stats(block: np.ndarray, first: int, step: int, acc: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """One stored block of a specimen (stations first.., whole sections): the running sum over s (``acc``, the
    previous blocks', float64, each station added in turn so the sum does not depend on how the specimen is
    chunked) and a subsample (every ``step``-th station of the specimen, every ``step``-th pixel across) for the
    percentiles."""
    block = np.asarray(block)
    acc = np.zeros(block.shape[1:], np.float64) if acc is None else acc.copy()
    for row in block:
        acc += row
    return acc, np.asarray(block[(-first) % step::step, ::step, ::step], dtype=np.float32).ravel()


def _running_sum(parts: tuple) -> np.ndarray:
    return parts[0]


def _subsample(parts: tuple) -> np.ndarray:
    return parts[1]


def _average_chunk(slabs: Sequence[Sequence[np.ndarray]], plan: Sequence[tuple], shape: tuple[int, int, int],
                   out_c: tuple[float, float]) -> tuple[np.ndarray, ...]:
    """One chunk of output stations: every specimen's slab (its stored blocks along s that the chunk needs)
    resampled (``plan``: per specimen the first block's first station, k0, w, centre, roll, zoom, lo,
    1 / (hi - lo)), then the voxel statistics and residual sums."""
    m, ny, nx = shape
    N = len(slabs)
    stack = np.empty((N, m, ny * nx), np.float32)
    for i, (parts, (first, k0, w, centre, roll, zoom, lo, inv)) in enumerate(zip(slabs, plan, strict=True)):
        slab = np.asarray(parts[0]) if len(parts) == 1 else np.concatenate([np.asarray(x) for x in parts])
        idx, wt = _bilinear_taps(float(centre[0]), float(centre[1]), float(roll), float(zoom), ny, nx,
                                 float(out_c[0]), float(out_c[1]), slab.shape[1], slab.shape[2])
        _resample(np.ascontiguousarray(slab).reshape(slab.shape[0], -1), k0 - first, w, idx, wt, lo, inv, stack[i])
    mean, median, std = (np.empty((m, ny * nx), np.float32) for _ in range(3))
    sums, msums = np.zeros((N, 4)), np.zeros(2)
    _voxel_stats(stack, _sorting_network(N), mean, median, std, sums, msums)
    return mean.reshape(shape), median.reshape(shape), std.reshape(shape), sums, msums


def _sections(data: Any) -> Any:
    """A specimen's data as a dask array with whole cross-sections per block (chunked along s only)."""
    import dask.array as da

    if not isinstance(data, da.Array):
        data = da.from_array(np.asarray(data), chunks=(64, -1, -1))
    if len(data.chunks[1]) > 1 or len(data.chunks[2]) > 1:
        data = data.rechunk({1: -1, 2: -1})
    return data


def _landmark_knots(landmarks: Any, vols: Sequence[Any], names: Sequence[str], n: int
                    ) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray | None]:
    """Per specimen the piecewise-linear map from the average's stations to its own: knots (output stations,
    input stations). Without landmarks, head to head and tail to tail; with them, each specimen's landmark k goes to
    the batch's mean position of landmark k (as a fraction of the length). Also the mean positions (fractions)."""
    ends = [(np.array([0.0, n - 1.0]), np.array([0.0, v.shape[0] - 1.0])) for v in vols]
    if landmarks is None:
        return ends, None
    if isinstance(landmarks, (str, bytes)) or not hasattr(landmarks, "__len__"):
        raise InvalidInputError(f"landmarks must be one sequence of arc-length positions per specimen, got "
                                f"{type(landmarks).__name__}")
    if len(landmarks) != len(vols):
        raise InvalidInputError(f"landmarks has {len(landmarks)} rows for {len(vols)} specimens: give one row of "
                                "positions per specimen, in the order of the specimens")
    rows = []
    for i, (row, v, name) in enumerate(zip(landmarks, vols, names, strict=True)):
        try:
            r = np.asarray(row, dtype=float).ravel()
        except (TypeError, ValueError):
            raise InvalidInputError(f"landmarks of {name} must be numbers (arc-length positions), got {row!r}") \
                from None
        if i and len(r) != len(rows[0]):
            raise InvalidInputError(f"{name} has {len(r)} landmarks, {names[0]} has {len(rows[0])}: every specimen "
                                    "needs the same landmarks, in the same order")
        if len(r) == 0:
            raise InvalidInputError(f"{name} has no landmark: give at least one position along s, or none at all")
        length = (v.shape[0] - 1) * float(v.spacing[0])
        if not np.isfinite(r).all() or (r < 0).any() or (r > length * (1 + 1e-9)).any():
            raise InvalidInputError(f"landmarks of {name} must lie inside its length [0, {length:g}] "
                                    f"{v.unit or ''}, got {r.tolist()}".replace("  ", " "))
        if (np.diff(r) <= 0).any():
            raise InvalidInputError(f"landmarks of {name} must increase along s (head to tail), got {r.tolist()}")
        rows.append(np.minimum(r, length) / length)
    frac = np.array(rows)                                  # (N, K) fractions of each specimen's length
    mean_frac = frac.mean(axis=0)
    knots = []
    for v, fr in zip(vols, frac, strict=True):
        out = np.concatenate([[0.0], mean_frac * (n - 1), [n - 1.0]])
        inp = np.concatenate([[0.0], fr * (v.shape[0] - 1), [v.shape[0] - 1.0]])
        keep = np.concatenate([[True], np.diff(out) > 0])  # a landmark every specimen has at an end adds nothing
        knots.append((out[keep], inp[keep]))
    return knots, mean_frac


def average_iter(
    specimens: Sequence[Any],
    *,
    stations: int | None = None,
    landmarks: Sequence[Sequence[float]] | None = None,
    scale: str = "length",
    normalise: str = "robust",
    max_roll: float = 90.0,
    chunk: int = 32,
    scheduler: str | None = None,
    names: Sequence[str] | None = None,
) -> Generator[Progress, None, AverageResult]:
    """:func:`average` as a generator of :class:`~napari_unwind.progress.Progress`; returns the result."""
    if scale not in SCALES:
        raise InvalidInputError(f"scale must be one of {', '.join(SCALES)}, got {scale!r}")
    if normalise not in NORMALISATIONS:
        raise InvalidInputError(f"normalise must be one of {', '.join(NORMALISATIONS)}, got {normalise!r}")
    if isinstance(specimens, (str, os.PathLike)) or len(specimens) < 2:
        raise InvalidInputError(f"an average needs at least 2 straight specimens, got "
                                f"{1 if isinstance(specimens, (str, os.PathLike)) else len(specimens)}")
    if not (np.isfinite(max_roll) and 0 <= max_roll <= 180):
        raise InvalidInputError(f"max_roll must be between 0 and 180 degrees, got {max_roll!r}")
    chunk = int(chunk)
    if chunk < 1:
        raise InvalidInputError(f"chunk must be a positive number of stations, got {chunk}")
    if stations is not None and int(stations) < 2:
        raise InvalidInputError(f"stations must be at least 2, got {stations}")
    vols, found = zip(*(_as_volume(x, i) for i, x in enumerate(specimens)), strict=True)
    if names is None:
        names = found
    elif isinstance(names, str) or len(names) != len(vols):
        raise InvalidInputError(f"names must give one name per specimen ({len(vols)}), got {names!r}"[:300])
    names = tuple(str(x) for x in names)
    units = {v.unit for v in vols}
    if len(units) > 1:
        raise InvalidInputError(f"the specimens are in different units ({', '.join(sorted(map(str, units)))}): "
                                "convert them to one unit first")
    for v, n in zip(vols, names, strict=True):
        sp = np.asarray(v.spacing, float)
        if not np.allclose(sp, sp[0], rtol=1e-6):
            raise InvalidInputError(f"{n} has spacing {tuple(sp)}: a straight volume is isotropic (s, y, x); is it a "
                                    "bent scan?")
        if v.shape[0] < 2:
            raise InvalidInputError(f"{n} has {v.shape[0]} station(s) along s: too short to resample")
    N = len(vols)
    lengths = np.array([v.shape[0] for v in vols])
    n = int(stations) if stations is not None else int(np.median(lengths))
    knots, mean_frac = _landmark_knots(landmarks, vols, names, n)
    ds = float(np.median([v.spacing[0] for v in vols]))
    spacings = np.array([v.spacing[0] for v in vols])
    f = (n - 1) / (lengths - 1)                       # output stations per input station (head to head, tail to tail)
    # the physical factor of each length: the average's (n - 1) ds against the specimen's (Ns - 1) spacing
    length_factor = (n - 1) * ds / ((lengths - 1) * spacings)
    # input pixels -> output pixels across: with the length's factor (shape), or the physical size kept
    xy_zoom = f.copy() if scale == "length" else spacings / ds
    import dask

    from .scheduler import SYNCHRONOUS, THREADS, use_scheduler

    datas = [_sections(v.data) for v in vols]
    # read once: the batch is held in memory between the two passes when it fits (on a cluster it is read twice,
    # by the workers, rather than brought into this process)
    hold = (scheduler is None or scheduler in THREADS or scheduler in SYNCHRONOUS) and \
        sum(d.nbytes for d in datas) <= HOLD_BYTES
    yield Progress("average", 0, 3 * N, "read, normalise and centre")
    with use_scheduler(scheduler):
        norm, centres, profiles = [], [], []
        group = max(4, -(-N // 4))     # specimens read together (progress 4 times)
        for g in range(0, N, group):
            part = datas[g:g + group]
            if hold:
                part = list(dask.persist(*part))
                datas[g:g + group] = part
            tasks = []
            for d in part:
                step = max(1, int(np.ceil((int(np.prod(d.shape)) / 2**18) ** (1 / 3))))   # ~2^18 samples
                firsts = np.concatenate([[0], np.cumsum(d.chunks[0])[:-1]])
                chain, acc = [], None      # block by block along s: the running sum, the subsamples
                for b, a in zip(d.to_delayed().ravel(), firsts, strict=True):
                    parts = dask.delayed(_block_stats, pure=True)(b, int(a), step, acc)
                    acc = dask.delayed(_running_sum, pure=True)(parts)
                    chain.append(dask.delayed(_subsample, pure=True)(parts))
                tasks.append((acc, chain))
            for i, parts in zip(range(g, g + len(part)), dask.compute(*tasks), strict=True):
                acc, samples = parts
                if normalise == "robust":
                    lo, hi = (float(x) for x in np.percentile(np.concatenate(samples), [50, 99]))
                    hi = hi if hi > lo else lo + 1.0
                else:
                    lo, hi = 0.0, 1.0
                norm.append((lo, hi))
                prof = (acc / vols[i].shape[0] - lo) / (hi - lo)
                w = np.clip(prof, 0, None)
                if w.sum() <= 0:
                    raise InvalidInputError(f"{names[i]} holds nothing above its median grey value: an empty "
                                            "straight volume?")
                yy, xx = np.indices(prof.shape, dtype=float)
                centres.append(np.array([(w * yy).sum() / w.sum(), (w * xx).sum() / w.sum()]))
                profiles.append(prof)
            yield Progress("average", g + len(part), 3 * N)
        # the output cross-section: large enough for every specimen, scaled, around its centre
        half = np.max([np.maximum(c, np.asarray(p.shape) - 1 - c) * z
                       for c, p, z in zip(centres, profiles, xy_zoom, strict=True)], axis=0)
        ny, nx = (2 * np.ceil(half) + 1).astype(int)
        out_c = np.array([(ny - 1) / 2, (nx - 1) / 2])

        def section(i: int, angle: float) -> np.ndarray:
            idx, wt = _bilinear_taps(centres[i][0], centres[i][1], float(angle), float(xy_zoom[i]), ny, nx,
                                     out_c[0], out_c[1], *profiles[i].shape)
            out = np.empty((ny, nx))
            _sample_section(profiles[i], idx, wt, out)
            return out

        def best_roll(i: int, ref: np.ndarray, around: float | None) -> float:
            def score(angle: float, stride: int = 1) -> tuple[float, float]:
                return _roll_score(profiles[i], centres[i][0], centres[i][1], float(angle), float(xy_zoom[i]), ref,
                                   out_c[0], out_c[1], stride), float(angle)

            if around is None:    # every 4 degrees on every other pixel, then 1 and 0.25 around the best
                coarse = np.unique(np.clip(np.arange(-max_roll, max_roll + 4.0, 4.0), -max_roll, max_roll))
                around = max(score(a, 2) for a in coarse)[1]
                steps = ((1.0, 3.0), (0.25, 0.75))
            else:                 # the second round: within 8 degrees of the first's
                steps = ((1.0, 8.0), (0.25, 0.75))
            best = (-2.0, around)
            for step, reach in steps:
                around = best[1]
                best = max([best] + [score(a) for a in np.arange(around - reach, around + reach + 1e-9, step)
                                     if abs(a) <= max_roll])
            return best[1]

        ref_i = int(np.argsort(lengths)[N // 2])
        ref = section(ref_i, 0.0)
        roll = np.zeros(N)
        from concurrent.futures import ThreadPoolExecutor

        for rnd in range(2):
            # specimens in parallel (the scores are numba without the GIL; each specimen's search is its own)
            with ThreadPoolExecutor(max_workers=min(N, os.cpu_count() or 1)) as pool:
                roll[:] = list(pool.map(lambda i, r=rnd, against=ref: best_roll(
                    i, against, None if r == 0 else float(roll[i])), range(N)))
            yield Progress("average", N + (rnd + 1) * N // 2, 3 * N, "roll")
            ref = np.mean([section(i, roll[i]) for i in range(N)], axis=0)
        roll -= np.median(roll)        # the batch's own roll is kept: the average is turned as its typical member
        # the average, chunk by chunk along s: one task per chunk of output stations reads every specimen's slab
        tasks = []
        blocks = [d.to_delayed().ravel() for d in datas]      # whole sections, along s
        bounds = [np.concatenate([[0], np.cumsum(d.chunks[0])]) for d in datas]
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            slabs, plan = [], []
            for i, v in enumerate(vols):
                s_in = np.clip(np.interp(np.arange(a, b, dtype=float), *knots[i]), 0.0, v.shape[0] - 1)
                k0 = np.minimum(np.floor(s_in).astype(np.int64), v.shape[0] - 2)
                first, stop = int(k0.min()), int(k0.max()) + 2
                b0 = int(np.searchsorted(bounds[i], first, side="right")) - 1
                b1 = int(np.searchsorted(bounds[i], stop, side="left"))
                slabs.append(list(blocks[i][b0:b1]))
                plan.append((int(bounds[i][b0]), k0, s_in - k0, tuple(centres[i]), float(roll[i]), float(xy_zoom[i]),
                             float(norm[i][0]), 1.0 / (norm[i][1] - norm[i][0])))
            tasks.append(dask.delayed(_average_chunk, pure=True)(slabs, plan, (b - a, ny, nx), tuple(out_c)))
        mean = np.empty((n, ny, nx), np.float32)
        median = np.empty_like(mean)
        std = np.empty_like(mean)
        sums, msums = np.zeros((N, 4)), np.zeros(2)
        group = max(4, -(-len(tasks) // 4))
        for g in range(0, len(tasks), group):
            for c, (m_, md, sd, s_, ms) in zip(range(g, min(g + group, len(tasks))), dask.compute(*tasks[g:g + group]),
                                               strict=True):
                a = c * chunk
                mean[a:a + len(m_)], median[a:a + len(m_)], std[a:a + len(m_)] = m_, md, sd
                sums += s_
                msums += ms
            yield Progress("average", 2 * N + int(N * min(len(tasks), g + group) / len(tasks)), 3 * N,
                           "mean, median, std")
    count = n * ny * nx
    rms = np.sqrt(sums[:, 0] / count)
    cov = sums[:, 3] / count - sums[:, 1] / count * msums[0] / count
    var_x = sums[:, 2] / count - (sums[:, 1] / count) ** 2
    var_m = msums[1] / count - (msums[0] / count) ** 2
    corr = cov / np.sqrt(np.maximum(var_x * var_m, 1e-300))
    shift = np.array([(c - (np.asarray(p.shape) - 1) / 2) * v.spacing[1]
                      for c, p, v in zip(centres, profiles, vols, strict=True)])
    lm = None if mean_frac is None else mean_frac * (n - 1) * ds
    return AverageResult(mean=mean, median=median, std=std, spacing=ds, unit=vols[0].unit, names=tuple(names),
                         roll=roll, shift=shift, scale=length_factor, rms=rms, correlation=corr, landmarks=lm)


def average(specimens: Sequence[Any], *, stations: int | None = None,
            landmarks: Sequence[Sequence[float]] | None = None, scale: str = "length", normalise: str = "robust",
            max_roll: float = 90.0, chunk: int = 32, scheduler: str | None = None,
            names: Sequence[str] | None = None, progress: Any = None) -> AverageResult:
    """The average straight specimen of a batch.

    Parameters
    ----------
    specimens : sequence of Volume, path or array, each shape (Ns_i, Ny_i, Nx_i)
        Straight volumes (axis0 = s, head first; isotropic spacing, one unit for all); at least two.
    stations : int, optional
        Stations along s of the average (default: the batch's median).
    landmarks : sequence of N sequences of K floats, optional
        Per specimen, in its order, K arc-length positions (its unit, from the head, increasing, inside its length
        [0, L]) of the same features (e.g. the gill, the dorsal fin's start, the anus). The resampling along s is
        then piecewise linear between them (the head and the tail are implicit landmarks): each specimen's landmark
        k lands on the batch's mean position of landmark k, as a fraction of the length.
    scale : {"length", "none"}
        Scale each cross-section by its length factor (shape, default) or keep it (size).
    normalise : {"robust", "none"}
        Map each specimen's median grey value to 0 and its 99th percentile to 1 (default), or keep the values.
    max_roll : float
        Largest roll (degrees) searched each way when aligning the cross-sections (0: no roll).
    chunk : int
        Stations computed together, one dask task (bounds memory: specimens x chunk x cross-section).
    scheduler : str, optional
        Where the dask tasks run: None (threads), ``"synchronous"`` or a ``dask.distributed`` scheduler address
        such as ``"tcp://host:8786"`` (its workers must see the specimens' paths); see
        :func:`napari_unwind.scheduler.use_scheduler`.
    names : sequence of str, optional
        One per specimen, for the residual table (default: the file names, or ``specimen<i>``).
    progress : callable, optional
        Called with each :class:`~napari_unwind.progress.Progress`.

    Returns
    -------
    AverageResult
    """
    return _run(average_iter(specimens, stations=stations, landmarks=landmarks, scale=scale, normalise=normalise,
                             max_roll=max_roll, chunk=chunk, scheduler=scheduler, names=names), progress)


def read_landmarks(path: str | os.PathLike, specimens: Sequence[str | os.PathLike]) -> list[list[float]]:
    """Landmarks per specimen from a CSV file, in the order of ``specimens``.

    Parameters
    ----------
    path : path
        A CSV file: one row per specimen, its name (file name) or path first, then its K landmark positions along
        s (arc length from the head, in the specimens' length unit). An optional first row of column names (the
        landmarks' names) is recognised by its positions not being numbers.
    specimens : sequence of paths, length N
        The specimens' paths, as given to :func:`average`.

    Returns
    -------
    list of N lists of K floats

    Raises
    ------
    InvalidInputError
        A row that names no specimen (or an ambiguous file name), a specimen named twice or not at all, rows of
        different lengths, a position that is not a number. (Whether they increase and lie inside each length is
        checked by :func:`average`.)
    """
    import csv

    keys = [os.path.abspath(os.fspath(p)).rstrip("/\\") for p in specimens]
    base = [os.path.basename(k) for k in keys]
    try:
        with open(path, newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except OSError as exc:
        raise InvalidInputError(f"cannot read the landmarks {path}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InvalidInputError(f"{path} is not a CSV file of landmarks ({exc})") from None

    def numbers(r: list[str]) -> list[float] | None:
        try:
            return [float(c) for c in r[1:]]
        except ValueError:
            return None

    if rows and numbers(rows[0]) is None:
        rows = rows[1:]                       # the header: names of the landmarks
    if not rows:
        raise InvalidInputError(f"{path} holds no landmarks: one row per specimen, its name then its positions")
    found: dict[int, list[float]] = {}
    for r in rows:
        name = r[0].strip()
        vals = numbers(r)
        if vals is None:
            raise InvalidInputError(f"{path}: the positions of {name} must be numbers (arc length from the head), "
                                    f"got {', '.join(c.strip() for c in r[1:])}")
        if len(vals) != len(numbers(rows[0]) or []):
            raise InvalidInputError(f"{path}: {name} has {len(vals)} landmarks, {rows[0][0].strip()} has "
                                    f"{len(numbers(rows[0]) or [])}: every specimen needs the same landmarks")
        full = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(path)), name)).rstrip("/\\")
        hits = [i for i, k in enumerate(keys) if k in (os.path.abspath(name).rstrip("/\\"), full)]
        if not hits:
            hits = [i for i, b in enumerate(base) if b == os.path.basename(name.rstrip("/\\"))]
            if len(hits) > 1:
                raise InvalidInputError(f"{path}: {name} names {len(hits)} specimens (the same file name in "
                                        "different folders): give their paths instead")
        if not hits:
            raise InvalidInputError(f"{path}: {name} is not one of the specimens being averaged")
        if hits[0] in found:
            raise InvalidInputError(f"{path}: {base[hits[0]]} is named twice: give one row per specimen")
        found[hits[0]] = vals
    missing = [base[i] for i in range(len(keys)) if i not in found]
    if missing:
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        raise InvalidInputError(f"{path} has no landmarks for {', '.join(missing[:3])}{more}: give one row per "
                                "specimen")
    return [found[i] for i in range(len(keys))]
