"""Multi-page TIFF and BigTIFF volumes: ImageJ hyperstacks, OME-TIFF, plain page stacks.

Reading is lazy. Uncompressed contiguous data (what ImageJ and this module write by default) is memory-mapped
chunk by chunk; compressed or scattered pages are decoded page by page when a chunk is computed. Nothing but the
TIFF headers is read when the file is opened.

Geometry, first found wins:

1. the exact spacing, unit and origin this module stores (key ``unwind`` of the ImageJ description, or of
   tifffile's JSON description for plain TIFFs);
2. ImageJ metadata: ``spacing`` (axis0), ``unit`` (``micron``, ``\\u00B5m``, ``mm``...) and the X/YResolution
   tags (axis2/axis1 spacing = 1 / resolution), ``xorigin``/``yorigin``/``zorigin`` (in pixels);
3. OME-XML ``PhysicalSizeX/Y/Z`` and their units;
4. X/YResolution with ResolutionUnit centimetre (or tifffile's millimetre/micrometre). Resolution in inches or
   without a unit is ignored (it is almost always a 72 dpi default of the writing program), as is a missing
   one: the spacing is then 1 and the unit None, and the user passes the real spacing to ``import_volume``.

Writing makes an ImageJ hyperstack (uint8, uint16, float32: what ImageJ holds) that Fiji opens with the right
calibration; other voxel types, and volumes over 4 GB, become a plain (Big)TIFF with the same resolution tags
(in pixels per centimetre) and the exact geometry in a JSON description, which :func:`read_tiff` reads back.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import queue
import re
import shutil
import struct
import threading
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import tifffile

from .._json import loads as safe_loads
from ..errors import InvalidInputError, OutputError
from ..progress import Progress
from ._atomic import final_name
from ._files import ConfinementError, check_regular, current_confinement, open_regular
from ._formats import numbered_siblings, reader_for
from ._lazy import RawFileArray, slab_depth
from ._straight_record import parse_record, record_text, straightening_record
from ._volume import LazyArray, Volume, normalise_unit

if TYPE_CHECKING:
    import dask.array as da

__all__ = ["BIGTIFF_THRESHOLD", "IMAGEJ_DTYPES", "read_tiff", "tiff_geometry", "write_tiff"]

#: Voxel types an ImageJ hyperstack can hold.
IMAGEJ_DTYPES = (np.dtype("uint8"), np.dtype("uint16"), np.dtype("float32"))
#: Above this many bytes of voxels a classic TIFF cannot address its data: BigTIFF (tifffile's own limit).
BIGTIFF_THRESHOLD = 2**32 - 2**25
#: NGFF unit -> the spelling ImageJ writes and shows (``micron`` is displayed as µm).
IMAGEJ_UNITS = {"micrometer": "micron", "millimeter": "mm", "nanometer": "nm", "centimeter": "cm", "meter": "m"}
#: NGFF unit -> metres, to convert between units.
_METERS = {"meter": 1.0, "centimeter": 1e-2, "millimeter": 1e-3, "micrometer": 1e-6, "nanometer": 1e-9}
_OME_UNITS = {"m": "meter", "cm": "centimeter", "mm": "millimeter", "µm": "micrometer", "μm": "micrometer",
              "um": "micrometer", "nm": "nanometer"}


# ------------------------------------------------------------------------------------------------------------------
# geometry
# ------------------------------------------------------------------------------------------------------------------
def _unit_or_none(unit: Any, where: str) -> tuple[str | None, float]:
    """(NGFF unit, factor to multiply lengths by) for a unit spelled by some program; inches become mm."""
    if unit is None:
        return None, 1.0
    text = str(unit).strip()
    if text.lower() in ("inch", "inches", "in"):
        return "millimeter", 25.4
    try:
        return normalise_unit(text), 1.0
    except InvalidInputError:
        warnings.warn(f"{where}: unknown length unit {text!r}; the unit is left unknown", stacklevel=3)
        return None, 1.0


def _resolution(page: tifffile.TiffPage) -> tuple[float, float] | None:
    """(spacing along axis2, along axis1) = 1 / (X, Y)Resolution from the rational tags, or None."""
    out = []
    for name in ("XResolution", "YResolution"):
        tag = page.tags.get(name)
        if tag is None:
            return None
        value = tag.value
        num, den = (value if isinstance(value, tuple) else (float(value), 1.0))
        if not num or not den or num <= 0 or den <= 0:
            return None
        out.append(float(den) / float(num))  # den/num rounds once: 1/(10/3) gives exactly 0.3
    return out[0], out[1]


def _ome_geometry(xml: str, series: int) -> dict[str, Any] | None:
    try:
        root = ET.fromstring(xml)
    except ET.ParseError:
        return None
    images = [el for el in root if el.tag.endswith("Image")]
    if not images:
        return None
    image = images[min(series, len(images) - 1)]
    pixels = next((el for el in image if el.tag.endswith("Pixels")), None)
    if pixels is None:
        return None
    sizes, units = [], []
    for ax in ("Z", "Y", "X"):
        v = pixels.get(f"PhysicalSize{ax}")
        sizes.append(float(v) if v is not None else None)
        units.append(_OME_UNITS.get(pixels.get(f"PhysicalSize{ax}Unit", "µm"), None))
    if all(s is None for s in sizes):
        return None
    unit = next((u for u, s in zip(units[::-1], sizes[::-1], strict=True) if s is not None and u), None)
    spacing = []
    for s, u in zip(sizes, units, strict=True):
        if s is None or not s > 0:
            spacing.append(1.0)
        elif u and unit and u != unit:
            spacing.append(s * _METERS[u] / _METERS[unit])
        else:
            spacing.append(s)
    return {"spacing": tuple(spacing), "unit": unit, "origin": (0.0, 0.0, 0.0), "from": "ome"}


def _stored_geometry(value: Any) -> dict[str, Any] | None:
    """The exact geometry this module writes under the key ``unwind``."""
    if isinstance(value, str):
        try:
            value = safe_loads(value)
        except ValueError:
            return None
    if not isinstance(value, dict) or "spacing" not in value:
        return None
    try:
        spacing = tuple(float(v) for v in value["spacing"])
        origin = tuple(float(v) for v in value.get("origin", (0.0, 0.0, 0.0)))
        unit = normalise_unit(value.get("unit"))
    except (TypeError, ValueError):
        return None
    if len(spacing) != 3 or len(origin) != 3:
        return None
    return {"spacing": spacing, "unit": unit, "origin": origin, "from": "unwind",
            "straightening": parse_record(value.get("straightening"))}


def _consistent(stored: dict[str, Any], other: dict[str, Any]) -> bool:
    """Whether the stored exact geometry agrees with the tags (a program may have changed the tags since)."""
    if other.get("xy") is None:
        return True
    su, ou = stored["unit"], other["unit"]
    factor = _METERS[ou] / _METERS[su] if su in _METERS and ou in _METERS else 1.0
    return all(abs(a * factor - b) <= 1e-6 * abs(b) for a, b in zip(other["xy"], stored["spacing"][1:], strict=True))


def tiff_geometry(tif: tifffile.TiffFile, series: int = 0, *, path: Any = "") -> dict[str, Any]:
    """Spacing (axis0, axis1, axis2), NGFF unit and origin that a TIFF file declares.

    Returns
    -------
    dict
        ``spacing``, ``unit`` (None when unknown), ``origin`` and ``from`` (``"unwind"``, ``"imagej"``,
        ``"ome"``, ``"resolution"`` or ``"none"``).
    """
    page = tif.pages.first if hasattr(tif.pages, "first") else tif.pages[0]
    xy = _resolution(page)
    tags: dict[str, Any] = {"spacing": (1.0, 1.0, 1.0), "unit": None, "origin": (0.0, 0.0, 0.0), "from": "none",
                            "xy": None}
    ij = tif.imagej_metadata if tif.is_imagej else None
    shaped = tif.shaped_metadata[0] if tif.is_shaped and tif.shaped_metadata else None
    stored = _stored_geometry((ij or {}).get("unwind")) or _stored_geometry((shaped or {}).get("unwind"))

    if ij is not None:
        unit, factor = _unit_or_none(ij.get("unit"), str(path))
        sx, sy = xy if xy is not None else (1.0, 1.0)
        sz = float(ij.get("spacing", 1.0) or 1.0)
        if sz < 0:  # ImageJ stores a negative voxel depth for a reversed slice order
            warnings.warn(f"{path}: negative slice spacing {sz} (reversed slice order in ImageJ); using {-sz}",
                          stacklevel=3)
            sz = -sz
        spacing = (sz * factor, sy * factor, sx * factor)
        origin = tuple(-float(ij.get(f"{a}origin", 0.0) or 0.0) * s
                       for a, s in zip("zyx", spacing, strict=True))
        tags = {"spacing": spacing, "unit": unit, "origin": origin, "from": "imagej",
                "xy": None if xy is None else (sy * factor, sx * factor)}
    elif tif.is_ome and tif.ome_metadata:
        ome = _ome_geometry(tif.ome_metadata, series)
        if ome is not None:
            tags = ome
    elif xy is not None:
        resunit = int(page.resolutionunit or 1)
        scale = {3: ("millimeter", 10.0), 4: ("millimeter", 1.0), 5: ("micrometer", 1.0)}.get(resunit)
        if scale is not None:
            unit, f = scale
            tags = {"spacing": (1.0, xy[1] * f, xy[0] * f), "unit": unit, "origin": (0.0, 0.0, 0.0),
                    "from": "resolution", "xy": (xy[1] * f, xy[0] * f)}
    if stored is not None and _consistent(stored, tags):
        return stored
    tags.pop("xy", None)
    if any(not (np.isfinite(s) and s > 0) for s in tags["spacing"]):
        warnings.warn(f"{path}: invalid spacing {tags['spacing']} in the TIFF metadata; using 1", stacklevel=2)
        tags["spacing"] = (1.0, 1.0, 1.0)
    return tags


# ------------------------------------------------------------------------------------------------------------------
# damaged files
# ------------------------------------------------------------------------------------------------------------------
_LOG_LOCK = threading.Lock()
_BAD_OFFSET = re.compile(r"invalid (?:page|IFD) offset (\d+)", re.IGNORECASE)


class _Collect(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@contextlib.contextmanager
def _tifffile_log() -> Iterator[list[str]]:
    """Collect what tifffile logs while a file is opened (damage it works around), instead of printing it."""
    logger = logging.getLogger("tifffile")
    handler = _Collect()
    with _LOG_LOCK:
        propagate = logger.propagate
        logger.addHandler(handler)
        logger.propagate = False
        try:
            yield handler.messages
        finally:
            logger.removeHandler(handler)
            logger.propagate = propagate


def _check_complete(tif: tifffile.TiffFile, s: Any, path: Path, messages: list[str]) -> None:
    """Refuse a file cut short (or a damaged page list) instead of reading what is left as something else.

    Evidence: voxels that would lie past the end of the file; a page list pointing past the end (tifffile then
    silently stops, and an ImageJ stack looks like one 2D image); fewer planes than the ImageJ or tifffile
    metadata announce.
    """
    size = os.path.getsize(path)
    what = None
    if s.dataoffset is not None:
        end = int(s.dataoffset) + int(s.nbytes)
        if end > size:
            what = f"its voxels end at byte {end}"
    else:
        for page in s.pages:
            if page is None or not getattr(page, "dataoffsets", None):
                continue
            end = max(int(o) + int(c) for o, c in zip(page.dataoffsets, page.databytecounts, strict=True))
            if end > size:
                what = f"page {page.index} ends at byte {end}"
                break
    if what is None:
        cut = [int(m.group(1)) for m in map(_BAD_OFFSET.search, messages) if m]
        if any(offset >= size for offset in cut):
            what = f"its list of pages points to byte {max(cut)}"
    if what is not None:
        raise InvalidInputError(f"{path} is truncated: {what} but the file has {size} bytes; the copy is "
                                "incomplete: copy it again")
    planes = int(np.prod([n for a, n in zip(s.axes, s.shape, strict=True) if a not in "YXS"], dtype=np.int64))
    found, announced = planes, None
    if tif.is_imagej and isinstance((tif.imagej_metadata or {}).get("images"), int):
        announced, where, what = tif.imagej_metadata["images"], "the ImageJ metadata announce", "planes"
    elif tif.is_shaped and tif.shaped_metadata and isinstance(tif.shaped_metadata[0], dict):
        shaped = tif.shaped_metadata[0].get("shape")
        if isinstance(shaped, list | tuple) and all(isinstance(n, int) for n in shaped):
            announced, where, what = int(np.prod(shaped, dtype=np.int64)), "the tifffile metadata announce", "values"
            found = int(np.prod(s.shape, dtype=np.int64))
    if announced is not None and announced > found and len(tif.series) == 1:
        raise InvalidInputError(f"{path} is truncated or damaged: {where} {announced} {what} but only {found} "
                                "were found; copy the file again")


# ------------------------------------------------------------------------------------------------------------------
# lazy page access
# ------------------------------------------------------------------------------------------------------------------
def _expand_key(key: Any, ndim: int) -> tuple:
    if not isinstance(key, tuple):
        key = (key,)
    if any(k is Ellipsis for k in key):
        i = next(i for i, k in enumerate(key) if k is Ellipsis)
        key = key[:i] + (slice(None),) * (ndim - len(key) + 1) + key[i + 1:]
    return key + (slice(None),) * (ndim - len(key))


class _TiffPlanes:
    """Picklable array-like (N, Y, X) reading TIFF pages on demand (a fresh file handle per access).

    ``pages`` lists the IFD index of each plane, ``files`` the file holding it (default all ``path``: a multi-file
    OME-TIFF names others); with ``pages=None`` the whole series is read at each access (the fallback for layouts
    without one plane per page).

    Opened under :func:`~napari_unwind.io._files.confined_reads` (the server), it keeps that confinement: every
    file is opened by :func:`~napari_unwind.io._files.open_regular` and checked where the opened descriptor lies
    before tifffile reads it, so a file swapped for a symbolic link out after the open is never read.
    """

    def __init__(self, path: str, series: int, pages: list[int] | None, shape: tuple[int, int, int], dtype: Any,
                 files: list[str] | None = None):
        self.path = str(path)
        self.series = int(series)
        self.pages = None if pages is None else [int(p) for p in pages]
        self.files = None if files is None or all(str(f) == self.path for f in files) else [str(f) for f in files]
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)
        self.ndim = 3
        self.confine = current_confinement()  # opened confined: every read is (see _files.confined_reads)

    def __getitem__(self, key: Any) -> np.ndarray:
        try:
            return self._read(key)
        except (InvalidInputError, ConfinementError):
            raise  # a file outside the confinement: one line naming no path
        except Exception as exc:  # noqa: BLE001 - codecs raise their own types (DeflateError, ...) for damaged pages
            text = (str(exc).strip().splitlines() or [""])[0][:200]
            raise InvalidInputError(f"{self.path}: cannot decode its pages ({type(exc).__name__}: {text}); the file "
                                    "is damaged or was changed since it was opened: copy it again") from None

    @contextlib.contextmanager
    def _open(self, path: str) -> Iterator[tifffile.TiffFile]:
        if self.confine is None:
            with tifffile.TiffFile(path) as tif:
                yield tif
            return
        # tifffile reads the handle we opened and checked; it opens no other file (a multi-file OME series read
        # whole would name others by path: refused instead, read_tiff checked them and lists them in ``files``)
        with open_regular(path, "TIFF", confine=self.confine) as fh, \
                tifffile.TiffFile(fh, name=os.path.basename(path), _multifile=False) as tif:
            yield tif

    def _read(self, key: Any) -> np.ndarray:
        key = _expand_key(key, 3)
        if self.pages is None:
            with self._open(self.path) as tif:
                whole = tif.series[self.series].asarray().reshape(self.shape)
            return np.array(whole[key], dtype=self.dtype)
        planes = np.arange(self.shape[0])[key[0]]
        single = np.ndim(planes) == 0
        wanted = [int(z) for z in np.atleast_1d(planes)]
        out = np.empty((len(wanted),) + self.shape[1:], dtype=self.dtype)
        files = self.files or [self.path] * self.shape[0]
        for name in dict.fromkeys(files[z] for z in wanted):  # each file opened once, in the order first needed
            with self._open(name) as tif:
                for i, z in enumerate(wanted):
                    if files[z] == name:
                        out[i] = tif.pages[self.pages[z]].asarray().reshape(self.shape[1:])
        out = out[(slice(None),) + tuple(key[1:])]
        return out[0] if single else out


def tiff_channel_names(tif: tifffile.TiffFile, count: int) -> list[str]:
    """Channel names from ImageJ ``Labels`` (one per channel, or one per plane in ZCYX order) or OME ``Channel``
    names; ``c<k>`` where none is given."""
    names: list[str] = []
    try:
        if tif.is_imagej:
            labels = (tif.imagej_metadata or {}).get("Labels") or []
            if labels and len(labels) % count == 0:  # per channel, or per plane in ImageJ's ZCYX order
                names = [str(x) for x in labels[:count]]
        elif tif.is_ome:
            import xml.etree.ElementTree as ET

            root = ET.fromstring(tif.ome_metadata or "")
            chans = [el for el in root.iter() if el.tag.endswith("}Channel") or el.tag == "Channel"]
            if len(chans) == count:
                names = [str(el.get("Name") or "") for el in chans]
    except Exception:  # noqa: BLE001 - names are a convenience; malformed metadata gives c<k>
        names = []
    return [n if n else f"c{k}" for k, n in enumerate(names or [""] * count)]


def tiff_channel_count(path: Path, series: int = 0) -> int:
    """How many channels a TIFF series has along a ``C`` axis (1 when it has none). tifffile's complaints about a
    damaged file are kept, not printed: :func:`read_tiff` reports them."""
    with _tifffile_log(), tifffile.TiffFile(path) as tif:
        if not tif.series or not 0 <= series < len(tif.series):
            return 1
        s = tif.series[series]
        return int(dict(zip(s.axes, s.shape, strict=True)).get("C", 1))


def _channel_pages(s: Any, keep: list[tuple[str, int]], channel: Any,
                   path: Path) -> tuple[list[int], str, list[str]]:
    """The IFD index of every plane of one channel of a ``ZCYX``/``CZYX`` series, the channel's name and the file
    holding each plane."""
    plane_axes = [(a, n) for a, n in keep if a not in "YX"]
    count = dict(plane_axes)["C"]
    if isinstance(channel, bool) or not isinstance(channel, int | np.integer) or not 0 <= channel < count:
        raise InvalidInputError(f"{path} has channels 0..{count - 1}, got channel={channel!r}")
    pages = list(s.pages)
    nplanes = int(np.prod([n for _, n in plane_axes]))
    if len(pages) != nplanes or any(p is None for p in pages):
        raise InvalidInputError(f"{path}: its {count} channels are not stored one plane per page; save it as an "
                                "ImageJ hyperstack or OME-TIFF (Fiji: File > Save As > Tiff...)")
    shape = tuple(n for _, n in plane_axes)
    other = next(n for a, n in plane_axes if a != "C")
    index = []
    for z in range(other):
        pos = tuple(int(channel) if a == "C" else z for a, _ in plane_axes)
        index.append(pages[int(np.ravel_multi_index(pos, shape))])
    return [p.index for p in index], tiff_channel_names(s.parent, count)[int(channel)], _page_files(index, path)


def _page_files(pages: list[Any], path: Path) -> list[str]:
    """The file holding each of ``pages`` (a multi-file OME-TIFF's series spans several files); opened confined
    (the server), every other file is checked now, where it really lies, as each read checks it again."""
    files = [str(p.parent.filehandle.path) if p.parent is not None else str(path) for p in pages]
    confine = current_confinement()
    if confine is not None:
        for other in dict.fromkeys(f for f in files if f != str(path)):
            try:
                open_regular(other, "TIFF", confine=confine).close()
            except ConfinementError:
                raise ConfinementError(f"a file the OME-TIFF's metadata names lies outside {confine.where}: none of "
                                       "its voxels is read; keep every file of a multi-file OME-TIFF in the scan's "
                                       "folder") from None
    return files


def _colour_error(path: Path, axes: str, shape: tuple[int, ...], what: str) -> InvalidInputError:
    return InvalidInputError(
        f"{path} holds {what} (axes {axes}, shape {shape}); napari-unwind needs one grey value per voxel: "
        "convert it to grey first (Fiji: Image > Type > 8-bit or 16-bit, or Image > Color > Split Channels "
        "and save one channel)"
    )


def read_tiff(path: Path, *, series: int = 0, pattern: str | None = None,
              chunk_planes: int | None = None, channel: int | None = None) -> Volume:
    """Open a multi-page TIFF / BigTIFF (ImageJ hyperstack, OME-TIFF, plain page stack) lazily.

    A single-page 2D TIFF that belongs to a numbered series (``fish_0001.tif``, ``fish_0002.tif``...) opens the
    whole series through :func:`~napari_unwind.io.stack.read_stack`.

    Parameters
    ----------
    path : Path
        The TIFF file.
    series : int
        Which image series of the file (default the first).
    pattern : str, optional
        For a 2D slice: the glob choosing its stack (see :func:`~napari_unwind.io.stack.read_stack`).
    chunk_planes : int, optional
        Planes per dask chunk (default: about 64 MB per chunk).
    channel : int, optional
        For a multi-channel stack (ImageJ hyperstack ``ZCYX``, OME-TIFF ``CZYX``...): which channel (0-based); its
        name (ImageJ ``Labels``, OME ``Channel Name``, else ``c<k>``) is in ``metadata["channel"]``. See
        :func:`napari_unwind.io.open_channels` for all of them.

    Returns
    -------
    Volume
        Shape (N0, N1, N2) = (planes, rows, columns), geometry from the metadata (see the module docstring).

    Raises
    ------
    InvalidInputError
        Not a TIFF, a 2D image without numbered siblings, colour or multi-channel data, 4D data.
    """
    path = Path(path).expanduser().absolute()
    check_regular(path)
    with _tifffile_log() as messages:
        try:
            tif = tifffile.TiffFile(path)
            series_list = tif.series
        except (tifffile.TiffFileError, ValueError, struct.error, IndexError, KeyError, OverflowError) as exc:
            if isinstance(exc, InvalidInputError):
                raise
            raise InvalidInputError(f"{path} is not a readable TIFF file ({exc}); is the copy complete?") from None
    with tif:
        if not series_list:
            raise InvalidInputError(f"{path} holds no image")
        if not 0 <= series < len(series_list):
            raise InvalidInputError(f"{path} holds image series 0..{len(series_list) - 1}, got series={series}")
        s = series_list[series]
        axes, shape = s.axes, tuple(int(n) for n in s.shape)
        _check_complete(tif, s, path, messages)
        keep = [(a, n) for a, n in zip(axes, shape, strict=True) if n > 1 or a in "YX"]
        kaxes = "".join(a for a, _ in keep)
        kshape = tuple(n for _, n in keep)
        if "Y" not in kaxes or "X" not in kaxes:
            raise InvalidInputError(f"{path}: cannot find the image rows and columns in axes {axes!r}")
        planes = [(a, n) for a, n in keep if a not in "YXS"]
        if not planes:
            if pattern is not None or len(numbered_siblings(path)) > 1:
                return reader_for("stack")(path, pattern=pattern)  # through the registry: tiff never imports stack
            colour = f" of {dict(keep)['S']} samples per pixel (colour)" if "S" in kaxes else ""
            raise InvalidInputError(
                f"{path} is a single 2D image{colour} (shape {shape}); a volume needs 3D: a multi-page TIFF, or "
                f"numbered 2D slices in one folder (e.g. {path.stem}_0000{path.suffix}, "
                f"{path.stem}_0001{path.suffix}, ...)"
            )
        if "S" in kaxes:
            n = dict(keep)["S"]
            raise _colour_error(path, axes, shape, "RGB colour images" if n in (3, 4) else f"{n} samples per pixel")
        if len(planes) == 1 and planes[0][0] == "C":
            raise _colour_error(path, axes, shape, f"{planes[0][1]} channels and one plane each")
        pick = None
        if len(planes) == 2 and any(a == "C" for a, _ in planes) and channel is not None:
            pick = _channel_pages(s, keep, channel, path)
            keep = [(a, n) for a, n in keep if a != "C"]
            kaxes = "".join(a for a, _ in keep)
            kshape = tuple(n for _, n in keep)
        elif channel is not None:
            raise InvalidInputError(f"{path} has no channel axis (axes {axes}), got channel={channel!r}")
        elif len(planes) > 1 and any(a == "C" for a, _ in planes):
            raise InvalidInputError(
                f"{path} holds {dict(planes)['C']} channels (axes {axes}, shape {shape}); straighten them all with "
                "`unwind straighten` (napari_unwind.io.open_channels), or pick one with --input-channel NAME "
                "(channel= in Python)"
            )
        if len(planes) > 1 and pick is None:
            raise InvalidInputError(
                f"{path} is {len(planes) + 2}D (axes {axes}, shape {shape}); napari-unwind opens one 3D volume: "
                "export one time point (Fiji: Image > Duplicate... with one frame)"
            )
        if kaxes[-2:] != "YX":
            raise InvalidInputError(f"{path}: unsupported axis order {axes!r}; expected planes, rows, columns")
        n, ny, nx = kshape[0], kshape[-2], kshape[-1]
        dtype = np.dtype(s.dtype)
        geometry = tiff_geometry(tif, series, path=path)
        meta: dict[str, Any] = {"axes": axes, "series": series, "geometry_from": geometry["from"],
                                "is_imagej": tif.is_imagej, "is_ome": tif.is_ome, "is_bigtiff": tif.is_bigtiff}
        if tif.is_imagej:
            meta["imagej"] = {k: v for k, v in (tif.imagej_metadata or {}).items() if isinstance(v, (str, int, float))}
        if geometry.get("straightening"):
            meta["unwind"] = {"straightening": geometry["straightening"]}
        stat = os.stat(path)
        depth = int(chunk_planes) if chunk_planes else slab_depth((ny, nx), dtype)
        if depth < 1:
            raise InvalidInputError(f"chunk_planes must be >= 1, got {chunk_planes}")
        chunks = (min(depth, n), ny, nx)
        offset = s.dataoffset
        out_dtype = {np.dtype(bool): np.dtype("uint8"), np.dtype("float16"): np.dtype("float32")}.get(dtype, dtype)
        if pick is not None:
            meta["channel"] = pick[1]
            meta["memmap"] = False
            planes_arr = _TiffPlanes(str(path), series, pick[0], (n, ny, nx), out_dtype, pick[2])

            def build_channel(planes_arr: Any = planes_arr) -> da.Array:
                import dask.array as da
                from dask.base import tokenize

                token = tokenize(str(path), stat.st_mtime_ns, stat.st_size, series, channel)
                return da.from_array(planes_arr, chunks=chunks, name=f"tiff-{token}", asarray=False, fancy=False,
                                     meta=np.empty((0, 0, 0), dtype=out_dtype))

            data = LazyArray(build_channel, (n, ny, nx), out_dtype, chunks)
        elif offset is not None and out_dtype == dtype and not s.pages[0].is_tiled:
            arr = RawFileArray(path, dtype.newbyteorder(tif.byteorder), (n, ny, nx), int(offset))
            data = arr.to_lazy(depth=chunks[0], name="tiff")  # dask built on first use
            meta["memmap"] = True
        else:
            pages = list(s.pages)
            per_page = (len(pages) == n and all(p is not None for p in pages)
                        and int(np.prod(pages[0].shape)) == ny * nx)
            index = [p.index for p in pages] if per_page else None
            files = _page_files([p for p in pages if p is not None], path)  # checks others when confined
            files = files if per_page else None
            planes_arr = _TiffPlanes(str(path), series, index, (n, ny, nx), out_dtype, files)
            plane_chunks = chunks if per_page else (n, ny, nx)

            def build(planes_arr: Any = planes_arr, plane_chunks: tuple = plane_chunks) -> da.Array:
                import dask.array as da
                from dask.base import tokenize

                token = tokenize(str(path), stat.st_mtime_ns, stat.st_size, series)
                return da.from_array(planes_arr, chunks=plane_chunks, name=f"tiff-{token}", asarray=False,
                                     fancy=False, meta=np.empty((0, 0, 0), dtype=out_dtype))

            data = LazyArray(build, (n, ny, nx), out_dtype, plane_chunks)  # dask built on first use
            meta["memmap"] = False
    return Volume(data, spacing=geometry["spacing"], unit=geometry["unit"], origin=geometry["origin"],
                  source=str(path), format="tiff", metadata=meta)


# ------------------------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------------------------
def _zstd_available() -> bool:
    try:
        tifffile.TIFF.COMPRESSORS[50000](np.zeros(16, np.uint8))
    except Exception:  # noqa: BLE001 - KeyError, ImportError: neither imagecodecs nor Python 3.14's compression.zstd
        return False
    return True


def _compression(compression: str | None) -> str | None:
    if compression is None or str(compression).lower() in ("none", ""):
        return None
    c = str(compression).lower()
    if c in ("zlib", "deflate", "adobe_deflate"):
        return "zlib"
    if c == "zstd":
        if not _zstd_available():
            raise InvalidInputError(
                "zstd TIFF compression needs the imagecodecs package (pip install imagecodecs); "
                "use compression='zlib', which Fiji also reads"
            )
        return "zstd"
    raise InvalidInputError(f"unknown TIFF compression {compression!r}; use None, 'zlib' or 'zstd'")


def stored_geometry_json(volume: Volume) -> str:
    """The exact geometry as the one-line JSON stored under ``unwind`` (spacing and origin in axis order), with
    the straightening record of a straight volume (:mod:`napari_unwind.io._straight_record`)."""
    stored: dict[str, Any] = {"spacing": [float(v) for v in volume.spacing], "unit": volume.unit,
                              "origin": [float(v) for v in volume.origin], "axes": "ZYX"}
    record = straightening_record(volume)
    if record is not None:
        stored["straightening"] = json.loads(record_text(record))
    return json.dumps(stored)


#: The largest X/YResolution a TIFF holds: a fraction of two 32-bit whole numbers.
_MAX_RESOLUTION = 2**32 - 1


def _per(length: float) -> float:
    """A resolution of ``1 / length`` pixels per unit, or 0 (no resolution) below the fraction's smallest step
    (tifffile would write 1/4294967295, read back as another size); the exact size is in the JSON geometry."""
    return 1.0 / length if length <= _MAX_RESOLUTION else 0.0


def _check_resolution(volume: Volume, per_unit: float, unit: str) -> None:
    """Refuse a pixel size whose X/YResolution (``1 / (size * per_unit)`` pixels per ``unit``) is too large for the
    TIFF's fraction of 32-bit numbers (tifffile fails with an unrelated message), before anything is written."""
    for axis in (1, 2):
        size = volume.spacing[axis]
        length = size * per_unit  # 0 when the product underflows
        if length * _MAX_RESOLUTION < 1.0:
            resolution = f"{1.0 / length:.4g}" if length > 0 else "an infinite resolution"
            raise InvalidInputError(
                f"a TIFF stores the voxel size of axis{axis} ({size!r} {volume.unit or 'unit not recorded'}) as a "
                f"resolution in pixels per {unit}, a fraction of 32-bit whole numbers, which cannot hold "
                f"{resolution} (at most {_MAX_RESOLUTION:,}); choose a larger unit or another "
                "format (OME-Zarr, NRRD, .dat)"
            )


def imagej_options(volume: Volume) -> dict[str, Any]:
    """``tifffile.imwrite`` keywords making an ImageJ file with the volume's calibration (Fiji reads it)."""
    _check_resolution(volume, 1.0, IMAGEJ_UNITS.get(volume.unit, volume.unit) if volume.unit else "pixel")
    sz, sy, sx = volume.spacing
    metadata: dict[str, Any] = {"axes": "ZYX", "spacing": sz}
    if volume.unit:
        metadata["unit"] = IMAGEJ_UNITS.get(volume.unit, volume.unit)
    for a, o, s in zip("zyx", volume.origin, volume.spacing, strict=True):
        if o:
            metadata[f"{a}origin"] = -o / s  # ImageJ: the origin's position in pixels
    metadata["unwind"] = stored_geometry_json(volume)
    return {"imagej": True, "resolution": (_per(sx), _per(sy)), "metadata": metadata}


def plain_options(volume: Volume) -> dict[str, Any]:
    """``tifffile.imwrite`` keywords for a plain TIFF: resolution in pixels/cm plus the exact JSON geometry."""
    _, sy, sx = volume.spacing
    options: dict[str, Any] = {"photometric": "minisblack",
                               "metadata": {"axes": "ZYX", "unwind": json.loads(stored_geometry_json(volume))}}
    if volume.unit in _METERS:
        cm = _METERS[volume.unit] / _METERS["centimeter"]
        _check_resolution(volume, cm, "centimetre")
        options.update(resolution=(_per(sx * cm), _per(sy * cm)), resolutionunit="CENTIMETER")
    else:
        _check_resolution(volume, 1.0, "pixel")
        options.update(resolution=(_per(sx), _per(sy)), resolutionunit="NONE")
    return options


class _Aborted(Exception):
    pass


def _write_pages(path: Path, volume: Volume, *, bigtiff: bool, imagej: bool,
                 options: dict[str, Any], shape: tuple[int, ...] | None = None,
                 slab: Any = None) -> Iterator[Progress]:
    """Stream ``volume`` plane by plane into one TIFF series, yielding progress per slab.

    tifffile consumes an iterator of pages in a single ``write`` call, so it runs in a worker thread fed
    through a one-slab queue while this generator computes the next slab and reports progress. A hyperstack
    passes its series ``shape`` (``(Z, C, Y, X)``) and ``slab(z0, z1)``, the planes ``z0 .. z1 - 1`` of ``volume``
    (its pages in file order, shape (Z * C, Y, X)); ``z0`` and ``z1`` are then multiples of C.
    """
    n = volume.shape[0]
    depth = slab_depth(volume.shape[1:], volume.dtype)
    if shape is not None and len(shape) == 4:
        depth = max(1, depth // shape[1]) * shape[1]  # whole Z planes of every channel
    total = -(-n // depth)
    plane_bytes = volume.shape[1] * volume.shape[2] * volume.dtype.itemsize
    feed: queue.Queue = queue.Queue(maxsize=1)
    failure: list[BaseException] = []

    def pages() -> Iterator[np.ndarray]:
        while True:
            item = feed.get()
            if item is None:
                return
            if item is _Aborted:
                raise _Aborted
            yield from item

    def work() -> None:
        try:
            with tifffile.TiffWriter(path, bigtiff=bigtiff, imagej=imagej) as tw:
                tw.write(pages(), shape=volume.shape if shape is None else shape, dtype=volume.dtype, **options)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the generator's thread
            failure.append(_short_write(exc, path, plane_bytes))

    def put(item: Any) -> bool:
        while not failure and worker.is_alive():
            try:
                feed.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    worker = threading.Thread(target=work, name=f"write_tiff {path.name}", daemon=True)
    worker.start()
    try:
        for i, z0 in enumerate(range(0, n, depth)):
            z1 = min(n, z0 + depth)
            planes = volume.data[z0:z1].compute() if slab is None else slab(z0, z1)
            slab_ = np.ascontiguousarray(planes, dtype=volume.dtype)
            del planes
            if not put(slab_):
                break
            del slab_
            yield Progress("write tiff", i + 1, total, f"planes {z0}-{z1 - 1} of {n}")
        put(None)
        worker.join()
    except BaseException:
        while True:  # stop the writer: empty the queue, then tell it to give up
            try:
                feed.get_nowait()
            except queue.Empty:
                break
        feed.put(_Aborted)
        worker.join()
        raise
    if failure:
        exc = failure[0]
        if isinstance(exc, OSError):
            raise OutputError(f"cannot write {path.with_name(final_name(path))}: {exc.strerror or exc}") from exc
        raise exc


def _short_write(exc: BaseException, path: Path, plane_bytes: int) -> BaseException:
    """numpy reports a write cut short by a full disk without its errno ("N requested and M written"): when the
    disk has no room left for a plane, say ENOSPC, so the caller reports a full disk."""
    if not isinstance(exc, OSError) or exc.errno is not None or "requested and" not in str(exc):
        return exc
    try:
        free = shutil.disk_usage(path.parent).free
    except OSError:
        return exc
    if free >= plane_bytes + 2**16:
        return exc
    full = OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({exc})")
    full.__cause__ = exc
    return full


def write_tiff(
    volume: Volume,
    path: Path,
    *,
    compression: str | None = None,
    bigtiff: bool | None = None,
    imagej: bool | None = None,
    compression_level: int | None = None,
) -> Iterator[Progress]:
    """Write ``volume`` as a multi-page TIFF, page by page.

    uint8, uint16 and float32 volumes below 4 GB become an ImageJ hyperstack: Fiji opens it with the voxel size
    (X/YResolution = 1 / spacing of axis2/axis1, description ``spacing`` = axis0 spacing, ``unit`` as ImageJ
    spells it: ``micron``, ``mm``...). Other voxel types (int8, int16, int32, uint32, float64) and larger volumes
    become a plain TIFF / BigTIFF with the resolution in pixels per centimetre (Fiji: File > Import >
    Bio-Formats); every file also stores the exact spacing, unit and origin as JSON, which :func:`read_tiff`
    prefers, so a round trip keeps type and geometry exactly.

    Parameters
    ----------
    volume : Volume
        What to write.
    path : Path
        The file to create.
    compression : {None, "zlib", "zstd"}
        None (default) keeps the file memory-mappable (fastest to open). "zlib" (deflate) is read by ImageJ and
        Fiji. "zstd" needs the imagecodecs package and is not read by ImageJ's own TIFF reader.
    bigtiff : bool, optional
        Default: BigTIFF only when the voxels exceed 4 GB (``BIGTIFF_THRESHOLD``). True forces BigTIFF (then
        not an ImageJ file); False refuses volumes that need it.
    imagej : bool, optional
        Default: an ImageJ hyperstack whenever the type and size allow it. True insists (an error otherwise),
        False writes a plain TIFF.
    compression_level : int, optional
        zlib level 1-9 (zstd 1-22); default the codec's own (zlib 6). Level 1 is about twice as fast and
        compresses CT data nearly as well.

    Yields
    ------
    Progress
        One record per slab of planes.
    """
    name = final_name(path)
    if "{" in name and "}" in name:
        raise InvalidInputError(
            f"{name} looks like a slice name pattern; to write numbered 2D slices pass format='stack'"
        )
    codec = _compression(compression)
    dtype = volume.dtype
    big_needed = volume.nbytes > BIGTIFF_THRESHOLD
    gib = volume.nbytes / 2**30
    if bigtiff is False and big_needed:
        raise InvalidInputError(f"{gib:.1f} GiB of voxels need BigTIFF; pass bigtiff=None (automatic) or True")
    big = bool(bigtiff) or big_needed
    ij_possible = dtype in IMAGEJ_DTYPES and not big
    if imagej and not ij_possible:
        why = (f"ImageJ hyperstacks hold uint8, uint16 or float32, not {dtype}" if dtype not in IMAGEJ_DTYPES
               else "ImageJ hyperstacks cannot be BigTIFF")
        raise InvalidInputError(f"cannot write {Path(path).name} as ImageJ: {why}; pass imagej=None")
    use_imagej = ij_possible if imagej is None else bool(imagej)
    if big_needed and dtype in IMAGEJ_DTYPES and imagej is None and bigtiff is None:
        warnings.warn(
            f"{gib:.1f} GiB of voxels exceed the 4 GB of a classic TIFF: writing a plain BigTIFF, which ImageJ's "
            "own TIFF reader cannot open; open it in Fiji with File > Import > Bio-Formats (or write OME-Zarr)",
            stacklevel=2,
        )
    options = imagej_options(volume) if use_imagej else plain_options(volume)
    if codec is not None:
        options["compression"] = codec
        options["maxworkers"] = max(1, min(4, os.cpu_count() or 1))  # compress the strips of a page in parallel
        if compression_level is not None:
            options["compressionargs"] = {"level": int(compression_level)}
    if use_imagej:
        options.pop("imagej")
    yield from _write_pages(Path(path), volume, bigtiff=big, imagej=use_imagej, options=options)
