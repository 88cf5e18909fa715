"""Volume I/O: open any scan lazily, write any format atomically, import to an OME-Zarr pyramid.

The names are imported on first use, so that ``import napari_unwind.io`` stays quick (no dask, no format
library): opening a scan imports only its reader, and the voxels' dask array is built when first used.
"""

from importlib import import_module
from typing import Any

_LAZY = {
    "as_volume": "_api",
    "import_slabs_iter": "_api",
    "import_volume": "_api",
    "import_volume_iter": "_api",
    "open_volume": "_api",
    "write_volume": "_api",
    "write_volume_iter": "_api",
    "FORMATS": "_formats",
    "detect_format": "_formats",
    "Volume": "_volume",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})


__all__ = [
    "FORMATS",
    "Volume",
    "as_volume",
    "detect_format",
    "import_slabs_iter",
    "import_volume",
    "import_volume_iter",
    "open_volume",
    "write_volume",
    "write_volume_iter",
]
