"""Exceptions of napari-unwind.

Every error a user can cause derives from :class:`UnwindError`. The CLI prints these as one clear message and
exits non-zero; the gRPC interceptor maps them to status codes. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

__all__ = [
    "UnwindError",
    "InvalidInputError",
    "UnknownFormatError",
    "OutputError",
    "SeriesSelectionError",
    "FoldError",
    "finite_number",
]


class UnwindError(Exception):
    """Base class of every error caused by input, options or the environment, not by a bug."""


class InvalidInputError(UnwindError, ValueError):
    """The input data or an option is malformed: the message says what is wrong and what to do."""


class UnknownFormatError(InvalidInputError):
    """The path's format could not be recognised or is not supported for this operation."""


class SeriesSelectionError(InvalidInputError):
    """A source holds several series (DICOM) and none was chosen.

    Attributes
    ----------
    series : dict[str, str]
        Series instance UID -> human readable description, for every series found.
    """

    def __init__(self, message: str, series: dict[str, str]):
        super().__init__(message)
        self.series = dict(series)


class NoBodyError(InvalidInputError):
    """The scan shows no body above the medium around a selection: there is nothing there to straighten (a
    candidate of the working level that the full-resolution scan does not bear out)."""


class OutputError(UnwindError, OSError):
    """An output cannot be written (unwritable folder, existing file without ``overwrite``...)."""


class FoldError(UnwindError):
    """A deformation folds over the specimen and the export was refused (the one fold rule,
    :func:`napari_unwind.pipeline.fold_rule`); allow folds to export anyway."""


def finite_number(name: str, value: object) -> float:
    """``value`` as a finite float, or an :class:`InvalidInputError` naming ``name`` and the value received.

    Booleans and non-scalars (lists, arrays) are refused: ``True`` is not an angle, ``[3]`` not a distance.
    """
    import math

    if type(value) not in (int, float):  # plain numbers (the options' defaults) need no numpy: the CLI starts quick
        import numpy as np

        if isinstance(value, (bool, np.bool_)) or not np.isscalar(value):
            raise InvalidInputError(f"{name} must be a number, got {value!r}")
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise InvalidInputError(f"{name} must be a finite number, got {value!r}")
    return v


def source_date_epoch() -> int | None:
    """``SOURCE_DATE_EPOCH`` (whole seconds since 1970, UTC; the reproducible-builds convention) when set, else
    None; a value that is not such a number raises :class:`InvalidInputError` with the value."""
    import os

    text = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if not text:
        return None
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value < 253402300800:  # before the year 10000
        raise InvalidInputError(f"SOURCE_DATE_EPOCH must be whole seconds since 1970 (UTC), got {text!r}; unset it "
                                "or give e.g. SOURCE_DATE_EPOCH=1700000000")
    return value
