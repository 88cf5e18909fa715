"""The Shortcuts page: the dock's mouse gestures and the Refine editor's keys, in one table."""

from __future__ import annotations

from typing import Any

from qtpy.QtCore import Qt
from qtpy.QtWidgets import QAbstractItemView, QTableWidget, QTableWidgetItem, QVBoxLayout

from ._base import Step

#: The dock's own shortcuts (the editor's come from RefinePanel.SHORTCUTS).
DOCK_SHORTCUTS = (
    ("click", "Segment: select the feature under the mouse (2D or 3D)"),
    ("shift-click", "Segment: add the feature to the selection"),
    ("drag a point", "Ends: move a head/tail (points layer in select mode)"),
    ("click (add mode)", "Ends: place another end (more than two: a chain, start and end of each part)"),
)


class ShortcutsStep(Step):
    """A two-column table (key or mouse, action) that fits the dock's width; ``refine_panel`` (or None) adds the
    editor's ``SHORTCUTS``."""

    def __init__(self, dock: Any, refine_panel: Any = None) -> None:
        super().__init__(dock)
        rows = list(DOCK_SHORTCUTS)
        panel_cls = type(refine_panel) if refine_panel is not None else None
        editor = getattr(panel_cls, "SHORTCUTS", None)
        if isinstance(editor, dict):
            editor = list(editor.items())
        rows += [(str(k), f"Refine: {v}") for k, v in (editor or ())]
        table = QTableWidget(len(rows), 2)
        table.setHorizontalHeaderLabels(("key / mouse", "action"))
        table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        for i, (key, action) in enumerate(rows):
            table.setItem(i, 0, QTableWidgetItem(key))
            table.setItem(i, 1, QTableWidgetItem(action))
        # the two columns share the dock's width and wrap their text (no horizontal scrolling at napari's default
        # dock width); the rows grow to the wrapped text
        table.setWordWrap(True)
        table.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        header = table.horizontalHeader()
        header.setSectionResizeMode(header.ResizeMode.Stretch)
        header.setMinimumSectionSize(60)
        table.verticalHeader().setSectionResizeMode(header.ResizeMode.ResizeToContents)
        table.verticalHeader().hide()
        self.table = table
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(table)
