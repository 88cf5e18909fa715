"""Header-only readers for ``unwind info``: what the report prints, read without numpy, zarr or a format library.

``unwind info`` must start in a fraction of a second (issue 18), and importing numpy alone takes longer than that
on a slow machine. :func:`read_header` reads the headers of the common formats with the standard library alone:

- NRRD (``.nrrd``, attached data, raw or gzip encoding): the text header;
- NIfTI-1 and NIfTI-2 (``.nii``, ``.nii.gz``): the binary header, through :mod:`struct` (and :mod:`gzip`);
- OME-Zarr (NGFF 0.4 on zarr v2, NGFF 0.5 on zarr v3): the JSON metadata of the group and of its levels;

and returns a :class:`Header` that :func:`napari_unwind._report.describe` prints exactly as it prints the
:class:`~napari_unwind.io.Volume` the full reader (:func:`~napari_unwind.io.open_volume`) opens from the same path.

It is a fast path, not a second reader: it returns None, and the caller opens the scan with the full reader, for any
other format and on anything unusual or doubtful (an unknown or duplicate field, an encoding other than raw or gzip,
a detached data file, a line or byte skip, non-spatial axes, a size, spacing or origin that is zero, negative or
not finite, a unit that is not one of the known ones, a header nibabel would repair, a zarr codec or key it does not
know, sharding, a truncated file...). The full reader then prints the report, or its one-line error, or its warning:
the one place for those stays :mod:`napari_unwind.io`. The rules copied here (the NRRD axes reversed into array
order, the spacing as the length of the ``space directions`` vectors, NIfTI's scaled voxel type, the chunk shapes
of the dask arrays...) are checked against the full readers by ``tests/io/test_headers.py``.

What the fast path does not check: the voxels themselves. A gzip NRRD's stream is not inflated (the full reader
inflates it at open to check its length); the fast path checks instead that the stream starts with gzip's magic
bytes and that its trailer records the expected length, which catches a truncated copy but not bytes damaged in the
middle. NIfTI and OME-Zarr voxels are read lazily by the full reader too.
"""

from __future__ import annotations

import gzip
import json
import math
import os
import re
import shlex
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import InvalidInputError
from ._units import UNITS, axis_units, unit_label

__all__ = ["Header", "read_header"]

#: numpy's names of the voxel types a Volume accepts, by item size
_ITEMSIZE = {"int8": 1, "uint8": 1, "int16": 2, "uint16": 2, "int32": 4, "uint32": 4, "float32": 4, "float64": 8}
_INT_RANGE = {"uint8": (0, 2**8 - 1), "int8": (-2**7, 2**7 - 1), "uint16": (0, 2**16 - 1),
              "int16": (-2**15, 2**15 - 1), "uint32": (0, 2**32 - 1), "int32": (-2**31, 2**31 - 1)}
_MIB = 2**20


@dataclass(frozen=True)
class Header:
    """What ``unwind info`` reports of a scan, read from its header (the attributes :func:`describe` uses)."""

    source: str
    format: str
    shape: tuple[int, int, int]
    dtype: str
    spacing: tuple[float, float, float]
    unit: str | None
    origin: tuple[float, float, float]
    level_shapes: tuple[tuple[int, int, int], ...]
    level_chunks: tuple[tuple[tuple[int, ...], ...], ...]
    level_spacings: tuple[tuple[float, float, float], ...]

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * _ITEMSIZE[self.dtype]

    @property
    def unit_abbreviation(self) -> str:
        return unit_label(self.unit)


class _Defer(Exception):
    """Leave this scan to the full reader."""


def _check(condition: Any) -> None:
    if not condition:
        raise _Defer()


def _regular_chunks(shape: tuple[int, ...], chunks: tuple[int, ...]) -> tuple[tuple[int, ...], ...]:
    """Dask's normalised chunks of a regular chunk shape (the one copy; io._volume imports it)."""
    out = []
    for n, c in zip(shape, chunks, strict=True):
        c = max(1, min(int(c), n)) if n else 0
        out.append((c,) * (n // c) + ((n % c,) if n % c else ()) if c else (0,))
    return tuple(out)


def _finite_positive(values: Any) -> bool:
    return all(isinstance(v, float) and math.isfinite(v) and v > 0 for v in values)


def _unit(name: Any) -> str | None:
    """The NGFF name of a unit, or _Defer where the full reader would warn or fail."""
    key = str(name).strip().lower()
    _check(key in UNITS)
    return UNITS[key]


def read_header(path: str | os.PathLike, *, format: str | None = None, **options: Any) -> Header | None:
    """The ``unwind info`` facts of the scan at ``path`` from its header alone, or None: open it with the full reader.

    ``format`` and ``options`` are those of :func:`~napari_unwind.io.open_volume`; any option, or a ``format`` other
    than the one detected, leaves the scan to the full reader. Never raises for a bad file (it returns None).
    """
    if options:
        return None
    try:
        from ._formats import detect_format

        p = Path(path).expanduser().absolute()
        if not p.exists():
            return None
        fmt = detect_format(p)
        if format is not None and format != fmt:
            return None
        reader = {"nrrd": _nrrd, "nifti": _nifti, "ome-zarr": _ome_zarr}.get(fmt)
        if reader is None or p.is_dir() != (fmt == "ome-zarr"):
            return None
        return reader(p)
    except (_Defer, Exception):  # noqa: BLE001 - anything unexpected: the full reader decides and explains
        return None


# ------------------------------------------------------------------------------------------------------------------
# NRRD (as napari_unwind.io.nrrd_io.read_nrrd, through pynrrd's read_header)
# ------------------------------------------------------------------------------------------------------------------
_NRRD_TYPES = {
    "signed char": "int8", "int8": "int8", "int8_t": "int8",
    "uchar": "uint8", "unsigned char": "uint8", "uint8": "uint8", "uint8_t": "uint8",
    "short": "int16", "short int": "int16", "signed short": "int16", "signed short int": "int16", "int16": "int16",
    "int16_t": "int16",
    "ushort": "uint16", "unsigned short": "uint16", "unsigned short int": "uint16", "uint16": "uint16",
    "uint16_t": "uint16",
    "int": "int32", "signed int": "int32", "int32": "int32", "int32_t": "int32",
    "uint": "uint32", "unsigned int": "uint32", "uint32": "uint32", "uint32_t": "uint32",
    "float": "float32", "double": "float64",
}
_ANATOMICAL_SPACES = {
    "right-anterior-superior", "ras", "left-anterior-superior", "las", "left-posterior-superior", "lps",
    "right-anterior-superior-time", "ras-time", "left-anterior-superior-time", "las-time",
    "left-posterior-superior-time", "lps-time", "scanner-xyz", "scanner-xyz-time", "3d-right-handed",
    "3d-left-handed", "3d-right-handed-time", "3d-left-handed-time",
}
#: every field name pynrrd parses by type: a ``key:=value`` pair under one of these names is read as that field
_NRRD_FIELDS = {
    "dimension", "lineskip", "line skip", "byteskip", "byte skip", "space dimension", "min", "max", "oldmin",
    "old min", "oldmax", "old max", "endian", "encoding", "content", "sample units", "datafile", "data file", "space",
    "type", "sizes", "spacings", "thicknesses", "axismins", "axis mins", "axismaxs", "axis maxs", "kinds",
    "centerings", "labels", "units", "space units", "space origin", "measurement frame", "space directions",
}
_HEADER_LIMIT = 1 * _MIB


def _floats(tokens: list[str]) -> list[float]:
    return [float(t) for t in tokens]


def _vector(text: str) -> list[float]:
    """A NRRD vector ``(a,b,c)`` as pynrrd's parse_vector reads it."""
    _check(text[:1] == "(" and text[-1:] == ")")
    return _floats(text[1:-1].split(","))


def _number_tokens(value: str) -> None:
    _floats(value.split())


def _matrix(value: str) -> None:
    rows = [None if row == "none" else _vector(row) for row in value.split()]
    _check(len({len(r) for r in rows if r is not None}) == 1)


#: fields the report does not use, each with what pynrrd does with its value (a value it rejects is an error
#: of the full reader, so the fast path defers)
_NRRD_IGNORED = {
    "content": None, "sample units": None, "centerings": None, "space dimension": int,
    "labels": shlex.split, "thicknesses": _number_tokens, "axis mins": _number_tokens, "axismins": _number_tokens,
    "axis maxs": _number_tokens, "axismaxs": _number_tokens, "min": float, "max": float, "old min": float,
    "oldmin": float, "old max": float, "oldmax": float, "measurement frame": _matrix,
}
_NRRD_USED = {"type", "dimension", "sizes", "encoding", "endian", "space", "space directions", "space units",
              "space origin", "kinds", "spacings", "line skip", "lineskip", "byte skip", "byteskip"}


def _nrrd_fields(fh: Any) -> tuple[dict[str, str], int]:
    """The header's fields (name -> value text) and the byte offset of the data."""
    magic = fh.readline()
    _check(re.fullmatch(rb"NRRD000[1-5]\r?\n", magic))
    pos = len(magic)
    fields: dict[str, str] = {}
    while True:
        line = fh.readline(_HEADER_LIMIT)
        _check(line.endswith(b"\n"))  # a header ended by the end of the file holds no data (or is cut short)
        pos += len(line)
        _check(pos < _HEADER_LIMIT)
        text = line.decode("ascii").rstrip()  # non-ASCII: pynrrd drops those bytes; leave it to the full reader
        if text.startswith("#"):
            continue
        if text == "":
            return fields, pos
        m = re.match(r"([^:]*):(=?)(.*)$", text)
        _check(m is not None)
        name, pair, value = m.group(1).strip(), m.group(2), m.group(3).strip()
        _check(name not in fields)  # a duplicate is an error of pynrrd's
        if pair:
            _check(name not in _NRRD_FIELDS)  # a key/value pair: pynrrd keeps it as text, the reader ignores it
            fields[name] = ""
            continue
        _check(name in _NRRD_USED or name in _NRRD_IGNORED)
        fields[name] = value
        check = _NRRD_IGNORED.get(name)
        if check is not None:
            check(value)


def _nrrd(path: Path) -> Header:
    size = path.stat().st_size
    with open(path, "rb") as fh:
        fields, start = _nrrd_fields(fh)
        tail = b""
        if fields.get("encoding", "").lower() in ("gzip", "gz"):
            head = fh.read(2)
            _check(head == b"\x1f\x8b")
            fh.seek(-4, os.SEEK_END)
            tail = fh.read(4)
    for name in ("type", "dimension", "sizes", "encoding"):
        _check(name in fields)
    for name in ("line skip", "lineskip", "byte skip", "byteskip"):
        _check(int(fields.get(name, "0")) == 0)
    _check(int(fields["dimension"]) == 3)
    sizes_f = _floats(fields["sizes"].split())
    _check(len(sizes_f) == 3 and all(math.isfinite(s) and s >= 1 and s == int(s) for s in sizes_f))
    sizes = [int(s) for s in sizes_f]
    dtype = _NRRD_TYPES.get(fields["type"].strip().lower())
    _check(dtype is not None)
    itemsize = _ITEMSIZE[dtype]
    encoding = fields["encoding"].strip().lower()
    _check(encoding in ("raw", "gzip", "gz"))
    if itemsize > 1:
        _check(fields.get("endian", "").lower() in ("little", "big"))
    if "kinds" in fields:
        kinds = [k.lower() for k in fields["kinds"].split()]
        _check(len(kinds) == 3 and all(k in ("domain", "space") for k in kinds))

    if "space directions" in fields:
        rows = fields["space directions"].split()
        _check(len(rows) == 3 and "none" not in rows)
        vectors = [_vector(r) for r in rows]
        _check(all(len(v) == 3 and all(math.isfinite(x) for x in v) for v in vectors))
        spacing_file = [math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) for v in vectors]
    elif "spacings" in fields:
        spacing_file = _floats(fields["spacings"].split())
        _check(len(spacing_file) == 3)
    else:
        spacing_file = [1.0, 1.0, 1.0]
    _check(_finite_positive(spacing_file))
    origin_file = [0.0, 0.0, 0.0]
    if "space origin" in fields:
        origin_file = _vector(fields["space origin"])
        _check(len(origin_file) == 3 and all(math.isfinite(o) for o in origin_file))

    if "space units" in fields:
        names = {u.strip() for u in shlex.split(fields["space units"])}
        _check(len(names) == 1)
        unit = _unit(names.pop())
    else:
        unit = "millimeter" if fields.get("space", "").strip().lower() in _ANATOMICAL_SPACES else None

    shape = (sizes[2], sizes[1], sizes[0])
    nbytes = math.prod(shape) * itemsize
    if encoding == "raw":
        _check(size - start >= nbytes)
    else:  # the last gzip member's trailer: the stream's length modulo 2**32
        _check(size - start >= 18 and int.from_bytes(tail, "little") == nbytes % 2**32)
    plane = shape[1] * shape[2] * itemsize
    depth = max(1, min(shape[0], (64 * _MIB) // max(plane, 1)))
    chunks = (depth, shape[1], shape[2])
    spacing = (spacing_file[2], spacing_file[1], spacing_file[0])
    return Header(source=str(path), format="nrrd", shape=shape, dtype=dtype, spacing=spacing, unit=unit,
                  origin=(origin_file[2], origin_file[1], origin_file[0]), level_shapes=(shape,),
                  level_chunks=(_regular_chunks(shape, chunks),), level_spacings=(spacing,))


# ------------------------------------------------------------------------------------------------------------------
# NIfTI-1/2 (as napari_unwind.io.nifti.read_nifti, through nibabel)
# ------------------------------------------------------------------------------------------------------------------
_NIFTI_TYPES = {2: ("uint8", 8), 4: ("int16", 16), 8: ("int32", 32), 16: ("float32", 32), 64: ("float64", 64),
                256: ("int8", 8), 512: ("uint16", 16), 768: ("uint32", 32)}
_NIFTI_UNITS = {0: None, 1: "meter", 2: "millimeter", 3: "micrometer"}
# name -> (struct format, offset) in NIfTI-1 and NIfTI-2 headers
_NIFTI1 = {"dim": ("8h", 40), "datatype": ("h", 70), "bitpix": ("h", 72), "pixdim": ("8f", 76),
           "vox_offset": ("f", 108), "scl_slope": ("f", 112), "scl_inter": ("f", 116), "xyzt_units": ("B", 123),
           "qform_code": ("h", 252), "sform_code": ("h", 254), "srow_x": ("4f", 280),
           "srow_y": ("4f", 296), "srow_z": ("4f", 312)}
_NIFTI2 = {"dim": ("8q", 16), "datatype": ("h", 12), "bitpix": ("h", 14), "pixdim": ("8d", 104),
           "vox_offset": ("q", 168), "scl_slope": ("d", 176), "scl_inter": ("d", 184), "xyzt_units": ("i", 500),
           "qform_code": ("i", 344), "sform_code": ("i", 348), "srow_x": ("4d", 400),
           "srow_y": ("4d", 432), "srow_z": ("4d", 464)}


def _scaled_dtype(raw: str, slope: float, inter: float) -> str:
    """As :func:`napari_unwind.io.nifti._scaled_dtype`."""
    if slope == 1 and inter == 0:
        return raw
    if raw in _INT_RANGE and float(slope).is_integer() and float(inter).is_integer():
        lo0, hi0 = _INT_RANGE[raw]
        ends = (lo0 * slope + inter, hi0 * slope + inter)
        lo, hi = min(ends), max(ends)
        for cand in (raw, "uint8", "int8", "uint16", "int16", "uint32", "int32"):
            cmin, cmax = _INT_RANGE[cand]
            if cmin <= lo and hi <= cmax:
                return cand
    itemsize, kind = _ITEMSIZE[raw], raw[0]
    return "float64" if itemsize >= 4 and kind != "f" or raw == "float64" else "float32"


def _nifti(path: Path) -> Header:
    gz = path.name.lower().endswith(".gz")
    with (gzip.open(path, "rb") if gz else open(path, "rb")) as fh:
        block = fh.read(540)
    _check(len(block) >= 348)
    for endian in "<>":
        sizeof = struct.unpack_from(endian + "i", block, 0)[0]
        if sizeof in (348, 540):
            break
    else:
        raise _Defer()
    version = 1 if sizeof == 348 else 2
    if version == 1:
        _check(block[344:348] == b"n+1\x00")
        layout, min_offset = _NIFTI1, 352
    else:
        _check(len(block) == 540 and block[4:12] == b"n+2\x00\r\n\x1a\n")
        layout, min_offset = _NIFTI2, 544

    def get(name: str) -> Any:
        fmt, offset = layout[name]
        values = struct.unpack_from(endian + fmt, block, offset)
        return values if len(values) > 1 else values[0]

    dim = get("dim")
    ndim = dim[0]
    _check(3 <= ndim <= 7 and all(n >= 1 for n in dim[1:4]) and all(n == 1 for n in dim[4:ndim + 1]))
    _check(get("datatype") in _NIFTI_TYPES)
    raw, bitpix = _NIFTI_TYPES[get("datatype")]
    _check(get("bitpix") == bitpix)
    pixdim = [float(v) for v in get("pixdim")]
    _check(pixdim[0] in (-1.0, 0.0, 1.0) and _finite_positive(pixdim[1:4]))
    vox_offset = float(get("vox_offset"))
    _check(vox_offset >= min_offset and vox_offset.is_integer())
    slope, inter = float(get("scl_slope")), float(get("scl_inter"))
    if slope == 0 or not math.isfinite(slope):
        slope, inter = 1.0, 0.0  # nibabel: no scaling
    _check(math.isfinite(inter))
    dtype = _scaled_dtype(raw, slope, inter)
    _check(dtype in _ITEMSIZE)
    xyz = get("xyzt_units") % 8
    _check(xyz in _NIFTI_UNITS)
    unit = _NIFTI_UNITS[xyz]
    # the origin from the sform (nibabel's best affine); a qform alone, whose quaternion nibabel may refuse, or
    # neither (nibabel's base affine) is left to the full reader
    _check(get("qform_code") in range(5) and get("sform_code") in range(1, 5))
    origin_ijk = [float(get(row)[3]) for row in ("srow_x", "srow_y", "srow_z")]
    _check(all(math.isfinite(o) for o in origin_ijk))
    if not gz:
        need = int(vox_offset) + math.prod(dim[1:ndim + 1]) * (bitpix // 8)
        _check(path.stat().st_size >= need)

    ni, nj, nk = dim[1:4]
    shape = (nk, nj, ni)
    plane = ni * nj * _ITEMSIZE[dtype]
    depth = max(1, min(nk, ((512 if gz else 64) * _MIB) // max(plane, 1)))
    spacing = (pixdim[3], pixdim[2], pixdim[1])
    return Header(source=str(path), format="nifti", shape=shape, dtype=dtype, spacing=spacing, unit=unit,
                  origin=(origin_ijk[2], origin_ijk[1], origin_ijk[0]), level_shapes=(shape,),
                  level_chunks=(_regular_chunks(shape, (depth, nj, ni)),), level_spacings=(spacing,))


# ------------------------------------------------------------------------------------------------------------------
# OME-Zarr (as napari_unwind.io.ome_zarr.read_ome_zarr, through zarr)
# ------------------------------------------------------------------------------------------------------------------
_V2_DTYPES = {"|u1": "uint8", "<u1": "uint8", "|i1": "int8", "<i1": "int8", "<u2": "uint16", "<i2": "int16",
              "<u4": "uint32", "<i4": "int32", "<f4": "float32", "<f8": "float64"}
_V3_ARRAY_KEYS = {"shape", "data_type", "chunk_grid", "chunk_key_encoding", "fill_value", "codecs", "attributes",
                  "dimension_names", "zarr_format", "node_type", "storage_transformers"}
_V3_CODECS = {"bytes", "blosc", "crc32c", "zstd", "gzip"}
_V2_ARRAY_KEYS = {"zarr_format", "shape", "chunks", "dtype", "compressor", "fill_value", "order", "filters",
                  "dimension_separator"}
_V2_COMPRESSORS = {"blosc", "zstd", "gzip", "zlib", "lz4"}
_JSON_LIMIT = 16 * _MIB


def _json(path: Path) -> Any:
    _check(path.is_file() and path.stat().st_size < _JSON_LIMIT)
    with open(path, "rb") as fh:
        return json.loads(fh.read())


def _ints(values: Any, minimum: int) -> list[int]:
    _check(isinstance(values, list) and all(type(v) is int and v >= minimum for v in values))
    return values


def _zarr_array(folder: Path, v3: bool) -> tuple[list[int], list[int], str]:
    """(shape, chunk shape, dtype name) of the zarr array in ``folder``."""
    if v3:
        _check(not (folder / ".zarray").exists())
        meta = _json(folder / "zarr.json")
        _check(isinstance(meta, dict) and set(meta) <= _V3_ARRAY_KEYS)
        _check(meta.get("zarr_format") == 3 and meta.get("node_type") == "array")
        _check(not meta.get("storage_transformers"))
        grid = meta["chunk_grid"]
        _check(isinstance(grid, dict) and grid.get("name") == "regular")
        chunks = _ints(grid["configuration"]["chunk_shape"], 1)
        codecs = meta["codecs"]
        _check(isinstance(codecs, list) and codecs)
        _check(all(isinstance(c, dict) and c.get("name") in _V3_CODECS for c in codecs))
        dtype = meta["data_type"]
        _check(dtype in _ITEMSIZE)
    else:
        _check(not (folder / "zarr.json").exists())
        meta = _json(folder / ".zarray")
        _check(isinstance(meta, dict) and set(meta) <= _V2_ARRAY_KEYS and meta.get("zarr_format") == 2)
        _check(meta.get("order", "C") == "C" and not meta.get("filters"))
        compressor = meta.get("compressor")
        _check(compressor is None or (isinstance(compressor, dict) and compressor.get("id") in _V2_COMPRESSORS))
        chunks = _ints(meta["chunks"], 1)
        dtype = _V2_DTYPES.get(meta["dtype"]) if isinstance(meta["dtype"], str) else None
        _check(dtype is not None)
    shape = _ints(meta["shape"], 1)
    _check(len(chunks) == len(shape))
    return shape, chunks, dtype


def _transforms(transforms: Any, ndim: int) -> tuple[list[float], list[float]]:
    """As :func:`napari_unwind.io.ome_zarr._affine`."""
    scale, offset = [1.0] * ndim, [0.0] * ndim
    _check(transforms is None or isinstance(transforms, list))
    for t in transforms or []:
        _check(isinstance(t, dict))
        kind = t.get("type")
        if kind == "identity":
            continue
        _check(kind in ("scale", "translation") and kind in t and isinstance(t[kind], list))
        _check(all(type(v) in (int, float) for v in t[kind]))
        values = [float(v) for v in t[kind]]
        _check(len(values) == ndim and all(math.isfinite(v) for v in values))
        scale, offset = compose_transform(scale, offset, kind, values)
    return scale, offset


def compose_transform(scale: list[float], offset: list[float], kind: str, values: list[float]
                      ) -> tuple[list[float], list[float]]:
    """``(scale, offset)`` after one more OME-NGFF coordinate transformation (``kind`` ``"scale"`` or
    ``"translation"``, checked ``values``): a scale multiplies the offset so far too. Shared with
    :mod:`napari_unwind.io.ome_zarr`."""
    if kind == "scale":
        return ([s * v for s, v in zip(scale, values, strict=True)],
                [o * v for o, v in zip(offset, values, strict=True)])
    return scale, [o + v for o, v in zip(offset, values, strict=True)]


def _ome_zarr(path: Path) -> Header:
    v3 = (path / "zarr.json").exists()
    if v3:
        _check(not (path / ".zgroup").exists() and not (path / ".zarray").exists())
        root = _json(path / "zarr.json")
        _check(isinstance(root, dict) and root.get("zarr_format") == 3 and root.get("node_type") == "group")
        _check(set(root) <= {"zarr_format", "node_type", "attributes", "consolidated_metadata"})
        attrs = root.get("attributes", {})
    else:
        group = _json(path / ".zgroup")
        _check(isinstance(group, dict) and group.get("zarr_format") == 2 and not (path / ".zarray").exists())
        attrs = _json(path / ".zattrs") if (path / ".zattrs").exists() else {}
    _check(isinstance(attrs, dict))
    if isinstance(attrs.get("ome"), dict) and "multiscales" in attrs["ome"]:
        multiscales = attrs["ome"]["multiscales"]
    else:
        multiscales = attrs.get("multiscales")
    _check(isinstance(multiscales, list) and multiscales and isinstance(multiscales[0], dict))
    ms = multiscales[0]
    axes = ms.get("axes", [{"name": a} for a in ("z", "y", "x")])
    _check(isinstance(axes, list) and all(isinstance(a, str) or (isinstance(a, dict) and "name" in a)
                                          for a in axes))
    space = [i for i, a in enumerate(axes) if not isinstance(a, dict) or a.get("type", "space") == "space"]
    _check(len(space) == 3)
    units = [axes[a].get("unit") if isinstance(axes[a], dict) else None for a in space]
    _check(all(u is None or str(u).strip().lower() in UNITS for u in units))
    try:
        unit, factors = axis_units(units)
    except InvalidInputError:  # lengths mixed with none: the full reader says so
        _check(False)
    g_scale, g_offset = _transforms(ms.get("coordinateTransformations", []), len(axes))
    datasets = ms["datasets"]
    _check(isinstance(datasets, list) and datasets)
    shapes, chunks, spacings, origins, dtypes = [], [], [], [], []
    for ds in datasets:
        _check(isinstance(ds, dict) and isinstance(ds.get("path"), str))
        parts = ds["path"].split("/")
        _check(all(p and p not in (".", "..") and "\\" not in p for p in parts))
        shape, chunk, dtype = _zarr_array(path.joinpath(*parts), v3)
        _check(len(shape) == len(axes))
        _check(all(shape[ax] == 1 for ax in range(len(axes)) if ax not in space))
        scale, offset = _transforms(ds.get("coordinateTransformations", []), len(axes))
        level_shape = tuple(shape[a] for a in space)
        shapes.append(level_shape)
        chunks.append(_regular_chunks(level_shape, tuple(chunk[a] for a in space)))
        spacings.append(tuple(scale[a] * g_scale[a] * f for a, f in zip(space, factors, strict=True)))
        origins.append(tuple((offset[a] * g_scale[a] + g_offset[a]) * f for a, f in zip(space, factors, strict=True)))
        dtypes.append(dtype)
    _check(all(_finite_positive(s) for s in spacings))
    return Header(source=str(path), format="ome-zarr", shape=shapes[0], dtype=dtypes[0], spacing=spacings[0],
                  unit=unit, origin=origins[0], level_shapes=tuple(shapes), level_chunks=tuple(chunks),
                  level_spacings=tuple(spacings))
