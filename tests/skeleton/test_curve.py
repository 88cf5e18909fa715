"""Smoothing, resampling and keyframe selection against analytic curves."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from napari_unwind.deformation import parallel_transport_frames
from napari_unwind.errors import InvalidInputError
from napari_unwind.skeleton import resample_curve, select_keyframes, smooth_curve
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
    from napari_unwind.skeleton import regularise_ends

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
