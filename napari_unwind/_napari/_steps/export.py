"""Step 6, Export: format, spacing, order, padding, "allow folds" and path; the pipeline's export step in a worker."""

from __future__ import annotations

import os
from collections.abc import Generator
from dataclasses import replace
from pathlib import Path
from typing import Any

from qtpy.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFileDialog,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QMessageBox,
    QPushButton,
    QSpinBox,
    QVBoxLayout,
)

from ...errors import InvalidInputError, UnwindError
from ...io import open_volume
from ...io._volume import unit_label
from ...pipeline import ExportOptions
from ...progress import Progress
from .._messages import for_dock
from .._reader import contrast_limits
from .._workers import Job
from ._base import Step
from .channels import ChannelsBox
from .measure import MeasurePanel

#: Export formats offered: (label, suffix); any suffix write_volume knows may also be typed.
EXPORT_FORMATS = (("OME-Zarr", ".ome.zarr"), ("NRRD", ".nrrd"), ("NIfTI", ".nii.gz"), ("TIFF", ".tif"))


class ExportStep(Step):
    """The export page (its fields start at the pipeline's :class:`~napari_unwind.pipeline.ExportOptions`
    defaults) and :func:`napari_unwind.pipeline.export_step` through the workflow, in a worker with progress and
    Cancel; the written file opens as a layer. An existing file is replaced only after the dock's confirmation."""

    def __init__(self, dock: Any) -> None:
        super().__init__(dock)
        #: the last file written (None: nothing exported yet)
        self.exported: Path | None = None
        lay = QVBoxLayout(self)
        self.export_need = QLabel("")
        self.export_need.setWordWrap(True)
        lay.addWidget(self.export_need)
        form = QFormLayout()
        form.setFieldGrowthPolicy(QFormLayout.FieldGrowthPolicy.AllNonFixedFieldsGrow)  # fields take the dock's width
        self.format_combo = QComboBox()
        for label, suffix in EXPORT_FORMATS:
            self.format_combo.addItem(f"{label} ({suffix})", suffix)
        self.format_combo.activated.connect(self._on_format_chosen)
        form.addRow("format", self.format_combo)
        self.spacing_box = QDoubleSpinBox()
        self.spacing_box.setDecimals(4)
        self.spacing_box.setRange(0.0, 1e6)
        self.spacing_box.setSpecialValueText("finest scan spacing")
        self.spacing_box.setToolTip("Isotropic output voxel size (physical units); 0: the scan's finest spacing")
        form.addRow("spacing", self.spacing_box)
        self.order_combo = QComboBox()
        for order, label in ((1, "1 linear"), (3, "3 cubic"), (0, "0 nearest (labels)")):
            self.order_combo.addItem(label, order)
        form.addRow("order", self.order_combo)
        self.pad_box = QSpinBox()
        self.pad_box.setRange(0, 100000)
        self.pad_box.setToolTip("Extra slices at each end beyond the deformation's own padding")
        form.addRow("padding (slices)", self.pad_box)
        self.allow_folds_box = QCheckBox("allow folds")
        self.allow_folds_box.setToolTip("Export even where the deformation folds over the specimen; a fold over "
                                        "empty cage corners only is exported anyway, with a warning")
        form.addRow("", self.allow_folds_box)
        self.channels_box = ChannelsBox(dock)  # the other Image layers of the scan's grid, as one image
        form.addRow("channels", self.channels_box)
        self.show_options(self.workflow.options.export)
        row = QHBoxLayout()
        self.path_edit = QLineEdit()
        self.path_edit.setPlaceholderText("straight.ome.zarr")
        self.path_edit.textChanged.connect(self._on_path_edited)
        browse = QPushButton("...")
        browse.clicked.connect(self._export_dialog)
        row.addWidget(self.path_edit, 1)
        row.addWidget(browse)
        form.addRow("path", row)
        lay.addLayout(form)
        self.export_button, self.export_cancel = self.job_buttons(
            lay, "Export", lambda: self.export(self.path_edit.text()))
        self.export_info = QLabel("")
        self.export_info.setWordWrap(True)
        self.export_info.setMinimumWidth(1)  # the written path has no break: cut at the dock's edge, never widen it
        lay.addWidget(self.export_info)
        self.measure_panel = MeasurePanel(dock)  # the profile along the centreline, its plot (collapsible)
        lay.addWidget(self.measure_panel)
        lay.addStretch(1)

    def update_needs(self) -> None:
        scan = self.dock.volume is not None
        d = self.workflow.edit.deformation
        self.export_need.setText("Needs a scan and a deformation (step 4 or a session)." if d is None or not scan
                                 else f"deformation: length {d.length:.4g} {unit_label(d.unit)}, {len(d)} keyframes")
        self.export_button.setEnabled(d is not None and scan)
        self.channels_box.update_layers()
        self.measure_panel.update_needs()

    def _on_format_chosen(self, index: int) -> None:
        from ...io._formats import _suffix

        suffix = self.format_combo.itemData(index)
        text = self.path_edit.text().strip() or "straight"
        path = Path(text)
        try:
            old = _suffix(path)
        except Exception:  # noqa: BLE001 - any name without a known suffix
            old = ""
        stem = path.name[: len(path.name) - len(old)] if old and path.name.lower().endswith(old) else path.name
        self.path_edit.setText(str(path.with_name(stem + suffix)))

    def _on_path_edited(self, text: str) -> None:
        for i in range(self.format_combo.count()):
            if text.lower().endswith(self.format_combo.itemData(i)):
                self.format_combo.setCurrentIndex(i)
                return

    def _export_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Export the straight volume", self.path_edit.text(),
                                              options=QFileDialog.Option.DontConfirmOverwrite)
        if path:
            self.path_edit.setText(path)

    def confirm_overwrite(self, path: Path) -> bool:
        """Ask before replacing an existing file (saving is explicit, never on close)."""
        answer = QMessageBox.question(self, "Replace?", f"{path} exists. Replace it with the new export?",
                                      QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.No,
                                      QMessageBox.StandardButton.No)
        return answer == QMessageBox.StandardButton.Yes

    def show_options(self, options: ExportOptions) -> None:
        """Set the export page's fields to ``options`` (the pipeline's defaults when the dock starts)."""
        self.spacing_box.setValue(options.spacing or 0.0)
        self.order_combo.setCurrentIndex(max(0, self.order_combo.findData(options.order)))
        self.pad_box.setValue(int(options.pad))
        self.allow_folds_box.setChecked(bool(options.allow_folds))

    def export_options(self) -> ExportOptions:
        """The pipeline's export options with the export page's fields (spacing, order, padding, allow folds)."""
        return replace(self.workflow.options.export, spacing=self.spacing_box.value() or None,
                       order=int(self.order_combo.currentData()), pad=int(self.pad_box.value()),
                       allow_folds=self.allow_folds_box.isChecked())

    def export(self, path: str | os.PathLike) -> Job | None:
        """Straighten the scan with the model's deformation and write ``path`` (worker, progress, Cancel); the
        written file opens as a layer."""
        from ...io._formats import output_format

        dock = self.dock
        try:
            if dock.volume is None:
                raise InvalidInputError("there is no scan yet: pick an Image layer or open a file (step 1)")
            if self.workflow.edit.deformation is None:
                raise InvalidInputError("there is no deformation yet: compute the skeleton (step 4) or open a session")
            if not str(path).strip():
                raise InvalidInputError("give the export's path (its suffix names the format, e.g. straight.nrrd)")
            target = Path(path).expanduser()
            output_format(target)
        except UnwindError as exc:
            self._fail(exc)
            return None
        if self.path_edit.text() != str(path):
            self.path_edit.setText(str(path))  # the page shows what is written (its format follows the suffix)
        overwrite = False
        if target.exists():
            if not dock.confirm_overwrite(target):
                self._say(f"not exported: {target} was kept")
                return None
            overwrite = True
        channels = self.channels_box.volumes()
        try:
            task = self.workflow.export_task(target, options=self.export_options(), overwrite=overwrite,
                                             channels=channels)
        except UnwindError as exc:
            self._fail(exc)
            return None
        where = dock.where

        def make() -> Generator[Progress, None, tuple]:
            value = yield from task.make()
            if channels:
                from .._reader import read

                return value, read(str(value[0]))  # the layers of every channel, made off the UI thread
            from .._layers import image_layer

            volume = open_volume(value[0])  # the layer's tuple made off the UI thread too
            return value, [image_layer(volume, name=f"straight {Path(value[0]).name}",
                                       contrast_limits=contrast_limits(volume.levels))]

        def done(result: tuple) -> None:
            value, tuples = result
            task.apply(value)
            written, warned = value
            self.exported = Path(written)
            for data, meta, kind in tuples:  # one layer per channel; each shown a turn after napari adds it
                if channels:
                    meta["name"] = f"straight {meta['name']}"
                dock._add_layer((data, meta, kind), reveal=True)
            self.export_info.setText(for_dock("\n".join([f"written: {self.exported}{where}"]
                                                         + [f"warning: {w}" for w in warned])))
            self._say(f"exported to {self.exported}{where}" + (f" (warning: {warned[0]})" if warned else ""))

        return dock._start(make, task.label, done, (self.export_cancel,))
