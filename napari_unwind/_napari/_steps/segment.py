"""Step 2, Segment: the join tree's features (count slider, table, click to select), the selection's threshold,
or a mask (a Labels layer or a mask file) as the selection."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Generator
from pathlib import Path
from typing import Any

import numpy as np
from qtpy.QtCore import Qt
from qtpy.QtWidgets import (
    QAbstractItemView,
    QComboBox,
    QFileDialog,
    QGridLayout,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QPushButton,
    QSlider,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
)

from ...errors import InvalidInputError, UnwindError
from ...progress import Progress
from ...progress import run as run_progress
from .._workers import Job, prewarm
from ._base import SKELETON, Step, fmt, labels_layers, on_click

#: Positions of the threshold slider over the scan's intensity range.
ISO_STEPS = 1000
#: The feature table's columns: (header, tooltip); short headers so that the columns fit napari's default dock width.
TABLE_COLUMNS = (
    ("id", "The feature's label"),
    ("voxels", "Labelled voxels at working resolution"),
    ("elong.", "Elongation: principal-axis ratio (1 for a ball, about 6 for a fish)"),
    ("pers.", "Persistence: the feature's maximum minus the saddle where it merges into its parent"),
    ("thresh.", "Threshold: the half-maximum cut, the default isovalue of the mask"),
    ("edge", "Border: the feature reaches a face of the scan"),
    ("cont.", "Container: touches the border or encloses another feature (a tube, a dish)"),
)


class SegmentStep(Step):
    """The join tree is built once in a worker (Cancel stops it); the feature-count slider re-simplifies it live
    (no rebuild). The features are a Labels layer; a click on one (2D or 3D) selects it, shift-click adds it; the
    table lists their statistics and shows the selection (the Labels layer ``"selection"``). The threshold slider
    grows or shrinks the selection's mask; "or a mask" makes a Labels layer or a mask file the selection."""

    def __init__(self, dock: Any) -> None:
        super().__init__(dock)
        self._pending_segmentation: Any = None  # a loaded session's Segmentation, applied when the tree is built
        self._simplify_worker: Any = None
        self._simplify_pending: int | None = None
        self._syncing = False
        self._iso_range_cache: tuple | None = None
        self._measure_worker: Any = None
        self._measure_pending = False
        self._features_click = on_click(self._on_features_click)
        self._mask_click = on_click(self._on_mask_click)

        lay = QVBoxLayout(self)
        self.segment_need = QLabel("")
        self.segment_need.setWordWrap(True)
        lay.addWidget(self.segment_need)
        self.segment_button, self.segment_cancel = self.job_buttons(lay, "Build the join tree", lambda: self.segment())
        row = QHBoxLayout()
        row.addWidget(QLabel("features"))
        self.count_slider = QSlider(Qt.Orientation.Horizontal)
        k = self.workflow.options.segment.k
        self.count_slider.setRange(1, k)
        self.count_slider.setValue(k)
        self.count_slider.setEnabled(False)
        self.count_slider.valueChanged.connect(self.set_feature_count)
        self.count_label = QLabel(str(k))
        row.addWidget(self.count_slider, 1)
        row.addWidget(self.count_label)
        lay.addLayout(row)
        lay.addWidget(self._table(), 1)
        self.selection_label = QLabel("selected: none (click a feature; shift-click adds)")
        self.selection_label.setWordWrap(True)
        lay.addWidget(self.selection_label)
        # the selected features' threshold at full resolution: lower grows the mask, higher shrinks it
        grid = QGridLayout()
        grid.addWidget(QLabel("threshold"), 0, 0)
        self.iso_slider = QSlider(Qt.Orientation.Horizontal)
        self.iso_slider.setRange(0, ISO_STEPS)
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

    def _table(self) -> QTableWidget:
        """The feature table: its columns share the dock's width (no sideways scrolling at napari's 400 px)."""
        self.table = QTableWidget(0, len(TABLE_COLUMNS))
        for col, (name, tip) in enumerate(TABLE_COLUMNS):
            item = QTableWidgetItem(name)
            item.setToolTip(tip)
            self.table.setHorizontalHeaderItem(col, item)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.verticalHeader().hide()  # the id column names the rows
        header = self.table.horizontalHeader()
        header.setMinimumSectionSize(24)
        header.setSectionResizeMode(QHeaderView.ResizeMode.Stretch)  # the figures share what is left
        for col in (0, 5, 6):  # id, edge, container: as wide as their header or values
            header.setSectionResizeMode(col, QHeaderView.ResizeMode.ResizeToContents)
        self.table.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.table.itemSelectionChanged.connect(self._on_table_selection)
        return self.table

    @property
    def busy(self) -> bool:
        """A re-simplification or a measurement of the selection is running."""
        return self._simplify_worker is not None or self._measure_worker is not None

    def update_needs(self) -> None:
        scan = self.dock.volume is not None
        self.segment_need.setText("" if scan else "Needs a scan (step 1).")
        self.segment_button.setEnabled(scan)
        features_chosen = bool(self.workflow.selection.ids)
        self.iso_slider.setEnabled(features_chosen)
        self.iso_default_button.setEnabled(features_chosen and self.workflow.isovalue is not None)

    # ---- the join tree and the feature count ------------------------------------------------------------------------
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
            self._set_slider(int(getattr(self.workflow.tree, "n_maxima", 0) or 0), self.workflow.features.k)

        return self.dock._start(task.make, task.label, done, (self.segment_cancel,))

    def resume(self, segmentation: Any) -> Job | None:
        """Build the tree again for a session's :class:`~napari_unwind.session.Segmentation`; its selection is
        applied when the features are ready."""
        self._pending_segmentation = segmentation
        return self.segment(level=segmentation.level)

    def _set_slider(self, maxima: int, k: int | None) -> int:
        """The slider's range for a tree of ``maxima`` maxima (0: unknown) at ``k`` (default: its value); returns
        the value set."""
        from ...segmentation import MAX_FEATURES

        top = max(1, min(MAX_FEATURES, maxima or MAX_FEATURES))
        k = min(k or self.count_slider.value(), top)
        self.count_slider.blockSignals(True)
        self.count_slider.setRange(1, top)
        self.count_slider.setValue(k)
        self.count_slider.blockSignals(False)
        self.count_slider.setEnabled(True)
        self.count_label.setText(str(k))
        return k

    def set_feature_count(self, k: int) -> None:
        """Re-simplify the tree to ``k`` features (no rebuild), off the UI thread; while the slider moves only the
        latest value waits. The selection follows its clicks. On a server the segmentation is simplified there
        and the label volume of ``k`` features downloaded."""
        self.count_label.setText(str(int(k)))
        if self.workflow.tree is None:
            return
        self._simplify_pending = int(k)
        if self._simplify_worker is None:
            self._next_simplify()

    def _next_simplify(self) -> None:
        from napari.qt.threading import create_worker

        k, self._simplify_pending = self._simplify_pending, None
        source = self.workflow.tree  # this computer's tree or the server's segmentation
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
        if source is not self.workflow.tree:
            return  # from a tree or segmentation replaced meanwhile (another scan, another server)
        self.workflow.set_features(features)  # -> features_ready

    def features_ready(self, features: Any) -> None:
        """The workflow's features changed: draw them, fill the table; a loaded session's selection is applied
        (the workflow itself lets the clicked seeds choose again among the new features)."""
        f, dock = features, self.dock
        layer = dock._put_layer("_features_layer", self._labels_tuple(f.labels, "features", opacity=0.4))
        layer.metadata["napari_unwind"] = {"features": True}
        if self._features_click not in layer.mouse_drag_callbacks:
            layer.mouse_drag_callbacks.append(self._features_click)
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
            self.show_selection(self.workflow.selection)  # the table was refilled
        self._say(f"{f.k} features (level {f.level}, {fmt(f.shape, 6)} working voxels)")

    def _labels_tuple(self, labels: np.ndarray, name: str, **kwargs: Any) -> tuple:
        from .._layers import labels_layer

        f = self.workflow.features
        return labels_layer(labels, spacing=f.spacing, unit=f.unit, name=name,
                            translate=tuple(float(o) for o in f.working_origin), **kwargs)

    def _fill_table(self) -> None:
        f = self.workflow.features
        self._syncing = True
        self.table.setRowCount(len(f.stats))
        for row, st in enumerate(f.stats):
            values = (st.id, st.voxel_count, f"{st.elongation:.2f}", f"{st.persistence:.4g}", f"{st.threshold:.4g}",
                      "yes" if st.touches_border else "", "yes" if st.container else "")
            for col, v in enumerate(values):
                item = QTableWidgetItem(str(v))
                item.setData(Qt.ItemDataRole.UserRole, int(st.id))
                self.table.setItem(row, col, item)
        self._syncing = False

    # ---- the selection ----------------------------------------------------------------------------------------------
    def _on_features_click(self, layer: Any, event: Any) -> None:
        """A click on the features layer selects the feature under it; shift adds."""
        self.pick(event.position, view_direction=getattr(event, "view_direction", None),
                  dims_displayed=getattr(event, "dims_displayed", None),
                  add="Shift" in {str(getattr(m, "name", m)) for m in (event.modifiers or ())})

    def pick(self, position: Any, *, view_direction: Any = None, dims_displayed: Any = None,
             add: bool = False) -> int:
        """Select the feature at a world position (2D: the point; 3D: along the view ray); return its id (0: none)."""
        layer, features, volume = self.dock._features_layer, self.workflow.features, self.dock.volume
        if features is None or layer is None:
            return 0
        ndisp = 0 if dims_displayed is None else len(dims_displayed)
        value = layer.get_value(position, view_direction=view_direction if ndisp == 3 else None,
                                dims_displayed=list(dims_displayed) if ndisp == 3 else None, world=True)
        fid = int(value) if value is not None else 0
        if fid == 0:
            self._say("no feature there (background): click on a coloured feature")
            return 0
        st = features.stat(fid)
        if ndisp == 3:  # the ray's hit is not a point: take the feature's maximum as its seed
            seed = tuple(float(c) for c in st.max_position_full)
        else:
            vox = (np.asarray(position, dtype=float)[-3:] - np.asarray(volume.origin)) / np.asarray(volume.spacing)
            seed = tuple(float(c) for c in vox)
        selection = self.workflow.selection
        ids = list(selection.ids) if add else []
        seeds = {i: selection.seeds[i] for i in ids if i in selection.seeds}
        if fid not in ids:
            ids.append(fid)
        seeds[fid] = seed
        self.select_features(ids, seeds=seeds)
        return fid

    def select_features(self, ids: list[int], *, seeds: dict[int, tuple] | None = None) -> None:
        """Set the selection (feature ids of the current segmentation); shown in the table and the layer."""
        if self.workflow.features is None:
            return
        self.dock.mask_choice = None
        self.workflow.select(ids, seeds=seeds)  # -> show_selection

    def show_selection(self, selection: Any) -> None:
        """The workflow's selection changed: the selection layer, the table's rows and the label."""
        dock = self.dock
        if selection.mask is not None:
            self._measure()
            dock._update_needs()
            return
        ids, f = list(selection.ids), selection.features
        if f is not None:
            labels = np.where(np.isin(f.labels, ids), f.labels, 0).astype(f.labels.dtype)
            layer = dock._put_layer("_selection_layer", self._labels_tuple(labels, "selection", opacity=0.8,
                                                                           blending="additive"))
            if not layer.visible and layer in self.viewer.layers:
                layer.visible = True  # hidden while a mask was the selection
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
            prewarm(SKELETON)  # the skeleton's child process imports the core while the ends are placed
            self._measure()
        else:
            self.mask_info.setText("")
        self._activate_features()
        dock._update_needs()

    def _activate_features(self) -> None:
        """Make the features layer the active one (clicks keep reaching its callback); after the new layers'
        steps when some wait (:mod:`.._reveal`)."""
        from .. import _reveal

        layer = self.dock._features_layer

        def activate() -> None:
            if layer is self.dock._features_layer and layer in self.viewer.layers:
                self.viewer.layers.selection.active = layer

        if layer is not None and _reveal.pending():
            _reveal.later(activate, layer)
        else:
            activate()

    def _on_table_selection(self) -> None:
        if self._syncing or self.workflow.features is None:
            return
        rows = {i.row() for i in self.table.selectedItems()}
        ids = [self.table.item(r, 0).data(Qt.ItemDataRole.UserRole) for r in rows]
        self.select_features(ids, seeds={i: s for i, s in self.workflow.selection.seeds.items() if i in ids})

    # ---- the threshold slider ---------------------------------------------------------------------------------------
    def _iso_range(self) -> tuple[float, float]:
        if self._iso_range_cache is None or self._iso_range_cache[0] is not self.dock.volume:
            self._iso_range_cache = (self.dock.volume, self.workflow.intensity_range())
        return self._iso_range_cache[1]

    def _iso_at(self, position: int) -> float:
        lo, hi = self._iso_range()
        return lo + (hi - lo) * position / ISO_STEPS

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
        self.iso_slider.setValue(int(round(ISO_STEPS * (iso - lo) / (hi - lo))) if hi > lo else 0)
        self._syncing = False

    # ---- or a mask --------------------------------------------------------------------------------------------------
    def refresh_mask_combo(self) -> None:
        layers = labels_layers(self.dock)  # the viewer's 3D Labels layers but the dock's own
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

    def use_labels(self, layer: Any, *, label: int | None = None, at: Any = None) -> int:
        """Make a Labels layer the selection (an expert's mask, a mask file): every labelled voxel (``label``
        None), one ``label``, or the label under the world position ``at``. Returns the selected voxel count.

        The layer must lie on the scan's voxel grid: the same shape, or a box of it where the viewer shows it (the
        scan's voxel size, a translate a whole number of voxels from the scan's). The features' selection is
        cleared; a click on the layer afterwards (while it is the active layer) picks the label under it.
        """
        from napari.layers import Labels

        dock, volume = self.dock, self.dock.volume
        try:
            if volume is None:
                raise InvalidInputError("there is no scan yet: pick an Image layer or open a file (step 1)")
            if not isinstance(layer, Labels) or layer.ndim != 3:
                raise InvalidInputError(f"the layer {getattr(layer, 'name', layer)!r} is not a 3D Labels layer; "
                                        "pick a mask (Labels) layer")
            if at is not None:  # the voxel under the world position (napari's get_value needs the slice shown)
                idx = np.round(np.asarray(layer.world_to_data(np.asarray(at, dtype=float)[-3:]))).astype(int)
                inside = bool(np.all((idx >= 0) & (idx < np.asarray(layer.data.shape))))
                label = int(np.asarray(layer.data[tuple(idx)])) if inside else 0
                if label == 0:
                    raise InvalidInputError(f"no label there in {layer.name!r} (background): click inside the mask")
            if label is not None:
                label = int(label)
            data, placed = np.asarray(layer.data), None
            if data.shape != tuple(volume.shape):  # a box of the scan's grid where the viewer shows it (a cropped mask)
                from ...io._grid import place_array

                data, placed = place_array(data, volume, spacing=layer.scale[-3:], origin=layer.translate[-3:],
                                           name=f"the mask {layer.name!r}")
                data = np.asarray(data)
            if not np.count_nonzero(data == label if label else data):
                what = f"label {label}" if label else "any label"
                raise InvalidInputError(f"the mask {layer.name!r} holds no voxel of {what}: pick another label")
            meta = (layer.metadata or {}).get("napari_unwind", {})
            source = meta.get("source") or getattr(getattr(layer, "source", None), "path", None)
            # the key tells the server's cached upload apart from an edited mask; a digest, not a copy of the voxels
            digest = hashlib.blake2b(memoryview(np.ascontiguousarray(data)).cast("B"), digest_size=16).hexdigest()
            count = self.workflow.use_mask(data, label=label or None, key=(id(layer), label, digest), source=source)
        except UnwindError as exc:
            self._fail(exc)
            return 0
        dock.mask_choice = (layer, label or None)
        from .. import _reveal

        own = dock._selection_layer
        if own is not None:
            _reveal.cancel(own)  # its steps still waiting (put in, shown) are dropped
            if own in self.viewer.layers:
                # kept, hidden and emptied: a click on a feature later shows it again instead of napari inserting a
                # new Labels layer (its controls and overlays: about 110 ms of one turn, issue 21)
                own.visible = False
                if not getattr(own, "multiscale", False):
                    own.data = np.zeros(own.data.shape, dtype=own.data.dtype)
            else:
                dock._selection_layer = None
        if self._mask_click not in layer.mouse_drag_callbacks:
            layer.mouse_drag_callbacks.append(self._mask_click)
        share = 100 * count / max(1, int(np.prod(volume.shape)))
        what = f"label {label}" if label else "every label"
        self.selection_label.setText(f"selected: {what} of the mask {layer.name!r}, {count:,} voxels "
                                     f"({share:.3g} % of the scan)")
        # what reading the file did (read_mask) and placing the layer's box on the scan's grid
        notes = " ".join(f"Note: {n.rstrip('.')}." for n in (*meta.get("notes", ()), placed) if n)
        self._say(f"the selection is {what} of {layer.name!r}: suggest the ends next (step 3)"
                  + (f". {notes}" if notes else ""))
        prewarm(SKELETON)
        dock._update_needs()
        return count

    def _on_mask_click(self, layer: Any, event: Any) -> None:
        """A click on a mask chosen with :meth:`use_labels` picks the label under it."""
        choice = self.dock.mask_choice
        if choice is not None and choice[0] is layer:
            self.use_labels(layer, at=event.position)

    def open_mask(self, path: str | os.PathLike, *, label: int | None = None) -> Job | None:
        """Open a mask file (any scan format; non-zero voxels are the mask) as a Labels layer over the scan and
        make it (or its ``label``) the selection; a session records the file."""
        volume = self.dock.volume
        try:
            task = self.workflow.mask_file_task(path, label=label)  # the reading and the grid check
        except UnwindError as exc:
            self._fail(exc)
            return None
        def make() -> Generator[Progress, None, Any]:
            from napari.layers import Layer

            from .._layers import labels_layer

            data, notes = yield from task.make()
            return Layer.create(*labels_layer(  # made here, not on the UI thread
                data, spacing=volume.spacing, unit=volume.unit, name=Path(path).name, translate=tuple(volume.origin),
                metadata={"napari_unwind": {"source": str(Path(path).absolute()), "notes": list(notes)}}))

        def done(layer: Any) -> None:
            from .._layers import in_3d

            self.dock._add_layer(layer, reveal=True)  # napari's insert, and its first paint on the next turn
            in_3d(self.viewer, layer)
            self.use_labels(layer, label=label)

        return self.dock._start(make, "opening the mask", done)
