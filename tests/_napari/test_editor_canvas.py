"""The 2D cross-section editor: synthetic mouse drags on the vispy canvas (Qt events on its native widget) change
the model by the dragged amounts, computed here from a camera rectangle the test sets (40 x 40 units on 400 x 400
pixels: 0.1 unit per pixel, v up), and a render read back from GL shows the cage where the model's bounds say.

Run under Xvfb: QT_QPA_PLATFORM=xcb xvfb-run -a -s "-screen 0 1600x1200x24" .venv/bin/pytest tests/_napari
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

pytest.importorskip("napari")

from _gui_helpers import Events, drag, state  # noqa: E402
from qtpy.QtCore import Qt  # noqa: E402

from napari_unwind._napari._editor_canvas import EditorCanvas  # noqa: E402
from napari_unwind.deformation import Deformation  # noqa: E402
from napari_unwind.editing import EditModel  # noqa: E402

pytestmark = pytest.mark.gui

SIZE = 400
RECT = (-20.0, -20.0, 40.0, 40.0)  # left, bottom, width, height (scene units = the plane's physical units)
UNIT = RECT[2] / SIZE  # scene units per canvas pixel


def to_canvas(x, y):
    """The plane's (x, y) -> canvas pixel (column, row): x to the right, y (v) up."""
    return ((x - RECT[0]) / UNIT, (RECT[1] + RECT[3] - y) / UNIT)


def bent_deformation(cage=(9.0, 7.0)):
    t = np.linspace(0, np.pi / 2, 5)
    pos = np.stack([40 * np.sin(t), 40 * (1 - np.cos(t)), np.zeros_like(t)], axis=1) + [12.0, 10.0, 30.0]
    n = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    u = np.tile([0.0, 0.0, 1.0], (5, 1))
    v = np.cross(n, u)
    return Deformation.from_keyframes(pos, np.stack([u, v, n], axis=1), cage)


@pytest.fixture
def editor(qtbot):
    rng = np.random.default_rng(1)
    scan = ndimage.gaussian_filter(rng.random((72, 72, 64)).astype(np.float32), 2.0) * 100
    d = bent_deformation()
    model = EditModel(d)
    model.select_keyframe(2)
    ed = EditorCanvas(model, lambda: scan, size=(SIZE, SIZE))
    qtbot.addWidget(ed.native)
    ed.native.resize(SIZE, SIZE)
    ed.native.show()
    qtbot.waitExposed(ed.native)
    ed.view.camera.rect = RECT
    qtbot.wait(20)
    # the test's mapping is the canvas's (a check of the set-up, not of the code under test)
    np.testing.assert_allclose(ed.scene_at(to_canvas(3.0, -4.0)), (3.0, -4.0), atol=1e-6)
    yield ed, model, d
    ed.close()


def test_dragging_the_centre_moves_the_keyframe_by_the_dragged_plane_distance(editor, qtbot):
    ed, model, d = editor
    ev = Events(model)
    start = np.round(to_canvas(0.0, 0.0)).astype(int)
    end = start + (30, -20)  # 30 px right, 20 px up
    drag(qtbot, ed.native, start, end)
    dx, dy = 30 * UNIT, 20 * UNIT  # up on the canvas is +v
    k = d.keyframes[2]
    got = model.deformation.keyframes[2].position
    np.testing.assert_allclose(got, k.position + dx * k.u + dy * k.v, atol=1e-9)
    for j in (0, 1, 3, 4):
        assert model.deformation.keyframes[j] is d.keyframes[j]
    # one undo step, one history event; undo restores bit for bit with one event
    assert len(model.history) == 1 and model.history[0].label == "move" and ev.history == 1
    changed = ev.changed
    assert model.undo()
    assert model.deformation is d and state(model.deformation) == state(d) and ev.changed == changed + 1
    # the view still shows the plane of the model's position
    assert ed.cross is not None and ed.cross.s == model.s


def test_dragging_the_u_handle_twists_by_the_dragged_angle(editor, qtbot):
    ed, model, d = editor
    arm = 0.5 * min(18.0, 14.0) / 2  # the axes are half the cage's smaller half-size long
    start = np.round(to_canvas(arm, 0.0)).astype(int)
    end = np.round(to_canvas(arm * math.cos(0.6), arm * math.sin(0.6) + 2.0)).astype(int)
    drag(qtbot, ed.native, start, end)
    p0 = np.array([RECT[0] + start[0] * UNIT, RECT[1] + RECT[3] - start[1] * UNIT])
    p1 = np.array([RECT[0] + end[0] * UNIT, RECT[1] + RECT[3] - end[1] * UNIT])
    theta = math.atan2(p1[1], p1[0]) - math.atan2(p0[1], p0[0])
    assert theta > 0.5  # counter-clockwise on the screen
    k, k2 = d.keyframes[2], model.deformation.keyframes[2]
    np.testing.assert_allclose(k2.u, math.cos(theta) * k.u + math.sin(theta) * k.v, atol=1e-9)
    np.testing.assert_allclose(k2.v, -math.sin(theta) * k.u + math.cos(theta) * k.v, atol=1e-9)
    np.testing.assert_allclose(k2.n, k.n, atol=1e-12)
    np.testing.assert_array_equal(k2.position, k.position)
    assert len(model.history) == 1 and model.history[0].label == "twist"
    assert model.undo() and state(model.deformation) == state(d)


def test_shift_drag_anywhere_twists(editor, qtbot):
    ed, model, d = editor
    start = np.round(to_canvas(-15.0, -15.0)).astype(int)  # outside the cage
    end = np.round(to_canvas(15.0, -15.0)).astype(int)
    drag(qtbot, ed.native, start, end, modifier=Qt.KeyboardModifier.ShiftModifier)
    p0 = np.array([RECT[0] + start[0] * UNIT, RECT[1] + RECT[3] - start[1] * UNIT])
    p1 = np.array([RECT[0] + end[0] * UNIT, RECT[1] + RECT[3] - end[1] * UNIT])
    theta = math.atan2(p1[1], p1[0]) - math.atan2(p0[1], p0[0])
    k, k2 = d.keyframes[2], model.deformation.keyframes[2]
    np.testing.assert_allclose(k2.u, math.cos(theta) * k.u + math.sin(theta) * k.v, atol=1e-9)


@pytest.mark.parametrize("grab, move, expected", [
    ((9.0, 0.0), (25, 0), (9.0 + 2.5, -9.0, 7.0, -7.0)),          # the right edge, 25 px right
    ((0.0, -7.0), (0, 30), (9.0, -9.0, 7.0, -7.0 - 3.0)),        # the bottom edge, 30 px down
    ((-9.0, 7.0), (-10, -20), (9.0, -9.0 - 1.0, 7.0 + 2.0, -7.0)),  # the top-left corner, left and up
])
def test_dragging_an_edge_or_corner_resizes_those_sides(editor, qtbot, grab, move, expected):
    ed, model, d = editor
    x_hi, x_lo, y_hi, y_lo = expected
    start = np.round(to_canvas(*grab)).astype(int)
    # the grab point rounds to a pixel: the expected side moves by the pixel distance only
    drag(qtbot, ed.native, start, start + move)
    got = model.deformation.keyframes[2].bounds
    np.testing.assert_allclose(got, (x_lo, x_hi, y_lo, y_hi), atol=1e-9)
    assert len(model.history) == 1 and model.history[0].label == "resize"
    assert model.undo() and state(model.deformation) == state(d)


def test_a_drag_outside_the_cage_changes_nothing(editor, qtbot):
    ed, model, d = editor
    start = np.round(to_canvas(-15.0, 15.0)).astype(int)
    drag(qtbot, ed.native, start, start + (40, 0))
    assert model.deformation is d and not model.can_undo


def test_render_shows_the_cage_where_the_model_says(editor, qtbot):
    ed, model, d = editor
    model.set_cage((-6.0, 11.0, -8.0, 4.0))  # an off-centre cage
    qtbot.wait(20)
    img = ed.canvas.render()[..., :3].astype(int)  # (H, W), row 0 at the top
    assert img.shape[:2] == (SIZE, SIZE)
    amber = (img[..., 0] > 200) & (img[..., 1] > 140) & (img[..., 1] < 230) & (img[..., 2] < 80)
    x_lo, x_hi, y_lo, y_hi = model.deformation.keyframes[model.keyframe].bounds
    c_lo, r_lo = to_canvas(x_lo, y_lo)
    c_hi, r_hi = to_canvas(x_hi, y_hi)  # r_hi < r_lo: v up
    rows, cols = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    near_col = lambda c: np.abs(cols - c) <= 2.5  # noqa: E731
    near_row = lambda r: np.abs(rows - r) <= 2.5  # noqa: E731
    within_r = (rows >= r_hi - 2.5) & (rows <= r_lo + 2.5)
    within_c = (cols >= c_lo - 2.5) & (cols <= c_hi + 2.5)
    outline = ((near_col(c_lo) | near_col(c_hi)) & within_r) | ((near_row(r_lo) | near_row(r_hi)) & within_c)
    assert amber.sum() > 100
    assert not (amber & ~outline).any(), np.argwhere(amber & ~outline)[:5]
    # every edge is drawn along its length
    for c in (c_lo, c_hi):
        seen = (amber & near_col(c)).any(axis=1)[int(r_hi) + 3:int(r_lo) - 3]
        assert seen.all()
    for r in (r_lo, r_hi):
        seen = (amber & near_row(r)).any(axis=0)[int(c_lo) + 3:int(c_hi) - 3]
        assert seen.all()


def test_the_chunk_cache_reads_what_numpy_slicing_reads():
    import dask.array as da

    from napari_unwind._napari._editor_canvas import _ChunkCache

    rng = np.random.default_rng(5)
    a = rng.integers(0, 60000, (37, 41, 29)).astype(np.uint16)
    reader = _ChunkCache(da.from_array(a, chunks=((10, 20, 7), (5, 30, 6), (29,))), max_bytes=3 * 10 * 30 * 29 * 2)
    for _ in range(60):
        lo = rng.integers(0, (36, 40, 28))
        hi = lo + 1 + rng.integers(0, np.array(a.shape) - lo)
        box = tuple(slice(int(x), int(y)) for x, y in zip(lo, hi, strict=True))
        got = reader[box]
        assert got.dtype == a.dtype
        np.testing.assert_array_equal(got, a[box])
    assert reader._bytes <= reader.max_bytes or len(reader._blocks) == 1


def test_the_plane_of_a_lazy_scan_is_the_plane_of_the_array(qtbot):
    import dask.array as da

    from napari_unwind.editing import cross_section
    from napari_unwind.io import Volume

    rng = np.random.default_rng(6)
    scan = ndimage.gaussian_filter(rng.random((72, 72, 64)).astype(np.float32), 2.0) * 100
    model = EditModel(bent_deformation())
    model.select_keyframe(3)
    ed = EditorCanvas(model, lambda: Volume(da.from_array(scan, chunks=(20, 33, 17))), size=(200, 200))
    qtbot.addWidget(ed.native)
    for angle in (0.0, 0.4, 1.1):
        model.twist(angle)
        np.testing.assert_array_equal(ed.cross.image, cross_section(scan, model.deformation, model.s).image)
    ed.close()
