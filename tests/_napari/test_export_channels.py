"""The dock exports every channel of the scan's grid as one image (issue 24 item 1): a two-channel OME-Zarr opened
through napari, the scan one of its layers, the other taken along; each channel of the output equals that layer's
data straightened by the core alone (napari, Qt, Xvfb)."""

import numpy as np
import pytest
import zarr

pytest.importorskip("napari")

from napari_unwind._napari._widget import UnwindWidget  # noqa: E402
from napari_unwind.io import as_volume, open_channels  # noqa: E402
from napari_unwind.warp import straighten  # noqa: E402

pytestmark = pytest.mark.gui


def _two_channels(path, a, b):
    """A (c, z, y, x) OME-Zarr written with zarr itself (not by the code under test)."""
    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    stack = np.stack([a, b])
    arr = root.create_array("0", shape=stack.shape, chunks=(1, 16, 32, 32), dtype=stack.dtype)
    arr[...] = stack
    root.attrs["ome"] = {"version": "0.5", "multiscales": [{
        "axes": [{"name": "c", "type": "channel"}] + [{"name": x, "type": "space", "unit": "micrometer"}
                                                      for x in "zyx"],
        "datasets": [{"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 1, 1]}]}]}],
        "omero": {"channels": [{"label": "dapi"}, {"label": "gfp"}]}}


def test_the_export_takes_the_other_channel_layers_along(make_napari_viewer, qtbot, tmp_path):
    from test_widget import rod, rod_deformation

    a = rod()
    b = (a // 3 + 7).astype(np.uint16)
    _two_channels(tmp_path / "two.zarr", a, b)
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.open(str(tmp_path / "two.zarr"), plugin="napari-unwind")
    names = [layer.name for layer in viewer.layers]
    assert names == ["two.zarr [dapi]", "two.zarr [gfp]"]
    w.use_layer(viewer.layers[0])
    box = w.export_step.channels_box
    assert box.info.text() == "two.zarr [gfp]" and box.check.isEnabled()
    d = rod_deformation(unit="micrometer")
    w.model.set_deformation(d)
    box.check.setChecked(True)
    out = tmp_path / "both.ome.zarr"
    job = w.export(out)
    qtbot.waitUntil(lambda: job.done, timeout=120_000)
    assert "exported" in w.status.text(), w.status.text()
    chans = open_channels(out)
    assert [c.metadata["channel"] for c in chans] == ["dapi", "gfp"]
    for c, ref in zip(chans, (a, b), strict=True):
        expected = straighten(as_volume(ref, spacing=1.0, unit="micrometer"), d).data.compute()
        np.testing.assert_array_equal(np.asarray(c.data), expected)
    assert {"straight both.ome.zarr [dapi]", "straight both.ome.zarr [gfp]"} <= {layer.name for layer in viewer.layers}
    # the Measure section measures the other channel too (no selection here: the whole cage)
    from napari_unwind.measure import measure

    panel = w.export_step.measure_panel
    job = panel.measure()
    qtbot.waitUntil(lambda: job.done, timeout=120_000)
    expected = measure(d, channels={"scan": as_volume(a, spacing=1.0, unit="micrometer"),
                                    "gfp": as_volume(b, spacing=1.0, unit="micrometer")})
    for col in ("scan_mean", "gfp_mean", "gfp_max"):
        np.testing.assert_array_equal(panel.profile[col], expected[col])
    # a one-channel format with the box checked: refused in the status line, nothing written
    w.export(tmp_path / "x.nrrd")
    assert "holds one channel" in w.status.text() and not (tmp_path / "x.nrrd").exists()
    # another grid is not offered
    viewer.add_image(a[:-2], name="other grid")
    assert "other grid" not in box.info.text()
    qtbot.waitUntil(lambda: w.idle, timeout=60_000)
