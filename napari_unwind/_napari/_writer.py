"""napari writer contribution: an Image layer (the straight preview or export) saved through
:func:`napari_unwind.io.write_volume`, atomically, in the format the file name's suffix names.

No napari import: the layer arrives as napari's plain ``(path, data, meta)``. The layer's ``scale`` becomes the
voxel spacing, its ``translate`` the origin and its ``units`` the unit, so the file holds the geometry shown.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InvalidInputError
from ..io import write_volume
from ..io._volume import normalise_unit

__all__ = ["WRITER_SUFFIXES", "write_image"]

#: The suffixes the manifest's writers declare (each one :func:`~napari_unwind.io.write_volume` understands).
WRITER_SUFFIXES = (".ome.zarr", ".zarr", ".nrrd", ".nii.gz", ".nii", ".tif", ".tiff")


def _triple(meta: dict[str, Any], key: str, default: float, name: str) -> tuple[float, float, float]:
    value = meta.get(key)
    if value is None:
        return (default,) * 3
    values = tuple(float(v) for v in value)
    if len(values) != 3:
        raise InvalidInputError(f"the layer's {key} has {len(values)} values {values}; a {name} needs 3 (axis0, "
                                "axis1, axis2): save a 3D layer")
    return values  # type: ignore[return-value]


def _unit(meta: dict[str, Any]) -> str | None:
    units = meta.get("units")
    names = {str(u) for u in units} if units else set()
    if len(names) > 1:
        raise InvalidInputError(f"the layer's axes have different units {sorted(names)}; the formats written here "
                                "hold one length unit: set the same unit on every axis (layer.units)")
    if not names:
        stored = (meta.get("metadata") or {}).get("napari_unwind", {}).get("unit")
        return normalise_unit(stored) if stored else None
    return normalise_unit(names.pop())  # napari's "pixel" is no length unit: None


def write_image(path: str, data: Any, meta: dict[str, Any]) -> list[str]:
    """Write one 3D Image layer to ``path`` (OME-Zarr, NRRD, NIfTI or TIFF by its suffix); return ``[path]``.

    Parameters
    ----------
    path : str
        Target; ``.zarr``/``.ome.zarr``, ``.nrrd``, ``.nii``/``.nii.gz``, ``.tif``/``.tiff``. An existing file is
        replaced (napari's save dialog has asked), but only once the new one is complete.
    data : array-like or list of array-like
        The layer's data; for a multiscale layer the list of levels, of which the full resolution (the first) is
        written.
    meta : dict
        The layer's state: ``scale`` (spacing), ``translate`` (origin), ``units``, ``rgb``.

    Returns
    -------
    list of str
        The path written.

    Raises
    ------
    InvalidInputError
        An RGB layer, a layer that is not 3D, mixed units, or a voxel type the format cannot hold.
    """
    if meta.get("rgb"):
        raise InvalidInputError("an RGB image cannot be saved as a scan by napari-unwind; save a grey-level 3D layer")
    if meta.get("multiscale"):
        data = data[0]
    if np.ndim(data) != 3:
        raise InvalidInputError(f"napari-unwind saves 3D volumes; this layer has shape {tuple(np.shape(data))} "
                                "(select a 3D Image layer)")
    spacing = _triple(meta, "scale", 1.0, "spacing")
    origin = _triple(meta, "translate", 0.0, "origin")
    placed = (meta.get("metadata") or {}).get("napari_unwind", {}).get("straight_origin")
    if placed is not None:  # the straight preview, drawn beside the scan: its own straight grid's origin
        origin = _triple({"straight_origin": placed}, "straight_origin", 0.0, "origin")
    written = write_volume(data, path, spacing=spacing, origin=origin, unit=_unit(meta), overwrite=True)
    return [str(written)]
