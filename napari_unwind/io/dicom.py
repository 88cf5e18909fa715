"""DICOM series: a folder of slice files (or one multi-frame file), through pydicom.

Reading
-------
Every file of the folder is read once without its pixels (``stop_before_pixels``) and grouped by
SeriesInstanceUID. A folder holding several series needs a choice (``series=``, command line ``--series``):
otherwise :class:`~napari_unwind.errors.SeriesSelectionError` lists them all. The slices are sorted by their
ImagePositionPatient projected on the slice normal (the cross product of the two ImageOrientationPatient rows),
falling back to InstanceNumber when positions are missing. Array axes are (slice, row, column):

- axis0 spacing: the mean distance between consecutive slice positions (a warning gives the largest deviation
  when they are not uniform; without positions: SpacingBetweenSlices, else SliceThickness, else 1);
- axis1, axis2 spacing: PixelSpacing (row spacing, column spacing);
- origin: the first slice's position expressed along (normal, column direction, row direction), which is
  (z, y, x) for the usual orientation ``[1, 0, 0, 0, 1, 0]``;
- unit: millimetre, always.

RescaleSlope/RescaleIntercept are applied. The voxel type stays integer when the slope and intercept are integers
and the scaled range of the stored bits fits an integer type (e.g. 12-bit unsigned CT with intercept -1024 ->
int16; 16-bit unsigned with intercept -1024 -> int32); otherwise it is float32.

Pixel data are read lazily, one dask chunk per slice; compressed transfer syntaxes are decoded by pydicom's
plugins, and a syntax no installed plugin decodes is reported when the series is opened, not later.

Writing
-------
One file per slice (``IM00001.dcm``...) in a new folder: Explicit VR Little Endian, CT Image Storage (Modality
CT) for 16-bit data and Secondary Capture Image Storage (Modality OT) for 8-bit data (the CT image module allows
only 16 bits), fresh Study/Series/SOP Instance/Frame of Reference UIDs, ImageOrientationPatient
``[1, 0, 0, 0, 1, 0]`` and ImagePositionPatient ``(o2, o1, o0 + k * s0)`` for slice k. 8- and 16-bit integers are
stored as they are; 32-bit integers and floats are stored as 16-bit integers with RescaleSlope/RescaleIntercept,
exactly when their values are integers spanning at most 65536 values, otherwise quantised into 65536 levels (a
warning gives the largest change of value).

DICOM lengths are millimetres: a volume in another unit is converted (micrometres x 0.001...). A micrometre volume
therefore comes back from :func:`read_dicom` in millimetres, with the same physical size.
"""

from __future__ import annotations

import datetime
import os
import warnings
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import dask.array as da
import numpy as np
import pydicom
from dask.base import tokenize
from pydicom.dataset import Dataset, FileMetaDataset, validate_file_meta
from pydicom.errors import InvalidDicomError
from pydicom.pixels import get_decoder, pixel_array
from pydicom.uid import (
    PYDICOM_IMPLEMENTATION_UID,
    CTImageStorage,
    ExplicitVRLittleEndian,
    SecondaryCaptureImageStorage,
    generate_uid,
)
from pydicom.valuerep import format_number_as_ds

from ..errors import InvalidInputError, OutputError, SeriesSelectionError
from ..progress import Progress
from ._atomic import final_name
from ._files import ConfinementError, current_confinement, open_regular
from ._straight_record import parse_record, record_text, straightening_record
from ._volume import Volume

__all__ = ["read_dicom", "write_dicom", "list_series"]

_HEADER_TAGS = [
    "SOPClassUID", "SeriesInstanceUID", "SeriesDescription", "SeriesNumber", "StudyInstanceUID", "Modality",
    "Rows", "Columns", "SamplesPerPixel", "PhotometricInterpretation", "BitsAllocated", "BitsStored",
    "PixelRepresentation", "NumberOfFrames", "ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing",
    "ImagerPixelSpacing", "SliceThickness", "SpacingBetweenSlices", "InstanceNumber", "RescaleSlope",
    "RescaleIntercept", "SharedFunctionalGroupsSequence", "PerFrameFunctionalGroupsSequence",
]
_UNIT_TO_MM = {"meter": 1000.0, "centimeter": 10.0, "millimeter": 1.0, "micrometer": 1e-3, "nanometer": 1e-6}
_ORIENTATION_TOL = 1e-4
_SPACING_REL_TOL = 0.01


# ------------------------------------------------------------------------------------------------------------------
# header scan
# ------------------------------------------------------------------------------------------------------------------
@dataclass
class _Image:
    """What the reader needs of one image file (one slice, or one frame of a multi-frame file)."""

    path: Path
    frame: int | None
    uid: str
    number: int | None
    description: str
    rows: int
    cols: int
    samples: int
    bits_allocated: int
    bits_stored: int
    signed: bool
    position: np.ndarray | None
    orientation: np.ndarray | None
    pixel_spacing: tuple[float, float] | None
    thickness: float | None
    between: float | None
    instance: int | None
    slope: float
    inter: float
    transfer_syntax: str
    modality: str
    study: str


def _float_list(value: Any, n: int) -> np.ndarray | None:
    try:
        arr = np.asarray([float(v) for v in value], dtype=float)
    except (TypeError, ValueError):
        return None
    return arr if arr.shape == (n,) and np.all(np.isfinite(arr)) else None


def _number(value: Any) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def _first(seq: Any, attr: str) -> Any:
    """``seq[0].attr`` of a functional group (sequence) when present."""
    if seq is None or len(seq) == 0:
        return None
    return getattr(seq[0], attr, None)


class _Unreadable(Exception):
    """A file that claims to be DICOM (it has the ``DICM`` marker) but cannot be parsed."""


def _read_header(path: Path) -> Dataset | None:
    """The header of ``path`` without pixel data; None when it is not DICOM at all.

    Raises ``_Unreadable`` for a file marked as DICOM that cannot be parsed, or an image file whose header stops
    before its size and series are known (pydicom reads truncated files without complaint). Opened under
    :func:`~napari_unwind.io._files.confined_reads`, a file outside the confinement is a ConfinementError.
    """
    try:
        fh = open_regular(path, "DICOM", confine=current_confinement())
    except ConfinementError:
        raise
    except OSError:
        return None  # gone since the folder was listed, or unreadable: not a slice of the series
    with fh:
        return _header_of(path, fh)


def _header_of(path: Path, fh: Any) -> Dataset | None:
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            ds = pydicom.dcmread(fh, stop_before_pixels=True, specific_tags=_HEADER_TAGS)
        if "Rows" not in ds or "SeriesInstanceUID" not in ds:
            sop = str(getattr(getattr(ds, "file_meta", None), "MediaStorageSOPClassUID", "")
                      or getattr(ds, "SOPClassUID", ""))
            if sop and "Image Storage" in pydicom.uid.UID(sop).name:
                why = "; ".join(str(w.message) for w in caught[:2]) or "Rows or SeriesInstanceUID missing"
                raise _Unreadable(f"{path.name} (an incomplete image header: {why})")
        return ds
    except InvalidDicomError as exc:
        named = path.suffix.lower() in (".dcm", ".dicom", ".ima")
        if not named and path.suffix:
            return None
        try:  # DICOM without the 128-byte preamble (old exports)
            fh.seek(0)
            ds = pydicom.dcmread(fh, stop_before_pixels=True, specific_tags=_HEADER_TAGS, force=True)
        except Exception as forced:  # noqa: BLE001 - pydicom raises many types for garbage
            if named:  # named as DICOM but unreadable: damaged, not some other file
                raise _Unreadable(f"{path.name} ({type(forced).__name__}: {forced})") from None
            return None
        if "SeriesInstanceUID" in ds and "Rows" in ds:
            return ds
        if named:
            raise _Unreadable(f"{path.name} ({exc})") from None
        return None
    except _Unreadable:
        raise
    except Exception as exc:  # truncated or corrupt file: pydicom raises many types
        try:
            fh.seek(128)
            marked = fh.read(4) == b"DICM"
        except OSError:
            marked = False
        if marked:
            raise _Unreadable(f"{path.name} ({type(exc).__name__}: {exc})") from None
        return None


def _images_of(path: Path, ds: Dataset) -> list[_Image]:
    """One :class:`_Image` per slice (per frame of a multi-frame file), or [] when ``ds`` holds no image.

    Raises ``_Unreadable`` for a header whose values are not what their tags hold (a damaged file: several values
    in a single-valued tag, text in a number).
    """
    try:
        return _images_of_header(path, ds)
    except (TypeError, ValueError, OverflowError, AttributeError) as exc:
        raise _Unreadable(f"{path.name} (a damaged header: {type(exc).__name__}: {exc})") from None


def _images_of_header(path: Path, ds: Dataset) -> list[_Image]:
    if "Rows" not in ds or "Columns" not in ds or "SeriesInstanceUID" not in ds:
        return []
    ts = str(getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", ExplicitVRLittleEndian))
    spacing = _float_list(getattr(ds, "PixelSpacing", None), 2)
    if spacing is None:
        spacing = _float_list(getattr(ds, "ImagerPixelSpacing", None), 2)
    number = getattr(ds, "SeriesNumber", None)
    common = dict(
        path=path, uid=str(ds.SeriesInstanceUID), number=int(number) if number not in (None, "") else None,
        description=str(getattr(ds, "SeriesDescription", "") or ""), rows=int(ds.Rows), cols=int(ds.Columns),
        samples=int(getattr(ds, "SamplesPerPixel", 1) or 1), bits_allocated=int(getattr(ds, "BitsAllocated", 16)),
        bits_stored=int(getattr(ds, "BitsStored", getattr(ds, "BitsAllocated", 16))),
        signed=int(getattr(ds, "PixelRepresentation", 0) or 0) == 1, transfer_syntax=ts,
        modality=str(getattr(ds, "Modality", "") or ""), study=str(getattr(ds, "StudyInstanceUID", "") or ""),
    )
    slope = _number(getattr(ds, "RescaleSlope", None))
    inter = _number(getattr(ds, "RescaleIntercept", None))
    frames = int(getattr(ds, "NumberOfFrames", 1) or 1)
    instance = getattr(ds, "InstanceNumber", None)
    instance = int(instance) if instance not in (None, "") else None
    if frames == 1:
        return [_Image(
            frame=None, position=_float_list(getattr(ds, "ImagePositionPatient", None), 3),
            orientation=_float_list(getattr(ds, "ImageOrientationPatient", None), 6),
            pixel_spacing=None if spacing is None else (float(spacing[0]), float(spacing[1])),
            thickness=_number(getattr(ds, "SliceThickness", None)),
            between=_number(getattr(ds, "SpacingBetweenSlices", None)), instance=instance,
            slope=1.0 if slope is None else slope, inter=0.0 if inter is None else inter, **common,
        )]
    # multi-frame: geometry from the functional groups where present, else from the top level
    shared = getattr(ds, "SharedFunctionalGroupsSequence", None)
    shared = shared[0] if shared else Dataset()
    per_frame = getattr(ds, "PerFrameFunctionalGroupsSequence", None) or [Dataset()] * frames
    images = []
    for f in range(frames):
        fg = per_frame[f] if f < len(per_frame) else Dataset()

        def group(name: str, attr: str, fg: Dataset = fg) -> Any:
            value = _first(getattr(fg, name, None), attr)
            return value if value is not None else _first(getattr(shared, name, None), attr)

        position = _float_list(group("PlanePositionSequence", "ImagePositionPatient"), 3)
        orientation = _float_list(group("PlaneOrientationSequence", "ImageOrientationPatient"), 6)
        if orientation is None:
            orientation = _float_list(getattr(ds, "ImageOrientationPatient", None), 6)
        sp = _float_list(group("PixelMeasuresSequence", "PixelSpacing"), 2)
        sp = spacing if sp is None else sp
        f_slope = _number(group("PixelValueTransformationSequence", "RescaleSlope"))
        f_inter = _number(group("PixelValueTransformationSequence", "RescaleIntercept"))
        images.append(_Image(
            frame=f, position=position, orientation=orientation,
            pixel_spacing=None if sp is None else (float(sp[0]), float(sp[1])),
            thickness=_number(group("PixelMeasuresSequence", "SliceThickness")) or _number(
                getattr(ds, "SliceThickness", None)),
            between=_number(group("PixelMeasuresSequence", "SpacingBetweenSlices")) or _number(
                getattr(ds, "SpacingBetweenSlices", None)),
            instance=f + 1,
            slope=f_slope if f_slope is not None else (1.0 if slope is None else slope),
            inter=f_inter if f_inter is not None else (0.0 if inter is None else inter), **common,
        ))
    return images


def _scan_folder(folder: Path, *, strict: bool = True) -> dict[str, list[_Image]]:
    """Images of every series in ``folder`` (not recursive), keyed by SeriesInstanceUID.

    A file marked or named as DICOM that cannot be read may be a slice of the series (damaged or cut short):
    reading without it would give a volume with a slice missing, so it is an error (``strict``), or a warning
    when only listing the series.
    """
    files = sorted(p for p in folder.iterdir()
                   if p.is_file() and not p.name.startswith(".") and p.name.upper() != "DICOMDIR")
    by_uid: dict[str, list[_Image]] = {}
    unreadable: list[str] = []
    for f in files:
        try:
            ds = _read_header(f)
            images = [] if ds is None else _images_of(f, ds)
        except _Unreadable as exc:
            unreadable.append(str(exc))
            continue
        for image in images:
            by_uid.setdefault(image.uid, []).append(image)
    if unreadable:
        shown = "; ".join(unreadable[:5]) + (f"; and {len(unreadable) - 5} more" if len(unreadable) > 5 else "")
        shown = " ".join(shown.split())  # one line
        if strict:
            raise InvalidInputError(
                f"{len(unreadable)} DICOM file(s) in {folder} cannot be read: {shown}; a damaged slice would leave "
                "a gap in the volume: copy the files again, or move them out of the folder to read the rest")
        warnings.warn(f"{len(unreadable)} DICOM file(s) in {folder} could not be read: {shown}", stacklevel=3)
    return by_uid


def _describe(uid: str, images: list[_Image]) -> str:
    first = images[0]
    sizes = Counter((im.rows, im.cols) for im in images)
    size = " / ".join(f"{r} x {c}" for r, c in sizes)
    number = "?" if first.number is None else first.number
    return (f"SeriesNumber {number}, {first.description or '(no description)'!r}, {first.modality or '?'}, "
            f"{len(images)} slices of {size} pixels, UID {uid}")


def _ordered_series(by_uid: dict[str, list[_Image]]) -> list[str]:
    return sorted(by_uid, key=lambda u: (by_uid[u][0].number is None, by_uid[u][0].number or 0, u))


def list_series(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Describe the DICOM series in a folder (or in the folder of a file), in the order ``series=<index>`` uses.

    Returns
    -------
    list of dict
        One dict per series with ``index``, ``uid``, ``number``, ``description``, ``modality``, ``slices`` and
        ``size`` (rows, columns).
    """
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    by_uid = _scan_folder(folder, strict=False)
    out = []
    for i, uid in enumerate(_ordered_series(by_uid)):
        first = by_uid[uid][0]
        out.append({"index": i, "uid": uid, "number": first.number, "description": first.description,
                    "modality": first.modality, "slices": len(by_uid[uid]), "size": (first.rows, first.cols)})
    return out


def _choose_series(by_uid: dict[str, list[_Image]], series: Any, folder: Path) -> str:
    order = _ordered_series(by_uid)
    table = {uid: _describe(uid, by_uid[uid]) for uid in order}
    listing = "; ".join(f"[{i}] {table[uid]}" for i, uid in enumerate(order))  # one line, as every error
    how = ("choose one with series=<UID, SeriesNumber or 0-based index> (command line: --series ...); "
           "a number is taken as a SeriesNumber when one series has it, else as an index")
    if series is None:
        if len(order) == 1:
            return order[0]
        raise SeriesSelectionError(f"{folder} holds {len(order)} DICOM series; {how}: {listing}", table)
    if isinstance(series, bool):
        raise InvalidInputError(f"series must be a UID, a SeriesNumber or an index, got {series!r}")
    if isinstance(series, str):
        key = series.strip()
        if key in by_uid:
            return key
        try:
            series = int(key)
        except ValueError:
            raise SeriesSelectionError(
                f"no series with UID {key!r} in {folder}; {how}: {listing}", table) from None
    if isinstance(series, int | np.integer):
        value = int(series)
        numbered = [uid for uid in order if by_uid[uid][0].number == value]
        if len(numbered) == 1:
            return numbered[0]
        if len(numbered) > 1:
            raise SeriesSelectionError(
                f"{len(numbered)} series in {folder} have SeriesNumber {value}; choose by UID or index: {listing}",
                table)
        if 0 <= value < len(order):
            return order[value]
        raise SeriesSelectionError(
            f"no series with SeriesNumber or index {value} in {folder}; {how}: {listing}", table)
    raise InvalidInputError(f"series must be a UID (str), a SeriesNumber or an index (int), got {series!r}")


# ------------------------------------------------------------------------------------------------------------------
# geometry and voxel type
# ------------------------------------------------------------------------------------------------------------------
def _check_consistent(images: list[_Image], folder: Path, uid: str) -> None:
    sizes = Counter((im.rows, im.cols) for im in images)
    if len(sizes) > 1:
        detail = ", ".join(
            f"{r} x {c} ({n} files, e.g. {next(im.path.name for im in images if (im.rows, im.cols) == (r, c))})"
            for (r, c), n in sizes.most_common())
        raise InvalidInputError(
            f"the slices of series {uid} in {folder} have different sizes: {detail}; "
            "remove the odd files (a localizer or a reformat?) or move them into another folder"
        )
    layouts = Counter((im.bits_allocated, im.signed, im.samples) for im in images)
    if len(layouts) > 1:
        raise InvalidInputError(
            f"the slices of series {uid} in {folder} store pixels differently "
            f"(BitsAllocated, signed, SamplesPerPixel: {dict(layouts)}); remove the odd files"
        )
    first = images[0]
    if first.samples != 1:
        raise InvalidInputError(
            f"series {uid} in {folder} is colour ({first.samples} samples per pixel); convert it to grey first")
    if first.bits_allocated not in (8, 16, 32):
        raise InvalidInputError(
            f"series {uid} in {folder} has BitsAllocated {first.bits_allocated}; napari-unwind reads 8, 16 and 32 "
            "bit greyscale images")
    for ts in sorted({im.transfer_syntax for im in images}):
        try:
            decoder = get_decoder(ts)
        except NotImplementedError:
            raise InvalidInputError(
                f"series {uid} in {folder} uses transfer syntax {ts}, which pydicom cannot decode; "
                "convert it to an uncompressed syntax (e.g. `gdcmconv --raw` or `dcmdjpeg`)") from None
        if not decoder.is_available:
            raise InvalidInputError(
                f"series {uid} in {folder} is compressed ({pydicom.uid.UID(ts).name}) and no installed plugin "
                f"decodes it; install one of: {'; '.join(decoder.missing_dependencies)}")


def _sort_and_space(images: list[_Image], folder: Path, uid: str) -> tuple[list[_Image], float, np.ndarray | None,
                                                                           dict[str, Any]]:
    """Sort the slices; return them, the axis0 spacing, the slice-normal frame (3x3 rows: normal, col, row) or
    None when positions are missing, and notes for the metadata."""
    notes: dict[str, Any] = {}
    have_geometry = all(im.position is not None and im.orientation is not None for im in images)
    if have_geometry:
        iop = images[0].orientation
        for im in images[1:]:
            if np.max(np.abs(im.orientation - iop)) > _ORIENTATION_TOL:
                raise InvalidInputError(
                    f"series {uid} in {folder} mixes slice orientations ({im.path.name} differs from "
                    f"{images[0].path.name}); remove the odd files (a localizer?)")
        row, col = iop[:3], iop[3:]
        normal = np.cross(row, col)
        norm = np.linalg.norm(normal)
        if norm < 1e-6:
            raise InvalidInputError(f"series {uid} in {folder} has a degenerate ImageOrientationPatient {iop.tolist()}")
        normal = normal / norm
        dist = np.array([float(im.position @ normal) for im in images])
        order = np.argsort(dist, kind="stable")
        images = [images[i] for i in order]
        dist = dist[order]
        if len(images) > 1:
            steps = np.diff(dist)
            if np.min(steps) <= 1e-6 * max(1.0, float(np.max(np.abs(dist)))):
                i = int(np.argmin(steps))
                raise InvalidInputError(
                    f"series {uid} in {folder}: {images[i].path.name} and {images[i + 1].path.name} are at the same "
                    f"position {dist[i]:g} mm along the slice normal; the series holds several volumes (echoes, "
                    "time points or repeated acquisitions): move each volume into its own folder")
            spacing0 = float((dist[-1] - dist[0]) / (len(images) - 1))
            deviation = float(np.max(np.abs(steps - spacing0)))
            notes["slice_spacing_max_deviation"] = deviation
            if deviation > _SPACING_REL_TOL * spacing0:
                worst = int(np.argmax(np.abs(steps - spacing0)))
                warnings.warn(
                    f"series {uid} in {folder}: the slice spacing is not uniform: mean {spacing0:g} mm, steps from "
                    f"{np.min(steps):g} to {np.max(steps):g} mm, max deviation {deviation:g} mm (between "
                    f"{images[worst].path.name} and {images[worst + 1].path.name}); slices are treated as evenly "
                    "spaced (missing files?)", stacklevel=4)
        else:
            spacing0 = images[0].between or images[0].thickness or 1.0
        frame = np.stack([normal, col / np.linalg.norm(col), row / np.linalg.norm(row)])
        return images, spacing0, frame, notes

    images = sorted(images, key=lambda im: (im.instance is None, im.instance or 0, im.path.name, im.frame or 0))
    spacing0 = images[0].between or images[0].thickness
    if spacing0 is None or spacing0 <= 0:
        spacing0 = 1.0
        warnings.warn(f"series {uid} in {folder} has no slice positions nor slice spacing; slices are sorted by "
                      "InstanceNumber and the slice spacing is set to 1 mm (pass spacing= to correct it)",
                      stacklevel=4)
    else:
        warnings.warn(f"series {uid} in {folder} has no slice positions; slices are sorted by InstanceNumber and "
                      f"spaced {spacing0:g} mm (SpacingBetweenSlices/SliceThickness)", stacklevel=4)
    notes["sorted_by"] = "InstanceNumber"
    return images, float(spacing0), None, notes


_INT_CANDIDATES = tuple(np.dtype(t) for t in ("u1", "i1", "u2", "i2", "u4", "i4"))


def _raw_dtype(image: _Image) -> np.dtype:
    return np.dtype(f"{'i' if image.signed else 'u'}{image.bits_allocated // 8}")


def _output_dtype(images: list[_Image]) -> np.dtype:
    """Voxel type holding ``raw * slope + inter`` for every slice's stored bit range."""
    raw = _raw_dtype(images[0])
    pairs = {(im.slope, im.inter) for im in images}
    if pairs == {(1.0, 0.0)}:
        return raw
    bits = max(1, min(images[0].bits_stored, images[0].bits_allocated))
    lo_raw, hi_raw = ((-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if images[0].signed else (0, 2**bits - 1))
    if all(float(s).is_integer() and float(i).is_integer() for s, i in pairs):
        ends = [v for s, i in pairs for v in (lo_raw * s + i, hi_raw * s + i)]
        lo, hi = min(ends), max(ends)
        for cand in (raw, *_INT_CANDIDATES):
            info = np.iinfo(cand)
            if info.min <= lo and hi <= info.max:
                return cand
    return np.dtype("f4") if bits <= 24 else np.dtype("f8")


class _SeriesArray:
    """The sorted slices as a lazily read (N, rows, cols) array: each plane is decoded when it is indexed.

    Opened under :func:`~napari_unwind.io._files.confined_reads` (the server), each slice file is opened first and
    checked where the opened file lies, then decoded from that handle: a slice swapped for a symbolic link out
    after the open is refused (ConfinementError), the others still read."""

    def __init__(self, planes: list[tuple[str, int | None, float, float]], rows: int, cols: int,
                 dtype: np.dtype):
        self.planes = planes  # (path, frame or None, slope, intercept) in axis0 order
        self.shape = (len(planes), rows, cols)
        self.ndim = 3
        self.dtype = np.dtype(dtype)
        self.confine = current_confinement()  # opened confined: every read is (see _files.confined_reads)

    def _plane(self, i: int) -> np.ndarray:
        path, frame, slope, inter = self.planes[i]
        try:
            with open_regular(path, "DICOM", confine=self.confine) as fh:
                arr = pixel_array(fh, index=frame)
        except (ConfinementError, InvalidInputError):
            raise  # outside the confinement (one line naming no path), or no longer a regular file
        except Exception as exc:  # pydicom raises many types for truncated or damaged pixel data
            raise InvalidInputError(
                f"{path}: cannot decode its pixel data ({type(exc).__name__}: {exc}); the file is truncated or "
                "damaged: copy it again or remove it from the series") from None
        if arr.shape != self.shape[1:]:
            raise InvalidInputError(f"{path}: pixel data of shape {arr.shape}, expected {self.shape[1:]}")
        if slope == 1 and inter == 0:
            return arr.astype(self.dtype, copy=False)
        if self.dtype.kind in "iu":
            out = arr.astype(self.dtype)
            if slope != 1:
                out *= self.dtype.type(int(slope))
            if inter != 0:
                out += self.dtype.type(int(inter))
            return out
        return (arr.astype(np.float64) * slope + inter).astype(self.dtype)

    def __getitem__(self, key: Any) -> np.ndarray:
        if not isinstance(key, tuple):
            key = (key,)
        key = key + (slice(None),) * (3 - len(key))
        first = key[0]
        if isinstance(first, int | np.integer):
            return self._plane(int(first) % self.shape[0])[key[1:]]
        idx = range(self.shape[0])[first]
        if len(idx) == 0:
            return np.empty((0, *self.shape[1:]), self.dtype)[(slice(None), *key[1:])]
        return np.stack([self._plane(i)[key[1:]] for i in idx])


def read_dicom(path: Path, *, series: str | int | None = None) -> Volume:
    """Open a DICOM series lazily, one dask chunk per slice.

    Parameters
    ----------
    path : Path
        A folder of DICOM files, or one file of the series (its folder is scanned and, unless ``series`` says
        otherwise, the file's own series is opened).
    series : str or int, optional
        Which series, when the folder holds several: a SeriesInstanceUID, a SeriesNumber, or a 0-based index
        into the listing of :func:`list_series` (sorted by SeriesNumber). A number is a SeriesNumber when exactly
        one series has it, else an index.

    Returns
    -------
    Volume
        Shape (slices, rows, columns), spacing in millimetres (see the module docstring for geometry and type).

    Raises
    ------
    SeriesSelectionError
        Several series and none (or an unknown one) chosen; the message lists them all.
    InvalidInputError
        No DICOM images, slices of different sizes or orientations, duplicate positions, colour images,
        compression no installed plugin decodes.
    """
    path = Path(path).expanduser().absolute()  # workers of a cluster run in other folders
    if path.is_dir():
        folder = path
    else:
        folder = path.parent
        try:
            ds = _read_header(path)
            images = [] if ds is None else _images_of(path, ds)
        except _Unreadable as exc:
            raise InvalidInputError(f"{path} cannot be read as DICOM: {' '.join(str(exc).split())}; copy the file "
                                    "again") from None
        if not images:
            raise InvalidInputError(f"{path} is not a DICOM image file; point at a DICOM series folder or slice")
        if series is None:
            series = str(ds.SeriesInstanceUID)
    by_uid = _scan_folder(folder)
    if not by_uid:
        raise InvalidInputError(
            f"no DICOM images found in {folder}; point at the folder holding the series' slice files "
            "(sub-folders are not searched)")
    uid = _choose_series(by_uid, series, folder)
    images = by_uid[uid]
    _check_consistent(images, folder, uid)
    images, spacing0, frame, notes = _sort_and_space(images, folder, uid)

    first = images[0]
    pixel_spacing = first.pixel_spacing
    if pixel_spacing is None or min(pixel_spacing) <= 0:
        warnings.warn(f"series {uid} in {folder} has no PixelSpacing; 1 mm is assumed", stacklevel=2)
        pixel_spacing = (1.0, 1.0)
    if frame is not None:
        origin = tuple(float(v) for v in frame @ first.position)
    else:
        origin = (0.0, 0.0, 0.0)
    dtype = _output_dtype(images)
    planes = [(str(im.path), im.frame, im.slope, im.inter) for im in images]
    array = _SeriesArray(planes, first.rows, first.cols, dtype)
    stats = [(p, os.stat(p).st_mtime_ns) for p, *_ in planes]
    name = "dicom-" + tokenize(uid, stats, [pl[1:] for pl in planes], str(dtype))
    data = da.from_array(array, chunks=(1, first.rows, first.cols), name=name,
                         meta=np.empty((0, 0, 0), dtype=dtype), asarray=False)
    metadata = {
        "series_uid": uid,
        "series_number": first.number,
        "series_description": first.description,
        "study_uid": first.study,
        "modality": first.modality,
        "image_orientation_patient": None if first.orientation is None else first.orientation.tolist(),
        "image_position_patient": None if first.position is None else first.position.tolist(),
        "rescale": sorted({(im.slope, im.inter) for im in images}),
        "folder": str(folder),
        "n_files": len({im.path for im in images}),
        **notes,
    }
    record = _recorded(first.path)
    if record is not None:
        metadata["unwind"] = {"straightening": record}
    return Volume(data, spacing=(spacing0, *pixel_spacing), unit="millimeter", origin=origin, source=str(path),
                  format="dicom", metadata=metadata)


# ------------------------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------------------------
def _ds(value: float) -> str:
    """A DICOM decimal string (at most 16 characters) for ``value``."""
    return format_number_as_ds(float(value)) if value != 0 else "0"


def _check_geometry_holds(path: Path, spacing_mm: tuple[float, ...], origin_mm: tuple[float, ...], n0: int) -> None:
    """Refuse, before anything is written, slices closer than :func:`read_dicom` tells apart (1e-6 of the farthest
    position, at least 1e-6 mm): the series would read back as several volumes at the same positions."""
    far = max(abs(origin_mm[0]), abs(origin_mm[0] + (n0 - 1) * spacing_mm[0]))
    if n0 > 1 and spacing_mm[0] <= 1e-6 * max(1.0, far):
        raise InvalidInputError(
            f"cannot write {final_name(path)}: slices {spacing_mm[0]!r} mm apart at up to {far:g} mm from the origin "
            "are too close for a DICOM reader to tell apart (at most 1e-6 of that distance); choose another format "
            "(OME-Zarr, NRRD, TIFF, .dat)"
        )


def _storage_plan(volume: Volume) -> tuple[np.dtype, float, float, bool]:
    """(stored dtype, slope, intercept, exact) for writing ``volume`` as 8/16-bit DICOM pixels."""
    dtype = volume.dtype
    if dtype in (np.dtype("u1"), np.dtype("i1"), np.dtype("u2"), np.dtype("i2")):
        return dtype, 1.0, 0.0, True
    if dtype.kind == "f":
        lo, hi, integral = da.compute(volume.data.min(), volume.data.max(),
                                      (volume.data == da.round(volume.data)).all())
    else:
        lo, hi = da.compute(volume.data.min(), volume.data.max())
        integral = True
    lo, hi = float(lo), float(hi)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise InvalidInputError(f"the volume holds non-finite values (min {lo}, max {hi}); DICOM cannot store them")
    if bool(integral):
        if -32768 <= lo and hi <= 32767:
            return np.dtype("i2"), 1.0, 0.0, True
        if 0 <= lo and hi <= 65535:
            return np.dtype("u2"), 1.0, 0.0, True
        if hi - lo <= 65535:
            return np.dtype("u2"), 1.0, lo, True
    slope = (hi - lo) / 65535.0 if hi > lo else 1.0
    slope_ds = float(_ds(slope * (1 + 1e-12)))
    inter_ds = float(_ds(lo))
    return np.dtype("u2"), slope_ds, inter_ds, False


def _template(volume: Volume, stored: np.dtype, slope: float, inter: float, spacing_mm: tuple[float, ...],
              series_description: str, patient_name: str, patient_id: str, study_description: str,
              series_number: int, modality: str | None) -> Dataset:
    eight = stored.itemsize == 1
    sop_class = SecondaryCaptureImageStorage if eight else CTImageStorage
    now = datetime.datetime.now()
    date, time = now.strftime("%Y%m%d"), now.strftime("%H%M%S")

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    meta.ImplementationVersionName = "NAPARI_UNWIND"

    ds = Dataset()
    ds.file_meta = meta
    ds.SpecificCharacterSet = "ISO_IR 192"
    ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.StudyDate = ds.SeriesDate = ds.ContentDate = date
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = time
    ds.AccessionNumber = ""
    ds.Modality = modality or ("OT" if eight else "CT")
    if eight:
        ds.ConversionType = "WSD"
    ds.Manufacturer = ""
    ds.ReferringPhysicianName = ""
    ds.StudyDescription = study_description
    ds.SeriesDescription = series_description
    ds.PatientName = patient_name
    ds.PatientID = patient_id
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    if not eight:
        ds.KVP = ""
    ds.SliceThickness = _ds(spacing_mm[0])
    ds.SpacingBetweenSlices = _ds(spacing_mm[0])
    ds.StudyInstanceUID = generate_uid()
    ds.SeriesInstanceUID = generate_uid()
    ds.StudyID = ""
    ds.SeriesNumber = int(series_number)
    ds.AcquisitionNumber = 1
    ds.InstanceNumber = 1
    ds.ImageOrientationPatient = ["1", "0", "0", "0", "1", "0"]
    ds.FrameOfReferenceUID = generate_uid()
    ds.PositionReferenceIndicator = ""
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = volume.shape[1], volume.shape[2]
    ds.PixelSpacing = [_ds(spacing_mm[1]), _ds(spacing_mm[2])]
    ds.BitsAllocated = ds.BitsStored = 8 * stored.itemsize
    ds.HighBit = 8 * stored.itemsize - 1
    ds.PixelRepresentation = 1 if stored.kind == "i" else 0
    ds.RescaleIntercept = _ds(inter)
    ds.RescaleSlope = _ds(slope)
    if volume.source:
        ds.DerivationDescription = f"written by napari-unwind from {Path(volume.source).name}"[:1024]
    record = straightening_record(volume)
    if record is not None:  # a straight volume's record, in the free-text comment of each image
        ds.ImageComments = RECORD_PREFIX + record_text(record)
    return ds


#: The start of the ImageComments holding a straight volume's record (napari_unwind.io._straight_record).
RECORD_PREFIX = "napari-unwind straightening "


def _recorded(path: str | os.PathLike) -> dict[str, Any] | None:
    """The straightening record in the ImageComments of one image written by :func:`write_dicom`, else None."""
    try:
        with open_regular(path, "DICOM", confine=current_confinement()) as fh:
            ds = pydicom.dcmread(fh, stop_before_pixels=True, specific_tags=["ImageComments"])
    except ConfinementError:
        raise
    except (OSError, InvalidDicomError, InvalidInputError):
        return None
    text = str(getattr(ds, "ImageComments", "") or "")
    return parse_record(text[len(RECORD_PREFIX):]) if text.startswith(RECORD_PREFIX) else None


def write_dicom(
    volume: Volume,
    path: Path,
    *,
    series_description: str = "napari-unwind",
    patient_name: str = "Anonymous",
    patient_id: str = "UNWIND",
    study_description: str = "",
    series_number: int = 1,
    modality: str | None = None,
) -> Iterator[Progress]:
    """Write ``volume`` as a DICOM series: a new folder with one file per axis0 slice.

    Parameters
    ----------
    volume : Volume
        Shape (N0, N1, N2): N0 files of N1 rows by N2 columns. Lengths are converted to millimetres.
    path : Path
        The folder to create (usually the temporary name chosen by :func:`~napari_unwind.io.write_volume`).
        Files are named ``IM00001.dcm``, ``IM00002.dcm``...
    series_description, patient_name, patient_id, study_description : str
        Written as such (the patient fields default to an anonymous placeholder).
    series_number : int
        SeriesNumber (default 1).
    modality : str, optional
        Override the Modality (default CT for 16-bit data, OT for 8-bit data).

    Yields
    ------
    Progress
        One record per slab of slices written.

    Warns
    -----
    UserWarning
        When float or wide integer values had to be quantised into 16 bits (gives the largest change), or the
        volume has no unit (its spacing is then written as millimetres).
    """
    path = Path(path)
    n0, n1, n2 = volume.shape
    if n1 > 65535 or n2 > 65535:
        raise InvalidInputError(f"DICOM images are at most 65535 x 65535 pixels, got {n1} x {n2}")
    if volume.unit is None:
        factor = 1.0
        warnings.warn("the volume has no unit; its spacing is written to DICOM as millimetres", stacklevel=2)
    else:
        factor = _UNIT_TO_MM[volume.unit]
    spacing_mm = tuple(s * factor for s in volume.spacing)
    origin_mm = tuple(o * factor for o in volume.origin)
    _check_geometry_holds(path, spacing_mm, origin_mm, n0)

    yield Progress("write dicom", 0, n0, "checking the value range")
    stored, slope, inter, exact = _storage_plan(volume)
    ds = _template(volume, stored, slope, inter, spacing_mm, series_description, patient_name, patient_id,
                   study_description, series_number, modality)
    validate_file_meta(ds.file_meta, enforce_standard=True)
    stored_le = stored.newbyteorder("<")
    info = np.iinfo(stored)

    path.mkdir()
    width = max(5, len(str(n0)))
    plane = n1 * n2 * volume.dtype.itemsize
    c = int(volume.data.chunksize[0])
    depth = c if c * plane <= 256 * 2**20 else max(1, (256 * 2**20) // plane)
    max_error = 0.0
    for z0 in range(0, n0, depth):
        z1 = min(n0, z0 + depth)
        slab = np.asarray(volume.data[z0:z1].compute())
        if slope == 1.0 and inter == 0.0:
            pixels = slab.astype(stored_le, copy=False)
        elif exact:
            pixels = (slab.astype(np.float64) - inter).astype(stored_le)
        else:
            values = slab.astype(np.float64)
            q = np.clip(np.rint((values - inter) / slope), info.min, info.max)
            max_error = max(max_error, float(np.max(np.abs(q * slope + inter - values))))
            pixels = q.astype(stored_le)
        for k in range(z0, z1):
            uid = generate_uid()
            ds.file_meta.MediaStorageSOPInstanceUID = uid
            ds.SOPInstanceUID = uid
            ds.InstanceNumber = k + 1
            z = origin_mm[0] + k * spacing_mm[0]
            ds.ImagePositionPatient = [_ds(origin_mm[2]), _ds(origin_mm[1]), _ds(z)]
            ds.SliceLocation = _ds(z)
            data = np.ascontiguousarray(pixels[k - z0]).tobytes()
            if len(data) % 2:
                data += b"\x00"
            ds.PixelData = data
            ds["PixelData"].VR = "OB" if stored.itemsize == 1 else "OW"
            name = f"IM{k + 1:0{width}d}.dcm"
            try:
                ds.save_as(path / name, enforce_file_format=True)
            except OSError as exc:  # pydicom re-raises it with a traceback in the message: keep the cause
                cause = exc.__cause__ if isinstance(exc.__cause__, OSError) else exc
                raise OutputError(f"cannot write {path.with_name(final_name(path)) / name}: "
                                  f"{cause.strerror or cause}") from cause
        yield Progress("write dicom", z1, n0, f"slices {z0 + 1}-{z1} of {n0}")
    if not exact:
        warnings.warn(
            f"{volume.dtype} values from {inter:g} to {inter + slope * info.max:g} were quantised into 16-bit DICOM "
            f"pixels (RescaleSlope {slope:g}, RescaleIntercept {inter:g}): values change by up to {max_error:g}",
            stacklevel=2)
