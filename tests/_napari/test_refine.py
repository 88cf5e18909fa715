"""The Refine panel: buttons, keys and the s strip become model calls; every edit redraws the plane, the bent-view
wireframes (checked against corners computed here from the keyframes) and the straight preview."""

from __future__ import annotations

import math

import dask.array as da
import numpy as np
import pytest
from scipy import ndimage

pytest.importorskip("napari")

from _gui_helpers import Events  # noqa: E402
from qtpy.QtCore import QPoint, Qt  # noqa: E402
from qtpy.QtTest import QTest  # noqa: E402

from napari_unwind._napari._overlays import CAGE, CURVE, FRAMES  # noqa: E402
from napari_unwind._napari._refine import RefinePanel  # noqa: E402
from napari_unwind.deformation import Deformation  # noqa: E402
from napari_unwind.editing import EditModel  # noqa: E402
from napari_unwind.io import Volume  # noqa: E402
from napari_unwind.preview import preview_volume  # noqa: E402

pytestmark = pytest.mark.gui


def bent_deformation(cage=(9.0, 7.0), n_keys=5):
    t = np.linspace(0, np.pi / 2, n_keys)
    pos = np.stack([40 * np.sin(t), 40 * (1 - np.cos(t)), np.zeros_like(t)], axis=1) + [12.0, 10.0, 30.0]
    n = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    u = np.tile([0.0, 0.0, 1.0], (n_keys, 1))
    v = np.cross(n, u)
    return Deformation.from_keyframes(pos, np.stack([u, v, n], axis=1), cage)


@pytest.fixture
def panel(make_napari_viewer, qtbot):
    rng = np.random.default_rng(2)
    scan = ndimage.gaussian_filter(rng.random((72, 72, 64)).astype(np.float32), 2.0) * 100
    vol = Volume(da.from_array(scan, chunks=32))
    viewer = make_napari_viewer()
    viewer.add_image(scan, name="scan")  # the scan the dock works on, under the wireframes
    model = EditModel()
    p = RefinePanel(viewer, model, lambda: vol)
    p.preview.min_across = 4
    viewer.window.add_dock_widget(p, name="refine")
    qtbot.waitExposed(p)
    d = bent_deformation()
    model.set_deformation(d)
    model.select_keyframe(2)
    yield p, model, viewer, vol, d
    qtbot.waitUntil(lambda: p.preview.idle, timeout=20000)  # no result may reach a closed viewer


def corners(k):
    x_lo, x_hi, y_lo, y_hi = k.bounds
    return np.array([k.position + x * k.u + y * k.v for x, y in ((x_lo, y_lo), (x_hi, y_lo), (x_hi, y_hi),
                                                               (x_lo, y_hi))])


def test_the_bent_view_layers_follow_every_edit(panel, qtbot):
    p, model, viewer, vol, d = panel
    qtbot.waitUntil(lambda: not p.pending)  # the three layers, one per turn of the event loop
    for name in (CURVE, FRAMES, CAGE):
        assert name in viewer.layers
    model.move(2.0, -1.5)
    qtbot.waitUntil(lambda: not p.pending)  # the wireframes follow once the event loop is free
    k = model.deformation.keyframes[2]
    # the cage's wireframe holds the moved keyframe's corners (computed here from its position, frame and bounds)
    starts = viewer.layers[CAGE].data[:, 0]
    for c in corners(k):
        assert np.min(np.linalg.norm(starts - c, axis=1)) < 1e-9
    # the frames layer: u and v of the keyframe, as long as its cage's half-sizes
    vec = viewer.layers[FRAMES].data
    hit = np.linalg.norm(vec[:, 0] - k.position, axis=1) < 1e-9
    np.testing.assert_allclose(sorted(map(tuple, vec[hit, 1])),
                               sorted([tuple(k.u * k.half_extent[0]), tuple(k.v * k.half_extent[1])]), atol=1e-9)
    # the curve passes through every keyframe
    curve = viewer.layers[CURVE].data
    ends = np.concatenate([curve[:, 0], curve[-1:, 0] + curve[-1:, 1]])
    for kf in model.deformation.keyframes:
        assert np.min(np.linalg.norm(ends - kf.position, axis=1)) < 1e-9
    # the 2D plane is the model's, and the preview ends on the edited deformation
    assert p.editor.cross.s == model.s and p.editor._drawn[0] is model.deformation
    qtbot.waitUntil(lambda: p.preview.idle and p.preview.shown_generation == p.preview.generation, timeout=20000)
    np.testing.assert_array_equal(p.preview.layer.data, preview_volume(vol, model.deformation, min_across=4)[0])


def test_tilt_and_twist_buttons_turn_by_one_degree_once_per_click(panel, qtbot):
    p, model, viewer, vol, d = panel
    ev = Events(model)
    k = d.keyframes[2]
    a = math.radians(1.0)
    qtbot.mouseClick(p.tilt_buttons["tilt about u +1 degree"], Qt.MouseButton.LeftButton)
    k2 = model.deformation.keyframes[2]
    # a right-handed turn about u: v -> cos v + sin n, n -> cos n - sin v
    np.testing.assert_allclose(k2.u, k.u, atol=1e-12)
    np.testing.assert_allclose(k2.v, math.cos(a) * k.v + math.sin(a) * k.n, atol=1e-12)
    np.testing.assert_allclose(k2.n, math.cos(a) * k.n - math.sin(a) * k.v, atol=1e-12)
    assert ev.changed == 1 and ev.history == 1
    qtbot.mouseClick(p.undo_button, Qt.MouseButton.LeftButton)
    assert model.deformation is d
    qtbot.mouseClick(p.tilt_buttons["tilt about v -1 degree"], Qt.MouseButton.LeftButton)
    k3 = model.deformation.keyframes[2]
    np.testing.assert_allclose(k3.u, math.cos(-a) * k.u - math.sin(-a) * k.n, atol=1e-12)
    model.undo()
    qtbot.mouseClick(p.twist_plus, Qt.MouseButton.LeftButton)
    np.testing.assert_allclose(model.deformation.keyframes[2].u, math.cos(a) * k.u + math.sin(a) * k.v, atol=1e-12)


def test_keys_undo_redo_and_move_between_keyframes(panel, qtbot):
    p, model, viewer, vol, d = panel
    viewer.show()  # keys need a shown, active window
    p.window().activateWindow()
    p.editor.native.setFocus()
    qtbot.waitUntil(lambda: p.editor.native.hasFocus())
    QTest.keyClick(p.editor.native, Qt.Key.Key_E)  # twist +1 degree
    assert model.deformation is not d and model.can_undo
    QTest.keyClick(p.editor.native, Qt.Key.Key_Z, Qt.KeyboardModifier.ControlModifier)
    assert model.deformation is d and model.can_redo
    QTest.keyClick(p.editor.native, Qt.Key.Key_Z,
                   Qt.KeyboardModifier.ControlModifier | Qt.KeyboardModifier.ShiftModifier)
    assert model.deformation is not d and not model.can_redo
    QTest.keyClick(p.editor.native, Qt.Key.Key_PageDown)
    assert model.keyframe == 3
    QTest.keyClick(p.editor.native, Qt.Key.Key_Left)
    assert model.keyframe is None and model.s == pytest.approx(model.deformation.knots[3] - 1.0)
    QTest.keyClick(p.editor.native, Qt.Key.Key_K)  # add a keyframe here
    assert len(model.deformation) == 6 and model.keyframe == 3
    QTest.keyClick(p.editor.native, Qt.Key.Key_Delete)
    assert len(model.deformation) == 5


def test_a_refused_edit_shows_its_message(make_napari_viewer, qtbot):
    viewer = make_napari_viewer()
    model = EditModel(bent_deformation(n_keys=2))
    p = RefinePanel(viewer, model, lambda: None)
    qtbot.addWidget(p)
    model.select_keyframe(0)
    p.act("delete the keyframe")  # the last two cannot go: a message, no exception
    assert "at least 2 keyframes" in p.status.text() and len(model.deformation) == 2
    empty = RefinePanel(viewer, EditModel(), lambda: None)
    qtbot.addWidget(empty)
    empty.act("twist +1 degree (counter-clockwise)")
    assert "no deformation" in empty.status.text()


def test_the_strip_sets_s_where_clicked_and_the_pads_set_the_padding(panel, qtbot):
    p, model, viewer, vol, d = panel
    strip = p.strip
    w = strip.width()
    x = int(round(8 + 0.25 * (w - 16)))  # a quarter along the track (8 px margins)
    QTest.mouseClick(strip, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier, QPoint(x, strip.height() // 2))
    assert model.s == pytest.approx(d.length * (x - 8) / (w - 16), abs=1e-9)
    p.pad_head.setValue(5.0)
    assert model.deformation.pad == (5.0, 0.0) and len(model.history) == 1
    p.pad_tail.setValue(2.5)
    assert model.deformation.pad == (5.0, 2.5)
    model.undo()
    assert p.pad_tail.value() == 0.0 and p.pad_head.value() == 5.0


def test_every_action_of_the_shortcut_list_exists():
    names = {a for _, a in RefinePanel.SHORTCUTS}
    mouse = {a for k, a in RefinePanel.SHORTCUTS if "drag" in k}
    keys = [k for k, _ in RefinePanel.SHORTCUTS if "drag" not in k]
    assert len(keys) == len(set(keys))
    assert "undo" in names and "redo" in names and mouse


def test_the_wireframes_and_preview_leave_the_users_layer_selected(make_napari_viewer, qtbot):
    rng = np.random.default_rng(3)
    scan = ndimage.gaussian_filter(rng.random((72, 72, 64)).astype(np.float32), 2.0) * 100
    viewer = make_napari_viewer()
    viewer.add_image(scan, name="scan")
    ends = viewer.add_points(np.array([[12.0, 10.0, 30.0]]), name="ends")
    model = EditModel()
    p = RefinePanel(viewer, model, lambda: Volume(da.from_array(scan)))
    p.preview.min_across = 4
    qtbot.addWidget(p)
    model.set_deformation(bent_deformation())
    qtbot.waitUntil(lambda: not p.pending and p.preview.idle and p.preview.layer is not None, timeout=20000)
    assert CAGE in viewer.layers and viewer.layers.selection.active is ends


def test_the_live_gpu_straight_view_follows_the_edits_and_goes_when_unticked(panel, qtbot):
    """Issue 12 in the panel: ticking "live 3D straight view" adds the shader's layer in 3D and says which level is
    on screen; each edit re-uploads only the frame table; unticking removes the layer."""
    p, model, viewer, vol, d = panel
    viewer.window._qt_window.show()
    p.live_check.setChecked(True)
    sv = p.live
    assert sv is not None and viewer.dims.ndisplay == 3
    assert ("GPU shader, pyramid level 0" in p.live_label.text()) == sv.available
    if not sv.available:  # a GL without float textures: the CPU preview, and the reason
        assert "CPU preview (" in p.live_label.text()
        return
    layer = viewer.layers["straight view"]
    assert sv.deformation is model.deformation
    uploads = sv.frame_uploads
    model.twist(0.2)
    assert sv.deformation is model.deformation and sv.frame_uploads == uploads + 1
    model.undo()
    assert sv.deformation is d
    p.live_check.setChecked(False)
    assert p.live is None and layer not in viewer.layers and "straight view" not in viewer.layers


def test_the_live_view_says_why_when_it_cannot_start(panel, qtbot, monkeypatch):
    """Another napari minor (the shader's private access is pinned) or a GL without a volume node: one line in the
    panel, the box unticked, the CPU preview kept; no traceback from the Qt slot."""
    import napari_unwind._napari._straight_view as sv

    def refuse(*args, **kwargs):
        raise ImportError("napari-unwind's live straight view needs napari 0.9.x; this is napari 0.10.0")

    monkeypatch.setattr(sv, "StraightView", refuse)
    p, model, viewer, vol, d = panel
    p.live_check.setChecked(True)
    assert p.live is None and not p.live_check.isChecked()
    assert "not available: napari-unwind's live straight view needs napari 0.9.x" in p.live_label.text()
    assert p.preview.enabled


def test_the_wireframe_layers_are_added_one_per_turn_of_the_event_loop(make_napari_viewer):
    """Adding a layer costs napari 85-100 ms on software GL: three at once stalled the UI 0.3 s when a skeleton
    arrived. Each call adds at most ``new_layers`` and says whether all three are there."""
    from napari_unwind._napari._overlays import BentOverlays

    viewer = make_napari_viewer()
    overlays = BentOverlays(viewer)
    d = bent_deformation()
    added = []
    viewer.layers.events.inserted.connect(lambda event: added.append(event.value.name))
    done = [overlays.update(d, 0.0, None, new_layers=1) for _ in range(3)]
    assert done == [False, False, True] and added == [CURVE, FRAMES, CAGE]
    assert overlays.update(d, 1.0, 1, new_layers=1) and len(added) == 3   # all there: updated, none added
    overlays.remove()
    assert overlays.update(d) and len(added) == 6                          # no budget: all three at once
