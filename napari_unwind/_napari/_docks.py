"""Which napari viewers have an Unwind dock (no Qt, no napari import: the reader asks it).

A session opened by napari's reader restores its selection by recomputing the segmentation's join tree, seconds
on a large scan, on the UI thread (napari runs readers there). A viewer with an Unwind dock rebuilds that
selection itself in a worker, so the reader leaves it to the dock.
"""

from __future__ import annotations

import sys
import weakref
from typing import Any

__all__ = ["register", "has_dock", "current_viewer_has_dock"]

_DOCKS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # viewer -> its dock (weakly: both may go)


def register(viewer: Any, dock: Any) -> None:
    """Record that ``viewer`` has the Unwind ``dock``."""
    _DOCKS[viewer] = weakref.ref(dock)


def has_dock(viewer: Any) -> bool:
    """Whether ``viewer`` has a live Unwind dock."""
    ref = _DOCKS.get(viewer) if viewer is not None else None
    return ref is not None and ref() is not None


def current_viewer_has_dock() -> bool:
    """Whether napari's current viewer (the one a reader opens into) has a live Unwind dock; False without napari."""
    napari = sys.modules.get("napari")
    if napari is None:
        return False
    try:
        viewer = napari.current_viewer()
    except Exception:  # noqa: BLE001 - no application, no window: no dock
        return False
    return has_dock(viewer)
