"""The Export step's "Measure along the centreline" section: the profile of the specimen and its plot.

A collapsible section (closed until opened, so the Export page keeps its size): Measure runs the core's
:func:`napari_unwind.measure.measure_iter` in a worker with the dock's progress bar and Cancel, on the model's
deformation, the selection's mask (the cross-section columns; none without a selection), the scan (its intensity
as the ``scan`` channel) and, when one is chosen in "labels:", a Labels layer (each label's area along ``s``: an
``area_label_N`` column per label, as ``unwind measure --labels``), at the finest scan spacing. "labels:" lists
"(none)" and the viewer's 3D Labels layers of the scan's shape (not the dock's own "features" and "selection"),
kept up to date as layers are added, removed, renamed or given new data; a chosen layer that goes or changes
shape falls back to "(none)". Its voxels are read in the worker, integer labels as they are. The profile's plot
(:meth:`napari_unwind.measure.Profile.plot`, the same panels as ``unwind measure --plot``) is drawn in the dock on
matplotlib's Qt canvas. "Save profile..." writes it as CSV, Parquet or the PNG plot, by the suffix
(:meth:`~napari_unwind.measure.Profile.save`); an existing file is replaced only after the dock's confirmation.
Measured on this computer, whichever backend runs the steps.
"""

from __future__ import annotations

import os
from collections.abc import Generator
from pathlib import Path
from typing import Any

import numpy as np
from qtpy.QtCore import Qt
from qtpy.QtWidgets import (
    QComboBox,
    QFileDialog,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QSizePolicy,
    QToolButton,
    QVBoxLayout,
    QWidget,
)

from ...errors import InvalidInputError, UnwindError
from ...io._volume import unit_label
from ...progress import Progress
from .._workers import Job
from ._base import Step, fmt, labels_layers

#: The save dialog's filters: (filter, suffix); the typed suffix wins.
SAVE_FILTERS = (("CSV table (*.csv)", ".csv"), ("Parquet table (*.parquet)", ".parquet"), ("PNG plot (*.png)", ".png"))
#: The "labels:" choice of no label image.
NO_LABELS = "(none)"
#: Height of one panel of the plot in the dock (px): its y label, rotated, fits.
PANEL_HEIGHT = 170


class MeasurePanel(Step):
    """Measure the specimen along the centreline, show the profile's plot, save the profile (see the module)."""

    def __init__(self, dock: Any) -> None:
        super().__init__(dock)
        #: the last profile measured (None: none yet)
        self.profile: Any = None
        #: the plot's canvas (made at the first profile: matplotlib is imported then)
        self.canvas: Any = None
        self._measured_on: Any = None  # the deformation the profile was measured on
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.toggle = QToolButton()
        self.toggle.setText("Measure along the centreline")
        self.toggle.setToolTip("The specimen's profile along s: curvature, torsion, twist, cross-sections, the scan's "
                               "intensity; its plot, saved as CSV, Parquet or PNG")
        self.toggle.setCheckable(True)
        self.toggle.setToolButtonStyle(Qt.ToolButtonStyle.ToolButtonTextBesideIcon)
        self.toggle.setArrowType(Qt.ArrowType.RightArrow)
        self.toggle.setStyleSheet("QToolButton { border: none; }")
        self.toggle.toggled.connect(self.set_open)
        lay.addWidget(self.toggle)
        self.body = QWidget()
        body = QVBoxLayout(self.body)
        body.setContentsMargins(0, 0, 0, 0)
        self.need = QLabel("")
        self.need.setWordWrap(True)
        body.addWidget(self.need)
        row = QHBoxLayout()
        row.addWidget(QLabel("labels:"))
        self.labels_combo = QComboBox()
        self.labels_combo.setSizeAdjustPolicy(QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        self.labels_combo.setMinimumContentsLength(8)
        self.labels_combo.setMinimumWidth(1)  # a long layer name is cut at the dock's edge, never widens it
        self.labels_combo.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Fixed)
        self.labels_combo.setToolTip("A Labels layer of the scan's shape (parts, organs, a segmentation): the "
                                     "profile gets each label's cross-section area along s (an area_label_N column "
                                     "per label, nearest-neighbour); (none): no label areas")
        self.labels_combo.addItem(NO_LABELS, None)
        row.addWidget(self.labels_combo, 1)
        body.addLayout(row)
        self.measure_button, self.cancel_button = self.job_buttons(body, "Measure", self.measure)
        self.save_button = QPushButton("Save profile...")
        self.save_button.setToolTip("Write the profile: .csv or .parquet (units with each column), or .png (the plot)")
        self.save_button.clicked.connect(lambda: self.save_profile())
        body.addWidget(self.save_button)
        self.info = QLabel("")
        self.info.setWordWrap(True)
        self.info.setMinimumWidth(1)  # a long path has no break: cut at the dock's edge, never widen it
        body.addWidget(self.info)
        self.plot_box = QVBoxLayout()
        body.addLayout(self.plot_box)
        self.body.setVisible(False)
        lay.addWidget(self.body)
        # the Labels layers to choose from follow the viewer's layers (added, removed, renamed, new data)
        layers = self.viewer.layers
        layers.events.inserted.connect(self._on_layer_inserted)
        layers.events.removed.connect(self._on_layer_removed)
        for layer in layers:
            self._watch(layer)
        self.update_needs()

    def set_open(self, open_: bool) -> None:
        """Show or hide the section's controls and plot."""
        if self.toggle.isChecked() != bool(open_):
            self.toggle.setChecked(bool(open_))  # emits toggled: comes back here once
            return
        self.toggle.setArrowType(Qt.ArrowType.DownArrow if open_ else Qt.ArrowType.RightArrow)
        self.body.setVisible(bool(open_))

    # ---- labels: ----------------------------------------------------------------------------------------------------
    @property
    def labels_layer(self) -> Any:
        """The Labels layer chosen in "labels:" (None: "(none)")."""
        return self.labels_combo.currentData()

    def set_labels_layer(self, layer: Any) -> bool:
        """Choose ``layer`` (None: "(none)") in "labels:"; False (and "(none)") when it is not one of the listed."""
        self.refresh_labels()
        index = self.labels_combo.findData(layer) if layer is not None else 0
        self.labels_combo.setCurrentIndex(max(index, 0))
        return index >= 0

    def refresh_labels(self, event: Any = None) -> None:
        """List "(none)" and the viewer's Labels layers of the scan's shape; keep the choice while it is listed."""
        volume = self.dock.volume
        found = labels_layers(self.dock, tuple(volume.shape)) if volume is not None else []
        combo, current = self.labels_combo, self.labels_combo.currentData()
        listed = [combo.itemData(i) for i in range(1, combo.count())]
        names = [combo.itemText(i) for i in range(1, combo.count())]
        if len(listed) == len(found) and all(a is b for a, b in zip(listed, found, strict=True)) and \
                names == [layer.name for layer in found]:
            return  # nothing changed (most layer events): the open popup stays as it is
        combo.blockSignals(True)
        combo.clear()
        combo.addItem(NO_LABELS, None)
        for layer in found:
            combo.addItem(layer.name, layer)
        index = next((i + 1 for i, layer in enumerate(found) if layer is current), 0)
        combo.setCurrentIndex(index)  # a chosen layer gone, or of another shape now: back to "(none)"
        combo.blockSignals(False)

    def _watch(self, layer: Any) -> None:
        from napari.layers import Labels

        if isinstance(layer, Labels):
            layer.events.name.connect(self.refresh_labels)
            layer.events.data.connect(self.refresh_labels)

    def _on_layer_inserted(self, event: Any) -> None:
        self._watch(event.value)
        self.refresh_labels()

    def _on_layer_removed(self, event: Any) -> None:
        layer = event.value
        for emitter in (getattr(layer.events, "name", None), getattr(layer.events, "data", None)):
            if emitter is not None:
                emitter.disconnect(self.refresh_labels)
        self.refresh_labels()

    def update_needs(self) -> None:
        self.refresh_labels()  # the scan may have changed: its shape decides the layers listed
        d, scan = self.workflow.edit.deformation, self.dock.volume is not None
        if d is None or not scan:
            self.need.setText("Needs a scan and a deformation (step 4 or a session).")
        else:
            has_mask = self.dock.has_selection
            self.need.setText("The specimen's cross-sections come from the selection (step 2)." if has_mask else
                              "No selection (step 2): the profile has the curve and the scan's intensity only.")
        self.measure_button.setEnabled(d is not None and scan)
        self.save_button.setEnabled(self.profile is not None)
        if self.profile is not None and self._measured_on is not d:
            self.info.setText(f"{self._summary()}; the deformation changed since: measure again")

    def _summary(self) -> str:
        p = self.profile
        unit = p.units.get("s", "")
        return f"{len(p)} stations, s = 0 to {float(p['s'][-1]):.4g} {unit}, {len(p.columns)} columns"

    def measure(self) -> Job | None:
        """Measure the specimen along the model's deformation (worker, progress, Cancel); the plot shows it."""
        from ...io import Volume
        from ...measure import measure_iter

        dock, workflow = self.dock, self.workflow
        try:
            volume = dock.volume
            if volume is None:
                raise InvalidInputError("there is no scan yet: pick an Image layer or open a file (step 1)")
            d = workflow.edit.deformation
            if d is None:
                raise InvalidInputError("there is no deformation yet: compute the skeleton (step 4) or open a session")
            selected = dock.has_selection
            if selected:
                dock._check_selection()
            labels_layer = self.labels_layer
            labels_data = None
            if labels_layer is not None:
                if labels_layer not in self.viewer.layers:
                    raise InvalidInputError(f"the Labels layer {labels_layer.name!r} is no longer in the viewer: "
                                            "choose another in \"labels:\" or (none)")
                labels_data = labels_layer.data[0] if getattr(labels_layer, "multiscale", False) else labels_layer.data
                if tuple(labels_data.shape) != tuple(volume.shape):
                    raise InvalidInputError(
                        f"the Labels layer {labels_layer.name!r} has {fmt(labels_data.shape, 6)} voxels, the scan "
                        f"{fmt(volume.shape, 6)}: choose a Labels layer of the scan's shape in \"labels:\" or (none)")
            # the Export page's other channels (when "with the other channels" is ticked) are measured too
            channels = {"scan": volume}
            for v in dock.export_step.channels_box.volumes():
                name = str(v.metadata.get("channel"))
                if name in channels:
                    raise InvalidInputError(f"two channels are named {name!r}: rename a layer")
                channels[name] = v
        except UnwindError as exc:
            self._fail(exc)
            return None
        self.set_open(True)

        def make() -> Generator[Progress, None, Any]:
            mask = None
            if selected:  # the features refined by the pipeline's select step, or the chosen mask: in the worker
                mask = Volume(workflow.mask().astype("uint8"), spacing=volume.spacing, origin=volume.origin,
                              unit=volume.unit)
            labels = None
            if labels_data is not None:  # the layer's voxels read here, in the worker (a lazy layer loads now)
                data = np.asarray(labels_data)
                labels = Volume(data.astype(np.uint8) if data.dtype == bool else data, spacing=volume.spacing,
                                origin=volume.origin, unit=volume.unit)
            return (yield from measure_iter(d, mask=mask, labels=labels, channels=channels))

        def done(profile: Any) -> None:
            self.profile, self._measured_on = profile, d
            parts = [n for n in profile.names if n.startswith("area_label_")]
            text = self._summary() + ("" if selected else " (no selection: no cross-sections)")
            if labels_layer is not None:
                text += f"; {len(parts)} label{'s' if len(parts) != 1 else ''} of {labels_layer.name!r}"
            self.info.setText(text)
            try:
                self.show_plot()
            except UnwindError as exc:  # no matplotlib: the profile is there to save as a table all the same
                self.info.setText(f"{self.info.text()}; {exc}")
            self._say(f"measured {len(profile)} stations along {d.length:.4g} {unit_label(d.unit)}")

        return dock._start(make, "measuring", done, (self.cancel_button,))

    def show_plot(self) -> None:
        """Draw the profile's plot in the section (the canvas is made the first time)."""
        from ...measure import _need, _plot_panels

        _need("matplotlib", "plot", "the plot")
        from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
        from matplotlib.figure import Figure

        n = len(_plot_panels(self.profile, None))
        if self.canvas is None:
            self.canvas = FigureCanvasQTAgg(Figure(figsize=(4.0, 3.0), dpi=100, layout="constrained"))
            self.canvas.setMinimumWidth(1)  # the plot takes the dock's width, never widens it
            self.canvas.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Fixed)
            self.plot_box.addWidget(self.canvas)
        height = PANEL_HEIGHT * n + 40
        self.canvas.setFixedHeight(height)
        # the figure at the section's width before drawing: the legends' columns follow it
        fig, ratio = self.canvas.figure, self.canvas.device_pixel_ratio
        fig.set_size_inches(max(self.body.width(), 200) * ratio / fig.dpi, height * ratio / fig.dpi)
        self.profile.plot(figure=fig)
        self.canvas.draw_idle()

    def save_profile(self, path: str | os.PathLike | None = None) -> Path | None:
        """Write the profile to ``path`` (asked for when None): .csv, .parquet or .png (the plot), by its suffix."""
        from ...measure import profile_format

        if self.profile is None:
            self._fail(InvalidInputError("there is no profile yet: click Measure first"))
            return None
        if path is None:
            filters = ";;".join(f for f, _ in SAVE_FILTERS)
            path, chosen = QFileDialog.getSaveFileName(self, "Save the profile", "profile.csv", filters,
                                                       options=QFileDialog.Option.DontConfirmOverwrite)
            if not path:
                return None
            if not Path(path).suffix:
                path += dict(SAVE_FILTERS).get(chosen, ".csv")
        target = Path(path).expanduser()
        try:
            profile_format(target)
            overwrite = False
            if target.exists():
                if not self.dock.confirm_overwrite(target):
                    self._say(f"not saved: {target} was kept")
                    return None
                overwrite = True
            written = self.profile.save(target, overwrite=overwrite)
        except UnwindError as exc:
            self._fail(exc)
            return None
        self.info.setText(f"{self._summary()}\nsaved: {written}")
        self._say(f"profile saved to {written}")
        return written
