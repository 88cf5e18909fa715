"""The Unwind dock: the whole workflow in one widget, from a scan to an exported straight specimen.

Steps (pages of a tool box, revisitable in any order; each says what it still needs):

Scan
    An Image layer of the viewer, or a file opened with :func:`napari_unwind.io.open_volume`; shape, spacing and
    unit, and a warning when the spacing is missing (no unit and 1 x 1 x 1: lengths are then in voxels). The
    "backend" row above it: "this computer", or "server" (address, token or token file, CA file for TLS; Connect
    checks health and the token; "path on server" names a scan the server already holds, which is then registered
    there instead of uploaded). On a server the segmentation, the ends, the skeleton and the export run through
    :class:`napari_unwind.client.Client` (:mod:`napari_unwind._remote`): the scan is uploaded once, the features'
    label volume comes back to draw and pick, the selection's mask is made there (a Select job), the export is
    downloaded to the chosen path; same progress bar and Cancel (which cancels the server's job).
Segment
    The join tree is built once in a worker (Cancel stops it); the feature-count slider re-simplifies it live (no
    rebuild; on a server the server simplifies its cached tree and sends the label volume). The features are a
    Labels layer; a click on one (2D or 3D) selects it, shift-click adds it; the table lists their statistics and
    shows the selection, which is also a Labels layer ``"selection"``.
Ends
    Suggested head and tail (:func:`napari_unwind.skeleton.suggest_endpoints`) in a Points layer ``"ends"``:
    drag them in select mode, place more in add mode. Two points are head and tail; more are read in order as a
    chain (start and end of each part, head to tail) for a specimen in pieces.
Skeleton
    The pipeline's :func:`napari_unwind.pipeline.skeleton_step` (options: ``self.options.skeleton``, a
    :class:`~napari_unwind.pipeline.PipelineOptions`) in a child process with progress and Cancel; the status line
    shows its status by :func:`napari_unwind.pipeline.judge` (``ok``, or ``partial`` with the reason, e.g. coverage
    under 0.99), the report its figures and warnings, and the deformation goes to the editing model.
Refine
    The cross-section editor (:class:`napari_unwind._napari._refine.RefinePanel`) on the same model.
Export
    Format, spacing, order, padding, "allow folds" and path (the fields start at the pipeline's
    :class:`~napari_unwind.pipeline.ExportOptions` defaults); :func:`napari_unwind.pipeline.export_step` in a worker
    with progress and Cancel: the one fold rule (a fold over the specimen is refused with the command line's
    message unless "allow folds" is ticked), then the writer; the result opens as a layer. Saving is explicit; an
    existing file is replaced only after confirmation.
Session
    Save and load (:mod:`napari_unwind.session`) at any step.

The dock's steps call the one pipeline (:mod:`napari_unwind.pipeline`, through the Qt-free
:mod:`napari_unwind._steps`) with its option objects (no default is restated here), the core and the
:class:`~napari_unwind.editing.EditModel`; every long job runs in a ``thread_worker`` (:mod:`._workers`), so the UI
never waits on one.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Generator
from dataclasses import replace
from pathlib import Path
from typing import Any

import dask.array as da
import numpy as np
from qtpy.QtCore import Qt
from qtpy.QtWidgets import (
    QAbstractItemView,
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFileDialog,
    QFormLayout,
    QGridLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QMessageBox,
    QPlainTextEdit,
    QPushButton,
    QSlider,
    QSpinBox,
    QTableWidget,
    QTableWidgetItem,
    QToolBox,
    QVBoxLayout,
    QWidget,
)

from ..errors import InvalidInputError, UnwindError
from ..io import Volume, open_volume
from ..io._volume import normalise_unit, unit_label
from ..pipeline import ExportOptions
from ..progress import Progress
from ..progress import run as run_progress
from ..workflow import LocalBackend, ServerBackend, Workflow
from . import _docks
from ._messages import for_dock
from ._reader import contrast_limits
from ._workers import Job, JobCancelled, in_child, prewarm, start_job, start_process_job

__all__ = ["UnwindWidget", "volume_from_layer"]

#: Export formats offered: (label, suffix); any suffix write_volume knows may also be typed.
EXPORT_FORMATS = (("OME-Zarr", ".ome.zarr"), ("NRRD", ".nrrd"), ("NIfTI", ".nii.gz"), ("TIFF", ".tif"))
#: The dock's own shortcuts (the editor's come from RefinePanel.SHORTCUTS).
DOCK_SHORTCUTS = (
    ("click", "Segment: select the feature under the mouse (2D or 3D)"),
    ("shift-click", "Segment: add the feature to the selection"),
    ("drag a point", "Ends: move a head/tail (points layer in select mode)"),
    ("click (add mode)", "Ends: place another end (more than two: a chain, start and end of each part)"),
)
#: The skeleton step (the pipeline's skeleton_step, judged), run in a child process by name (the UI process need not
#: import the mesher; the spare child imports the pipeline and the solver while idle).
_SKELETON = "napari_unwind._steps:skeleton"
#: Positions of the threshold slider over the scan's intensity range.
_ISO_STEPS = 1000

_TABLE_COLUMNS = ("id", "voxels", "elongation", "persistence", "threshold", "border", "container")


def _status_line(specimen: Any, where: str = "") -> str:
    """The skeleton's status for the dock: ``skeleton: ok`` or ``skeleton: partial: <the pipeline's reason>``."""
    head = f"skeleton{where}: {specimen.status}"
    return f"{head}: {specimen.reason}" if specimen.reason else head


def _folds_line(deformation: Any, folded: float | None, advice: str) -> str:
    """``FOLDS at s = a..b (x % of the mask): <advice>``, or "" when the deformation does not fold."""
    folds = deformation.folds()
    if not folds:
        return ""
    share = "" if folded is None else f" ({100 * folded:.2g} % of the mask)"
    return "FOLDS at s = " + ", ".join(f"{a:.4g}..{b:.4g}" for a, b in folds) + f"{share}: {advice}"


def volume_from_layer(layer: Any) -> Volume:
    """The :class:`~napari_unwind.io.Volume` behind a napari Image layer: its data (lazy), scale as spacing,
    translate as origin, its unit; the pyramid when it is multiscale.

    Raises
    ------
    InvalidInputError
        Not a 3D single-channel image, or a voxel type a Volume cannot hold.
    """
    if getattr(layer, "rgb", False) or getattr(layer, "ndim", 0) != 3:
        raise InvalidInputError(f"the layer {layer.name!r} is not a 3D grey-value image (ndim "
                                f"{getattr(layer, 'ndim', '?')}, rgb {getattr(layer, 'rgb', False)}); pick a 3D scan")
    meta = (layer.metadata or {}).get("napari_unwind", {})
    raw = list(layer.data) if layer.multiscale else [layer.data]
    levels = tuple(a if isinstance(a, da.Array) else da.from_array(a, chunks="auto") for a in raw)
    spacing = tuple(float(s) for s in layer.scale)
    origin = tuple(float(t) for t in layer.translate)
    unit = meta.get("unit")
    if unit is None and getattr(layer, "units", None) is not None:
        names = {str(u) for u in layer.units}
        if len(names) == 1:
            try:
                unit = normalise_unit(names.pop())
            except InvalidInputError:
                unit = None
    full = np.asarray(levels[0].shape, dtype=float)
    level_spacings, level_origins = [], []
    for lvl in levels:
        sp = np.asarray(spacing) * full / np.asarray(lvl.shape, dtype=float)
        level_spacings.append(tuple(float(v) for v in sp))
        level_origins.append(tuple(float(v) for v in np.asarray(origin) + (sp - np.asarray(spacing)) / 2))
    return Volume(levels[0], spacing=spacing, unit=unit, origin=origin, levels=levels if len(levels) > 1 else (),
                  level_spacings=tuple(level_spacings) if len(levels) > 1 else (),
                  level_origins=tuple(level_origins) if len(levels) > 1 else (),
                  source=meta.get("source"), format=meta.get("format"))


def _with_geometry(volume: Volume, spacing: Any, origin: Any) -> Volume:
    """``volume`` with another spacing and origin (a session's), its pyramid levels scaled alike."""
    sp0, sp = np.asarray(volume.spacing, dtype=float), np.asarray(spacing, dtype=float)
    ratio = sp / sp0
    level_spacings = tuple(tuple(float(v) for v in np.asarray(ls) * ratio) for ls in volume.level_spacings)
    level_origins = tuple(tuple(float(v) for v in np.asarray(origin, dtype=float) + (np.asarray(ls) - sp) / 2)
                          for ls in level_spacings)
    return replace(volume, spacing=tuple(float(v) for v in sp), origin=tuple(float(v) for v in origin),
                   level_spacings=level_spacings, level_origins=level_origins)


def ends_size(shape: Any, spacing: Any) -> float:
    """The ends' marker size (world units): 3 % of the scan's largest extent, at least 6 voxels (was 4 voxels:
    a dot on a scan of hundreds)."""
    extent = max(n * s for n, s in zip(shape, spacing, strict=True))
    return float(max(0.03 * extent, 6 * max(spacing)))


def _spacing_missing(volume: Volume) -> bool:
    return volume.unit is None and all(s == 1.0 for s in volume.spacing)


def _fmt(values: Any, digits: int = 4) -> str:
    return " x ".join(f"{float(v):.{digits}g}" for v in values)


class UnwindWidget(QWidget):
    """The Unwind dock (see the module docstring).

    Parameters
    ----------
    napari_viewer : napari.Viewer
        The viewer whose layers the dock reads and writes.
    """

    def __init__(self, napari_viewer: Any, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.viewer = napari_viewer
        #: The workflow's state and steps (Qt-free); the dock shows it and turns clicks into its calls. Its
        #: backend runs the steps on this computer (the skeleton in a child process) or on a server.
        self.workflow = Workflow(LocalBackend(runner=in_child))
        self.model = self.workflow.edit
        self.scan_layer: Any = None
        #: the Labels layer whose mask is the selection: (layer, label; None: every label), or None
        self.mask_choice: tuple[Any, int | None] | None = None
        self.exported: Path | None = None
        self.job: Job | None = None
        self._features_layer: Any = None
        self._selection_layer: Any = None
        self._ends_layer: Any = None
        self._pending_segmentation: Any = None  # a loaded session's Segmentation, applied when the tree is built
        self._simplify_worker: Any = None
        self._simplify_pending: int | None = None
        self._syncing = False
        self._iso_range_cache: tuple | None = None
        self._measure_worker: Any = None
        self._measure_pending = False
        self.workflow.features_changed.connect(self._features_ready)
        self.workflow.selection_changed.connect(self._show_selection)

        self.toolbox = QToolBox()
        self.toolbox.addItem(self._scan_page(), "1. Scan")
        self.toolbox.addItem(self._segment_page(), "2. Segment")
        self.toolbox.addItem(self._ends_page(), "3. Ends")
        self.toolbox.addItem(self._skeleton_page(), "4. Skeleton")
        self.toolbox.addItem(self._refine_page(), "5. Refine")
        self.toolbox.addItem(self._export_page(), "6. Export")
        self.toolbox.addItem(self._session_page(), "7. Session")
        self.toolbox.addItem(self._shortcuts_page(), "Shortcuts")
        self.status = QLabel("")
        self.status.setWordWrap(True)
        layout = QVBoxLayout(self)
        layout.addWidget(self.toolbox, 1)  # the open step gets the height; the status line only its own
        layout.addWidget(self.status)
        self.setMinimumWidth(400)  # the feature table and the reports need room; napari's docks start narrow

        self.viewer.layers.events.inserted.connect(self._on_layers_changed)
        self.viewer.layers.events.removed.connect(self._on_layers_changed)
        _docks.register(self.viewer, self)  # a session opened by napari's reader leaves its selection to us
        self.model.deformation_changed.connect(self._on_deformation_changed)
        self._refresh_layer_combo()
        self._update_needs()

    # the workflow's state, under the names the dock's views and tests read
    volume = property(lambda self: self.workflow.volume)
    tree = property(lambda self: self.workflow.tree)
    features = property(lambda self: self.workflow.features)
    selected = property(lambda self: list(self.workflow.selection.ids))
    seeds = property(lambda self: dict(self.workflow.selection.seeds))

    @property
    def options(self) -> Any:
        """The pipeline's options (napari_unwind.pipeline: every default once); the export page's fields and the
        "allow folds" box override its export part when an export starts."""
        return self.workflow.options

    @options.setter
    def options(self, value: Any) -> None:
        self.workflow.options = value

    specimen = property(lambda self: None if self.workflow.skeleton is None else self.workflow.skeleton.specimen)
    result = property(lambda self: None if self.specimen is None else getattr(self.specimen, "skeleton", None))

    @property
    def server(self) -> Any:
        """The server the steps run on (a ServerBackend's), or None: this computer."""
        return getattr(self.workflow.backend, "server", None)

    @property
    def _remote(self) -> dict[str, Any]:
        """The server's ids of this scan (volume, segmentation, mask, session); empty on this computer."""
        return getattr(self.workflow.backend, "_ids", {})

    # ==============================================================================================================
    # pages
    # ==============================================================================================================
    def _job_buttons(self, layout: Any, text: str, start: Callable[[], Any]) -> tuple[QPushButton, QPushButton]:
        """A step's row: the button that starts its job and a Cancel button (enabled while the job runs)."""
        row = QHBoxLayout()
        button = QPushButton(text)
        button.clicked.connect(start)
        cancel = QPushButton("Cancel")
        cancel.clicked.connect(self.cancel)
        cancel.setEnabled(False)
        row.addWidget(button, 1)
        row.addWidget(cancel)
        layout.addLayout(row)
        return button, cancel

    def _scan_page(self) -> QWidget:
        # the steps take the dock's height: napari adds a stretch under a dock with no vertically expanding
        # widget, weighted by how many docks the process opened before (the 4th got the open step ~50 px tall)
        policy = self.toolbox.sizePolicy()
        policy.setVerticalPolicy(policy.Policy.Expanding)
        self.toolbox.setSizePolicy(policy)
        w = QWidget()
        lay = QVBoxLayout(w)
        lay.addLayout(self._backend_form())
        row = QHBoxLayout()
        self.layer_combo = QComboBox()
        self.layer_combo.setToolTip("The 3D Image layer to straighten")
        # a layer named after a long file must not widen the dock (napari's starts ~400 px): the combo shows what
        # fits, its list shows the whole names
        self.layer_combo.setSizeAdjustPolicy(QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        self.layer_combo.setMinimumContentsLength(12)
        self.layer_combo.activated.connect(self._on_layer_chosen)
        self.open_button = QPushButton("Open file...")
        self.open_button.clicked.connect(self._open_dialog)
        row.addWidget(self.layer_combo, 1)
        row.addWidget(self.open_button)
        lay.addLayout(row)
        self.scan_info = QLabel("no scan: pick an Image layer or open a file")
        self.scan_info.setWordWrap(True)
        self.scan_info.setMinimumWidth(1)  # a layer's name (a file's) has no break: cut at the edge, never widen
        self.scan_warning = QLabel("")
        self.scan_warning.setWordWrap(True)
        self.scan_warning.setStyleSheet("color: #ff8c00")
        self.scan_warning.hide()
        lay.addWidget(self.scan_info)
        lay.addWidget(self.scan_warning)
        lay.addStretch(1)
        return w

    def _backend_form(self) -> QFormLayout:
        form = QFormLayout()
        form.setFieldGrowthPolicy(QFormLayout.FieldGrowthPolicy.AllNonFixedFieldsGrow)  # fields take the dock's width
        self.backend_combo = QComboBox()
        self.backend_combo.addItem("this computer", "local")
        self.backend_combo.addItem("server", "server")
        self.backend_combo.setToolTip("Where the segmentation, the ends, the skeleton and the export run")
        self.backend_combo.currentIndexChanged.connect(self._on_backend_chosen)
        form.addRow("backend", self.backend_combo)
        self.server_address = QLineEdit()
        self.server_address.setPlaceholderText("host:port, e.g. 127.0.0.1:50051")
        self.server_token = QLineEdit()
        self.server_token.setEchoMode(QLineEdit.EchoMode.Password)
        self.server_token.setPlaceholderText("token, or the path of a file holding it")
        self.server_ca = QLineEdit()
        self.server_ca.setPlaceholderText("CA certificate (PEM) for TLS; empty: no TLS")
        self.server_path = QLineEdit()
        self.server_path.setPlaceholderText("the scan's path under the server's data root; empty: upload it")
        self.server_path.setToolTip("A scan the server already holds (relative to its data root) is registered "
                                    "there instead of uploaded; this computer opens the same file for display")
        self.server_path.textChanged.connect(self._on_server_path_edited)
        self.connect_button = QPushButton("Connect")
        self.connect_button.clicked.connect(self.connect_server)
        self.backend_info = QLabel("")
        self.backend_info.setWordWrap(True)
        self.backend_info.setMinimumWidth(1)  # a long server address has no break: cut, never widen the dock
        self._server_rows = (self.server_address, self.server_token, self.server_ca, self.server_path,
                             self.connect_button)
        for label, widget in zip(("address", "token", "TLS CA", "path on server", ""), self._server_rows):
            form.addRow(label, widget)
        form.addRow(self.backend_info)
        self._on_backend_chosen()
        return form

    def _on_backend_chosen(self, index: int | None = None) -> None:
        server = self.backend_combo.currentData() == "server"
        for widget in self._server_rows:
            widget.setEnabled(server)
        if not isinstance(self.workflow.backend, LocalBackend):
            self.workflow.set_backend(LocalBackend(runner=in_child))  # until "Connect" succeeds
        self.backend_info.setText("jobs run on a server once connected" if server else "jobs run on this computer")

    def _on_server_path_edited(self, text: str) -> None:
        backend = self.workflow.backend
        if isinstance(backend, ServerBackend):
            backend.forget()  # another scan on the server: its ids (volume, segmentation, mask, session) start again
            backend.server_path = text

    def connect_server(self) -> Job | None:
        """Check the server's health and the token (with a deadline); on success the dock's jobs run there."""
        from .._remote import check_server, parse_server

        if not isinstance(self.workflow.backend, LocalBackend):
            self.workflow.set_backend(LocalBackend(runner=in_child))
        try:
            server = parse_server(self.server_address.text(), self.server_token.text(), self.server_ca.text())
        except UnwindError as exc:
            self._fail(exc)
            return None

        def done(status: str) -> None:
            self.workflow.set_backend(ServerBackend(server, server_path=self.server_path.text()))
            self.backend_info.setText(f"connected to {server.address} ({status})")
            self._say(f"server {server.address}: {status}")

        return self._start(lambda: check_server(server), "connecting", done)

    def _segment_page(self) -> QWidget:
        w = QWidget()
        lay = QVBoxLayout(w)
        self.segment_need = QLabel("")
        self.segment_need.setWordWrap(True)
        lay.addWidget(self.segment_need)
        self.segment_button, self.segment_cancel = self._job_buttons(lay, "Build the join tree", lambda: self.segment())
        row = QHBoxLayout()
        row.addWidget(QLabel("features"))
        self.count_slider = QSlider(Qt.Orientation.Horizontal)
        k = self.options.segment.k
        self.count_slider.setRange(1, k)
        self.count_slider.setValue(k)
        self.count_slider.setEnabled(False)
        self.count_slider.valueChanged.connect(self.set_feature_count)
        self.count_label = QLabel(str(k))
        row.addWidget(self.count_slider, 1)
        row.addWidget(self.count_label)
        lay.addLayout(row)
        self.table = QTableWidget(0, len(_TABLE_COLUMNS))
        self.table.setHorizontalHeaderLabels(_TABLE_COLUMNS)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.itemSelectionChanged.connect(self._on_table_selection)
        lay.addWidget(self.table, 1)
        self.selection_label = QLabel("selected: none (click a feature; shift-click adds)")
        self.selection_label.setWordWrap(True)
        lay.addWidget(self.selection_label)
        # the selected features' threshold at full resolution: lower grows the mask, higher shrinks it
        grid = QGridLayout()
        grid.addWidget(QLabel("threshold"), 0, 0)
        self.iso_slider = QSlider(Qt.Orientation.Horizontal)
        self.iso_slider.setRange(0, _ISO_STEPS)
        self.iso_slider.setEnabled(False)
        self.iso_slider.setToolTip("The selected features' threshold at full resolution: left grows the mask, "
                                   "right shrinks it")
        self.iso_slider.valueChanged.connect(self._on_iso_slider)
        grid.addWidget(self.iso_slider, 0, 1)
        self.iso_default_button = QPushButton("default")
        self.iso_default_button.setToolTip("The threshold the pipeline chooses from the scan (its one rule)")
        self.iso_default_button.setEnabled(False)
        self.iso_default_button.clicked.connect(lambda: self.set_isovalue(None))
        grid.addWidget(self.iso_default_button, 0, 2)
        grid.setColumnStretch(1, 1)
        lay.addLayout(grid)
        self.mask_info = QLabel("")
        self.mask_info.setWordWrap(True)
        lay.addWidget(self.mask_info)
        # or a mask: a Labels layer (an expert's segmentation) or a mask file
        masks = QGridLayout()
        masks.addWidget(QLabel("or a mask"), 0, 0)
        self.mask_combo = QComboBox()
        self.mask_combo.setSizeAdjustPolicy(QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        self.mask_combo.setMinimumContentsLength(12)
        self.mask_combo.setToolTip("A Labels layer on the scan's grid; its label under a click is then the selection")
        masks.addWidget(self.mask_combo, 0, 1, 1, 2)
        self.use_mask_button = QPushButton("Use mask")
        self.use_mask_button.setToolTip("Every labelled voxel of the chosen Labels layer is the selection; click a "
                                        "label in the viewer to take that label alone")
        self.use_mask_button.clicked.connect(self._use_chosen_mask)
        masks.addWidget(self.use_mask_button, 1, 1)
        self.open_mask_button = QPushButton("Open mask file...")
        self.open_mask_button.clicked.connect(self._open_mask_dialog)
        masks.addWidget(self.open_mask_button, 1, 2)
        masks.setColumnStretch(1, 1)
        masks.setColumnStretch(2, 1)
        lay.addLayout(masks)
        return w

    # ---- the threshold slider and the mask controls -----------------------------------------------------------------
    def _iso_range(self) -> tuple[float, float]:
        if self._iso_range_cache is None or self._iso_range_cache[0] is not self.volume:
            self._iso_range_cache = (self.volume, self.workflow.intensity_range())
        return self._iso_range_cache[1]

    def _iso_at(self, position: int) -> float:
        lo, hi = self._iso_range()
        return lo + (hi - lo) * position / _ISO_STEPS

    def _on_iso_slider(self, position: int) -> None:
        if not self._syncing:
            self.set_isovalue(self._iso_at(position))

    def set_isovalue(self, value: float | None) -> None:
        """Threshold the selected features at ``value`` (None: the pipeline's default rule); the mask is measured
        again in a worker (while the slider moves only the latest value waits)."""
        self.workflow.set_isovalue(value)
        self._measure()

    def _measure(self) -> None:
        """Measure the selection (voxels, share of the scan, threshold) off the UI thread; latest request wins."""
        if not self.workflow.has_selection:
            self.mask_info.setText("")
            return
        self._measure_pending = True
        if self._measure_worker is None:
            self._next_measure()

    def _next_measure(self) -> None:
        from napari.qt.threading import create_worker

        if not self._measure_pending or not self.workflow.has_selection:
            self._measure_worker = None
            return
        self._measure_pending = False
        task = self.workflow.measure_task()
        selection = self.workflow.selection

        def compute() -> tuple:
            return selection, run_progress(task.make())

        worker = create_worker(compute, _start_thread=False, _ignore_errors=True)
        worker.returned.connect(self._on_measured)
        worker.errored.connect(self._fail)
        worker.finished.connect(self._next_measure)
        self._measure_worker = worker
        worker.start()

    def _on_measured(self, value: tuple) -> None:
        selection, (count, share, iso) = value
        if selection is not self.workflow.selection:
            return  # another selection or threshold meanwhile: its own measurement follows
        chosen = self.workflow.isovalue
        if iso is None:
            self.mask_info.setText(f"mask: {count:,} voxels ({100 * share:.3g} % of the scan)")
            return
        how = "default" if chosen is None else "chosen"
        self.mask_info.setText(f"mask: {count:,} voxels ({100 * share:.3g} % of the scan) at threshold "
                               f"{iso:.4g} ({how})")
        lo, hi = self._iso_range()
        self._syncing = True
        self.iso_slider.setValue(int(round(_ISO_STEPS * (iso - lo) / (hi - lo))) if hi > lo else 0)
        self._syncing = False

    def _refresh_mask_combo(self) -> None:
        from napari.layers import Labels

        own = {id(self._features_layer), id(self._selection_layer)}
        layers = [lyr for lyr in self.viewer.layers
                  if isinstance(lyr, Labels) and lyr.ndim == 3 and id(lyr) not in own]
        current = self.mask_combo.currentData()
        self.mask_combo.blockSignals(True)
        self.mask_combo.clear()
        self.mask_combo.addItem("(choose a Labels layer)", None)
        for lyr in layers:
            self.mask_combo.addItem(lyr.name, lyr)
        if current is not None and current in layers:
            self.mask_combo.setCurrentIndex(layers.index(current) + 1)
        self.mask_combo.blockSignals(False)

    def _use_chosen_mask(self) -> None:
        layer = self.mask_combo.currentData()
        if layer is None:
            self._fail(InvalidInputError("choose a Labels layer in \"or a mask\" first, or open a mask file"))
            return
        self.use_labels(layer)

    def _open_mask_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open a mask")
        if path:
            self.open_mask(path)

    def _ends_page(self) -> QWidget:
        w = QWidget()
        lay = QVBoxLayout(w)
        self.ends_need = QLabel("")
        self.ends_need.setWordWrap(True)
        lay.addWidget(self.ends_need)
        self.suggest_button = QPushButton("Suggest head and tail")
        self.suggest_button.clicked.connect(self.suggest_ends)
        lay.addWidget(self.suggest_button)
        lay.addWidget(QLabel("Drag the points of the \"ends\" layer (select mode) or place them (add mode). Two "
                             "points: head, tail. More: a chain, start and end of each part, head to tail."))
        lay.itemAt(lay.count() - 1).widget().setWordWrap(True)
        self.ends_info = QLabel("")
        self.ends_info.setWordWrap(True)
        lay.addWidget(self.ends_info)
        lay.addStretch(1)
        return w

    def _skeleton_page(self) -> QWidget:
        w = QWidget()
        lay = QVBoxLayout(w)
        self.skeleton_need = QLabel("")
        self.skeleton_need.setWordWrap(True)
        lay.addWidget(self.skeleton_need)
        self.skeleton_button, self.skeleton_cancel = self._job_buttons(lay, "Compute the skeleton", self.run_skeleton)
        self.skeleton_report = QPlainTextEdit()
        self.skeleton_report.setReadOnly(True)
        self.skeleton_report.setPlaceholderText("the skeleton's report and warnings appear here")
        lay.addWidget(self.skeleton_report, 1)
        return w

    def _refine_page(self) -> QWidget:
        try:
            from ._refine import RefinePanel
        except ImportError:
            self.refine_panel = None
            label = QLabel("The cross-section editor is not available in this build (napari_unwind._napari._refine "
                           "is missing); the deformation can still be exported as the skeleton made it.")
            label.setWordWrap(True)
            return label
        self.refine_panel = RefinePanel(self.viewer, self.model, lambda: self.volume)
        return self.refine_panel

    def _export_page(self) -> QWidget:
        w = QWidget()
        lay = QVBoxLayout(w)
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
        self._show_export_options(self.options.export)
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
        self.export_button, self.export_cancel = self._job_buttons(
            lay, "Export", lambda: self.export(self.path_edit.text()))
        self.export_info = QLabel("")
        self.export_info.setWordWrap(True)
        self.export_info.setMinimumWidth(1)  # the written path has no break: cut at the dock's edge, never widen it
        lay.addWidget(self.export_info)
        lay.addStretch(1)
        return w

    def _session_page(self) -> QWidget:
        w = QWidget()
        lay = QVBoxLayout(w)
        row = QHBoxLayout()
        save = QPushButton("Save session...")
        save.clicked.connect(self._save_dialog)
        load = QPushButton("Open session...")
        load.clicked.connect(self._load_dialog)
        row.addWidget(save)
        row.addWidget(load)
        lay.addLayout(row)
        self.session_info = QLabel("A session (*.unwind.json) keeps the scan, the selection, the ends and the "
                                   "deformation; save it at any step.")
        self.session_info.setWordWrap(True)
        lay.addWidget(self.session_info)
        lay.addStretch(1)
        return w

    def _shortcuts_page(self) -> QWidget:
        rows = list(DOCK_SHORTCUTS)
        panel_cls = type(self.refine_panel) if self.refine_panel is not None else None
        editor = getattr(panel_cls, "SHORTCUTS", None)
        if isinstance(editor, dict):
            editor = list(editor.items())
        rows += [(str(k), f"Refine: {v}") for k, v in (editor or ())]
        table = QTableWidget(len(rows), 2)
        table.setHorizontalHeaderLabels(("key / mouse", "action"))
        table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        for i, (key, action) in enumerate(rows):
            table.setItem(i, 0, QTableWidgetItem(key))
            table.setItem(i, 1, QTableWidgetItem(action))
        # the two columns share the dock's width and wrap their text (no horizontal scrolling at napari's default
        # dock width); the rows grow to the wrapped text
        table.setWordWrap(True)
        table.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        header = table.horizontalHeader()
        header.setSectionResizeMode(header.ResizeMode.Stretch)
        header.setMinimumSectionSize(60)
        table.verticalHeader().setSectionResizeMode(header.ResizeMode.ResizeToContents)
        table.verticalHeader().hide()
        self.shortcuts_table = table
        return table

    # ==============================================================================================================
    # jobs and messages
    # ==============================================================================================================
    def _start(self, make: Callable[[], Generator[Progress, None, Any]] | None, label: str,
               on_returned: Callable[[Any], Any], cancel_buttons: tuple = (), *,
               process: tuple | None = None) -> Job | None:
        """Start a job: ``make()`` in a thread worker, or ``process = (fn, args, kwargs)`` in a child process."""
        if self.job is not None and self.job.running:
            self._fail(InvalidInputError(f"{self.job.label} is still running: wait for it or cancel it first"))
            return None
        for b in cancel_buttons:
            b.setEnabled(True)

        def returned(value: Any) -> None:
            try:
                on_returned(value)
            except Exception as exc:  # noqa: BLE001 - shown in the dock, never a traceback dialog
                self._fail(exc)

        def finished() -> None:
            for b in cancel_buttons:
                b.setEnabled(False)
            self._update_needs()

        self._say(f"{label}...")
        callbacks = dict(label=label, on_returned=returned, on_error=self._fail, on_finished=finished)
        if process is not None:
            self.job = start_process_job(*process, **callbacks)
        else:
            self.job = start_job(make, **callbacks)
        return self.job

    @property
    def idle(self) -> bool:
        """No job running, no re-simplification or measurement of the selection, and nothing left for the Refine
        panel's straight preview."""
        preview = getattr(self.refine_panel, "preview", None)
        return ((self.job is None or self.job.done) and self._simplify_worker is None
                and self._measure_worker is None and bool(getattr(preview, "idle", True)))

    def cancel(self) -> None:
        """Cancel the running job (it stops at its next progress step)."""
        if self.job is not None and self.job.running:
            self.job.cancel()
            self._say(f"cancelling {self.job.label}...")

    def _say(self, text: str) -> None:
        self.status.setStyleSheet("")
        self.status.setText(for_dock(text))

    def _fail(self, exc: BaseException) -> None:
        if isinstance(exc, JobCancelled):
            self._say(f"{self.job.label if self.job else 'the job'} was cancelled")
            return
        text = str(exc) if isinstance(exc, (UnwindError, FileNotFoundError)) else f"{type(exc).__name__}: {exc}"
        self.status.setStyleSheet("color: #ff5050")
        self.status.setText(f"error: {for_dock(text)}")

    # ==============================================================================================================
    # scan
    # ==============================================================================================================
    def _image_layers(self) -> list:
        from napari.layers import Image

        return [lyr for lyr in self.viewer.layers if isinstance(lyr, Image) and lyr.ndim == 3 and not lyr.rgb]

    def _on_layers_changed(self, event: Any = None) -> None:
        self._refresh_layer_combo()
        self._refresh_mask_combo()
        layer = getattr(event, "value", None)
        if event is not None and getattr(event, "type", "") == "removed":
            if layer is self.scan_layer:
                self.scan_layer = None
            for name in ("_features_layer", "_selection_layer", "_ends_layer"):
                if getattr(self, name) is layer:
                    setattr(self, name, None)
            self._update_needs()
        elif layer is not None:
            self._adopt(layer)

    def _adopt(self, layer: Any) -> None:
        """Pick up what a session opened by napari's reader restores (ends, deformation) when the dock has none."""
        meta = (getattr(layer, "metadata", None) or {}).get("napari_unwind", {})
        if "deformation" in meta and self.model.deformation is None:
            from ..deformation import Deformation

            try:
                self.model.set_deformation(Deformation.from_dict(meta["deformation"]))
            except UnwindError as exc:
                self._fail(exc)
        if "endpoints" in meta and self._ends_layer is None:
            self._ends_layer = layer
        if "selected" in meta and self._selection_layer is None:
            self._selection_layer = layer  # the reader's selection: the dock updates it rather than add another
        if self.scan_layer is None and "session_path" in meta and layer in self._image_layers():
            self.use_layer(layer)
            seg = meta.get("segmentation")
            if seg and seg.get("k") and (seg.get("selected") or seg.get("seeds")) and self.tree is None:
                from ..session import Segmentation

                self._pending_segmentation = Segmentation.from_dict(seg)  # recomputed in a worker
                self.segment(level=self._pending_segmentation.level)

    def _refresh_layer_combo(self) -> None:
        layers = self._image_layers()
        self.layer_combo.blockSignals(True)
        self.layer_combo.clear()
        self.layer_combo.addItem("(choose an Image layer)", None)
        for lyr in layers:
            self.layer_combo.addItem(lyr.name, lyr)
        if self.scan_layer is not None and self.scan_layer in layers:
            self.layer_combo.setCurrentIndex(layers.index(self.scan_layer) + 1)
        self.layer_combo.blockSignals(False)

    def _on_layer_chosen(self, index: int) -> None:
        layer = self.layer_combo.itemData(index)
        if layer is not None and layer is not self.scan_layer:
            self.use_layer(layer)

    def use_layer(self, layer: Any) -> None:
        """Make an Image layer the scan."""
        try:
            volume = volume_from_layer(layer)
        except UnwindError as exc:
            self._fail(exc)
            return
        self._set_scan(volume, layer)

    def _set_scan(self, volume: Volume, layer: Any) -> None:
        changed = self.volume is None or volume.source != self.volume.source or volume.shape != self.volume.shape
        self.scan_layer = layer
        self.workflow.set_scan(volume, name=layer.name)
        from ._layers import in_3d

        in_3d(self.viewer, layer)
        if changed:
            self.mask_choice = None
        self._refresh_layer_combo()
        unit = unit_label(volume.unit)
        levels = f", {len(volume.levels)} pyramid levels" if len(volume.levels) > 1 else ""
        self.scan_info.setText(f"{layer.name}: {_fmt(volume.shape, 6)} voxels of {volume.dtype}{levels}\n"
                               f"spacing {_fmt(volume.spacing)} {unit}, unit {volume.unit or 'not recorded'}\n"
                               f"source {volume.source or '(not from a file: a saved session writes it beside it)'}")
        if _spacing_missing(volume):
            self.scan_warning.setText("Spacing missing: the scan records no voxel size, 1 x 1 x 1 is assumed and "
                                      "every length is in voxels. Open a format that stores it (OME-Zarr, NRRD, "
                                      "NIfTI) or set the layer's scale before segmenting.")
            self.scan_warning.show()
        else:
            self.scan_warning.hide()
        self._say(f"scan: {layer.name}")
        self._update_needs()

    def _open_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open a scan")
        if path:
            self.open_scan(path)

    def open_scan(self, path: str | os.PathLike, *, then: Callable[[], Any] | None = None) -> Job | None:
        """Open a scan file (lazily, in a worker) and add it as an Image layer; it becomes the scan."""
        from ._layers import image_layer

        def make() -> Generator[Progress, None, tuple]:
            yield Progress("open", 0, 1, str(path))
            volume = open_volume(path)
            clim = contrast_limits(volume.levels)  # from its voxels, as the reader does (napari's: [0, 1])
            yield Progress("open", 1, 1)
            return volume, clim

        def done(value: tuple) -> None:
            volume, clim = value
            layer = self._add_layer(image_layer(volume, contrast_limits=clim))
            self._set_scan(volume, layer)
            if then is not None:
                then()

        return self._start(make, "opening the scan", done)

    def _add_layer(self, layer_tuple: tuple) -> Any:
        from napari.layers import Layer

        layer = Layer.create(*layer_tuple)
        self.viewer.add_layer(layer)
        return layer

    def _put_layer(self, attr: str, layer_tuple: tuple) -> Any:
        """Update the dock's layer ``attr`` with new data and geometry, or add it when it is gone."""
        data, meta, _ = layer_tuple
        layer = getattr(self, attr)
        if layer is not None and layer in self.viewer.layers:
            layer.data = data
            for key in ("scale", "translate"):
                if key in meta:
                    setattr(layer, key, meta[key])
        else:
            layer = self._add_layer(layer_tuple)
            setattr(self, attr, layer)
            self._refresh_mask_combo()  # the dock's own layers are no masks to choose
            from ._layers import in_3d

            in_3d(self.viewer, layer)  # in 3D a coarse stand-in: napari's ray caster froze software GL
        return layer

    # ==============================================================================================================
    # segment
    # ==============================================================================================================
    def segment(self, *, level: int | None = None) -> Job | None:
        """Build the join tree of the scan in a worker (at pyramid ``level``, default the finest with every side
        <= 256), on this computer or on the server; then show the features (slider value), which the slider
        simplifies again without a rebuild."""
        pending = self._pending_segmentation
        k = pending.k if pending is not None and pending.k else self.count_slider.value()
        try:
            task = self.workflow.segment_task(level=level, k=k)
        except UnwindError as exc:
            self._fail(exc)
            return None

        def done(value: Any) -> None:
            task.apply(value)
            self._set_slider(int(getattr(self.tree, "n_maxima", 0) or 0), self.features.k)

        return self._start(task.make, task.label, done, (self.segment_cancel,))

    def _set_slider(self, maxima: int, k: int | None) -> int:
        """The slider's range for a tree of ``maxima`` maxima (0: unknown) at ``k`` (default: its value); returns
        the value set."""
        from ..segmentation import MAX_FEATURES

        top = max(1, min(MAX_FEATURES, maxima or MAX_FEATURES))
        k = min(k or self.count_slider.value(), top)
        self.count_slider.blockSignals(True)
        self.count_slider.setRange(1, top)
        self.count_slider.setValue(k)
        self.count_slider.blockSignals(False)
        self.count_slider.setEnabled(True)
        self.count_label.setText(str(k))
        return k

    def _simplify_source(self) -> Any:
        """What the slider simplifies: the workflow's tree (this computer's or the server's; None: nothing yet)."""
        return self.tree

    def set_feature_count(self, k: int) -> None:
        """Re-simplify the tree to ``k`` features (no rebuild), off the UI thread; while the slider moves only the
        latest value waits. The selection follows its clicks. On a server the segmentation is simplified there
        and the label volume of ``k`` features downloaded."""
        self.count_label.setText(str(int(k)))
        if self._simplify_source() is None:
            return
        self._simplify_pending = int(k)
        if self._simplify_worker is None:
            self._next_simplify()

    def _next_simplify(self) -> None:
        from napari.qt.threading import create_worker

        k, self._simplify_pending = self._simplify_pending, None
        source = self._simplify_source()
        if k is None or source is None:
            self._simplify_worker = None
            return
        worker = create_worker(lambda: (source, source.simplify(k)), _start_thread=False, _ignore_errors=True)
        worker.returned.connect(self._on_simplified)
        worker.errored.connect(self._fail)
        worker.finished.connect(self._next_simplify)
        self._simplify_worker = worker
        worker.start()

    def _on_simplified(self, value: tuple) -> None:
        source, features = value
        if source is not self._simplify_source():
            return  # from a tree or segmentation replaced meanwhile (another scan, another server)
        self.workflow.set_features(features)  # -> _features_ready

    def _features_ready(self, features: Any) -> None:
        """The workflow's features changed: draw them, fill the table; a loaded session's selection is applied
        (the workflow itself lets the clicked seeds choose again among the new features)."""
        f = features
        self._put_layer("_features_layer", self._labels_tuple(f.labels, "features", opacity=0.4))
        self._features_layer.metadata["napari_unwind"] = {"features": True}
        if self._on_features_click not in self._features_layer.mouse_drag_callbacks:
            self._features_layer.mouse_drag_callbacks.append(self._on_features_click)
        self._fill_table()
        pending = self._pending_segmentation
        if pending is not None and pending.k == f.k:  # a loaded session's selection
            self._pending_segmentation = None
            seeds = [tuple(p) for p in pending.seeds]
            ids = list(pending.selected)
            if ids:
                self.select_features(ids, seeds=dict(zip(ids, seeds)) if len(seeds) == len(ids) else None)
            else:
                self.select_features(list(f.ids_at(seeds)))
        else:
            self._show_selection(self.workflow.selection)  # the table was refilled
        self._say(f"{f.k} features (level {f.level}, {_fmt(f.shape, 6)} working voxels)")

    def _labels_tuple(self, labels: np.ndarray, name: str, **kwargs: Any) -> tuple:
        from ._layers import labels_layer

        f = self.features
        return labels_layer(labels, spacing=f.spacing, unit=f.unit, name=name,
                            translate=tuple(float(o) for o in f.working_origin), **kwargs)

    def _fill_table(self) -> None:
        f = self.features
        self._syncing = True
        self.table.setRowCount(len(f.stats))
        for row, st in enumerate(f.stats):
            values = (st.id, st.voxel_count, f"{st.elongation:.2f}", f"{st.persistence:.4g}", f"{st.threshold:.4g}",
                      "yes" if st.touches_border else "", "yes" if st.container else "")
            for col, v in enumerate(values):
                item = QTableWidgetItem(str(v))
                item.setData(Qt.ItemDataRole.UserRole, int(st.id))
                self.table.setItem(row, col, item)
        self.table.resizeColumnsToContents()
        self._syncing = False

    def _on_features_click(self, layer: Any, event: Any) -> Generator[None, None, None]:
        """Mouse callback of the features layer: a click (no drag) selects the feature under it; shift adds."""
        if event.type != "mouse_press":
            return
        yield
        dragged = False
        while event.type == "mouse_move":
            dragged = True
            yield
        if not dragged:
            self.pick(event.position, view_direction=getattr(event, "view_direction", None),
                      dims_displayed=getattr(event, "dims_displayed", None),
                      add="Shift" in {str(getattr(m, "name", m)) for m in (event.modifiers or ())})

    def pick(self, position: Any, *, view_direction: Any = None, dims_displayed: Any = None,
             add: bool = False) -> int:
        """Select the feature at a world position (2D: the point; 3D: along the view ray); return its id (0: none)."""
        layer = self._features_layer
        if self.features is None or layer is None:
            return 0
        ndisp = 0 if dims_displayed is None else len(dims_displayed)
        value = layer.get_value(position, view_direction=view_direction if ndisp == 3 else None,
                                dims_displayed=list(dims_displayed) if ndisp == 3 else None, world=True)
        fid = int(value) if value is not None else 0
        if fid == 0:
            self._say("no feature there (background): click on a coloured feature")
            return 0
        st = self.features.stat(fid)
        if ndisp == 3:  # the ray's hit is not a point: take the feature's maximum as its seed
            seed = tuple(float(c) for c in st.max_position_full)
        else:
            vox = (np.asarray(position, dtype=float)[-3:] - np.asarray(self.volume.origin)) / np.asarray(
                self.volume.spacing)
            seed = tuple(float(c) for c in vox)
        ids = list(self.selected) if add else []
        seeds = {i: self.seeds[i] for i in ids if i in self.seeds}
        if fid not in ids:
            ids.append(fid)
        seeds[fid] = seed
        self.select_features(ids, seeds=seeds)
        return fid

    def select_features(self, ids: list[int], *, seeds: dict[int, tuple] | None = None) -> None:
        """Set the selection (feature ids of the current segmentation); shown in the table and the layer."""
        if self.features is None:
            return
        self.mask_choice = None
        self.workflow.select(ids, seeds=seeds)  # -> _show_selection

    def _show_selection(self, selection: Any) -> None:
        """The workflow's selection changed: the selection layer, the table's rows and the label."""
        if selection.mask is not None:
            self._measure()
            self._update_needs()
            return
        ids, f = list(selection.ids), selection.features
        if f is not None:
            labels = np.where(np.isin(f.labels, ids), f.labels, 0).astype(f.labels.dtype)
            self._put_layer("_selection_layer", self._labels_tuple(labels, "selection", opacity=0.8,
                                                                   blending="additive"))
        self._syncing = True
        self.table.clearSelection()
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.MultiSelection)
        for row in range(self.table.rowCount()):
            if self.table.item(row, 0).data(Qt.ItemDataRole.UserRole) in ids:
                self.table.selectRow(row)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.ExtendedSelection)
        self._syncing = False
        self.selection_label.setText(f"selected: {', '.join(map(str, ids))}" if ids else
                                     "selected: none (click a feature; shift-click adds)")
        if ids:
            prewarm(_SKELETON)  # the skeleton's child process imports the core while the ends are placed
            self._measure()
        else:
            self.mask_info.setText("")
        if self._features_layer is not None and self._features_layer in self.viewer.layers:
            self.viewer.layers.selection.active = self._features_layer  # clicks keep reaching its callback
        self._update_needs()

    def _on_table_selection(self) -> None:
        if self._syncing or self.features is None:
            return
        rows = {i.row() for i in self.table.selectedItems()}
        ids = [self.table.item(r, 0).data(Qt.ItemDataRole.UserRole) for r in rows]
        self.select_features(ids, seeds={i: s for i, s in self.seeds.items() if i in ids})

    def use_labels(self, layer: Any, *, label: int | None = None, at: Any = None) -> int:
        """Make a Labels layer the selection (an expert's mask, a mask file): every labelled voxel (``label``
        None), one ``label``, or the label under the world position ``at``. Returns the selected voxel count.

        The layer must lie on the scan's voxel grid (same shape). The features' selection is cleared; a click on
        the layer afterwards (while it is the active layer) picks the label under it.
        """
        from napari.layers import Labels

        try:
            if self.volume is None:
                raise InvalidInputError("there is no scan yet: pick an Image layer or open a file (step 1)")
            if not isinstance(layer, Labels) or layer.ndim != 3:
                raise InvalidInputError(f"the layer {getattr(layer, 'name', layer)!r} is not a 3D Labels layer; "
                                        "pick a mask (Labels) layer")
            if tuple(layer.data.shape) != tuple(self.volume.shape):
                raise InvalidInputError(
                    f"the mask {layer.name!r} has {_fmt(layer.data.shape, 6)} voxels, the scan "
                    f"{_fmt(self.volume.shape, 6)}: a mask must lie on the scan's voxel grid")
            if at is not None:  # the voxel under the world position (napari's get_value needs the slice shown)
                idx = np.round(np.asarray(layer.world_to_data(np.asarray(at, dtype=float)[-3:]))).astype(int)
                inside = bool(np.all((idx >= 0) & (idx < np.asarray(layer.data.shape))))
                label = int(np.asarray(layer.data[tuple(idx)])) if inside else 0
                if label == 0:
                    raise InvalidInputError(f"no label there in {layer.name!r} (background): click inside the mask")
            if label is not None:
                label = int(label)
            data = np.asarray(layer.data)
            if not np.count_nonzero(data == label if label else data):
                what = f"label {label}" if label else "any label"
                raise InvalidInputError(f"the mask {layer.name!r} holds no voxel of {what}: pick another label")
            count = self.workflow.use_mask(data, label=label or None,
                                           key=(id(layer), label, hash(data.tobytes())))
        except UnwindError as exc:
            self._fail(exc)
            return 0
        self.mask_choice = (layer, label or None)
        if self._selection_layer is not None and self._selection_layer in self.viewer.layers:
            self.viewer.layers.remove(self._selection_layer)
        self._selection_layer = None
        if self._on_mask_click not in layer.mouse_drag_callbacks:
            layer.mouse_drag_callbacks.append(self._on_mask_click)
        share = 100 * count / max(1, int(np.prod(self.volume.shape)))
        what = f"label {label}" if label else "every label"
        self.selection_label.setText(f"selected: {what} of the mask {layer.name!r}, {count:,} voxels "
                                     f"({share:.3g} % of the scan)")
        self._say(f"the selection is {what} of {layer.name!r}: suggest the ends next (step 3)")
        prewarm(_SKELETON)
        self._update_needs()
        return count

    def _on_mask_click(self, layer: Any, event: Any) -> Generator[None, None, None]:
        """Mouse callback of a mask chosen with :meth:`use_labels`: a click (no drag) picks the label under it."""
        if event.type != "mouse_press":
            return
        yield
        dragged = False
        while event.type == "mouse_move":
            dragged = True
            yield
        if not dragged and self.mask_choice is not None and self.mask_choice[0] is layer:
            self.use_labels(layer, at=event.position)

    def open_mask(self, path: str | os.PathLike) -> Job | None:
        """Open a mask file (any scan format; non-zero voxels are the mask) as a Labels layer over the scan and
        make it the selection."""
        volume = self.volume
        if volume is None:
            self._fail(InvalidInputError("there is no scan yet: pick an Image layer or open a file (step 1)"))
            return None

        def make() -> Generator[Progress, None, np.ndarray]:
            yield Progress("open", 0, 1, str(path))
            mask = open_volume(path)
            if tuple(mask.shape) != tuple(volume.shape):
                raise InvalidInputError(f"the mask {path} has {_fmt(mask.shape, 6)} voxels, the scan "
                                        f"{_fmt(volume.shape, 6)}: a mask must lie on the scan's voxel grid")
            data = np.asarray(mask.data)
            if not (np.issubdtype(data.dtype, np.integer) or data.dtype == np.bool_):
                data = data != 0
            yield Progress("open", 1, 1)
            return data.astype(np.uint8) if data.dtype == np.bool_ else data

        def done(data: np.ndarray) -> None:
            from ._layers import in_3d, labels_layer

            layer = self._add_layer(labels_layer(data, spacing=volume.spacing, unit=volume.unit,
                                                 name=Path(path).name, translate=tuple(volume.origin)))
            in_3d(self.viewer, layer)
            self.use_labels(layer)

        return self._start(make, "opening the mask", done)

    def mask(self) -> Any:
        """The selection at full resolution (lazy dask bool array): the chosen mask, or the selected features
        through the pipeline's select_step with the dock's segmentation options (nothing is computed here)."""
        self._check_selection()
        return self.workflow.mask()

    # ==============================================================================================================
    # ends
    # ==============================================================================================================
    def suggest_ends(self) -> Job | None:
        """Suggest head and tail on the selection's mask (in a worker, here or on the server) and show them in the
        "ends" layer."""
        try:
            self._check_selection()
            task = self.workflow.suggest_ends_task()
        except UnwindError as exc:
            self._fail(exc)
            return None

        def done(ends: Any) -> None:
            task.apply(ends)
            self.set_ends([self.workflow.ends.head, self.workflow.ends.tail])
            self._say("suggested head and tail: check them in the \"ends\" layer, drag to move")

        return self._start(task.make, task.label, done)

    def set_ends(self, voxels: list, roles: list[str] | None = None) -> Any:
        """Show ends (full-resolution voxel coordinates, head first) in the "ends" Points layer."""
        pts = np.asarray(voxels, dtype=float).reshape(-1, 3)
        world = pts * np.asarray(self.volume.spacing) + np.asarray(self.volume.origin)
        if roles is None:
            roles = ["head" if i == 0 else "tail" if i == len(pts) - 1 else f"point {i + 1}" for i in range(len(pts))]
        size = ends_size(self.volume.shape, self.volume.spacing)
        if self._ends_layer is not None and self._ends_layer in self.viewer.layers:
            self._ends_layer.data = world
            self._ends_layer.features = {"end": roles}
        else:
            from ._layers import scan_units

            self._ends_layer = self._add_layer((world, {"name": "ends", "features": {"end": roles}, "size": size,
                                                        "face_color": "yellow", "border_color": "black",
                                                        "text": {"string": "{end}", "size": 12, "color": "yellow",
                                                                 "anchor": "upper_left"},
                                                        **scan_units(self.viewer)}, "points"))
        self._ends_layer.mode = "select"
        self.viewer.layers.selection.active = self._ends_layer
        if len(world):
            self._go_to(world[0])
        self._update_needs()
        return self._ends_layer

    def _go_to(self, world: Any) -> None:
        """Show the slice through a world point (2D) with the point at the centre of the view."""
        world = [float(v) for v in np.asarray(world, dtype=float)[-3:]]
        if self.viewer.dims.ndisplay == 2:
            for axis in self.viewer.dims.not_displayed:
                self.viewer.dims.set_point(axis, world[axis])
        self.viewer.scene.camera.center = tuple(world)  # napari uses the displayed axes' values

    def endpoints(self) -> Any:
        """The ends layer's points as an :class:`~napari_unwind.session.Endpoints` (None: no ends layer).

        Two points are head and tail; more are read in order as a chain: the start and end of each part.
        """
        from ..session import Endpoints

        layer = self._ends_layer
        if layer is None or layer not in self.viewer.layers or len(layer.data) == 0:
            return None
        world = np.asarray(layer.data, dtype=float)[:, -3:]
        vox = [tuple(float(c) for c in p) for p in
               (world - np.asarray(self.volume.origin)) / np.asarray(self.volume.spacing)]
        if len(vox) == 2:
            return Endpoints(head=vox[0], tail=vox[1])
        if len(vox) < 2 or len(vox) % 2:
            raise InvalidInputError(f"the ends layer has {len(vox)} point(s); give 2 (head, tail) or, for a specimen "
                                    "in pieces, an even number: the start and end of each part, head to tail")
        chain = tuple((vox[i], vox[i + 1]) for i in range(0, len(vox), 2))
        return Endpoints(head=vox[0], tail=vox[-1], chain=chain)

    # ==============================================================================================================
    # skeleton
    # ==============================================================================================================
    def run_skeleton(self) -> Job | None:
        """Estimate the deformation of the selection in a worker (progress, Cancel), here (in a child process) or
        on the server; the model gets it."""
        try:
            self._check_selection()
            self.workflow.set_ends(self.endpoints())  # the ends layer as the user left it (None: suggested)
            task = self.workflow.skeleton_task()
        except UnwindError as exc:
            self._fail(exc)
            return None
        self.skeleton_report.setPlainText("computing...")

        def done(result: Any) -> None:
            had_ends = self._ends_layer is not None
            task.apply(result)
            self._skeleton_ready(result, show_ends=not had_ends)

        return self._start(task.make, task.label, done, (self.skeleton_cancel,))

    def _skeleton_ready(self, outcome: Any, *, show_ends: bool = True) -> None:
        specimen, d = outcome.specimen, outcome.deformation
        result = getattr(specimen, "skeleton", None)
        where = outcome.where
        lines = [_status_line(specimen), f"length {d.length:.4g} {unit_label(d.unit)}, {len(d)} keyframes"
                 + (" (suggested ends)" if result is not None and result.suggested else "") + where]
        if result is not None:
            lines.append(result.report())
        folds = _folds_line(d, specimen.folded, "edit the keyframes there (Refine)")
        if folds:
            lines.append(folds)
        lines += [f"warning: {w}" for w in specimen.warnings]
        self.skeleton_report.setPlainText(for_dock("\n".join(lines)))
        if show_ends and outcome.endpoints is not None:
            self._show_session_ends(outcome.endpoints)
        self._say(_status_line(specimen) + (" (server)" if where else "")
                  + (" (warnings: see Skeleton)" if specimen.warnings or folds else ""))

    def _show_session_ends(self, ends: Any) -> None:
        if ends.chain:
            pts = [p for pair in ends.chain for p in pair]
        else:
            pts = [ends.head, ends.tail]
        self.set_ends(pts)

    def _on_deformation_changed(self, d: Any) -> None:
        self._update_needs()

    # ==============================================================================================================
    # export
    # ==============================================================================================================
    def _on_format_chosen(self, index: int) -> None:
        from ..io._formats import _suffix

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

    def _show_export_options(self, options: ExportOptions) -> None:
        """Set the export page's fields to ``options`` (the pipeline's defaults when the dock starts)."""
        self.spacing_box.setValue(options.spacing or 0.0)
        self.order_combo.setCurrentIndex(max(0, self.order_combo.findData(options.order)))
        self.pad_box.setValue(int(options.pad))
        self.allow_folds_box.setChecked(bool(options.allow_folds))

    def export_options(self) -> ExportOptions:
        """The pipeline's export options with the export page's fields (spacing, order, padding, allow folds)."""
        return replace(self.options.export, spacing=self.spacing_box.value() or None,
                       order=int(self.order_combo.currentData()), pad=int(self.pad_box.value()),
                       allow_folds=self.allow_folds_box.isChecked())

    def _folded(self) -> float | None:
        """The fraction of the specimen's mask in the folds of the model's deformation: the skeleton's figure
        while the deformation is as the skeleton left it, else None (unknown: the fold rule then refuses any
        fold unless folds are allowed)."""
        return self.workflow.folded()

    def export(self, path: str | os.PathLike) -> Job | None:
        """Straighten the scan with the model's deformation and write ``path`` (worker, progress, Cancel); the
        written file opens as a layer."""
        from ..io._formats import output_format

        try:
            if self.volume is None:
                raise InvalidInputError("there is no scan yet: pick an Image layer or open a file (step 1)")
            if self.model.deformation is None:
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
            if not self.confirm_overwrite(target):
                self._say(f"not exported: {target} was kept")
                return None
            overwrite = True
        try:
            task = self.workflow.export_task(target, options=self.export_options(), overwrite=overwrite)
        except UnwindError as exc:
            self._fail(exc)
            return None
        where = "" if self.server is None else " (server)"

        def make() -> Generator[Progress, None, tuple]:
            value = yield from task.make()
            return value, contrast_limits(open_volume(value[0]).levels)

        def done(result: tuple) -> None:
            from ._layers import image_layer

            value, clim = result
            task.apply(value)
            written, warned = value
            self.exported = Path(written)
            self._add_layer(image_layer(open_volume(written), name=f"straight {self.exported.name}",
                                        contrast_limits=clim))
            self.export_info.setText(for_dock("\n".join([f"written: {self.exported}{where}"]
                                                         + [f"warning: {w}" for w in warned])))
            self._say(f"exported to {self.exported}{where}" + (f" (warning: {warned[0]})" if warned else ""))

        return self._start(make, task.label, done, (self.export_cancel,))

    def _check_selection(self) -> None:
        if self.mask_choice is not None and self.mask_choice[0] not in self.viewer.layers:
            self.mask_choice = None
            self.workflow.select([]) if self.features is not None else None
            raise InvalidInputError("the mask layer chosen as the selection was removed: choose another mask "
                                    "or click a feature (step 2)")
        if not self.workflow.has_selection:
            raise InvalidInputError("no feature is selected: segment the scan and click the specimen (step 2)")

    # ==============================================================================================================
    # session
    # ==============================================================================================================
    def _session_or_none(self) -> Any:
        """The session written into an export (None: the scan's checksum is not known yet)."""
        return self.workflow.session_or_none()

    def _session(self, source: Any) -> Any:
        return self.workflow.session(source)

    def _save_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save the session", "", "Sessions (*.unwind.json)")
        if path:
            self.save_session(path)

    def _load_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open a session", "", "Sessions (*.unwind.json)")
        if path:
            self.load_session(path)

    def save_session(self, path: str | os.PathLike) -> Job | None:
        """Save the current state as a session (the scan's checksum is computed once, in a worker).

        A session records the scan's file. A scan that has none (File > Open Sample, a layer made in napari) is
        written first, beside the session, as ``<name>.scan.ome.zarr``, and the session records that file: it
        opens again from the dock and from File > Open. The dock then works on that file.
        """
        from ..session import SESSION_SUFFIX, SourceInfo, save_session

        volume = self.volume
        path = Path(path).expanduser()
        try:
            if volume is None:
                raise InvalidInputError("there is no scan yet: pick an Image layer or open a file (step 1)")
            self._session(SourceInfo(path=volume.source or "scan", shape=volume.shape, dtype=volume.dtype.name,
                                     spacing=volume.spacing))  # checks selection and ends before hashing
            scan_file = None
            if not volume.source or not Path(volume.source).exists():
                stem = path.name[:-len(SESSION_SUFFIX)] if path.name.endswith(SESSION_SUFFIX) else path.stem
                scan_file = path.with_name(f"{stem}.scan.ome.zarr")
                if scan_file.exists():
                    raise InvalidInputError(
                        f"the scan {self.scan_layer.name!r} has no file, and the session would write it to "
                        f"{scan_file}, which exists: choose another session name, or move that file away")
        except UnwindError as exc:
            self._fail(exc)
            return None
        known = self.workflow.source_info if scan_file is None else None

        def make() -> Generator[Progress, None, Any]:
            if known is not None:
                return known, volume
            scan = volume
            if scan_file is not None:
                from ..io import write_volume_iter

                written = yield from write_volume_iter(volume, scan_file)
                scan = _with_geometry(open_volume(written), volume.spacing, volume.origin)
            yield Progress("checksum", 0, 1, scan.source)
            info = SourceInfo.from_path(scan.source, volume=scan)  # reads every byte once
            yield Progress("checksum", 1, 1)
            return info, scan

        def done(result: Any) -> None:
            source, scan = result
            self.workflow.source_info = source
            if scan is not volume:
                self.workflow.volume = scan  # the dock now works on the file the session records (same voxels)
                meta = dict(self.scan_layer.metadata or {})
                meta["napari_unwind"] = {**meta.get("napari_unwind", {}), "source": scan.source,
                                         "format": scan.format}
                self.scan_layer.metadata = meta
            written = save_session(self._session(source), path)
            saved_scan = f" with its scan {scan.source}" if scan is not volume else ""
            if self.mask_choice is not None:
                saved_scan += (" (a session records a selection of features, not a mask layer: after reopening, "
                               "choose the mask again in step 2)")
            self.session_info.setText(f"saved: {written}{saved_scan}")
            self._say(f"session saved to {written}{saved_scan}")

        return self._start(make, "saving the session", done)

    def load_session(self, path: str | os.PathLike) -> Job | None:
        """Open a session: its scan (a layer), the ends, the deformation, and the selection (the join tree is
        rebuilt in a worker, then the recorded features are selected)."""
        from ..session import load_session

        try:
            session = load_session(path)
        except (UnwindError, FileNotFoundError) as exc:
            self._fail(exc)
            return None
        src = session.source

        def make() -> Generator[Progress, None, Volume]:
            yield Progress("open", 0, 1, src.path)
            if not Path(src.path).exists():
                raise InvalidInputError(f"the session's scan is missing: expected at {src.path}; put it back or "
                                        "correct \"source\" -> \"path\" in the session file")
            volume = open_volume(src.path)
            if volume.shape != tuple(src.shape):
                raise InvalidInputError(f"the scan at {src.path} holds {volume.shape} voxels, the session's scan "
                                        f"{tuple(src.shape)}: it is not the scan the session was made from")
            yield Progress("open", 1, 1)
            origin = session.deformation.origin if session.deformation is not None else volume.origin
            return _with_geometry(volume, src.spacing, origin), contrast_limits(volume.levels)

        def done(value: tuple) -> None:
            from ._layers import image_layer

            volume, clim = value
            layer = self._add_layer(image_layer(volume, contrast_limits=clim))
            self.workflow.volume = None  # a fresh start, even on the same scan
            self._set_scan(volume, layer)
            self.workflow.source_info = src if src.checksum else None
            if session.endpoints is not None:
                self._show_session_ends(session.endpoints)
            if session.deformation is not None:
                self.model.set_deformation(session.deformation)
            seg = session.segmentation
            if seg is not None and seg.k is not None and (seg.selected or seg.seeds):
                self._pending_segmentation = seg
                self.job = None
                self.segment(level=seg.level)
            self.session_info.setText(f"opened: {Path(path).absolute()}")

        return self._start(make, "opening the session", done)

    # ==============================================================================================================
    # what each step needs
    # ==============================================================================================================
    def _update_needs(self) -> None:
        scan = self.volume is not None
        self.segment_need.setText("" if scan else "Needs a scan (step 1).")
        self.segment_button.setEnabled(scan)
        sel = self.workflow.has_selection and (self.mask_choice is None or self.mask_choice[0] in self.viewer.layers)
        features_chosen = bool(self.workflow.selection.ids)
        self.iso_slider.setEnabled(features_chosen)
        self.iso_default_button.setEnabled(features_chosen and self.workflow.isovalue is not None)
        self.ends_need.setText("" if sel else "Needs a selected feature (step 2).")
        self.suggest_button.setEnabled(sel)
        ends = self._ends_layer is not None and self._ends_layer in self.viewer.layers
        self.ends_info.setText(f"{len(self._ends_layer.data)} point(s) in \"ends\"" if ends else "no ends yet")
        self.skeleton_need.setText("" if sel else "Needs a selected feature (step 2); the ends (step 3) are "
                                                  "suggested when there are none.")
        self.skeleton_button.setEnabled(sel)
        d = self.model.deformation
        self.export_need.setText("Needs a scan and a deformation (step 4 or a session)." if d is None or not scan
                                 else f"deformation: length {d.length:.4g} {unit_label(d.unit)}, {len(d)} keyframes")
        self.export_button.setEnabled(d is not None and scan)
