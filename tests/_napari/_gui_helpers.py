"""Helpers shared by the Qt tests of the editor, the Refine panel and the workflow (no tests here)."""

from __future__ import annotations

import json

import numpy as np
from qtpy.QtCore import QPoint, Qt
from qtpy.QtTest import QTest

from napari_unwind.deformation import Deformation


def state(d: Deformation) -> str:
    """Bit-exact fingerprint of a deformation."""
    return json.dumps(d.to_dict(), sort_keys=True, default=lambda x: float(x).hex()) + "|" + "".join(
        np.asarray(k.position).tobytes().hex() + np.asarray(k.frame).tobytes().hex() for k in d.keyframes)


class Events:
    """Counts the model's deformation_changed and history_changed emissions."""

    def __init__(self, model):
        self.changed = self.history = 0
        model.deformation_changed.connect(self._changed)
        model.history_changed.connect(self._history)

    def _changed(self, *_):
        self.changed += 1

    def _history(self, *_):
        self.history += 1


def drag(qtbot, widget, start, end, *, steps=4, modifier=Qt.KeyboardModifier.NoModifier):
    """Press at canvas pixel ``start``, move in steps, release at ``end`` (integers)."""
    start, end = np.asarray(start), np.asarray(end)
    QTest.mousePress(widget, Qt.MouseButton.LeftButton, modifier, QPoint(*map(int, start)))
    for t in np.linspace(0, 1, steps + 1)[1:]:
        qtbot.wait(15)  # vispy drops moves closer than 10 ms
        p = np.round(start + t * (end - start)).astype(int)
        QTest.mouseMove(widget, QPoint(*map(int, p)))
    qtbot.wait(15)
    QTest.mouseRelease(widget, Qt.MouseButton.LeftButton, modifier, QPoint(*map(int, end)))
