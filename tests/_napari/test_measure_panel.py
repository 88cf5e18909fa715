"""The Export step's "Measure along the centreline" section (issue 24 item 2): on napari's sample fish, with its
true mask as the selection and the phantom's true deformation, Measure runs in a worker and the dock's plot draws
exactly the columns of :func:`napari_unwind.measure.measure` called directly on the same arrays; the section fits
napari's default dock width with the plot shown; "Save profile..." writes CSV, Parquet and PNG.

Its "labels:" choice (issue 24, measurements along the centreline): a Labels layer splitting the true mask at a
known plane gives one area column per label whose integrals along s are the labels' voxel counts (numpy), which
match ``measure()``'s areas of each half as a mask built here with numpy, which are zero where a station lies wholly
on the other side of the plane; the choice lists only 3D Labels layers of the scan's shape (not the dock's own),
follows renames and falls back to "(none)" when its layer is removed or changes shape.

References: ``measure()`` called here (not through the dock), numpy's voxel counts, pyarrow's reader, the CSV module.
Set ``UNWIND_MEASURE_SCREENSHOT`` to a path to keep the window's picture.
"""

from __future__ import annotations

import csv
import os

import numpy as np
import pytest

pytest.importorskip("napari")
pytest.importorskip("matplotlib")
pq = pytest.importorskip("pyarrow.parquet")

from test_dock_geometry import check_step, open_step, scroll_area  # noqa: E402 - the geometry test's checks
from test_workflow import wait  # noqa: E402

from napari_unwind.io import Volume  # noqa: E402
from napari_unwind.measure import measure  # noqa: E402

pytestmark = pytest.mark.gui


@pytest.fixture(scope="module")
def truth():
    """The sample fish's phantom (napari's "fish" sample is fish_phantom() with its defaults) and its deformation."""
    from napari_unwind.datasets import fish_phantom
    from napari_unwind.demo import true_deformation

    fish = fish_phantom()
    return fish, true_deformation(fish)


def test_the_dock_measures_the_sample_fish_and_plots_measures_columns(make_napari_viewer, qtbot, tmp_path, truth,
                                                                       monkeypatch):
    fish, d = truth
    viewer = make_napari_viewer(show=True)
    window = viewer.window._qt_window
    window.resize(1280, 800)                                  # napari's default window, the smaller of the two
    dock, w = viewer.window.add_plugin_dock_widget("napari-unwind", "Unwind")
    qtbot.waitExposed(window)
    layers = viewer.open_sample("napari-unwind", "fish")
    image = next(lyr for lyr in layers if lyr.name == "fish phantom")
    mask = next(lyr for lyr in layers if lyr.name == "fish phantom true mask")
    np.testing.assert_array_equal(image.data, fish.volume)    # the sample is this phantom
    w.use_layer(image)
    assert w.use_labels(mask) > 0, w.status.text()
    w.model.set_deformation(d)
    panel = w.export_step.measure_panel
    export = next(i for i in range(w.toolbox.count()) if "Export" in w.toolbox.itemText(i))
    open_step(qtbot, w, export)
    assert not panel.measure_button.isVisible()               # closed until opened
    qtbot.mouseClick(panel.toggle, qtbot_left())
    assert panel.measure_button.isVisible() and panel.measure_button.isEnabled()
    assert not panel.save_button.isEnabled()
    qtbot.mouseClick(panel.measure_button, qtbot_left())
    job = w.job
    assert job is not None and job.label == "measuring", w.status.text()
    wait(qtbot, w, job)
    qtbot.waitUntil(lambda: panel.canvas is not None and panel.canvas.isVisible(), timeout=10_000)

    # the reference: measure() here, on the same arrays, with the dock's choices (the mask, the scan as "scan")
    geometry = dict(spacing=fish.spacing, unit=fish.unit)
    direct = measure(d, mask=Volume(fish.mask.astype(np.uint8), **geometry),
                     channels={"scan": Volume(fish.volume, **geometry)})
    drawn = {line.get_gid(): line for ax in panel.canvas.figure.axes for line in ax.get_lines() if line.get_gid()}
    assert set(drawn) == {"curvature", "torsion", "twist", "area", "radius", "major_axis", "minor_axis",
                          "eccentricity", "scan_mean"}
    for name, line in drawn.items():
        np.testing.assert_array_equal(line.get_xdata(), direct["s"])
        np.testing.assert_array_equal(line.get_ydata(), direct[name], err_msg=name)
    assert panel.canvas.figure.axes[4].get_xlabel() == f"arc length s [{direct.units['s']}]"
    assert f"{len(direct)} stations" in panel.info.text() and panel.save_button.isEnabled()

    # the section, open with its plot, fits the default dock width (every control inside; no sideways bar)
    qtbot.wait(50)
    viewport_width = check_step(w, dock, export, f"1280x800 with the profile's plot, dock {dock.width()} px")
    assert panel.canvas.width() <= viewport_width
    target = os.environ.get("UNWIND_MEASURE_SCREENSHOT") or str(tmp_path / "measure_panel.png")
    scroll_area(w.export_step).ensureWidgetVisible(panel.canvas, 0, 0)  # the plot in view, as a user scrolls
    qtbot.wait(50)
    assert window.grab().save(target)
    assert w.export_step.grab().save(target.replace(".png", "_page.png"))  # the whole Export page

    # Save profile: the format by the suffix; an existing file is kept unless the dock's question says yes
    saved = {s: panel.save_profile(tmp_path / f"p{s}") for s in (".csv", ".parquet", ".png")}
    assert all(p is not None and p.exists() for p in saved.values()), w.status.text()
    table = pq.read_table(saved[".parquet"])
    for name in direct.names:
        got = np.asarray(table.column(name).to_numpy(zero_copy_only=False), dtype=float)
        np.testing.assert_array_equal(got, np.where(np.isfinite(direct[name]), direct[name], np.nan))
    rows = list(csv.reader(open(saved[".csv"])))
    assert rows[0][0] == f"s [{direct.units['s']}]" and len(rows) == len(direct) + 1
    direct.plot(tmp_path / "direct.png")
    assert saved[".png"].read_bytes() == (tmp_path / "direct.png").read_bytes()
    monkeypatch.setattr(w, "confirm_overwrite", lambda path: False)
    before = saved[".csv"].read_bytes()
    assert panel.save_profile(saved[".csv"]) is None and saved[".csv"].read_bytes() == before
    assert "kept" in w.status.text()
    assert panel.save_profile(tmp_path / "p.xlsx") is None and w.status.text().startswith("error: a profile is")

    # an edit of the deformation makes the profile stale: the section says so
    w.model.select_keyframe(1)
    w.model.tilt(0.01, axis="u")
    qtbot.waitUntil(lambda: "measure again" in panel.info.text(), timeout=5000)
    qtbot.waitUntil(lambda: w.refine_panel.preview.idle, timeout=20_000)


def qtbot_left():
    from qtpy.QtCore import Qt

    return Qt.MouseButton.LeftButton


def _docked_fish(make_napari_viewer, qtbot):
    """The dock at napari's default window with the sample fish: (viewer, dock widget, its QDockWidget, the scan's
    layer, the true mask's layer, the Export step's index); no scan chosen yet."""
    viewer = make_napari_viewer(show=True)
    window = viewer.window._qt_window
    window.resize(1280, 800)
    dock, w = viewer.window.add_plugin_dock_widget("napari-unwind", "Unwind")
    qtbot.waitExposed(window)
    layers = viewer.open_sample("napari-unwind", "fish")
    image = next(lyr for lyr in layers if lyr.name == "fish phantom")
    mask = next(lyr for lyr in layers if lyr.name == "fish phantom true mask")
    export = next(i for i in range(w.toolbox.count()) if "Export" in w.toolbox.itemText(i))
    return viewer, w, dock, image, mask, export


def _halves(fish, z0):
    """The true mask split at the plane axis0 = z0 (voxel index): label 1 before it, label 2 from it on."""
    z = np.arange(fish.mask.shape[0])[:, None, None]
    return np.where(fish.mask, np.where(z < z0, 1, 2), 0).astype(np.uint16)


def _items(combo):
    return [combo.itemText(i) for i in range(combo.count())]


def test_labels_give_each_labels_area_along_s(make_napari_viewer, qtbot, truth):
    fish, d = truth
    viewer, w, dock, image, mask, export = _docked_fish(make_napari_viewer, qtbot)
    w.use_layer(image)
    assert w.use_labels(mask) > 0, w.status.text()
    w.model.set_deformation(d)
    z0 = fish.mask.shape[0] // 2
    halves = _halves(fish, z0)
    layer = viewer.add_labels(halves, name="halves", scale=image.scale, translate=image.translate)
    panel = w.export_step.measure_panel
    open_step(qtbot, w, export)
    panel.set_open(True)
    assert "halves" in _items(panel.labels_combo)
    panel.labels_combo.setCurrentIndex(panel.labels_combo.findText("halves"))  # as a user picks it
    assert panel.labels_layer is layer
    qtbot.mouseClick(panel.measure_button, qtbot_left())
    job = w.job
    assert job is not None and job.label == "measuring", w.status.text()
    wait(qtbot, w, job)
    qtbot.waitUntil(lambda: panel.profile is not None and panel.canvas is not None, timeout=10_000)
    p = panel.profile
    assert [n for n in p.names if n.startswith("area_label_")] == ["area_label_1", "area_label_2"]
    a1, a2, s = p["area_label_1"], p["area_label_2"], p["s"]
    ds = float(s[1] - s[0])
    assert p.units["area_label_1"] == f"{p.units['s']}^2"

    # (1) the integral of each label's area along s is its volume: numpy's voxel count (a straight stretch of the
    # fish; the bends' inner and outer sides cancel), to 2 %
    voxel = float(np.prod(fish.spacing))
    for area, label in ((a1, 1), (a2, 2)):
        count = int(np.count_nonzero(halves == label))
        assert abs(float(np.sum(area)) * ds - count * voxel) <= 0.02 * count * voxel, (label, np.sum(area) * ds,
                                                                                       count)
    # (2) each label's area follows measure()'s area of that half as a mask built here (linear resampling against
    # the labels' nearest neighbour: within a tenth of the fish's largest cross-section), and the two add up to
    # the whole mask's area
    geometry = dict(spacing=fish.spacing, unit=fish.unit)
    whole = np.nan_to_num(measure(d, mask=Volume(fish.mask.astype(np.uint8), **geometry))["area"])
    tol = 0.1 * float(whole.max())
    for area, label in ((a1, 1), (a2, 2)):
        half = np.nan_to_num(measure(d, mask=Volume((halves == label).astype(np.uint8), **geometry))["area"])
        np.testing.assert_allclose(area, half, rtol=0, atol=tol, err_msg=f"label {label}")
    np.testing.assert_allclose(a1 + a2, whole, rtol=0, atol=tol)
    # (3) a station whose centre lies more than the fish's radius (8) and a margin from the plane holds only the
    # label of its side: the other's area is exactly 0; a station at the plane holds both
    z = (p["centre_0"] - image.translate[0]) / fish.spacing[0]
    before, after = z < z0 - 12, z > z0 + 12
    assert before.sum() > 40 and after.sum() > 40
    assert np.all(a2[before] == 0) and np.all(a1[after] == 0)
    assert np.all(a1[before & (whole > tol)] > 0) and np.all(a2[after & (whole > tol)] > 0)
    at = int(np.argmin(np.abs(z - z0)))
    assert a1[at] > 0 and a2[at] > 0
    # the plot's labels panel and the section's line
    drawn = {line.get_gid() for ax in panel.canvas.figure.axes for line in ax.get_lines()}
    assert {"area_label_1", "area_label_2", "area"} <= drawn
    assert "2 labels of 'halves'" in panel.info.text(), panel.info.text()

    # "(none)" again: no label columns
    panel.labels_combo.setCurrentIndex(0)
    qtbot.mouseClick(panel.measure_button, qtbot_left())
    wait(qtbot, w, w.job)
    qtbot.waitUntil(lambda: panel.profile is not p, timeout=10_000)
    assert not [n for n in panel.profile.names if n.startswith("area_label_")]
    qtbot.waitUntil(lambda: w.refine_panel.preview.idle, timeout=20_000)


def test_labels_choice_lists_the_scans_shape_and_falls_back_to_none(make_napari_viewer, qtbot, truth):
    fish, d = truth
    viewer, w, dock, image, mask, export = _docked_fish(make_napari_viewer, qtbot)
    panel = w.export_step.measure_panel
    combo = panel.labels_combo
    halves = _halves(fish, fish.mask.shape[0] // 2)
    layer = viewer.add_labels(halves, name="halves")
    assert _items(combo) == ["(none)"]                          # no scan yet: no shape to match
    w.use_layer(image)
    assert _items(combo) == ["(none)", "fish phantom true mask", "halves"]
    # another shape, a 2D layer, an Image layer of the scan's shape: not listed
    small = viewer.add_labels(np.zeros((20, 30, 30), np.uint8), name="small")
    viewer.add_labels(np.zeros(fish.mask.shape[1:], np.uint8), name="flat")
    viewer.add_image(fish.volume, name="another image")
    assert _items(combo) == ["(none)", "fish phantom true mask", "halves"]
    # a layer of the scan's shape added later: listed at once; the dock's own "features" layer: never
    extra = viewer.add_labels(np.zeros_like(halves), name="extra")
    assert _items(combo) == ["(none)", "fish phantom true mask", "halves", "extra"]
    w._features_layer = extra
    panel.refresh_labels()
    assert "extra" not in _items(combo)
    w._features_layer = None
    # a rename follows; the choice is kept
    combo.setCurrentIndex(combo.findText("halves"))
    layer.name = "parts"
    assert "parts" in _items(combo) and "halves" not in _items(combo)
    assert panel.labels_layer is layer and combo.currentText() == "parts"
    # the chosen layer changes shape: not listed, "(none)"; back to the scan's shape: listed, still "(none)"
    layer.data = np.zeros((20, 30, 30), np.uint16)
    assert panel.labels_layer is None and combo.currentText() == "(none)" and "parts" not in _items(combo)
    layer.data = halves
    assert "parts" in _items(combo) and panel.labels_layer is None
    # a layer of another shape made the scan's shape: listed
    small.data = np.zeros_like(halves)
    assert "small" in _items(combo)
    # the chosen layer removed: "(none)"
    assert panel.set_labels_layer(layer) and combo.currentText() == "parts"
    viewer.layers.remove(layer)
    assert panel.labels_layer is None and combo.currentText() == "(none)" and "parts" not in _items(combo)
    assert not panel.set_labels_layer(layer) and panel.labels_layer is None
    # the combo keeps to the dock's width with the section open and a long name (the dock is not widened)
    open_step(qtbot, w, export)
    panel.set_open(True)
    qtbot.wait(50)
    width = dock.width()
    small.name = "a_labels_layer_with_a_very_long_name_from_a_file_0.8um_reconstructed_segmentation.ome.zarr"
    assert panel.set_labels_layer(small)
    qtbot.wait(50)
    assert combo.isVisible()
    check_step(w, dock, export, f"1280x800 with a long labels name, dock {dock.width()} px")
    assert dock.width() == width and combo.width() < 0.9 * combo.fontMetrics().horizontalAdvance(small.name)
    # more labels than a profile takes: the core's refusal in the dock's one line
    many = viewer.add_labels(np.arange(halves.size, dtype=np.uint16).reshape(halves.shape) % 400 + 1,
                             name="many")
    assert panel.set_labels_layer(many)
    w.model.set_deformation(d)
    qtbot.mouseClick(panel.measure_button, qtbot_left())
    job = w.job
    assert job is not None and job.label == "measuring", w.status.text()
    qtbot.waitUntil(lambda: job.done, timeout=60_000)
    assert w.status.text().startswith("error: the label image has more than 256 labels"), w.status.text()
    assert "unwind" not in w.status.text() and "--" not in w.status.text()
    qtbot.waitUntil(lambda: w.refine_panel.preview.idle, timeout=20_000)
