"""The layered 2D cross-section editor: the scan on the plane of the frame at s, with the cage, the centre and the
u/v axes drawn over it, in a vispy SceneCanvas that the Refine panel embeds (``EditorCanvas.native``).

Coordinates
    The view's scene coordinates are the plane's straight coordinates ``(x, y)`` (physical units, relative to the
    curve point at s): x along u to the right, y along v up (a PanZoomCamera with y up). The image is placed with
    the CrossSection's geometry (``to_plane`` of its pixel corners), so the cage and the axes are drawn in the same
    units as the model's bounds.
Drags (each one gesture of the model: the amounts are totals since the press, undone in one step)
    - the centre, or inside the cage: ``model.move(dx, dy)``;
    - a cage edge or corner: ``model.set_cage`` with the dragged sides;
    - an axis handle, or anywhere with Shift: ``model.twist(angle)``, the angle of the drag about the centre;
    - elsewhere: pan (and the wheel zooms), as vispy's PanZoomCamera does.
    While a move or twist is dragged, the drawing is shifted or turned by the dragged amount so that the image stays
    still under the mouse and the cage follows it; at the release the view re-centres on the new frame (a move
    pans the camera by the same amount, so nothing jumps).
"""

from __future__ import annotations

import contextlib
import itertools
import math
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import dask.array as da
import numpy as np
from vispy import scene
from vispy.gloo.context import forget_canvas
from vispy.visuals.transforms import MatrixTransform, STTransform

from ..editing import CrossSection, EditModel, cross_section
from ..errors import UnwindError
from ..io import Volume

__all__ = ["EditorCanvas", "CAGE_COLOR"]

#: The cage box's colour (no grey: the image is grey, so a render shows the box apart from it).
CAGE_COLOR = (1.0, 0.75, 0.0, 1.0)
U_COLOR = (1.0, 0.25, 0.25, 1.0)
V_COLOR = (0.3, 1.0, 0.3, 1.0)
CENTRE_COLOR = (0.3, 0.7, 1.0, 1.0)
#: How near (canvas pixels) the mouse must be to grab a handle, an edge or the centre.
GRAB = 8.0


class _ChunkCache:
    """A dask array read chunk by chunk on the calling thread, the chunks kept (least recently used dropped past
    ``max_bytes``). The editor reads one small box per edit, mostly in the chunks of the last one: building and
    running a dask graph for it cost ~11 of the 19 ms of an edit on a 256^3 scan; from the cache it costs < 1 ms."""

    def __init__(self, data: da.Array, max_bytes: int = 256 * 2**20) -> None:
        self.data = data
        self.shape = data.shape
        self.dtype = data.dtype
        self.max_bytes = max_bytes
        self._edges = [np.cumsum((0, *c)) for c in data.chunks]
        self._blocks: OrderedDict[tuple[int, ...], np.ndarray] = OrderedDict()
        self._bytes = 0

    def _block(self, idx: tuple[int, ...]) -> np.ndarray:
        b = self._blocks.get(idx)
        if b is not None:
            self._blocks.move_to_end(idx)
            return b
        b = np.asarray(self.data.blocks[idx].compute(scheduler="synchronous"))
        self._blocks[idx] = b
        self._bytes += b.nbytes
        while self._bytes > self.max_bytes and len(self._blocks) > 1:
            self._bytes -= self._blocks.popitem(last=False)[1].nbytes
        return b

    def __getitem__(self, index: tuple[slice, ...]) -> np.ndarray:
        lo = [int(sl.start) for sl in index]
        hi = [int(sl.stop) for sl in index]
        out = np.empty([b - a for a, b in zip(lo, hi, strict=True)], dtype=self.dtype)
        ranges = [range(int(np.searchsorted(e, a, "right")) - 1, int(np.searchsorted(e, b - 1, "right")))
                  for e, a, b in zip(self._edges, lo, hi, strict=True)]
        for idx in itertools.product(*ranges):
            c0 = [int(e[i]) for e, i in zip(self._edges, idx, strict=True)]
            block = self._block(idx)
            a = [max(x, c) for x, c in zip(lo, c0, strict=True)]
            b = [min(x, c + n) for x, c, n in zip(hi, c0, block.shape, strict=True)]
            out[tuple(slice(x - y, z - y) for x, y, z in zip(a, lo, b, strict=True))] = \
                block[tuple(slice(x - c, z - c) for x, c, z in zip(a, c0, b, strict=True))]
        return out


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class EditorCanvas:
    """The 2D editor canvas over an :class:`~napari_unwind.editing.EditModel`.

    Parameters
    ----------
    model : EditModel
        The editing model; every drag becomes model calls, and every model event redraws.
    scan : callable
        Returns the scan (a Volume or an array on the deformation's voxel grid), or None when there is none.
    size : (int, int)
        Initial canvas size in pixels.
    """

    def __init__(self, model: EditModel, scan: Callable[[], Any], *, size: tuple[int, int] = (420, 420)) -> None:
        self.model = model
        self._scan = scan
        self.canvas = scene.SceneCanvas(keys=None, size=size, bgcolor="black", show=False)
        self.view = self.canvas.central_widget.add_view(border_width=0)
        self.view.camera = scene.PanZoomCamera(aspect=1)
        # everything drawn lives under one node: its transform shows a move or twist while it is dragged
        self.root = scene.Node(parent=self.view.scene)
        self.root.transform = MatrixTransform()
        self.image = scene.visuals.Image(np.zeros((2, 2), np.float32), parent=self.root, cmap="grays",
                                         interpolation="linear", clim=(0.0, 1.0))
        self.image.transform = STTransform()
        self.box = scene.visuals.Line(np.zeros((5, 2)), color=CAGE_COLOR, width=2, method="gl", parent=self.root)
        self.axes = scene.visuals.Line(np.zeros((4, 2)), color=np.array([U_COLOR, U_COLOR, V_COLOR, V_COLOR]),
                                       connect="segments", width=2, method="gl", parent=self.root)
        self.handles = scene.visuals.Markers(parent=self.root)
        self.centre = scene.visuals.Markers(parent=self.root)
        for v in (self.box, self.axes, self.handles, self.centre):
            v.order = 1  # over the image, whatever the depth
            v.set_gl_state("translucent", depth_test=False)
        self.cross: CrossSection | None = None
        self.clim: tuple[float, float] | None = None
        self.update_seconds: float = 0.0
        self._drawn: tuple[Any, float] | None = None
        self._drag: dict[str, Any] | None = None
        self._fitted = False
        self._last_scan: Any = None
        self._reader: _ChunkCache | None = None
        self.canvas.events.mouse_press.connect(self._on_press)
        self.canvas.events.mouse_move.connect(self._on_move)
        self.canvas.events.mouse_release.connect(self._on_release)
        model.deformation_changed.connect(self._on_deformation)
        model.position_changed.connect(self._on_position)
        self.redraw()

    def close(self) -> None:
        """Close the canvas (its widget still alive) and :meth:`release` it."""
        self.canvas.close()
        self.release()

    def release(self) -> None:
        """Stop listening to the model and drop the canvas from vispy's list, without touching Qt (for when the
        widget is already gone). vispy keeps a list of canvases and napari takes the newest for its GL queries
        (``get_gl_extensions`` when the first Image layer is added): a canvas left there whose widget is gone makes
        those queries fail."""
        for sig, slot in ((self.model.deformation_changed, self._on_deformation),
                          (self.model.position_changed, self._on_position)):
            with contextlib.suppress(Exception):
                sig.disconnect(slot)
        forget_canvas(self.canvas)

    # --------------------------------------------------------------------------------------------------------------
    # geometry
    # --------------------------------------------------------------------------------------------------------------
    @property
    def native(self) -> Any:
        """The Qt widget to embed."""
        return self.canvas.native

    def scene_at(self, pos: Any) -> np.ndarray:
        """Canvas pixel position -> the view's scene coordinates (the plane's x, y outside a drag)."""
        tr = self.canvas.scene.node_transform(self.view.scene)
        return np.asarray(tr.map(np.asarray(pos, dtype=float)[:2]))[:2]

    def canvas_at(self, xy: Any) -> np.ndarray:
        """Scene coordinates -> canvas pixel position."""
        tr = self.view.scene.node_transform(self.canvas.scene)
        return np.asarray(tr.map(np.asarray(xy, dtype=float)[:2]))[:2]

    def _units_per_pixel(self) -> float:
        return float(np.linalg.norm(self.scene_at((1.0, 0.0)) - self.scene_at((0.0, 0.0))))

    def _arm(self) -> float:
        """Length of the drawn u and v axes: half the cage's smaller half-size."""
        assert self.cross is not None
        x_lo, x_hi, y_lo, y_hi = self.cross.bounds
        return 0.5 * min(x_hi - x_lo, y_hi - y_lo) / 2

    def fit(self) -> None:
        """Frame the whole cross-section."""
        if self.cross is None:
            return
        c = self.cross
        h, w = c.image.shape
        x, y = c.to_plane(-0.5, -0.5)
        self.view.camera.set_range(x=(float(x), float(x) + w * c.pixel), y=(float(y), float(y) + h * c.pixel),
                                   margin=0.0)
        self._fitted = True

    # --------------------------------------------------------------------------------------------------------------
    # drawing
    # --------------------------------------------------------------------------------------------------------------
    def _on_deformation(self, _d: Any = None) -> None:
        m = self.model
        if not m.in_gesture and not m.can_undo and not m.can_redo:
            self._fitted = False  # a new deformation (a skeleton, a session): frame it
        self.redraw()

    def _on_position(self, *_: Any) -> None:
        self.redraw()

    def redraw(self, *, force: bool = False) -> None:
        """Resample the plane at the model's s and redraw; nothing when neither s nor the deformation changed."""
        d, scan = self.model.deformation, self._scan()
        visible = d is not None and scan is not None
        for v in (self.image, self.box, self.axes, self.handles, self.centre):
            v.visible = visible
        if not visible:
            self.cross, self._drawn = None, None
            self.canvas.update()
            return
        if scan is not self._last_scan:  # another scan: its own contrast, framed anew
            self._last_scan, self.clim, self._fitted = scan, None, False
        key = (d, self.model.s)
        if self._drawn is not None and self._drawn[0] is d and self._drawn[1] == key[1] and not force:
            return
        t0 = time.perf_counter()
        data = scan.data if isinstance(scan, Volume) else scan
        if isinstance(data, da.Array):
            if self._reader is None or self._reader.data is not data:
                self._reader = _ChunkCache(data)
            data = self._reader
        try:
            c = cross_section(data, d, self.model.s)
        except UnwindError:
            self.cross, self._drawn = None, None
            for v in (self.image, self.box, self.axes, self.handles, self.centre):
                v.visible = False
            self.canvas.update()
            return
        self.cross, self._drawn = c, key
        if self.clim is None:
            lo, hi = (float(q) for q in np.percentile(c.image, (1.0, 99.5)))
            self.clim = (lo, hi if hi > lo else lo + 1.0)
        self.image.set_data(c.image)
        self.image.clim = self.clim
        x, y = c.to_plane(-0.5, -0.5)
        self.image.transform.scale = (c.pixel, c.pixel, 1.0)
        self.image.transform.translate = (float(x), float(y), 0.0)
        x_lo, x_hi, y_lo, y_hi = c.bounds
        self.box.set_data(np.array([[x_lo, y_lo], [x_hi, y_lo], [x_hi, y_hi], [x_lo, y_hi], [x_lo, y_lo]]))
        arm = self._arm()
        self.axes.set_data(np.array([[0.0, 0.0], [arm, 0.0], [0.0, 0.0], [0.0, arm]]))
        self.handles.set_data(np.array([[arm, 0.0], [0.0, arm]]), symbol="square", size=11,
                              face_color=np.array([U_COLOR, V_COLOR]), edge_color="white", edge_width=1)
        self.centre.set_data(np.array([[0.0, 0.0]]), symbol="disc", size=11, face_color=CENTRE_COLOR,
                             edge_color="white", edge_width=1)
        if not self._fitted:
            self.fit()
        self.canvas.update()
        self.update_seconds = time.perf_counter() - t0

    # --------------------------------------------------------------------------------------------------------------
    # mouse
    # --------------------------------------------------------------------------------------------------------------
    def hit(self, xy: Any, *, shift: bool = False) -> tuple[str, Any] | None:
        """What a press at scene point ``xy`` grabs: ("twist", axis), ("resize", sides), ("move", None) or None."""
        if self.cross is None:
            return None
        if shift:
            return ("twist", None)
        x, y = (float(v) for v in xy)
        tol = GRAB * self._units_per_pixel()
        arm = self._arm()
        if math.hypot(x - arm, y) <= tol:
            return ("twist", "u")
        if math.hypot(x, y - arm) <= tol:
            return ("twist", "v")
        if math.hypot(x, y) <= tol:
            return ("move", None)
        x_lo, x_hi, y_lo, y_hi = self.cross.bounds
        in_x = x_lo - tol <= x <= x_hi + tol
        in_y = y_lo - tol <= y <= y_hi + tol
        sides = []
        if in_y and abs(x - x_lo) <= tol:
            sides.append(0)
        elif in_y and abs(x - x_hi) <= tol:
            sides.append(1)
        if in_x and abs(y - y_lo) <= tol:
            sides.append(2)
        elif in_x and abs(y - y_hi) <= tol:
            sides.append(3)
        if sides:
            return ("resize", tuple(sides))
        if x_lo < x < x_hi and y_lo < y < y_hi:
            return ("move", None)
        return None

    def _on_press(self, event: Any) -> None:
        if event.button != 1 or self._drag is not None or self.model.deformation is None:
            return
        xy = self.scene_at(event.pos)
        what = self.hit(xy, shift="Shift" in {getattr(k, "name", k) for k in event.modifiers})
        if what is None:
            return
        self.view.camera.interactive = False
        assert self.cross is not None
        self._drag = {"kind": what[0], "detail": what[1], "press": xy, "bounds": self.cross.bounds,
                      "angle": math.atan2(xy[1], xy[0]), "turn": 0.0, "last": math.atan2(xy[1], xy[0])}
        self.model.begin_gesture({"move": "move", "twist": "twist", "resize": "resize"}[what[0]])

    def _on_move(self, event: Any) -> None:
        if self._drag is None:
            return
        self._apply(self.scene_at(event.pos))

    def _on_release(self, event: Any) -> None:
        if self._drag is None:
            return
        try:
            self._apply(self.scene_at(event.pos))
        finally:
            self._finish(commit=True)

    def cancel_drag(self) -> None:
        """Abandon the drag in progress (Escape): the model returns to the state before the press."""
        if self._drag is not None:
            self._finish(commit=False)

    def _finish(self, *, commit: bool) -> None:
        drag, self._drag = self._drag, None
        self.view.camera.interactive = True
        self.root.transform.reset()
        if commit:
            if drag and drag["kind"] == "move" and "offset" in drag:
                # the view re-centres on the moved keyframe: pan by the same amount so nothing jumps
                dx, dy = drag["offset"]
                r = self.view.camera.rect
                self.view.camera.rect = (r.left - dx, r.bottom - dy, r.width, r.height)
            self.model.end_gesture()
        else:
            self.model.cancel_gesture()
        self.redraw(force=True)

    def _apply(self, xy: np.ndarray) -> None:
        drag = self._drag
        assert drag is not None
        kind = drag["kind"]
        tr = MatrixTransform()
        if kind == "move":
            dx, dy = (float(v) for v in xy - drag["press"])
            drag["offset"] = (dx, dy)
            self.model.move(dx, dy)
            tr.translate((dx, dy, 0.0))
        elif kind == "twist":
            a = math.atan2(xy[1], xy[0])
            drag["turn"] += _wrap(a - drag["last"])
            drag["last"] = a
            self.model.twist(drag["turn"])
            tr.rotate(math.degrees(drag["turn"]), (0, 0, 1))
        else:
            b = list(drag["bounds"])
            delta = xy - drag["press"]
            min_side = 2 * (self.cross.pixel if self.cross is not None else 1.0)
            for side in drag["detail"]:
                b[side] += float(delta[0] if side < 2 else delta[1])
            # a side never crosses its opposite: keep at least two pixels between them
            for lo, hi in ((0, 1), (2, 3)):
                if b[hi] - b[lo] < min_side:
                    if lo in drag["detail"]:
                        b[lo] = b[hi] - min_side
                    else:
                        b[hi] = b[lo] + min_side
            self.model.set_cage(b)
        self.root.transform = tr
