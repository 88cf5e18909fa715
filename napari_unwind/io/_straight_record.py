"""The straightening record every writer stores with a straight volume, so that ``unwind bend`` reads it back.

:func:`napari_unwind.warp.straighten` puts ``pad``, ``output_spacing``, ``order`` and ``fill`` into
``Volume.metadata``; an OME-Zarr export keeps them (with the deformation) under the attribute
``unwind.straightening``. The other formats have no room for a deformation, but each keeps this small record in its
own place for free text (NRRD key/value pair, NIfTI comment extension, the TIFF/PNG ``unwind`` JSON, a ``.dat``
line), and every reader returns it as ``Volume.metadata["unwind"]["straightening"]``, where OME-Zarr's reader puts
it too. The text is one line of JSON (no ``#``, no newline), so it fits each of those places.
"""

from __future__ import annotations

import json
import math
from typing import Any

from .._json import loads as safe_loads

__all__ = ["straightening_record", "record_text", "parse_record", "in_metadata"]

#: The keys of the record: the straight grid's geometry as straighten made it.
_KEYS = ("pad", "output_spacing", "unit", "order", "fill")


def _clean(info: Any, unit: Any) -> dict[str, Any] | None:
    """The record's keys of ``info`` (a dict), checked; None when ``info`` is not a straightening record."""
    if not isinstance(info, dict):
        return None
    pad, ds = info.get("pad"), info.get("output_spacing")
    if isinstance(pad, bool) or not isinstance(pad, (int, float)) or not (pad >= 0 and float(pad).is_integer()):
        return None
    if isinstance(ds, bool) or not isinstance(ds, (int, float)) or not (math.isfinite(ds) and ds > 0):
        return None
    record: dict[str, Any] = {"pad": int(pad), "output_spacing": float(ds),
                              "unit": info.get("unit", unit) if isinstance(info.get("unit", unit), str) else None}
    order, fill = info.get("order"), info.get("fill")
    if isinstance(order, int) and not isinstance(order, bool):
        record["order"] = order
    if isinstance(fill, (int, float)) and not isinstance(fill, bool) and math.isfinite(fill):
        record["fill"] = float(fill)
    return record


def straightening_record(volume: Any) -> dict[str, Any] | None:
    """The record to store with ``volume``: from straighten's metadata, or from a straight file read back."""
    meta = getattr(volume, "metadata", None) or {}
    unit = getattr(volume, "unit", None)
    if "deformation" in meta and "pad" in meta:  # straighten's own output
        return _clean(meta, unit)
    return in_metadata(meta, unit)


def in_metadata(meta: Any, unit: Any = None) -> dict[str, Any] | None:
    """The record a reader returned under ``metadata["unwind"]["straightening"]`` (None when there is none)."""
    unwind = meta.get("unwind") if isinstance(meta, dict) else None
    return _clean(unwind.get("straightening"), unit) if isinstance(unwind, dict) else None


def record_text(record: dict[str, Any]) -> str:
    """One line of JSON."""
    return json.dumps({k: record[k] for k in _KEYS if k in record}, separators=(",", ":"), allow_nan=False)


def parse_record(value: Any) -> dict[str, Any] | None:
    """A record from its text (or an already parsed dict); None for anything else."""
    if isinstance(value, bytes):
        value = value.decode("utf-8", errors="replace")
    if isinstance(value, str):
        try:
            value = safe_loads(value)
        except ValueError:
            return None
    return _clean(value, None)
