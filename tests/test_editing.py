"""The Qt-free editing model: every edit against geometry computed here, undo/redo bit for bit over 1000 random
edits, one event per edit, gestures as one step, and the cross-section against scipy on the same plane."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from napari_unwind.deformation import Deformation
from napari_unwind.editing import EditModel, cross_section
from napari_unwind.errors import InvalidInputError


def arc_deformation(n_keys=6, radius=40.0, cage=(4.0, 6.0), spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)):
    """Keyframes on a quarter circle in the axis0-axis1 plane (frames: n the tangent, u = axis2)."""
    t = np.linspace(0, np.pi / 2, n_keys)
    pos = np.stack([radius * np.sin(t), radius * (1 - np.cos(t)), np.zeros_like(t)], axis=1) + [10.0, 10.0, 30.0]
    n = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    u = np.tile([0.0, 0.0, 1.0], (n_keys, 1))
    v = np.cross(n, u)
    return Deformation.from_keyframes(pos, np.stack([u, v, n], axis=1), cage, spacing=spacing, origin=origin)


def state(d: Deformation) -> str:
    """Bit-exact fingerprint: the float64 bytes of every number."""
    return json.dumps(d.to_dict(), sort_keys=True, default=lambda x: float(x).hex()) + "|" + "".join(
        np.asarray(k.position).tobytes().hex() + np.asarray(k.frame).tobytes().hex() for k in d.keyframes)


class Counter:
    def __init__(self, model: EditModel):
        self.changed, self.history, self.position = 0, 0, 0
        model.deformation_changed.connect(lambda *_: self._inc("changed"))
        model.history_changed.connect(lambda *_: self._inc("history"))
        model.position_changed.connect(lambda *_: self._inc("position"))

    def _inc(self, name):
        setattr(self, name, getattr(self, name) + 1)


def test_move_shifts_the_keyframe_by_the_amount_along_u_and_v():
    d = arc_deformation()
    m = EditModel(d)
    m.select_keyframe(2)
    k = d.keyframes[2]
    m.move(1.5, -2.0)
    got = m.deformation.keyframes[2].position
    np.testing.assert_allclose(got, k.position + 1.5 * k.frame[0] - 2.0 * k.frame[1], atol=1e-12)
    # the other keyframes did not move; the position follows the moved keyframe
    for j in (0, 1, 3, 4, 5):
        np.testing.assert_array_equal(m.deformation.keyframes[j].position, d.keyframes[j].position)
    assert m.keyframe == 2 and m.s == pytest.approx(m.deformation.knots[2])


def test_twist_and_tilt_rotate_the_frame_by_the_angle_about_the_right_axis():
    d = arc_deformation()
    m = EditModel(d)
    m.select_keyframe(3)
    u, v, n = d.keyframes[3].frame
    m.twist(np.radians(30))
    u2, v2, n2 = m.deformation.keyframes[3].frame
    np.testing.assert_allclose(n2, n, atol=1e-12)
    np.testing.assert_allclose(u2, np.cos(np.radians(30)) * u + np.sin(np.radians(30)) * v, atol=1e-12)
    m.undo()
    m.tilt(np.radians(1), axis="u")
    u3, v3, n3 = m.deformation.keyframes[3].frame
    np.testing.assert_allclose(u3, u, atol=1e-12)
    assert np.degrees(np.arccos(np.clip(n3 @ n, -1, 1))) == pytest.approx(1.0, abs=1e-9)
    m.undo()
    m.tilt(np.radians(-1), axis="v")
    u4, v4, n4 = m.deformation.keyframes[3].frame
    np.testing.assert_allclose(v4, v, atol=1e-12)
    assert np.degrees(np.arccos(np.clip(n4 @ n, -1, 1))) == pytest.approx(1.0, abs=1e-9)


def test_set_cage_gives_the_sides_and_keeps_the_centre():
    d = arc_deformation()
    m = EditModel(d)
    m.select_keyframe(1)
    m.set_cage((-3.0, 5.0, -7.0, 2.0))
    k = m.deformation.keyframes[1]
    assert k.bounds == pytest.approx((-3.0, 5.0, -7.0, 2.0))
    np.testing.assert_array_equal(k.position, d.keyframes[1].position)
    with pytest.raises(InvalidInputError, match="x_lo < x_hi"):
        m.set_cage((2.0, 1.0, -1.0, 1.0))


def test_an_edit_between_keyframes_adds_one_there_in_the_same_step_and_keeps_the_map():
    d = arc_deformation()
    m = EditModel(d)
    s = 0.5 * (d.knots[1] + d.knots[2])
    m.set_s(s)
    assert m.keyframe is None
    m.add_keyframe()
    assert len(m.deformation) == len(d) + 1 and m.keyframe == 2
    rng = np.random.default_rng(0)
    xys = np.column_stack([rng.uniform(-4, 4, 50), rng.uniform(-6, 6, 50), rng.uniform(0, d.length, 50)])
    np.testing.assert_allclose(m.deformation.forward(xys), d.forward(xys), atol=1e-9)
    m.undo()
    m.set_s(s)
    m.move(0.0, 1.0)  # adds the keyframe and moves it: one step
    assert len(m.deformation) == len(d) + 1 and len(m.history) == 1
    m.undo()
    assert state(m.deformation) == state(d)


def test_delete_and_pad_and_their_errors():
    d = arc_deformation(n_keys=3)
    m = EditModel(d)
    m.select_keyframe(1)
    m.delete_keyframe()
    assert len(m.deformation) == 2
    with pytest.raises(InvalidInputError, match="at least 2 keyframes"):
        m.delete_keyframe(0)
    m.set_pad(3.0, 4.5)
    assert m.deformation.pad == (3.0, 4.5)
    with pytest.raises(InvalidInputError, match=">= 0"):
        m.set_pad(-1.0, 0.0)
    with pytest.raises(InvalidInputError, match="no deformation"):
        EditModel().move(1.0, 0.0)
    with pytest.raises(InvalidInputError, match="finite"):
        m.twist(float("nan"))


def test_events_fire_once_per_edit_undo_and_redo():
    m = EditModel(arc_deformation())
    c = Counter(m)
    m.select_keyframe(2)
    c.changed = c.history = 0
    edits = [lambda: m.move(1.0, 0.0), lambda: m.twist(0.1), lambda: m.tilt(0.02, axis="v"),
             lambda: m.set_cage((-2.0, 2.0, -3.0, 3.0)), lambda: m.set_pad(1.0, 1.0), lambda: m.undo(),
             lambda: m.redo()]
    for k, edit in enumerate(edits, start=1):
        edit()
        assert (c.changed, c.history) == (k, k), f"edit {k}"
    assert m.undo() and m.undo() and c.changed == len(edits) + 2
    # nothing to redo after a fresh edit: the branch is dropped
    m.move(0.5, 0.5)
    assert not m.can_redo and m.redo() is False


def test_a_gesture_is_one_step_with_totals_not_increments():
    d = arc_deformation()
    m = EditModel(d)
    m.select_keyframe(4)
    c = Counter(m)
    k = d.keyframes[4]
    with m.gesture("move"):
        for t in np.linspace(0.1, 3.0, 30):
            m.move(t, 0.0)
    assert c.changed == 30 and len(m.history) == 1
    np.testing.assert_allclose(m.deformation.keyframes[4].position, k.position + 3.0 * k.frame[0], atol=1e-12)
    m.undo()
    assert state(m.deformation) == state(d)
    # a cancelled gesture leaves nothing behind: the state and the history (the redo included) as they were
    m.begin_gesture("twist")
    m.twist(0.5)
    m.cancel_gesture()
    assert state(m.deformation) == state(d) and m.can_redo and len(m.history) == 0


def test_undo_redo_over_1000_random_edits_restores_every_state_bit_for_bit():
    rng = np.random.default_rng(12)
    d0 = arc_deformation(n_keys=5)
    m = EditModel(d0)
    states = [state(d0)]
    n_edits = 0
    while n_edits < 1000:
        d = m.deformation
        op = rng.integers(0, 8)
        try:
            if op == 0:
                m.set_s(rng.uniform(0, d.length))
                continue  # moving along the curve is not an edit
            if op == 1:
                m.select_keyframe(int(rng.integers(0, len(d))))
                continue
            if op == 2:
                m.move(*rng.normal(0, 0.3, 2))
            elif op == 3:
                m.twist(rng.normal(0, 0.1))
            elif op == 4:
                m.tilt(np.radians(rng.choice([-1.0, 1.0])), axis=str(rng.choice(["u", "v"])))
            elif op == 5:
                b = rng.uniform(1.0, 6.0, 4) * [-1, 1, -1, 1]
                m.set_cage(b)
            elif op == 6:
                if len(d) > 3 and m.keyframe is not None:
                    m.delete_keyframe()
                else:
                    continue
            else:
                m.set_pad(*rng.uniform(0, 5, 2))
        except InvalidInputError:
            continue  # e.g. two keyframes moved onto each other: refused, nothing changed
        n_edits += 1
        states.append(state(m.deformation))
    assert len(set(states)) > 900  # the edits did change things
    for k in range(len(states) - 1, 0, -1):
        assert state(m.deformation) == states[k]
        assert m.undo()
    assert state(m.deformation) == states[0] and not m.can_undo
    for k in range(1, len(states)):
        assert m.redo()
        assert state(m.deformation) == states[k]
    assert not m.can_redo


def test_set_deformation_clears_or_records_the_history():
    a, b = arc_deformation(), arc_deformation(cage=(2.0, 2.0))
    m = EditModel(a)
    m.select_keyframe(1)
    m.move(1.0, 0.0)
    m.set_deformation(b)
    assert not m.can_undo and m.deformation is b
    m.set_deformation(a, keep_history=True)
    assert m.undo() and m.deformation is b


def test_next_and_previous_keyframe():
    d = arc_deformation()
    m = EditModel(d)
    m.set_s(0.5 * (d.knots[2] + d.knots[3]))
    m.next_keyframe()
    assert m.keyframe == 3
    m.previous_keyframe()
    m.previous_keyframe()
    assert m.keyframe == 1
    m.select_keyframe(-1)
    m.next_keyframe()
    assert m.keyframe == len(d) - 1


def test_cross_section_of_a_straight_deformation_is_the_scan_slice():
    """Along axis0 with v = axis1 (u = v x n = -axis2), the plane at s = k is slice k of the scan, exactly."""
    rng = np.random.default_rng(1)
    vol = rng.random((40, 30, 20)).astype(np.float32)
    frame = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    d = Deformation.from_keyframes(np.array([[2.0, 15.0, 10.0], [37.0, 15.0, 10.0]]), np.stack([frame, frame]),
                                   (4.0, 5.0))
    sec = cross_section(vol, d, 11.0, half_size=(4.0, 5.0), pixel=1.0)
    assert sec.image.shape == (11, 9)
    np.testing.assert_allclose(sec.image, vol[13, 10:21, 14:5:-1], atol=1e-6)
    assert sec.bounds == pytest.approx((-4.0, 4.0, -5.0, 5.0))
    col, row = sec.to_pixel(0.0, 0.0)
    assert (col, row) == (4.0, 5.0)


def test_cross_section_matches_scipy_on_the_tilted_plane_with_spacing_and_origin():
    rng = np.random.default_rng(2)
    sp, org = (2.0, 1.0, 0.5), (5.0, -3.0, 1.0)
    vol = ndimage.gaussian_filter(rng.random((60, 80, 100)), 2).astype(np.float32)
    d = arc_deformation(spacing=sp, origin=org).tilt_keyframe(2, np.radians(8), axis="v")
    s = 0.4 * d.length
    sec = cross_section(vol, d, s, pixel=0.7)
    h, w = sec.image.shape
    yy, xx = np.meshgrid(sec.y0 + 0.7 * np.arange(h), sec.x0 + 0.7 * np.arange(w), indexing="ij")
    xys = np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, s)])
    vox = (d.forward(xys) - np.asarray(org)) / np.asarray(sp)
    ref = ndimage.map_coordinates(vol, vox.T, order=1, mode="constant", cval=0.0).reshape(h, w)
    inside = ((vox > 0.5) & (vox < np.asarray(vol.shape) - 1.5)).all(axis=1).reshape(h, w)
    assert inside.mean() > 0.3
    np.testing.assert_allclose(sec.image[inside], ref[inside], atol=1e-5)
    assert (sec.image[~((vox > -1) & (vox < np.asarray(vol.shape))).all(axis=1).reshape(h, w)] == 0).all()


def test_cross_section_errors():
    d = arc_deformation()
    with pytest.raises(InvalidInputError, match="3D"):
        cross_section(np.zeros((4, 4)), d, 1.0)
    with pytest.raises(InvalidInputError, match="range"):
        cross_section(np.zeros((4, 4, 4)), d, d.length + 10)


def test_undo_of_a_move_reselects_the_keyframe_at_its_old_place():
    """Moving a keyframe sideways changes the chord lengths, so its s changes; undo must come back to the s before
    the edit (the keyframe's old knot, recorded here before the edit), with the keyframe still selected, and redo
    to the moved one's (issue 19: undo restored the s after the edit, and the selection was lost)."""
    t = np.linspace(0, np.pi / 2, 5)
    pos = np.stack([30 * np.sin(t), 30 * (1 - np.cos(t)), np.zeros_like(t)], axis=1)
    n = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    u = np.tile([0.0, 0.0, 1.0], (5, 1))
    d = Deformation.from_keyframes(pos, np.stack([u, np.cross(n, u), n], axis=1), 4.0)
    model = EditModel(d)
    model.select_keyframe(2)
    s_before = float(d.knots[2])
    assert model.s == s_before and model.keyframe == 2
    seen = []
    model.position_changed.connect(lambda s, k: seen.append((s, k)))
    # 5 along v = (0, 0, 1) x n: the chords to keyframes 1 and 3 lengthen (hand: the old chord is
    # 2 * 30 sin(pi / 16); the new one is sqrt(c^2 + 25) > c)
    model.move(0.0, 5.0)
    s_after = model.s
    chord = 2 * 30 * np.sin(np.pi / 16)
    assert s_after == pytest.approx(s_before - chord + np.hypot(chord, 5.0), rel=0.05)
    assert model.keyframe == 2
    seen.clear()
    assert model.undo()
    assert model.deformation is d
    assert model.s == s_before and model.keyframe == 2
    assert seen == [(s_before, 2)]
    assert model.redo()
    assert model.s == s_after and model.keyframe == 2


# ------------------------------------------------------------------------------------------------------------------
# planted-bug pass (docs/testing-mutation.md, issue 19): the events' values, boundaries, messages, defaults
# ------------------------------------------------------------------------------------------------------------------
def test_every_event_carries_the_state_it_announces():
    d = arc_deformation()
    m = EditModel(d)
    assert m.s == 0.0 and m.keyframe == 0  # a new model starts at the head, on keyframe 0
    log = []
    for name in ("deformation_changed", "position_changed", "history_changed"):
        getattr(m, name).connect(lambda *a, name=name: log.append((name, a)))

    def take(name):
        got = [a for n, a in log if n == name]
        log.clear()
        return got

    m.set_s(d.knots[1])
    assert take("position_changed") == [(d.knots[1], 1)]
    m.set_pad(2.0, 3.0)
    padded = m.deformation
    assert [a for n, a in log if n == "deformation_changed"] == [(padded,)]
    assert take("history_changed") == [(True, False)]
    m.undo()
    assert take("history_changed") == [(False, True)]
    m.set_deformation(d, keep_history=True)
    assert [a for n, a in log if n == "deformation_changed"] == [(d,)]
    assert take("history_changed") == [(True, False)]
    with m.gesture("move"):
        m.move(0.5, 0.0)
    assert take("history_changed") == [(True, False)]
    s0, k0 = m.s, m.keyframe
    m.begin_gesture("move")
    m.move(1.0, 0.0)
    log.clear()
    m.cancel_gesture()
    assert take("position_changed") == [(s0, k0)] and k0 == 1
    m.move(0.25, 0.0)
    assert take("history_changed") == [(True, False)]
    m.delete_keyframe(4)
    assert [a[1] for n, a in log if n == "position_changed"] == [1]
    assert take("history_changed") == [(True, False)]


def test_a_gesture_between_keyframes_is_one_step_under_its_own_label():
    d = arc_deformation()
    m = EditModel(d)
    m.set_s(0.5 * (d.knots[1] + d.knots[2]))
    with m.gesture("move"):
        m.move(0.5, 0.0)
        m.move(1.0, 0.0)
    m.set_cage((-1.0, 2.0, -3.0, 4.0))
    assert [st.label for st in m.history] == ["move", "resize"]


def test_the_smallest_history_and_the_edges_of_the_edits():
    d = arc_deformation()
    m = EditModel(d, max_history=1)
    m.select_keyframe(1)
    m.move(1.0, 0.0)
    m.move(1.0, 0.0)
    assert len(m.history) == 1 and m.undo() and not m.undo()
    m.select_keyframe(0)
    m.previous_keyframe()
    assert m.keyframe == 0
    with pytest.raises(InvalidInputError, match=r"^keyframe index must be a whole number in \[-6, 5\], got 6$"):
        m.select_keyframe(6)
    with pytest.raises(InvalidInputError, match=r"^keyframe index must be a whole number in \[-6, 5\], got -7$"):
        m.delete_keyframe(-7)
    with pytest.raises(InvalidInputError, match="^tilt axis must be 'u' or 'v', got 'n'$"):
        m.tilt(0.1, axis="n")
    with pytest.raises(InvalidInputError, match="cage bounds must be 4 finite numbers"):
        m.set_cage([0.0, 1.0, 2.0])
    for before, after in ((-1.0, 2.0), (2.0, -1.0)):
        with pytest.raises(InvalidInputError, match="padding must be >= 0 at both ends"):
            m.set_pad(before, after)
    with pytest.raises(InvalidInputError, match=r"^there is a keyframe at s=0 already \(keyframe 0\)"):
        m.add_keyframe()
    m.set_s(0.5 * (d.knots[1] + d.knots[2]))
    with pytest.raises(InvalidInputError, match=r"^no keyframe at s=.* to delete; go to one first"):
        m.delete_keyframe()


def test_cross_section_sizes_and_values_worked_out_by_hand():
    """A straight deformation along axis0: the default pixel of a view taller than wide (cage x 100, y 500:
    1.5 x 500 = 750 half height, 1500 / 512 = 2.9296875 per pixel), the 2-pixel minimum, nearest sampling, and
    0 (float32) wherever the plane leaves the scan."""
    frame = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    d = Deformation.from_keyframes(np.array([[2.0, 15.0, 10.0], [37.0, 15.0, 10.0]]), np.stack([frame, frame]),
                                   (100.0, 500.0))
    vol = np.ones((40, 30, 20), np.float32)
    sec = cross_section(vol, d, 11.0)
    assert sec.pixel == 1500 / 512
    assert sec.image.shape == (513, 104)  # ceil(2 * 750 / p) + 1, ceil(2 * 150 / p) + 1
    np.testing.assert_allclose(sec.to_plane(2, 3), (sec.x0 + 2 * sec.pixel, sec.y0 + 3 * sec.pixel))
    assert cross_section(vol, d, 11.0, half_size=(0.4, 0.4), pixel=1.0).image.shape == (2, 2)
    # rows run along v = axis1 (scan row 15 at y = 0), columns along u = -axis2 (scan column 10 at x = 0)
    ramp = np.broadcast_to(np.arange(20, dtype=np.float32), (40, 30, 20))
    near = cross_section(ramp, d, 11.0, half_size=(3.0, 3.0), pixel=1.0, order=0)
    np.testing.assert_array_equal(near.image, np.tile(np.arange(13.0, 6.0, -1.0), (7, 1)))
    # a plane past the scan's end reads 0, in float32; one half out reads 0 on the outside half
    out = cross_section(vol, d.with_pad(0.0, 20.0), 50.0, half_size=(3.0, 3.0), pixel=1.0)
    assert out.image.dtype == np.float32 and not out.image.any()
    edge = cross_section(vol, d, 11.0, half_size=(20.0, 3.0), pixel=1.0)
    # columns j: x = -20 + j, scan column 10 - x: inside for x in [-9, 10], 0 beyond 1 voxel past the edge
    assert (edge.image[:, :10] == 0).all() and (edge.image[:, 12:30] == 1).all() and (edge.image[:, 32:] == 0).all()
    with pytest.raises(InvalidInputError, match="volume must be a 3D array"):
        cross_section(object(), d, 11.0)
    with pytest.raises(InvalidInputError, match="^the volume must hold numbers, got dtype complex128$"):
        cross_section(np.zeros((40, 30, 20), complex), d, 11.0, half_size=2.0)
