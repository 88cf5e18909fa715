"""The UI thread's heavy steps one per turn of the event loop: a new layer added hidden and shown a turn later.

Adding a layer costs napari about 40-80 ms on the UI thread (its layer controls, the vispy layer, the layer list and
the selection), and the first paint of its visual more (vispy builds the visual's GLSL and parses it, renders the
text's glyphs, the GL driver compiles): 100-250 ms in one turn under Xvfb's software GL, above the 100 ms goal of a
UI stall (issue 21). A layer added hidden is not drawn, so its first paint waits until it is shown.

Here the steps wait in one queue and run one per ``STEP_MS`` timer shot: the timers and input that waited, and the
paint the previous step caused, run in between, so no turn holds two of them (a skeleton's result adds five layers:
the ends, the straight preview and three wireframes). :func:`add_layer` inserts a layer hidden (now or as a step)
and shows it as the next step; the layer is the same layer with the same name, data and place in the list. A
visibility set by anyone in between (the user's eye button, the code) wins: the layer is then left as they set it.
:func:`flush` runs what waits at once (for code that needs the layer in the viewer now).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

from qtpy.QtCore import QTimer

__all__ = ["STEP_MS", "add_layer", "cancel", "flush", "later", "pending", "waiting"]

#: the time between two steps (ms): more than a paint's posting, so the paint a step caused runs on its own turn
STEP_MS = 15

_QUEUE: deque[tuple[Any, Callable[[], Any]]] = deque()
_TIMER: list[QTimer] = []


def _timer() -> QTimer:
    if not _TIMER:
        t = QTimer()
        t.setSingleShot(True)
        t.setInterval(STEP_MS)
        t.timeout.connect(_run_one)
        _TIMER.append(t)
    return _TIMER[0]


def pending() -> bool:
    """True while steps wait (a layer to be added or shown)."""
    return bool(_QUEUE)


def waiting(owner: Any) -> bool:
    """True while steps of ``owner`` wait."""
    return any(o is owner for o, _ in _QUEUE)


def later(step: Callable[[], Any], owner: Any = None) -> None:
    """Run ``step()`` on a later turn of the event loop, after the steps queued before it; ``owner``: what
    :func:`cancel` drops it by."""
    _QUEUE.append((owner, step))
    t = _timer()
    if not t.isActive():
        t.start()


def cancel(owner: Any) -> None:
    """Drop the waiting steps of ``owner``."""
    keep = [(o, s) for o, s in _QUEUE if o is not owner]
    _QUEUE.clear()
    _QUEUE.extend(keep)


def _run_one() -> None:
    if _QUEUE:
        _, step = _QUEUE.popleft()
        try:
            step()
        finally:
            if _QUEUE:
                _timer().start()


def flush() -> None:
    """Run every waiting step now."""
    while _QUEUE:
        _, step = _QUEUE.popleft()
        step()


def add_layer(viewer: Any, layer: Any, *, keep_active: bool = False, now: bool = True,
              then: Callable[[], Any] | None = None) -> Any:
    """Add ``layer`` (a napari Layer) to ``viewer`` hidden -- ``now`` or as a step -- and show it as the next step
    when it was to be visible, make it the active layer as napari does (unless ``keep_active``: the active layer
    stays the one that was) as the step after, then ``then()``."""
    show = bool(layer.visible)
    if show:
        layer.visible = False
    touched: list[bool] = []

    def on_visible(event: Any = None) -> None:  # someone set the visibility: theirs stands
        touched.append(True)

    def insert() -> None:
        from . import _private

        _private.add_layer_unselected(viewer, layer)  # the selection's change apart (napari selects a new layer)
        if show:
            layer.events.visible.connect(on_visible)

    def select() -> None:
        if layer in viewer.layers:
            viewer.layers.selection.active = layer

    def reveal() -> None:
        layer.events.visible.disconnect(on_visible)
        if not touched and layer in viewer.layers:  # and the layer is still there
            layer.visible = True

    def alive(step: Callable[[], Any]) -> Callable[[], Any]:
        def run() -> None:
            from . import _private

            if not _private.viewer_closed(viewer):  # a closed viewer gets no more layers
                step()
        return run

    if now:
        insert()
    else:
        later(alive(insert), layer)
    if show:
        later(alive(reveal), layer)
    if not keep_active:
        later(alive(select), layer)
    if then is not None:
        later(alive(then), layer)
    return layer
