"""The Unwind dock's steps: one small widget per step, each in its own module, over the Qt-free
:class:`~napari_unwind.workflow.Workflow` and the dock's shared context (:class:`._base.Dock`).

:class:`~napari_unwind._napari._widget.UnwindWidget` is their container: the pages, the job runner, the status
line, the layers the steps share and the workflow's event wiring.
"""

from .ends import EndsStep
from .export import ExportStep
from .refine import refine_page
from .scan import ScanStep
from .segment import SegmentStep
from .session import SessionStep
from .shortcuts import DOCK_SHORTCUTS, ShortcutsStep
from .skeleton import SkeletonStep

__all__ = ["DOCK_SHORTCUTS", "EndsStep", "ExportStep", "ScanStep", "SegmentStep", "SessionStep", "ShortcutsStep",
           "SkeletonStep", "refine_page"]
