"""Volumes as napari layer-data tuples: plain data and dicts, no napari import (the core stays Qt-free)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..io import Volume

__all__ = ["image_layer", "labels_layer"]


def _geometry(spacing: Any, unit: str | None, origin: Any = (0.0, 0.0, 0.0)) -> dict[str, Any]:
    kwargs: dict[str, Any] = {
        "scale": tuple(float(s) for s in spacing),
        "translate": tuple(float(o) for o in origin),
        "axis_labels": ("axis0", "axis1", "axis2"),
    }
    if unit:
        kwargs["units"] = (unit,) * 3
    return kwargs


def image_layer(volume: Volume, *, name: str | None = None, **kwargs: Any) -> tuple[Any, dict[str, Any], str]:
    """An Image layer tuple: multiscale when the volume has a pyramid, lazy (dask) either way."""
    data: Any = list(volume.levels) if len(volume.levels) > 1 else volume.data
    meta = {
        "name": name or (volume.source and volume.source.rstrip("/").split("/")[-1]) or "volume",
        "multiscale": len(volume.levels) > 1,
        "metadata": {"napari_unwind": {"source": volume.source, "format": volume.format,
                                       "spacing": volume.spacing, "unit": volume.unit}},
        **_geometry(volume.spacing, volume.unit, volume.origin),
    }
    meta.update(kwargs)
    return data, meta, "image"


def labels_layer(labels: np.ndarray, *, spacing: Any, unit: str | None, name: str,
                 **kwargs: Any) -> tuple[Any, dict[str, Any], str]:
    """A Labels layer tuple with the same geometry conventions as :func:`image_layer`."""
    meta = {"name": name, **_geometry(spacing, unit)}
    meta.update(kwargs)
    return labels, meta, "labels"


def scan_units(viewer: Any) -> dict[str, Any]:
    """``{"units": ...}`` of the viewer's scan (its first Image layer with a physical unit), or ``{}``: the layers
    added over the scan take them, since napari stops using units when the layers' units disagree."""
    for layer in viewer.layers:
        units = getattr(layer, "units", None)
        if layer.__class__.__name__ == "Image" and units is not None and {str(u) for u in units} != {"pixel"}:
            return {"units": tuple(units)}
    return {}
