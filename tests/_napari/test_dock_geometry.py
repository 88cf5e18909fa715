"""Issue 21: every step of the Unwind dock works at napari's default window and dock geometry.

The dock is added the way napari adds the plugin's widget (``add_plugin_dock_widget``, the manifest's "Unwind"),
at the width napari gives it (never widened here), in a main window of 1280 x 800 and of 1600 x 1200. Each step
is made current in turn; every visible control of it (button, check box, combo box, slider, spin box, line edit)
must lie inside the visible viewport of its step horizontally, and no horizontal scroll bar may show (vertical
scrolling is allowed). The Refine step is checked again with a deformation loaded (all its controls in use).
Set ``UNWIND_DOCK_SCREENSHOT`` to a path to keep the window's picture with the Refine step open at 1600 x 1200.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

pytest.importorskip("napari")

from qtpy.QtCore import QPoint, Qt  # noqa: E402
from qtpy.QtWidgets import (  # noqa: E402
    QAbstractButton,
    QAbstractSpinBox,
    QComboBox,
    QLineEdit,
    QScrollArea,
    QScrollBar,
    QSlider,
)

from napari_unwind.deformation import Deformation  # noqa: E402

pytestmark = pytest.mark.gui

GEOMETRIES = ((1280, 800), (1600, 1200))
CONTROLS = (QAbstractButton, QComboBox, QSlider, QAbstractSpinBox, QLineEdit)
#: A scan's layer name as a file gives it (the layer list shows it whole: it must not widen the dock).
LONG_NAME = "fish_2024-03-11_microCT_whole_body_0.8um_reconstructed_stack_final.ome.zarr"


def rod(shape=(48, 32, 32)):
    """A bright rod in a dim volume (as test_widget's)."""
    rng = np.random.default_rng(0)
    a = (rng.random(shape) * 200).astype(np.uint16)
    z, y, x = np.indices(shape)
    a[(z > 6) & (z < shape[0] - 6) & ((y - 16) ** 2 + (x - 16) ** 2 < 16)] = 3000
    return a


@pytest.fixture(params=GEOMETRIES, ids=[f"{w}x{h}" for w, h in GEOMETRIES])
def docked(request, make_napari_viewer, qtbot):
    """(viewer, the Unwind widget, its QDockWidget, the window size) in a shown main window of the given size."""
    viewer = make_napari_viewer(show=True)
    window = viewer.window._qt_window
    window.resize(*request.param)
    dock, w = viewer.window.add_plugin_dock_widget("napari-unwind", "Unwind")  # as napari's Plugins menu does
    qtbot.waitExposed(window)
    qtbot.wait(50)
    assert (window.width(), window.height()) == request.param, "the window did not take the geometry asked for"
    yield viewer, w, dock, request.param
    if w.refine_panel is not None:
        qtbot.waitUntil(lambda: w.refine_panel.preview.idle, timeout=20000)  # no result may reach a closed viewer


def scroll_area(page):
    """The QScrollArea that shows a step's page (QToolBox puts every page in one)."""
    a = page.parentWidget()
    while a is not None and not isinstance(a, QScrollArea):
        a = a.parentWidget()
    assert a is not None, "a step's page outside any scroll area"
    return a


def open_step(qtbot, w, index):
    w.toolbox.setCurrentIndex(index)
    qtbot.waitUntil(lambda: w.toolbox.widget(index).isVisible(), timeout=5000)
    qtbot.wait(30)  # the layouts settle (the scroll area's bars follow the page's size)


def check_step(w, dock, index, where):
    """Every visible control of step ``index`` inside its viewport and the dock horizontally; no horizontal bar."""
    page = w.toolbox.widget(index)
    area = scroll_area(page)
    viewport = area.viewport()
    name = f"{where}, step {w.toolbox.itemText(index)!r}"
    left = viewport.mapTo(dock, QPoint(0, 0)).x()
    assert left >= 0 and left + viewport.width() <= dock.width(), f"{name}: the step's viewport leaves the dock"
    assert not area.horizontalScrollBar().isVisible(), (
        f"{name}: horizontal scroll bar (page needs {page.minimumSizeHint().width()} px, viewport "
        f"{viewport.width()} px)")
    controls = [c for c in page.findChildren(CONTROLS) if c.isVisible()]
    if isinstance(page, CONTROLS) and page.isVisible():
        controls.append(page)
    assert controls or index == w.toolbox.count() - 1, f"{name}: no visible control found"
    for c in controls:
        x = c.mapTo(viewport, QPoint(0, 0)).x()
        label = getattr(c, "text", lambda: "")() or c.toolTip()[:40] or type(c).__name__
        assert x >= 0 and x + c.width() <= viewport.width(), (
            f"{name}: {type(c).__name__} {label!r} spans x {x}..{x + c.width()} of a {viewport.width()} px viewport")
        assert c.width() >= min(c.minimumSizeHint().width(), c.sizeHint().width()), (
            f"{name}: {type(c).__name__} {label!r} squeezed to {c.width()} px, below its minimum "
            f"{c.minimumSizeHint().width()} px (its text is cut)")
    bars = [b for b in dock.findChildren(QScrollBar) if b.orientation() == Qt.Orientation.Horizontal
            and b.isVisible()]  # the feature table's columns too fit the dock
    assert not bars, f"{name}: a horizontal scroll bar shows in {[type(b.parentWidget()).__name__ for b in bars]}"
    return viewport.width()


def test_every_step_fits_the_default_dock_width(docked, qtbot):
    viewer, w, dock, geometry = docked
    window = viewer.window._qt_window
    w.use_layer(viewer.add_image(rod(), name=LONG_NAME))
    assert dock.x() + dock.width() <= window.width(), "the dock leaves the window"
    # the steps get the dock's height (napari adds a stretch under a dock without a vertically expanding widget,
    # weighted by the docks opened before: the open step was left a few lines tall)
    assert w.toolbox.height() + w.status.height() + 40 >= w.height(), (
        f"the steps get {w.toolbox.height()} of the dock's {w.height()} px")
    spacers = [i for i in range(w.layout().count()) if w.layout().itemAt(i).spacerItem() is not None]
    assert not spacers, "napari put a stretch under the steps (its weight grows with the docks opened before)"
    widths = {}
    for i in range(w.toolbox.count()):
        open_step(qtbot, w, i)
        widths[w.toolbox.itemText(i)] = check_step(w, dock, i, f"{geometry}, dock {dock.width()} px")
    for button in w.toolbox.findChildren(QAbstractButton):  # the steps' own title buttons
        if button.isVisible() and button.parentWidget() is w.toolbox:
            assert button.mapTo(dock, QPoint(0, 0)).x() + button.width() <= dock.width()


def test_the_refine_step_with_a_deformation_fits_the_default_dock_width(docked, qtbot, tmp_path):
    viewer, w, dock, geometry = docked
    w.use_layer(viewer.add_image(rod(), name=LONG_NAME))
    refine = next(i for i in range(w.toolbox.count()) if "Refine" in w.toolbox.itemText(i))
    open_step(qtbot, w, refine)
    d = Deformation.from_polyline(np.array([[8.0, 16, 16], [24, 16, 16], [40, 16, 16]]), spacing=1.0,
                                  cage_half_extent=6.0)
    w.model.set_deformation(d)
    w.model.select_keyframe(1)
    w.model.tilt(0.01, axis="u")  # undo in use
    w.model.select_keyframe(1)
    p = w.refine_panel
    qtbot.waitUntil(lambda: not p.pending and p.preview.idle, timeout=20000)
    qtbot.wait(50)
    assert not p.hint.isVisible() and p.delete_button.isEnabled() and p.undo_button.isEnabled()
    for button in (p.delete_button, p.tilt_buttons["tilt about v +1 degree"], p.redo_button, p.preview_check,
                   p.finer_button, p.live_check, p.bent_check, p.pad_head, p.pad_tail):
        assert button.isVisible()
    check_step(w, dock, refine, f"{geometry} with a deformation, dock {dock.width()} px")
    if geometry == (1600, 1200):
        target = os.environ.get("UNWIND_DOCK_SCREENSHOT") or str(tmp_path / "refine_default_width.png")
        assert viewer.window._qt_window.grab().save(target)


def test_the_feature_table_fits_the_default_dock_width(docked, qtbot):
    """The Segment step with features shown: the table's columns share its width (no horizontal scroll bar), and
    every header and value is shown whole."""
    viewer, w, dock, geometry = docked
    w.use_layer(viewer.add_image(rod(), name=LONG_NAME))
    job = w.segment()
    assert job is not None, w.status.text()
    qtbot.waitUntil(lambda: job.done and w.idle and w.features is not None, timeout=60000)
    segment = next(i for i in range(w.toolbox.count()) if "Segment" in w.toolbox.itemText(i))
    open_step(qtbot, w, segment)
    table = w.segment_step.table
    assert table.rowCount() == len(w.features.stats) > 0
    assert dock.width() <= 420, f"napari's default dock is ~400 px wide, this one {dock.width()} px"
    where = f"{geometry}, dock {dock.width()} px, features shown"
    check_step(w, dock, segment, where)
    assert not table.horizontalScrollBar().isVisible(), f"{where}: the feature table scrolls sideways"
    header = table.horizontalHeader()
    assert header.length() <= table.viewport().width(), (
        f"{where}: the columns need {header.length()} px of the table's {table.viewport().width()} px")
    for col in range(table.columnCount()):
        name = table.horizontalHeaderItem(col).text()
        width = table.columnWidth(col)
        assert width >= header.sectionSizeHint(col), f"{where}: the header {name!r} is cut ({width} px)"
        assert width >= table.sizeHintForColumn(col), f"{where}: the values of {name!r} are cut ({width} px)"
