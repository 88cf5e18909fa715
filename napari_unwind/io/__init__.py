"""Volume I/O: open any scan lazily, write any format atomically, import to an OME-Zarr pyramid.

The names are imported on first use, so that ``import napari_unwind.io`` stays quick (no dask, no format
library): opening a scan imports only its reader, and the voxels' dask array is built when first used.
"""

from .._lazyattr import lazy_attributes

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
    "read_points": "points",
    "open_channels": "channels",
    "write_channels_iter": "channels",
}

__getattr__, __dir__ = lazy_attributes(__name__, _LAZY, globals())


__all__ = [
    "FORMATS",
    "Volume",
    "as_volume",
    "detect_format",
    "import_slabs_iter",
    "import_volume",
    "import_volume_iter",
    "open_channels",
    "open_volume",
    "read_points",
    "write_volume",
    "write_channels_iter",
    "write_volume_iter",
]
