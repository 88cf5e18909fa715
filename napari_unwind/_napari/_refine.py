"""The Refine step of the Unwind dock: the 2D cross-section editor, the s strip, the keyframe and history buttons,
the bent-view wireframes and the straight preview, all on one :class:`~napari_unwind.editing.EditModel`.

The panel only translates buttons, keys and the strip into model calls; every model event redraws the plane
(:class:`EditorCanvas`) at once, requests the preview (:class:`StraightPreview`, off the UI thread), and updates the
bent view's layers (:class:`BentOverlays`) and the strip's fold marks as soon as the event loop is free (the updates
of a drag that arrive in between are drawn once: napari's layer bookkeeping costs ~10 ms per layer update).
A refused edit (deleting one of the last two keyframes...) shows its one-line message under the buttons.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from qtpy.QtCore import QPointF, QRectF, Qt, QTimer, Signal
from qtpy.QtGui import QColor, QKeySequence, QPainter, QPen
from qtpy.QtWidgets import (
    QCheckBox,
    QDoubleSpinBox,
    QGridLayout,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QShortcut,
    QSizePolicy,
    QVBoxLayout,
    QWidget,
)

from ..editing import EditModel
from ..errors import UnwindError
from ..io import Volume
from ..io._volume import unit_label
from ._editor_canvas import EditorCanvas
from ._overlays import BentOverlays
from ._preview import StraightPreview

__all__ = ["RefinePanel", "SStrip"]

_STEP = math.radians(1.0)  # tilt and twist step of the keys and buttons, as in the paper


class SStrip(QWidget):
    """A slider over s in [0, L]: keyframes as ticks, folding intervals in red, the current s as a handle.

    Clicking or dragging sets s (``s_requested``); the strip draws whatever :meth:`set_state` gives it.
    """

    s_requested = Signal(float)

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setMinimumHeight(28)
        self.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Fixed)
        self.setToolTip("s along the curve: click or drag to move; ticks are keyframes, red spans fold")
        self.length = 0.0
        self.s = 0.0
        self.knots: list[float] = []
        self.folds: list[tuple[float, float]] = []
        self.selected: int | None = None
        self._margin = 8

    def set_state(self, length: float, s: float, knots: Any, folds: Any, selected: int | None) -> None:
        self.length, self.s = float(length), float(s)
        self.knots = [float(k) for k in knots]
        self.folds = [(float(a), float(b)) for a, b in folds]
        self.selected = selected
        self.update()

    def x_of(self, s: float) -> float:
        """The widget x of arclength ``s``."""
        w = self.width() - 2 * self._margin
        return self._margin + (w * s / self.length if self.length > 0 else 0.0)

    def s_of(self, x: float) -> float:
        w = max(1, self.width() - 2 * self._margin)
        return min(max((x - self._margin) / w, 0.0), 1.0) * self.length

    def paintEvent(self, _event: Any) -> None:  # noqa: N802 (Qt's name)
        p = QPainter(self)
        h = self.height()
        mid = h / 2
        p.fillRect(QRectF(self._margin, mid - 3, self.width() - 2 * self._margin, 6), QColor(90, 90, 90))
        for a, b in self.folds:
            p.fillRect(QRectF(self.x_of(a), mid - 5, max(2.0, self.x_of(b) - self.x_of(a)), 10), QColor(220, 40, 40))
        for i, k in enumerate(self.knots):
            pen = QPen(QColor(255, 255, 255) if i == self.selected else QColor(80, 200, 255))
            pen.setWidth(3 if i == self.selected else 2)
            p.setPen(pen)
            x = self.x_of(k)
            p.drawLine(QPointF(x, 2), QPointF(x, h - 2))
        if self.length > 0:
            p.setPen(QPen(QColor(0, 0, 0)))
            p.setBrush(QColor(255, 200, 0))
            p.drawEllipse(QPointF(self.x_of(self.s), mid), 6, 6)
        p.end()

    def mousePressEvent(self, event: Any) -> None:  # noqa: N802
        if self.length > 0:
            self.s_requested.emit(self.s_of(event.position().x()))

    def mouseMoveEvent(self, event: Any) -> None:  # noqa: N802
        if self.length > 0 and event.buttons() & Qt.MouseButton.LeftButton:
            self.s_requested.emit(self.s_of(event.position().x()))


class RefinePanel(QWidget):
    """The cross-section editor and its controls.

    Parameters
    ----------
    viewer : napari.Viewer
        Where the bent-view wireframes and the straight preview go.
    model : EditModel
        The editing model the dock shares.
    scan : callable
        Returns the current scan (a Volume on the deformation's grid, with its pyramid), or None.
    """

    #: (key, action) pairs, active while the focus is in the panel (the dock lists them).
    SHORTCUTS: list[tuple[str, str]] = [
        ("Ctrl+Z", "undo"),
        ("Ctrl+Shift+Z", "redo"),
        ("PgUp", "previous keyframe"),
        ("PgDown", "next keyframe"),
        ("Left", "step s back one voxel"),
        ("Right", "step s forward one voxel"),
        ("K", "add a keyframe here"),
        ("Delete", "delete the keyframe"),
        ("W", "tilt about u +1 degree"),
        ("S", "tilt about u -1 degree"),
        ("D", "tilt about v +1 degree"),
        ("A", "tilt about v -1 degree"),
        ("E", "twist +1 degree (counter-clockwise)"),
        ("Q", "twist -1 degree"),
        ("F", "fit the cross-section in the view"),
        ("Escape", "cancel the drag"),
        ("drag centre / inside the cage", "move the keyframe"),
        ("drag an edge or corner", "resize the cage"),
        ("drag an axis handle, or Shift-drag", "twist"),
    ]

    def __init__(self, viewer: Any, model: EditModel, scan: Callable[[], Volume | None]) -> None:
        super().__init__()
        self.viewer = viewer
        self.model = model
        self._scan = scan
        self.editor = EditorCanvas(model, scan)
        self.overlays = BentOverlays(viewer)
        self.preview = StraightPreview(viewer, scan)
        self._actions: dict[str, Callable[[], Any]] = {
            "undo": model.undo,
            "redo": model.redo,
            "previous keyframe": model.previous_keyframe,
            "next keyframe": model.next_keyframe,
            "step s back one voxel": lambda: self._step(-1),
            "step s forward one voxel": lambda: self._step(+1),
            "add a keyframe here": model.add_keyframe,
            "delete the keyframe": model.delete_keyframe,
            "tilt about u +1 degree": lambda: model.tilt(_STEP, axis="u"),
            "tilt about u -1 degree": lambda: model.tilt(-_STEP, axis="u"),
            "tilt about v +1 degree": lambda: model.tilt(_STEP, axis="v"),
            "tilt about v -1 degree": lambda: model.tilt(-_STEP, axis="v"),
            "twist +1 degree (counter-clockwise)": lambda: model.twist(_STEP),
            "twist -1 degree": lambda: model.twist(-_STEP),
            "fit the cross-section in the view": self.editor.fit,
            "cancel the drag": self.editor.cancel_drag,
        }
        self._shown: tuple[Any, float, int | None] | None = None
        self._folds: tuple[Any, list[tuple[float, float]]] = (None, [])
        self._slow = QTimer(self)
        self._slow.setSingleShot(True)
        self._slow.setInterval(0)
        self._slow.timeout.connect(self._update_slow)
        self._build()
        self._shortcuts = []
        for key, action in self.SHORTCUTS:
            if action in self._actions:
                sc = QShortcut(QKeySequence(key), self)
                sc.setContext(Qt.ShortcutContext.WidgetWithChildrenShortcut)
                sc.activated.connect(lambda a=action: self.act(a))
                self._shortcuts.append(sc)
        model.deformation_changed.connect(self._on_deformation)
        model.position_changed.connect(self._on_position)
        model.history_changed.connect(self._on_history)
        self.preview.status.connect(self._on_preview_status)
        self.destroyed.connect(lambda *_: self._disconnect(model))
        self.refresh()

    # --------------------------------------------------------------------------------------------------------------
    # layout
    # --------------------------------------------------------------------------------------------------------------
    def _button(self, text: str, action: str, tip: str | None = None) -> QPushButton:
        b = QPushButton(text)
        key = next((k for k, a in self.SHORTCUTS if a == action), None)
        b.setToolTip(f"{tip or action}" + (f" ({key})" if key else ""))
        b.clicked.connect(lambda *_: self.act(action))
        return b

    def _build(self) -> None:
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        self.hint = QLabel("Run the skeleton step or open a session: the editor needs a deformation.")
        self.hint.setWordWrap(True)
        lay.addWidget(self.hint)
        native = self.editor.native
        native.setMinimumSize(240, 240)
        native.setFocusPolicy(Qt.FocusPolicy.StrongFocus)
        native.setToolTip("drag the centre or inside the cage: move; an edge or corner: resize; an axis handle or "
                          "Shift-drag: twist; elsewhere: pan; wheel: zoom")
        lay.addWidget(native, 1)
        self.strip = SStrip()
        self.strip.s_requested.connect(lambda s: self._call(lambda: self.model.set_s(s)))
        lay.addWidget(self.strip)
        self.position_label = QLabel("")
        self.position_label.setWordWrap(True)  # "s = ... , keyframe k of n; folds at ..." must not widen the dock
        lay.addWidget(self.position_label)

        # napari's dock starts ~400 px wide (a 365 px viewport once the step scrolls vertically): the controls go
        # in rows of at most ~300 px (issue 21), never in one long row that needs a horizontal scroll bar
        nav = QGridLayout()
        self.prev_button = self._button("< keyframe", "previous keyframe")
        self.next_button = self._button("keyframe >", "next keyframe")
        self.add_button = self._button("add here", "add a keyframe here")
        self.delete_button = self._button("delete", "delete the keyframe")
        for i, b in enumerate((self.prev_button, self.next_button, self.add_button, self.delete_button)):
            nav.addWidget(b, i // 2, i % 2)
        lay.addLayout(nav)

        grid = QGridLayout()
        self.tilt_buttons = {}
        for col, (text, action) in enumerate((("tilt u -", "tilt about u -1 degree"),
                                              ("tilt u +", "tilt about u +1 degree"),
                                              ("tilt v -", "tilt about v -1 degree"),
                                              ("tilt v +", "tilt about v +1 degree"))):
            self.tilt_buttons[action] = b = self._button(text, action)
            grid.addWidget(b, 0, col)
        self.twist_minus = self._button("twist -1", "twist -1 degree")
        self.twist_plus = self._button("twist +1", "twist +1 degree (counter-clockwise)")
        self.undo_button = self._button("undo", "undo")
        self.redo_button = self._button("redo", "redo")
        for col, b in enumerate((self.twist_minus, self.twist_plus, self.undo_button, self.redo_button)):
            grid.addWidget(b, 1, col)
        lay.addLayout(grid)

        pad = QGridLayout()  # one row each: "pad head [box]", "pad tail [box]" (side by side they need ~450 px)
        self.pad_head = QDoubleSpinBox()
        self.pad_tail = QDoubleSpinBox()
        for row, (box, end) in enumerate(((self.pad_head, "head"), (self.pad_tail, "tail"))):
            box.setRange(0.0, 1e6)
            box.setDecimals(2)
            box.setKeyboardTracking(False)
            box.setToolTip(f"extra length of the straight box beyond the {end} (physical units)")
            box.valueChanged.connect(self._on_pad)
            pad.addWidget(QLabel(f"pad {end}"), row, 0)
            pad.addWidget(box, row, 1)
        pad.setColumnStretch(2, 1)  # the boxes keep their own width
        lay.addLayout(pad)
        self.preview_check = QCheckBox("straight preview")
        self.preview_check.setChecked(True)
        self.preview_check.setToolTip("recompute the straight preview layer after every edit (coarse level)")
        self.preview_check.toggled.connect(self._on_preview_toggled)
        lay.addWidget(self.preview_check)

        self.live_check = QCheckBox("live 3D straight view (GPU)")
        self.live_check.setToolTip("draw the straight fish in the 3D view with the GLSL shader, from the scan's own "
                                   "texture: an edit re-uploads only the frame table (falls back to the CPU preview "
                                   "where GL lacks what it needs)")
        self.live_check.toggled.connect(self._on_live_toggled)
        lay.addWidget(self.live_check)
        live = QHBoxLayout()  # under the live view's box: its "bent" box and "finer level here"
        self.bent_check = QCheckBox("bent")
        self.bent_check.setToolTip("show the scan bent (as scanned) in the same layer and texture; off: straight")
        self.bent_check.setEnabled(False)
        self.bent_check.toggled.connect(lambda on: self.live is not None and self.live.set_straight(not on))
        live.addWidget(self.bent_check)
        self.finer_button = QPushButton("finer level here")
        self.finer_button.setToolTip("upload the finest pyramid level the memory budget allows, cropped around the "
                                     "specimen")
        self.finer_button.setEnabled(False)
        self.finer_button.clicked.connect(self._on_finer)
        live.addWidget(self.finer_button)
        live.addStretch(1)
        lay.addLayout(live)
        self.live_label = QLabel("")
        self.live_label.setWordWrap(True)
        self.live_label.setMinimumWidth(1)  # a path in it has no break: cut, never widen the dock
        lay.addWidget(self.live_label)
        self.live: Any = None

        self.status = QLabel("")
        self.status.setWordWrap(True)
        self.status.setMinimumWidth(1)  # a path in it has no break: cut, never widen the dock
        self.status.setStyleSheet("color: #ff8080")
        lay.addWidget(self.status)

    # --------------------------------------------------------------------------------------------------------------
    # actions
    # --------------------------------------------------------------------------------------------------------------
    def act(self, action: str) -> None:
        """Run a named action (a button, a shortcut); a refused edit shows its message instead of raising."""
        self._call(self._actions[action])

    def _call(self, fn: Callable[[], Any]) -> None:
        if self.model.deformation is None:
            self.status.setText("there is no deformation to edit yet: run the skeleton step or open a session")
            return
        try:
            fn()
        except UnwindError as e:
            self.status.setText(str(e))
        else:
            self.status.setText("")

    def _step(self, sign: int) -> None:
        d = self.model.deformation
        if d is not None:
            self.model.set_s(self.model.s + sign * float(min(d.spacing)))

    def _on_pad(self, *_: Any) -> None:
        d = self.model.deformation
        if d is None:
            return
        before, after = self.pad_head.value(), self.pad_tail.value()
        if (before, after) != tuple(round(p, 2) for p in d.pad):
            self._call(lambda: self.model.set_pad(before, after))

    def _on_live_toggled(self, on: bool) -> None:
        """Start or stop the GPU straight view (issue 12); it needs the 3D display."""
        if not on:
            if self.live is not None:
                self.live.close()
            self.live = None
            self.live_label.setText("")
            self.bent_check.setEnabled(False)
            self.finer_button.setEnabled(False)
            return
        scan = self._scan()
        if scan is None or self.model.deformation is None:
            self.live_label.setText("the live straight view needs a scan and a deformation (skeleton or session)")
            self.live_check.blockSignals(True)
            self.live_check.setChecked(False)
            self.live_check.blockSignals(False)
            return
        try:
            from ._straight_view import StraightView  # checks napari's version (private API pinned)

            self.viewer.dims.ndisplay = 3
            self.live = StraightView(self.viewer, scan)
            self.live.status.connect(lambda text: self.live_label.setText(text))
            self.live.request(self.model.deformation)
        except (ImportError, RuntimeError, UnwindError) as exc:  # another napari, a GL without a volume node, ...
            if self.live is not None:
                self.live.close()
            self.live = None
            self.live_label.setText(f"the live straight view is not available: {exc}; the straight preview is used")
            self.live_check.blockSignals(True)
            self.live_check.setChecked(False)
            self.live_check.blockSignals(False)
            return
        self.live_label.setText(self.live.level_text)
        self.bent_check.setEnabled(self.live.available)
        self.finer_button.setEnabled(self.live.available)

    def _on_finer(self) -> None:
        if self.live is not None and self.live.available:
            self.live.focus()
            self.live_label.setText(self.live.level_text)

    def _on_preview_toggled(self, on: bool) -> None:
        self.preview.enabled = bool(on)
        if on:
            self.preview.request(self.model.deformation)

    # --------------------------------------------------------------------------------------------------------------
    # model -> views
    # --------------------------------------------------------------------------------------------------------------
    def refresh(self) -> None:
        """Redraw everything from the model and the scan (after the dock changed the scan)."""
        self.editor.clim = None
        self.editor.redraw(force=True)
        self._shown = None
        self._on_deformation()

    def _on_deformation(self, *_: Any) -> None:
        d = self.model.deformation
        self.hint.setVisible(d is None)
        if d is not None:
            for box, value in ((self.pad_head, d.pad[0]), (self.pad_tail, d.pad[1])):
                box.blockSignals(True)
                box.setValue(value)
                box.blockSignals(False)
        self._on_position()
        self._on_history(self.model.can_undo, self.model.can_redo)
        self.preview.request(d)
        if self.live is not None:
            self.live.request(d)

    def _on_position(self, *_: Any) -> None:
        d, m = self.model.deformation, self.model
        if d is None:
            self._slow.stop()
            self.strip.set_state(0.0, 0.0, [], [], None)
            self.position_label.setText("")
            self.overlays.update(None)
            self._shown = None
            return
        key = (d, m.s, m.keyframe)
        if self._shown is not None and self._shown[0] is d and self._shown[1:] == key[1:]:
            return  # a gesture update sends both events: draw once
        self._shown = key
        folds = self._folds[1] if self._folds[0] is d else self.strip.folds
        self.strip.set_state(d.length, m.s, d.knots, folds, m.keyframe)
        self._label(d, folds)
        self.delete_button.setEnabled(m.keyframe is not None and len(d) > 2)
        self.add_button.setEnabled(m.keyframe is None)
        self._slow.start()  # the folds and the wireframes once the event loop is free (a drag's updates coalesce)

    @property
    def pending(self) -> bool:
        """True while the folds and the bent-view wireframes wait for the event loop (a new layer, to be shown)."""
        from . import _reveal

        return self._slow.isActive() or _reveal.pending()

    def _update_slow(self, queued: bool = False) -> None:
        from . import _private, _reveal

        d, m = self.model.deformation, self.model
        if d is None or _private.viewer_closed(self.viewer):
            return
        if self._folds[0] is not d:
            self._folds = (d, m.folds())
            self.strip.set_state(d.length, m.s, d.knots, self._folds[1], m.keyframe)
            self._label(d, self._folds[1])
        if not queued and self.overlays.missing():
            # a new wireframe layer costs napari ~50 ms: it waits its turn behind the other new layers' steps
            _reveal.later(lambda: self._update_slow(queued=True), self)
            return
        if not self.overlays.update(d, m.s, m.keyframe, new_layers=1):
            self._slow.start()  # one new wireframe layer per turn of the event loop

    def _label(self, d: Any, folds: list[tuple[float, float]]) -> None:
        m = self.model
        where = f"keyframe {m.keyframe + 1} of {len(d)}" if m.keyframe is not None else "between keyframes"
        text = f"; folds at {len(folds)} place(s), in red" if folds else ""
        self.position_label.setText(f"s = {m.s:.4g} of {d.length:.4g} {unit_label(d.unit)}, {where}{text}")

    def _on_history(self, can_undo: bool, can_redo: bool) -> None:
        self.undo_button.setEnabled(bool(can_undo))
        self.redo_button.setEnabled(bool(can_redo))

    def _on_preview_status(self, message: str) -> None:
        if message:
            self.status.setText(message)

    def _disconnect(self, model: EditModel) -> None:
        from . import _reveal

        _reveal.cancel(self)  # a queued wireframe update of a panel that is gone
        self.preview.close()
        if self.live is not None:
            self.live.close()
        self.editor.release()  # the Qt widgets are gone already
        for sig, slot in ((model.deformation_changed, self._on_deformation),
                          (model.position_changed, self._on_position),
                          (model.history_changed, self._on_history)):
            try:
                sig.disconnect(slot)
            except Exception:  # noqa: BLE001 (already gone with the widget)
                pass
