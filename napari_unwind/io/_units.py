"""Length units: the NGFF names of the spellings file formats use, and their short labels.

Free of numpy, so that the header-only readers of ``unwind info`` (:mod:`napari_unwind.io._headers`) share the one
table with :mod:`napari_unwind.io._volume`.
"""

from __future__ import annotations

from ..errors import InvalidInputError

__all__ = ["UNITS", "UNIT_ABBREVIATIONS", "normalise_unit", "unit_label"]

# NGFF unit names (UDUNITS-2) for the spellings file formats use.
UNITS = {
    "m": "meter", "meter": "meter", "metre": "meter",
    "cm": "centimeter", "centimeter": "centimeter",
    "mm": "millimeter", "millimeter": "millimeter", "millimetre": "millimeter",
    "um": "micrometer", "µm": "micrometer", "μm": "micrometer", "micron": "micrometer", "microns": "micrometer",
    "micrometer": "micrometer", "micrometre": "micrometer", "\\u00b5m": "micrometer",
    "nm": "nanometer", "nanometer": "nanometer",
    "pixel": None, "": None, "unknown": None, "none": None,
}

#: Short spellings for display and for formats that want them.
UNIT_ABBREVIATIONS = {"meter": "m", "centimeter": "cm", "millimeter": "mm", "micrometer": "um", "nanometer": "nm"}


def unit_label(unit: str | None) -> str:
    """How a length in ``unit`` is labelled for people: ``"um"`` for micrometer; ``"voxels"`` without a unit."""
    if not unit:
        return "voxels"
    return UNIT_ABBREVIATIONS.get(unit, unit)


def normalise_unit(unit: str | None) -> str | None:
    """Return the NGFF name of a length unit (``"mm"`` -> ``"millimeter"``), or None when unknown."""
    if unit is None:
        return None
    key = str(unit).strip().lower()
    if key in UNITS:
        return UNITS[key]
    raise InvalidInputError(
        f"unknown length unit {unit!r}; use one of meter, millimeter, micrometer, nanometer (or m, mm, um, nm)"
    )
