"""Tests for mutants of deformation.py that survived the sampled mutation pass (docs/testing-mutation.md, issue 19).

Each test names the mutants it kills (numbers as in ``mutmut show napari_unwind.deformation.<function>__mutmut_N``).
Every expected value is worked out by hand from the construction, or comes from scipy, never from a run of the
code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation, Slerp

from napari_unwind.deformation import Deformation, Keyframe, _min_rotation, parallel_transport_frames
from napari_unwind.errors import InvalidInputError

E0, E1, E2 = np.eye(3)
# rows u, v, n along axis0: u = axis1, v = axis2, n = axis0 (e1 x e2 = e0)
ALONG_AXIS0 = np.array([E1, E2, E0])


def _line(knots=(0.0, 10.0, 25.0), cage=(3.0, 2.0), **kw) -> Deformation:
    """A straight deformation along axis0 with keyframes at s = knots (positions (s, 0, 0))."""
    pos = np.array([[s, 0.0, 0.0] for s in knots])
    return Deformation.from_keyframes(pos, [ALONG_AXIS0] * len(knots), cage, **kw)


# ------------------------------------------------------------------------------------------------------------------
# keyframe edits and look-ups
# ------------------------------------------------------------------------------------------------------------------
def test_index_at_finds_only_a_keyframe_within_its_tolerance():
    # knots 0, 10, 25: the tolerance is 1e-9 * max(1, L) = 2.5e-8.
    # Kills index_at 10 (tolerance 1.000000001 * L: every s was "at a keyframe").
    d = _line()
    assert [d.index_at(0.0), d.index_at(10.0 + 1e-8), d.index_at(25.0)] == [0, 1, 2]
    for s in (5.0, 10.0 + 1e-6):
        with pytest.raises(InvalidInputError, match="no keyframe at s="):
            d.index_at(s)


def test_add_keyframe_at_an_existing_keyframe_says_so():
    # Kills add_keyframe 10 (|knots + s|: the check never fires, and the duplicate position is refused later with
    # another message).
    with pytest.raises(InvalidInputError, match="there is a keyframe at s=10 already"):
        _line().add_keyframe(10.0)


def test_set_frame_keeps_the_cage_offset():
    # Kills set_frame 10 (offset None: refused as not finite).
    d = _line().set_cage(1, (-1.0, 5.0, -2.0, 0.0))  # half extents (3, 1), offset (2, -1)
    quarter = np.array([E2, -E1, E0])  # a quarter twist about n: u = axis2, v = -axis1
    k = d.set_frame(-2, quarter).keyframes[1]
    np.testing.assert_array_equal(k.frame, quarter)
    assert k.offset == (2.0, -1.0) and k.half_extent == (3.0, 1.0)
    np.testing.assert_array_equal(k.position, [10.0, 0, 0])


def test_cage_bounds_of_five_numbers_are_refused():
    # Kills Keyframe.from_bounds 10 ('and' for 'or': five finite numbers were taken as the first four).
    with pytest.raises(InvalidInputError, match="cage bounds must be 4 finite numbers"):
        Keyframe.from_bounds([0.0, 0, 0], ALONG_AXIS0, [-1.0, 1.0, -1.0, 1.0, 9.0])


# ------------------------------------------------------------------------------------------------------------------
# serialisation
# ------------------------------------------------------------------------------------------------------------------
def test_from_dict_defaults_the_unit_and_names_a_wrong_schema():
    # Kills Deformation.from_dict 10 (the schema in the message), 50 (pad default None), 70 (unit dropped).
    d = _line().to_dict()
    del d["pad"]
    loaded = Deformation.from_dict(dict(d, unit="mm"))
    assert loaded.pad == (0.0, 0.0)
    assert loaded.unit == "millimeter"
    with pytest.raises(InvalidInputError, match="got 'napari-unwind/other/1'"):
        Deformation.from_dict(dict(d, schema="napari-unwind/other/1"))


# ------------------------------------------------------------------------------------------------------------------
# frames
# ------------------------------------------------------------------------------------------------------------------
def test_min_rotation_worked_by_hand():
    # e0 -> e1 is the quarter turn about e2; e0 -> -e0 the half turn about e1 (the axis least aligned with e0,
    # the first of the ties), the matrix 2 e1 e1^T - I.
    # Kills _min_rotation 20 (c clipped to [1, 1]: a 45 degree turn, and the identity for opposite vectors),
    # 30 (np.eye(None)), 40 (np.dot(a)).
    np.testing.assert_allclose(_min_rotation(E0, E1), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(_min_rotation(E0, -E0), np.diag([-1.0, 1.0, -1.0]), atol=1e-15)
    c = np.cos(np.pi / 3)
    a, b = E0, np.array([c, np.sin(np.pi / 3), 0.0])  # 60 degrees apart
    np.testing.assert_allclose(_min_rotation(a, b) @ a, b, atol=1e-15)


def test_parallel_transport_first_and_last_frames_by_hand():
    # Points (0, 0, 0), (1, 0, 0), (1, 2, 0): the last tangent is the last segment's direction e1. Along axis0 the
    # default 'up' is the axis least aligned with e0, e1, so v0 = e1 and u0 = v0 x n0 = e1 x e0 = -e2.
    # Kills parallel_transport_frames 50 (tangents[-1] from seg[-2]), 80 (argmin(None): up = e0, parallel to n0).
    frames = parallel_transport_frames(np.array([[0.0, 0, 0], [1, 0, 0], [1, 2, 0]]))
    np.testing.assert_allclose(frames[-1, 2], E1, atol=1e-15)
    np.testing.assert_allclose(frames[0], [-E2, E1, E0], atol=1e-15)


def test_parallel_transport_projects_a_slanted_up_onto_the_normal_plane():
    # Along axis2 with up = (0, 1, 1): v0 = up - (up . n0) n0 = (0, 1, 0), u0 = v0 x n0 = e1 x e2 = e0.
    # Kills parallel_transport_frames 90 (up + (up . n0) n0 = (0, 1, 2) / sqrt(5)).
    frames = parallel_transport_frames(np.array([[0.0, 0, 0], [0, 0, 1], [0, 0, 2]]), up=(0.0, 1.0, 1.0))
    np.testing.assert_allclose(frames[0], [E0, E1, E2], atol=1e-15)


# ------------------------------------------------------------------------------------------------------------------
# inverse
# ------------------------------------------------------------------------------------------------------------------
def test_inverse_seeds_are_the_projections_onto_the_segments_and_the_padded_ends():
    # On a straight segment and in the padding, the seed of a point is its projection onto the segment, which is
    # already the answer: with max_iter=0 (no Newton step) inverse must return it exactly.
    # A polyline (0, 0, 0) -> (10, 0, 0) -> (10, 10, 0), the last keyframe turned a quarter about e2 (n = e1), a
    # padding of 5 after the tail (s up to 25); rows (u, v, n) with v = e2 and u = v x n: the first two frames
    # n = e0, u = e2 x e0 = e1; the last n = e1, u = e2 x e1 = -e0.
    # Kills inverse 30 (the tail padding's segment starts at pos[-2]), 40 (it runs along the second frame's n),
    # 120 (t = dot * |seg|^2), 130 (t clipped to [1, 1]).
    f0 = np.array([E1, E2, E0])
    f2 = np.array([-E0, E2, E1])
    d = Deformation.from_keyframes([[0.0, 0, 0], [10, 0, 0], [10, 10, 0]], [f0, f0, f2], 3.0, pad=(0.0, 5.0))
    res = d.inverse(np.array([[4.0, 1.5, -2.0], [10.0, 13.0, 0.0], [12.0, 14.0, 1.0]]), max_iter=0)
    # (4, 1.5, -2): s = 4 on the first segment, x = 1.5 (e1), y = -2 (e2)
    # (10, 13, 0): s = L + 3 = 23 in the padding, x = y = 0
    # (12, 14, 1): s = 24, x = -2 (along -e0), y = 1
    np.testing.assert_allclose(res.xys, [[1.5, -2.0, 4.0], [0.0, 0.0, 23.0], [-2.0, 1.0, 24.0]], atol=1e-12)
    np.testing.assert_array_equal(res.inside, [True, True, True])


def test_inverse_picks_the_cross_section_nearest_the_curve_in_a_u_turn():
    # Two straight legs joined by a half circle of radius 5 (keyframes every 30 degrees, v = e2 throughout, u =
    # v x n): leg 1 from (0, 0, 0) to (20, 0, 0), leg 2 back from (20, 10, 0) to (0, 10, 0). The point (2, 8, 0)
    # lies in a cross-section of each leg: 8 from leg 1 (x = 8 at s = 2) and 2 from leg 2 (u = -e1 there: x = 2
    # at s = 20 + 6 chords + 18). The nearer, leg 2, wins.
    # Kills inverse 170 (the candidates compared by hypot(x, s) instead of hypot(x, y): leg 1, at small s, won).
    th = np.deg2rad(np.arange(0, 181, 30))
    arc = np.stack([20 + 5 * np.sin(th), 5 - 5 * np.cos(th), np.zeros_like(th)], axis=1)
    n_arc = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=1)
    pos = np.vstack([[0.0, 0, 0], arc, [0.0, 10, 0]])
    n = np.vstack([E0, n_arc, -E0])
    v = np.broadcast_to(E2, n.shape)
    frames = np.stack([np.cross(v, n), v, n], axis=1)
    d = Deformation.from_keyframes(pos, frames, 1.0)
    chord = 2 * 5 * math.sin(np.deg2rad(15))
    res = d.inverse(np.array([[2.0, 8.0, 0.0]]))
    np.testing.assert_allclose(res.xys, [[2.0, 0.0, 20 + 6 * chord + 18]], atol=1e-9)


def test_a_point_exactly_on_the_cage_sides_is_inside():
    # Straight cage (rx, ry) = (3, 2) along axis0 (u = e1, v = e2): the points at x = +-3 and y = +-2 exactly are
    # on the sides and inside (the test allows 1e-9); 1e-6 further out they are not.
    # Kills inverse 220 (x >= x_lo + 1e-9), 230 (y >= y_lo + 1e-9).
    d = _line()
    pts = np.array([[5.0, -3, 0], [5, 3, 0], [5, 0, -2], [5, 0, 2], [5, -3 - 1e-6, 0], [5, 0, -2 - 1e-6]])
    np.testing.assert_array_equal(d.inverse(pts).inside, [True, True, True, True, False, False])


def test_newton_converges_fast_on_the_last_segment_of_a_bend():
    # One segment (two keyframes 10 apart) whose frame turns 60 degrees about u = e2 (so n goes from e0 towards
    # e1); a point 4 along v of the cross-section at s = 6.3. The reference s solves g(s) = (p - c(s)) . n(s) = 0 by
    # brentq, with c linear and n from scipy's Slerp. With the exact derivative of n, Newton reaches it in 4 steps.
    # Kills _newton 40 (s <= knots[-2]: the last segment taken as padding, n' = 0, only linear convergence).
    a = np.pi / 3
    rot = Rotation.from_rotvec([[0, 0, 0], [0, 0, a]])  # about e2
    f0 = np.array([E2, np.cross(E0, E2), E0])  # u = e2, v = n x u = e0 x e2 = -e1, n = e0
    f1 = rot[1].as_matrix() @ f0.T
    d = Deformation.from_keyframes([[0.0, 0, 0], [10, 0, 0]], [f0, f1.T], 5.0)
    slerp = Slerp([0.0, 10.0], Rotation.concatenate([Rotation.from_matrix(f0.T), Rotation.from_matrix(f1)]))

    def centre(s):
        return np.array([s, 0.0, 0.0])

    def frame(s):
        return slerp([s]).as_matrix()[0].T  # rows u, v, n

    s_true = 6.3
    p = centre(s_true) + 4.0 * frame(s_true)[1]
    s_ref = brentq(lambda s: float(np.dot(p - centre(s), frame(s)[2])), 0.0, 10.0, xtol=1e-14)
    assert abs(s_ref - s_true) < 1e-12
    res = d.inverse(p[None], max_iter=4)
    np.testing.assert_allclose(res.xys[0], [0.0, 4.0, s_ref], atol=1e-9)


# ------------------------------------------------------------------------------------------------------------------
# Jacobian and folds
# ------------------------------------------------------------------------------------------------------------------
def test_jacobian_on_an_arc_worked_by_hand():
    # A quarter arc of radius R = 10 with 7 keyframes (15 degrees apart), frames exact: u = e2 (the binormal),
    # n the tangent, v = n x u pointing away from the centre. On a chord of half angle h the frame turns at
    # k = 2h / (2 R sin h) about u, and mid-chord n . c' = 1: det J = 1 + y k (no x term). In the padding it is 1.
    # Kills jacobian 10, 20, 30, 40, 50 (y read from s), 60.
    radius, h = 10.0, np.deg2rad(7.5)
    th = np.deg2rad(np.arange(0, 91, 15))
    pos = np.stack([radius * np.sin(th), radius * (1 - np.cos(th)), np.zeros_like(th)], axis=1)
    n = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=1)
    u = np.broadcast_to(E2, n.shape)
    d = Deformation.from_keyframes(pos, np.stack([u, np.cross(n, u), n], axis=1), 3.0, pad=2.0)
    chord = 2 * radius * math.sin(h)
    k = 2 * h / chord
    s_mid = np.array([0.5, 2.5, 5.5]) * chord
    xys = np.array([[1.0, 2.0, s_mid[0]], [-2.5, -3.0, s_mid[1]], [0.0, 1.5, s_mid[2]], [2.0, 2.0, -1.0],
                    [-2.0, -2.0, 6 * chord + 1.0]])
    np.testing.assert_allclose(d.jacobian(xys), [1 + 2 * k, 1 - 3 * k, 1 + 1.5 * k, 1.0, 1.0], rtol=1e-12)
    with pytest.raises(InvalidInputError, match="shape"):
        d.jacobian(np.zeros((2, 2)))


def test_a_fold_that_starts_inside_the_curve():
    # Straight for 10 along axis0, then a quarter circle of radius 2 (7 keyframes) with a cage of 5 > 2: the map
    # folds from the arc's start (s = 10) to its end; folds() reports from the sample before the first bad one.
    # Kills folds 40 (max(None, 0) when the interval does not start at the first sample).
    th = np.deg2rad(np.arange(0, 91, 15))
    arc = np.stack([10 + 2 * np.sin(th), 2 * (1 - np.cos(th)), np.zeros_like(th)], axis=1)
    n_arc = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=1)
    pos = np.vstack([[0.0, 0, 0], arc])
    n = np.vstack([E0, n_arc])
    u = np.broadcast_to(E2, n.shape)
    d = Deformation.from_keyframes(pos, np.stack([u, np.cross(n, u), n], axis=1), 5.0)
    length = 10 + 6 * 2 * 2 * math.sin(np.deg2rad(7.5))
    (start, end), = d.folds(step=0.1)
    assert 9.9 - 1e-9 <= start < 10.0
    assert end == pytest.approx(length, abs=1e-12)


# ------------------------------------------------------------------------------------------------------------------
# the straight grid
# ------------------------------------------------------------------------------------------------------------------
def test_grid_of_a_cage_whose_top_is_below_one():
    # Cage y in [-3, 0.5] at ds 0.25: rows 3 / 0.25 = 12 below the curve, 0.5 / 0.25 = 2 above, plus the curve's
    # row: 15 rows, the curve on row 12. x in [-2, 2]: 8 + 8 + 1 = 17 columns. s: 25 / 0.25 + 1 = 101 slices.
    # Kills _grid 20 (max(y1, 1.0): 4 rows above).
    d = _line().set_cage(None, (-2.0, 2.0, -3.0, 0.5))
    assert d.output_shape(0.25) == (101, 15, 17)
    assert d.grid_centre(0.25) == (12, 8)


def test_an_absurd_spacing_is_refused_with_the_grids_size():
    # Length 25, cage (3, 2), ds = 25 / 2**62: 2**62 + 1 slices (above the 2**61 limit), about 4 * 2**62 / 25 =
    # 7.38e17 rows and 6 * 2**62 / 25 = 1.11e18 columns.
    # Kills _grid 40 (limit 3**61: accepted), 50 (columns as the difference of the two sides: 0).
    d = _line()
    ds = 25 / 2**62
    with pytest.raises(InvalidInputError, match=r"about 4\.61e\+18 x 7\.38e\+17 x 1\.11e\+18 voxels"):
        d.output_shape(ds)


def test_a_zero_output_spacing_is_refused():
    # Kills _ds 10 (ds >= 0: a ZeroDivisionError later).
    with pytest.raises(InvalidInputError, match="output spacing must be finite and positive, got 0"):
        _line().output_shape(0)


def test_sample_refuses_a_nan_arclength_by_name():
    # Kills sample 10 (the message).
    with pytest.raises(InvalidInputError, match="^arclengths must be finite$"):
        _line().sample([1.0, np.nan])
