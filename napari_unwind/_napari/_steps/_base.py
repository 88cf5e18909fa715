"""What every step widget shares: the dock's context (:class:`Dock`), the step's base class and small helpers."""

from __future__ import annotations

from collections.abc import Callable, Generator
from pathlib import Path
from typing import Any, Protocol

from qtpy.QtWidgets import QHBoxLayout, QPushButton, QWidget

from ...io import Volume
from ...progress import Progress
from ...workflow import Workflow
from .._workers import Job

#: The skeleton step (the pipeline's skeleton_step, judged), run in a child process by name (the UI process need not
#: import the mesher; the spare child imports the pipeline and the solver while idle).
SKELETON = "napari_unwind._steps:skeleton"


class Dock(Protocol):
    """The dock as its steps see it (:class:`~napari_unwind._napari._widget.UnwindWidget`): the viewer, the
    workflow, the job runner and the status line, and the layers the steps share."""

    viewer: Any
    workflow: Workflow
    scan_layer: Any
    #: the Labels layer whose mask is the selection: (layer, label; None: every label), or None
    mask_choice: tuple[Any, int | None] | None
    _features_layer: Any
    _selection_layer: Any
    _ends_layer: Any

    @property
    def volume(self) -> Volume | None: ...

    @property
    def features(self) -> Any: ...

    @property
    def where(self) -> str: ...

    def _start(self, make: Callable[[], Generator[Progress, None, Any]] | None, label: str,
               on_returned: Callable[[Any], Any], cancel_buttons: tuple = (), *,
               process: tuple | None = None) -> Job | None: ...

    def cancel(self) -> None: ...

    def _say(self, text: str) -> None: ...

    def _fail(self, exc: BaseException) -> None: ...

    def _add_layer(self, layer_tuple: tuple, *, reveal: bool = False) -> Any: ...

    def _put_layer(self, attr: str, layer_tuple: tuple) -> Any: ...

    def _update_needs(self) -> None: ...

    def _check_selection(self) -> None: ...

    def _set_scan(self, volume: Volume, layer: Any) -> None: ...

    def set_ends(self, voxels: list, roles: list[str] | None = None) -> Any: ...

    def segment(self, *, level: int | None = None) -> Job | None: ...

    def confirm_overwrite(self, path: Path) -> bool: ...


class Step(QWidget):
    """A step's page: its controls and handlers over ``dock.workflow``; jobs, messages and shared layers through
    ``dock``."""

    def __init__(self, dock: Dock, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.dock = dock

    @property
    def viewer(self) -> Any:
        return self.dock.viewer

    @property
    def workflow(self) -> Workflow:
        return self.dock.workflow

    def _say(self, text: str) -> None:
        self.dock._say(text)

    def _fail(self, exc: BaseException) -> None:
        self.dock._fail(exc)

    def update_needs(self) -> None:
        """Show what the step still needs and enable what it can do (called by the dock after every change)."""

    def job_buttons(self, layout: Any, text: str, start: Callable[[], Any]) -> tuple[QPushButton, QPushButton]:
        """A step's row: the button that starts its job and a Cancel button (enabled while the job runs)."""
        row = QHBoxLayout()
        button = QPushButton(text)
        button.clicked.connect(start)
        cancel = QPushButton("Cancel")
        cancel.clicked.connect(self.dock.cancel)
        cancel.setEnabled(False)
        row.addWidget(button, 1)
        row.addWidget(cancel)
        layout.addLayout(row)
        return button, cancel


def on_click(callback: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Generator[None, None, None]]:
    """A napari mouse-drag callback that calls ``callback(layer, event)`` on a click (a press released without a
    drag) and leaves drags to the camera."""

    def handler(layer: Any, event: Any) -> Generator[None, None, None]:
        if event.type != "mouse_press":
            return
        yield
        dragged = False
        while event.type == "mouse_move":
            dragged = True
            yield
        if not dragged:
            callback(layer, event)

    handler.__doc__ = callback.__doc__
    return handler


def labels_layers(dock: Dock, shape: tuple[int, ...] | None = None) -> list[Any]:
    """The viewer's 3D Labels layers a user may choose (the dock's own "features" and "selection" layers left out),
    only those whose data (a multiscale layer's finest level) has ``shape`` when given."""
    from napari.layers import Labels

    own = {id(dock._features_layer), id(dock._selection_layer)}
    out = []
    for layer in dock.viewer.layers:
        if not isinstance(layer, Labels) or layer.ndim != 3 or id(layer) in own:
            continue
        data = layer.data[0] if getattr(layer, "multiscale", False) else layer.data
        if shape is None or tuple(int(n) for n in data.shape) == tuple(int(n) for n in shape):
            out.append(layer)
    return out


def fmt(values: Any, digits: int = 4) -> str:
    return " x ".join(f"{float(v):.{digits}g}" for v in values)
