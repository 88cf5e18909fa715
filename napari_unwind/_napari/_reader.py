"""napari reader contribution: every format :func:`napari_unwind.io.open_volume` knows."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import UnknownFormatError
from ..io import detect_format, open_volume

__all__ = ["get_reader"]


def get_reader(path: str | list[str]) -> Callable[[Any], list] | None:
    """Return a reader function when napari-unwind can open ``path``, else None (napari then asks others)."""
    if isinstance(path, list):
        if len(path) != 1:
            return None  # a list of files is a stack napari handles itself
        path = path[0]
    try:
        detect_format(Path(path))
    except (UnknownFormatError, FileNotFoundError):
        return None
    return read


def read(path: str | list[str]) -> list:
    """Open one scan as a (multiscale, lazy) Image layer with its spacing, origin and unit."""
    from ._layers import image_layer

    if isinstance(path, list):
        path = path[0]
    return [image_layer(open_volume(path))]
