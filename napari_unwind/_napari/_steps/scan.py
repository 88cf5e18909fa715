"""Step 1, Scan: the backend row (this computer or a server) and the scan (an Image layer or a file)."""

from __future__ import annotations

import os
from collections.abc import Callable, Generator
from typing import Any

import dask.array as da
import numpy as np
from qtpy.QtWidgets import QComboBox, QFileDialog, QFormLayout, QHBoxLayout, QLabel, QLineEdit, QPushButton, QVBoxLayout

from ...errors import InvalidInputError, UnwindError
from ...io import Volume, open_volume
from ...io._volume import normalise_unit, unit_label
from ...progress import Progress
from ...workflow import LocalBackend, ServerBackend
from .._reader import contrast_limits
from .._workers import Job, in_child
from ._base import Step, fmt


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
                  source=meta.get("source"), format=meta.get("format"),
                  metadata={"channel": str(meta["channel"])} if meta.get("channel") else {})


def _spacing_missing(volume: Volume) -> bool:
    return volume.unit is None and all(s == 1.0 for s in volume.spacing)


class ScanStep(Step):
    """The backend row above the scan's: "this computer", or "server" (address, token or token file, CA file for
    TLS, "path on server"; Connect checks health and the token); then the Image layer or the file to straighten."""

    def __init__(self, dock: Any) -> None:
        super().__init__(dock)
        lay = QVBoxLayout(self)
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

    # ---- the backend ------------------------------------------------------------------------------------------------
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
        from ..._remote import check_server, parse_server

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

        return self.dock._start(lambda: check_server(server), "connecting", done)

    # ---- the scan ---------------------------------------------------------------------------------------------------
    def image_layers(self) -> list:
        from napari.layers import Image

        return [lyr for lyr in self.viewer.layers if isinstance(lyr, Image) and lyr.ndim == 3 and not lyr.rgb]

    def refresh_layer_combo(self) -> None:
        layers = self.image_layers()
        scan_layer = self.dock.scan_layer
        self.layer_combo.blockSignals(True)
        self.layer_combo.clear()
        self.layer_combo.addItem("(choose an Image layer)", None)
        for lyr in layers:
            self.layer_combo.addItem(lyr.name, lyr)
        if scan_layer is not None and scan_layer in layers:
            self.layer_combo.setCurrentIndex(layers.index(scan_layer) + 1)
        self.layer_combo.blockSignals(False)

    def _on_layer_chosen(self, index: int) -> None:
        layer = self.layer_combo.itemData(index)
        if layer is not None and layer is not self.dock.scan_layer:
            self.use_layer(layer)

    def use_layer(self, layer: Any) -> None:
        """Make an Image layer the scan."""
        try:
            volume = volume_from_layer(layer)
        except UnwindError as exc:
            self._fail(exc)
            return
        self.set_scan(volume, layer)

    def set_scan(self, volume: Volume, layer: Any) -> None:
        """Make ``volume`` (shown by ``layer``) the workflow's scan; a new scan forgets the chosen mask."""
        dock = self.dock
        old = dock.volume
        changed = old is None or volume.source != old.source or volume.shape != old.shape
        dock.scan_layer = layer
        self.workflow.set_scan(volume, name=layer.name)
        from .._layers import in_3d, side_view_in_3d

        in_3d(self.viewer, layer)
        side_view_in_3d(self.viewer, layer)
        if changed:
            dock.mask_choice = None
        self.refresh_layer_combo()
        unit = unit_label(volume.unit)
        levels = f", {len(volume.levels)} pyramid levels" if len(volume.levels) > 1 else ""
        self.scan_info.setText(f"{layer.name}: {fmt(volume.shape, 6)} voxels of {volume.dtype}{levels}\n"
                               f"spacing {fmt(volume.spacing)} {unit}, unit {volume.unit or 'not recorded'}\n"
                               f"source {volume.source or '(not from a file: a saved session writes it beside it)'}")
        if _spacing_missing(volume):
            self.scan_warning.setText("Spacing missing: the scan records no voxel size, 1 x 1 x 1 is assumed and "
                                      "every length is in voxels. Open a format that stores it (OME-Zarr, NRRD, "
                                      "NIfTI) or set the layer's scale before segmenting.")
            self.scan_warning.show()
        else:
            self.scan_warning.hide()
        self._say(f"scan: {layer.name}")
        dock._update_needs()
        self._warm_glyphs()

    def _warm_glyphs(self) -> None:
        """Render the glyphs of the ends' labels a few per turn of the event loop, while the user segments (they
        were 40-50 ms of the first paint of the "ends" layer; issue 21)."""
        from .. import _private, _reveal

        def step() -> None:
            if not _private.viewer_closed(self.viewer) and not _private.warm_glyphs(self.viewer, limit=3):
                _reveal.later(step, self)

        _reveal.later(step, self)

    def _open_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open a scan")
        if path:
            self.open_scan(path)

    def open_scan(self, path: str | os.PathLike, *, then: Callable[[], Any] | None = None) -> Job | None:
        """Open a scan file (lazily, in a worker) and add it as an Image layer; it becomes the scan."""
        from .._layers import image_layer

        def make() -> Generator[Progress, None, tuple]:
            from napari.layers import Layer

            yield Progress("open", 0, 1, str(path))
            volume = open_volume(path)
            clim = contrast_limits(volume.levels)  # from its voxels, as the reader does (napari's: [0, 1])
            layer = Layer.create(*image_layer(volume, contrast_limits=clim))  # here, not on the UI thread (~50 ms)
            yield Progress("open", 1, 1)
            return volume, layer

        def done(value: tuple) -> None:
            volume, layer = value
            layer = self.dock._add_layer(layer, reveal=True)  # shown on a later turn, then made active
            self.set_scan(volume, layer)
            if then is not None:
                then()

        return self.dock._start(make, "opening the scan", done)
