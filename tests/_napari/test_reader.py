"""The napari face, tested for real: napari with Qt under Xvfb, Mesa llvmpipe for GL."""

import numpy as np
import pytest

pytest.importorskip("napari")
pytestmark = pytest.mark.gui

from napari_unwind.io import write_volume  # noqa: E402


@pytest.fixture
def scan(tmp_path):
    rng = np.random.default_rng(3)
    a = (rng.random((64, 48, 40)) * 3000).astype(np.uint16)
    a[20:40, 10:30, 10:30] = 60000  # a bright block to see in the screenshot
    return a, write_volume(a, tmp_path / "scan.zarr", spacing=(2.0, 1.0, 1.0), unit="um", max_side=16)


def test_manifest_is_valid_and_discovered():
    import npe2

    pm = npe2.PluginManager.instance()
    pm.discover()
    manifest = pm.get_manifest("napari-unwind")
    keys = {s.key for s in manifest.contributions.sample_data}
    assert {"fish", "tank", "cylinder"} <= keys
    assert manifest.contributions.readers


def test_reader_opens_pyramid_with_geometry(make_napari_viewer, scan):
    a, path = scan
    viewer = make_napari_viewer()
    layers = viewer.open(str(path), plugin="napari-unwind")
    layer = layers[0]
    assert layer.multiscale and len(layer.data) == 3
    np.testing.assert_array_equal(np.asarray(layer.data[0]), a)
    np.testing.assert_allclose(layer.scale, (2.0, 1.0, 1.0))
    assert [str(u) for u in layer.units] == ["micrometer"] * 3


def test_rendered_slice_matches_the_data(make_napari_viewer, scan):
    """Render plane 30 and check the bright block sits where the data has it (pixels read back from GL)."""
    a, path = scan
    viewer = make_napari_viewer(show=True)
    layer = viewer.open(str(path), plugin="napari-unwind")[0]
    layer.contrast_limits = (0, 65535)
    layer.colormap = "gray"
    viewer.dims.set_point(0, 30 * 2.0)
    viewer.reset_view()
    shot = viewer.screenshot(canvas_only=True, flash=False)
    grey = shot[..., :3].mean(axis=-1)
    bright = grey > 200
    assert bright.any(), "nothing bright was rendered"
    rows, cols = np.nonzero(bright)
    # the block covers rows 10..29 of 48 and columns 10..29 of 40: compare the proportions on screen
    data_rows, data_cols = np.nonzero(a[30] > 50000)
    h_ratio = (rows.max() - rows.min() + 1) / (cols.max() - cols.min() + 1)
    data_ratio = (data_rows.max() - data_rows.min() + 1) / (data_cols.max() - data_cols.min() + 1)
    assert abs(h_ratio - data_ratio) < 0.1
