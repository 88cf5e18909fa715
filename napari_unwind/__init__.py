"""napari-unwind: straighten bent and twisted specimens in 3D scans.

The numerical core (this package, minus ``_qt``) imports no Qt, napari or gRPC.
"""

from importlib.metadata import PackageNotFoundError, version

from ._lazyattr import lazy_attributes
from .errors import InvalidInputError, OutputError, UnknownFormatError, UnwindError
from .progress import Progress

# Imported on first use, so that `import napari_unwind` (and the CLI's start: `unwind --version`, `unwind info`)
# stays quick: numpy, dask, scipy and numba are heavy. tests/test_startup.py checks it.
_LAZY = {
    "Volume": "io",
    "import_volume": "io",
    "open_volume": "io",
    "write_volume": "io",
    "Deformation": "deformation",
    "Keyframe": "deformation",
    "Session": "session",
    "load_session": "session",
    "save_session": "session",
    "bend": "warp",
    "export": "warp",
    "map_labels": "warp",
    "map_mesh": "warp",
    "map_points": "warp",
    "straighten": "warp",
    "estimate_deformation": "skeleton",
    "suggest_endpoints": "skeleton",
}


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY, globals())

try:
    __version__ = version("napari-unwind")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0+unknown"

__all__ = [
    "Deformation",
    "InvalidInputError",
    "Keyframe",
    "Session",
    "bend",
    "estimate_deformation",
    "export",
    "load_session",
    "map_labels",
    "map_mesh",
    "map_points",
    "save_session",
    "straighten",
    "suggest_endpoints",
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
