"""napari-unwind: straighten bent and twisted specimens in 3D scans.

The numerical core (this package, minus ``_qt``) imports no Qt, napari or gRPC.
"""

from importlib.metadata import PackageNotFoundError, version

from .errors import InvalidInputError, OutputError, UnknownFormatError, UnwindError
from .io import Volume, import_volume, open_volume, write_volume
from .progress import Progress

try:
    __version__ = version("napari-unwind")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0+unknown"

__all__ = [
    "InvalidInputError",
    "OutputError",
    "Progress",
    "UnknownFormatError",
    "UnwindError",
    "Volume",
    "__version__",
    "import_volume",
    "open_volume",
    "write_volume",
]
