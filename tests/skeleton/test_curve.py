"""Smoothing, resampling and keyframe selection against analytic curves."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from napari_unwind.deformation import parallel_transport_frames
from napari_unwind.errors import InvalidInputError
from napari_unwind.skeleton import regularise_ends, resample_curve, select_keyframes, smooth_curve
from napari_unwind.skeleton._curve import arclength


def _arc(radius=30.0, angle=np.pi, n=100):
    t = np.linspace(0, angle, n)
    return np.stack([radius * np.sin(t), radius * (1 - np.cos(t)), np.zeros_like(t)], axis=1)


def test_laplacian_smoothing_shrinks_a_bend_and_taubin_does_not():
    pts = _arc()
    centre = np.array([0.0, 30.0, 0.0])
    lap = smooth_curve(pts, iterations=50, method="laplacian")
    tau = smooth_curve(pts, iterations=50, method="taubin")
    r_lap = np.linalg.norm(lap - centre, axis=1)[10:-10]
    r_tau = np.linalg.norm(tau - centre, axis=1)[10:-10]
    # each plain step moves a point by h^2 / (2 R) inwards (h = 30 pi / 99): the bend shrinks visibly
    assert (30.0 - r_lap).max() > 0.2
    assert np.abs(r_tau - 30.0).max() < 0.5 * (30.0 - r_lap).max()
    np.testing.assert_array_equal(lap[[0, -1]], pts[[0, -1]])  # ends fixed
    np.testing.assert_array_equal(tau[[0, -1]], pts[[0, -1]])


@pytest.mark.parametrize(("method", "factor"), [("taubin", 0.6), ("laplacian", 0.4)])
def test_smoothing_removes_noise(method, factor):
    rng = np.random.default_rng(1)
    t = np.linspace(0, 100, 101)
    line = np.stack([t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    noisy = line + rng.normal(0, 0.7, line.shape) * [0, 1, 1]
    noisy[[0, -1]] = line[[0, -1]]
    out = smooth_curve(noisy, iterations=50, method=method)
    assert np.abs(out[:, 1:]).std() < factor * np.abs(noisy[:, 1:]).std()


def test_smoothing_validates():
    with pytest.raises(InvalidInputError, match="unknown smoothing"):
        smooth_curve(_arc(), method="gauss")
    with pytest.raises(InvalidInputError, match=">= 0"):
        smooth_curve(_arc(), iterations=-1)
    with pytest.raises(InvalidInputError, match="shape"):
        smooth_curve(np.zeros((4, 2)))


def test_resample_is_uniform_and_keeps_the_ends():
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [1, 3, 0], [1, 3, 4]])
    out = resample_curve(pts)  # half the smallest segment: 0.5
    np.testing.assert_array_equal(out[[0, -1]], pts[[0, -1]])
    seg = np.linalg.norm(np.diff(out, axis=0), axis=1)
    assert seg.max() <= 0.5 + 1e-9
    assert arclength(out)[-1] == pytest.approx(8.0)
    # every resampled point lies on the polyline
    assert np.allclose(out[:, 2] * (out[:, 1] < 3), 0)
    assert len(resample_curve(pts, step=0.01, max_points=100)) == 100
    with pytest.raises(InvalidInputError, match="zero length"):
        resample_curve(np.zeros((3, 3)))


def _interp_boxes(points, frames, idx, r):
    """Dense boxes of the keyframe interpolation, computed here with scipy directly."""
    s = arclength(points)
    out = []
    for a, b in zip(idx[:-1], idx[1:], strict=True):
        seg = np.arange(a, b + 1)
        lam = (s[seg] - s[a]) / (s[b] - s[a])
        c = (1 - lam)[:, None] * points[a] + lam[:, None] * points[b]
        rot = Slerp([0, 1], Rotation.from_matrix(np.transpose(frames[[a, b]], (0, 2, 1))))(lam).as_matrix()
        u, v = rot[:, :, 0], rot[:, :, 1]
        out.append((seg, np.stack([c, c + r * (u + v), c - r * (u + v), c + r * (u - v), c - r * (u - v)], 1)))
    return out


@pytest.mark.parametrize("tol", [0.25, 0.5, 2.0])
def test_keyframes_reproduce_the_dense_boxes(tol):
    pts = _arc(n=200)
    frames = parallel_transport_frames(pts)
    idx = select_keyframes(pts, frames, radius=10.0, tolerance=tol)
    assert idx[0] == 0 and idx[-1] == len(pts) - 1 and (np.diff(idx) > 0).all()
    u, v = frames[:, 0], frames[:, 1]
    r = 10.0
    dense = np.stack([pts, pts + r * (u + v), pts - r * (u + v), pts + r * (u - v), pts - r * (u - v)], 1)
    worst = max(np.linalg.norm(box - dense[seg], axis=2).max() for seg, box in _interp_boxes(pts, frames, idx, r))
    assert worst <= tol + 1e-9


def test_fewer_keyframes_for_looser_tolerance_and_two_on_a_straight_line():
    pts = _arc(n=200)
    frames = parallel_transport_frames(pts)
    counts = [len(select_keyframes(pts, frames, radius=10.0, tolerance=t)) for t in (0.1, 0.5, 2.0)]
    assert counts[0] > counts[1] > counts[2]
    line = np.stack([np.linspace(0, 50, 60), np.zeros(60), np.zeros(60)], 1)
    assert len(select_keyframes(line, parallel_transport_frames(line), radius=10.0, tolerance=0.1)) == 2


def test_twist_alone_needs_keyframes():
    # a straight line whose frames turn by 270 degrees: one SLERP cannot turn more than 180
    line = np.stack([np.linspace(0, 90, 91), np.zeros(91), np.zeros(91)], 1)
    frames = parallel_transport_frames(line)
    th = np.linspace(0, 1.5 * np.pi, 91)[:, None]
    u, v = frames[:, 0].copy(), frames[:, 1].copy()
    frames[:, 0], frames[:, 1] = np.cos(th) * u + np.sin(th) * v, -np.sin(th) * u + np.cos(th) * v
    idx = select_keyframes(line, frames, radius=10.0, tolerance=0.5)
    assert len(idx) >= 3  # a linear twist is reproduced exactly by SLERP steps of less than 180 degrees
    assert np.diff(th[idx, 0]).max() < np.pi
    u, v = frames[:, 0], frames[:, 1]
    dense = np.stack([line, line + 10 * (u + v), line - 10 * (u + v), line + 10 * (u - v), line - 10 * (u - v)], 1)
    worst = max(np.linalg.norm(box - dense[seg], axis=2).max() for seg, box in _interp_boxes(line, frames, idx, 10.0))
    assert worst <= 0.5


def test_regularise_ends_removes_an_end_kink_and_keeps_the_bend():
    arc = resample_curve(_arc(radius=40.0, angle=1.5), step=0.5)
    kinked = arc.copy()
    s = arclength(arc)
    kinked[s < 3.0] += np.array([0.0, 0.0, 2.0]) * (1 - s[s < 3.0, None] / 3.0)  # a 2-voxel wander at the tip
    out = regularise_ends(kinked, 8.0)

    def curvature(p):
        t = np.diff(p, axis=0)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        return np.arccos(np.clip(np.sum(t[1:] * t[:-1], axis=1), -1, 1)) / 0.5

    # the kink (curvature ~1 per voxel) is gone: the ends bend no more than a few times the arc's 1/40
    assert curvature(kinked).max() > 0.3
    assert curvature(out).max() < 3 / 40.0
    # and the curve stays within the kink's size of the circle
    centre = np.array([0.0, 40.0, 0.0])
    assert np.abs(np.linalg.norm(out - centre, axis=1) - 40.0).max() < 2.0
    # away from the ends nothing moved
    np.testing.assert_array_equal(out[(s > 16.0) & (s < s[-1] - 16.0)], kinked[(s > 16.0) & (s < s[-1] - 16.0)])
    np.testing.assert_array_equal(regularise_ends(kinked, 0.0), kinked)


# ------------------------------------------------------------------------------------------------------------------
# Edge cases written for the survivors of the mutation pass (docs/testing-mutation.md, skeleton/_curve.py). Every
# expected value is worked out by hand or computed here from the docstrings' definitions.
# ------------------------------------------------------------------------------------------------------------------
def test_arclength_of_a_hand_worked_polyline():
    pts = np.array([[0.0, 0, 0], [3, 4, 0], [3, 4, 12], [3, 4, 12]])
    np.testing.assert_array_equal(arclength(pts), [0.0, 5.0, 17.0, 17.0])
    np.testing.assert_array_equal(arclength(pts[:1]), [0.0])


def test_one_smoothing_iteration_worked_by_hand():
    # three points (0,0,0), (1,1,0), (2,0,0): the middle one moves towards the mean of its neighbours (1, 0, 0).
    # Laplacian: to it. Taubin: lambda 0.5 takes y to 0.5, then mu -0.53 to 0.5 + 0.53 * 0.5 = 0.765.
    pts = np.array([[0.0, 0, 0], [1, 1, 0], [2, 0, 0]])
    np.testing.assert_allclose(smooth_curve(pts, iterations=1, method="laplacian"), [[0, 0, 0], [1, 0, 0], [2, 0, 0]],
                               atol=1e-15)
    np.testing.assert_allclose(smooth_curve(pts, iterations=1), [[0, 0, 0], [1, 0.765, 0], [2, 0, 0]], atol=1e-15)
    # two Laplacian iterations on four points move both inner points at once (Jacobi, not one after the other):
    # y = (0, 1, 1, 0) -> (0, 0.5, 0.5, 0) -> (0, 0.25, 0.25, 0)
    four = np.array([[0.0, 0, 0], [1, 1, 0], [2, 1, 0], [3, 0, 0]])
    out = smooth_curve(four, iterations=2, method="laplacian")
    np.testing.assert_allclose(out[:, 1], [0, 0.25, 0.25, 0], atol=1e-15)
    np.testing.assert_array_equal(out[:, 0], [0, 1, 2, 3])
    np.testing.assert_array_equal(four[:, 1], [0, 1, 1, 0])  # the input is not touched


def test_smoothing_zero_iterations_and_two_points_leave_the_curve_alone():
    pts = _arc(n=7)
    out = smooth_curve(pts, iterations=0)
    np.testing.assert_array_equal(out, pts)
    assert out is not pts
    two = np.array([[0.0, 0, 0], [1, 2, 3]])
    np.testing.assert_array_equal(smooth_curve(two, iterations=5), two)
    np.testing.assert_array_equal(smooth_curve(two, iterations=5, method="laplacian"), two)
    assert smooth_curve([[0, 0, 0], [1, 1, 0], [2, 0, 0]], iterations=1, method="laplacian").dtype == float


def test_smoothing_error_messages():
    with pytest.raises(InvalidInputError) as info:
        smooth_curve(np.zeros((4, 2)))
    assert str(info.value) == "points must have shape (K, 3), got (4, 2)"
    with pytest.raises(InvalidInputError) as info:
        smooth_curve(np.zeros(3))
    assert str(info.value) == "points must have shape (K, 3), got (3,)"
    with pytest.raises(InvalidInputError) as info:
        smooth_curve(_arc(), iterations=-1)
    assert str(info.value) == "smoothing iterations must be >= 0, got -1"
    with pytest.raises(InvalidInputError) as info:
        smooth_curve(_arc(), method="gauss")
    assert str(info.value) == "unknown smoothing method 'gauss'; use 'taubin' or 'laplacian'"


def test_resample_a_straight_segment_and_the_step_rules():
    seg = np.array([[0.0, 0, 0], [3, 0, 0]])
    # default: half the only segment, 1.5
    np.testing.assert_allclose(resample_curve(seg), [[0, 0, 0], [1.5, 0, 0], [3, 0, 0]], atol=1e-15)
    # a step that does not divide the length: ceil(3 / 0.7) = 5 pieces of 0.6
    np.testing.assert_allclose(resample_curve(seg, step=0.7)[:, 0], np.arange(6) * 0.6, atol=1e-12)
    np.testing.assert_allclose(resample_curve(seg, step=1)[:, 0], [0, 1, 2, 3], atol=1e-15)
    # a step longer than the curve keeps the two ends
    np.testing.assert_array_equal(resample_curve(seg, step=10.0), seg)
    np.testing.assert_array_equal(resample_curve(seg, min_step=10.0), seg)
    # max_points: 10 long, at most 11 points -> a step of 1
    long = np.array([[0.0, 0, 0], [0, 10, 0]])
    np.testing.assert_allclose(resample_curve(long, step=0.001, max_points=11)[:, 1], np.arange(11.0), atol=1e-12)
    np.testing.assert_allclose(resample_curve(long, step=2.5, max_points=11)[:, 1], [0, 2.5, 5, 7.5, 10], atol=1e-12)
    # the default max_points is 4000: 3999 long with a step of 0.5 comes out 1 apart
    out = resample_curve(np.array([[0.0, 0, 0], [3999, 0, 0]]), step=0.5)
    assert len(out) == 4000
    np.testing.assert_allclose(out[:, 0], np.arange(4000.0), atol=1e-9)


def test_resample_drops_repeated_points_before_taking_the_smallest_segment():
    # segments 0, 0.5e-9 (both repeats), 2 and 0.25: the default step is 0.125, not 0 or 0.25e-9
    pts = np.array([[0.0, 0, 0], [0, 0, 0], [0, 0, 5e-10], [2, 0, 0], [2, 0.25, 0]])
    out = resample_curve(pts)
    assert len(out) == 19  # 2.25 / 0.125 = 18 pieces
    np.testing.assert_allclose(out[[0, 16, 17, 18]], [[0, 0, 0], [2, 0, 0], [2, 0.125, 0], [2, 0.25, 0]], atol=1e-9)
    # segments of 1e-9 or less count as repeats; a segment of 2e-9 is kept
    np.testing.assert_allclose(resample_curve(np.array([[0.0, 0, 0], [2e-9, 0, 0]]))[:, 0], [0, 1e-9, 2e-9], rtol=1e-12)
    with pytest.raises(InvalidInputError, match="zero length"):
        resample_curve(np.array([[0.0, 0, 0], [1e-9, 0, 0]]))
    with pytest.raises(InvalidInputError) as info:
        resample_curve(np.array([[1.0, 2, 3], [1, 2, 3 + 1e-10]]))
    assert str(info.value) == "the curve has zero length: the head and the tail coincide"
    with pytest.raises(InvalidInputError, match="zero length"):
        resample_curve(np.array([[1.0, 2, 3]]))


def test_box_corners_worked_by_hand():
    from napari_unwind.skeleton._curve import _box_corners

    c = np.array([[1.0, 2.0, 3.0]])
    frames = np.eye(3)[None]  # u = x, v = y, n = z
    expected = [[1, 2, 3], [3, 4, 3], [3, 0, 3], [-1, 0, 3], [-1, 4, 3]]  # c, c + r(u + v), c + r(u - v), ...
    np.testing.assert_array_equal(_box_corners(c, frames, 2.0), [expected])


def _fixed_frames(n):
    return np.broadcast_to(np.eye(3), (n, 3, 3)).copy()


def test_select_keyframes_checks_every_piece_down_to_a_single_inner_point():
    # With one fixed frame the box strays exactly as its centre does, |chord(lambda) - p|. On this zigzag every inner
    # point is off every chord, so a tiny tolerance keeps every point. The first split is at point 4 (it strays
    # most from the chord 0-5): the piece (4, 5) has no inner point and is popped before (0, 4), which still
    # needs three splits. A 3-point corner keeps its middle point; 2 points are their own keyframes.
    zig = np.array([[0.0, 0, 0], [1, 1, 0], [2, 0, 0], [3, 1, 0], [4, 6, 0], [5, 0, 0]])
    np.testing.assert_array_equal(select_keyframes(zig, _fixed_frames(6), radius=1.0, tolerance=1e-6), np.arange(6))
    corner = np.array([[0.0, 0, 0], [1, 1, 0], [2, 0, 0]])
    np.testing.assert_array_equal(select_keyframes(corner, _fixed_frames(3), radius=1.0, tolerance=0.99), [0, 1, 2])
    # the middle point strays by exactly 1 (the chord's midpoint is (1, 0, 0)): a tolerance of 1 keeps the ends only
    np.testing.assert_array_equal(select_keyframes(corner, _fixed_frames(3), radius=1.0, tolerance=1.0), [0, 2])
    np.testing.assert_array_equal(select_keyframes(corner[:2], _fixed_frames(2), radius=1.0, tolerance=1.0), [0, 1])


def test_select_keyframes_error_messages():
    pts = _arc(n=5)
    frames = parallel_transport_frames(pts)
    with pytest.raises(InvalidInputError) as info:
        select_keyframes(pts[:1], frames[:1], radius=1.0, tolerance=1.0)
    assert str(info.value) == "a curve needs at least 2 points, got 1"
    for radius, tol in ((0.0, 1.0), (1.0, 0.0), (-1.0, 1.0), (1.0, -1.0)):
        with pytest.raises(InvalidInputError) as info:
            select_keyframes(pts, frames, radius=radius, tolerance=tol)
        assert str(info.value) == f"radius and tolerance must be > 0, got {radius} and {tol}"


def _regularised_by_the_definition(points, window):
    """regularise_ends from its docstring: a least-squares quadratic in arclength over [0, 2 window] of each end
    (solved here with lstsq on the Vandermonde matrix), weight 1 up to window and falling linearly to 0 at 2 window;
    window at most a quarter of the length, nothing done under 8 points or when an end has fewer than 4 points."""
    pts = np.array(points, dtype=float)
    s = np.concatenate([[0.0], np.cumsum(np.sqrt((np.diff(pts, axis=0) ** 2).sum(axis=1)))])
    window = min(window, s[-1] / 4)
    out = pts.copy()
    if window <= 0 or len(pts) < 8:
        return out
    for d in (s, s[-1] - s):
        on = np.flatnonzero(d <= 2 * window)
        if len(on) < 4:
            continue
        a = np.stack([np.ones(len(on)), d[on], d[on] ** 2], axis=1)
        coef = np.linalg.lstsq(a, pts[on], rcond=None)[0]
        for j, i in enumerate(on):
            w = 1.0 if d[i] <= window else (2 * window - d[i]) / window
            out[i] = w * (a[j] @ coef) + (1 - w) * pts[i]
    return out


def _noisy_helix(n, seed=3, noise=0.3):
    t = np.linspace(0.0, 4.0, n)
    helix = np.stack([5 * np.cos(t), 5 * np.sin(t), 2 * t], axis=1)
    return helix + np.random.default_rng(seed).normal(0, noise, helix.shape)


@pytest.mark.parametrize("window", [1.5, 3.0, 100.0])
def test_regularise_ends_equals_its_definition_on_a_noisy_helix(window):
    # the helix is about 21.5 long: 100 is capped to a quarter of it
    pts = _noisy_helix(80)
    out = regularise_ends(pts, window)
    np.testing.assert_allclose(out, _regularised_by_the_definition(pts, window), rtol=0, atol=1e-9)
    assert np.abs(out - pts).max() > 0.05  # something was done


def test_regularise_ends_needs_8_points_and_4_at_each_end():
    eight = _noisy_helix(8, seed=5)
    out = regularise_ends(eight, 100.0)
    np.testing.assert_allclose(out, _regularised_by_the_definition(eight, 100.0), atol=1e-9)
    assert np.abs(out - eight).max() > 0.01
    np.testing.assert_array_equal(regularise_ends(eight[:7], 100.0), eight[:7])
    # points about 1 apart at the head, closer at the tail: a window of 1.1 fits 3 points at the head (left alone)
    # and at least 4 at the tail (regularised)
    x = np.concatenate([np.arange(0.0, 8.0), 7.0 + 0.25 * np.arange(1, 33)])
    pts = np.stack([x, 0.1 * np.sin(3 * x), 0.05 * x ** 2], axis=1)
    s = arclength(pts)
    assert (s <= 2.2).sum() == 3 and (s[-1] - s <= 2.2).sum() >= 4
    out = regularise_ends(pts, 1.1)
    np.testing.assert_allclose(out, _regularised_by_the_definition(pts, 1.1), atol=1e-9)
    np.testing.assert_array_equal(out[:3], pts[:3])
    assert np.abs(out[-4:] - pts[-4:]).max() > 1e-3
    np.testing.assert_array_equal(regularise_ends(pts, -1.0), pts)


def test_regularise_ends_of_voxel_coordinates_and_a_fit_span_ending_on_a_sample():
    # A staircase of integer voxel coordinates (steps of 1 along x, y, z in turn): the arclengths are exact integers,
    # so with a window of 2 the fit span [0, 4] ends exactly on sample 4, which is fitted (weight 0 there). Integer
    # input gives the float result of the same points as floats.
    steps = np.eye(3, dtype=np.int64)[np.arange(20) % 3]
    stair = np.concatenate([np.zeros((1, 3), np.int64), np.cumsum(steps, axis=0)])
    np.testing.assert_array_equal(arclength(stair), np.arange(21.0))
    out = regularise_ends(stair, 2.0)
    assert out.dtype == float
    np.testing.assert_allclose(out, _regularised_by_the_definition(stair.astype(float), 2.0), atol=1e-12)
    np.testing.assert_allclose(out, regularise_ends(stair.astype(float), 2.0), atol=1e-12)
    assert np.abs(out[1] - stair[1]).max() > 0.1


def test_regularise_ends_with_a_window_under_one():
    pts = _noisy_helix(400, seed=7, noise=0.01)  # points about 0.06 apart: about 20 in [0, 1.2]
    out = regularise_ends(pts, 0.6)
    np.testing.assert_allclose(out, _regularised_by_the_definition(pts, 0.6), atol=1e-9)
    assert np.abs(out - pts).max() > 0.005
