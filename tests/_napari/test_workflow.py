"""The whole workflow through the Unwind dock on a small fish phantom (napari, Qt, Xvfb).

Scan file -> join tree -> a click on the fish (the callback napari calls, with a world position) -> suggested ends
-> skeleton in a worker -> an edit of the model and its undo -> export -> session saved and reopened in a fresh dock.
References are independent of the dock: the phantom's ground truth (mask, centreline), the core's ``straighten``
read back against the exported file, and geometry computed here from the deformation's own keyframe frames.
"""

from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("napari")

from _gui_helpers import drag  # noqa: E402
from napari.utils._proxies import ReadOnlyWrapper  # noqa: E402
from napari.utils.interactions import mouse_press_callbacks, mouse_release_callbacks  # noqa: E402
from qtpy.QtCore import Qt  # noqa: E402

from napari_unwind._napari._widget import UnwindWidget  # noqa: E402
from napari_unwind.datasets import fish_phantom  # noqa: E402
from napari_unwind.io import open_volume, write_volume  # noqa: E402
from napari_unwind.warp import straighten  # noqa: E402

pytestmark = pytest.mark.gui


@pytest.fixture(scope="module")
def fish():
    return fish_phantom(length=80, body_radius=5, tube=False, seed=1)


@pytest.fixture
def scan_path(tmp_path, fish):
    path = tmp_path / "fish.nrrd"
    write_volume(fish.volume, path, spacing=fish.spacing, unit=fish.unit)
    return path


def wait(qtbot, widget, job, timeout=60_000):
    assert job is not None, widget.status.text()
    qtbot.waitUntil(lambda: job.done, timeout=timeout)
    assert not widget.status.text().startswith("error"), widget.status.text()


def click(layer, world, *, ndisplay=2, shift=False, view_direction=None, viewer=None):
    """A click as napari's canvas delivers it to the active layer: press, then release at the same place (in 2D
    on the slice through the point, which the viewer is moved to first, as the user would)."""
    if viewer is not None and ndisplay == 2:
        viewer.dims.set_point(0, float(world[0]))
    displayed = [0, 1, 2] if ndisplay == 3 else [1, 2]
    mods = [SimpleNamespace(name="Shift")] if shift else []
    common = dict(position=tuple(float(c) for c in world), modifiers=mods, view_direction=view_direction,
                  dims_displayed=displayed, handled=False)
    mouse_press_callbacks(layer, ReadOnlyWrapper(SimpleNamespace(type="mouse_press", **common),
                                                 exceptions=("handled",)))
    mouse_release_callbacks(layer, ReadOnlyWrapper(SimpleNamespace(type="mouse_release", **common),
                                                   exceptions=("handled",)))


def fish_voxel(fish, labels_scale=1):
    """A voxel on the phantom's centreline, halfway along, inside its mask."""
    p = np.round(fish.centerline[len(fish.centerline) // 2]).astype(int)
    assert fish.mask[tuple(p)]
    return p


def test_whole_workflow(make_napari_viewer, qtbot, tmp_path, fish, scan_path):
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.window.add_dock_widget(w, name="Unwind")

    # scan
    wait(qtbot, w, w.open_scan(scan_path))
    assert w.volume.shape == fish.volume.shape
    assert w.volume.spacing == pytest.approx(fish.spacing)
    assert "micrometer" in w.scan_step.scan_info.text() and w.scan_step.scan_warning.isHidden()

    # segment: the tree once, then live re-simplification (the same tree)
    wait(qtbot, w, w.segment())
    qtbot.waitUntil(lambda: w.idle, timeout=30_000)
    tree = w.tree
    w.segment_step.count_slider.setValue(2)
    qtbot.waitUntil(lambda: w.idle and w.features.k == 2, timeout=30_000)
    assert w.tree is tree
    for k in (3, 4, 5):  # a slider drag: only the latest value needs computing
        w.segment_step.count_slider.setValue(k)
    qtbot.waitUntil(lambda: w.idle and w.features.k == 5, timeout=30_000)
    assert w.tree is tree
    assert w.segment_step.table.rowCount() == 5

    # pick the fish in 3D (a ray along axis0 through a fish voxel), then in 2D; shift-click adds
    vox = fish_voxel(fish)
    world = vox * np.asarray(w.volume.spacing) + np.asarray(w.volume.origin)
    layer = w._features_layer
    assert viewer.layers.selection.active is layer
    viewer.dims.ndisplay = 3
    click(layer, world, ndisplay=3, view_direction=(1.0, 0.0, 0.0))
    fid = w.selected[0]
    assert len(w.selected) == 1
    viewer.dims.ndisplay = 2
    click(layer, world, viewer=viewer)
    assert w.selected == [fid]
    chosen = np.isin(w.features.labels, w.selected)  # working resolution = full resolution here (small scan)
    assert chosen.shape == fish.mask.shape
    assert (chosen & fish.mask).sum() > 0.9 * fish.mask.sum()  # the phantom's own mask, not the dock's
    assert (chosen & ~fish.mask).sum() < 0.3 * fish.mask.sum()
    other = next((st for st in w.features.stats if st.id != fid and st.voxel_count), None)
    if other is not None:
        at = np.asarray(other.max_position_full) * np.asarray(w.volume.spacing) + np.asarray(w.volume.origin)
        click(layer, at, shift=True, viewer=viewer)
        assert w.selected == sorted([fid, other.id])
        click(layer, world, viewer=viewer)
        assert w.selected == [fid]
    selection = viewer.layers["selection"]
    assert set(np.unique(selection.data)) == {0, fid}

    # ends: suggested, near the phantom's true head and tail
    wait(qtbot, w, w.suggest_ends())
    ends = w.endpoints()
    assert np.linalg.norm(np.asarray(ends.head) - fish.centerline[0]) < 12
    assert np.linalg.norm(np.asarray(ends.tail) - fish.centerline[-1]) < 12

    # skeleton in a worker; its report in the dock
    wait(qtbot, w, w.run_skeleton(), timeout=120_000)
    d0 = w.model.deformation
    assert d0 is not None
    assert abs(d0.length - fish.length) < 0.2 * fish.length
    assert "min Jacobian" in w.skeleton_step.skeleton_report.toPlainText()

    # an edit through the model moves the keyframe by the amount, in its own frame; undo restores bit for bit
    w.model.select_keyframe(1)
    w.model.move(2.0, -1.0)
    d1 = w.model.deformation
    expected = d0.positions[1] + 2.0 * d0.frames[1][0] - 1.0 * d0.frames[1][1]
    np.testing.assert_allclose(d1.positions[1], expected, atol=1e-9)
    assert w.model.undo()
    assert w.model.deformation is d0

    # the same through the Refine step's 2D editor, as a user does it: synthetic mouse drags on its canvas (Qt events
    # on the vispy canvas). The expected amounts come from the drag's pixels through vispy's own view transform
    # (set here: a known rectangle), and the keyframe's frame before the drag.
    w.toolbox.setCurrentIndex(4)
    w.model.select_keyframe(1)
    ed = w.refine_panel.editor
    qtbot.waitExposed(ed.native)
    qtbot.waitUntil(lambda: ed.cross is not None and ed.cross.s == w.model.s, timeout=10_000)
    side = min(ed.native.width(), ed.native.height())
    ed.view.camera.rect = (-30.0, -30.0, 60.0 * ed.native.width() / side, 60.0 * ed.native.height() / side)
    qtbot.wait(30)
    start = np.round(ed.canvas_at((0.0, 0.0))).astype(int)
    end = start + (20, -10)  # 20 px right, 10 px up
    dx, dy = ed.scene_at(end) - ed.scene_at(start)  # the plane distance of the drag (vispy's transform)
    assert dx > 0 and dy > 0 and abs(dx / dy - 2.0) < 0.01
    drag(qtbot, ed.native, start, end)
    k, k1 = d0.keyframes[1], w.model.deformation.keyframes[1]
    np.testing.assert_allclose(k1.position, k.position + dx * k.u + dy * k.v, atol=1e-6)
    assert len(w.model.history) == 1 and w.model.history[0].label == "move"
    moved = w.model.deformation
    # shift-drag twists by the angle swept about the centre (the view re-centres on the moved keyframe first)
    qtbot.waitUntil(lambda: ed.cross is not None and ed.cross.s == w.model.s, timeout=10_000)
    ed.view.camera.rect = (-30.0, -30.0, 60.0 * ed.native.width() / side, 60.0 * ed.native.height() / side)
    qtbot.wait(30)
    a = np.round(ed.canvas_at((12.0, 0.0))).astype(int)
    b = np.round(ed.canvas_at((12.0 * np.cos(0.5), 12.0 * np.sin(0.5)))).astype(int)
    p0, p1 = ed.scene_at(a), ed.scene_at(b)
    theta = np.arctan2(p1[1], p1[0]) - np.arctan2(p0[1], p0[0])
    drag(qtbot, ed.native, a, b, modifier=Qt.KeyboardModifier.ShiftModifier)
    k2 = w.model.deformation.keyframes[1]
    m1 = moved.keyframes[1]
    np.testing.assert_allclose(k2.u, np.cos(theta) * m1.u + np.sin(theta) * m1.v, atol=1e-6)
    assert [st.label for st in w.model.history] == ["move", "twist"]
    assert w.model.undo() and w.model.undo()
    assert w.model.deformation is d0  # undo restored it bit for bit (the very object)
    w.toolbox.setCurrentIndex(5)

    # export: equals the core's straighten of the same scan and deformation, read back
    out = tmp_path / "x.nrrd"
    wait(qtbot, w, w.export(out))
    written = np.asarray(open_volume(out).data)
    reference = np.asarray(straighten(open_volume(scan_path), d0).data)
    np.testing.assert_array_equal(written, reference)
    assert any(lyr.name == "straight x.nrrd" for lyr in viewer.layers)

    # session: saved from the dock, reopened in a fresh dock of a fresh viewer
    session_path = tmp_path / "fish.unwind.json"
    wait(qtbot, w, w.save_session(session_path))
    assert session_path.exists()
    viewer2 = make_napari_viewer()
    w2 = UnwindWidget(viewer2)
    wait(qtbot, w2, w2.load_session(session_path))
    wait(qtbot, w2, w2.job)  # the join tree of the recorded selection
    qtbot.waitUntil(lambda: w2.idle and bool(w2.selected), timeout=30_000)
    assert w2.model.deformation.to_dict() == d0.to_dict()
    assert w2.endpoints() == ends
    assert w2.selected == [fid]
    assert w2.volume.shape == fish.volume.shape

    # the dock renders (not blank)
    w.toolbox.setCurrentIndex(3)
    image = w.grab().toImage()
    png = tmp_path / "dock.png"
    assert image.save(str(png))
    pixels = np.array([[image.pixel(x, y) for x in range(0, image.width(), 7)] for y in range(0, image.height(), 7)])
    assert image.width() > 100 and image.height() > 100
    assert len(np.unique(pixels)) > 10, "the dock rendered blank"
    qtbot.waitUntil(lambda: w.idle and w2.idle, timeout=60_000)  # the Refine panels' previews
