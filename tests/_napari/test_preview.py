"""The straight preview, CPU path: the level choice on a pyramid, the preview against scipy on the chosen level's
voxels (coordinates computed here from the deformation's physical slice geometry), and latest-edit-wins in napari."""

from __future__ import annotations

import dask.array as da
import numpy as np
import pytest
from scipy import ndimage

from napari_unwind.deformation import Deformation
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume
from napari_unwind.preview import preview_level, preview_volume


def line_deformation(half=(150.0, 160.0), spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), length=100.0):
    """A straight curve along axis0 through the middle of the box (u = axis2, v = axis1)."""
    pos = np.array([[20.0, 0, 0], [20.0 + length / 2, 0, 0], [20.0 + length, 0, 0]]) + [0.0, 40.0, 40.0]
    # rows u, v, n with n the tangent (+axis0) and u x v = n
    frames = np.repeat(np.array([[[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]]), 3, axis=0)
    return Deformation.from_keyframes(pos, frames, half, spacing=spacing, origin=origin)


def bent_deformation(spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), cage=(9.0, 7.0)):
    """Keyframes on a quarter circle in the axis0-axis1 plane, physical units."""
    t = np.linspace(0, np.pi / 2, 5)
    pos = np.stack([40 * np.sin(t), 40 * (1 - np.cos(t)), np.zeros_like(t)], axis=1) + [12.0, 10.0, 30.0]
    n = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    u = np.tile([0.0, 0.0, 1.0], (5, 1))
    v = np.cross(n, u)
    return Deformation.from_keyframes(pos, np.stack([u, v, n], axis=1), cage, spacing=spacing, origin=origin)


def pyramid(base_shape, spacing, factors, origin=(0.0, 0.0, 0.0)):
    """A lazy pyramid of zeros: level i has spacing * factors[i] and the block-centre origin shift."""
    sp, o = np.asarray(spacing, float), np.asarray(origin, float)
    levels = tuple(da.zeros(tuple(max(1, n // f) for n in base_shape), dtype=np.uint8, chunks=64) for f in factors)
    return Volume(levels[0], spacing=tuple(sp), origin=tuple(o), levels=levels,
                  level_spacings=tuple(tuple(sp * f) for f in factors),
                  level_origins=tuple(tuple(o + sp * (f - 1) / 2) for f in factors))


# ------------------------------------------------------------------------------------------------------------------
# the level choice
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("width, spacing, expected", [
    (300.0, (1.0, 1.0, 1.0), 2),    # 300/4 = 75 >= 64 > 300/8
    (256.0, (1.0, 1.0, 1.0), 2),    # 256/4 = 64 exactly: kept
    (255.0, (1.0, 1.0, 1.0), 1),    # 255/4 < 64 <= 255/2
    (600.0, (1.0, 1.0, 1.0), 3),    # the coarsest level is enough
    (40.0, (1.0, 1.0, 1.0), 0),     # too thin even at full resolution: the finest level
    (300.0, (2.0, 1.0, 1.0), 1),    # anisotropic: the coarsest axis counts (300 / (2 * 2) = 75, / (2 * 4) < 64)
])
def test_the_level_is_the_coarsest_keeping_64_voxels_across(width, spacing, expected):
    vol = pyramid((1024, 1024, 1024), spacing, (1, 2, 4, 8))
    # the narrower side decides: x is width wide, y wider
    d = line_deformation(half=(width / 2, width), spacing=spacing)
    assert preview_level(vol, d) == expected
    # the smallest keyframe decides, not the first
    wide = line_deformation(half=(width, width), spacing=spacing)
    thin = wide.resize_keyframe(1, (width / 2, width))
    assert preview_level(vol, thin) == expected
    # a bare array has one level
    assert preview_level(np.zeros((4, 4, 4)), d) == 0


def test_the_level_is_chosen_in_the_deformations_unit():
    # scan in mm, deformation in micrometres of the same grid: the factor over the base spacing counts
    vol = pyramid((1024, 1024, 1024), (0.001, 0.001, 0.001), (1, 2, 4, 8))
    d = line_deformation(half=(150.0, 300.0))
    assert preview_level(vol, d) == 2


def test_bad_options_are_refused_in_one_line():
    d = line_deformation()
    for bad in (0, -3, float("nan"), True, "64"):
        with pytest.raises(InvalidInputError, match="min_across"):
            preview_level(np.zeros((4, 4, 4)), d, min_across=bad)
    with pytest.raises(InvalidInputError, match="Deformation"):
        preview_volume(np.zeros((4, 4, 4)), "not one")
    with pytest.raises(InvalidInputError, match="3D"):
        preview_volume(np.zeros((4, 4)), d)


# ------------------------------------------------------------------------------------------------------------------
# the preview against scipy on the chosen level
# ------------------------------------------------------------------------------------------------------------------
def smooth_scan(shape, seed=0):
    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.random(shape).astype(np.float32), 2.0) * 100


@pytest.mark.parametrize("factor", [1, 2])
def test_preview_equals_scipy_on_the_chosen_levels_voxels(factor):
    spacing, origin = (1.5, 1.0, 1.0), (3.0, -2.0, 1.0)
    base = smooth_scan((96, 112, 64))
    coarse = base.reshape(48, 2, 56, 2, 32, 2).mean(axis=(1, 3, 5)).astype(np.float32)
    sp = np.asarray(spacing)
    vol = Volume(da.from_array(base, chunks=32), spacing=spacing, origin=origin,
                 levels=(da.from_array(base, chunks=32), da.from_array(coarse, chunks=32)),
                 level_spacings=(spacing, tuple(sp * 2)), level_origins=(origin, tuple(np.asarray(origin) + sp / 2)))
    d = bent_deformation(spacing=spacing, origin=origin, cage=(9.0 * factor, 7.0 * factor))
    # the body is 14 * factor across; level 1's coarsest spacing is 3: min_across 9 keeps it for factor 2 only
    level = preview_level(vol, d, min_across=9)
    assert level == {1: 0, 2: 1}[factor]
    got, ds = preview_volume(vol, d, min_across=9)
    lsp = sp * (2 if level else 1)
    lorigin = np.asarray(origin) + (sp / 2 if level else 0)
    assert ds == pytest.approx(lsp.min())
    # independent reference: physical points of the straight grid -> the level's voxel coordinates -> scipy
    base_p, dv, du = d.slice_geometry(ds, voxels=False)
    ns, ny, nx = d.output_shape(ds)
    pts = (base_p[:, None, None, :] + np.arange(ny)[None, :, None, None] * dv[:, None, None, :]
           + np.arange(nx)[None, None, :, None] * du[:, None, None, :])
    vox = (pts - lorigin) / lsp
    ref = ndimage.map_coordinates((coarse if level else base), vox.reshape(-1, 3).T, order=1, mode="constant",
                                  cval=0.0).reshape(ns, ny, nx)
    assert got.shape == ref.shape and got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-3)
    assert np.abs(ref).max() > 10  # the box samples the scan


def test_preview_of_a_box_outside_the_scan_is_refused():
    d = bent_deformation()
    far = d.move_keyframe(0, 1e4, 0).move_keyframe(1, 1e4, 0).move_keyframe(2, 1e4, 0).move_keyframe(
        3, 1e4, 0).move_keyframe(4, 1e4, 0)
    with pytest.raises(InvalidInputError, match=r"lies entirely outside the scan: .* 10021\.\.10039 \(axis0"):
        preview_volume(np.zeros((64, 64, 64), np.float32), far)


# ------------------------------------------------------------------------------------------------------------------
# the layer in napari: latest edit wins
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.gui
def test_quick_edits_end_on_the_last_deformation_and_drop_stale_results(make_napari_viewer, qtbot):
    pytest.importorskip("napari")
    from napari_unwind._napari._preview import PREVIEW_NAME, StraightPreview
    from napari_unwind.editing import EditModel

    scan = smooth_scan((80, 72, 64), seed=3)
    vol = Volume(da.from_array(scan, chunks=32))
    viewer = make_napari_viewer(show=True)  # a GL context of its own (a closed editor canvas may be current)
    model = EditModel(bent_deformation())
    preview = StraightPreview(viewer, lambda: vol, min_across=4)
    shown = []
    model.deformation_changed.connect(preview.request)
    model.select_keyframe(2)
    preview.request(model.deformation)
    for k in range(6):  # quick edits while the first worker runs
        model.move(0.7, -0.4 * k)
    qtbot.waitUntil(lambda: preview.idle and preview.layer is not None, timeout=20000)
    qtbot.wait(50)
    layer = viewer.layers[PREVIEW_NAME]
    layer.events.data.connect(lambda e: shown.append(1))
    ref, ds = preview_volume(vol, model.deformation, min_across=4)
    np.testing.assert_array_equal(layer.data, ref)
    np.testing.assert_allclose(layer.scale, (ds, ds, ds))
    # the layer shows the newest request; the queued edits were coalesced (fewer workers than requests)
    assert preview.shown_generation == preview.generation == 7
    assert preview.computed < 7
    # one more edit: exactly one more worker and one more data update
    n = preview.computed
    model.twist(0.2)
    qtbot.waitUntil(lambda: preview.idle and preview.shown_generation == preview.generation, timeout=20000)
    assert preview.computed == n + 1 and len(shown) == 1
    np.testing.assert_array_equal(layer.data, preview_volume(vol, model.deformation, min_across=4)[0])


@pytest.mark.gui
def test_a_stale_result_is_dropped(make_napari_viewer, qtbot):
    from napari_unwind._napari._preview import StraightPreview

    scan = smooth_scan((80, 72, 64), seed=4)
    viewer = make_napari_viewer(show=True)  # a GL context of its own (a closed editor canvas may be current)
    d = bent_deformation()
    preview = StraightPreview(viewer, lambda: scan, min_across=4)
    shows = []
    original = preview._show
    preview._show = lambda *a: (shows.append(a), original(*a))  # a spy: counts what reaches the layer
    preview.request(d)
    preview.request(d.twist_keyframe(2, 0.3))  # queued while the first runs
    qtbot.waitUntil(lambda: preview.idle and preview.layer is not None, timeout=20000)
    # the first result came back while the second was the newest: it was never shown
    assert preview.computed == 2 and preview.shown_generation == 2 and len(shows) == 1
    np.testing.assert_array_equal(preview.layer.data, preview_volume(scan, d.twist_keyframe(2, 0.3), min_across=4)[0])
