"""Step 5, Refine: the cross-section editor (:class:`napari_unwind._napari._refine.RefinePanel`) on the dock's
editing model, or a note when this build has none."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from qtpy.QtWidgets import QLabel, QWidget


def refine_page(viewer: Any, model: Any, volume: Callable[[], Any]) -> tuple[QWidget, Any]:
    """(the page, the RefinePanel or None) for the editing ``model`` of the scan ``volume()``."""
    try:
        from .._refine import RefinePanel
    except ImportError:
        label = QLabel("The cross-section editor is not available in this build (napari_unwind._napari._refine "
                       "is missing); the deformation can still be exported as the skeleton made it.")
        label.setWordWrap(True)
        return label, None
    panel = RefinePanel(viewer, model, volume)
    return panel, panel
