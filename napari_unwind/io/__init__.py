"""Volume I/O: open any scan lazily, write any format atomically, import to an OME-Zarr pyramid."""

from ._api import (
    as_volume,
    import_slabs_iter,
    import_volume,
    import_volume_iter,
    open_volume,
    write_volume,
    write_volume_iter,
)
from ._formats import FORMATS, detect_format
from ._volume import Volume

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
