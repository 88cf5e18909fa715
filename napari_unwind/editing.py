"""The editing state of the interactive tool: a Qt-free model with undo/redo and events.

The plugin's dock and its 2D cross-section editor only translate mouse and keys into calls of :class:`EditModel`
(as napari-animation keeps its ``Animation`` apart from its widget); everything they show is read back from it.
It imports neither napari nor Qt, so it is tested without a viewer, and a script can drive it the same way.

State
    ``deformation`` (an immutable :class:`~napari_unwind.deformation.Deformation`), the current arclength ``s``
    and the selected keyframe (``keyframe``: its index when ``s`` sits on one, else None).
Edits
    Each edit is one undoable step that replaces the deformation by a new one (the Deformation's own edit methods do
    the geometry) and emits :attr:`EditModel.deformation_changed` once. An edit acts on the selected keyframe; when
    ``s`` lies between keyframes, the edit first adds a keyframe at ``s`` (in the same undo step) and selects it.
Gestures
    A drag sends many updates and must undo in one step. Between :meth:`EditModel.begin_gesture` and
    :meth:`EditModel.end_gesture`, each edit is applied to the deformation as it was when the gesture began (so the
    amounts are totals since the press, not increments: no drift), every update is emitted (live feedback), and the
    whole gesture is one undo step (``with model.gesture("move"): ...`` does both).
Undo
    ``undo`` and ``redo`` restore the exact objects that were current before and after a step, so undoing gives back
    the deformation bit for bit. A new edit after an undo drops the redo branch.

:func:`cross_section` samples a scan on the plane of the frame at ``s``: the image the 2D editor shows.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from psygnal import Signal
from scipy import ndimage

from .deformation import Deformation
from .errors import InvalidInputError, finite_number

__all__ = ["EditModel", "Step", "CrossSection", "cross_section"]

#: A keyframe is "at s" when closer than this fraction of the curve's length (the slider's resolution is coarser).
_AT_KNOT = 1e-6


@dataclass(frozen=True)
class Step:
    """One undoable step: the states before and after it (deformation, s, keyframe)."""

    label: str
    before: Deformation
    after: Deformation
    s_before: float
    s_after: float


class EditModel:
    """The deformation being edited, the position along it, and the undo/redo history.

    Parameters
    ----------
    deformation : Deformation, optional
        The deformation to edit (None: nothing yet; :meth:`set_deformation` gives one later).
    max_history : int
        Undo steps kept (the oldest are dropped beyond it).

    Signals
    -------
    deformation_changed(Deformation)
        Once per edit, undo, redo, gesture update and :meth:`set_deformation`.
    position_changed(float, object)
        ``(s, keyframe)`` when the position or the selected keyframe changes.
    history_changed(bool, bool)
        ``(can_undo, can_redo)`` after any change of the history.
    """

    deformation_changed = Signal(object)
    position_changed = Signal(float, object)
    history_changed = Signal(bool, bool)

    def __init__(self, deformation: Deformation | None = None, *, max_history: int = 10_000) -> None:
        if isinstance(max_history, bool) or not isinstance(max_history, int) or max_history < 1:
            raise InvalidInputError(f"max_history must be a whole number >= 1, got {max_history!r}")
        if deformation is not None and not isinstance(deformation, Deformation):
            raise InvalidInputError(f"deformation must be a Deformation, got {type(deformation).__name__}")
        self._d = deformation
        self._s = 0.0
        self._undo: list[Step] = []
        self._redo: list[Step] = []
        self._max = max_history
        self._gesture: tuple[str, Deformation, float, Deformation, float] | None = None
        self._gesture_steps = 0

    # --------------------------------------------------------------------------------------------------------------
    # state
    # --------------------------------------------------------------------------------------------------------------
    @property
    def deformation(self) -> Deformation | None:
        return self._d

    @property
    def s(self) -> float:
        """The current arclength, physical units, in ``[0, L]``."""
        return self._s

    @property
    def keyframe(self) -> int | None:
        """Index of the keyframe at ``s``, or None when ``s`` lies between keyframes."""
        if self._d is None:
            return None
        knots = self._d.knots
        i = int(np.argmin(np.abs(knots - self._s)))
        return i if abs(knots[i] - self._s) <= _AT_KNOT * max(1.0, self._d.length) else None

    @property
    def can_undo(self) -> bool:
        return bool(self._undo)

    @property
    def can_redo(self) -> bool:
        return bool(self._redo)

    @property
    def history(self) -> tuple[Step, ...]:
        """The undo steps, oldest first."""
        return tuple(self._undo)

    def folds(self) -> list[tuple[float, float]]:
        """The s-intervals where the current deformation folds (for the slider's red marks)."""
        return [] if self._d is None else self._d.folds()

    def _need(self) -> Deformation:
        if self._d is None:
            raise InvalidInputError("there is no deformation to edit yet: run the skeleton step or open a session")
        return self._d

    # --------------------------------------------------------------------------------------------------------------
    # position (not undoable: moving along the curve changes nothing)
    # --------------------------------------------------------------------------------------------------------------
    def set_s(self, s: float) -> None:
        """Move to arclength ``s`` (clamped to ``[0, L]``)."""
        d = self._need()
        s = float(s)
        if not math.isfinite(s):
            raise InvalidInputError(f"s must be a finite number, got {s!r}")
        s = min(max(s, 0.0), d.length)
        if s != self._s:
            self._s = s
            self.position_changed.emit(self._s, self.keyframe)

    def select_keyframe(self, i: int) -> None:
        """Move to keyframe ``i`` (negative counts from the end)."""
        d = self._need()
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -len(d) <= int(i) < len(d):
            raise InvalidInputError(f"keyframe index must be a whole number in [{-len(d)}, {len(d) - 1}], got {i!r}")
        self.set_s(float(d.knots[int(i) % len(d)]))

    def next_keyframe(self) -> None:
        """Move to the first keyframe after ``s`` (stays at the last)."""
        d = self._need()
        eps = _AT_KNOT * max(1.0, d.length)
        after = np.flatnonzero(d.knots > self._s + eps)
        self.select_keyframe(int(after[0]) if len(after) else len(d) - 1)

    def previous_keyframe(self) -> None:
        """Move to the last keyframe before ``s`` (stays at the first)."""
        d = self._need()
        eps = _AT_KNOT * max(1.0, d.length)
        before = np.flatnonzero(d.knots < self._s - eps)
        self.select_keyframe(int(before[-1]) if len(before) else 0)

    # --------------------------------------------------------------------------------------------------------------
    # history
    # --------------------------------------------------------------------------------------------------------------
    def set_deformation(self, deformation: Deformation, *, s: float | None = None, keep_history: bool = False) -> None:
        """Replace the deformation (a new skeleton, an opened session). Clears the history unless ``keep_history``,
        in which case the replacement is itself an undoable step."""
        if not isinstance(deformation, Deformation):
            raise InvalidInputError(f"deformation must be a Deformation, got {type(deformation).__name__}")
        self._end_gesture_silently()
        new_s = min(max(float(self._s if s is None else s), 0.0), deformation.length)
        if keep_history and self._d is not None:
            self._push(Step("replace", self._d, deformation, self._s, new_s))
        else:
            self._undo.clear()
            self._redo.clear()
        self._d, self._s = deformation, new_s
        self.deformation_changed.emit(deformation)
        self.position_changed.emit(self._s, self.keyframe)
        self.history_changed.emit(self.can_undo, self.can_redo)

    def undo(self) -> bool:
        """Undo the last step; False when there is none."""
        self._end_gesture_silently()
        if not self._undo:
            return False
        step = self._undo.pop()
        self._redo.append(step)
        self._restore(step.before, step.s_before)
        return True

    def redo(self) -> bool:
        """Redo the last undone step; False when there is none."""
        self._end_gesture_silently()
        if not self._redo:
            return False
        step = self._redo.pop()
        self._undo.append(step)
        self._restore(step.after, step.s_after)
        return True

    def _restore(self, d: Deformation, s: float) -> None:
        self._d, self._s = d, s
        self.deformation_changed.emit(d)
        self.position_changed.emit(s, self.keyframe)
        self.history_changed.emit(self.can_undo, self.can_redo)

    def _push(self, step: Step) -> None:
        self._undo.append(step)
        if len(self._undo) > self._max:
            del self._undo[0]
        self._redo.clear()

    # --------------------------------------------------------------------------------------------------------------
    # gestures
    # --------------------------------------------------------------------------------------------------------------
    def begin_gesture(self, label: str = "drag") -> None:
        """Start a gesture: the following edits are totals from here, and undo in one step."""
        self._need()
        self._end_gesture_silently()
        self._gesture = (str(label), self._d, self._s, self._d, self._s)  # type: ignore[assignment]
        self._gesture_steps = 0

    def end_gesture(self) -> None:
        """End the gesture: one undo step if it changed anything."""
        if self._gesture is None:
            return
        label, before, s_before, _, _ = self._gesture
        self._gesture = None
        if self._gesture_steps and self._d is not before:
            self._push(Step(label, before, self._d, s_before, self._s))  # type: ignore[arg-type]
            self.history_changed.emit(self.can_undo, self.can_redo)

    def cancel_gesture(self) -> None:
        """Abandon the gesture: back to the state before it (Escape during a drag)."""
        if self._gesture is None:
            return
        _, before, s_before, _, _ = self._gesture
        self._gesture = None
        if self._d is not before:
            self._d, self._s = before, s_before
            self.deformation_changed.emit(before)
            self.position_changed.emit(s_before, self.keyframe)

    @contextlib.contextmanager
    def gesture(self, label: str = "drag") -> Iterator[None]:
        """``with model.gesture("move"): model.move(...); model.move(...)``: one undo step."""
        self.begin_gesture(label)
        try:
            yield
        finally:
            self.end_gesture()

    @property
    def in_gesture(self) -> bool:
        return self._gesture is not None

    def _end_gesture_silently(self) -> None:
        if self._gesture is not None:
            self.end_gesture()

    # --------------------------------------------------------------------------------------------------------------
    # edits
    # --------------------------------------------------------------------------------------------------------------
    def _edit(self, label: str, fn: Callable[[Deformation, int], Deformation]) -> Deformation:
        """Apply ``fn(deformation, keyframe_index)`` as one step (or one gesture update)."""
        self._need()
        if self._gesture is not None:
            base, s0 = self._gesture[3], self._gesture[4]
        else:
            base, s0 = self._d, self._s
        assert base is not None
        i = self._index_in(base, s0)
        if i is None:
            base = base.add_keyframe(s0)
            i = base.index_at(s0)
            if self._gesture is not None:  # later updates of this gesture start from the added keyframe
                g = self._gesture
                self._gesture = (g[0], g[1], g[2], base, s0)
        new = fn(base, i)
        before, s_before = self._d, self._s
        self._d, self._s = new, float(new.knots[i])
        if self._gesture is not None:
            self._gesture_steps += 1
        else:
            self._push(Step(label, before, new, s_before, self._s))  # type: ignore[arg-type]
        self.deformation_changed.emit(new)
        if self._s != s_before:
            self.position_changed.emit(self._s, self.keyframe)
        if self._gesture is None:
            self.history_changed.emit(self.can_undo, self.can_redo)
        return new

    @staticmethod
    def _index_in(d: Deformation, s: float) -> int | None:
        knots = d.knots
        i = int(np.argmin(np.abs(knots - s)))
        return i if abs(knots[i] - s) <= _AT_KNOT * max(1.0, d.length) else None

    def move(self, dx: float, dy: float) -> Deformation:
        """Move the keyframe's centre by ``dx`` along u and ``dy`` along v (physical units)."""
        dx, dy = finite_number("dx", dx), finite_number("dy", dy)
        return self._edit("move", lambda d, i: d.move_keyframe(i, dx, dy))

    def twist(self, angle: float) -> Deformation:
        """Turn the keyframe's u and v about n by ``angle`` radians (counter-clockwise seen from the tail)."""
        angle = finite_number("angle", angle)
        return self._edit("twist", lambda d, i: d.twist_keyframe(i, angle))

    def tilt(self, angle: float, *, axis: str = "u") -> Deformation:
        """Tilt the keyframe's section about its ``u`` or ``v`` axis by ``angle`` radians."""
        angle = finite_number("angle", angle)
        if axis not in ("u", "v"):
            raise InvalidInputError(f"tilt axis must be 'u' or 'v', got {axis!r}")
        return self._edit(f"tilt about {axis}", lambda d, i: d.tilt_keyframe(i, angle, axis=axis))

    def set_cage(self, bounds: Sequence[float]) -> Deformation:
        """Set the keyframe's cage sides ``(x_lo, x_hi, y_lo, y_hi)`` in its section plane (physical units)."""
        b = np.asarray(bounds, dtype=float).reshape(-1)
        if b.shape != (4,) or not np.isfinite(b).all() or not (b[1] > b[0] and b[3] > b[2]):
            raise InvalidInputError(f"cage bounds must be 4 finite numbers (x_lo, x_hi, y_lo, y_hi) with x_lo < x_hi "
                                    f"and y_lo < y_hi, got {list(bounds)!r}")
        return self._edit("resize", lambda d, i: d.set_cage(i, b))

    def add_keyframe(self, s: float | None = None) -> Deformation:
        """Add a keyframe at ``s`` (default: the current position) and select it; the map does not change."""
        d = self._need()
        if s is not None:
            self.set_s(s)
        if self.keyframe is not None:
            raise InvalidInputError(f"there is a keyframe at s={self._s:.4g} already (keyframe {self.keyframe}); "
                                    "edit it, or move along the curve first")
        if not 0.0 < self._s < d.length:
            raise InvalidInputError(f"a keyframe can be added at 0 < s < {d.length:.4g}, got s={self._s:.4g}")
        return self._edit("add keyframe", lambda d, i: d)

    def delete_keyframe(self, i: int | None = None) -> Deformation:
        """Delete keyframe ``i`` (default: the selected one); at least two remain. ``s`` stays where it was."""
        d = self._need()
        if i is None:
            i = self.keyframe
            if i is None:
                raise InvalidInputError(f"no keyframe at s={self._s:.4g} to delete; go to one first (previous/next)")
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -len(d) <= int(i) < len(d):
            raise InvalidInputError(f"keyframe index must be a whole number in [{-len(d)}, {len(d) - 1}], got {i!r}")
        if len(d) <= 2:
            raise InvalidInputError("a deformation needs at least 2 keyframes: this one cannot lose another")
        self._end_gesture_silently()
        new = d.delete_keyframe(int(i))
        self._push(Step("delete keyframe", d, new, self._s, min(self._s, new.length)))
        self._d, self._s = new, min(self._s, new.length)
        self.deformation_changed.emit(new)
        self.position_changed.emit(self._s, self.keyframe)
        self.history_changed.emit(self.can_undo, self.can_redo)
        return new

    def set_pad(self, before: float, after: float) -> Deformation:
        """Set the padding of the straight box ahead of the head and past the tail (physical units, >= 0)."""
        d = self._need()
        before, after = finite_number("before", before), finite_number("after", after)
        if before < 0 or after < 0:
            raise InvalidInputError(f"padding must be >= 0 at both ends, got ({before:g}, {after:g})")
        self._end_gesture_silently()
        new = d.with_pad(before, after)
        self._push(Step("pad", d, new, self._s, self._s))
        self._d = new
        self.deformation_changed.emit(new)
        self.history_changed.emit(self.can_undo, self.can_redo)
        return new


# ------------------------------------------------------------------------------------------------------------------
# the cross-section at s
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CrossSection:
    """The scan on the plane of the frame at ``s``.

    Attributes
    ----------
    image : ndarray of float32, shape (H, W)
        Row i, column j is the straight point ``x = x0 + j * pixel``, ``y = y0 + i * pixel`` (rows along v, columns
        along u, as the straight volume's axis1 and axis2); 0 outside the scan.
    x0, y0 : float
        Straight coordinates of pixel (0, 0)'s centre, physical units (relative to the curve point at ``s``).
    pixel : float
        Pixel size, physical units.
    s : float
        The arclength.
    bounds : tuple of 4 float
        The cage at ``s``: ``(x_lo, x_hi, y_lo, y_hi)``.
    centre : ndarray, shape (3,)
        The curve point at ``s`` (physical).
    frame : ndarray, shape (3, 3)
        Rows u, v, n at ``s``.
    """

    image: np.ndarray
    x0: float
    y0: float
    pixel: float
    s: float
    bounds: tuple[float, float, float, float]
    centre: np.ndarray
    frame: np.ndarray

    def to_pixel(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        """Straight ``(x, y)`` -> fractional ``(column, row)``."""
        return (np.asarray(x, float) - self.x0) / self.pixel, (np.asarray(y, float) - self.y0) / self.pixel

    def to_plane(self, col: Any, row: Any) -> tuple[np.ndarray, np.ndarray]:
        """Fractional ``(column, row)`` -> straight ``(x, y)``."""
        return self.x0 + np.asarray(col, float) * self.pixel, self.y0 + np.asarray(row, float) * self.pixel


def cross_section(
    volume: Any,
    deformation: Deformation,
    s: float,
    *,
    half_size: float | Sequence[float] | None = None,
    pixel: float | None = None,
    order: int = 1,
) -> CrossSection:
    """Sample a scan on the plane of the deformation's frame at ``s``: the 2D editor's image.

    Parameters
    ----------
    volume : array_like, shape (N0, N1, N2)
        The scan on the deformation's voxel grid (``deformation.spacing`` and ``origin``): numpy, dask or zarr;
        only the box around the plane is read.
    deformation : Deformation
    s : float
        Arclength (physical units; padding allowed: ``s_range``).
    half_size : float or (2,) float, optional
        Half-width and half-height of the view, physical units. Default: 1.5 times the cage's largest reach
        (the whole deformation's), so the cage and what it leaves out are both seen.
    pixel : float, optional
        Pixel size, physical units. Default: the finest spacing, coarsened so the image is at most 512 pixels across.
    order : int
        Interpolation order (0 nearest, 1 linear).

    Returns
    -------
    CrossSection
    """
    if not isinstance(deformation, Deformation):
        raise InvalidInputError(f"deformation must be a Deformation, got {type(deformation).__name__}")
    shape = getattr(volume, "shape", None)
    if shape is None or len(shape) != 3:
        raise InvalidInputError(f"volume must be a 3D array (axis0, axis1, axis2), got shape {shape}")
    s = finite_number("s", s)
    lo, hi = deformation.s_range
    if not lo - 1e-9 <= s <= hi + 1e-9:
        raise InvalidInputError(f"s must lie in the deformation's range [{lo:.4g}, {hi:.4g}], got {s:.4g}")
    if order not in (0, 1):
        raise InvalidInputError(f"order must be 0 or 1, got {order!r}")
    sp = np.asarray(deformation.spacing, dtype=float)
    if half_size is None:
        mx, my = deformation.max_half_extent
        hw, hh = 1.5 * mx, 1.5 * my
        x_mid, y_mid = 0.0, 0.0
    else:
        hs = np.broadcast_to(np.asarray(half_size, dtype=float), (2,))
        if not (np.isfinite(hs).all() and (hs > 0).all()):
            raise InvalidInputError(f"half_size must be positive, got {half_size!r}")
        hw, hh = float(hs[0]), float(hs[1])
        x_mid, y_mid = 0.0, 0.0
    if pixel is None:
        pixel = max(float(sp.min()), 2.0 * max(hw, hh) / 512.0)
    pixel = finite_number("pixel", pixel)
    if pixel <= 0:
        raise InvalidInputError(f"pixel must be > 0, got {pixel!r}")
    nx = max(2, int(math.ceil(2 * hw / pixel)) + 1)
    ny = max(2, int(math.ceil(2 * hh / pixel)) + 1)
    x0 = x_mid - (nx - 1) * pixel / 2
    y0 = y_mid - (ny - 1) * pixel / 2
    c, r = deformation.sample([s])
    c, r = c[0], r[0]
    xs = x0 + pixel * np.arange(nx)
    ys = y0 + pixel * np.arange(ny)
    # voxel coordinates of the plane's pixels: p = c + x u + y v
    base = (c - np.asarray(deformation.origin)) / sp
    du, dv = r[0] / sp, r[1] / sp
    pts = base[:, None, None] + dv[:, None, None] * ys[None, :, None] + du[:, None, None] * xs[None, None, :]
    image = _sample(volume, pts, order)
    bounds = tuple(float(b) for b in deformation.bounds_at(min(max(s, 0.0), deformation.length))[0])
    return CrossSection(image=image, x0=float(x0), y0=float(y0), pixel=float(pixel), s=float(s),
                        bounds=bounds, centre=c, frame=r)  # type: ignore[arg-type]


def _sample(volume: Any, pts: np.ndarray, order: int) -> np.ndarray:
    """Values of ``volume`` at voxel coordinates ``pts`` (3, H, W), reading only the box around them."""
    shape = np.asarray(volume.shape)
    lo = np.floor(pts.reshape(3, -1).min(axis=1)).astype(int) - 1
    hi = np.ceil(pts.reshape(3, -1).max(axis=1)).astype(int) + 2
    lo_c, hi_c = np.clip(lo, 0, shape), np.clip(hi, 0, shape)
    out_shape = pts.shape[1:]
    if (hi_c <= lo_c).any():
        return np.zeros(out_shape, dtype=np.float32)
    block = np.asarray(volume[tuple(slice(a, b) for a, b in zip(lo_c, hi_c, strict=True))])
    if block.dtype.kind not in "fiub":
        raise InvalidInputError(f"the volume must hold numbers, got dtype {block.dtype}")
    local = pts - lo_c[:, None, None]
    out = ndimage.map_coordinates(block.astype(np.float32, copy=False), local.reshape(3, -1), order=order,
                                  mode="constant", cval=0.0, prefilter=False)
    # points beyond the scan read 0 (mode constant treats the block's own edge as the scan's only where it is)
    return out.reshape(out_shape).astype(np.float32, copy=False)
