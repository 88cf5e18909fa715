"""The Export step's "Measure along the centreline" section (issue 24 item 2): on napari's sample fish, with its
true mask as the selection and the phantom's true deformation, Measure runs in a worker and the dock's plot draws
exactly the columns of :func:`napari_unwind.measure.measure` called directly on the same arrays; the section fits
napari's default dock width with the plot shown; "Save profile..." writes CSV, Parquet and PNG.

References: ``measure()`` called here (not through the dock), pyarrow's reader, the CSV module.
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
