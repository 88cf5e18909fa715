"""The GPU straight view (issue 12): napari's ray caster samples the scan through the frame table.

References are independent of the shader: the CPU ``straighten`` of the same scan and deformation, its numpy MIP,
and napari's own unmodified renderer drawing that CPU volume in the same mode with the same camera.
Run: QT_QPA_PLATFORM=xcb xvfb-run -a -s "-screen 0 1600x1200x24" .venv/bin/pytest -q tests/_napari/test_straight_view.py
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from napari_unwind.deformation import Deformation
from napari_unwind.editing import EditModel
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume
from napari_unwind.warp import straighten

pytestmark = pytest.mark.gui

ZOOM = 6.0


def bent(shift=0.0, twist_deg=0.0, cage=(9.0, 7.0)):
    """Keyframes on a quarter circle in the axis0-axis1 plane; ``shift`` moves every keyframe along u (axis2) and
    ``twist_deg`` turns every frame's u, v about n."""
    t = np.linspace(0, np.pi / 2, 5)
    pos = np.stack([40 * np.sin(t), 40 * (1 - np.cos(t)), np.zeros_like(t)], axis=1) + [8.0, 8.0, 30.0 + shift]
    n = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    u = np.tile([0.0, 0.0, 1.0], (5, 1))
    v = np.cross(n, u)
    a = np.deg2rad(twist_deg)
    u, v = np.cos(a) * u + np.sin(a) * v, -np.sin(a) * u + np.cos(a) * v
    return Deformation.from_keyframes(pos, np.stack([u, v, n], axis=1), cage, spacing=(1.0, 1.0, 1.0),
                                      origin=(0.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def scan():
    rng = np.random.default_rng(0)
    vol = ndimage.gaussian_filter(rng.random((56, 56, 60)), 2)
    return ((vol - vol.min()) / (vol.max() - vol.min())).astype(np.float32)


def cpu(scan, d, order=1):
    return np.asarray(straighten(scan, d, spacing=1.0, order=order).data)


def _viewer(make_napari_viewer):
    from napari_unwind._napari import _private

    viewer = make_napari_viewer(show=True)
    viewer.window._qt_window.resize(700, 640)
    viewer.dims.ndisplay = 3
    return viewer, _private


def look(viewer, shape, ds=1.0):
    """Orthographic, looking down axis1 (rows = axis0, columns = axis2), centred on the straight box."""
    camera = viewer.scene.camera
    camera.perspective = 0
    camera.angles = (0, 0, 90)
    camera.center = tuple((np.array(shape, float) / 2 - 0.5) * ds)
    camera.zoom = ZOOM


def shot(viewer):
    return viewer.screenshot(canvas_only=True, flash=False)[..., :3].astype(int)


def reference_render(viewer, sv, array, **kwargs):
    """napari's own renderer on the CPU-straightened volume, same camera, straight view hidden."""
    sv.layer.visible = False
    layer = viewer.add_image(array, scale=sv.layer.scale, **{"contrast_limits": (0, 1), **kwargs})
    img = shot(viewer)
    viewer.layers.remove(layer)
    sv.layer.visible = True
    return img


def numpy_mip_at_voxels(img, shape):
    """The render's grey value at each (axis0, axis2) voxel centre of the straight box (ZOOM px per voxel)."""
    h, w = img.shape[:2]
    rows = np.floor(h / 2 + (np.arange(shape[0]) - (shape[0] - 1) / 2) * ZOOM).astype(int)
    cols = np.floor(w / 2 + (np.arange(shape[2]) - (shape[2] - 1) / 2) * ZOOM).astype(int)
    return img[np.ix_(rows, cols)][..., 0] / 255.0


# ----------------------------------------------------------------------------------------------------------------
# no GL: the level choice and the version pin
# ----------------------------------------------------------------------------------------------------------------
def test_level_choice_under_texture_limit_and_budget():
    from napari_unwind._napari._straight_view import choose_level

    shapes = [(600, 500, 400), (300, 250, 200), (150, 125, 100)]
    assert choose_level(shapes, 4, max_texture_size=2048, memory_budget=1 << 30) == 0     # 480 MB fits 1 GiB
    assert choose_level(shapes, 4, max_texture_size=512, memory_budget=1 << 30) == 1      # 600 > 512
    assert choose_level(shapes, 4, max_texture_size=2048, memory_budget=50 << 20) == 2    # 60 MB > 50 MiB
    with pytest.raises(InvalidInputError, match="no pyramid level fits the GPU"):
        choose_level(shapes, 4, max_texture_size=100, memory_budget=1 << 30)
    with pytest.raises(InvalidInputError, match="memory_budget must be a positive"):
        choose_level(shapes, 4, max_texture_size=100, memory_budget=0)


def test_other_napari_minor_is_refused_with_a_clear_message():
    from napari_unwind._napari import _private

    _private._check_version("0.9.7")
    with pytest.raises(ImportError, match=r"napari 0\.10\.0 is installed; install 'napari>=0\.9\.2,<0\.10'"):
        _private._check_version("0.10.0")


# ----------------------------------------------------------------------------------------------------------------
# the render against the CPU
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("frames", ["uniform", "texture"])
def test_mip_equals_cpu_straighten_and_a_wrong_deformation_fails(make_napari_viewer, scan, frames):
    from napari_unwind._napari._straight_view import StraightView

    viewer, _ = _viewer(make_napari_viewer)
    d = bent()
    sv = StraightView(viewer, scan, frames=frames)
    sv.update(d)
    assert sv.available, sv.reason
    sv.layer.contrast_limits = (0, 1)
    ref = cpu(scan, d)
    look(viewer, ref.shape)
    img = shot(viewer)

    # 1. the numpy MIP along axis1 of the CPU volume, read at the voxel centres (grey colormap, clim 0..1)
    got = numpy_mip_at_voxels(img, ref.shape)
    want = ref.max(axis=1)
    err = np.abs(got - want)
    # tolerance: 8-bit readback, and the ray samples between voxel centres along the ray (<= the true max)
    assert err.mean() < 0.02 and err.max() < 0.08, (err.mean(), err.max())

    # 2. napari's own MIP of the CPU volume, pixel by pixel
    other = reference_render(viewer, sv, ref)
    diff = np.abs(img - other)
    assert diff.mean() < 1.0 and np.percentile(diff, 99.9) <= 16, (diff.mean(), diff.max())

    # the same tolerances reject a deformation moved by 2 voxels or twisted by 10 degrees
    for wrong in (bent(shift=2.0), bent(twist_deg=10.0)):
        bad = cpu(scan, wrong)
        assert bad.shape == ref.shape
        e = np.abs(got - bad.max(axis=1))
        assert not (e.mean() < 0.02 and e.max() < 0.08), (e.mean(), e.max())


@pytest.mark.parametrize("mode", ["translucent", "iso"])
def test_translucent_and_iso_equal_napari_rendering_the_cpu_volume(make_napari_viewer, scan, mode):
    from napari_unwind._napari._straight_view import StraightView

    viewer, _ = _viewer(make_napari_viewer)
    d = bent()
    sv = StraightView(viewer, scan)
    sv.update(d)
    kw = {"rendering": mode, "iso_threshold": 0.55} if mode == "iso" else {"rendering": mode}
    sv.layer.contrast_limits = (0, 1)
    for k, v in kw.items():
        setattr(sv.layer, k, v)
    ref = cpu(scan, d)
    look(viewer, ref.shape)
    img = shot(viewer)
    other = reference_render(viewer, sv, ref, **kw)
    assert img.max() > 40  # something drawn
    bad = reference_render(viewer, sv, cpu(scan, bent(twist_deg=10.0)), **kw)
    diff, bad_diff = np.abs(img - other), np.abs(img - bad)
    corr = np.corrcoef(img[..., 0].ravel(), other[..., 0].ravel())[0, 1]
    bad_corr = np.corrcoef(img[..., 0].ravel(), bad[..., 0].ravel())[0, 1]
    print(mode, "diff", diff.mean(), "corr", corr, "| twisted 10 deg: diff", bad_diff.mean(), "corr", bad_corr)
    if mode == "iso":
        # the surface's silhouette (anything drawn): the CPU interpolates values, the shader positions, so the
        # crossing of the threshold moves by a fraction of a voxel at the edge
        sil, ref_sil, bad_sil = (x.max(axis=2) > 0 for x in (img, other, bad))
        mismatch, bad_mismatch = (sil != ref_sil).sum() / ref_sil.sum(), (sil != bad_sil).sum() / bad_sil.sum()
        print("silhouette mismatch", mismatch, "twisted", bad_mismatch)
        assert ref_sil.mean() > 0.02 and mismatch < 0.08 and bad_mismatch > 2 * mismatch
        # shading follows the gradients of the two different interpolants on a noisy surface: only loosely equal
        assert corr > 0.8 and bad_corr < corr, (corr, bad_corr)
    else:
        # translucent: measured mean 0.45 grey levels, correlation 0.9997 (twisted: 1.55, 0.9967)
        assert corr > 0.999 and diff.mean() < 1.0, (corr, diff.mean())
        assert bad_diff.mean() > 2 * diff.mean() and bad_corr < 0.998


NUMPY = {"mip": np.max, "minip": np.min, "average": np.mean}


def _matches(img, ref_img, mode, interpolation, got=None, want=None):
    """A render against a reference render (and against numpy's projection for MIP, MinIP and average), within
    the method's error: 8-bit readback (half a grey level each), and the ray sampling the scan between the CPU
    volume's voxel centres (the MIP test's bounds: mean under 1 grey level, 99.9th percentile within 16).

    - nearest rounds twice in the reference (to the straight voxel, then to the scan voxel), so a step of the scan
      moves by up to half a straight voxel (3 px at ``ZOOM``): only the mean is bounded;
    - average and additive average the sampling error over the about 20 samples of a ray: what is left is the
      readback's rounding, so the mean is bounded by half a grey level;
    - numpy: the ray's max / min lies within one interpolation step of the voxel centres' (mean 0.02, max 0.08 of
      the grey range); the average of about 20 samples within half of that largest error;
    - iso: the silhouette, whose edge moves by a fraction of a voxel (the CPU interpolates values, the shader
      positions), within 8 % of its area, up to half a voxel with nearest (twice that); the shading, from the
      gradients of two different interpolants, correlated above 0.8 (0.7 with nearest's blocks).
    """
    nearest = interpolation == "nearest"
    if mode == "iso":
        sil, ref_sil = img.max(axis=2) > 0, ref_img.max(axis=2) > 0
        mismatch = (sil != ref_sil).sum() / ref_sil.sum()
        corr = np.corrcoef(img[..., 0].ravel(), ref_img[..., 0].ravel())[0, 1]
        return (ref_sil.mean() > 0.02 and mismatch < (0.16 if nearest else 0.08) and corr > (0.7 if nearest else 0.8),
                (mismatch, corr))
    diff = np.abs(img - ref_img)
    mean_bound = 0.5 if mode in ("average", "additive") else 1.0
    ok = diff.mean() < mean_bound and (nearest or np.percentile(diff, 99.9) <= 16)
    figures = [diff.mean(), np.percentile(diff, 99.9)]
    if got is not None:
        err = np.abs(got - want)
        ok = ok and err.mean() < 0.02 and err.max() < (0.04 if mode == "average" else 0.08)
        figures += [err.mean(), err.max()]
    return ok, figures


@pytest.mark.parametrize("interpolation", ["linear", "nearest"])
@pytest.mark.parametrize("mode", ["mip", "minip", "attenuated_mip", "average", "translucent", "additive", "iso"])
def test_every_rendering_mode_and_interpolation_equals_the_cpu_reference(make_napari_viewer, scan, mode,
                                                                          interpolation, capfd):
    """Each mode and interpolation against napari's own renderer drawing the CPU ``straighten`` of the scan (order
    1 for linear, 0 for nearest) in the same mode, and for MIP, MinIP and average also against numpy's max, min
    and mean of that volume along the rays; the same tolerances reject a wrong deformation."""
    from napari_unwind._napari._straight_view import StraightView

    viewer, _ = _viewer(make_napari_viewer)
    sv = StraightView(viewer, scan)
    sv.update(bent())
    # additive composites 1 - prod(1 - c) over about 20 samples: at 0..1 every ray inside the box is white
    kw = {"rendering": mode, "interpolation3d": interpolation, "contrast_limits": (0, 20 if mode == "additive" else 1)}
    if mode == "iso":
        kw["iso_threshold"] = 0.55
    for k, v in kw.items():
        setattr(sv.layer, k, v)
    order = 0 if interpolation == "nearest" else 1
    ref = cpu(scan, bent(), order=order)
    assert sv._shape == ref.shape
    look(viewer, ref.shape)
    img = shot(viewer)
    out = capfd.readouterr()   # vispy reports a failed draw or a shader error on stderr
    assert "error" not in (out.out + out.err).lower()
    assert (img.max(axis=2) > 0).mean() > 0.1  # the box is drawn (about 20 % of the canvas)
    got = numpy_mip_at_voxels(img, ref.shape) if mode in NUMPY else None

    def check(volume):
        return _matches(img, reference_render(viewer, sv, volume, **kw), mode, interpolation, got,
                        NUMPY[mode](volume, axis=1) if got is not None else None)

    ok, figures = check(ref)
    print(mode, interpolation, figures)
    assert ok, figures
    # the same tolerances reject the deformation moved by 2 voxels, and the one twisted by 10 degrees where the mode
    # shows it: the additive composite moves by under half a grey level on average (0.4), nearest's iso silhouette
    # by 14 % (its faces move by up to half a voxel anyway)
    wrongs = [bent(shift=2.0)]
    if mode != "additive" and not (mode == "iso" and interpolation == "nearest"):
        wrongs.append(bent(twist_deg=10.0))
    for wrong in wrongs:
        bad_ok, bad_figures = check(cpu(scan, wrong, order=order))
        print("   wrong", bad_figures)
        assert not bad_ok, bad_figures


# ----------------------------------------------------------------------------------------------------------------
# edits
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("frames", ["uniform", "texture"])
def test_edit_changes_the_render_undo_restores_it_and_the_scan_is_not_reuploaded(make_napari_viewer, scan, frames):
    """The edited render equals napari's render of the CPU straighten of the edited deformation (the uniform
    table's later uploads once set only its first element: vispy caches the array's count with its location)."""
    from napari_unwind._napari._straight_view import StraightView

    viewer, _ = _viewer(make_napari_viewer)
    model = EditModel(bent())
    sv = StraightView(viewer, scan, frames=frames)
    sv.update(model.deformation)
    model.deformation_changed.connect(sv.update)
    sv.layer.contrast_limits = (0, 1)
    look(viewer, sv._shape)
    before = shot(viewer)

    tex = sv.scan_texture
    calls = []
    for name in ("set_data", "scale_and_set_data"):
        orig = getattr(tex, name)
        setattr(tex, name, lambda *a, _o=orig, _n=name, **k: (calls.append(_n), _o(*a, **k))[1])
    uploads = sv.frame_uploads

    model.set_s(float(model.deformation.knots[2]))
    model.move(3.0, 0.0)
    edited = shot(viewer)
    assert np.abs(edited - before).mean() > 1.0
    assert sv._capacity == (256 if frames == "uniform" else 0)
    assert calls == []
    moved = reference_render(viewer, sv, cpu(scan, model.deformation))
    assert np.abs(edited - moved).mean() < 1.0
    calls.clear()
    model.undo()
    after = shot(viewer)
    np.testing.assert_array_equal(after, before)
    assert sv.frame_uploads == uploads + 2
    assert calls == []


# ----------------------------------------------------------------------------------------------------------------
# big scans, fallback
# ----------------------------------------------------------------------------------------------------------------
def test_forced_small_texture_limit_picks_a_coarser_level_that_still_renders_right(make_napari_viewer, scan):
    from napari_unwind._napari._straight_view import StraightView

    coarse = scan.reshape(28, 2, 28, 2, 30, 2).mean(axis=(1, 3, 5)).astype(np.float32)
    vol = Volume(scan, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), levels=(scan, coarse),
                 level_spacings=((1.0, 1.0, 1.0), (2.0, 2.0, 2.0)), level_origins=((0.0, 0.0, 0.0), (0.5, 0.5, 0.5)))
    viewer, _ = _viewer(make_napari_viewer)
    sv = StraightView(viewer, vol, max_texture_size=40)
    assert sv.level == 1 and "pyramid level 1 (28x28x30" in sv.level_text
    assert StraightView(viewer, vol, memory_budget=56 * 56 * 60 * 4 - 1).level == 1
    d = bent()
    sv.update(d)
    assert sv.layer.data.shape == coarse.shape
    sv.layer.contrast_limits = (0, 1)
    from napari_unwind.preview import level_deformation

    ref = np.asarray(straighten(coarse, level_deformation(vol, d, 1), spacing=2.0, order=1).data)
    assert tuple(sv._shape) == ref.shape
    look(viewer, ref.shape, ds=2.0)
    img = shot(viewer)
    other = reference_render(viewer, sv, ref)
    # measured 1.15 grey levels (a small box: edges weigh more); 4 scan voxels = 2 level voxels off is told apart
    err = np.abs(img - other).mean()
    bad = reference_render(viewer, sv, np.asarray(
        straighten(coarse, level_deformation(vol, bent(shift=4.0), 1), spacing=2.0, order=1).data))
    assert img.max() > 40 and err < 2.0 and np.abs(img - bad).mean() > 1.5 * err, (err, np.abs(img - bad).mean())


def test_fallback_uses_the_cpu_preview_and_says_why(make_napari_viewer, scan, qtbot):
    from napari_unwind._napari._straight_view import LAYER_NAME, StraightView

    viewer, _ = _viewer(make_napari_viewer)
    sv = StraightView(viewer, scan, disable="float textures unavailable (test)")
    lines = []
    sv.status.connect(lines.append)
    assert not sv.available
    sv.update(bent())
    assert sv.preview is not None and LAYER_NAME not in viewer.layers
    qtbot.waitUntil(lambda: sv.preview.idle and sv.preview.layer is not None, timeout=30000)
    assert lines == ["straight view: CPU preview (float textures unavailable (test))"]


def test_a_shader_that_does_not_compile_falls_back_with_its_reason(make_napari_viewer, scan, qtbot, monkeypatch):
    from napari_unwind._napari import _shaders, _straight_view
    from napari_unwind._napari._straight_view import LAYER_NAME, StraightView

    broken = _shaders.STRAIGHT_LOOKUP.replace("vec3 n = $scan_shape;", "vec3 n = $scan_shape + undeclared_thing;")
    monkeypatch.setattr(_straight_view, "STRAIGHT_LOOKUP", broken)   # the texture table's code
    monkeypatch.setattr(_shaders, "STRAIGHT_LOOKUP", broken)         # uniform_lookup's source
    viewer, _ = _viewer(make_napari_viewer)
    sv = StraightView(viewer, scan)
    assert sv.available
    sv.update(bent())
    assert not sv.available and sv.reason.startswith("the straight-view shader failed")
    assert LAYER_NAME not in viewer.layers and sv.preview is not None
    qtbot.waitUntil(lambda: sv.preview.idle and sv.preview.layer is not None, timeout=30000)


def test_toggle_shows_the_bent_scan_from_the_same_texture_and_back(make_napari_viewer, scan):
    from napari_unwind._napari._straight_view import StraightView

    viewer, _ = _viewer(make_napari_viewer)
    sv = StraightView(viewer, scan)
    sv.update(bent())
    sv.layer.contrast_limits = (0, 1)
    look(viewer, sv._shape)
    straight = shot(viewer)
    tex = sv.scan_texture
    calls = []
    orig = tex.scale_and_set_data
    tex.scale_and_set_data = lambda *a, **k: (calls.append(1), orig(*a, **k))[1]

    sv.set_straight(False)
    look(viewer, scan.shape)
    bent_img = shot(viewer)
    assert calls == []   # the toggle itself uploads nothing (napari re-uploads when a layer is shown again, below)
    sv.layer.visible = False
    plain = viewer.add_image(scan, contrast_limits=(0, 1))
    reference = shot(viewer)
    viewer.layers.remove(plain)
    sv.layer.visible = True
    np.testing.assert_array_equal(bent_img, reference)   # the bent view is napari's own render of the scan

    calls.clear()
    sv.set_straight(True)
    look(viewer, sv._shape)
    np.testing.assert_array_equal(shot(viewer), straight)
    assert calls == [] and sv.scan_texture is tex


def test_focus_uploads_a_finer_level_crop_around_the_specimen(make_napari_viewer, scan):
    from napari_unwind._napari._straight_view import StraightView

    coarse = scan.reshape(28, 2, 28, 2, 30, 2).mean(axis=(1, 3, 5)).astype(np.float32)
    vol = Volume(scan, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), levels=(scan, coarse),
                 level_spacings=((1.0, 1.0, 1.0), (2.0, 2.0, 2.0)), level_origins=((0.0, 0.0, 0.0), (0.5, 0.5, 0.5)))
    viewer, _ = _viewer(make_napari_viewer)
    d = bent()
    sv = StraightView(viewer, vol, max_texture_size=54)   # level 0 (60 voxels along axis2) does not fit
    sv.update(d)
    assert sv.level == 1
    assert sv.focus() == 0
    assert max(sv.layer.data.shape) <= 54 and sv.layer.data.shape != scan.shape and "crop from voxel" in sv.level_text
    sv.layer.contrast_limits = (0, 1)
    ref = cpu(scan, d)                      # full resolution, whole scan
    assert tuple(sv._shape) == ref.shape
    look(viewer, ref.shape)
    img = shot(viewer)
    other = reference_render(viewer, sv, ref)
    assert img.max() > 40 and np.abs(img - other).mean() < 1.0


# ----------------------------------------------------------------------------------------------------------------
# the frame table along s, on sharp edges (issue 19, item 3)
# ----------------------------------------------------------------------------------------------------------------
RING_EVERY = 5


def ringed_scan():
    """A straight rod along axis0 (axis1 = axis2 = 20): a sharp-edged body of radius 6 (grey 0.3) and, in every
    RING_EVERY-th axis0 plane from 10 to 50, a bright annulus (3 <= radius <= 5, grey 1) one voxel thick along the
    rod; zero outside. Returns the scan and the axis0 planes of the rings."""
    g = np.indices((60, 40, 40), dtype=float)
    rho = np.hypot(g[1] - 20, g[2] - 20)
    vol = np.where(rho <= 6, 0.3, 0.0)
    planes = np.arange(10, 51, RING_EVERY)
    ring = np.isin(g[0], planes) & (rho >= 3) & (rho <= 5)
    vol[ring] = 1.0
    return vol.astype(np.float32), planes


@pytest.mark.parametrize("frames", ["uniform", "texture"])
def test_rings_one_slice_thick_land_on_the_cpu_rows(make_napari_viewer, frames, tmp_path):
    """A half-slice error in the frame table along s moves every ring by half a slice (3 px at ZOOM 6): the smooth
    scan of the tests above hides it under their tolerances, a one-voxel ring does not. Default window size."""
    from napari_unwind._napari._straight_view import StraightView

    vol, planes = ringed_scan()
    n = np.array([1.0, 0.0, 0.0])
    u, v = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])  # u x v = n: columns run along axis1
    d = Deformation.from_keyframes([[4.0, 20.0, 20.0], [56.0, 20.0, 20.0]], np.array([[u, v, n]] * 2), (8.0, 8.0),
                                   spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0))
    viewer = make_napari_viewer(show=True)  # napari's default window size
    viewer.dims.ndisplay = 3
    sv = StraightView(viewer, vol, frames=frames)
    sv.update(d)
    assert sv.available, sv.reason
    sv.layer.contrast_limits = (0, 1)
    ref = cpu(vol, d)
    look(viewer, ref.shape)
    img = shot(viewer)
    from imageio.v3 import imwrite

    imwrite(tmp_path / f"rings_{frames}.png", img.astype(np.uint8))

    # hand-derived: straight slice k is the axis0 plane 4 + k (the curve starts at axis0 = 4, no padding, ds = 1)
    assert d.s_range == (0.0, 52.0) and ref.shape == (53, 17, 17)
    rows = planes - 4
    cpu_mip = ref.max(axis=2)  # looking down v (axis2): rows s, columns x (axis1)
    ring_rows = np.flatnonzero((cpu_mip[:, 8 - 4:8 + 5] >= 0.99).all(axis=1))
    np.testing.assert_array_equal(ring_rows, rows)  # the CPU reference itself puts each ring on its plane

    # 1. the GL render read at the voxel centres: each ring's row is bright, its neighbours are the body's grey
    got = numpy_mip_at_voxels(img, ref.shape)
    ring_cols = slice(8 - 4, 8 + 5)  # |x| <= 4: the annulus crosses every ray there
    bright = got[rows][:, ring_cols]
    beside = np.concatenate([got[rows - 1][:, ring_cols], got[rows + 1][:, ring_cols]])
    # tolerance: 8-bit readback, and the pixel centre within half a pixel (1/12 slice) of the voxel centre: the ring
    # (a one-slice ramp in the scan's linear texture) loses at most 1/12 of its contrast 0.7 there, 0.06
    assert bright.min() >= 1.0 - 0.7 / 12 - 0.02, bright.min()
    assert beside.max() <= 0.3 + 0.7 / 12 + 0.02, beside.max()

    # 2. each ring's centre along s, at pixel resolution: the brightness above the body's grey weighted over the
    # pixel rows within a slice of the ring (the scan's linear texture makes it a triangle centred on the plane)
    h = img.shape[0]
    cols = np.floor(img.shape[1] / 2 + (np.arange(ring_cols.start, ring_cols.stop) - 8) * ZOOM).astype(int)
    profile = img[:, cols, 0].mean(axis=1) / 255.0 - 0.3
    px_of = (h / 2 + (np.arange(ref.shape[0]) - (ref.shape[0] - 1) / 2) * ZOOM)  # the pixel edge at a voxel centre
    centres = []
    for r in rows:
        lo, hi = int(np.floor(px_of[r] - ZOOM)), int(np.ceil(px_of[r] + ZOOM))
        w = np.clip(profile[lo:hi], 0, None)
        centres.append(((np.arange(lo, hi) + 0.5) * w).sum() / w.sum())
    centres = (np.array(centres) - h / 2) / ZOOM + (ref.shape[0] - 1) / 2
    # tolerance: the pixel grid's half pixel (1/12 slice) and the 8-bit steps; a half-slice error is 0.5
    np.testing.assert_allclose(centres, rows, atol=0.15)
