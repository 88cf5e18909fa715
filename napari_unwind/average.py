"""An average straight specimen from a batch of straight volumes (issue 24 item 3).

Every specimen is a straight volume (axis0 = s, axis1 = y, axis2 = x, as :func:`napari_unwind.warp.straighten`
writes it). They are brought onto one grid and averaged:

1. **length**: each is resampled along s to the common number of stations (the median of the batch, or
   ``stations=``), linearly by arc length, head to head and tail to tail;
2. **size**: with ``scale="length"`` (default) the cross-section is scaled by the same factor, so a fish twice as
   long is also halved across (shape is compared, not size); ``scale="none"`` keeps the physical cross-section;
3. **centre and roll**: each specimen's cross-section centre is its intensity-weighted centroid (after
   normalisation, averaged along s); its roll about s is the angle that best correlates its mean cross-section with
   the batch's (a grid search every 4 degrees, then 1 and 0.25 around the best; two rounds against the batch mean,
   the first against the specimen of median length);
4. **intensity**: ``normalise="robust"`` (default) maps each specimen's median to 0 and its 99th percentile to 1;
   ``"none"`` keeps the grey values.

The mean, median and standard deviation volumes are computed chunk by chunk along s (each specimen is read in
its stored chunks, each once per pass: one pass for the percentiles and the mean cross-section, one for the
average); the cross-section map is the same at every station, so it is four bilinear taps computed once per
specimen. Per specimen the residual: the RMS difference to the mean and the correlation with it.
"""

from __future__ import annotations

import os
from collections.abc import Generator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import InvalidInputError
from .progress import Progress
from .progress import run as _run

__all__ = ["AverageResult", "average", "average_iter", "SCALES", "NORMALISATIONS"]

SCALES = ("length", "none")
NORMALISATIONS = ("robust", "none")


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

    def table(self) -> list[dict[str, Any]]:
        """One row per specimen: name, scale, roll, shift, rms, correlation."""
        return [{"name": n, "scale": float(self.scale[i]), "roll_deg": float(self.roll[i]),
                 "shift_y": float(self.shift[i, 0]), "shift_x": float(self.shift[i, 1]),
                 "rms": float(self.rms[i]), "correlation": float(self.correlation[i])}
                for i, n in enumerate(self.names)]


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


def _rotate2(img: np.ndarray, angle: float, centre: np.ndarray, out_shape: tuple[int, int], out_centre: np.ndarray,
             zoom: float = 1.0) -> np.ndarray:
    """Sample ``img`` so that output pixel p shows input pixel centre + R(-angle) (p - out_centre) / zoom."""
    from scipy.ndimage import map_coordinates

    yy, xx = np.indices(out_shape, dtype=float)
    dy, dx = (yy - out_centre[0]) / zoom, (xx - out_centre[1]) / zoom
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    iy = centre[0] + c * dy - s * dx
    ix = centre[1] + s * dy + c * dx
    return map_coordinates(img, [iy, ix], order=1, mode="constant", cval=0.0)


def _bilinear_taps(iy: np.ndarray, ix: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (M, 4) into a (shape) image and weights (M, 4) of bilinear sampling at (iy, ix) (order 1, 0
    beyond the edge as scipy's ``mode="constant"``: a sample is valid iff 0 <= c <= n - 1 on both axes)."""
    iy, ix = iy.ravel(), ix.ravel()
    ny, nx = shape
    valid = (iy >= 0) & (iy <= ny - 1) & (ix >= 0) & (ix <= nx - 1)
    y0 = np.clip(np.floor(iy).astype(int), 0, max(ny - 2, 0))
    x0 = np.clip(np.floor(ix).astype(int), 0, max(nx - 2, 0))
    fy, fx = np.clip(iy - y0, 0, 1), np.clip(ix - x0, 0, 1)
    y1, x1 = np.minimum(y0 + 1, ny - 1), np.minimum(x0 + 1, nx - 1)
    idx = np.stack([y0 * nx + x0, y0 * nx + x1, y1 * nx + x0, y1 * nx + x1], axis=1)
    wt = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], axis=1) * valid[:, None]
    return idx, wt


class _SlabReader:
    """Reads stations [lo, hi) of a (lazy) straight volume, normalised, whole storage chunks at a time, keeping the
    last chunks read (the output chunks walk along s, so each stored chunk is read and decompressed once)."""

    def __init__(self, data: Any, lo: float, hi: float) -> None:
        self.data, self.lo, self.scale = data, lo, 1.0 / (hi - lo)
        chunks = getattr(data, "chunks", None)
        self.step = int(chunks[0][0]) if chunks else 64
        self.start, self.block = 0, np.empty((0,) + tuple(data.shape[1:]), np.float32)

    def read(self, a: int, b: int) -> tuple[int, np.ndarray]:
        """``(a, stations a..b-1)``, normalised, float32."""
        b = min(b, self.data.shape[0])
        if a < self.start or b > self.start + len(self.block):
            start = (a // self.step) * self.step
            stop = min(self.data.shape[0], -(-b // self.step) * self.step)
            keep = self.block[max(0, start - self.start):] if start >= self.start else self.block[:0]
            kept_from = max(start, self.start) if len(keep) else start
            new_from = kept_from + len(keep)
            fresh = (np.asarray(self.data[new_from:stop], dtype=np.float32) - self.lo) * self.scale
            self.start, self.block = kept_from, np.concatenate([keep, fresh]) if len(keep) else fresh
        return a, self.block[a - self.start:b - self.start]


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else 0.0


def _best_roll(img: np.ndarray, centre: np.ndarray, ref: np.ndarray, ref_centre: np.ndarray, zoom: float,
               max_roll: float) -> float:
    best = (-2.0, 0.0)
    for angle in np.unique(np.clip(np.arange(-max_roll, max_roll + 4.0, 4.0), -max_roll, max_roll)):
        best = max(best, (_ncc(_rotate2(img, angle, centre, ref.shape, ref_centre, zoom), ref), float(angle)))
    for step, reach in ((1.0, 3.0), (0.25, 0.75)):
        around = best[1]
        for angle in np.arange(around - reach, around + reach + 1e-9, step):
            if abs(angle) <= max_roll:
                best = max(best, (_ncc(_rotate2(img, angle, centre, ref.shape, ref_centre, zoom), ref),
                                  float(angle)))
    return best[1]


def average_iter(
    specimens: Sequence[Any],
    *,
    stations: int | None = None,
    scale: str = "length",
    normalise: str = "robust",
    max_roll: float = 90.0,
    chunk: int = 32,
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
    vols, names = zip(*(_as_volume(x, i) for i, x in enumerate(specimens)), strict=True)
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
    if n < 2:
        raise InvalidInputError(f"stations must be at least 2, got {stations}")
    ds = float(np.median([v.spacing[0] for v in vols]))
    spacings = np.array([v.spacing[0] for v in vols])
    f = (n - 1) / (lengths - 1)                       # output stations per input station (head to head, tail to tail)
    # the physical factor of each length: the average's (n - 1) ds against the specimen's (Ns - 1) spacing
    length_factor = (n - 1) * ds / ((lengths - 1) * spacings)
    # input pixels -> output pixels across: with the length's factor (shape), or the physical size kept
    xy_zoom = f.copy() if scale == "length" else spacings / ds
    yield Progress("average", 0, 3 * N, "normalise and centre")
    norm, centres, profiles = [], [], []
    for i, v in enumerate(vols):
        # one pass: the mean cross-section (raw) and a subsample for the percentiles
        acc = np.zeros(v.shape[1:], np.float64)
        step = max(1, int(round((int(np.prod(v.shape)) / 2e6) ** (1 / 3))))
        sample = []
        reader = _SlabReader(v.data, 0.0, 1.0)
        for a in range(0, v.shape[0], reader.step):
            _, block = reader.read(a, a + reader.step)
            acc += block.sum(axis=0, dtype=np.float64)
            sample.append(block[(-a) % step::step, ::step, ::step].ravel())
        if normalise == "robust":
            lo, hi = (float(x) for x in np.percentile(np.concatenate(sample), [50, 99]))
            hi = hi if hi > lo else lo + 1.0
        else:
            lo, hi = 0.0, 1.0
        norm.append((lo, hi))
        prof = (acc / v.shape[0] - lo) / (hi - lo)
        w = np.clip(prof, 0, None)
        if w.sum() <= 0:
            raise InvalidInputError(f"{names[i]} holds nothing above its median grey value: an empty straight volume?")
        yy, xx = np.indices(prof.shape, dtype=float)
        centres.append(np.array([(w * yy).sum() / w.sum(), (w * xx).sum() / w.sum()]))
        profiles.append(prof)
        yield Progress("average", i + 1, 3 * N)
    # the output cross-section: large enough for every specimen, scaled, around its centre
    half = np.max([np.maximum(c, np.asarray(p.shape) - 1 - c) * z
                   for c, p, z in zip(centres, profiles, xy_zoom, strict=True)], axis=0)
    ny, nx = (2 * np.ceil(half) + 1).astype(int)
    out_c = np.array([(ny - 1) / 2, (nx - 1) / 2])
    ref_i = int(np.argsort(lengths)[N // 2])
    ref = _rotate2(profiles[ref_i], 0.0, centres[ref_i], (ny, nx), out_c, xy_zoom[ref_i])
    roll = np.zeros(N)
    for rnd in range(2):
        for i in range(N):
            roll[i] = _best_roll(profiles[i], centres[i], ref, out_c, xy_zoom[i], max_roll)
            yield Progress("average", N + rnd * N // 2 + (i + 1) // 2, 3 * N, "roll")
        ref = np.mean([_rotate2(profiles[i], roll[i], centres[i], (ny, nx), out_c, xy_zoom[i]) for i in range(N)],
                      axis=0)
    roll -= np.median(roll)            # the batch's own roll is kept: the average is turned as its typical member
    mean = np.zeros((n, ny, nx), np.float32)
    median = np.zeros_like(mean)
    std = np.zeros_like(mean)
    sq = np.zeros(N)
    dots = np.zeros((N, 3))            # sums of x, x^2, x * mean per specimen, for the correlation
    msum = np.zeros(2)                 # sums of mean, mean^2
    yy, xx = np.indices((ny, nx), dtype=float)
    # the cross-section map is the same at every station: its bilinear taps (4 flat indices and weights, 0 outside)
    taps = []
    for i, v in enumerate(vols):
        dy, dx = (yy - out_c[0]) / xy_zoom[i], (xx - out_c[1]) / xy_zoom[i]
        cs, sn = np.cos(np.radians(roll[i])), np.sin(np.radians(roll[i]))
        taps.append(_bilinear_taps(centres[i][0] + cs * dy - sn * dx, centres[i][1] + sn * dy + cs * dx,
                                   v.shape[1:]))
    readers = [_SlabReader(v.data, float(norm[i][0]), float(norm[i][1])) for i, v in enumerate(vols)]
    n_chunks = -(-n // chunk)
    for c in range(n_chunks):
        a, b = c * chunk, min(n, (c + 1) * chunk)
        stack = np.empty((N, b - a, ny, nx), np.float32)
        for i, v in enumerate(vols):
            s_in = np.clip(np.arange(a, b, dtype=float) / f[i], 0.0, v.shape[0] - 1)   # input station of each
            k0 = np.minimum(np.floor(s_in).astype(int), v.shape[0] - 2)
            w = (s_in - k0)[:, None]
            lo0, slab = readers[i].read(int(k0.min()), int(k0.max()) + 2)
            flat = slab.reshape(slab.shape[0], -1)
            rows = (1.0 - w) * flat[k0 - lo0] + w * flat[k0 + 1 - lo0]        # linear in s, (b - a, Ny * Nx)
            idx, wt = taps[i]
            sec = (rows[:, idx] * wt).sum(axis=-1)                            # bilinear across, (b - a, ny * nx)
            stack[i] = sec.reshape(b - a, ny, nx)
        m = stack.mean(axis=0)
        mean[a:b] = m
        median[a:b] = np.median(stack, axis=0)
        std[a:b] = stack.std(axis=0)
        d = stack - m[None]
        sq += (d.astype(np.float64) ** 2).reshape(N, -1).sum(axis=1)
        flat = stack.reshape(N, -1).astype(np.float64)
        mf = m.ravel().astype(np.float64)
        dots += np.stack([flat.sum(axis=1), (flat ** 2).sum(axis=1), flat @ mf], axis=1)
        msum += (mf.sum(), (mf ** 2).sum())
        yield Progress("average", 2 * N + int(N * (c + 1) / n_chunks), 3 * N, "mean, median, std")
    count = n * ny * nx
    rms = np.sqrt(sq / count)
    cov = dots[:, 2] / count - dots[:, 0] / count * msum[0] / count
    var_x = dots[:, 1] / count - (dots[:, 0] / count) ** 2
    var_m = msum[1] / count - (msum[0] / count) ** 2
    corr = cov / np.sqrt(np.maximum(var_x * var_m, 1e-300))
    shift = np.array([(c - (np.asarray(p.shape) - 1) / 2) * v.spacing[1]
                      for c, p, v in zip(centres, profiles, vols, strict=True)])
    return AverageResult(mean=mean, median=median, std=std, spacing=ds, unit=vols[0].unit, names=tuple(names),
                         roll=roll, shift=shift, scale=length_factor, rms=rms, correlation=corr)


def average(specimens: Sequence[Any], *, stations: int | None = None, scale: str = "length",
            normalise: str = "robust", max_roll: float = 90.0, chunk: int = 32,
            progress: Any = None) -> AverageResult:
    """The average straight specimen of a batch.

    Parameters
    ----------
    specimens : sequence of Volume, path or array, each shape (Ns_i, Ny_i, Nx_i)
        Straight volumes (axis0 = s, head first; isotropic spacing, one unit for all); at least two.
    stations : int, optional
        Stations along s of the average (default: the batch's median).
    scale : {"length", "none"}
        Scale each cross-section by its length factor (shape, default) or keep it (size).
    normalise : {"robust", "none"}
        Map each specimen's median grey value to 0 and its 99th percentile to 1 (default), or keep the values.
    max_roll : float
        Largest roll (degrees) searched each way when aligning the cross-sections (0: no roll).
    chunk : int
        Stations computed together (bounds memory: specimens x chunk x cross-section).
    progress : callable, optional
        Called with each :class:`~napari_unwind.progress.Progress`.

    Returns
    -------
    AverageResult
    """
    return _run(average_iter(specimens, stations=stations, scale=scale, normalise=normalise, max_roll=max_roll,
                             chunk=chunk), progress)
