"""While a dock is open, Python's full garbage collections skip the heap that has already survived one.

Why: napari's process holds some 350 thousand objects that live as long as it does (the modules of napari, Qt, numba
and dask, the viewer and its layers). Every full pass of Python's cyclic collector walks all of them: 0.1-0.26 s on
the 2-core test machine, run by whichever thread happens to allocate, holding the interpreter, so the UI thread
stalls at turns no step chose (issue 21, benchmarks/RESULTS.md: 344-372 ms on the click after choosing a mask,
224-227 ms while the segment step ran).

What: after each full collection while a dock's viewer is open, the survivors are frozen (``gc.freeze``): later full
passes walk only the objects made since (3-40 ms measured). The first such collection runs once the new dock is idle
(its imports ahead done), so that its cost falls between the user's steps, not inside one. Frozen objects are still
freed by reference counting, but the cyclic collector never frees them, and a napari layer lives in reference cycles
(its events call its own methods), as may what a step leaves behind. So the freeze is lifted (``gc.unfreeze``) and
the heap collected once when the docks have been idle a few seconds (:data:`RELEASE_AFTER_MS`) after a layer left a
viewer or a dock's job ended (at most one full pass per step, at a moment the user is not using the dock); and
lifted at once when a viewer closes, so that everything the viewer held is collectable. The collection that follows
freezes the survivors again while a dock's viewer is still open. With no dock open the collector is Python's own.
"""

from __future__ import annotations

import gc
import weakref
from typing import Any

from qtpy.QtCore import QEvent, QObject, QTimer

from . import _private

__all__ = ["RELEASE_AFTER_MS", "engage", "engaged", "pending", "release", "soon"]

#: ms after a layer's removal, the docks idle, before the freeze is lifted and the heap collected once
RELEASE_AFTER_MS = 3000
#: ms after a dock opens before its first collection (when the docks are busy then: :data:`RELEASE_AFTER_MS` later)
FIRST_AFTER_MS = 500

_DOCKS: weakref.WeakSet = weakref.WeakSet()  # the open docks (their ``idle`` and their viewer)
_TIMER: list[QTimer] = []  # the release timer, made with the first dock


def engaged() -> bool:
    """True while a dock's viewer is open (the survivors of a full collection are then frozen)."""
    return any(not _private.viewer_closed(dock.viewer) for dock in list(_DOCKS))


def _after_collection(phase: str, info: dict) -> None:
    if phase == "stop" and info.get("generation") == 2 and engaged():
        gc.freeze()


def release(collect: bool = True) -> None:
    """Lift the freeze; with ``collect`` collect the whole heap now (and freeze its survivors while engaged)."""
    if _TIMER:
        _TIMER[0].stop()
    gc.unfreeze()
    if collect:
        gc.collect()


def _busy(dock: Any) -> bool:
    """A dock of an open viewer whose step runs. A dock whose viewer closed is never busy: a job the close cut short
    never reports its end, and the dock lingers until a collection frees its cycles (its ``idle`` would stay False
    and hold back every other dock's collection)."""
    if _private.viewer_closed(dock.viewer):
        _DOCKS.discard(dock)
        return False
    try:
        return not dock.idle
    except RuntimeError:  # its Qt widgets were deleted (the viewer closed)
        return False


def _release_when_idle() -> None:
    if any(_busy(dock) for dock in list(_DOCKS)):
        _TIMER[0].start(RELEASE_AFTER_MS)  # a step runs (or the dock's imports ahead): after it, idle again a while
        return
    release()


def soon() -> None:
    """Lift the freeze and collect the heap once the docks have been idle for :data:`RELEASE_AFTER_MS` (restarted
    by each call): after a layer's removal and after each of a dock's jobs, so that what they left in reference
    cycles is freed."""
    if _TIMER:
        _TIMER[0].start(RELEASE_AFTER_MS)


def pending() -> bool:
    """True while a collection of the whole heap waits for the docks to be idle."""
    return bool(_TIMER) and _TIMER[0].isActive()


def _on_removed(event: Any = None) -> None:
    soon()


class _OnClose(QObject):
    """An event filter of a viewer's main window: its closing lifts the freeze."""

    def eventFilter(self, obj: Any, event: Any) -> bool:  # noqa: N802 - Qt's name
        if event.type() == QEvent.Type.Close:
            release(collect=False)  # napari's own collection after a close (or the next full pass) frees the viewer
        return False


def engage(dock: Any) -> None:
    """Apply the policy (see the module) while ``dock``'s viewer is open."""
    if dock in _DOCKS:
        return
    if not _TIMER:
        timer = QTimer()
        timer.setSingleShot(True)
        timer.timeout.connect(_release_when_idle)
        _TIMER.append(timer)
    if _after_collection not in gc.callbacks:
        gc.callbacks.append(_after_collection)
    _DOCKS.add(dock)
    _TIMER[0].start(FIRST_AFTER_MS)  # the heap so far collected and frozen once the dock is idle
    viewer = dock.viewer
    viewer.layers.events.removed.connect(_on_removed)
    window = _private.main_window(viewer)
    if window is not None:
        window.installEventFilter(_OnClose(window))
