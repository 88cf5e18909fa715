"""The Export page's "every channel" choice: the other Image layers on the scan's grid, exported with the scan as
one multi-channel image (issue 24 item 1). The grid test and the export are the workflow's."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from qtpy.QtWidgets import QCheckBox, QLabel, QVBoxLayout, QWidget

from ...errors import UnwindError


def _shape(layer: Any) -> tuple[int, ...]:
    data = layer.data[0] if getattr(layer, "multiscale", False) else layer.data
    return tuple(int(n) for n in data.shape)


def channel_layers(viewer: Any, scan_layer: Any) -> list[Any]:
    """The Image layers other than ``scan_layer`` on its grid: 3D, grey, same shape, scale and translate."""
    if scan_layer is None:
        return []
    shape = _shape(scan_layer)
    out = []
    for layer in viewer.layers:
        if layer is scan_layer or layer.__class__.__name__ != "Image" or getattr(layer, "rgb", False):
            continue
        if getattr(layer, "ndim", 0) != 3 or _shape(layer) != shape:
            continue
        if not (np.allclose(layer.scale, scan_layer.scale, rtol=1e-6, atol=0)
                and np.allclose(layer.translate, scan_layer.translate, rtol=0, atol=1e-6 * float(np.min(np.abs(
                    scan_layer.scale))))):
            continue
        out.append(layer)
    return out


class ChannelsBox(QWidget):
    """A check box "with the other channels" and the names of the layers it takes (updated with the layers)."""

    def __init__(self, dock: Any) -> None:
        super().__init__()
        self.dock = dock
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.check = QCheckBox("with the other channels")
        self.check.setToolTip("Straighten the other Image layers of the scan's grid (channels, stains) with the scan "
                              "in one pass, into one multi-channel image (OME-Zarr with a c axis, or a TIFF "
                              "hyperstack)")
        self.info = QLabel("")
        self.info.setWordWrap(True)
        self.info.setMinimumWidth(1)
        lay.addWidget(self.check)
        lay.addWidget(self.info)
        self.update_layers()

    def layers(self) -> list[Any]:
        return channel_layers(self.dock.viewer, self.dock.scan_layer)

    def update_layers(self) -> None:
        found = self.layers()
        self.check.setEnabled(bool(found))
        if not found:
            self.check.setChecked(False)
        self.info.setText(", ".join(layer.name for layer in found) if found else
                          "no other Image layer on the scan's grid")

    def volumes(self) -> list[Any]:
        """The chosen channels as Volumes named after their layers (none when unchecked)."""
        from .scan import volume_from_layer

        if not self.check.isChecked():
            return []
        out = []
        for layer in self.layers():
            try:
                v = volume_from_layer(layer)
            except UnwindError:
                continue
            out.append(replace(v, metadata={**v.metadata, "channel": v.metadata.get("channel") or layer.name}))
        return out
