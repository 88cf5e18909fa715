"""A session saved from napari's sample data (issue 21, item 3): File > Open Sample > Tank, select a fish, ends,
skeleton, Save session. Before, the dock refused ("the layer is not from a file") and its advice failed. Now the
scan is written beside the session (``<name>.scan.ome.zarr``) and the session records it; the session reopens with
its selection, ends and deformation, in a fresh dock and through File > Open.

References: the sample's own true labels (the fish selected is the one the click was on) and the sample's voxels
(the written scan holds them bit for bit).
"""

import numpy as np
import pytest

pytest.importorskip("napari")

from test_workflow import click, wait  # noqa: E402

from napari_unwind._napari._widget import UnwindWidget  # noqa: E402
from napari_unwind.io import open_volume  # noqa: E402
from napari_unwind.session import load_session  # noqa: E402

pytestmark = pytest.mark.gui


def _tank(viewer):
    layers = viewer.open_sample("napari-unwind", "tank")
    image = next(lyr for lyr in layers if lyr.name == "tank")
    truth = next(lyr for lyr in layers if lyr.name == "tank true fish")
    return image, truth


def test_a_session_saved_from_the_sample_tank_reopens(make_napari_viewer, qtbot, tmp_path):
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.window.add_dock_widget(w, name="Unwind")
    image, truth = _tank(viewer)
    w.use_layer(image)
    assert w.volume is not None and not w.volume.source  # a layer in memory: no file

    wait(qtbot, w, w.segment())
    qtbot.waitUntil(lambda: w.idle and w.features is not None, timeout=60_000)
    fish = truth.data == 1
    inside = np.argwhere(fish)[len(np.argwhere(fish)) // 2]
    click(w._features_layer, inside * np.asarray(w.volume.spacing) + np.asarray(w.volume.origin), viewer=viewer)
    assert w.selected, w.status.text()
    chosen = np.isin(w.features.labels, w.selected)
    assert (chosen & fish).sum() > 0.8 * fish.sum() and (chosen & (truth.data > 1)).sum() == 0
    wait(qtbot, w, w.suggest_ends())
    wait(qtbot, w, w.run_skeleton(), timeout=180_000)
    d0, ends, selected = w.model.deformation, w.endpoints(), list(w.selected)
    assert d0 is not None

    session = tmp_path / "tank fish.unwind.json"
    wait(qtbot, w, w.save_session(session))
    scan_file = tmp_path / "tank fish.scan.ome.zarr"
    assert session.exists() and scan_file.is_dir(), sorted(p.name for p in tmp_path.iterdir())
    assert "tank fish.scan.ome.zarr" in w.session_step.session_info.text()
    recorded = load_session(session)
    assert recorded.source.path == str(scan_file.absolute())
    assert recorded.twist is not None and recorded.twist.source == "estimated"  # the skeleton's twist profile
    written = open_volume(scan_file)
    np.testing.assert_array_equal(np.asarray(written.data), np.asarray(image.data))
    assert written.spacing == pytest.approx(tuple(image.scale)) and written.unit == w.volume.unit
    # saved again (the dock now works on that file): nothing else written, the same session
    wait(qtbot, w, w.save_session(session))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tank fish.scan.ome.zarr", "tank fish.unwind.json"]

    # a fresh dock of a fresh viewer: selection, ends, deformation
    viewer2 = make_napari_viewer()
    w2 = UnwindWidget(viewer2)
    wait(qtbot, w2, w2.load_session(session))
    qtbot.waitUntil(lambda: w2.idle and bool(w2.selected), timeout=60_000)
    assert w2.model.deformation.to_dict() == d0.to_dict()
    assert w2.endpoints() == ends
    assert w2.selected == selected
    again = tmp_path / "again.unwind.json"  # saved from the reopened session: the twist profile kept
    wait(qtbot, w2, w2.save_session(again))
    assert load_session(again).twist == recorded.twist

    # File > Open of the session in a third viewer: the scan, the ends and the curve as layers
    viewer3 = make_napari_viewer()
    layers = viewer3.open(str(session), plugin="napari-unwind")
    names = {lyr.name for lyr in layers}
    assert "ends" in names and "curve" in names, names
    ends_layer = next(lyr for lyr in layers if lyr.name == "ends")
    world = np.asarray([ends.head, ends.tail]) * np.asarray(w.volume.spacing) + np.asarray(w.volume.origin)
    np.testing.assert_allclose(np.asarray(ends_layer.data)[:, -3:], world, atol=1e-6)
    qtbot.waitUntil(lambda: w.idle and w2.idle, timeout=60_000)  # the Refine panels' previews


def test_a_scan_file_in_the_way_is_named_and_nothing_is_written(make_napari_viewer, tmp_path):
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    image, _ = _tank(viewer)
    w.use_layer(image)
    (tmp_path / "s.scan.ome.zarr").mkdir()
    (tmp_path / "s.scan.ome.zarr" / "thesis.docx").write_text("mine")
    assert w.save_session(tmp_path / "s.unwind.json") is None
    assert w.status.text().startswith("error: the scan 'tank' has no file, and the session would write it to ")
    assert "choose another session name" in w.status.text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.scan.ome.zarr"]
    assert (tmp_path / "s.scan.ome.zarr" / "thesis.docx").read_text() == "mine"
