"""Format detection and the reader/writer registry.

Each format lives in its own module with two functions:

``read_<fmt>(path: Path, **options) -> Volume``
    Lazy where the format allows it (memory maps, per-slice delayed reads, zarr). Validates up front and raises
    :class:`~napari_unwind.errors.InvalidInputError` with a message that says what is wrong and what to do.
``write_<fmt>(volume: Volume, path: Path, **options) -> Iterator[Progress]``
    Writes ``volume`` to exactly ``path`` (a temporary sibling chosen by :func:`write_volume`, renamed over the
    real target once the generator finishes), chunk by chunk where the format allows it, yielding progress.

The registry names modules as strings so that importing :mod:`napari_unwind.io` stays cheap.
"""

from __future__ import annotations

import importlib
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import InvalidInputError, UnknownFormatError
from ._files import check_regular, open_regular

__all__ = ["FORMATS", "detect_format", "reader_for", "writer_for", "output_format", "IMAGE_SLICE_SUFFIXES",
           "natural_key", "numbered_siblings"]

#: format name -> (module, reader function, writer function or None, description)
FORMATS: dict[str, tuple[str, str, str | None, str]] = {
    "ome-zarr": ("ome_zarr", "read_ome_zarr", "write_ome_zarr", "OME-Zarr (NGFF 0.5, zarr v3) with a pyramid"),
    "tiff": ("tiff", "read_tiff", "write_tiff", "multi-page TIFF / BigTIFF, ImageJ hyperstack"),
    "stack": ("stack", "read_stack", "write_stack", "folder of numbered 2D slices (bmp, png, tif)"),
    "dicom": ("dicom", "read_dicom", "write_dicom", "DICOM series (folder of .dcm files)"),
    "nrrd": ("nrrd_io", "read_nrrd", "write_nrrd", "NRRD / NHDR"),
    "nifti": ("nifti", "read_nifti", "write_nifti", "NIfTI-1/2 (.nii, .nii.gz)"),
    "raw": ("raw", "read_raw", "write_raw", "raw voxels with the original Unwind .dat header"),
}

IMAGE_SLICE_SUFFIXES = (".bmp", ".png", ".tif", ".tiff", ".jpg", ".jpeg")

# ------------------------------------------------------------------------------------------------------------------
# numbered slices: shared by the stack reader and the TIFF reader (a 2D TIFF may be one slice of a stack), so it
# lives here, below both, and neither imports the other for it
# ------------------------------------------------------------------------------------------------------------------
#: ``<prefix><number><suffix>``: the slice number is the last run of digits in the name.
_NUMBERED = re.compile(r"^(?P<prefix>.*?)(?P<num>\d+)(?P<suffix>\D*)$")


def natural_key(name: str) -> tuple:
    """Sort key treating runs of digits as numbers: ``fish_2.png`` < ``fish_10.png``."""
    tokens = [t for t in re.split(r"(\d+)", name) if t]
    return tuple((0, int(t), "") if t.isdigit() else (1, 0, t.lower()) for t in tokens), name


def _image_files(folder: Path) -> list[Path]:
    try:
        entries = list(folder.iterdir())
    except OSError as exc:
        raise InvalidInputError(f"cannot list the folder {folder}: {exc.strerror or exc}") from None
    return [p for p in entries if not p.name.startswith(".") and p.suffix.lower() in IMAGE_SLICE_SUFFIXES
            and p.is_file()]


def _group_key(name: str) -> tuple[str, str] | None:
    m = _NUMBERED.match(name)
    if m is None:
        return None
    return m.group("prefix"), m.group("suffix").lower()


def _groups(files: list[Path]) -> dict[tuple[str, str], list[tuple[int, Path]]]:
    groups: dict[tuple[str, str], list[tuple[int, Path]]] = {}
    for p in files:
        m = _NUMBERED.match(p.name)
        if m is not None:
            groups.setdefault((m.group("prefix"), m.group("suffix").lower()), []).append((int(m.group("num")), p))
    for members in groups.values():
        members.sort(key=lambda t: (t[0], natural_key(t[1].name)))
    return groups


def numbered_siblings(path: str | os.PathLike) -> list[Path]:
    """The slices of the numbered stack ``path`` belongs to (same prefix and suffix), in number order.

    ``[path]`` when ``path`` has no number or no sibling.
    """
    path = Path(path)
    key = _group_key(path.name)
    if key is None or path.suffix.lower() not in IMAGE_SLICE_SUFFIXES:
        return [path]
    members = _groups(_image_files(path.parent)).get(key, [])
    return [p for _, p in members] or [path]


_SUFFIX_FORMAT = {
    ".zarr": "ome-zarr",
    ".tif": "tiff",
    ".tiff": "tiff",
    ".btf": "tiff",
    ".tf8": "tiff",
    ".nrrd": "nrrd",
    ".nhdr": "nrrd",
    ".nii": "nifti",
    ".nii.gz": "nifti",
    ".dat": "raw",
    ".raw": "raw",
    ".dcm": "dicom",
    ".dicom": "dicom",
}

_HELP = (
    "supported: OME-Zarr (.zarr), TIFF (.tif/.tiff), NRRD (.nrrd/.nhdr), NIfTI (.nii/.nii.gz), "
    "raw + .dat header (.dat/.raw), a DICOM series folder (.dicom or any folder of .dcm files), "
    "a folder of numbered 2D slices (bmp/png/tif)"
)


def _suffix(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".nii.gz"):
        return ".nii.gz"
    return path.suffix.lower()


def _is_dicom_file(path: Path) -> bool:
    try:
        with open_regular(path) as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except (OSError, InvalidInputError):
        return False


def detect_format(path: str | Path) -> str:
    """Name the format of an existing path (a key of :data:`FORMATS`).

    Raises
    ------
    FileNotFoundError
        When the path does not exist.
    UnknownFormatError
        When nothing recognisable is there.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist")
    suffix = _suffix(path)
    if path.is_dir():
        if (path / "zarr.json").exists() or (path / ".zgroup").exists() or (path / ".zarray").exists():
            return "ome-zarr"
        files = sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
        if not files:
            raise UnknownFormatError(f"{path} is an empty folder; point at a scan file or a folder of slices")
        if any(p.suffix.lower() == ".dcm" for p in files) or _is_dicom_file(files[0]):
            return "dicom"
        if any(p.suffix.lower() in IMAGE_SLICE_SUFFIXES for p in files):
            return "stack"
        raise UnknownFormatError(f"cannot tell what the folder {path} holds; {_HELP}")
    check_regular(path)  # a named pipe or a device would block or stream for ever
    if suffix in _SUFFIX_FORMAT:
        return _SUFFIX_FORMAT[suffix]
    if suffix in (".bmp", ".png", ".jpg", ".jpeg"):
        return "stack"  # one slice of a numbered stack: the stack reader takes its siblings
    if _is_dicom_file(path):
        return "dicom"
    raise UnknownFormatError(f"unknown format of {path} (suffix {suffix!r}); {_HELP}")


def output_format(path: str | Path, format: str | None = None) -> str:
    """The format to write ``path`` in: ``format`` if given, else from the suffix."""
    if format is not None:
        if format not in FORMATS:
            raise UnknownFormatError(f"unknown output format {format!r}; choose one of {', '.join(FORMATS)}")
        return format
    suffix = _suffix(Path(path))
    if re.search(r"\{[^}]*\}", Path(path).name) and suffix in IMAGE_SLICE_SUFFIXES:
        return "stack"  # a numbered slice pattern, e.g. slices/fish_{:04d}.tif
    if suffix in _SUFFIX_FORMAT:
        return _SUFFIX_FORMAT[suffix]
    raise UnknownFormatError(f"cannot choose an output format for {path} from its suffix {suffix!r}; {_HELP}")


def _load(fmt: str, which: int) -> Callable:
    if fmt not in FORMATS:
        raise UnknownFormatError(f"unknown format {fmt!r}; choose one of {', '.join(FORMATS)}")
    entry = FORMATS[fmt]
    name = entry[which]
    if name is None:
        raise UnknownFormatError(f"writing {fmt} is not supported")
    module = importlib.import_module(f"napari_unwind.io.{entry[0]}")
    return getattr(module, name)


def reader_for(fmt: str) -> Callable:
    """The ``read_<fmt>`` function of a format."""
    return _load(fmt, 1)


def writer_for(fmt: str) -> Callable:
    """The ``write_<fmt>`` generator function of a format."""
    return _load(fmt, 2)


def compresses(fmt: str, path: str | os.PathLike, options: dict[str, Any]) -> bool:
    """Whether the writer of ``fmt`` compresses the voxels of ``path`` with these write ``options``: an option not
    given takes the writer's own default, read from its signature (nothing here restates a default)."""
    import inspect

    def option(name: str) -> Any:
        if name in options:
            return options[name]
        p = inspect.signature(writer_for(fmt)).parameters.get(name)
        return None if p is None or p.default is inspect.Parameter.empty else p.default

    name = Path(str(path)).name.lower()
    if fmt in ("ome-zarr", "tiff"):
        return str(option("compression") or "none").lower() not in ("none", "")
    if fmt == "nrrd":
        return str(option("encoding") or "raw").lower() != "raw"
    if fmt == "nifti":
        return name.endswith(".gz")
    if fmt == "stack":
        return str(option("pattern") or name).lower().endswith((".png", ".jpg", ".jpeg"))
    return False  # raw, DICOM: the voxels as they are
