"""An inverse of a deformation's cage written here, for coverage checks independent of napari_unwind.warp (issue 19).

The map is rebuilt from the keyframes alone, as napari_unwind.deformation's docstrings define it: the centre c(s)
is the polyline through the keyframe positions (s its arclength), the frames (rows u, v, n) are SLERPed between
keyframes (scipy's Slerp), both ends go on along the end normals over the padding, and the cage's sides are linear
in s between keyframes. The forward map is f(x, y, s) = c(s) + x u(s) + y v(s).

A point p lies on the cross-section at s where g(s) = (p - c(s)) . n(s) = 0. At such a root p - c = x u + y v,
and dg/ds = -n . (c' + x u' + y v') = -J, the Jacobian of f there. So p is held, unfolded, when g falls through zero
at some s (J > 0) where (x, y) = ((p - c) . u, (p - c) . v) is inside the cage. The roots are found by a sign change
of g on a dense grid of s (a quarter of the finest voxel), then linear interpolation: no Newton step, no seeding
from the nearest segment, nothing shared with ``Deformation.inverse`` or ``warp._fast_inverse``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def _sampled(d, step: float):
    kf = d.keyframes
    pos = np.array([k.position for k in kf], dtype=float)
    frames = np.array([k.frame for k in kf], dtype=float)  # rows u, v, n
    sides = np.array([[k.offset[0] - k.half_extent[0], k.offset[0] + k.half_extent[0],
                       k.offset[1] - k.half_extent[1], k.offset[1] + k.half_extent[1]] for k in kf], dtype=float)
    knots = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    length = knots[-1]
    s = np.arange(-d.pad[0], length + d.pad[1] + step, step)
    sc = np.clip(s, 0.0, length)
    rot = Slerp(knots, Rotation.from_matrix(frames.transpose(0, 2, 1)))(sc).as_matrix().transpose(0, 2, 1)
    centre = np.stack([np.interp(sc, knots, pos[:, i]) for i in range(3)], axis=1)
    centre += (s - sc)[:, None] * np.where((s < 0)[:, None], frames[0, 2], frames[-1, 2])
    bounds = np.stack([np.interp(sc, knots, sides[:, i]) for i in range(4)], axis=1)
    return centre, rot, bounds


def held(d, points: np.ndarray, *, chunk: int = 1024) -> np.ndarray:
    """For each physical point (N, 3), whether the cage of ``d`` holds it where the map does not fold."""
    points = np.asarray(points, dtype=float)
    step = min(d.spacing) / 4
    centre, rot, bounds = _sampled(d, step)
    reach = float(np.hypot(np.abs(bounds[:, :2]).max(), np.abs(bounds[:, 2:]).max())) + 2 * step
    out = np.zeros(len(points), bool)
    for a in range(0, len(points), chunk):
        p = points[a:a + chunk]
        # the cross-sections that can hold a point of this chunk: centre within reach of the chunk's box
        near = np.all((centre >= p.min(axis=0) - reach) & (centre <= p.max(axis=0) + reach), axis=1)
        near[:-1] |= near[1:]
        k = np.flatnonzero(near)
        if len(k) < 2:
            continue
        rel = p[:, None, :] - centre[None, k, :]                        # (m, K, 3)
        x, y, g = (np.einsum("mkc,kc->mk", rel, rot[k, i]) for i in range(3))
        pair = np.flatnonzero(np.diff(k) == 1)                          # consecutive samples j, j + 1
        g0, g1 = g[:, pair], g[:, pair + 1]
        falls = (g0 > 0) & (g1 <= 0)
        t = np.where(falls, g0 / np.where(falls, g0 - g1, 1.0), 0.0)
        xr = x[:, pair] + t * (x[:, pair + 1] - x[:, pair])
        yr = y[:, pair] + t * (y[:, pair + 1] - y[:, pair])
        b = bounds[k[pair]] + t[..., None] * (bounds[k[pair + 1]] - bounds[k[pair]])
        inside = falls & (xr >= b[..., 0]) & (xr <= b[..., 1]) & (yr >= b[..., 2]) & (yr <= b[..., 3])
        out[a:a + chunk] = inside.any(axis=1)
    return out


def coverage(d, mask: np.ndarray, spacing, origin=(0.0, 0.0, 0.0)) -> float:
    """Fraction of the voxels of ``mask`` (on a grid of ``spacing`` and ``origin``) that the cage holds unfolded."""
    pts = np.argwhere(np.asarray(mask) != 0) * np.asarray(spacing, float) + np.asarray(origin, float)
    return float(held(d, pts).mean())
