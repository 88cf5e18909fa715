"""Curve post-processing: smoothing, resampling by arclength, minimal keyframes (docs/design.md 4, steps 6-9)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..errors import InvalidInputError
from ..progress import checkpoint

__all__ = ["smooth_curve", "resample_curve", "regularise_ends", "select_keyframes", "arclength"]

#: Taubin's (lambda, mu) pair: a shrinking step then an inflating one, so bends keep their radius.
_TAUBIN = (0.5, -0.53)


def arclength(points: np.ndarray) -> np.ndarray:
    """Cumulative arclength (K,) of a polyline (K, 3), starting at 0."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def smooth_curve(points: np.ndarray, *, iterations: int = 50, method: str = "taubin") -> np.ndarray:
    """Smooth a polyline with its ends fixed.

    Parameters
    ----------
    points : ndarray, shape (K, 3)
    iterations : int
        Number of smoothing iterations (the paper's ``s = 50``).
    method : {"taubin", "laplacian"}
        ``"laplacian"`` is the paper's ``c_i <- (c_{i-1} + c_{i+1}) / 2``. It shrinks every bend: each iteration
        moves a point by about ``h^2 / (2 R)`` towards the centre of curvature (``h`` the point spacing, ``R``
        the bend radius), which at the defaults costs a bent fish one to three voxels and 2-5 % of its length.
        ``"taubin"`` (default) follows each such step by an inflating one (Taubin's lambda = 0.5, mu = -0.53),
        which removes the same noise without the shrinkage.

    Returns
    -------
    ndarray, shape (K, 3)
    """
    pts = np.array(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInputError(f"points must have shape (K, 3), got {pts.shape}")
    if iterations < 0:
        raise InvalidInputError(f"smoothing iterations must be >= 0, got {iterations}")
    if method == "laplacian":
        steps: tuple[float, ...] = (1.0,)
    elif method == "taubin":
        steps = _TAUBIN
    else:
        raise InvalidInputError(f"unknown smoothing method {method!r}; use 'taubin' or 'laplacian'")
    if len(pts) < 3:
        return pts
    for _ in range(int(iterations)):
        checkpoint()
        for lam in steps:
            pts[1:-1] += lam * (0.5 * (pts[:-2] + pts[2:]) - pts[1:-1])
    return pts


def regularise_ends(points: np.ndarray, window: float) -> np.ndarray:
    """Replace the first and last ``window`` of a curve by quadratic fits over twice that length.

    Near a point-like Dirichlet end the level sets are small caps around one mesh vertex, and their centroids
    wander by a voxel or two: at the scale of the cage that is a sharp kink, and the deformation folds there
    (a kink of curvature k folds a cage wider than 1 / k). A quadratic in arclength, fitted to the curve over
    ``[0, 2 window]`` (and the same at the tail), keeps the body's real bend and drops the kink; the fit takes over
    fully within ``window`` of the end and blends linearly into the curve over the next ``window``.

    Parameters
    ----------
    points : ndarray, shape (K, 3)
        A curve sampled densely and evenly (after :func:`resample_curve`).
    window : float
        Length of the end stretch to replace, in the units of ``points``; 0 leaves the curve alone.

    Returns
    -------
    ndarray, shape (K, 3)
    """
    pts = np.array(points, dtype=float)
    s = arclength(pts)
    total = s[-1]
    window = min(float(window), total / 4.0)
    if window <= 0 or len(pts) < 8:
        return pts
    for dist in (s, total - s):  # head end, then tail end
        fit_on = dist <= 2.0 * window
        if fit_on.sum() < 4:
            continue
        coef = np.polynomial.polynomial.polyfit(dist[fit_on], pts[fit_on], 2)
        fitted = np.polynomial.polynomial.polyval(dist[fit_on], coef).T
        w = np.clip((2.0 * window - dist[fit_on]) / window, 0.0, 1.0)[:, None]
        pts[fit_on] = w * fitted + (1.0 - w) * pts[fit_on]
    return pts


def resample_curve(points: np.ndarray, *, step: float | None = None, min_step: float = 0.0,
                   max_points: int = 4000) -> np.ndarray:
    """Resample a polyline uniformly by arclength.

    Parameters
    ----------
    points : ndarray, shape (K, 3)
    step : float, optional
        Target spacing; default half the smallest segment (the paper's rule), but at least ``min_step`` and
        coarse enough that at most ``max_points`` points result.

    Returns
    -------
    ndarray, shape (M, 3)
        Points with the first and last of ``points`` kept, equally spaced along the polyline.
    """
    pts = np.asarray(points, dtype=float)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    pts = pts[keep]
    if len(pts) < 2:
        raise InvalidInputError("the curve has zero length: the head and the tail coincide")
    s = arclength(pts)
    total = s[-1]
    if step is None:
        step = 0.5 * float(np.diff(s).min())
    step = max(float(step), float(min_step), total / (max_points - 1))
    m = max(int(np.ceil(total / step)), 1) + 1
    t = np.linspace(0.0, total, m)
    return np.stack([np.interp(t, s, pts[:, i]) for i in range(3)], axis=1)


def _box_corners(c: np.ndarray, frames: np.ndarray, r: float) -> np.ndarray:
    """Centre plus the four corners of the box of half-size r in each frame: (K, 5, 3)."""
    u, v = frames[:, 0], frames[:, 1]
    return np.stack([c, c + r * (u + v), c + r * (u - v), c - r * (u + v), c - r * (u - v)], axis=1)


def select_keyframes(points: np.ndarray, frames: np.ndarray, *, radius: float, tolerance: float) -> np.ndarray:
    """Fewest keyframes whose interpolation reproduces a dense curve and its frames (prism subdivision).

    Start from the two ends; between two keyframes the deformation moves the centre linearly and SLERPs the
    frame. Where the dense curve's box of half-size ``radius`` (its centre and four corners) strays from the
    interpolated box by more than ``tolerance`` at some point, split there (at the worst point, not at the
    middle as the original did: fewer keyframes) and recurse.

    The paper split while a curve point left the prism spanned by the two boxes, which lets the centreline
    stray by up to ``radius`` (10 voxels by default) from the keyframe polyline; the test here bounds the
    deviation of the whole box, bend and twist, by ``tolerance`` instead.

    Parameters
    ----------
    points : ndarray, shape (K, 3)
        Dense curve, physical units.
    frames : ndarray, shape (K, 3, 3)
        Rows ``u, v, n`` at each point.
    radius, tolerance : float
        Box half-size and allowed deviation, physical units.

    Returns
    -------
    ndarray of int
        Sorted indices of the keyframes into ``points`` (first and last included).
    """
    pts = np.asarray(points, dtype=float)
    if len(pts) < 2:
        raise InvalidInputError(f"a curve needs at least 2 points, got {len(pts)}")
    if not (radius > 0 and tolerance > 0):
        raise InvalidInputError(f"radius and tolerance must be > 0, got {radius} and {tolerance}")
    s = arclength(pts)
    dense = _box_corners(pts, frames, radius)
    rots = Rotation.from_matrix(np.transpose(frames, (0, 2, 1)))
    chosen = {0, len(pts) - 1}
    stack = [(0, len(pts) - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        idx = np.arange(a + 1, b)
        lam = (s[idx] - s[a]) / (s[b] - s[a])
        c = (1 - lam)[:, None] * pts[a] + lam[:, None] * pts[b]
        slerp = Slerp([0.0, 1.0], rots[[a, b]])
        fr = np.transpose(slerp(lam).as_matrix(), (0, 2, 1))
        dev = np.linalg.norm(_box_corners(c, fr, radius) - dense[idx], axis=2).max(axis=1)
        worst = int(np.argmax(dev))
        if dev[worst] > tolerance:
            k = int(idx[worst])
            chosen.add(k)
            stack += [(a, k), (k, b)]
    return np.array(sorted(chosen), dtype=np.int64)
