"""Fold-free cages and the figures that say how well a deformation holds its specimen (docs/design.md section 3).

The Jacobian of ``f(x, y, s) = c(s) + x u(s) + y v(s)`` is ``det J = n . c' + y w_x - x w_y`` on each keyframe
segment (``w`` the segment's SLERP rate in the local frame). It is affine in ``(x, y)``, so its minimum over a
cage ``[x_lo, x_hi] x [y_lo, y_hi]`` is at the corner nearest the centre of curvature, and ``n . c'`` is smallest
at the segment's ends. :func:`unfold` shrinks, where ``det J`` would fall below ``eps``, only the inner sides of
the cages at the two keyframes of the segment (the side of the faster rotation first, which gives up the least
cage) (the third way out of docs/design.md section 3; the per-side fit of
:func:`~napari_unwind.skeleton.fit_cages` is the first). Shrinking a side never lowers the Jacobian of the
neighbouring segment, so a few sweeps settle.

:func:`coverage` maps the mask's voxels into the straight box with the compiled inverse and counts those inside
the cage where the map does not fold; the voxels left out are grouped into arclength intervals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..deformation import Deformation, Keyframe

__all__ = ["unfold", "coverage", "held_points", "max_tilt", "Coverage", "format_lost"]


def unfold(d: Deformation, *, eps: float = 0.2, floor: np.ndarray | None = None, max_sweeps: int = 20,
           least: str = "length") -> Deformation:
    """Shrink the inner sides of the cages where ``det J < eps``; returns the deformation (unchanged if none).

    Parameters
    ----------
    d : Deformation
    eps : float
        The smallest Jacobian determinant kept (0 < eps < 1).
    floor : ndarray, shape (m, 4), optional
        Sides ``(x_lo, x_hi, y_lo, y_hi)`` no side is shrunk past (e.g. the tissue's own extent, so that only
        margins are given up); default: none (a side may shrink to the curve).
    max_sweeps : int
        Passes over the segments at most.
    least : {"length", "area"}
        What the split of a corner's deficit between its x and y sides gives up least of: "length" cuts the side
        of the faster rotation first (the least cage depth per unit of J); "area" the side whose cut loses the
        least of the section's area per unit of J (rate over the other side's extent: a tall body's tall side
        first when the bend turns about both frame axes).
    """
    if least not in ("length", "area"):
        raise ValueError(f"least must be 'length' or 'area', got {least!r}")
    bounds = d.bounds.copy()
    # the magnitude a side may shrink to
    keep = np.zeros_like(bounds) if floor is None else np.minimum(np.abs(np.asarray(floor, dtype=float)),
                                                                  np.abs(bounds))
    rates = d._segment_rates()
    knots = d.knots
    seg_dir = np.diff(d.positions, axis=0) / np.diff(knots)[:, None]
    changed = False
    for _ in range(max_sweeps):
        moved = False
        for k in range(len(knots) - 1):
            wx, wy = rates[k, 0], rates[k, 1]
            _, r = d.sample(np.array([knots[k], knots[k + 1]]))
            for end, e in enumerate((k, k + 1)):
                base = float(np.dot(r[end, 2], seg_dir[k]))
                xlo, xhi, ylo, yhi = bounds[e]
                # the inner corner: the x side with the largest x w_y, the y side with the smallest y w_x
                ix = 1 if xhi * wy >= xlo * wy else 0
                iy = 2 if ylo * wx <= yhi * wx else 3
                a = max(0.0, bounds[e, ix] * wy)
                b = max(0.0, -bounds[e, iy] * wx)
                if base - a - b >= eps - 1e-12 or a + b <= 0:
                    continue
                # the deficit comes off the side of the faster rotation first: the least cage lost per unit
                deficit = (a + b) - max(0.0, base - eps) + 1e-12
                before = bounds[e].copy()
                if least == "area":  # depth lost per unit of J, times the length of the side that is cut
                    order = ((ix, abs(wy), a, bounds[e, 3] - bounds[e, 2]),
                             (iy, abs(wx), b, bounds[e, 1] - bounds[e, 0]))
                else:
                    order = ((ix, abs(wy), a, 1.0), (iy, abs(wx), b, 1.0))
                for side, rate, part, _ in sorted(order, key=lambda t: -t[1] / max(t[3], 1e-12)):
                    if deficit <= 0 or part <= 0 or rate <= 0:
                        continue
                    mag = abs(bounds[e, side])
                    cut = min(deficit / rate, mag - min(keep[e, side], mag))
                    bounds[e, side] = np.sign(bounds[e, side]) * (mag - cut)
                    deficit -= cut * rate
                if np.any(bounds[e] != before):
                    moved = changed = True
        if not moved:
            break
    if not changed:
        return d
    # a side shrunk onto the curve keeps a sliver so that the box stays a box
    tiny = 1e-6 * max(1.0, float(np.abs(bounds).max()))
    bounds[:, 1] = np.maximum(bounds[:, 1], bounds[:, 0] + tiny)
    bounds[:, 3] = np.maximum(bounds[:, 3], bounds[:, 2] + tiny)
    kfs = [Keyframe.from_bounds(k.position, k.frame, b) for k, b in zip(d.keyframes, bounds, strict=True)]
    return d._with(kfs)


def max_tilt(d: Deformation, *, step: float | None = None) -> float:
    """The largest angle (degrees) between a cross-section's normal ``n(s)`` and the curve's direction ``c'(s)``."""
    step = step or min(d.spacing) / 2
    s = np.union1d(np.arange(0.0, d.length, step), d.knots)
    _, r = d.sample(s)
    k = d.segment_of(s)
    seg_dir = np.diff(d.positions, axis=0) / np.diff(d.knots)[:, None]
    cos = np.clip(np.einsum("ij,ij->i", r[:, 2], seg_dir[k]), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).max())


@dataclass(frozen=True)
class Coverage:
    """How much of a mask a deformation holds.

    Attributes
    ----------
    fraction : float
        Mask voxels inside the cage where ``det J > 0``, over all mask voxels.
    lost : tuple of (s_start, s_end, fraction)
        Arclength intervals (physical units) whose nearby mask voxels are left out, with the fraction of the
        whole mask each loses.
    folded : float
        Fraction of the mask's voxels that lie where the map folds (``det J <= 0``).
    """

    fraction: float
    lost: tuple[tuple[float, float, float], ...]
    folded: float


def held_points(d: Deformation, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which of the physical ``points`` (N, 3) the deformation holds (inside the cage, where its Jacobian is
    positive) and which lie inside it where it folds (J <= 0); two bool arrays (N,)."""
    from ..warp import _fast_inverse

    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    xys, inside = _fast_inverse(d, pts)
    det = np.full(len(pts), -1.0)
    ok = np.isfinite(xys[:, 2])
    det[ok] = d.jacobian(xys[ok])
    return inside & (det > 0), inside & (det <= 0)


def coverage(d: Deformation, points: np.ndarray, *, weights: np.ndarray | None = None, bin_width: float | None = None
             ) -> Coverage:
    """The coverage of mask voxels at physical positions ``points`` (N, 3) by the deformation ``d``.

    ``weights`` (N,) weigh the voxels (e.g. the occupancy of working voxels; default 1). Lost voxels are
    binned by the arclength of their nearest curve point, ``bin_width`` wide (default 2 voxels), and
    consecutive bins are merged into intervals.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    w = np.ones(len(pts)) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    total = float(w.sum())
    if total <= 0:
        return Coverage(1.0, (), 0.0)
    held, folded = held_points(d, pts)
    lost = ~held
    intervals: list[tuple[float, float, float]] = []
    if lost.any():
        step = bin_width or 2 * max(d.spacing)
        lo, hi = d.s_range
        s_dense = np.arange(lo, hi + step / 2, step / 4)
        c, _ = d.sample(s_dense)
        from scipy.spatial import cKDTree

        _, nearest = cKDTree(c).query(pts[lost])
        s_lost = np.clip(s_dense[nearest], lo, hi)  # s_dense runs past hi: keep those voxels in the last bin
        edges = np.arange(lo, hi + step, step)
        hist, _ = np.histogram(s_lost, bins=edges, weights=w[lost])
        i = 0
        while i < len(hist):
            if hist[i] > 0:
                j = i
                while j + 1 < len(hist) and hist[j + 1] > 0:
                    j += 1
                intervals.append((float(edges[i]), float(min(edges[j + 1], hi)), float(hist[i:j + 1].sum() / total)))
                i = j + 1
            else:
                i += 1
    return Coverage(float(w[held].sum() / total), tuple(intervals), float(w[folded].sum() / total))


def format_lost(lost: tuple[tuple[float, float, float], ...], unit: str, *, top: int = 3) -> str:
    """The largest lost intervals as text: ``s = a..b (f %)``."""
    if not lost:
        return "none"
    worst = sorted(lost, key=lambda t: -t[2])[:top]
    text = ", ".join(f"s = {a:.4g}..{b:.4g} {unit} ({100 * f:.2g} %)" for a, b, f in sorted(worst))
    more = len(lost) - len(worst)
    return text + (f" and {more} more" if more > 0 else "")


def tilted_frames(frames: np.ndarray, arclength: np.ndarray, keys: np.ndarray, sigma: np.ndarray, *,
                  twist: np.ndarray | None = None, confidence: np.ndarray | None = None) -> np.ndarray:
    """Keyframe frames whose normals are the dense tangents smoothed over a Gaussian of width ``sigma`` (per
    keyframe, arclength units; 0 keeps the frame).

    Each frame's ``u`` is the dense frame's turned by the minimal rotation onto its new normal (the *absolute*
    choice: where the twist was read from the cross-sections, ``v`` stays as near the dorsal direction as the
    tilted plane allows). With ``twist`` and ``confidence`` (dense, as the twist estimate gives them) ``u`` is
    instead carried from one keyframe to the next by the minimal rotation between their own normals, turned by
    the twist's increment, and pulled toward the absolute choice by the confidence at the keyframe (docs/design.md
    section 3): where the twist is not read (a round vessel) the straight sections do not spin about their own
    normals, which the absolute choice makes them do wherever the tilt varies (the minimal rotation along the
    dense tangents is not the minimal rotation along the tilted normals: up to 40 degrees within 10 voxels on
    round tubes with a tight bend).

    Parameters
    ----------
    frames : ndarray, shape (K, 3, 3)
        Dense frames (rows u, v, n) along the curve.
    arclength : ndarray, shape (K,)
        Arclength of the dense points.
    keys : ndarray of int, shape (m,)
        Indices of the keyframes.
    sigma : ndarray, shape (m,)
        Smoothing width per keyframe.
    twist, confidence : ndarray, shape (K,), optional
        The twist (radians) that turned the dense frames about the curve, and its confidence in [0, 1].

    Returns
    -------
    frames : ndarray, shape (m, 3, 3)
    """
    from ..deformation import _min_rotation

    out = frames[keys].copy()
    tangents = frames[:, 2]
    for i, (k, sg) in enumerate(zip(keys, sigma, strict=True)):
        if sg <= 0:
            continue
        w = np.exp(-0.5 * ((arclength - arclength[k]) / sg) ** 2)
        n = (w[:, None] * tangents).sum(axis=0)
        if np.linalg.norm(n) < 1e-9:
            continue
        n /= np.linalg.norm(n)
        rot = _min_rotation(out[i, 2], n)
        u = rot @ out[i, 0]
        u -= np.dot(u, n) * n
        u /= np.linalg.norm(u)
        out[i] = (u, np.cross(n, u), n)
    if twist is None or confidence is None:
        return out
    theta = np.asarray(twist, dtype=float)[keys]
    conf = np.clip(np.asarray(confidence, dtype=float)[keys], 0.0, 1.0)
    carried = out.copy()
    for i in range(1, len(out)):
        n = out[i, 2]
        u = _min_rotation(carried[i - 1, 2], n) @ carried[i - 1, 0]
        u -= np.dot(u, n) * n
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        turn = theta[i] - theta[i - 1]  # the twist's increment (apply_twist's sense: u toward v)
        u, v = np.cos(turn) * u + np.sin(turn) * v, -np.sin(turn) * u + np.cos(turn) * v
        if conf[i] > 0:  # toward the absolute choice, as far as the cross-section is trusted
            off = np.arctan2(np.dot(np.cross(u, out[i, 0]), n), np.dot(u, out[i, 0])) * conf[i]
            u, v = np.cos(off) * u + np.sin(off) * v, -np.sin(off) * u + np.cos(off) * v
        u /= np.linalg.norm(u)
        carried[i] = (u, np.cross(n, u), n)
    return carried
