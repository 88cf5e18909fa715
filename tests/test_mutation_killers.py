"""Tests written for mutants that survived the mutation-testing pass (docs/testing-mutation.md).

Each test names the mutant(s) it kills; every expected value comes from an analytic construction, never from the
code under test.
"""

from __future__ import annotations

import numpy as np
import pytest

from napari_unwind.deformation import Deformation
from napari_unwind.skeleton import regularise_ends, resample_curve, select_keyframes
from napari_unwind.skeleton._curve import arclength


# ------------------------------------------------------------------------------------------------------------------
# skeleton/_curve.py
# ------------------------------------------------------------------------------------------------------------------
def _circle_with_exact_frames(radius: float, angle: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A planar arc (K, 3) and its analytic frames (K, 3, 3): u the binormal, n the tangent, v = n x u."""
    th = np.linspace(0.0, angle, n)
    pts = np.stack([radius * np.sin(th), radius * (1 - np.cos(th)) + 5.0, np.full_like(th, 7.0)], axis=1)
    n_ = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=1)
    u = np.broadcast_to([0.0, 0.0, 1.0], n_.shape)
    return pts, np.stack([u, np.cross(n_, u), n_], axis=1)


@pytest.mark.parametrize(("tol", "depth"), [(1.0, 3), (0.2, 4)])
def test_keyframes_on_a_circle_halve_until_the_sagitta_fits(tol, depth):
    # Between two keyframes on a circle the SLERPed frame is exactly the circle's (both turn uniformly with the
    # arclength), so every box point strays by the chord-to-arc distance, largest mid-way: the sagitta
    # R (1 - cos(delta / 2)) of a sub-arc of angle delta. The worst point of each piece is its middle sample, so
    # the pieces halve until R (1 - cos(pi / 2^(d + 1))) <= tol: 30 (1 - cos(pi / 8)) = 2.28 > 1 >=
    # 30 (1 - cos(pi / 16)) = 0.58 > 0.2 >= 30 (1 - cos(pi / 32)) = 0.14.
    # Kills: lam = (s - s[a]) / (s[b] + s[a]); c = (1 + lam) p[a] + ...; c = (2 - lam) p[a] + ...;
    # Slerp([0, 2], ...) (the arc does not start at the origin, and the pieces after the first are checked).
    radius, angle = 30.0, np.pi
    assert radius * (1 - np.cos(angle / 2 ** depth)) > tol >= radius * (1 - np.cos(angle / 2 ** (depth + 1)))
    pts, frames = _circle_with_exact_frames(radius, angle, 257)
    idx = select_keyframes(pts, frames, radius=10.0, tolerance=tol)
    np.testing.assert_array_equal(idx, np.arange(0, 257, 256 // 2 ** depth))


@pytest.mark.parametrize(("factor", "expected"), [(1.02, [0, 128]), (0.98, [0, 64, 128])])
def test_a_twist_splits_exactly_when_the_box_corners_stray_by_the_tolerance(factor, expected):
    # A straight line whose frame twists about the tangent by phi(s) = A sin(pi s / L), zero at both ends: one
    # SLERP keeps the frame fixed, and a corner r (+-u +-v) (|.| = r sqrt 2) of the box strays by
    # 2 r sqrt(2) sin(A / 2) mid-way. Halved, each piece strays by much less (phi departs from linear by 0.21 A).
    # Kills: u, v = frames[:, 1], frames[:, 1] (2 r instead of r sqrt 2) and u, v = frames[:, 0], frames[:, 2]
    # (r: the tangent does not turn).
    n, length, r, a = 129, 64.0, 10.0, 0.2
    s = np.linspace(0.0, length, n)
    line = np.stack([s, np.zeros(n), np.zeros(n)], axis=1)
    phi = a * np.sin(np.pi * s / length)
    y, z, x = np.eye(3)[1], np.eye(3)[2], np.eye(3)[0]
    u = np.cos(phi)[:, None] * y + np.sin(phi)[:, None] * z
    v = -np.sin(phi)[:, None] * y + np.cos(phi)[:, None] * z
    frames = np.stack([u, v, np.broadcast_to(x, u.shape)], axis=1)
    worst = 2 * r * np.sqrt(2) * np.sin(a / 2)
    idx = select_keyframes(line, frames, radius=r, tolerance=factor * worst)
    np.testing.assert_array_equal(idx, expected)


def test_regularise_ends_treats_the_tail_as_the_head():
    # The tail is regularised exactly as the head: running the curve backwards gives the same curve backwards,
    # and a kink at the tail alone is removed. Kills: for dist in (s, total + s) (the tail never fitted).
    th = np.linspace(0.0, 1.5, 121)
    arc = np.stack([40 * np.sin(th), 40 * (1 - np.cos(th)), np.zeros_like(th)], axis=1)
    s = arclength(arc)
    kinked = arc.copy()
    tip = s[-1] - s < 3.0
    kinked[tip] += np.array([0.0, 0.0, 2.0]) * (1 - (s[-1] - s[tip, None]) / 3.0)  # a 2-unit wander at the tail
    out = regularise_ends(kinked, 8.0)
    np.testing.assert_allclose(regularise_ends(kinked[::-1], 8.0)[::-1], out, atol=1e-9)

    def curvature(p):  # turning angle per unit length (the points are 0.5 apart)
        t = np.diff(p, axis=0)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        return np.arccos(np.clip(np.sum(t[1:] * t[:-1], axis=1), -1, 1)) / 0.5

    # the kink (curvature ~1 per unit) is gone: the tail bends no more than a few times the arc's 1/40
    assert curvature(kinked).max() > 0.3
    assert curvature(out).max() < 3 / 40.0


def test_resample_default_step_is_half_the_smallest_segment_and_min_step_wins():
    # Segments of 2 and 4: the default step is 1, so 7 points one unit apart along the L; min_step = 2 gives 4.
    # Kills: step = 0.5 / min(segment) (25 points) and min_step ignored.
    pts = np.array([[0.0, 0, 0], [2, 0, 0], [2, 4, 0]])
    expected = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 1, 0], [2, 2, 0], [2, 3, 0], [2, 4, 0]], float)
    np.testing.assert_allclose(resample_curve(pts), expected, atol=1e-12)
    np.testing.assert_allclose(resample_curve(pts, min_step=2.0), expected[::2], atol=1e-12)


# ------------------------------------------------------------------------------------------------------------------
# deformation.py
# ------------------------------------------------------------------------------------------------------------------
def test_voxel_geometry_with_anisotropic_spacing_and_an_origin():
    # A straight cage along axis0 from (10, 0, 0) to (30, 0, 0) (L = 20), u = axis1, v = axis2, (rx, ry) = (3, 2),
    # in a scan of spacing (2, 0.5, 4) and origin (10, -4, 3); every number below follows from those by hand.
    # Kills: to_voxels (p + origin) / spacing; output_shape off by one (+-1, -1e-9 instead of +1e-9, ceil(r / ds +
    # 1e-9), * ds); slice_geometry in voxels with * spacing or + origin.
    spacing, origin = (2.0, 0.5, 4.0), (10.0, -4.0, 3.0)
    frame = np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]])  # rows u, v, n (u x v = n)
    d = Deformation.from_keyframes([[10.0, 0, 0], [30, 0, 0]], [frame, frame], (3.0, 2.0), spacing=spacing,
                                   origin=origin)
    np.testing.assert_allclose(d.to_voxels([[10.0, -4, 3], [14, -3, 11]]), [[0, 0, 0], [2, 2, 2]])
    np.testing.assert_allclose(d.to_physical([[2.0, 2, 2]]), [[14, -3, 11]])
    # the straight grid at ds (default: the finest spacing, 0.5): L / ds + 1 slices, 2 ry / ds + 1 rows,
    # 2 rx / ds + 1 columns, the cage's edges on the outermost pixels
    assert d.output_shape() == (41, 9, 13)
    assert d.output_shape(0.25) == (81, 17, 25)
    assert d.output_shape(0.3) == (67, 15, 21)  # 66.7 -> 66 steps; ceil(6.7) = 7, ceil(10) = 10 on each side
    # slice k: pixel (0, 0) at (10 + 0.5 k, 0, 0) - 4 ds v - 6 ds u = (10 + 0.5 k, -3, -2), in voxels
    # ((0.5 k) / 2, (-3 + 4) / 0.5, (-2 - 3) / 4); a row step is ds v, a column step ds u
    k = np.arange(41)
    base, dv, du = d.slice_geometry()
    np.testing.assert_allclose(base, np.stack([0.25 * k, np.full(41, 2.0), np.full(41, -1.25)], axis=1), atol=1e-12)
    np.testing.assert_allclose(dv, np.tile([0.0, 0.0, 0.125], (41, 1)), atol=1e-12)
    np.testing.assert_allclose(du, np.tile([0.0, 1.0, 0.0], (41, 1)), atol=1e-12)
    base, dv, du = d.slice_geometry(voxels=False)
    np.testing.assert_allclose(base, np.stack([10 + 0.5 * k, np.full(41, -3.0), np.full(41, -2.0)], axis=1),
                               atol=1e-12)
    np.testing.assert_allclose(dv, np.tile([0.0, 0.0, 0.5], (41, 1)), atol=1e-12)
    np.testing.assert_allclose(du, np.tile([0.0, 0.5, 0.0], (41, 1)), atol=1e-12)


def test_the_jacobian_is_one_in_the_padding_even_where_the_cage_folds():
    # A quarter circle of radius R with a cage of 2R: inside, the cage folds (det = 1 - 2R / R = -1, bent in the
    # plane of v); in the padding the box is carried rigidly along the end normal, so det = 1 there.
    # Kills: every change to the "outside [0, L]" mask (None, & for |, <= 0, < 1, >= L) and 2.0 for 1.0.
    radius = 10.0
    pts, frames = _circle_with_exact_frames(radius, np.pi / 2, 65)  # v in the plane of the bend
    d = Deformation.from_keyframes(pts, frames, 2 * radius, pad=5.0)
    length = d.length
    jm = d.jacobian_min(np.array([-3.0, -1e-6, 0.0, 0.5 * length, length, length + 1e-6, length + 3.0]))
    np.testing.assert_array_equal(jm[[0, 1, 5, 6]], 1.0)
    np.testing.assert_allclose(jm[[2, 3, 4]], -1.0, atol=0.02)


def test_tilt_about_v_and_resize_every_keyframe():
    # Frame rows u = axis1, v = axis2, n = axis0. A quarter turn about v (axis2, right-handed) takes axis0 to axis1
    # and axis1 to -axis0: u -> -axis0, n -> axis1, v unchanged. resize_keyframe(None, ...) sets every keyframe,
    # resize_keyframe(i, ...) only keyframe i.
    # Kills: tilt about v done about n or about u; resize with i=None failing or resizing the wrong keyframes.
    frame = np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]])
    d = Deformation.from_keyframes([[0.0, 0, 0], [10, 0, 0], [20, 0, 0]], [frame] * 3, (3.0, 2.0))
    tilted = d.tilt_keyframe(1, np.pi / 2, axis="v")
    np.testing.assert_allclose(tilted.keyframes[1].frame, [[-1, 0, 0], [0, 0, 1], [0, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(tilted.keyframes[0].frame, frame)
    assert [k.half_extent for k in d.resize_keyframe(None, (4.0, 5.0)).keyframes] == [(4.0, 5.0)] * 3
    assert [k.half_extent for k in d.resize_keyframe(1, 2.0).keyframes] == [(3.0, 2.0), (2.0, 2.0), (3.0, 2.0)]
