"""Raw voxels with the original Unwind ``.dat`` header.

The header is a small text file of ``Key: value`` lines (keys are case-insensitive, ``#`` starts a comment)::

    RawFile: fish.raw              (alias ObjectFileName:) the voxel file, relative to the .dat
    Resolution: 512 256 900        X Y Z, fastest axis first: the array shape is (Z, Y, X)
    Format: USHORT                 UCHAR CHAR USHORT SHORT UINT INT FLOAT DOUBLE
                                   (also UINT8 INT8 UINT16 INT16 UINT32 INT32 FLOAT32 FLOAT64)
    SliceThickness: 0.02 0.02 0.03 (alias Spacing:) voxel size X Y Z; optional, default 1 1 1
    ByteOrder: LittleEndian        or BigEndian; optional, default little endian
    Unit: mm                       optional (a napari-unwind extension)
    Origin: 0 0 0                  optional X Y Z position of the first voxel (a napari-unwind extension)

Other keys of the Voreen-style ``.dat`` files the original program came from (``TaggedFileName``,
``GridType``, ``ObjectModel: I``) are accepted and ignored; a colour ``ObjectModel`` is refused.

The voxels are read lazily: the dask array has one chunk per slab of planes, and each chunk memory-maps the
file only while it is being computed, so opening a 20 GB scan reads nothing but the header.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidInputError, OutputError
from ..progress import Progress
from ._atomic import atomic_output, final_name
from ._files import check_regular, open_regular
from ._lazy import RawFileArray, slab_depth
from ._straight_record import parse_record, record_text, straightening_record
from ._volume import UNIT_ABBREVIATIONS, Volume, normalise_unit

__all__ = ["read_dat_header", "read_raw", "write_raw"]

#: Format spellings -> numpy dtype (byte order applied separately).
FORMATS_DAT: dict[str, str] = {
    "UCHAR": "u1", "UINT8": "u1", "BYTE": "u1",
    "CHAR": "i1", "INT8": "i1",
    "USHORT": "u2", "UINT16": "u2", "USHORT_12": "u2",
    "SHORT": "i2", "INT16": "i2",
    "UINT": "u4", "UINT32": "u4",
    "INT": "i4", "INT32": "i4",
    "FLOAT": "f4", "FLOAT32": "f4",
    "DOUBLE": "f8", "FLOAT64": "f8",
}
#: The line holding the straightening record of a straight volume (napari_unwind.io._straight_record).
RECORD_KEY = "UnwindStraightening"
#: numpy dtype -> the spelling written in headers (the original program's names).
_DTYPE_FORMAT = {"u1": "UCHAR", "i1": "CHAR", "u2": "USHORT", "i2": "SHORT", "u4": "UINT", "i4": "INT",
                 "f4": "FLOAT", "f8": "DOUBLE"}
_KEY_ALIASES = {"objectfilename": "rawfile", "rawfile": "rawfile", "slicethickness": "slicethickness",
                "spacing": "slicethickness", "resolution": "resolution", "format": "format",
                "byteorder": "byteorder", "unit": "unit", "origin": "origin", "objectmodel": "objectmodel"}
#: Target bytes per dask chunk when reading and per slab when writing.
# ------------------------------------------------------------------------------------------------------------------
# the .dat header
# ------------------------------------------------------------------------------------------------------------------
def _numbers(dat: Path, lineno: int, key: str, value: str, kind: type, count: int = 3) -> list:
    parts = value.replace(",", " ").split()
    try:
        values = [kind(p) if kind is float else int(p, 10) for p in parts]
    except ValueError:
        values = []
    if len(values) != count:
        what = "whole numbers" if kind is int else "numbers"
        raise InvalidInputError(
            f"{dat}, line {lineno}: {key} needs {count} {what} (X Y Z), got {value!r}"
            + ("; napari-unwind opens 3D volumes only" if len(parts) == 2 else "")
        )
    return values


#: The largest .dat header read (a few lines of text in practice).
_DAT_LIMIT = 1 << 20


def read_dat_header(dat: str | os.PathLike) -> dict[str, Any]:
    """Parse an Unwind ``.dat`` header.

    Returns
    -------
    dict
        ``raw`` (Path of the voxel file), ``shape`` (Z, Y, X), ``dtype`` (with byte order), ``spacing``
        (Z, Y, X), ``unit`` (NGFF name or None), ``origin`` (Z, Y, X) and ``fields`` (every key as written).

    Raises
    ------
    InvalidInputError
        A malformed line, a missing key, an unknown ``Format``...: the message names the file and line.
    """
    dat = Path(dat)
    try:
        with open_regular(dat, "header") as fh:
            block = fh.read(_DAT_LIMIT + 1)
    except OSError as exc:
        raise InvalidInputError(f"cannot read the header {dat}: {exc.strerror or exc}") from None
    if len(block) > _DAT_LIMIT:
        raise InvalidInputError(f"{dat} is not a .dat header: it is larger than {_DAT_LIMIT // 1024} KiB; open the "
                                ".dat header that describes the raw file instead")
    text = block.decode("utf-8", errors="replace")
    if "\x00" in text[:4096]:
        raise InvalidInputError(f"{dat} is not a text .dat header (it holds binary data); "
                                "open the .dat header that describes the raw file instead")
    fields: dict[str, str] = {}
    found: dict[str, tuple[int, str, str]] = {}  # canonical key -> (line, key as written, value)
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        if ":" not in stripped:
            raise InvalidInputError(
                f"{dat}, line {lineno}: expected 'Key: value', got {stripped!r}; "
                "a .dat header holds lines such as 'Resolution: 512 512 300'"
            )
        key, value = (s.strip() for s in stripped.split(":", 1))
        fields[key] = value
        canon = _KEY_ALIASES.get(key.lower())
        if canon is None:
            continue  # TaggedFileName, GridType...: not needed
        if canon in found:
            raise InvalidInputError(
                f"{dat}, line {lineno}: {key!r} repeats line {found[canon][0]} ({found[canon][1]!r}); "
                "keep only one of them"
            )
        found[canon] = (lineno, key, value)

    missing = [k for k in ("rawfile", "resolution", "format") if k not in found]
    if missing:
        names = {"rawfile": "RawFile (or ObjectFileName)", "resolution": "Resolution", "format": "Format"}
        raise InvalidInputError(
            f"{dat} lacks {', '.join(names[k] for k in missing)}; a .dat header needs at least "
            "'RawFile: <name>.raw', 'Resolution: X Y Z' and 'Format: UCHAR|USHORT|SHORT|FLOAT|...'"
        )

    lineno, key, value = found["rawfile"]
    if not value:
        raise InvalidInputError(f"{dat}, line {lineno}: {key} is empty; give the raw file name")
    raw = Path(value)
    raw = raw if raw.is_absolute() else dat.parent / raw

    lineno, key, value = found["resolution"]
    xyz = _numbers(dat, lineno, key, value, int)
    if any(n < 1 for n in xyz):
        raise InvalidInputError(f"{dat}, line {lineno}: {key} sizes must be positive, got {value!r}")
    shape = (xyz[2], xyz[1], xyz[0])

    lineno, key, value = found["format"]
    fmt = value.strip().upper()
    if fmt not in FORMATS_DAT:
        raise InvalidInputError(
            f"{dat}, line {lineno}: unknown Format {value!r}; use one of "
            "UCHAR, CHAR, USHORT, SHORT, UINT, INT, FLOAT, DOUBLE"
        )
    order = "<"
    if "byteorder" in found:
        lineno, key, value = found["byteorder"]
        bo = value.strip().lower().replace("-", "").replace("_", "").replace(" ", "")
        if bo in ("littleendian", "little", "le"):
            order = "<"
        elif bo in ("bigendian", "big", "be"):
            order = ">"
        else:
            raise InvalidInputError(f"{dat}, line {lineno}: {key} must be LittleEndian or BigEndian, got {value!r}")
    dtype = np.dtype(order + FORMATS_DAT[fmt]) if FORMATS_DAT[fmt][1] != "1" else np.dtype(FORMATS_DAT[fmt])

    spacing = (1.0, 1.0, 1.0)
    if "slicethickness" in found:
        lineno, key, value = found["slicethickness"]
        sx, sy, sz = _numbers(dat, lineno, key, value, float)
        if not all(np.isfinite(s) and s > 0 for s in (sx, sy, sz)):
            raise InvalidInputError(f"{dat}, line {lineno}: {key} must be positive numbers, got {value!r}")
        spacing = (sz, sy, sx)
    origin = (0.0, 0.0, 0.0)
    if "origin" in found:
        lineno, key, value = found["origin"]
        ox, oy, oz = _numbers(dat, lineno, key, value, float)
        origin = (oz, oy, ox)
    unit = None
    if "unit" in found:
        lineno, key, value = found["unit"]
        try:
            unit = normalise_unit(value)
        except InvalidInputError as exc:
            raise InvalidInputError(f"{dat}, line {lineno}: {exc}") from None
    if "objectmodel" in found:
        lineno, key, value = found["objectmodel"]
        if value.strip().upper() not in ("I", "L", ""):
            raise InvalidInputError(
                f"{dat}, line {lineno}: ObjectModel {value!r} is a colour/multi-channel volume; "
                "napari-unwind needs one intensity per voxel (ObjectModel: I); convert it to grey first"
            )
    return {"raw": raw, "shape": shape, "dtype": dtype, "spacing": spacing, "unit": unit, "origin": origin,
            "fields": fields}


def _find_header(raw: Path) -> Path:
    """The .dat describing ``raw``: same stem first, else any .dat of the folder naming it."""
    for suffix in (".dat", ".DAT", ".Dat"):
        cand = raw.with_suffix(suffix)
        if cand.is_file():
            return cand
    for cand in sorted(raw.parent.iterdir()):
        if cand.suffix.lower() != ".dat" or not cand.is_file() or cand.stat().st_size > 65536:
            continue
        try:
            if read_dat_header(cand)["raw"].resolve() == raw.resolve():
                return cand
        except InvalidInputError:
            continue
    raise InvalidInputError(
        f"no .dat header found for {raw}: raw voxels need one to give their size and type. "
        f"Write {raw.with_suffix('.dat').name} next to it with the lines 'RawFile: {raw.name}', "
        "'Resolution: <X> <Y> <Z>', 'Format: UCHAR|USHORT|SHORT|FLOAT', 'SliceThickness: <sx> <sy> <sz>' and "
        "'Unit: mm'"
    )


# ------------------------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------------------------
def read_raw(path: Path, *, chunk_planes: int | None = None) -> Volume:
    """Open raw voxels described by an Unwind ``.dat`` header, lazily.

    Parameters
    ----------
    path : Path
        The ``.dat`` header, or the ``.raw`` file (its header is then the ``.dat`` of the same stem, or any
        ``.dat`` of the folder naming it).
    chunk_planes : int, optional
        Planes per dask chunk (default: about 64 MB per chunk).

    Returns
    -------
    Volume
        Shape (Z, Y, X) (``Resolution`` is written X Y Z), spacing (Z, Y, X) from ``SliceThickness``, the unit
        from ``Unit`` (None when absent), ``format="raw"``.

    Raises
    ------
    InvalidInputError
        No header, a malformed header, a missing or truncated raw file. A raw file larger than the header
        implies is read with a warning (the extra bytes are ignored).
    """
    path = Path(path).expanduser().absolute()  # workers of a cluster run in other folders
    dat = path if path.suffix.lower() == ".dat" else _find_header(path)
    header = read_dat_header(dat)
    raw: Path = header["raw"]
    check_regular(raw, "raw")
    if not raw.is_file():
        raise InvalidInputError(f"{dat} names the raw file {raw}, which does not exist; is the copy complete?")
    shape, dtype = header["shape"], header["dtype"]
    expected = int(np.prod(shape)) * dtype.itemsize
    found = raw.stat().st_size
    if found < expected:
        x, y, z = shape[2], shape[1], shape[0]
        raise InvalidInputError(
            f"truncated raw file {raw}: expected {expected} bytes ({x} x {y} x {z} x {dtype.itemsize}), "
            f"found {found}; the copy is probably incomplete"
        )
    if found > expected:
        warnings.warn(
            f"{raw} holds {found} bytes but {dat.name} describes {expected}; reading the first {expected} bytes "
            "and ignoring the rest (check Resolution and Format if the volume looks wrong)",
            stacklevel=2,
        )
    if chunk_planes is not None and int(chunk_planes) < 1:
        raise InvalidInputError(f"chunk_planes must be >= 1, got {chunk_planes}")
    data = RawFileArray(raw, dtype, shape).to_lazy(depth=chunk_planes)  # dask built on first use
    return Volume(data, spacing=header["spacing"], unit=header["unit"], origin=header["origin"],
                  source=str(path), format="raw",
                  metadata={"header": str(dat), "raw": str(raw), "byteorder": "big" if dtype.byteorder == ">"
                            else "little", "dat_fields": header["fields"],
                            **({"unwind": {"straightening": parse_record(header["fields"][RECORD_KEY])}}
                               if parse_record(header["fields"].get(RECORD_KEY)) else {})})


# ------------------------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------------------------
def _fmt(v: float) -> str:
    return repr(float(v))  # shortest text that reads back to the same float


def dat_text(volume: Volume, raw_name: str, *, byteorder: str = "little") -> str:
    """The text of the ``.dat`` header describing ``volume`` stored in ``raw_name``."""
    z, y, x = volume.shape
    sz, sy, sx = volume.spacing
    lines = [
        f"RawFile: {raw_name}",
        f"Resolution: {x} {y} {z}",
        f"SliceThickness: {_fmt(sx)} {_fmt(sy)} {_fmt(sz)}",
        f"Format: {_DTYPE_FORMAT[volume.dtype.str[1:]]}",
        f"ByteOrder: {'BigEndian' if byteorder == 'big' else 'LittleEndian'}",
    ]
    if volume.unit:
        lines.append(f"Unit: {UNIT_ABBREVIATIONS.get(volume.unit, volume.unit)}")
    if any(volume.origin):
        oz, oy, ox = volume.origin
        lines.append(f"Origin: {_fmt(ox)} {_fmt(oy)} {_fmt(oz)}")
    record = straightening_record(volume)
    if record is not None:  # a key the original program ignores, as it ignores TaggedFileName
        lines.append(f"{RECORD_KEY}: {record_text(record)}")
    return "\n".join(lines) + "\n"


def write_raw(
    volume: Volume,
    path: Path,
    *,
    byteorder: str = "little",
    overwrite: bool = False,
) -> Iterator[Progress]:
    """Write ``volume`` as a ``.raw`` voxel file plus its ``.dat`` header, slab by slab.

    ``path`` is the output :func:`~napari_unwind.io.write_volume` renames into place (usually a temporary
    ``.fish.dat.<hex8>.unwind-tmp``); the name it will get (``fish.dat`` or ``fish.raw``) decides the pair:
    ``fish.dat`` + ``fish.raw``. The companion file is written through its own temporary name and renamed into
    place here; the voxels are always complete before the header that describes them is written.

    Parameters
    ----------
    volume : Volume
        What to write; integer or float voxels (``Format`` UCHAR ... DOUBLE).
    path : Path
        The main output (``.dat`` or ``.raw``).
    byteorder : {"little", "big"}
        Byte order of the voxels (default little endian, what the original program wrote).
    overwrite : bool
        Replace an existing companion file. Without it, an existing companion is replaced only when the main
        target exists too (the caller then already agreed to overwrite the pair).

    Yields
    ------
    Progress
        One record per slab of planes written.
    """
    if byteorder not in ("little", "big"):
        raise InvalidInputError(f"byteorder must be 'little' or 'big', got {byteorder!r}")
    path = Path(path)
    target = path.with_name(final_name(path))
    suffix = target.suffix.lower()
    if suffix not in (".dat", ".raw"):
        raise InvalidInputError(f"a raw volume is written as <name>.dat + <name>.raw; got the name {target.name}")
    key = volume.dtype.str[1:]
    if key not in _DTYPE_FORMAT:
        raise InvalidInputError(f"the .dat format cannot store {volume.dtype} voxels")
    dat_final = target.with_suffix(".dat")
    raw_final = target.with_suffix(".raw")
    companion = raw_final if suffix == ".dat" else dat_final
    if companion.exists() and not (overwrite or target.exists()):
        raise OutputError(
            f"{companion} already exists and writing {target.name} would replace it; "
            "remove it, pass overwrite=True or choose another name"
        )
    stored = np.dtype(("<" if byteorder == "little" else ">") + key) if volume.dtype.itemsize > 1 else volume.dtype
    header = dat_text(volume, raw_final.name, byteorder=byteorder)

    def stream(dst: Path) -> Iterator[Progress]:
        n = volume.shape[0]
        depth = slab_depth(volume.shape[1:], volume.dtype)
        total = -(-n // depth)
        with open(dst, "wb") as fh:
            for i, z0 in enumerate(range(0, n, depth)):
                z1 = min(n, z0 + depth)
                slab = np.asarray(volume.data[z0:z1].compute())
                fh.write(np.ascontiguousarray(slab, dtype=stored).tobytes(order="C"))
                del slab
                yield Progress("write raw", i + 1, total, f"planes {z0}-{z1 - 1} of {n}")
            fh.flush()
            os.fsync(fh.fileno())

    if suffix == ".dat":
        # voxels first (companion, renamed into place when complete), then the header the caller renames
        with atomic_output(raw_final, overwrite=True) as raw_tmp:
            yield from stream(raw_tmp)
            path.write_text(header, encoding="utf-8")
    else:
        yield from stream(path)
        with atomic_output(dat_final, overwrite=True) as dat_tmp:
            dat_tmp.write_text(header, encoding="utf-8")
