"""The Unwind dock, step by step: the scan from a layer, the spacing warning, the layer list, ends as chains,
explicit saving, Cancel, clear errors, a session opened by napari's reader (napari, Qt, Xvfb)."""

import numpy as np
import pytest

pytest.importorskip("napari")

from napari_unwind._napari._widget import DOCK_SHORTCUTS, UnwindWidget, volume_from_layer  # noqa: E402
from napari_unwind.deformation import Deformation  # noqa: E402
from napari_unwind.io import write_volume  # noqa: E402
from napari_unwind.session import Endpoints, Segmentation, Session, SourceInfo, save_session  # noqa: E402

pytestmark = pytest.mark.gui


def rod(shape=(48, 32, 32)):
    """A bright bent rod (a specimen the segmentation finds as one feature) in a dim noisy volume."""
    rng = np.random.default_rng(0)
    a = (rng.random(shape) * 200).astype(np.uint16)
    z, y, x = np.indices(shape)
    cy = 16 + 5 * np.sin(z / shape[0] * np.pi)
    a[(z > 6) & (z < shape[0] - 6) & ((y - cy) ** 2 + (x - 16) ** 2 < 16)] = 3000
    return a


def rod_deformation(**kw):
    """A straight deformation along the rod's axis (axis0), cage 6 voxels."""
    return Deformation.from_polyline(np.array([[8.0, 16, 16], [24, 16, 16], [40, 16, 16]]), spacing=1.0,
                                     cage_half_extent=6.0, **kw)


@pytest.fixture
def rod_dock(make_napari_viewer):
    """The dock of a fresh viewer, its scan the rod (an in-memory Image layer)."""
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    w.use_layer(viewer.add_image(rod()))
    return w


def wait(qtbot, job, timeout=60_000):
    assert job is not None
    qtbot.waitUntil(lambda: job.done, timeout=timeout)


def test_volume_from_layer_keeps_geometry(make_napari_viewer):
    viewer = make_napari_viewer()
    data = rod()
    layer = viewer.add_image(data, scale=(2.0, 0.5, 0.5), translate=(10.0, -3.0, 1.0), units="micrometer")
    v = volume_from_layer(layer)
    assert v.shape == data.shape and v.spacing == (2.0, 0.5, 0.5) and v.origin == (10.0, -3.0, 1.0)
    assert v.unit == "micrometer"
    np.testing.assert_array_equal(np.asarray(v.data), data)
    pyramid = viewer.add_image([data, data[::2, ::2, ::2]], scale=(2.0, 0.5, 0.5), multiscale=True)
    vp = volume_from_layer(pyramid)
    assert len(vp.levels) == 2
    assert vp.level_spacings[1] == pytest.approx((4.0, 1.0, 1.0))  # twice level 0's voxel size
    assert vp.level_origins[1] == pytest.approx((1.0, 0.25, 0.25))  # the centre of the 2x2x2 block it covers
    rgb = viewer.add_image(np.zeros((8, 8, 3), np.uint8), rgb=True)
    with pytest.raises(Exception, match="not a 3D grey-value image"):
        volume_from_layer(rgb)


def test_scan_step_lists_layers_and_warns_of_missing_spacing(make_napari_viewer):
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    plain = viewer.add_image(rod(), name="plain")
    scaled = viewer.add_image(rod(), name="scaled", scale=(1.5, 1.0, 1.0), units="micrometer")
    names = [w.scan_step.layer_combo.itemText(i) for i in range(w.scan_step.layer_combo.count())]
    assert names[1:] == ["plain", "scaled"]
    w.scan_step.layer_combo.setCurrentIndex(1)
    w.scan_step.layer_combo.activated.emit(1)
    assert w.scan_layer is plain and not w.scan_step.scan_warning.isHidden()
    assert "Spacing missing" in w.scan_step.scan_warning.text()
    w.use_layer(scaled)
    assert w.scan_layer is scaled and w.scan_step.scan_warning.isHidden()
    assert "1.5 x 1 x 1" in w.scan_step.scan_info.text()
    viewer.layers.remove(plain)
    names = [w.scan_step.layer_combo.itemText(i) for i in range(w.scan_step.layer_combo.count())]
    assert names[1:] == ["scaled"]


def test_every_step_says_what_it_needs(make_napari_viewer):
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    assert "Needs a scan" in w.segment_step.segment_need.text() and not w.segment_step.segment_button.isEnabled()
    assert "Needs a selected feature" in w.ends_step.ends_need.text() and not w.ends_step.suggest_button.isEnabled()
    export = w.export_step
    assert "Needs a scan and a deformation" in export.export_need.text() and not export.export_button.isEnabled()
    w.export("somewhere.nrrd")
    assert w.status.text() == "error: there is no scan yet: pick an Image layer or open a file (step 1)"
    rows = [w.shortcuts_step.table.item(i, 0).text() for i in range(w.shortcuts_step.table.rowCount())]
    assert rows[: len(DOCK_SHORTCUTS)] == [k for k, _ in DOCK_SHORTCUTS]


def test_ends_more_than_two_points_are_a_chain(make_napari_viewer):
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    w.use_layer(viewer.add_image(rod(), scale=(2.0, 1.0, 1.0), translate=(4.0, 0.0, 0.0)))
    w.set_ends([(8, 16, 16), (30, 16, 16)])
    assert w.endpoints() == Endpoints(head=(8, 16, 16), tail=(30, 16, 16))
    np.testing.assert_allclose(w._ends_layer.data[0], (8 * 2.0 + 4.0, 16, 16))  # world = voxel * spacing + origin
    w.set_ends([(8, 16, 16), (18, 16, 16), (22, 16, 16), (40, 16, 16)])
    ends = w.endpoints()
    assert ends.head == (8, 16, 16) and ends.tail == (40, 16, 16)
    assert ends.chain == (((8, 16, 16), (18, 16, 16)), ((22, 16, 16), (40, 16, 16)))
    w._ends_layer.data = w._ends_layer.data[:3]
    with pytest.raises(Exception, match="has 3 point"):
        w.endpoints()


def test_export_never_replaces_a_file_without_confirmation(rod_dock, qtbot, tmp_path, monkeypatch):
    w = rod_dock
    w.model.set_deformation(rod_deformation())
    target = tmp_path / "kept.nrrd"
    target.write_bytes(b"the user's file")
    asked = []
    monkeypatch.setattr(w, "confirm_overwrite", lambda path: asked.append(path) or False)
    assert w.export(target) is None
    assert asked == [target] and target.read_bytes() == b"the user's file"
    assert "was kept" in w.status.text()
    qtbot.waitUntil(lambda: w.idle, timeout=60_000)  # the Refine panel's preview of the deformation


def test_cancel_stops_the_skeleton(rod_dock, qtbot):
    w = rod_dock
    wait(qtbot, w.segment())
    qtbot.waitUntil(lambda: w.idle, timeout=30_000)
    w.select_features([int(w.features.labels[24, 21, 16])])
    job = w.run_skeleton()
    assert w.skeleton_step.skeleton_cancel.isEnabled()
    w.cancel()
    wait(qtbot, job)
    assert w.status.text() == "computing the skeleton was cancelled"
    assert w.model.deformation is None and not w.skeleton_step.skeleton_cancel.isEnabled()


def test_saving_a_session_of_a_scan_in_memory_writes_the_scan_beside_it(make_napari_viewer, qtbot, tmp_path):
    """Before, refused ("not opened from a file"); now the scan is written as <name>.scan.ome.zarr and recorded
    (test_session_sample.py follows the whole round trip)."""
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    w.use_layer(viewer.add_image(rod(), name="in memory"))
    wait(qtbot, w.save_session(tmp_path / "x.unwind.json"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.scan.ome.zarr", "x.unwind.json"]
    assert w.volume.source == str(tmp_path / "x.scan.ome.zarr")


def test_a_session_opened_by_napari_gives_the_dock_its_deformation(make_napari_viewer, qtbot, tmp_path,
                                                                   monkeypatch):
    import threading

    from napari_unwind._napari import _reader

    ui_thread = threading.current_thread()
    segmented_on = []
    real_selection = _reader._selection_layer

    def watched(*args, **kwargs):  # the reader's recomputation of the selection (a join tree: seconds on big scans)
        segmented_on.append(threading.current_thread())
        return real_selection(*args, **kwargs)

    monkeypatch.setattr(_reader, "_selection_layer", watched)
    scan = tmp_path / "rod.nrrd"
    write_volume(rod(), scan, spacing=(1.0, 1.0, 1.0), unit="micrometer")
    d = rod_deformation(unit="micrometer")
    ends = Endpoints(head=(8.0, 16.0, 16.0), tail=(40.0, 16.0, 16.0))
    seg = Segmentation(k=3, level=0, selected=(1,), seeds=((24.0, 21.0, 16.0),))
    path = save_session(Session(source=SourceInfo.from_path(scan), deformation=d, endpoints=ends, segmentation=seg),
                        tmp_path / "rod.unwind.json")
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.open(str(path), plugin="napari-unwind")
    assert w.model.deformation.to_dict() == d.to_dict()
    assert w.scan_layer is not None and w.volume.shape == (48, 32, 32)
    assert w.endpoints() == ends
    qtbot.waitUntil(lambda: w.idle and bool(w.selected), timeout=60_000)  # the selection, rebuilt in a worker
    assert w.features.k == 3 and w.selected == [1]
    assert [lyr.name for lyr in viewer.layers].count("selection") == 1
    # with the dock open, the UI thread does not segment: the dock rebuilds the selection in its worker only
    assert ui_thread not in segmented_on
    rod_voxels = rod() == 3000
    chosen = np.isin(w.features.labels, [1])
    assert (chosen & rod_voxels).sum() > 0.8 * rod_voxels.sum()


def test_cancel_stops_an_export_and_leaves_no_file(rod_dock, qtbot, tmp_path, monkeypatch):
    import time

    import napari_unwind.warp as warp

    real = warp.export_iter

    def export_iter(*args, **kwargs):
        # the export of this small rod can finish before the click on Cancel reaches the worker (a flaky test):
        # its first step waits a little, as a big export's would take, so the Cancel always arrives during the job
        gen = real(*args, **kwargs)
        time.sleep(0.5)
        return (yield from gen)

    monkeypatch.setattr(warp, "export_iter", export_iter)
    w = rod_dock
    w.model.set_deformation(rod_deformation())
    target = tmp_path / "cancelled.nrrd"
    job = w.export(target)
    w.cancel()
    wait(qtbot, job)
    assert w.status.text() == "exporting was cancelled"
    assert not target.exists() and list(tmp_path.iterdir()) == []  # nothing half-written left behind
    assert w.exported is None
    qtbot.waitUntil(lambda: w.idle, timeout=60_000)


def test_a_failed_skeleton_says_why_in_the_dock(rod_dock, qtbot):
    w = rod_dock
    wait(qtbot, w.segment())
    qtbot.waitUntil(lambda: w.idle, timeout=30_000)
    w.select_features([int(w.features.labels[24, 21, 16])])
    w.set_ends([(0, 0, 0), (47, 31, 31)])  # the volume's corners: far from the rod
    wait(qtbot, w.run_skeleton())
    text = w.status.text()
    assert text.startswith("error: ") and "\n" not in text and "Traceback" not in text
    assert "the head [0.0, 0.0, 0.0]" in text and "from the mask" in text, text  # the core's message, as is
    assert w.model.deformation is None


def test_a_scan_opened_in_the_dock_gets_contrast_from_its_voxels(make_napari_viewer, qtbot, tmp_path):
    """The dock's "Open file..." showed a CT black and white (napari's [0, 1] for lazy float data, the first
    slice's range for integers): the layer's limits are the voxels' 0.5 and 99.5 percentiles (numpy's, here),
    as the plugin's reader gives them."""
    from napari_unwind.io import write_volume

    rng = np.random.default_rng(3)
    ct = np.full((40, 48, 56), -1000.0, np.float32)
    ct[:, 10:38, 8:48] = rng.normal(40.0, 30.0, (40, 28, 40))  # soft tissue
    ct[15:25, 20:28, 20:30] = 1800.0  # bone
    path = tmp_path / "ct.nrrd"
    write_volume(ct, path, spacing=(1.0, 0.8, 0.8), unit="millimeter")
    w = UnwindWidget(make_napari_viewer())
    wait(qtbot, w.open_scan(path))
    lo, hi = np.percentile(ct, [0.5, 99.5])
    clim = w.scan_layer.contrast_limits
    assert clim[0] == pytest.approx(lo, abs=0.01 * (hi - lo)) and clim[1] == pytest.approx(hi, abs=0.01 * (hi - lo))
