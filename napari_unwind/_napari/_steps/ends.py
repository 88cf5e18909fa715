"""Step 3, Ends: suggested head and tail in the "ends" Points layer, moved or placed by hand."""

from __future__ import annotations

from typing import Any

import numpy as np
from qtpy.QtWidgets import QLabel, QPushButton, QVBoxLayout

from ...errors import InvalidInputError, UnwindError
from .._workers import Job
from ._base import Step


def ends_size(shape: Any, spacing: Any) -> float:
    """The ends' marker size (world units): 3 % of the scan's largest extent, at least 6 voxels (was 4 voxels:
    a dot on a scan of hundreds)."""
    extent = max(n * s for n, s in zip(shape, spacing, strict=True))
    return float(max(0.03 * extent, 6 * max(spacing)))


class EndsStep(Step):
    """Suggested head and tail (:func:`napari_unwind.skeleton.suggest_endpoints`) in a Points layer ``"ends"``: drag
    them in select mode, place more in add mode. Two points are head and tail; more are read in order as a chain."""

    def __init__(self, dock: Any) -> None:
        super().__init__(dock)
        lay = QVBoxLayout(self)
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

    def update_needs(self) -> None:
        sel = self.dock.has_selection
        self.ends_need.setText("" if sel else "Needs a selected feature (step 2).")
        self.suggest_button.setEnabled(sel)
        layer = self.dock._ends_layer
        ends = layer is not None and layer in self.viewer.layers
        self.ends_info.setText(f"{len(layer.data)} point(s) in \"ends\"" if ends else "no ends yet")

    def suggest_ends(self) -> Job | None:
        """Suggest head and tail on the selection's mask (in a worker, here or on the server) and show them in the
        "ends" layer."""
        try:
            self.dock._check_selection()
            task = self.workflow.suggest_ends_task()
        except UnwindError as exc:
            self._fail(exc)
            return None

        def done(ends: Any) -> None:
            task.apply(ends)
            self.set_ends([self.workflow.ends.head, self.workflow.ends.tail])
            self._say("suggested head and tail: check them in the \"ends\" layer, drag to move")

        return self.dock._start(task.make, task.label, done)

    def set_ends(self, voxels: list, roles: list[str] | None = None, *, later: bool = False) -> Any:
        """Show ends (full-resolution voxel coordinates, head first) in the "ends" Points layer. ``later``: a new
        layer goes into the viewer, is shown and the view moves to the head on the next turns of the event loop,
        one a turn (:mod:`.._reveal`: after a skeleton, whose result adds other layers too)."""
        dock, volume = self.dock, self.dock.volume
        pts = np.asarray(voxels, dtype=float).reshape(-1, 3)
        world = pts * np.asarray(volume.spacing) + np.asarray(volume.origin)
        if roles is None:
            roles = ["head" if i == 0 else "tail" if i == len(pts) - 1 else f"point {i + 1}" for i in range(len(pts))]
        size = ends_size(volume.shape, volume.spacing)
        from .. import _reveal

        if dock._ends_layer is not None and dock._ends_layer not in self.viewer.layers:
            _reveal.flush()  # a new "ends" layer still on its way in
        added = False
        if dock._ends_layer is not None and dock._ends_layer in self.viewer.layers:
            later = False
            dock._ends_layer.data = world
            dock._ends_layer.features = {"end": roles}
        else:
            from napari.layers import Points

            from .._layers import scan_units

            layer = Points(world, name="ends", features={"end": roles}, size=size, face_color="yellow",
                           border_color="black", text={"string": "{end}", "size": 12, "color": "yellow",
                                                       "anchor": "upper_left"}, **scan_units(self.viewer))
            layer.mode = "select"

            def needs() -> None:
                if layer in self.viewer.layers:
                    dock._update_needs()

            if later:  # into the viewer, shown, made active, the step's text, one a turn
                dock._ends_layer = _reveal.add_layer(self.viewer, layer, now=False, then=needs)
            else:  # into the viewer now, shown and made active on the next turns (the suggest step's result)
                dock._ends_layer = _reveal.add_layer(self.viewer, layer)
                added = True
        layer = dock._ends_layer
        layer.mode = "select"
        if later:
            if len(world):
                _reveal.later(lambda: self._go_to(world[0]), layer)
            return layer
        if not added:
            self.viewer.layers.selection.active = layer
        if len(world):
            self._go_to(world[0])
        dock._update_needs()
        return layer

    def show_session_ends(self, ends: Any, *, later: bool = False) -> None:
        """Show an :class:`~napari_unwind.session.Endpoints` (a session's, the skeleton's suggestion)."""
        if ends.chain:
            pts = [p for pair in ends.chain for p in pair]
        else:
            pts = [ends.head, ends.tail]
        self.set_ends(pts, later=later)

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
        from ...session import Endpoints
        from .. import _reveal

        layer, volume = self.dock._ends_layer, self.dock.volume
        if layer is not None and layer not in self.viewer.layers:
            _reveal.flush()  # a new "ends" layer still on its way in
        if layer is None or layer not in self.viewer.layers or len(layer.data) == 0:
            return None
        world = np.asarray(layer.data, dtype=float)[:, -3:]
        vox = [tuple(float(c) for c in p) for p in
               (world - np.asarray(volume.origin)) / np.asarray(volume.spacing)]
        if len(vox) == 2:
            return Endpoints(head=vox[0], tail=vox[1])
        if len(vox) < 2 or len(vox) % 2:
            raise InvalidInputError(f"the ends layer has {len(vox)} point(s); give 2 (head, tail) or, for a specimen "
                                    "in pieces, an even number: the start and end of each part, head to tail")
        chain = tuple((vox[i], vox[i + 1]) for i in range(0, len(vox), 2))
        return Endpoints(head=vox[0], tail=vox[-1], chain=chain)
