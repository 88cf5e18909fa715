"""Issue 21 item 6: switching to 3D does not ray cast the Labels layers (a coarse Surface stands in for them), and
the straight specimen is placed beside the scan (2D preview) and seen from its side (3D live view).

The timing goal is in benchmarks/bench_gui_3d.py; here the behaviour. References are independent of the code under
test: the mask's own numpy projection (compared with the pixels read back from the 3D screenshot through the
orthographic camera's own centre and zoom), and world boxes computed here from shape, scale and translate.
Run: QT_QPA_PLATFORM=xcb xvfb-run -a -s "-screen 0 1600x1200x24" .venv/bin/python -m pytest -q \
tests/_napari/test_3d_switch.py
"""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("napari")

from napari_unwind.deformation import Deformation  # noqa: E402
from napari_unwind.io import Volume  # noqa: E402

pytestmark = pytest.mark.gui

SHAPE = (90, 48, 40)
FID = 3


def specimen(shape=SHAPE):
    """A bent rod (label FID) along axis0, its axis1 position on a parabola, and a small blob (label 1)."""
    z, y, x = np.indices(shape, dtype=float)
    cy = 14 + 20 * ((z - 45) / 45) ** 2
    rod = ((y - cy) ** 2 + (x - 24) ** 2 <= 36) & (z >= 8) & (z < 82)
    blob = (z - 20) ** 2 + (y - 38) ** 2 + (x - 8) ** 2 <= 16
    labels = np.zeros(shape, np.uint16)
    labels[rod] = FID
    labels[blob] = 1
    return labels


def _viewer(make_napari_viewer):
    viewer = make_napari_viewer(show=True)
    viewer.window._qt_window.resize(800, 700)
    return viewer


def shot(viewer):
    return viewer.screenshot(canvas_only=True, flash=False)[..., :3].astype(float)


def test_labels_are_a_coarse_surface_in_3d_and_themselves_in_2d(make_napari_viewer, qtbot):
    from napari_unwind._napari import _private
    from napari_unwind._napari._layers import SURFACE_3D_SUFFIX, labels_in_3d

    viewer = _viewer(make_napari_viewer)
    labels = specimen()
    scale, translate = (2.0, 1.0, 1.0), (5.0, -3.0, 2.0)
    layer = viewer.add_labels(labels, name="selection", scale=scale, translate=translate, opacity=0.8)
    hook = labels_in_3d(viewer, layer)
    assert labels_in_3d(viewer, layer) is hook
    names_2d = [x.name for x in viewer.layers]
    assert viewer.layers.selection.active is layer

    viewer.dims.ndisplay = 3
    surface = viewer.layers["selection" + SURFACE_3D_SUFFIX]
    assert hook.active and surface is hook.surface
    assert viewer.layers.selection.active is layer          # clicks still reach the Labels layer
    # the Labels layer's own ray caster draws nothing in 3D (its draw is replaced), the surface follows its geometry
    node = _private.volume_node(viewer, layer)
    assert "draw" in node.__dict__
    np.testing.assert_allclose(surface.scale, scale)
    np.testing.assert_allclose(surface.translate, translate)
    assert surface.opacity == pytest.approx(0.8) and surface.visible
    verts = surface.data[0]
    assert verts.min(axis=0).min() >= -1 and (verts.max(axis=0) <= np.array(SHAPE) + 1).all()
    assert set(np.unique(surface.data[2]).astype(int)) == {1, FID}

    # the pixels: orthographic view along axis2 (rows = axis1 downwards, columns = axis0); the selection's colour
    # where the numpy projection of the rod is, dark where nothing projects
    camera = viewer.scene.camera
    camera.perspective = 0
    camera.set_view_direction((0.0, 0.0, 1.0), up_direction=(0.0, -1.0, 0.0))
    centre = np.asarray(translate) + (np.asarray(SHAPE) - 1) / 2 * np.asarray(scale)
    camera.center = tuple(centre)
    camera.zoom = 3.0
    img = shot(viewer)
    h, w = img.shape[:2]
    rows, cols = np.mgrid[0:h, 0:w]
    wy = centre[1] + (rows + 0.5 - h / 2) / camera.zoom      # world axis1 of a pixel
    wz = centre[0] + (cols + 0.5 - w / 2) / camera.zoom      # world axis0
    iz = np.round((wz - translate[0]) / scale[0]).astype(int)
    iy = np.round((wy - translate[1]) / scale[1]).astype(int)
    inside = (iz >= 0) & (iz < SHAPE[0]) & (iy >= 0) & (iy < SHAPE[1])
    proj_rod = (labels == FID).any(axis=2)
    proj_any = (labels > 0).any(axis=2)
    expected = np.zeros((h, w), bool)
    expected[inside] = proj_rod[iz[inside], iy[inside]]
    nothing = np.ones((h, w), bool)
    nothing[inside] = ~proj_any[iz[inside], iy[inside]]
    colour = np.asarray(layer.get_color(FID))[:3]
    norm = np.linalg.norm(img, axis=2)
    cosine = (img @ colour) / np.maximum(norm * np.linalg.norm(colour), 1e-9)
    drawn = (norm > 20) & (cosine > 0.97)
    # away from the outline (one coarse step): every projected pixel is drawn in the colour, nothing elsewhere
    from scipy import ndimage

    core = ndimage.binary_erosion(expected, iterations=8)
    far = ndimage.binary_erosion(nothing, iterations=8)
    assert core.sum() > 2000
    assert drawn[core].mean() > 0.97, drawn[core].mean()
    assert (norm[far] > 20).mean() < 0.01
    iou = (drawn & expected).sum() / (drawn | expected).sum()
    assert iou > 0.8, iou

    # a data edit in 3D: the surface follows (one more marching cubes), the layer keeps its full data
    builds = hook.builds
    edited = labels.copy()
    edited[edited == 1] = 0
    layer.data = edited
    assert hook.builds == builds + 1
    assert set(np.unique(hook.surface.data[2]).astype(int)) == {FID}
    assert layer.data is edited
    layer.visible = False
    assert not hook.surface.visible
    layer.visible = True
    assert hook.surface.visible

    # napari's pick along the view ray still reads the Labels layer (its data, not what is drawn)
    world = centre.copy()
    world[1] = translate[1] + cy_at(45) * scale[1]
    value = layer.get_value(tuple(world), view_direction=(0.0, 0.0, 1.0), dims_displayed=[0, 1, 2], world=True)
    assert value == FID

    # back to 2D: exactly the layers there were, no draw spent on a stand-in, the edits in 2D build nothing
    viewer.dims.ndisplay = 2
    assert [x.name for x in viewer.layers] == names_2d
    assert not hook.active and viewer.layers.selection.active is layer
    builds = hook.builds
    layer.data = labels
    assert hook.builds == builds
    hook.close()
    assert "draw" not in node.__dict__


def test_the_mesh_is_built_ahead_in_2d_and_empty_labels_add_no_layer(make_napari_viewer, qtbot):
    """The switch to 3D finds the surface of the labels already made (in a background thread while in 2D), the same
    as made on the spot; a Labels layer with no label (an empty selection) gets no stand-in layer at all."""
    from napari_unwind._napari._layers import SURFACE_3D_SUFFIX, labels_in_3d, labels_surface

    viewer = _viewer(make_napari_viewer)
    labels = specimen()
    layer = viewer.add_labels(np.zeros_like(labels), name="features")
    empty = viewer.add_labels(np.zeros(SHAPE, np.uint8), name="selection")
    hook, none = labels_in_3d(viewer, layer), labels_in_3d(viewer, empty)
    layer.data = labels                          # new features while in 2D: their mesh is made in the background
    qtbot.waitUntil(lambda: hook._ahead is not None and hook._ahead[1].done(), timeout=30_000)
    names = [x.name for x in viewer.layers]
    viewer.dims.ndisplay = 3
    assert hook.builds == 0 and hook.prefetches >= 1      # nothing made on the UI thread at the switch
    reference = labels_surface(labels)                      # made here, independently of the hook
    for got, want in zip(hook.surface.data, reference):
        np.testing.assert_array_equal(got, want)
    assert [x.name for x in viewer.layers] == ["features", "features" + SURFACE_3D_SUFFIX, "selection"]
    assert not none.active and none.builds + none.prefetches >= 1
    viewer.dims.ndisplay = 2
    assert [x.name for x in viewer.layers] == names
    # labels drawn later in the empty layer, in 3D: its surface appears
    viewer.dims.ndisplay = 3
    empty.data = (labels == FID).astype(np.uint8)
    assert none.active and "selection" + SURFACE_3D_SUFFIX in viewer.layers
    hook.close()
    none.close()


def test_no_labels_layer_is_ray_cast_during_the_switch_itself(make_napari_viewer, qtbot, monkeypatch):
    """napari's own handlers of the switch run before any plugin's, and its Labels controls make Qt paint the canvas
    there, already in 3D: the Labels layers' ray casters must be silent by then (that paint was 1.7 s of a 2.2 s
    switch on a 440 x 148 x 148 tank). Every draw of a volume node is recorded from the 2D view to the next frame."""
    from vispy.visuals.volume import VolumeVisual

    from napari_unwind._napari import _private
    from napari_unwind._napari._layers import labels_in_3d

    viewer = make_napari_viewer(show=True)   # napari's default window: there its Labels controls paint the canvas
    labels = specimen()
    layers = [viewer.add_labels(labels, name="features", opacity=0.4),
              viewer.add_labels((labels == FID).astype(np.uint8), name="selection")]
    hooks = [labels_in_3d(viewer, x) for x in layers]
    canvas = viewer.window._qt_viewer.canvas.native
    canvas.repaint()
    qtbot.wait(50)
    drawn: list[int] = []
    original = VolumeVisual.draw

    def record(self, *args, **kwargs):
        drawn.append(id(self))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(VolumeVisual, "draw", record)
    # and, whatever Qt does, a paint in 3D before the plugin's own handlers of the switch (placed first among them)
    viewer.dims.events.ndisplay.connect(lambda event: canvas.repaint(), position="first")
    viewer.dims.ndisplay = 3
    canvas.repaint()
    qtbot.wait(50)
    nodes = {id(_private.volume_node(viewer, x)) for x in layers}
    assert all(h.active for h in hooks)
    assert not nodes & set(drawn), f"{len(nodes & set(drawn))} Labels volume nodes ray cast at the switch"
    for h in hooks:
        h.close()


def cy_at(z):
    return 14 + 20 * ((z - 45) / 45) ** 2


def bent(origin=(0.0, 0.0, 0.0)):
    """Keyframes on a quarter circle in the axis0-axis1 plane (as in test_preview)."""
    t = np.linspace(0, np.pi / 2, 5)
    pos = np.stack([40 * np.sin(t), 40 * (1 - np.cos(t)), np.zeros_like(t)], axis=1) + [12.0, 10.0, 30.0]
    pos = pos + np.asarray(origin)
    n = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    u = np.tile([0.0, 0.0, 1.0], (5, 1))
    v = np.cross(n, u)
    return Deformation.from_keyframes(pos, np.stack([u, v, n], axis=1), (9.0, 7.0), spacing=(1.0, 1.0, 1.0),
                                      origin=origin)


def box_of(layer):
    n = np.asarray(layer.data.shape, float)
    s, t = np.asarray(layer.scale, float), np.asarray(layer.translate, float)
    return np.stack([t - s / 2, t + (n - 0.5) * s])


def test_the_2d_preview_lies_beside_the_scan_and_the_camera_shows_both(make_napari_viewer, qtbot):
    from scipy import ndimage

    from napari_unwind._napari._preview import PREVIEW_NAME, StraightPreview

    origin = (4.0, -6.0, 3.0)
    rng = np.random.default_rng(2)
    data = ndimage.gaussian_filter(rng.random((70, 64, 60)).astype(np.float32), 2.0)
    vol = Volume(data, spacing=(1.0, 1.0, 1.0), origin=origin)
    viewer = _viewer(make_napari_viewer)
    scan = viewer.add_image(data, translate=origin, name="scan")
    preview = StraightPreview(viewer, lambda: vol, min_across=4)
    preview.request(bent(origin))
    qtbot.waitUntil(lambda: preview.idle and preview.layer is not None, timeout=20000)
    layer = viewer.layers[PREVIEW_NAME]
    a, b = box_of(scan), box_of(layer)
    overlap = np.minimum(a[1], b[1]) - np.maximum(a[0], b[0])
    assert (overlap <= 0).any(), (a, b)                 # disjoint boxes
    assert b[0, 2] > a[1, 2]                            # beside the scan along the last axis, with a gap
    # the straight coordinates are kept
    assert layer.metadata["napari_unwind"]["straight_origin"][0] == pytest.approx(bent(origin).s_range[0])
    # the 2D camera (axis1 rows, axis2 columns) takes in both
    h, w = viewer.canvas.size
    c, z = np.asarray(viewer.scene.camera.center)[-2:], viewer.scene.camera.zoom
    seen = np.stack([c - np.array([h, w]) / (2 * z), c + np.array([h, w]) / (2 * z)])
    for box in (a, b):
        assert (seen[0] <= box[0, 1:] + 1e-6).all() and (box[1, 1:] <= seen[1] + 1e-6).all(), (seen, box)
    # a later edit keeps it beside the scan
    preview.request(bent(origin).replace_cage((8.0, 6.0)) if hasattr(Deformation, "replace_cage") else bent(origin))
    qtbot.waitUntil(lambda: preview.idle and preview.shown_generation == preview.generation, timeout=20000)
    assert box_of(layer)[0, 2] > a[1, 2]


def test_the_live_straight_view_is_seen_from_its_side_and_framed(make_napari_viewer, qtbot):
    from scipy import ndimage

    from napari_unwind._napari._straight_view import StraightView

    rng = np.random.default_rng(0)
    data = ndimage.gaussian_filter(rng.random((70, 64, 60)), 2).astype(np.float32)
    viewer = _viewer(make_napari_viewer)
    viewer.dims.ndisplay = 3
    sv = StraightView(viewer, data)
    if not sv.available:
        pytest.skip(sv.reason)
    sv.update(bent())
    if not sv.available:
        pytest.skip(sv.reason)
    long_axis = np.array([1.0, 0.0, 0.0])   # the straight box's axis0 (arclength)
    view = np.asarray(viewer.scene.camera.view_direction, float)
    angle = np.degrees(np.arccos(abs(view @ long_axis) / np.linalg.norm(view)))
    assert abs(angle - 90) <= 10, angle
    box = box_of(sv.layer) if sv.layer.data.shape == sv._shape else None
    ds = float(sv.layer.scale[0])
    box = np.stack([-np.full(3, ds / 2), (np.asarray(sv._shape) - 0.5) * ds])
    np.testing.assert_allclose(viewer.scene.camera.center, box.mean(axis=0), atol=1e-6)
    h, w = viewer.canvas.size
    length = box[1, 0] - box[0, 0]
    assert 0.5 * w <= length * viewer.scene.camera.zoom <= w   # the length spans most of the canvas, all of it on it
    # the bent toggle and back: framed again from the side
    sv.set_straight(False)
    sv.set_straight(True)
    view = np.asarray(viewer.scene.camera.view_direction, float)
    assert abs(np.degrees(np.arccos(abs(view @ long_axis) / np.linalg.norm(view))) - 90) <= 10
    img = shot(viewer)
    assert img.max() > 0


# -- a large Image in 3D: napari's ray caster on a block-reduced copy (ImageIn3D) ----------------------------------
BIG = (152, 128, 120)      # 2.33M voxels: over IMAGE_3D_MIN_VOXELS
BLOBS = [((33.5, 41.5, 61.5), 9.0, 1.0), ((97.5, 81.5, 45.5), 7.0, 0.7), ((121.5, 33.5, 81.5), 5.0, 0.85)]


def blobs(shape=BIG):
    """Bright balls on a dark ground, each centred on a corner shared by 4-voxel blocks (centre = 4k + 1.5), so a
    block reduction keeps it symmetric about its centre and a misplaced copy shows as a shifted ball."""
    idx = np.indices(shape, dtype=np.float32)
    vol = np.zeros(shape, np.float32)
    for centre, radius, value in BLOBS:
        r2 = sum((idx[a] - centre[a]) ** 2 for a in range(3))
        vol = np.maximum(vol, value * np.clip(1.5 - np.sqrt(r2) / radius, 0.0, 1.0))
    return vol


def look_along_axis2(viewer, shape, scale, translate, zoom):
    """Orthographic view along axis2 (rows = axis1 downwards, columns = axis0), centred on the volume."""
    camera = viewer.scene.camera
    camera.perspective = 0
    camera.set_view_direction((0.0, 0.0, 1.0), up_direction=(0.0, -1.0, 0.0))
    centre = np.asarray(translate) + (np.asarray(shape) - 1) / 2 * np.asarray(scale)
    camera.center = tuple(centre)
    camera.zoom = zoom
    return centre


def ball_centres(img, centre, zoom, scale, translate):
    """Intensity-weighted centre (in data voxels along axis0, axis1) of each BLOBS ball in a screenshot's grey
    values, each over a window around where the ball should be."""
    grey = img.mean(axis=2)
    h, w = grey.shape
    out = []
    for (c0, c1, _), radius, _ in BLOBS:
        col = (translate[0] + c0 * scale[0] - centre[0]) * zoom + w / 2 - 0.5
        row = (translate[1] + c1 * scale[1] - centre[1]) * zoom + h / 2 - 0.5
        half = 2.0 * radius * max(scale[:2]) * zoom
        r0, r1 = int(max(row - half, 0)), int(min(row + half, h))
        q0, q1 = int(max(col - half, 0)), int(min(col + half, w))
        win = grey[r0:r1, q0:q1]
        rows, cols = np.mgrid[r0:r1, q0:q1]
        m = win.sum()
        rc, cc = (rows * win).sum() / m, (cols * win).sum() / m
        out.append((((cc + 0.5 - w / 2) / zoom + centre[0] - translate[0]) / scale[0],
                    ((rc + 0.5 - h / 2) / zoom + centre[1] - translate[1]) / scale[1]))
    return np.asarray(out)


def test_a_large_image_is_ray_cast_from_a_coarse_copy_that_looks_like_the_full_volume(make_napari_viewer, qtbot):
    from napari_unwind._napari import _private
    from napari_unwind._napari._layers import ImageIn3D, image_in_3d, in_3d

    viewer = _viewer(make_napari_viewer)
    vol = blobs()
    scale, translate = (1.5, 1.0, 1.0), (5.0, -3.0, 2.0)
    layer = viewer.add_image(vol, name="scan", scale=scale, translate=translate, contrast_limits=(0.0, 1.0),
                             colormap="gray")
    other = viewer.add_labels(np.zeros((8, 8, 8), np.uint8), name="other")
    viewer.layers.selection.active = layer
    names = [x.name for x in viewer.layers]

    # the full volume, napari's own drawing, as the reference
    viewer.dims.ndisplay = 3
    zoom = 2.5
    centre = look_along_axis2(viewer, BIG, scale, translate, zoom)
    full = shot(viewer)
    node = _private.volume_node(viewer, layer)
    assert node._last_data.shape == BIG

    # a step-4 copy (max_side 40): 38 x 32 x 30 voxels, placed by napari through the layer's tile2data
    hook = image_in_3d(viewer, layer, max_side=40)
    assert isinstance(hook, ImageIn3D) and in_3d(viewer, layer) is hook
    assert hook.active and hook.step == 4
    assert node._last_data.shape == (38, 32, 30)
    coarse = shot(viewer)
    assert [x.name for x in viewer.layers] == names                  # no layer added
    assert viewer.layers.selection.active is layer and set(viewer.layers.selection) == {layer}
    grey_full, grey_coarse = full.mean(axis=2), coarse.mean(axis=2)
    assert grey_full.max() > 200
    corr = np.corrcoef(grey_full.ravel(), grey_coarse.ravel())[0, 1]
    assert corr > 0.9, corr
    # each ball where napari draws it from the full volume (to a fifth of a block), and where the data has it
    got, ref = ball_centres(coarse, centre, zoom, scale, translate), ball_centres(full, centre, zoom, scale, translate)
    np.testing.assert_allclose(got, ref, atol=0.8)
    np.testing.assert_allclose(ref, [b[0][:2] for b in BLOBS], atol=0.5)
    # clicks read the full data, not the copy
    world = np.asarray(translate) + np.asarray(BLOBS[2][0]) * np.asarray(scale)
    assert layer.get_value(tuple(world), view_direction=(0.0, 0.0, 1.0), dims_displayed=[0, 1, 2],
                           world=True) == pytest.approx(vol[121, 33, 81].item())
    assert layer.data is vol

    # the layer's properties apply to the copy (napari's own node draws it)
    layer.colormap = "red"
    red = shot(viewer)
    assert red[..., 0].max() > 200 and red[..., 1:].max() < 30
    layer.colormap = "gray"
    layer.contrast_limits = (0.0, 4.0)
    dim = shot(viewer).mean(axis=2)
    assert 0.15 < dim.max() / grey_coarse.max() < 0.35
    layer.contrast_limits = (0.0, 1.0)
    layer.visible = False
    assert shot(viewer).max() < 10
    layer.visible = True
    assert node._last_data.shape == (38, 32, 30) and hook.active
    # a rendering that averages along the ray takes the blocks' means (the maximum only for the MIP ones)
    builds = hook.builds
    layer.rendering = "average"
    blocks = vol.reshape(38, 4, 32, 4, 30, 4)
    assert hook.builds == builds + 1
    np.testing.assert_allclose(node._last_data, blocks.mean(axis=(1, 3, 5)), rtol=1e-5, atol=1e-6)
    layer.rendering = "mip"
    assert hook.builds == builds + 2
    np.testing.assert_array_equal(node._last_data, blocks.max(axis=(1, 3, 5)))

    # back to 2D: napari's 2D drawing of the full data, exactly as before; the same layers and selection
    viewer.dims.ndisplay = 2
    assert not hook.active
    np.testing.assert_allclose(np.asarray(layer._transforms["tile2data"].scale), 1.0)
    np.testing.assert_allclose(np.asarray(layer._transforms["tile2data"].translate), 0.0)
    viewer.dims.set_point(0, translate[0] + 33 * scale[0])           # through the first ball
    viewer.reset_view()
    vispy_2d = _private.vispy_layer(viewer, layer)
    plane = int(round((viewer.dims.point[0] - translate[0]) / scale[0]))
    np.testing.assert_array_equal(vispy_2d.node._data, vol[plane])   # the full slice
    np.testing.assert_allclose(vispy_2d.scale[:2], scale[1:][::-1])
    assert shot(viewer).max() > 200
    assert [x.name for x in viewer.layers] == names and viewer.layers.selection.active is layer
    # and to 3D again: the copy again
    viewer.dims.ndisplay = 3
    assert hook.active and node._last_data.shape == (38, 32, 30)

    # close(): napari's own upload of the full volume, at once
    hook.close()
    assert node._last_data.shape == BIG and not hook.active
    assert in_3d(viewer, layer) is not hook                            # a fresh hook (default budget: step 2)
    assert layer._napari_unwind_3d.step == 2 and node._last_data.shape == (76, 64, 60)
    # removing the layer closes the hook and leaves napari's vispy layer as it was
    fresh = layer._napari_unwind_3d
    vispy_layer = _private.vispy_layer(viewer, layer)
    viewer.layers.remove(layer)
    assert fresh._closed and "downsample_texture" not in vispy_layer.__dict__
    assert [x.name for x in viewer.layers] == ["other"]
    assert other in viewer.layers


def test_small_rgb_and_multiscale_images_are_drawn_as_napari_draws_them(make_napari_viewer, qtbot):
    from napari_unwind._napari import _private
    from napari_unwind._napari._layers import IMAGE_3D_MIN_VOXELS, coarse_step, in_3d

    viewer = _viewer(make_napari_viewer)
    small_shape = (120, 120, 120)                                     # 1.73M voxels: under the budget
    assert np.prod(small_shape) <= IMAGE_3D_MIN_VOXELS and coarse_step(small_shape) == 1
    small = viewer.add_image(np.random.default_rng(0).random(small_shape, dtype=np.float32), name="small")
    hook = in_3d(viewer, small)
    rgb = viewer.add_image(np.zeros((4, 64, 64, 3), np.uint8), rgb=True, name="rgb")
    assert in_3d(viewer, rgb) is None
    pyramid = [np.zeros((160, 128, 128), np.float32), np.zeros((80, 64, 64), np.float32)]
    assert in_3d(viewer, viewer.add_image(pyramid, multiscale=True, name="pyramid")) is None
    viewer.dims.ndisplay = 3
    shot(viewer)
    assert not hook.active and hook.step == 1 and hook.builds == 0
    assert _private.volume_node(viewer, small)._last_data.shape == small_shape
    np.testing.assert_allclose(np.asarray(small._transforms["tile2data"].scale), 1.0)
    # a large one at the default budget: the tank's 440 x 148 x 148 takes step 4 (at most 128 a side)
    assert coarse_step((440, 148, 148)) == 4 and coarse_step((300, 300, 300)) == 3


def test_block_reduce_keeps_the_dtype_and_reduces_partial_blocks():
    from napari_unwind._napari._layers import block_reduce

    data = np.arange(5 * 3 * 2, dtype=np.uint16).reshape(5, 3, 2)
    out = block_reduce(data, 2, "max")
    assert out.shape == (3, 2, 1) and out.dtype == np.uint16
    assert out[2, 1, 0] == data[4, 2, :].max() and out[0, 0, 0] == data[:2, :2, :2].max()
    mean = block_reduce(data.astype(np.float32), 2, "mean")
    assert mean[2, 1, 0] == pytest.approx(data[4, 2, :].mean()) and mean[0, 0, 0] == pytest.approx(
        data[:2, :2, :2].mean())
    assert block_reduce(data, 2, "min")[1, 0, 0] == data[2:4, :2, :2].min()
    assert block_reduce(data, 2, "mean").dtype == np.uint16


def test_the_scan_is_first_seen_in_3d_from_its_side_and_a_turned_camera_is_kept(make_napari_viewer, qtbot):
    """napari's first 3D view looks down axis0 (end-on down a tube of fish); the dock's scan is seen from its side:
    its longest world axis across the screen, looking along its shortest, the box on the canvas."""
    from napari_unwind._napari._widget import UnwindWidget

    viewer = _viewer(make_napari_viewer)
    dock = UnwindWidget(viewer)
    viewer.window.add_dock_widget(dock, name="Unwind")
    data = np.zeros((30, 50, 20), np.float32)   # world (60, 50, 40) with the scale: axis0 longest, axis2 shortest
    data[5:25, 10:40, 5:15] = 1.0
    scale = (2.0, 1.0, 2.0)
    layer = viewer.add_image(data, name="scan", scale=scale)
    dock.use_layer(layer)
    viewer.dims.ndisplay = 3
    view = np.asarray(viewer.scene.camera.view_direction, float)
    view /= np.linalg.norm(view)
    assert abs(view[2]) > 0.99, view   # along axis2, the shortest (40)
    up = np.asarray(viewer.scene.camera.up_direction, float)
    assert abs(up[1]) > 0.99, up       # axis1 up: axis0 (the longest, 60) runs across
    h, w = viewer.canvas.size
    assert 0.5 * w <= 60 * viewer.scene.camera.zoom <= w
    assert 50 * viewer.scene.camera.zoom <= h
    np.testing.assert_allclose(viewer.scene.camera.center, [29.0, 24.5, 19.0], atol=1e-6)
    # the user's own camera is kept across 2D and back
    viewer.scene.camera.angles = (10.0, 20.0, 30.0)
    viewer.dims.ndisplay = 2
    viewer.dims.ndisplay = 3
    np.testing.assert_allclose(viewer.scene.camera.angles, (10.0, 20.0, 30.0), atol=1e-6)
