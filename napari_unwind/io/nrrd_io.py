"""NRRD and NHDR (detached header) volumes, through pynrrd.

Geometry
--------
NRRD lists its axes fastest first (x, y, z); napari-unwind's arrays are C ordered (axis0, axis1, axis2) with axis0
the slowest, so every per-axis field is reversed: ``sizes`` (164, 126, 120) is an array of shape (120, 126, 164),
and the spacing and origin are reversed the same way. The spacing of an axis is the length of its
``space directions`` vector (or its ``spacings`` entry when the file has no directions), the origin is
``space origin``, the unit ``space units``. Files in a named anatomical space (``left-posterior-superior``...)
without ``space units`` are in millimetres, as ITK and 3D Slicer assume. The direction vectors themselves are kept in
``Volume.metadata["space directions"]`` (file axis order).

Reading
-------
Raw encoding (attached or detached) is memory mapped: nothing is read until a chunk is computed. gzip and bzip2
streams cannot be read at random, so they are decompressed **eagerly** when the file is opened (peak memory: the
whole uncompressed volume) and wrapped in a dask array. ASCII data are parsed eagerly too. A data stream shorter
than the header announces is an :class:`~napari_unwind.errors.InvalidInputError` giving the expected and found
byte counts.

Writing
-------
The header stores the spacing as a diagonal ``space directions`` matrix with ``space units`` and ``space origin``,
all in file axis order. The voxels stream slab by slab along axis0 (the file's slowest axis), gzip compressed by
default. A ``.nhdr`` target gets a detached companion ``NAME.raw`` (``.raw.gz``, ``.raw.bz2``) in the same folder,
written under a temporary name and renamed once complete; the header refers to it by its final name.
"""

from __future__ import annotations

import bz2
import gzip
import math
import os
import warnings
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import nrrd
import numpy as np

from ..errors import InvalidInputError, OutputError
from ..progress import Progress
from ._atomic import final_name, remove_path, temp_path
from ._files import current_confinement, open_regular, skip_lines
from ._lazy import RawFileArray, iter_slabs, write_slab_depth
from ._straight_record import parse_record, record_text, straightening_record
from ._volume import UNIT_ABBREVIATIONS, LazyArray, Volume, normalise_unit, warn_bad_spacing

if TYPE_CHECKING:
    import dask.array as da

__all__ = ["read_nrrd", "write_nrrd", "ENCODINGS"]

#: Encodings :func:`write_nrrd` can write.
ENCODINGS = ("gzip", "raw", "bzip2")
#: The key/value pair holding the straightening record of a straight volume (napari_unwind.io._straight_record).
RECORD_KEY = "unwind_straightening"

# NRRD type names (the spec's table) -> numpy kind and size
_NRRD_TYPES = {
    "signed char": "i1", "int8": "i1", "int8_t": "i1",
    "uchar": "u1", "unsigned char": "u1", "uint8": "u1", "uint8_t": "u1",
    "short": "i2", "short int": "i2", "signed short": "i2", "signed short int": "i2", "int16": "i2", "int16_t": "i2",
    "ushort": "u2", "unsigned short": "u2", "unsigned short int": "u2", "uint16": "u2", "uint16_t": "u2",
    "int": "i4", "signed int": "i4", "int32": "i4", "int32_t": "i4",
    "uint": "u4", "unsigned int": "u4", "uint32": "u4", "uint32_t": "u4",
    "longlong": "i8", "long long": "i8", "long long int": "i8", "signed long long": "i8",
    "signed long long int": "i8", "int64": "i8", "int64_t": "i8",
    "ulonglong": "u8", "unsigned long long": "u8", "unsigned long long int": "u8", "uint64": "u8", "uint64_t": "u8",
    "float": "f4", "double": "f8",
}
_NUMPY_TO_NRRD = {"i1": "int8", "u1": "uint8", "i2": "int16", "u2": "uint16", "i4": "int32", "u4": "uint32",
                  "f4": "float", "f8": "double"}
_ANATOMICAL_SPACES = {
    "right-anterior-superior", "ras", "left-anterior-superior", "las", "left-posterior-superior", "lps",
    "right-anterior-superior-time", "ras-time", "left-anterior-superior-time", "las-time",
    "left-posterior-superior-time", "lps-time", "scanner-xyz", "scanner-xyz-time", "3d-right-handed",
    "3d-left-handed", "3d-right-handed-time", "3d-left-handed-time",
}
_GZIP = ("gzip", "gz")
_BZIP2 = ("bzip2", "bz2")
_ASCII = ("ascii", "text", "txt")
_SLAB_BYTES = 64 * 2**20  # target size of one dask chunk (a slab of whole planes along axis0)
_READ_PIECE = 64 * 2**20  # decompress in pieces of this many bytes


# ------------------------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------------------------
def _slab_depth(shape: tuple[int, ...], itemsize: int, target: int = _SLAB_BYTES) -> int:
    plane = int(np.prod(shape[1:])) * itemsize
    return int(max(1, min(shape[0], target // max(plane, 1))))


# ------------------------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------------------------
def _file_dtype(header: dict, path: Path) -> np.dtype:
    kind = _NRRD_TYPES.get(str(header.get("type", "")).strip().lower())
    if kind is None:
        raise InvalidInputError(
            f"{path}: unsupported NRRD voxel type {header.get('type')!r}; "
            "convert it to an 8/16/32-bit integer or float type (e.g. `unu convert`)"
        )
    dtype = np.dtype(kind)
    if dtype.itemsize > 1 and str(header["encoding"]).lower() not in _ASCII:
        endian = str(header.get("endian", "")).lower()
        if endian not in ("little", "big"):
            raise InvalidInputError(f"{path}: the header has no valid 'endian' field (got {endian or 'none'!r}); "
                                    "add 'endian: little' (or big) to the header")
        dtype = dtype.newbyteorder("<" if endian == "little" else ">")
    return dtype


def _direction_vectors(header: dict, ndim: int) -> list[np.ndarray | None]:
    """'space directions' as one vector (or None for a non-spatial axis) per file axis."""
    sd = header.get("space directions")
    if sd is None:
        return [None] * ndim
    vectors: list[np.ndarray | None] = []
    for row in list(sd):
        if row is None:
            vectors.append(None)
            continue
        v = np.asarray(row, dtype=float)
        vectors.append(None if not np.all(np.isfinite(v)) else v)
    if len(vectors) != ndim:
        return [None] * ndim
    return vectors


def _unit(header: dict, path: Path, spatial: list[int]) -> str | None:
    units = header.get("space units")
    if units is None and "space directions" not in header:
        units = header.get("units")
        if units is not None:
            units = [units[i] for i in spatial if i < len(units)]
    if units:
        names = {str(u).strip() for u in units}
        if len(names) > 1:
            warnings.warn(f"{path}: axes have different units {sorted(names)}; the unit is left unknown",
                          stacklevel=3)
            return None
        try:
            return normalise_unit(names.pop())
        except InvalidInputError:
            warnings.warn(f"{path}: unknown unit {units[0]!r}; the unit is left unknown", stacklevel=3)
            return None
    if str(header.get("space", "")).strip().lower() in _ANATOMICAL_SPACES:
        return "millimeter"  # ITK and 3D Slicer's convention for anatomical spaces
    return None


def _data_source(header: dict, path: Path) -> Path | None:
    name = header.get("data file", header.get("datafile"))
    if name is None:
        return None
    name = str(name).strip()
    if name.upper().startswith("LIST") or " " in name:
        raise InvalidInputError(
            f"{path}: multi-file NRRD data ('data file: {name}') is not supported; "
            "join the files into one (e.g. `unu join` or save from 3D Slicer as one .nrrd)"
        )
    data = Path(name)
    if not data.is_absolute():
        data = path.parent / data
    if not data.exists():
        raise InvalidInputError(f"{path}: its data file {data} does not exist; copy it next to the header")
    return data


class _Short(Exception):
    """The compressed stream ended early."""


def _inflate(fh: Any, encoding: str) -> Iterator[bytes]:
    """Decompress a gzip (possibly multi-member) or bzip2 stream from ``fh``'s position, in bounded pieces.

    Raises ``_Short`` when the input ends before an end-of-stream marker.
    """
    def new() -> Any:
        return zlib.decompressobj(zlib.MAX_WBITS | 16) if encoding == "gzip" else bz2.BZ2Decompressor()

    d, fresh = new(), True
    while True:
        data = fh.read(_READ_PIECE)
        if not data:
            if not fresh and not d.eof:
                raise _Short()
            return
        while data:
            if fresh and not data.strip(b"\x00"):
                return  # zero padding after the last member
            fresh = False
            if encoding == "gzip":
                yield d.decompress(data, _READ_PIECE)
                while d.unconsumed_tail and not d.eof:
                    yield d.decompress(d.unconsumed_tail, _READ_PIECE)
            else:
                yield d.decompress(data, _READ_PIECE)
                while not d.eof and not d.needs_input:
                    yield d.decompress(b"", _READ_PIECE)
            if not d.eof:
                break
            data = d.unused_data  # another member may follow
            d, fresh = new(), True


def _read_compressed(fh: Any, encoding: str, nbytes: int, byte_skip: int, path: Path) -> bytearray:
    """Decompress the stream at ``fh``'s position into exactly ``nbytes`` (after skipping ``byte_skip``)."""
    found = 0
    produced = 0
    try:
        if byte_skip == -1:  # the data are the last nbytes of the decompressed stream
            whole = bytearray()
            try:
                for piece in _inflate(fh, encoding):
                    whole += piece
            finally:
                found = len(whole)
            if found < nbytes:
                raise _Short()
            return whole[found - nbytes:]
        buf = bytearray(nbytes)
        for piece in _inflate(fh, encoding):
            lo = max(byte_skip - produced, 0)  # part of this piece still inside the byte skip
            produced += len(piece)
            if lo >= len(piece):
                continue
            n = min(len(piece) - lo, nbytes - found)
            buf[found:found + n] = piece[lo:lo + n]
            found += n
            if found == nbytes:
                return buf
        raise _Short()
    except _Short:
        raise InvalidInputError(
            f"{path}: the {encoding} data are truncated: expected {nbytes} bytes of voxels, found {found}; "
            "the file is incomplete (copy it again)"
        ) from None
    except (zlib.error, OSError, ValueError, EOFError) as exc:
        raise InvalidInputError(
            f"{path}: the {encoding} data are corrupt ({exc}): expected {nbytes} bytes of voxels, "
            f"{found} decoded before the damage; copy the file again"
        ) from None


def read_nrrd(path: Path, *, chunks: Any = None) -> Volume:
    """Open an NRRD (``.nrrd``) or detached-header NRRD (``.nhdr``) volume.

    Parameters
    ----------
    path : Path
        The ``.nrrd`` file or the ``.nhdr`` header (its ``data file`` is found relative to it).
    chunks : int or tuple of 3 int, optional
        Dask chunk shape; default: slabs of whole planes of about 64 MiB along axis0.

    Returns
    -------
    Volume
        Shape (N0, N1, N2) = the header's ``sizes`` reversed; spacing, origin reversed likewise (see the module
        docstring). Raw data are memory mapped lazily; gzip/bzip2/ASCII data are decompressed now.

    Raises
    ------
    InvalidInputError
        Not an NRRD header, unsupported type or encoding, not 3D, missing data file, truncated data.
    """
    path = Path(path).expanduser().absolute()  # workers of a cluster run in other folders
    confine = current_confinement()  # opened confined (the server): the header and the data checked where they lie
    try:
        with open_regular(path, confine=confine) as fh:
            header = nrrd.read_header(fh)
            header_end = fh.tell()
    except nrrd.NRRDError as exc:
        raise InvalidInputError(f"{path} is not a readable NRRD header: {exc}") from None
    except (UnicodeDecodeError, ValueError, StopIteration) as exc:
        raise InvalidInputError(f"{path} is not a readable NRRD header ({exc})") from None
    for field in ("type", "dimension", "sizes", "encoding"):
        if field not in header:
            raise InvalidInputError(f"{path}: the NRRD header lacks the required field {field!r}")

    sizes = [int(s) for s in np.atleast_1d(header["sizes"])]
    ndim = len(sizes)
    if ndim != int(header["dimension"]):
        raise InvalidInputError(f"{path}: 'dimension: {header['dimension']}' but {ndim} sizes {sizes}")
    if any(s < 1 for s in sizes):
        raise InvalidInputError(f"{path}: the header's sizes {sizes} hold a size below 1; every axis has at least one "
                                "sample: the header is damaged (fix its 'sizes:' line)")
    encoding = str(header["encoding"]).strip().lower()
    if encoding not in ("raw", *_GZIP, *_BZIP2, *_ASCII):
        raise InvalidInputError(f"{path}: unsupported NRRD encoding {encoding!r}; re-save it as raw or gzip")
    file_dtype = _file_dtype(header, path)

    # which file axes are spatial; non-spatial axes of length 1 (a scalar 'list'/'vector' axis) are dropped
    vectors = _direction_vectors(header, ndim)
    kinds = [str(k).lower() for k in header.get("kinds", ["domain"] * ndim)]
    nonspatial = [
        i for i in range(ndim)
        if ("space directions" in header and vectors[i] is None)
        or (i < len(kinds) and kinds[i] in ("list", "vector", "point", "covariant-vector", "normal", "scalar",
                                            "2-vector", "3-vector", "4-vector", "3-color", "4-color", "rgb-color",
                                            "rgba-color", "complex", "time", "stub"))
    ]
    spatial = [i for i in range(ndim) if i not in nonspatial]
    if any(sizes[i] > 1 for i in nonspatial) or len(spatial) != 3:
        raise InvalidInputError(
            f"{path} has sizes {sizes} with kinds {kinds}; napari-unwind needs a 3D scalar volume "
            "(extract one channel or time point first, e.g. `unu slice`)"
        )

    # spacing, origin, unit (file order, then reversed into array order)
    spacing_file = []
    spacings = header.get("spacings")
    for k, i in enumerate(spatial):
        if vectors[i] is not None:
            s = math.hypot(*(float(c) for c in vectors[i]))  # no overflow of the squares (1e200 stays 1e200)
        elif spacings is not None and i < len(spacings):
            s = abs(float(spacings[i]))
        else:
            s = 1.0  # the file states no voxel size: 1, as every NRRD reader reads it
        if not (np.isfinite(s) and s > 0):
            warn_bad_spacing(path, 2 - k, s)
            s = 1.0
        spacing_file.append(s)
    origin_file = [0.0, 0.0, 0.0]
    if header.get("space origin") is not None:
        o = np.asarray(header["space origin"], dtype=float)
        if o.shape == (3,) and np.all(np.isfinite(o)):
            origin_file = [float(v) for v in o]
    unit = _unit(header, path, spatial)
    # C order: slowest axis first; dropping length-1 non-spatial axes does not change the byte layout
    out_shape = tuple(sizes[i] for i in spatial[::-1])

    # locate the data
    data_path = _data_source(header, path)
    line_skip = int(header.get("line skip", header.get("lineskip", 0)))
    byte_skip = int(header.get("byte skip", header.get("byteskip", 0)))
    if line_skip < 0 or byte_skip < -1:
        raise InvalidInputError(f"{path}: invalid line skip {line_skip} / byte skip {byte_skip} in the header")
    nbytes = int(np.prod(sizes, dtype=np.int64)) * file_dtype.itemsize
    source = data_path or path
    native = file_dtype.newbyteorder("=")

    with open_regular(source, "data" if data_path is not None else "", confine=confine) as fh:
        if data_path is None:
            fh.seek(header_end)
        skip_lines(fh, line_skip, source)
        start = fh.tell()
        if encoding == "raw":
            file_size = os.fstat(fh.fileno()).st_size
            offset = file_size - nbytes if byte_skip == -1 else start + byte_skip
            found = file_size - max(offset, 0) if byte_skip != -1 else file_size - start
            if offset < 0 or found < nbytes:
                raise InvalidInputError(
                    f"{source}: the raw data are truncated: expected {nbytes} bytes of voxels "
                    f"({' x '.join(map(str, sizes))} x {file_dtype.itemsize}), found {max(found, 0)}; "
                    "the file is incomplete (copy it again) or the header's sizes/type are wrong"
                )
            array: Any = RawFileArray(source, file_dtype, out_shape, offset)
            lazy = True
        elif encoding in _ASCII:
            fh.seek(max(byte_skip, 0), os.SEEK_CUR)
            values = np.array(fh.read().split(), dtype=float)
            if values.size < int(np.prod(sizes)):
                raise InvalidInputError(f"{source}: expected {int(np.prod(sizes))} ASCII values, found {values.size}")
            array = values[: int(np.prod(sizes))].astype(native).reshape(out_shape)
            lazy = False
        else:
            buf = _read_compressed(fh, "gzip" if encoding in _GZIP else "bzip2", nbytes, byte_skip, source)
            array = np.frombuffer(buf, dtype=file_dtype).reshape(out_shape)
            if file_dtype != native:
                array = array.astype(native)
            lazy = False

    default_chunks = chunks is None
    if default_chunks:
        chunks = (_slab_depth(out_shape, native.itemsize),) + out_shape[1:]
    st = os.stat(source) if lazy else None

    def build() -> da.Array:
        import dask.array as da

        if lazy:
            from dask.base import tokenize

            name = "nrrd-" + tokenize(str(source), st.st_mtime_ns, st.st_size, offset, str(file_dtype), out_shape)
            return da.from_array(array, chunks=chunks, name=name, meta=np.empty((0, 0, 0), dtype=native),
                                 asarray=False)
        return da.from_array(array, chunks=chunks)

    # the default chunks are regular: the dask array is built on first use (unwind info reads the header alone);
    # chunks given by the caller are checked by dask now
    data: Any = LazyArray(build, out_shape, native, chunks) if default_chunks else build()

    metadata = {
        "header": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in header.items()},
        "space": header.get("space"),
        "space directions": [None if v is None else v.tolist() for v in vectors],
        "encoding": encoding,
        "data file": str(data_path) if data_path else None,
    }
    if parse_record(header.get(RECORD_KEY)) is not None:
        metadata["unwind"] = {"straightening": parse_record(header[RECORD_KEY])}
    return Volume(
        data,
        spacing=tuple(spacing_file[::-1]),
        unit=unit,
        origin=tuple(origin_file[::-1]),
        source=str(path),
        format="nrrd",
        metadata=metadata,
    )


# ------------------------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------------------------
#: Voxel sizes whose square is a normal 64-bit float: NRRD readers take the size as the length of a space direction
#: vector, the square root of its squares, which overflows above (and loses digits below) this range.
_LENGTHS = (np.sqrt(np.finfo(np.float64).tiny), np.sqrt(np.finfo(np.float64).max))


def _check_lengths(path: Path, spacing: tuple[float, ...]) -> None:
    """Refuse, before anything is written, a spacing that comes back from the file as another number."""
    for axis, size in enumerate(spacing):
        if not _LENGTHS[0] <= size <= _LENGTHS[1]:
            raise InvalidInputError(
                f"cannot write {final_name(path)}: NRRD stores the voxel size as the length of a space direction "
                f"vector, which readers compute as the square root of its squares; for {size!r} (axis{axis}) that "
                f"overflows or loses digits (sizes {_LENGTHS[0]:.3g} to {_LENGTHS[1]:.3g} come back intact); "
                "choose another unit or another format (OME-Zarr, TIFF, .dat)"
            )


def _header_text(volume: Volume, encoding: str, data_file: str | None) -> str:
    dtype = volume.dtype
    s0, s1, s2 = volume.spacing
    o0, o1, o2 = volume.origin
    lines = [
        "NRRD0005",
        "# Complete NRRD file format specification at:",
        "# http://teem.sourceforge.net/nrrd/format.html",
        "# written by napari-unwind",
        f"type: {_NUMPY_TO_NRRD[dtype.str[1:]]}",
        "dimension: 3",
        "space dimension: 3",
        f"sizes: {volume.shape[2]} {volume.shape[1]} {volume.shape[0]}",
        "space directions: " + " ".join(
            nrrd.format_vector(np.array(v, dtype=float)) for v in ((s2, 0, 0), (0, s1, 0), (0, 0, s0))
        ),
        "kinds: domain domain domain",
    ]
    if dtype.itemsize > 1:
        lines.append("endian: little")
    lines.append(f"encoding: {encoding}")
    if volume.unit is not None:
        u = UNIT_ABBREVIATIONS.get(volume.unit, volume.unit)
        lines.append(f'space units: "{u}" "{u}" "{u}"')
    lines.append("space origin: " + nrrd.format_vector(np.array([o2, o1, o0], dtype=float)))
    if data_file is not None:
        lines.append(f"data file: {data_file}")
    record = straightening_record(volume)
    if record is not None:  # a key/value pair (pynrrd reads it back as a string)
        lines.append(f"{RECORD_KEY}:={record_text(record)}")
    return "\n".join(lines) + "\n\n" if data_file is None else "\n".join(lines) + "\n"


class _Compressor:
    """Write bytes to an open binary file, raw or through a gzip/bzip2 stream."""

    def __init__(self, fh: Any, encoding: str, level: int):
        self.fh = fh
        if encoding == "gzip":
            self.stream: Any = gzip.GzipFile(fileobj=fh, mode="wb", compresslevel=level, mtime=0)
        elif encoding == "bzip2":
            self.stream = bz2.BZ2File(fh, mode="wb", compresslevel=max(1, level))
        else:
            self.stream = None

    def write(self, data: np.ndarray) -> None:
        (self.stream or self.fh).write(memoryview(data).cast("B"))

    def close(self) -> None:
        if self.stream is not None:
            self.stream.close()


def _stream_voxels(volume: Volume, fh: Any, encoding: str, level: int) -> Iterator[Progress]:
    little = volume.dtype.newbyteorder("<")
    depth = write_slab_depth(volume)
    total = -(-volume.shape[0] // depth)
    out = _Compressor(fh, encoding, level)
    try:
        for i, (z0, z1, slab) in enumerate(iter_slabs(volume, depth)):
            out.write(np.ascontiguousarray(slab, dtype=little))
            yield Progress("write nrrd", i + 1, total, f"planes {z0}-{z1 - 1} of {volume.shape[0]}")
    finally:
        out.close()


def write_nrrd(
    volume: Volume,
    path: Path,
    *,
    encoding: str = "gzip",
    compression_level: int = 4,
) -> Iterator[Progress]:
    """Write ``volume`` as NRRD, or as an NHDR header plus a raw data file when the target ends in ``.nhdr``.

    Parameters
    ----------
    volume : Volume
        Shape (N0, N1, N2); written as NRRD ``sizes: N2 N1 N0`` with a diagonal ``space directions``
        ``(s2,0,0) (0,s1,0) (0,0,s0)``, ``space units`` and ``space origin (o2, o1, o0)``.
    path : Path
        The file to write (usually the temporary name chosen by :func:`~napari_unwind.io.write_volume`; its final
        name decides between ``.nrrd`` and ``.nhdr``). For ``.nhdr`` the companion ``NAME.raw[.gz|.bz2]`` is
        written next to it, atomically.
    encoding : {"gzip", "raw", "bzip2"}
        Voxel encoding (default gzip).
    compression_level : int
        1 (fast) to 9 (small) for gzip and bzip2.

    Yields
    ------
    Progress
        One record per slab of planes written.
    """
    path = Path(path)
    encoding = str(encoding).lower()
    encoding = {"gz": "gzip", "bz2": "bzip2"}.get(encoding, encoding)
    if encoding not in ENCODINGS:
        raise InvalidInputError(f"NRRD encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    if not 1 <= int(compression_level) <= 9:
        raise InvalidInputError(f"compression_level must be 1..9, got {compression_level}")
    if volume.dtype.str[1:] not in _NUMPY_TO_NRRD:
        raise InvalidInputError(f"cannot write voxel type {volume.dtype} to NRRD")
    _check_lengths(path, volume.spacing)
    final = path.with_name(final_name(path))

    if final.suffix.lower() != ".nhdr":
        with open(path, "wb") as fh:
            fh.write(_header_text(volume, encoding, None).encode("ascii"))
            yield from _stream_voxels(volume, fh, encoding, int(compression_level))
        return

    # detached: NAME.nhdr + NAME.raw[.gz|.bz2], the companion written under a temporary name first
    companion = final.with_name(final.stem + {"raw": ".raw", "gzip": ".raw.gz", "bzip2": ".raw.bz2"}[encoding])
    if companion.exists() and not final.exists():
        raise OutputError(
            f"writing {final} would replace {companion}, which belongs to no existing header; "
            "move it away or choose another name"
        )
    tmp = temp_path(companion)
    try:
        with open(tmp, "wb") as fh:
            yield from _stream_voxels(volume, fh, encoding, int(compression_level))
        with open(path, "wb") as fh:
            fh.write(_header_text(volume, encoding, companion.name).encode("ascii"))
        os.replace(tmp, companion)
    except BaseException:
        remove_path(tmp)
        raise
