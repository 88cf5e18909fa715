"""A mask as the selection (issue 21, item 5): a Labels layer (every label, one label, or the label under a click)
or a mask file, instead of the join tree's features.

References independent of the dock: the mask files read with pynrrd, the sample tank's true labels, and the
spinal cord's manual centreline (its length).
"""

import nrrd
import numpy as np
import pytest

pytest.importorskip("napari")

from test_workflow import click, wait  # noqa: E402

from napari_unwind._napari._widget import UnwindWidget  # noqa: E402

pytestmark = pytest.mark.gui


def test_a_mask_file_is_the_selection_and_the_cord_is_straightened(make_napari_viewer, qtbot, shared_data):
    """The spine MRI with its manual cord mask: the mask opened from its file is the selection voxel for voxel, and
    the skeleton of it is as long as the manual centreline (within 15 %)."""
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    wait(qtbot, w, w.open_scan(shared_data / "spine_t2.nrrd"))
    wait(qtbot, w, w.open_mask(shared_data / "spine_t2_cord_mask.nrrd"))
    truth, _ = nrrd.read(str(shared_data / "spine_t2_cord_mask.nrrd"), index_order="C")
    layer = viewer.layers["spine_t2_cord_mask.nrrd"]
    assert w.mask_choice == (layer, None)
    np.testing.assert_array_equal(np.asarray(w.mask()), truth != 0)
    assert f"{int((truth != 0).sum()):,} voxels" in w.segment_step.selection_label.text()
    assert w.ends_step.suggest_button.isEnabled() and w.skeleton_step.skeleton_button.isEnabled()
    wait(qtbot, w, w.suggest_ends())
    qtbot.waitUntil(lambda: w.idle, timeout=60_000)  # the new "ends" layer is shown a turn after it is added
    # the ends: large enough to see, and the view moved to the head (its slice, centred)
    ends = viewer.layers["ends"]
    head = np.asarray(ends.data)[0]
    assert np.all(ends.size >= 6 * max(w.volume.spacing))
    assert viewer.dims.point[0] == pytest.approx(head[0], abs=max(w.volume.spacing))
    np.testing.assert_allclose(viewer.scene.camera.center[-2:], head[-2:], atol=1e-6)
    viewer.window._qt_window.show()
    shot = viewer.screenshot(canvas_only=True, flash=False)
    h, wd = shot.shape[:2]
    middle = shot[h // 2 - 40:h // 2 + 40, wd // 2 - 40:wd // 2 + 40, :3].astype(int)
    yellow = (middle[..., 0] > 200) & (middle[..., 1] > 200) & (middle[..., 2] < 80)
    assert yellow.sum() > 30, "the head's marker is not drawn at the centre of the view"
    wait(qtbot, w, w.run_skeleton(), timeout=180_000)
    d = w.model.deformation
    manual = np.loadtxt(shared_data / "spine_t2_centerline_manual.csv", delimiter=",", skiprows=1)
    length = np.linalg.norm(np.diff(manual, axis=0) * np.asarray(w.volume.spacing), axis=1).sum()
    assert abs(d.length - length) < 0.15 * length, (d.length, length)
    qtbot.waitUntil(lambda: w.idle, timeout=60_000)  # the Refine panel's preview, the selection's measurement


def test_a_labels_layer_whole_one_label_or_the_label_clicked(make_napari_viewer, qtbot):
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    layers = viewer.open_sample("napari-unwind", "tank")
    image = next(lyr for lyr in layers if lyr.name == "tank")
    labels = next(lyr for lyr in layers if lyr.name == "tank true fish")
    truth = np.asarray(labels.data)
    w.use_layer(image)

    assert w.use_labels(labels) == int((truth > 0).sum())
    np.testing.assert_array_equal(np.asarray(w.mask()), truth > 0)
    assert w.use_labels(labels, label=3) == int((truth == 3).sum())
    np.testing.assert_array_equal(np.asarray(w.mask()), truth == 3)

    # a click on the mask layer (active) picks the label under it
    inside = np.argwhere(truth == 2)[len(np.argwhere(truth == 2)) // 2]
    world = inside * np.asarray(labels.scale) + np.asarray(labels.translate)
    viewer.layers.selection.active = labels
    click(labels, world, viewer=viewer)
    assert w.mask_choice == (labels, 2)
    np.testing.assert_array_equal(np.asarray(w.mask()), truth == 2)
    assert "label 2 of the mask 'tank true fish'" in w.segment_step.selection_label.text()

    # refusals, each one line; the selection stays as it was
    assert w.use_labels(labels, label=9) == 0
    assert w.status.text() == "error: the mask 'tank true fish' holds no voxel of label 9: pick another label"
    outside = np.argwhere(truth == 0)[0] * np.asarray(labels.scale) + np.asarray(labels.translate)
    assert w.use_labels(labels, at=outside) == 0
    assert "no label there" in w.status.text()
    # a box of the scan's grid where the viewer shows it (a mask cropped to its fish): placed there
    box = np.argwhere(truth == 2)
    lo, hi = box.min(axis=0), box.max(axis=0) + 1
    crop = (truth[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] == 2).astype(np.uint8)
    cropped = viewer.add_labels(crop, name="cropped", scale=labels.scale,
                                translate=np.asarray(labels.translate) + lo * np.asarray(labels.scale))
    assert w.use_labels(cropped) == int((truth == 2).sum())
    np.testing.assert_array_equal(np.asarray(w.mask()), truth == 2)
    assert f"Note: the mask 'cropped' (shape {crop.shape[0]} x" in w.status.text()  # said, as the CLI says it
    assert f"placed at voxel {lo[0]} x {lo[1]} x {lo[2]}" in w.status.text()
    w.use_labels(labels, label=2)
    # off the grid by half a voxel, or of another voxel size: refused, saying why
    off = viewer.add_labels(crop, name="off", scale=labels.scale,
                            translate=np.asarray(labels.translate) + (lo + 0.5) * np.asarray(labels.scale))
    assert w.use_labels(off) == 0
    assert "voxels off the scan's grid" in w.status.text()
    small = viewer.add_labels(truth[:, :10].copy(), name="cut", scale=2 * np.asarray(labels.scale))
    assert w.use_labels(small) == 0
    assert "must lie on the scan's voxel grid" in w.status.text()
    assert w.use_labels(image) == 0
    assert "is not a 3D Labels layer" in w.status.text()
    assert w.mask_choice == (labels, 2)

    # the mask layer removed: the steps that need a selection say so
    viewer.layers.remove(labels)
    assert not w.ends_step.suggest_button.isEnabled()
    assert w.suggest_ends() is None
    assert "was removed" in w.status.text()
    qtbot.waitUntil(lambda: w.idle, timeout=60_000)


def test_the_threshold_slider_grows_and_shrinks_the_selection(make_napari_viewer, qtbot):
    """The tank: a fish clicked, its mask measured (voxels, share of the scan, the default threshold); the slider
    to the left grows it, to the right shrinks it (each count against the core's refine_mask at the slider's
    threshold); "default" gives the default rule's mask again. The mask controls list the true labels layer."""
    from napari_unwind.segmentation import refine_mask, select

    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    layers = viewer.open_sample("napari-unwind", "tank")
    image = next(lyr for lyr in layers if lyr.name == "tank")
    truth = next(lyr for lyr in layers if lyr.name == "tank true fish")
    w.use_layer(image)
    assert not w.segment_step.iso_slider.isEnabled()
    wait(qtbot, w, w.segment())
    qtbot.waitUntil(lambda: w.idle and w.features is not None, timeout=60_000)
    inside = np.argwhere(np.asarray(truth.data) == 1)[len(np.argwhere(np.asarray(truth.data) == 1)) // 2]
    click(w._features_layer, inside * np.asarray(w.volume.spacing) + np.asarray(w.volume.origin), viewer=viewer)
    assert w.selected and w.segment_step.iso_slider.isEnabled() and not w.segment_step.iso_default_button.isEnabled()
    qtbot.waitUntil(lambda: "(default)" in w.segment_step.mask_info.text(), timeout=60_000)

    def count() -> int:
        return int(w.segment_step.mask_info.text().split("mask: ")[1].split(" voxels")[0].replace(",", ""))

    def reference(iso) -> int:
        return int(np.asarray(refine_mask(w.volume, select(w.features, ids=w.selected), features=w.features,
                                          isovalue=iso)).sum())

    default = count()
    assert default == reference(None)
    position = w.segment_step.iso_slider.value()
    for move in (-60, +60):
        w.segment_step.iso_slider.setValue(position + move)
        iso = w.segment_step._iso_at(position + move)
        qtbot.waitUntil(lambda iso=iso: f"{iso:.4g} (chosen)" in w.segment_step.mask_info.text(), timeout=60_000)
        assert count() == reference(iso)
        assert (count() > default) == (move < 0) and count() != default
    assert w.segment_step.iso_default_button.isEnabled()
    w.segment_step.iso_default_button.click()
    qtbot.waitUntil(lambda: "(default)" in w.segment_step.mask_info.text(), timeout=60_000)
    assert count() == default and w.workflow.isovalue is None

    # the mask controls: the true labels layer is listed (the dock's own layers are not); "Use mask" takes it
    names = [w.segment_step.mask_combo.itemText(i) for i in range(w.segment_step.mask_combo.count())]
    assert "tank true fish" in names and "features" not in names and "selection" not in names
    w.segment_step.mask_combo.setCurrentIndex(names.index("tank true fish"))
    w.segment_step.use_mask_button.click()
    assert w.mask_choice == (truth, None) and not w.segment_step.iso_slider.isEnabled()
    info = w.segment_step.mask_info
    qtbot.waitUntil(lambda: info.text().startswith("mask: ") and "threshold" not in info.text(),
                    timeout=60_000)  # a mask is taken as it is: no threshold
    assert count() == int((np.asarray(truth.data) > 0).sum())
    qtbot.waitUntil(lambda: w.idle, timeout=60_000)


def test_a_probability_map_opened_as_the_mask_file_is_thresholded_and_the_dock_says_so(make_napari_viewer, qtbot,
                                                                                        tmp_path):
    """A mask file holding a probability map (float, fractional values) opened in step 2: the selection is its
    voxels >= 0.5 (reference: numpy on the map written with pynrrd) and the status line says it was thresholded."""
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    layers = viewer.open_sample("napari-unwind", "tank")
    w.use_layer(next(lyr for lyr in layers if lyr.name == "tank"))
    truth = np.asarray(next(lyr for lyr in layers if lyr.name == "tank true fish").data) == 2
    rng = np.random.default_rng(5)
    prob = np.where(truth, rng.uniform(0.5, 1.0, truth.shape), rng.uniform(0.0, 0.5, truth.shape)).astype(np.float32)
    nrrd.write(str(tmp_path / "prob.nrrd"), prob, index_order="C")
    wait(qtbot, w, w.open_mask(tmp_path / "prob.nrrd"))
    np.testing.assert_array_equal(np.asarray(w.mask()), prob >= 0.5)
    assert "Note: the mask holds fractional values" in w.status.text()
    assert ">= 0.5 are the specimen" in w.status.text()


def test_a_mask_selection_is_saved_and_reopens_from_the_dock_and_file_open(make_napari_viewer, qtbot, tmp_path):
    """Issue 21 items 3/5: a session whose selection is a mask. A Labels layer without a file (the sample's true
    fish, one label) is written beside the session; a mask file opened in step 2 is recorded by its path and label.
    Both reopen as that selection in a fresh dock, and through File > Open into a viewer with the dock.
    Reference: the sample's own true labels, and the mask file read back with pynrrd."""
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.window.add_dock_widget(w, name="Unwind")
    layers = viewer.open_sample("napari-unwind", "tank")
    image = next(lyr for lyr in layers if lyr.name == "tank")
    labels = next(lyr for lyr in layers if lyr.name == "tank true fish")
    truth = np.asarray(labels.data) == 2
    w.use_layer(image)
    assert w.use_labels(labels, label=2) == int(truth.sum())
    wait(qtbot, w, w.suggest_ends())
    ends = w.endpoints()

    session = tmp_path / "fish two.unwind.json"
    wait(qtbot, w, w.save_session(session))
    mask_file = tmp_path / "fish two.mask.ome.zarr"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fish two.mask.ome.zarr", "fish two.scan.ome.zarr",
                                                          "fish two.unwind.json"]
    assert "fish two.mask.ome.zarr" in w.session_step.session_info.text()
    from napari_unwind.session import load_session

    seg = load_session(session).segmentation
    assert seg.mask == str(mask_file.absolute()) and seg.mask_label is None

    fresh = UnwindWidget(make_napari_viewer())
    wait(qtbot, fresh, fresh.load_session(session))
    qtbot.waitUntil(lambda: fresh.idle and fresh.mask_choice is not None, timeout=60_000)
    np.testing.assert_array_equal(np.asarray(fresh.mask()), truth)
    assert fresh.endpoints() == ends

    viewer3 = make_napari_viewer()
    w3 = UnwindWidget(viewer3)
    viewer3.window.add_dock_widget(w3, name="Unwind")
    viewer3.open(str(session), plugin="napari-unwind")
    qtbot.waitUntil(lambda: w3.idle and w3.mask_choice is not None, timeout=60_000)
    np.testing.assert_array_equal(np.asarray(w3.mask()), truth)

    # a mask file with several labels, one chosen: the session records the file and the label, writes nothing
    nrrd.write(str(tmp_path / "expert.nrrd"), np.asarray(labels.data), index_order="C")
    wait(qtbot, fresh, fresh.open_mask(tmp_path / "expert.nrrd", label=3))
    np.testing.assert_array_equal(np.asarray(fresh.mask()), np.asarray(labels.data) == 3)
    second = tmp_path / "fish three.unwind.json"
    wait(qtbot, fresh, fresh.save_session(second))
    assert not (tmp_path / "fish three.mask.ome.zarr").exists()
    seg = load_session(second).segmentation
    assert seg.mask == str((tmp_path / "expert.nrrd").absolute()) and seg.mask_label == 3
    again = UnwindWidget(make_napari_viewer())
    wait(qtbot, again, again.load_session(second))
    qtbot.waitUntil(lambda: again.idle and again.mask_choice is not None, timeout=60_000)
    np.testing.assert_array_equal(np.asarray(again.mask()), np.asarray(labels.data) == 3)
    # painted after it was chosen: the file no longer holds the selection, so the voxels are written
    layer = again.mask_choice[0]
    edited = np.asarray(layer.data).copy()
    edited[np.argwhere(edited == 3)[0][0]] = 0
    layer.data = edited
    again.use_labels(layer, label=3)
    third = tmp_path / "fish four.unwind.json"
    wait(qtbot, again, again.save_session(third))
    assert load_session(third).segmentation.mask == str((tmp_path / "fish four.mask.ome.zarr").absolute())
    for dock in (w, fresh, w3, again):
        qtbot.waitUntil(lambda dock=dock: dock.idle, timeout=60_000)
