"""Length units: the NGFF names of the spellings file formats use, and their short labels.

Free of numpy, so that the header-only readers of ``unwind info`` (:mod:`napari_unwind.io._headers`) share the one
table with :mod:`napari_unwind.io._volume`.
"""

from __future__ import annotations

from ..errors import InvalidInputError

__all__ = ["UNITS", "UNIT_ABBREVIATIONS", "axis_units", "normalise_unit", "unit_label"]

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


#: Each unit as a power of ten of metres, to bring axes of different units to one (exact factors: 10 ** 3).
POWER_OF_METRE = {"meter": 0, "centimeter": -2, "millimeter": -3, "micrometer": -6, "nanometer": -9}


def axis_units(units: list) -> tuple[str | None, list[float]]:
    """One unit for axes that each name theirs (OME-Zarr): the finest of them, and the factor that brings each
    axis's lengths to it (1 where it already is). Axes without a unit with axes with one are refused: their
    voxel sizes cannot be compared.

    Raises
    ------
    InvalidInputError
        For an unknown unit, or a mix of axes with and without one.
    """
    names = [normalise_unit(u) for u in units]
    known = {n for n in names if n is not None}
    if not known:
        return None, [1.0] * len(names)
    if len(known) < len(names) and any(n is None for n in names):
        raise InvalidInputError(f"the spatial axes' units {units} mix lengths with none; give every axis a length "
                                "unit (or none)")
    finest = min(known, key=lambda n: POWER_OF_METRE[n])
    return finest, [10.0 ** (POWER_OF_METRE[n] - POWER_OF_METRE[finest]) for n in names]
