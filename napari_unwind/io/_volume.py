"""The in-memory description of a scan: a lazy array plus its geometry."""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InvalidInputError
from ._units import UNIT_ABBREVIATIONS, normalise_unit, unit_label  # noqa: F401 (also this module's interface)
from ._units import UNITS as _UNITS  # noqa: F401

if TYPE_CHECKING:
    import dask.array as da

__all__ = ["Volume", "LazyArray", "SUPPORTED_DTYPES", "check_spacing", "normalise_unit"]

#: Voxel types the pipeline accepts: 8- and 16-bit integers (signed or not) and floats.
SUPPORTED_DTYPES = tuple(
    np.dtype(t) for t in ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")
)


def _numbers(name: str, what: str, value: Any, ndim: int, errors: tuple) -> tuple[float, ...]:
    """``value`` as ``ndim`` floats (one number broadcast), or the refusal naming ``name`` and ``what`` it must be."""
    try:
        return tuple(float(v) for v in np.broadcast_to(np.asarray(value, dtype=float), (ndim,)))
    except errors:
        raise InvalidInputError(
            f"{name} must be {ndim} {what} in array axis order (axis0, axis1, axis2), got {value!r}"
        ) from None


def check_spacing(spacing: Any, ndim: int = 3) -> tuple[float, ...]:
    """Validate a voxel spacing: ``ndim`` finite positive numbers, in array axis order."""
    values = _numbers("spacing", "positive numbers", spacing, ndim, (TypeError, ValueError))
    if not all(np.isfinite(v) and v > 0 for v in values):
        raise InvalidInputError(f"spacing must be finite and positive, got {values}")
    return values


def check_origin(origin: Any, ndim: int = 3) -> tuple[float, ...]:
    """Validate an origin: ``ndim`` finite numbers (the position of voxel 0), in array axis order."""
    values = _numbers("origin", "numbers", origin, ndim, (TypeError, ValueError, OverflowError))
    if not all(np.isfinite(v) for v in values):
        raise InvalidInputError(f"origin must be finite numbers, got {values}")
    return values


def _is_dask(value: Any) -> bool:
    """``isinstance(value, dask.array.Array)`` without importing dask: no dask array exists before dask is imported."""
    da = sys.modules.get("dask.array")
    return da is not None and isinstance(value, da.Array)


# one copy, numpy-free, shared with the header reader (unwind info's fast path)
from ._headers import _regular_chunks  # noqa: E402


class LazyArray:
    """What a reader knows from a file's header (shape, dtype, regular chunk shape) and how to build the dask array.

    A :class:`Volume` given one (as ``data`` or among ``levels``) builds its dask arrays, importing dask, only when
    ``data`` or ``levels`` is first used, so that ``unwind info`` reads the header alone. ``build`` must return an
    array of exactly this shape, dtype and chunks.
    """

    __slots__ = ("shape", "dtype", "chunks", "_build")

    def __init__(self, build: Callable[[], da.Array], shape: tuple[int, ...], dtype: Any, chunks: tuple[int, ...]):
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        self.chunks = _regular_chunks(self.shape, chunks)
        self._build = build

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def build(self) -> da.Array:
        return self._build()

    def __repr__(self) -> str:
        return f"LazyArray(shape={self.shape}, dtype={self.dtype}, chunks={self.chunks})"


_BUILD_LOCK = threading.RLock()


class _Voxels:
    """``Volume.data`` and ``Volume.levels``: stored as given, :class:`LazyArray` s built on first read."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        state = obj.__dict__
        if isinstance(state["data"], LazyArray) or any(isinstance(lvl, LazyArray) for lvl in state["levels"]):
            with _BUILD_LOCK:
                _build_voxels(state)
        return state[self.name]

    def __set__(self, obj: Any, value: Any) -> None:
        obj.__dict__[self.name] = value


def _build_voxels(state: dict[str, Any]) -> None:
    data, levels = state["data"], state["levels"]
    built: dict[int, Any] = {}
    for a in (data, *levels):  # data is levels[0]: each LazyArray is built once (a reader opens its file once)
        if isinstance(a, LazyArray) and id(a) not in built:
            built[id(a)] = a.build()
    state["levels"] = tuple(built.get(id(lvl), lvl) for lvl in levels)  # levels[0] stays ``data`` itself
    state["data"] = built.get(id(data), data)


@dataclass(frozen=True)
class Volume:
    """A scan: a lazy 3D array in array index order (axis0, axis1, axis2) with its geometry.

    Attributes
    ----------
    data : dask.array.Array, shape (N0, N1, N2)
        The voxels at full resolution. Nothing is read until it is computed.
    spacing : tuple of 3 float
        Voxel size along axis0, axis1, axis2, in ``unit``.
    unit : str or None
        NGFF length unit name (``"micrometer"``, ``"millimeter"``...), None when the file does not say.
    origin : tuple of 3 float
        Physical position of voxel (0, 0, 0), in ``unit``.
    levels : tuple of dask.array.Array
        The multiscale pyramid, finest first (``levels[0] is data``). A single level for non-pyramidal files.
    level_spacings : tuple of tuple of 3 float
        The spacing of each pyramid level.
    level_origins : tuple of tuple of 3 float
        The physical position of voxel (0, 0, 0) of each pyramid level (a downsampled level's first voxel is the
        centre of the block it averages, so its origin differs from level 0's). Default: ``origin`` for every
        level.
    source : str or None
        Where the volume was read from.
    format : str or None
        The reader that produced it (``"ome-zarr"``, ``"tiff"``, ``"nrrd"``...).
    metadata : dict
        Anything else the reader found worth keeping (DICOM series UID, TIFF description...).
    """

    data: da.Array
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    unit: str | None = None
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    levels: tuple[da.Array, ...] = ()
    level_spacings: tuple[tuple[float, float, float], ...] = ()
    level_origins: tuple[tuple[float, float, float], ...] = ()
    source: str | None = None
    format: str | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        data = self.__dict__["data"]
        if not isinstance(data, LazyArray) and not _is_dask(data):
            import dask.array as da

            data = da.asarray(np.asarray(data))
            object.__setattr__(self, "data", data)
        if data.ndim != 3:
            raise InvalidInputError(f"a volume must be 3D (axis0, axis1, axis2), got shape {data.shape}")
        if 0 in data.shape:
            raise InvalidInputError(f"a volume must not have a dimension of size 0, got shape {data.shape}")
        if np.dtype(data.dtype) not in SUPPORTED_DTYPES:
            raise InvalidInputError(
                f"unsupported voxel type {data.dtype}; supported are "
                + ", ".join(str(d) for d in SUPPORTED_DTYPES)
                + " (convert colour images to grey first)"
            )
        object.__setattr__(self, "spacing", check_spacing(self.spacing))
        object.__setattr__(self, "origin", check_origin(self.origin))
        object.__setattr__(self, "unit", normalise_unit(self.unit))
        if not self.__dict__["levels"]:
            object.__setattr__(self, "levels", (data,))
            object.__setattr__(self, "level_spacings", (self.spacing,))
            object.__setattr__(self, "level_origins", (self.origin,))
        elif len(self.level_spacings) != len(self.__dict__["levels"]):
            raise InvalidInputError("a Volume needs one spacing per pyramid level")
        if not self.level_origins:
            object.__setattr__(self, "level_origins", (self.origin,) * len(self.__dict__["levels"]))
        elif len(self.level_origins) != len(self.__dict__["levels"]):
            raise InvalidInputError("a Volume needs one origin per pyramid level")
        object.__setattr__(self, "level_origins",
                           tuple(tuple(float(o) for o in np.broadcast_to(lo, (3,))) for lo in self.level_origins))

    # -- conveniences -------------------------------------------------------------------------------------------
    # read from the header where a reader left a LazyArray: neither builds the dask arrays
    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.__dict__["data"].shape)  # type: ignore[return-value]

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self.__dict__["data"].dtype)

    @property
    def level_shapes(self) -> tuple[tuple[int, ...], ...]:
        """The shape of each pyramid level, finest first."""
        return tuple(tuple(int(n) for n in lvl.shape) for lvl in self.__dict__["levels"])

    @property
    def level_chunks(self) -> tuple[tuple[tuple[int, ...], ...], ...]:
        """The (dask) chunks of each pyramid level, finest first."""
        return tuple(tuple(tuple(c) for c in lvl.chunks) for lvl in self.__dict__["levels"])

    def __getstate__(self) -> dict[str, Any]:
        _ = self.data  # LazyArray builders need not pickle: send the dask arrays
        return dict(self.__dict__)

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape)) * self.dtype.itemsize

    @property
    def unit_abbreviation(self) -> str:
        """Short unit for display (``"um"``), or ``"voxels"`` when unknown."""
        return unit_label(self.unit)

    def level_for(self, max_side: int = 256) -> int:
        """Index of the finest pyramid level whose every side is ``<= max_side`` (the coarsest if none is)."""
        shapes = self.level_shapes
        for i, shape in enumerate(shapes):
            if max(shape) <= max_side:
                return i
        return len(shapes) - 1

    def level(self, index: int) -> Volume:
        """Pyramid level ``index`` as a single-level Volume with that level's own spacing and origin."""
        if not 0 <= int(index) < len(self.levels):
            raise InvalidInputError(f"{self.source or 'the volume'} has pyramid levels 0..{len(self.levels) - 1}, "
                                    f"got level {index}")
        i = int(index)
        return replace(self, data=self.levels[i], spacing=self.level_spacings[i], origin=self.level_origins[i],
                       levels=(), level_spacings=(), level_origins=())

    def with_data(self, data: da.Array, **changes: Any) -> Volume:
        """A copy holding other voxels (levels reset to that one array unless given).

        When ``data`` is one of this volume's own pyramid levels, its spacing and origin are that level's unless
        given in ``changes``.
        """
        for i, lvl in enumerate(self.levels):
            if i and data is lvl:
                changes.setdefault("spacing", self.level_spacings[i])
                changes.setdefault("origin", self.level_origins[i])
                break
        changes.setdefault("levels", ())
        changes.setdefault("level_spacings", ())
        changes.setdefault("level_origins", ())
        return replace(self, data=data, **changes)

    def __repr__(self) -> str:
        return (
            f"Volume(shape={self.shape}, dtype={self.dtype}, spacing={self.spacing}, unit={self.unit!r}, "
            f"levels={len(self.level_shapes)}, format={self.format!r}, source={self.source!r})"
        )


# after @dataclass, which would take them for the fields' defaults
Volume.data = _Voxels()  # type: ignore[assignment,misc]
Volume.data.__set_name__(Volume, "data")
Volume.levels = _Voxels()  # type: ignore[assignment,misc]
Volume.levels.__set_name__(Volume, "levels")


def warn_bad_spacing(path: Any, axis: int, value: float) -> None:
    """Say that a file declares a voxel size that is not a positive number along array ``axis``, read as 1."""
    import warnings

    warnings.warn(f"{Path(str(path)).name} declares a voxel size of {value:g} along axis{axis}, which is not a "
                  "positive number: it is read as 1; give the real spacing (--spacing A0,A1,A2, or spacing= in "
                  "Python) or fix the file's header", UserWarning, stacklevel=3)
