"""Folders of numbered 2D slices (bmp, png, tif/tiff, jpg): ``<prefix><N><suffix>.<ext>``.

This is how the original Unwind program stored scans (8-bit BMP stacks) and how many CT reconstruction programs
export them. A stack is found from a folder or from any one of its slices; the slice number is the last run of
digits in the name, sorted as a number (``fish_2`` before ``fish_10``, zero padded or not).

Reading is lazy: one dask chunk per slice, decoded when computed. Only the image headers are read up front,
to check that every slice has the same size and type.

Geometry: slice files carry no spacing between slices. The spacing is taken from the first slice when it says
something: the exact geometry this package writes (a ``unwind`` PNG text chunk or TIFF description), or ImageJ
TIFF calibration (X/YResolution and unit; the distance between slices is assumed equal to the X spacing when
the slice does not give it, with a warning). Otherwise the spacing is 1 and the unit None: pass the real
voxel size to :func:`~napari_unwind.io.import_volume` (``spacing=``, ``unit=``) or on the command line.
"""

from __future__ import annotations

import fnmatch
import io
import os
import re
import string
import warnings
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import dask.array as da
import numpy as np
import tifffile
from dask.base import tokenize

from ..errors import InvalidInputError, OutputError, SeriesSelectionError
from ..progress import Progress
from ._atomic import final_name
from ._files import ConfinementError, ReadConfinement, current_confinement, open_regular
from ._formats import _NUMBERED, IMAGE_SLICE_SUFFIXES, _group_key, _groups, _image_files, natural_key, numbered_siblings
from ._lazy import slab_depth
from ._volume import Volume

__all__ = [
    "DEFAULT_PATTERN",
    "natural_key",
    "numbered_siblings",
    "read_stack",
    "split_stack_target",
    "write_stack",
]

#: Slice name pattern used when the output name does not give one.
DEFAULT_PATTERN = "slice_{:05d}.png"
_TIFF = (".tif", ".tiff")
_FIELD = re.compile(r"\{[^{}]*\}")
#: Voxel types each slice format can store, and what to use instead.
_WRITABLE = {
    ".png": ((np.dtype("uint8"), np.dtype("uint16")), "write .tif slices (any type) or a .tif/.zarr volume"),
    ".bmp": ((np.dtype("uint8"),), "write .png slices (uint8, uint16) or .tif slices (any type)"),
    ".jpg": ((np.dtype("uint8"),), "write .png slices (uint8, uint16) or .tif slices (any type)"),
    ".jpeg": ((np.dtype("uint8"),), "write .png slices (uint8, uint16) or .tif slices (any type)"),
}


# ------------------------------------------------------------------------------------------------------------------
# finding the slices
# ------------------------------------------------------------------------------------------------------------------
def _glob_of(key: tuple[str, str]) -> str:
    return f"{key[0]}*{key[1]}"


def _check_numbers(members: list[tuple[int, Path]], where: str) -> None:
    numbers = [n for n, _ in members]
    dup = sorted({n for n in numbers if numbers.count(n) > 1})
    if dup:
        names = [p.name for n, p in members if n == dup[0]]
        raise InvalidInputError(
            f"{where}: slice number {dup[0]} appears more than once ({', '.join(names)}); "
            "remove the duplicates or choose the slices with pattern='...'"
        )
    expected = numbers[-1] - numbers[0] + 1
    if expected != len(numbers):
        have = set(numbers)
        missing = [n for n in range(numbers[0], numbers[-1] + 1) if n not in have]
        shown = ", ".join(str(n) for n in missing[:10]) + (" ..." if len(missing) > 10 else "")
        warnings.warn(
            f"{where}: {len(missing)} slice number(s) missing between {numbers[0]} and {numbers[-1]} ({shown}); "
            "the slices are stacked without gaps, so distances along axis 0 are wrong there",
            stacklevel=4,
        )


def _select(path: Path, pattern: str | None) -> tuple[list[Path], str]:
    """The slice files, in order, and a glob describing them."""
    if pattern is not None:
        folder = path if path.is_dir() else path.parent
        glob = _FIELD.sub("*", str(pattern))
        if "/" in glob or os.sep in glob:
            raise InvalidInputError(f"pattern= is a file name glob such as 'fish_*.png', got {pattern!r}")
        files = [p for p in _image_files(folder) if fnmatch.fnmatch(p.name, glob)]
        if not files:
            raise InvalidInputError(f"no image slice in {folder} matches the pattern {glob!r}")
        files.sort(key=lambda p: natural_key(p.name))
        numbered = [(int(_NUMBERED.match(p.name).group("num")), p) for p in files if _NUMBERED.match(p.name)]
        if len(numbered) == len(files) and len(_groups(files)) == 1:
            _check_numbers(numbered, f"{folder}/{glob}")
        return files, glob
    if path.is_file():
        key = _group_key(path.name)
        members = _groups(_image_files(path.parent)).get(key, []) if key else []
        if len(members) < 2:
            raise InvalidInputError(
                f"{path} is a single 2D image; a volume needs 3D: numbered slices in one folder "
                f"(e.g. {path.stem}_0000{path.suffix}, {path.stem}_0001{path.suffix}, ...) or a 3D file"
            )
        _check_numbers(members, f"{path.parent}/{_glob_of(key)}")
        return [p for _, p in members], _glob_of(key)
    files = _image_files(path)
    groups = _groups(files)
    if not groups and len(files) == 1 and files[0].suffix.lower() in _TIFF:
        return files, files[0].name  # a folder holding one TIFF: read_stack hands it to read_tiff
    if not groups:
        raise InvalidInputError(
            f"{path} holds no numbered image slices (bmp, png, tif, jpg named like fish_0001.png); "
            "point at a scan file, or pass pattern='...' to choose the slices"
        )
    ranked = sorted(groups.items(), key=lambda kv: (-len(kv[1]), kv[0]))
    described = {_glob_of(k): f"{len(v)} slices, {v[0][1].name} ... {v[-1][1].name}" for k, v in ranked}
    if len(ranked) > 1 and len(ranked[0][1]) == len(ranked[1][1]):
        tied = [_glob_of(k) for k, v in ranked if len(v) == len(ranked[0][1])]
        raise SeriesSelectionError(
            f"{path} holds several stacks of {len(ranked[0][1])} slices ({', '.join(tied)}); choose one with "
            f"pattern='{tied[0]}' (CLI: --pattern)",
            described,
        )
    key, members = ranked[0]
    others = len(files) - len(members)
    if others:
        other_groups = [g for g in described if g != _glob_of(key)]
        warnings.warn(
            f"{path}: reading the {len(members)} slices {_glob_of(key)} and ignoring {others} other image(s)"
            + (f" ({', '.join(other_groups[:5])})" if other_groups else "")
            + "; pass pattern='...' to choose other slices",
            stacklevel=3,
        )
    _check_numbers(members, f"{path}/{_glob_of(key)}")
    return [p for _, p in members], _glob_of(key)


# ------------------------------------------------------------------------------------------------------------------
# headers and decoding
# ------------------------------------------------------------------------------------------------------------------
# PIL mode -> (numpy dtype, how to turn the decoded image into grey)
_PIL_MODES = {
    "L": ("uint8", "grey"), "P": ("uint8", "palette"), "1": ("uint8", "bool"), "LA": ("uint8", "first"),
    "RGB": ("uint8", "rgb"), "RGBA": ("uint8", "rgb"), "RGBX": ("uint8", "rgb"),
    "I;16": ("uint16", "grey"), "I;16L": ("uint16", "grey"), "I;16B": ("uint16", "grey"),
    "I;16N": ("uint16", "grey"), "I": ("int32", "grey"), "F": ("float32", "grey"),
}


def _header(path: Path) -> tuple[tuple[int, int], np.dtype, str]:
    """(rows, columns), voxel type and kind of one slice, from its header only."""
    try:
        with open_regular(path, "slice", confine=current_confinement()) as fh:
            return _slice_header(path, fh)
    except (OSError, ValueError, tifffile.TiffFileError) as exc:
        if isinstance(exc, InvalidInputError | ConfinementError):
            raise
        raise InvalidInputError(f"cannot read the slice {path} ({exc}); is the file complete?") from None


def _slice_header(path: Path, fh: Any) -> tuple[tuple[int, int], np.dtype, str]:
    if path.suffix.lower() in _TIFF:
        with tifffile.TiffFile(fh, name=path.name) as tif:
            page = tif.pages.first
            shape = tuple(int(n) for n in page.shape)
            spp = int(page.samplesperpixel)
            photometric = int(page.photometric)
            dtype = np.dtype(page.dtype)
            pages = len(tif.pages)
        if pages > 1:
            return shape[-2:], dtype, f"{pages} pages (a multi-page TIFF, not a 2D slice: open it directly)"
        if photometric == 3:  # palette
            return (shape[0], shape[1]), dtype, "tiff-palette"
        if spp > 1:
            if spp not in (3, 4) or len(shape) != 3:
                return (0, 0), dtype, f"{spp} samples per pixel"
            rows, cols = (shape[0], shape[1]) if shape[-1] == spp else (shape[1], shape[2])
            return (rows, cols), dtype, "rgb"
        if len(shape) != 2:
            return shape[-2:], dtype, f"shape {shape}"
        if dtype == np.dtype(bool):
            return (shape[0], shape[1]), np.dtype("uint8"), "bool"
        return (shape[0], shape[1]), dtype, "grey"
    from PIL import Image

    with Image.open(fh) as im:
        cols, rows = im.size
        mode = im.mode
    if mode not in _PIL_MODES:
        return (rows, cols), np.dtype("uint8"), f"PIL mode {mode}"
    dtype, kind = _PIL_MODES[mode]
    return (rows, cols), np.dtype(dtype), kind


def _grey(rgb: np.ndarray, path: Path) -> np.ndarray:
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    if not (np.array_equal(r, g) and np.array_equal(r, b)):
        raise InvalidInputError(
            f"{path} is a colour image (its red, green and blue differ); napari-unwind needs grey slices: "
            "convert the stack to grey first (Fiji: Image > Type > 8-bit)"
        )
    return np.ascontiguousarray(r)


def _check_png(path: Path, data: memoryview) -> None:
    """Check the CRC of every PNG chunk: Pillow stops decoding once it has the pixels, so flipped bytes in the
    image data would otherwise give other values without an error."""
    pos = 8
    while pos + 12 <= len(data):
        length = int.from_bytes(data[pos:pos + 4], "big")
        end = pos + 8 + length
        if end + 4 > len(data):
            return  # cut short: Pillow reports it
        kind = bytes(data[pos + 4:pos + 8])
        if zlib.crc32(data[pos + 4:end]) != int.from_bytes(data[end:end + 4], "big"):
            raise InvalidInputError(f"cannot decode the slice {path}: its {kind.decode('latin-1')!r} chunk fails "
                                    "its CRC check; the file is damaged: copy it again")
        if kind == b"IEND":
            return
        pos = end + 4


def read_slice(path: str | os.PathLike, shape: tuple[int, int] | None = None, dtype: Any = None, *,
               confine: ReadConfinement | None = None) -> np.ndarray:
    """Decode one slice as a 2D grey array (RGB slices must be grey: r == g == b).

    With ``confine`` the slice file is opened first and checked where the opened file lies (the decoders read
    that handle, never the path again).

    Raises
    ------
    InvalidInputError
        A colour slice, or one whose size or type differs from ``shape`` / ``dtype``.
    ConfinementError
        The file lies outside ``confine`` (a PermissionError, naming no path).
    """
    path = Path(path)
    try:
        with open_regular(path, "slice", confine=confine) as fh:
            arr = _decode_slice(path, fh)
    except (OSError, ValueError, tifffile.TiffFileError) as exc:
        if isinstance(exc, InvalidInputError | ConfinementError):
            raise
        raise InvalidInputError(f"cannot decode the slice {path} ({exc}); is the file complete?") from None
    if shape is not None and tuple(arr.shape) != tuple(shape):
        raise InvalidInputError(
            f"slice {path} is {arr.shape[1]} x {arr.shape[0]} pixels (shape {arr.shape}) but the stack's slices "
            f"are {shape[1]} x {shape[0]} (shape {tuple(shape)}); every slice must have the same size"
        )
    if dtype is not None and arr.dtype != np.dtype(dtype):
        raise InvalidInputError(f"slice {path} holds {arr.dtype} values but the stack holds {np.dtype(dtype)}; "
                                "every slice must have the same type")
    return arr


def _decode_slice(path: Path, fh: Any) -> np.ndarray:
    """The grey pixels of the slice open as ``fh`` (``path`` names it in messages and chooses the decoder)."""
    if path.suffix.lower() in _TIFF:
        with tifffile.TiffFile(fh, name=path.name) as tif:
            page = tif.pages.first
            arr = page.asarray()
            if int(page.photometric) == 3:
                cmap = page.colormap
                if cmap is None or not (np.array_equal(cmap[0], cmap[1]) and np.array_equal(cmap[0], cmap[2])):
                    raise InvalidInputError(
                        f"{path} is a colour palette image; convert the stack to grey first "
                        "(Fiji: Image > Type > 8-bit)"
                    )
                lut = cmap[0]
                if lut.max() > 255:
                    lut = lut >> 8
                arr = lut.astype(np.uint8)[arr]
        if arr.ndim == 3 and arr.shape[-1] in (3, 4):
            arr = _grey(arr, path)
        elif arr.ndim == 3 and arr.shape[0] in (3, 4):  # planar RGB
            arr = _grey(np.moveaxis(arr, 0, -1), path)
        if arr.dtype == bool:
            arr = arr.astype(np.uint8)
    else:
        from PIL import Image

        source: Any = fh
        if path.suffix.lower() == ".png":
            source = io.BytesIO(fh.read())
            _check_png(path, source.getbuffer())
        with Image.open(source) as im:
            im.load()
            mode = im.mode
            if mode == "P":
                palette = np.asarray(im.getpalette() or [], dtype=np.uint8).reshape(-1, 3)
                idx = np.asarray(im)
                if palette.size == 0:
                    arr = idx.astype(np.uint8)
                else:
                    padded = np.zeros((256, 3), np.uint8)
                    padded[: len(palette)] = palette[:256]
                    arr = _grey(padded[idx], path)
            elif mode in ("RGB", "RGBA", "RGBX"):
                arr = _grey(np.asarray(im), path)
            elif mode == "LA":
                arr = np.ascontiguousarray(np.asarray(im)[..., 0])
            elif mode in _PIL_MODES:
                arr = np.asarray(im)
                if arr.dtype == bool:
                    arr = arr.astype(np.uint8)
                arr = arr.astype(arr.dtype.newbyteorder("="), copy=False)
            else:
                raise InvalidInputError(f"{path} has the image mode {mode}; convert the stack to 8- or 16-bit "
                                        "grey first")
    return arr


class _SliceStack:
    """Picklable array-like (N, Y, X) decoding the slice files a key touches; opened under
    :func:`~napari_unwind.io._files.confined_reads` (the server), each slice file is checked where it lies at each
    read (a slice swapped for a symbolic link out after the open is refused, the others still read)."""

    def __init__(self, files: list[str], shape: tuple[int, int, int], dtype: Any):
        self.files = [str(f) for f in files]
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)
        self.ndim = 3
        self.confine = current_confinement()  # opened confined: every slice read is (see _files.confined_reads)

    def __getitem__(self, key: Any) -> np.ndarray:
        if not isinstance(key, tuple):
            key = (key,)
        if any(k is Ellipsis for k in key):
            i = next(i for i, k in enumerate(key) if k is Ellipsis)
            key = key[:i] + (slice(None),) * (3 - len(key) + 1) + key[i + 1:]
        key = key + (slice(None),) * (3 - len(key))
        planes = np.arange(self.shape[0])[key[0]]
        single = np.ndim(planes) == 0
        out = np.stack([read_slice(self.files[int(z)], self.shape[1:], self.dtype, confine=self.confine)[key[1:]]
                        for z in np.atleast_1d(planes)])
        return out[0] if single else out


# ------------------------------------------------------------------------------------------------------------------
# geometry of the first slice
# ------------------------------------------------------------------------------------------------------------------
def _slice_geometry(first: Path) -> dict[str, Any]:
    from .tiff import _stored_geometry, tiff_geometry

    none = {"spacing": (1.0, 1.0, 1.0), "unit": None, "origin": (0.0, 0.0, 0.0), "from": "none"}
    try:
        if first.suffix.lower() in _TIFF:
            with tifffile.TiffFile(first) as tif:
                geo = tiff_geometry(tif, path=first)
                ij = tif.imagej_metadata if tif.is_imagej else None
            if geo["from"] == "imagej" and "spacing" not in (ij or {}):
                geo = dict(geo, spacing=(geo["spacing"][2],) + tuple(geo["spacing"][1:]))
                warnings.warn(
                    f"{first} gives the pixel size but not the distance between slices; assuming cubic voxels "
                    f"({geo['spacing'][2]:g} {geo['unit'] or 'pixel'}); pass spacing= to override",
                    stacklevel=4,
                )
            elif geo["from"] == "resolution":
                geo = dict(geo, spacing=(geo["spacing"][2],) + tuple(geo["spacing"][1:]))
            return geo
        if first.suffix.lower() == ".png":
            from PIL import Image

            with Image.open(first) as im:
                text = getattr(im, "text", {}) or {}
            return _stored_geometry(text.get("unwind")) or none
    except (OSError, ValueError, tifffile.TiffFileError):
        return none
    return none


# ------------------------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------------------------
def _check_kind(path: Path, kind: str) -> None:
    if kind not in ("grey", "palette", "bool", "first", "rgb", "tiff-palette"):
        raise InvalidInputError(f"the slice {path} has {kind}; napari-unwind reads 8/16-bit or float grey "
                                "slices: convert the stack to grey first")


def read_stack(path: Path, *, pattern: str | None = None) -> Volume:
    """Open a stack of numbered 2D slices lazily, one dask chunk per slice.

    Parameters
    ----------
    path : Path
        A folder of slices, or one slice (its siblings with the same prefix and suffix are taken).
    pattern : str, optional
        A file name glob choosing the slices in the folder (``"fish_*.png"``); a ``{...}`` field counts as
        ``*``, so the pattern given to :func:`write_stack` works too. Needed when a folder holds several stacks
        of the same size. Slices are sorted by their numbers.

    Returns
    -------
    Volume
        Shape (number of slices, rows, columns). Spacing 1 and unit None unless the first slice declares a
        pixel size (see the module docstring): pass the voxel size to ``import_volume`` otherwise.

    Raises
    ------
    InvalidInputError
        No slices, a slice of another size or type (named, with both sizes), colour slices, a lone 2D image.
    SeriesSelectionError
        The folder holds several equally large stacks; ``.series`` maps their globs to a description.
    """
    path = Path(path).expanduser().absolute()  # workers of a cluster run in other folders
    files, glob = _select(path, pattern)
    if len(files) == 1 and path.is_dir() and _group_key(files[0].name) is None:
        from .tiff import read_tiff

        return read_tiff(files[0])
    shape0, dtype, kind = _header(files[0])
    _check_kind(files[0], kind)
    first = read_slice(files[0], shape0, dtype, confine=current_confinement())  # catches colour stacks up front
    for f in files[1:]:
        shape, dt, k = _header(f)
        _check_kind(f, k)
        if shape != shape0:
            raise InvalidInputError(
                f"slice {f} is {shape[1]} x {shape[0]} pixels but {files[0].name} is {shape0[1]} x {shape0[0]}; "
                f"every slice of a stack must have the same size (expected shape {shape0}, found {shape})"
            )
        if dt != dtype:
            raise InvalidInputError(f"slice {f} holds {dt} values but {files[0].name} holds {dtype}; every slice "
                                    "of a stack must have the same type")
    del first
    geometry = _slice_geometry(files[0])
    stat = [os.stat(f) for f in (files[0], files[-1])]
    token = tokenize([str(f) for f in files], [(s.st_mtime_ns, s.st_size) for s in stat])
    arr = _SliceStack([str(f) for f in files], (len(files),) + tuple(shape0), dtype)
    data = da.from_array(arr, chunks=(1,) + tuple(shape0), name=f"stack-{token}", asarray=False, fancy=False,
                         meta=np.empty((0, 0, 0), dtype=dtype))
    return Volume(data, spacing=geometry["spacing"], unit=geometry["unit"], origin=geometry["origin"],
                  source=str(path), format="stack",
                  metadata={"files": [str(f) for f in files], "pattern": glob, "geometry_from": geometry["from"],
                            **({"unwind": {"straightening": geometry["straightening"]}}
                               if geometry.get("straightening") else {})})


# ------------------------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------------------------
def _check_pattern(pattern: str, count: int, start: int) -> str:
    """Validate a slice name pattern; returns its (lower-case) image suffix."""
    try:
        fields = [f for _, f, _, _ in string.Formatter().parse(pattern) if f is not None]
    except ValueError as exc:
        raise InvalidInputError(f"bad slice name pattern {pattern!r}: {exc}") from None
    if len(fields) != 1 or fields[0] not in ("", "0"):
        raise InvalidInputError(
            f"a slice name pattern needs exactly one {{}} field for the slice number, e.g. 'fish_{{:04d}}.png'; "
            f"got {pattern!r}"
        )
    try:
        names = {pattern.format(start), pattern.format(start + count - 1), pattern.format(start + 1)}
    except (ValueError, IndexError, KeyError) as exc:
        raise InvalidInputError(f"cannot number slices with the pattern {pattern!r}: {exc}") from None
    if len(names) < min(count, 3) or any(("/" in n or os.sep in n or n.startswith(".")) for n in names):
        raise InvalidInputError(f"the pattern {pattern!r} must give one plain file name per slice number")
    suffix = Path(pattern.format(start)).suffix.lower()
    if suffix not in IMAGE_SLICE_SUFFIXES:
        raise InvalidInputError(
            f"the slice pattern {pattern!r} must end with an image suffix: {', '.join(IMAGE_SLICE_SUFFIXES)}"
        )
    return suffix


def split_stack_target(path: str | os.PathLike) -> tuple[Path, str]:
    """Split a stack output ``out/slices/fish_{:04d}.png`` into the folder to create and the slice pattern.

    The folder is the unit that is written atomically. It must be a folder of its own: an existing folder is
    only replaced when it holds nothing but slices matching the pattern (so that overwriting never deletes
    other files).

    Raises
    ------
    InvalidInputError
        No ``{}`` field, no image suffix, or no folder part.
    OutputError
        The folder exists and holds other files.
    """
    path = Path(path)
    pattern = path.name
    _check_pattern(pattern, 2, 0)
    if path.parent == Path(".") and not Path(path).is_absolute():
        raise InvalidInputError(f"put the slices in a folder of their own, e.g. slices/{pattern}")
    folder = path.parent.expanduser().absolute()
    if folder.is_dir():
        glob = _FIELD.sub("*", pattern)
        others = [p.name for p in folder.iterdir() if not fnmatch.fnmatch(p.name, glob)]
        if others:
            raise OutputError(
                f"{folder} exists and holds other files ({', '.join(sorted(others)[:5])}); "
                "write the slices to a new folder"
            )
    return folder, pattern


def _tiff_slice_options(volume: Volume) -> dict[str, Any]:
    from .tiff import IMAGEJ_DTYPES, imagej_options, plain_options

    opts = imagej_options(volume) if volume.dtype in IMAGEJ_DTYPES else plain_options(volume)
    opts["metadata"] = dict(opts["metadata"], axes="YX")
    return opts


def write_stack(
    volume: Volume,
    path: Path,
    *,
    pattern: str | None = None,
    start: int = 0,
    quality: int = 95,
) -> Iterator[Progress]:
    """Write ``volume`` as a folder of numbered 2D slices, one per plane of axis 0.

    Design: ``path`` is the folder to create (here the temporary name chosen by
    :func:`~napari_unwind.io.write_volume`, renamed into place once every slice is written), and the slices
    inside are named by ``pattern``, a :meth:`str.format` pattern with one integer field such as
    ``"fish_{:04d}.png"``. The suffix of the pattern chooses the file type. Without ``pattern`` the folder's
    final name is used when it is one (``write_volume(v, "out/fish_{:04d}.png")`` gives the folder
    ``out/fish_{:04d}.png/`` holding ``fish_0000.png`` ...), else ``slice_{:05d}.png``.
    :func:`split_stack_target` splits ``out/slices/fish_{:04d}.png`` into the folder ``out/slices`` and the
    pattern, for callers that write the folder ``out/slices`` instead.

    PNG and TIFF slices carry the exact spacing, unit and origin (a text chunk / the ImageJ description), which
    :func:`read_stack` reads back; BMP and JPEG carry none.

    Parameters
    ----------
    volume : Volume
        What to write: uint8 or uint16 for PNG, uint8 for BMP and JPEG, any type for TIFF.
    path : Path
        The folder to create (must not exist).
    pattern : str, optional
        Slice file name pattern, e.g. ``"fish_{:04d}.png"``.
    start : int
        Number of the first slice (default 0).
    quality : int
        JPEG quality (1-100; JPEG is lossy: prefer PNG for data).

    Yields
    ------
    Progress
        One record per slab of slices.
    """
    path = Path(path)
    if pattern is None:
        name = final_name(path)
        pattern = name if _FIELD.search(name) and Path(name).suffix.lower() in IMAGE_SLICE_SUFFIXES else DEFAULT_PATTERN
    n = volume.shape[0]
    start = int(start)
    if start < 0:
        raise InvalidInputError(f"start must be >= 0, got {start}")
    suffix = _check_pattern(pattern, n, start)
    dtype = volume.dtype
    if suffix in _WRITABLE and dtype not in _WRITABLE[suffix][0]:
        allowed, instead = _WRITABLE[suffix]
        raise InvalidInputError(
            f"{suffix} slices hold {' or '.join(str(d) for d in allowed)}, not {dtype}: {instead} "
            "(or rescale the data first)"
        )
    if suffix in (".jpg", ".jpeg"):
        warnings.warn("JPEG slices are lossy: the voxel values change; prefer .png for data", stacklevel=2)
    from .tiff import stored_geometry_json

    geometry = stored_geometry_json(volume)
    tiff_opts = _tiff_slice_options(volume) if suffix in _TIFF else None
    try:
        path.mkdir()
    except FileExistsError:
        raise OutputError(f"{path} already exists; write the slices to a new folder") from None
    except OSError as exc:
        raise OutputError(f"cannot create the folder {path}: {exc.strerror or exc}") from None

    from PIL import Image, PngImagePlugin

    depth = max(1, min(64, slab_depth(volume.shape[1:], dtype)))
    total = -(-n // depth)
    for i, z0 in enumerate(range(0, n, depth)):
        z1 = min(n, z0 + depth)
        slab = np.ascontiguousarray(volume.data[z0:z1].compute(), dtype=dtype)
        for k in range(z1 - z0):
            target = path / pattern.format(start + z0 + k)
            plane = slab[k]
            try:
                if tiff_opts is not None:
                    tifffile.imwrite(target, plane, **tiff_opts)
                elif suffix == ".png":
                    info = PngImagePlugin.PngInfo()
                    info.add_text("unwind", geometry)
                    Image.fromarray(plane).save(target, format="PNG", pnginfo=info)
                elif suffix == ".bmp":
                    Image.fromarray(plane).save(target, format="BMP")
                else:
                    Image.fromarray(plane).save(target, format="JPEG", quality=int(quality))
            except OSError as exc:
                raise OutputError(f"cannot write {target}: {exc.strerror or exc}") from None
        del slab
        yield Progress("write slices", i + 1, total, f"slices {z0}-{z1 - 1} of {n}")

