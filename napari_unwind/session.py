"""The session file (``*.unwind.json``): what was done to which scan, so a straight fish traces back to its raw scan.

A session records

- the **source scan**: absolute path, a content checksum, size in bytes, shape, dtype, spacing, unit and format
  (:class:`SourceInfo`). A session a server job wrote names the scan by its file name alone (the server's paths
  mean nothing elsewhere): :func:`load_session` takes a relative path as relative to the session file's folder,
  so a session downloaded next to its scan finds it;
- the **deformation** (:class:`~napari_unwind.deformation.Deformation`, stored with its own ``to_dict`` layout);
- the **segmentation selection** (:class:`Segmentation`) and the **endpoints** (:class:`Endpoints`);
- the software name and version, ``created`` / ``modified`` timestamps (ISO 8601, UTC) and free-text notes.

Files are pretty JSON (sorted keys, indent 2) so that diffs in version control stay readable, written atomically
(:func:`save_session`), never holding NaN or infinity. Every file read passes :mod:`napari_unwind._json` (safe
parsing, then ``napari_unwind/schemas/session.schema.json``). :func:`load_session` refuses a damaged file with a
message naming the file and what is wrong, refuses a file from a newer napari-unwind, and migrates an older schema
through :data:`_MIGRATIONS`. :func:`verify_source` checks that the scan is still there and unchanged.

Schema 2 (``"schema": "napari-unwind/session"``, ``"schema_version": 2``)::

    {
      "schema": "napari-unwind/session", "schema_version": 2,
      "software": {"name": "napari-unwind", "version": "0.1.0"},
      "created": "2025-01-31T12:00:00.000Z", "modified": "2025-01-31T12:05:00.000Z",
      "source": {"path": "/data/fish.zarr", "checksum": "sha256:<64 hex>", "size": 123456, "shape": [Z, Y, X],
                 "dtype": "uint16", "spacing": [sz, sy, sx], "unit": "micrometer", "format": "ome-zarr"},
      "deformation": {... Deformation.to_dict() ...} or null,
      "segmentation": {"k": 5, "level": 2, "selected": [3, 7], "seeds": [[z, y, x], ...], "isovalue": 812.0,
                       "fill_holes": true} or null,
          (or, when a mask was the selection: {"mask": "/data/fish_mask.nrrd", "mask_label": 2 or null})
      "endpoints": {"head": [z, y, x], "tail": [z, y, x], "chain": [[[z, y, x], [z, y, x]], ...]} or null,
      "notes": ""
    }

Schema 1 is the same with a deformation of schema ``napari-unwind/deformation/1``: keyframe cages centred on the
curve (no ``"offset"``). It migrates with zero offsets (an offset a keyframe carries anyway is kept). A schema-2
file is refused by a napari-unwind that reads schema 1 at most (it is "written by a newer napari-unwind"), so
per-side cages are never silently dropped.

Schema 0 is the pre-release layout: one flat object with no ``schema`` key, recognised by its ``source_path``::

    {"source_path": "/data/fish.tif", "shape": [Z, Y, X], "dtype": "uint16", "spacing": [sz, sy, sx],
     "unit": "micrometer",                      (optional)
     "keyframes": [{"position": [...], "frame": [[u], [v], [n]], "half_extent": [rx, ry]}, ...],  (physical units)
     "pad": [before, after],                    (optional)
     "head": [z, y, x], "tail": [z, y, x],      (optional, voxels)
     "k": 5, "level": 2, "selected": [3, 7], "isovalue": 812.0,   (optional)
     "napari_unwind_version": "0.0.1.dev3", "saved": "2024-11-02T10:00:00",  (a naive time, taken as UTC)
     "notes": ""}                               (optional)

It had no checksum: a migrated session's ``source.checksum`` is None, and :func:`verify_source` then checks shape,
dtype and spacing only, warns, and returns the checksum so that saving again records it.

Checksums (:func:`checksum`) are ``"sha256:<hex>"``:

- a single file: the SHA-256 of its bytes (the same as ``sha256sum FILE``);
- a folder (OME-Zarr, DICOM series, slice stack) or a file with companions: the SHA-256 of a manifest that lists,
  sorted by relative path (``/`` separators, Unicode NFC), one line ``"<sha256 of the file>  <relative path>\\n"`` per
  file, i.e. ``find . -type f | sort | xargs sha256sum | sha256sum`` run inside the folder. Hidden operating-system
  files (``.DS_Store``, ``._*``, ``Thumbs.db``...) and our ``.unwind-tmp`` temporaries are left out; other hidden
  files are content (zarr v2's ``.zarray``). The order files were created in does not matter.

Companions of a file are found with the readers' knowledge: an NRRD header (``.nhdr`` or ``.nrrd``) brings every
file its ``data file`` field names (one name, ``LIST`` or a ``printf`` pattern with min/max/step); a ``.dat`` header
brings the ``.raw`` it names and a ``.raw`` the ``.dat`` describing it; one numbered slice of a stack brings the
whole stack; one DICOM file brings the DICOM files of its folder. Companion paths in the manifest are relative to
the folder of the file given (so ``checksum("fish.dat") == checksum("fish.raw")``).

Everything is streamed in blocks of 8 MiB: memory stays bounded for a 45 GB scan.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import unicodedata
import warnings
from collections.abc import Callable, Generator
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from . import _json
from .deformation import SCHEMA as DEFORMATION_SCHEMA
from .deformation import Deformation
from .errors import InvalidInputError, OutputError, UnwindError, source_date_epoch
from .io import Volume, detect_format, open_volume
from .io._atomic import TMP_MARK, atomic_output
from .io._volume import SUPPORTED_DTYPES, normalise_unit
from .progress import Progress, run

__all__ = [
    "SCHEMA_ID",
    "SCHEMA_VERSION",
    "SESSION_SUFFIX",
    "Endpoints",
    "Segmentation",
    "TwistProfile",
    "Session",
    "SourceChangedError",
    "SourceInfo",
    "SourceMissingError",
    "checksum",
    "checksum_iter",
    "load_session",
    "save_session",
    "verify_source",
]

#: Identifies a session file.
SCHEMA_ID = "napari-unwind/session"
#: The schema version this napari-unwind writes.
SCHEMA_VERSION = 2
#: Every session file name ends with this.
SESSION_SUFFIX = ".unwind.json"
SOFTWARE = "napari-unwind"

_BLOCK = 8 * 2**20  # bytes read and hashed at a time
_MAX_SCHEMA_VERSION = 1000  # the bound of session.schema.json
_MAX_SESSION_BYTES = 64 * 2**20  # a session is a few kB; anything this large is not one
_CHECKSUM_RE = re.compile(r"^sha256:[0-9a-f]{64}$")
# operating-system litter that is never part of a scan
_IGNORED_NAMES = frozenset({
    ".DS_Store", ".Spotlight-V100", ".Trashes", ".fseventsd", ".TemporaryItems", ".DocumentRevisions-V100",
    ".AppleDouble", "Icon\r", "Thumbs.db", "ehthumbs.db", "desktop.ini", "$RECYCLE.BIN",
})


class SourceMissingError(InvalidInputError):
    """The scan a session was made from is not where the session says (moved, renamed, unmounted)."""


class SourceChangedError(InvalidInputError):
    """The scan at the session's path is not the one the session was made from (its content changed)."""


# ------------------------------------------------------------------------------------------------------------------
# checksums
# ------------------------------------------------------------------------------------------------------------------
def _ignored(name: str) -> bool:
    return name in _IGNORED_NAMES or name.startswith("._") or name.endswith(TMP_MARK)


def _rel(path: Path, root: Path) -> str:
    try:
        rel = Path(os.path.relpath(path, root)).as_posix()
    except ValueError:  # another drive (Windows): keep it absolute
        rel = path.absolute().as_posix()
    return unicodedata.normalize("NFC", rel)


def _tree_files(folder: Path) -> list[tuple[str, Path]]:
    def fail(exc: OSError) -> None:
        raise InvalidInputError(f"cannot list {exc.filename}: {exc.strerror or exc}")

    members = []
    for root, dirs, files in os.walk(folder, onerror=fail):
        dirs[:] = [d for d in dirs if not _ignored(d)]
        for name in files:
            p = Path(root) / name
            if not _ignored(name) and p.is_file():  # skips sockets, fifos and broken links
                members.append((_rel(p, folder), p))
    return members


def _nrrd_data_files(header: Path) -> list[Path]:
    """Every file the ``data file`` field of an NRRD header names (single name, ``LIST`` or printf pattern)."""
    names: list[str] = []
    listing = False
    with open(header, "rb") as fh:
        if not fh.readline(64).startswith(b"NRRD"):
            return []
        while fh.tell() < 16 * 2**20:
            raw = fh.readline(65536)
            if not raw:
                break
            line = raw.decode("latin-1").rstrip("\r\n")
            if listing:  # 'data file: LIST' is the last field; file names follow, one a line
                if line.strip():
                    names.append(line.strip())
                continue
            if not line.strip():
                break  # end of the header (an attached .nrrd's voxels follow)
            if line.startswith("#") or ":=" in line:
                continue
            key, _, value = line.partition(":")
            if key.strip().lower() not in ("data file", "datafile"):
                continue
            parts = value.split()
            if parts and parts[0].upper() == "LIST":
                listing = True
            elif len(parts) >= 4 and "%" in parts[0]:
                try:
                    lo, hi, step = int(parts[1]), int(parts[2]), int(parts[3])
                    if step == 0:
                        raise ValueError("step 0")
                    names = [parts[0] % i for i in range(lo, hi + (1 if step > 0 else -1), step)]
                except (ValueError, TypeError) as exc:
                    raise InvalidInputError(
                        f"{header}: cannot expand the data file pattern {value.strip()!r} ({exc}); "
                        "fix the header's 'data file' field"
                    ) from None
            elif value.strip():
                names = [value.strip()]
    return [Path(n) if Path(n).is_absolute() else header.parent / n for n in names]


def _companions(path: Path) -> list[Path]:
    """The other files holding part of the scan ``path`` names (see the module docstring)."""
    try:
        fmt = detect_format(path)
    except UnwindError:
        return []
    if fmt == "nrrd":
        return _nrrd_data_files(path)
    if fmt == "raw":
        from .io import raw as raw_io

        try:
            if path.suffix.lower() == ".dat":
                return [raw_io.read_dat_header(path)["raw"]]
            return [raw_io._find_header(path)]
        except InvalidInputError:
            return []  # not readable as a scan: the file alone is what there is
    if fmt == "stack":
        from .io.stack import numbered_siblings

        return numbered_siblings(path)
    if fmt == "dicom":
        from .io._formats import _is_dicom_file

        return [p for p in path.parent.iterdir()
                if p.is_file() and not _ignored(p.name) and (p.suffix.lower() == ".dcm" or _is_dicom_file(p))]
    return []


def scan_members(path: str | os.PathLike) -> list[Path]:
    """The other files a scan file brings with it (as they are named, not resolved): an NRRD header's data files,
    a ``.dat`` header's raw file (or a raw file's header), a stack's numbered siblings, a DICOM series' files.
    Empty for a file that names no other."""
    return [Path(p) for p in _companions(Path(path).expanduser())]


def _source_files(path: str | os.PathLike) -> tuple[list[tuple[str, Path, int]], bool]:
    """The files making up a scan as ``(relative name, path, size)``, sorted, and whether a manifest is hashed."""
    path = Path(path).expanduser()
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist")
    if path.is_dir():
        members = _tree_files(path)
        if not members:
            raise InvalidInputError(f"{path} is an empty folder: there is no scan in it to checksum")
        manifest = True
    elif path.is_file():
        found = {path.resolve(): (unicodedata.normalize("NFC", path.name), path)}
        for c in _companions(path):
            if not c.is_file():
                raise SourceMissingError(
                    f"{path} needs its data file {c}, which does not exist; copy it next to {path.name} "
                    "(or correct the file name in the header)"
                )
            found.setdefault(c.resolve(), (_rel(c, path.parent), c))
        members = list(found.values())
        manifest = len(members) > 1
    else:
        raise InvalidInputError(f"{path} is neither a file nor a folder; point at the scan")
    members.sort(key=lambda m: m[0])
    return [(rel, p, p.stat().st_size) for rel, p in members], manifest


def _digest_iter(members: list[tuple[str, Path, int]], manifest: bool) -> Generator[Progress, None, tuple[str, int]]:
    """Hash ``members`` block by block; returns ``("sha256:<hex>", bytes read)``."""
    total = sum(size for _, _, size in members)
    buf = bytearray(_BLOCK)
    view = memoryview(buf)
    done = 0
    lines = []
    yield Progress("checksum", 0, total, members[0][0] if members else "")
    for rel, p, size in members:
        h = hashlib.sha256()
        n_file = 0
        try:
            with open(p, "rb", buffering=0) as fh:
                while n := fh.readinto(buf):
                    h.update(view[:n])
                    n_file += n
                    done += n
                    yield Progress("checksum", done, total, rel)
        except OSError as exc:
            raise InvalidInputError(f"cannot read {p} to checksum it: {exc.strerror or exc}") from None
        if n_file != size:
            raise InvalidInputError(
                f"{p} changed while it was being checksummed ({size} bytes, then {n_file}); "
                "is it still being copied or written? Try again once it is complete"
            )
        lines.append(f"{h.hexdigest()}  {rel}\n")
        if not manifest:
            return f"sha256:{h.hexdigest()}", done
    return "sha256:" + hashlib.sha256("".join(lines).encode("utf-8")).hexdigest(), done


def checksum_iter(path: str | os.PathLike) -> Generator[Progress, None, str]:
    """Generator form of :func:`checksum`: yields progress in bytes, returns ``"sha256:<hex>"``."""
    members, manifest = _source_files(path)
    digest, _ = yield from _digest_iter(members, manifest)
    return digest


def checksum(path: str | os.PathLike, progress: Callable[[Progress], Any] | None = None) -> str:
    """Content checksum of a scan: a file, a file with its companions, or a folder tree.

    Parameters
    ----------
    path : str or path-like
        A scan file (``.tif``, ``.nrrd``, ``.nhdr``, ``.dat``...) or folder (OME-Zarr, DICOM series, slice stack).
    progress : callable, optional
        Called with :class:`~napari_unwind.progress.Progress` records (``done``/``total`` in bytes).

    Returns
    -------
    str
        ``"sha256:<64 hex digits>"``; how files and folders are hashed is described in the module docstring.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    SourceMissingError
        A companion file a header names (``.nhdr`` data file, ``.dat`` raw file) does not exist.
    InvalidInputError
        An empty folder, an unreadable file, or a file that changed while it was being read.
    """
    return run(checksum_iter(path), progress)


# ------------------------------------------------------------------------------------------------------------------
# validation helpers: every message names the field ("source.shape") and the value received
# ------------------------------------------------------------------------------------------------------------------
def _json_kind(value: Any) -> str:
    return {dict: "an object", list: "a list", tuple: "a list", str: "a string", bool: "a boolean", int: "a number",
            float: "a number", type(None): "null"}.get(type(value), type(value).__name__)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidInputError(f"{where} must be a number, got {_json_kind(value)} ({value!r})")
    value = float(value)
    if not math.isfinite(value):
        raise InvalidInputError(f"{where} must be a finite number, got {value}")
    return value


def _integer(value: Any, where: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InvalidInputError(f"{where} must be an integer >= {minimum}, got {_json_kind(value)} ({value!r})")
    if int(value) < minimum:
        raise InvalidInputError(f"{where} must be an integer >= {minimum}, got {int(value)}")
    return int(value)


def _sequence(value: Any, where: str, length: int | None = None, what: str = "values") -> list:
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)):
        raise InvalidInputError(f"{where} must be a list of {what}, got {_json_kind(value)} ({value!r})")
    if length is not None and len(value) != length:
        raise InvalidInputError(f"{where} must hold {length} {what}, got {len(value)}: {value!r}")
    return list(value)


def _point(value: Any, where: str) -> tuple[float, float, float]:
    items = _sequence(value, where, 3, "coordinates (axis0, axis1, axis2)")
    return tuple(_number(v, f"{where}[{i}]") for i, v in enumerate(items))  # type: ignore[return-value]


def _string(value: Any, where: str, *, optional: bool = False) -> str | None:
    if value is None and optional:
        return None
    if not isinstance(value, str):
        raise InvalidInputError(f"{where} must be a string, got {_json_kind(value)} ({value!r})")
    return value


def _utcnow() -> str:
    """Now, or the time of ``SOURCE_DATE_EPOCH`` when that is set (:func:`~napari_unwind.errors.source_date_epoch`),
    so that two runs of the same job give byte-identical sessions and straightened volumes (whose metadata embeds
    the session)."""
    epoch = source_date_epoch()
    return _format_time(datetime.now(UTC) if epoch is None else datetime.fromtimestamp(epoch, UTC))


def _format_time(t: datetime) -> str:
    return t.astimezone(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _timestamp(value: Any, where: str) -> str:
    if isinstance(value, datetime):
        t = value
    else:
        _string(value, where)
        try:
            t = datetime.fromisoformat(value)
        except ValueError:
            raise InvalidInputError(
                f"{where} must be an ISO 8601 time such as 2025-01-31T12:00:00Z, got {value!r}"
            ) from None
    if t.tzinfo is None:
        raise InvalidInputError(f"{where} must say its time zone (UTC: a trailing Z), got {value!r}")
    return _format_time(t)


def _require(d: dict, key: str, where: str) -> Any:
    if key not in d:
        raise InvalidInputError(f"{where}.{key} is missing" if where else f"the field {key!r} is missing")
    return d[key]


def _object(value: Any, where: str) -> dict:
    if not isinstance(value, dict):
        raise InvalidInputError(f"{where} must be an object, got {_json_kind(value)}")
    return value


def _current_version() -> str:
    from . import __version__  # at call time: the package may import this module while it initialises

    return str(__version__)


# ------------------------------------------------------------------------------------------------------------------
# the records
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SourceInfo:
    """Where a session's scan is and what it holds.

    Attributes
    ----------
    path : str
        Absolute path of the scan as it was opened (a file, or a folder for OME-Zarr, DICOM, slice stacks).
    checksum : str or None
        ``"sha256:<hex>"`` of its content (see :func:`checksum`); None only in sessions migrated from schema 0.
    size : int or None
        Total bytes of the files hashed (None when unknown).
    shape : tuple of 3 int
        Array shape (axis0, axis1, axis2) at full resolution.
    dtype : str
        Voxel type name (``"uint16"``...).
    spacing : tuple of 3 float
        Voxel size in array axis order, as the session used it (given by hand for formats that do not store it).
    unit : str or None
        NGFF length unit name.
    format : str or None
        The reader that opened it (a key of ``napari_unwind.io.FORMATS``).
    channel : str or None
        For one channel of a multi-channel file: the channel's name (None for a single-channel image).
    """

    path: str
    shape: tuple[int, int, int]
    dtype: str
    spacing: tuple[float, float, float]
    unit: str | None = None
    checksum: str | None = None
    size: int | None = None
    format: str | None = None
    channel: str | None = None

    def __post_init__(self) -> None:
        path = os.fspath(self.path) if isinstance(self.path, os.PathLike) else self.path
        if not _string(path, "source.path"):
            raise InvalidInputError("source.path must not be empty")
        object.__setattr__(self, "path", path)
        shape = _sequence(self.shape, "source.shape", 3, "sizes")
        object.__setattr__(self, "shape", tuple(_integer(s, f"source.shape[{i}]", 1) for i, s in enumerate(shape)))
        if not isinstance(self.dtype, (str, np.dtype, type)):
            raise InvalidInputError(f"source.dtype must be a string such as 'uint16', got {_json_kind(self.dtype)} "
                                    f"({self.dtype!r})")
        try:
            dtype = np.dtype(self.dtype)
        except TypeError:
            raise InvalidInputError(f"source.dtype: {self.dtype!r} is not a voxel type") from None
        if dtype not in SUPPORTED_DTYPES:
            raise InvalidInputError(f"source.dtype must be one of {', '.join(d.name for d in SUPPORTED_DTYPES)}, "
                                    f"got {self.dtype!r}")
        object.__setattr__(self, "dtype", dtype.name)
        spacing = tuple(_number(s, f"source.spacing[{i}]")
                        for i, s in enumerate(_sequence(self.spacing, "source.spacing", 3, "numbers")))
        if not all(s > 0 for s in spacing):
            raise InvalidInputError(f"source.spacing must be positive, got {spacing}")
        object.__setattr__(self, "spacing", spacing)
        try:
            object.__setattr__(self, "unit", normalise_unit(_string(self.unit, "source.unit", optional=True)))
        except InvalidInputError as exc:
            raise InvalidInputError(f"source.unit: {exc}") from None
        if self.checksum is not None and not (isinstance(self.checksum, str) and _CHECKSUM_RE.match(self.checksum)):
            raise InvalidInputError(f"source.checksum must look like 'sha256:<64 hex digits>', got {self.checksum!r}")
        if self.size is not None:
            object.__setattr__(self, "size", _integer(self.size, "source.size", 0))
        _string(self.format, "source.format", optional=True)
        _string(self.channel, "source.channel", optional=True)

    @classmethod
    def from_path(
        cls,
        path: str | os.PathLike,
        *,
        volume: Volume | None = None,
        progress: Callable[[Progress], Any] | None = None,
    ) -> SourceInfo:
        """Describe the scan at ``path``, checksum included (reads every byte once, in blocks).

        Parameters
        ----------
        path : str or path-like
            The scan, as given to :func:`~napari_unwind.io.open_volume`.
        volume : Volume, optional
            The scan already opened (with any reader options or a spacing given by hand); default: opened here,
            lazily (only headers are read).
        progress : callable, optional
            Called with the checksum's :class:`~napari_unwind.progress.Progress` records (bytes).
        """
        p = Path(os.path.abspath(Path(path).expanduser()))
        if not p.exists():
            raise FileNotFoundError(f"{p} does not exist")
        if volume is None:
            volume = open_volume(p)
        elif not isinstance(volume, Volume):
            raise InvalidInputError(f"volume must be a napari_unwind Volume, got {type(volume).__name__}")
        members, manifest = _source_files(p)
        digest, size = run(_digest_iter(members, manifest), progress)
        channel = volume.metadata.get("channel") if isinstance(volume.metadata, dict) else None
        return cls(path=str(p), shape=tuple(volume.shape), dtype=np.dtype(volume.dtype).name,
                   spacing=volume.spacing, unit=volume.unit, checksum=digest, size=size, format=volume.format,
                   channel=str(channel) if channel else None)

    def to_dict(self) -> dict[str, Any]:
        return {"path": self.path, "checksum": self.checksum, "size": self.size, "shape": list(self.shape),
                "dtype": self.dtype, "spacing": list(self.spacing), "unit": self.unit, "format": self.format,
                **({"channel": self.channel} if self.channel is not None else {})}

    @classmethod
    def from_dict(cls, d: Any) -> SourceInfo:
        d = _object(d, "source")
        return cls(path=_require(d, "path", "source"), shape=_require(d, "shape", "source"),
                   dtype=_require(d, "dtype", "source"), spacing=_require(d, "spacing", "source"),
                   unit=d.get("unit"), checksum=d.get("checksum"), size=d.get("size"), format=d.get("format"),
                   channel=d.get("channel"))


@dataclass(frozen=True)
class Segmentation:
    """The segmentation selection that made the specimen mask (every field optional).

    Attributes
    ----------
    k : int or None
        Number of features kept after simplifying the join tree.
    level : int or None
        Pyramid level the join tree was computed on (0 = full resolution).
    selected : tuple of int
        Ids of the features the user selected.
    seeds : tuple of (3,) float
        Seed points, scan voxel coordinates at full resolution, array axis order.
    isovalue : float or None
        Intensity threshold of the mask.
    fill_holes : bool or None
        Whether holes of the mask were filled.
    mask : str or None
        Instead of features: the mask file that was the selection (absolute path; a Labels layer without a file
        is written beside the session by the plugin).
    mask_label : int or None
        The label of ``mask`` that was the selection (None: every non-zero voxel).
    """

    k: int | None = None
    level: int | None = None
    selected: tuple[int, ...] = ()
    seeds: tuple[tuple[float, float, float], ...] = ()
    isovalue: float | None = None
    fill_holes: bool | None = None
    mask: str | None = None
    mask_label: int | None = None

    def __post_init__(self) -> None:
        if self.mask is not None:
            _string(self.mask, "segmentation.mask")
            if not self.mask:
                raise InvalidInputError("segmentation.mask must be a file path or null, got an empty string")
        if self.mask_label is not None:
            object.__setattr__(self, "mask_label", _integer(self.mask_label, "segmentation.mask_label", 1))
            if self.mask is None:
                raise InvalidInputError("segmentation.mask_label is given without segmentation.mask: give the mask "
                                        "file, or remove the label")
        if self.k is not None:
            object.__setattr__(self, "k", _integer(self.k, "segmentation.k", 1))
        if self.level is not None:
            object.__setattr__(self, "level", _integer(self.level, "segmentation.level", 0))
        selected = _sequence(() if self.selected is None else self.selected, "segmentation.selected",
                             what="feature ids")
        object.__setattr__(self, "selected",
                           tuple(_integer(v, f"segmentation.selected[{i}]", 0) for i, v in enumerate(selected)))
        seeds = _sequence(() if self.seeds is None else self.seeds, "segmentation.seeds", what="points")
        object.__setattr__(self, "seeds", tuple(_point(p, f"segmentation.seeds[{i}]") for i, p in enumerate(seeds)))
        if self.isovalue is not None:
            object.__setattr__(self, "isovalue", _number(self.isovalue, "segmentation.isovalue"))
        if self.fill_holes is not None and not isinstance(self.fill_holes, (bool, np.bool_)):
            raise InvalidInputError(f"segmentation.fill_holes must be true or false, got {self.fill_holes!r}")
        if self.fill_holes is not None:
            object.__setattr__(self, "fill_holes", bool(self.fill_holes))

    def to_dict(self) -> dict[str, Any]:
        d = {"k": self.k, "level": self.level, "selected": list(self.selected),
             "seeds": [list(p) for p in self.seeds], "isovalue": self.isovalue, "fill_holes": self.fill_holes}
        if self.mask is not None:  # written only when used: files without it stay as they were
            d.update(mask=self.mask, mask_label=self.mask_label)
        return d

    @classmethod
    def from_dict(cls, d: Any) -> Segmentation:
        d = _object(d, "segmentation")
        return cls(k=d.get("k"), level=d.get("level"), selected=d.get("selected", ()), seeds=d.get("seeds", ()),
                   isovalue=d.get("isovalue"), fill_holes=d.get("fill_holes"), mask=d.get("mask"),
                   mask_label=d.get("mask_label"))


@dataclass(frozen=True)
class Endpoints:
    """Where the specimen starts and ends, in scan voxel coordinates (full resolution, array axis order).

    Attributes
    ----------
    head, tail : tuple of 3 float
        The two ends of the specimen.
    chain : tuple of ((3,), (3,)) pairs
        For a specimen in disconnected parts: the ``(start, end)`` of each part, in order from head to tail
        (the first part starts at ``head``, the last ends at ``tail``); empty when it is in one piece.
    """

    head: tuple[float, float, float]
    tail: tuple[float, float, float]
    chain: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "head", _point(self.head, "endpoints.head"))
        object.__setattr__(self, "tail", _point(self.tail, "endpoints.tail"))
        if self.head == self.tail:
            raise InvalidInputError(f"endpoints.head and endpoints.tail are the same point {self.head}")
        pairs = _sequence(() if self.chain is None else self.chain, "endpoints.chain", what="(start, end) pairs")
        chain = []
        for i, pair in enumerate(pairs):
            a, b = _sequence(pair, f"endpoints.chain[{i}]", 2, "points (start, end)")
            chain.append((_point(a, f"endpoints.chain[{i}][0]"), _point(b, f"endpoints.chain[{i}][1]")))
        object.__setattr__(self, "chain", tuple(chain))

    def to_dict(self) -> dict[str, Any]:
        return {"head": list(self.head), "tail": list(self.tail),
                "chain": [[list(a), list(b)] for a, b in self.chain]}

    @classmethod
    def from_dict(cls, d: Any) -> Endpoints:
        d = _object(d, "endpoints")
        return cls(head=_require(d, "head", "endpoints"), tail=_require(d, "tail", "endpoints"),
                   chain=d.get("chain", ()))


TWIST_SOURCES = ("estimated", "landmarks", "none")


@dataclass(frozen=True)
class TwistProfile:
    """How the skeleton turned the frames about the curve, for the record (the deformation's keyframes carry the
    twist itself).

    Attributes
    ----------
    s : tuple of float
        Arclengths (physical units), increasing, at most :data:`TWIST_STATIONS` stations.
    angle : tuple of float
        The twist at each (degrees) relative to the parallel-transport (minimal-rotation) frames.
    confidence : tuple of float
        In [0, 1]: 1 where the cross-sections' orientation (or the landmarks) set the twist, 0 where the frames
        follow parallel transport.
    source : {"estimated", "landmarks", "none"}
        What set it.
    """

    s: tuple[float, ...]
    angle: tuple[float, ...]
    confidence: tuple[float, ...]
    source: str = "estimated"

    def __post_init__(self) -> None:
        for name in ("s", "angle", "confidence"):
            values = _sequence(getattr(self, name), f"twist.{name}")
            object.__setattr__(self, name, tuple(_number(v, f"twist.{name}[{i}]") for i, v in enumerate(values)))
        if not len(self.s) == len(self.angle) == len(self.confidence):
            raise InvalidInputError(f"twist.s, twist.angle and twist.confidence must be as long as each other, got "
                                    f"{len(self.s)}, {len(self.angle)} and {len(self.confidence)}")
        if any(b <= a for a, b in zip(self.s, self.s[1:], strict=False)):
            raise InvalidInputError("twist.s must increase")
        if any(not 0 <= c <= 1 for c in self.confidence):
            raise InvalidInputError("twist.confidence must lie in [0, 1]")
        if self.source not in TWIST_SOURCES:
            raise InvalidInputError(f"twist.source must be one of {TWIST_SOURCES}, got {self.source!r}")

    def to_dict(self) -> dict[str, Any]:
        return {"s": list(self.s), "angle": list(self.angle), "confidence": list(self.confidence),
                "source": self.source}

    @classmethod
    def from_dict(cls, d: Any) -> TwistProfile:
        d = _object(d, "twist")
        return cls(s=_require(d, "s", "twist"), angle=_require(d, "angle", "twist"),
                   confidence=_require(d, "confidence", "twist"), source=_require(d, "source", "twist"))


#: Most stations of a session's twist profile (the skeleton's dense curve is resampled to these).
TWIST_STATIONS = 400


@dataclass
class Session:
    """Everything needed to redo, audit or continue the straightening of one specimen.

    Attributes
    ----------
    source : SourceInfo
        The scan.
    deformation : Deformation or None
        The straightening map (physical units of the scan).
    segmentation : Segmentation or None
        The selection that made the mask.
    endpoints : Endpoints or None
        Head, tail and the parts' endpoints.
    notes : str
        Free text.
    twist : TwistProfile or None
        The twist along the curve and where it was estimated (written by the skeleton solve).
    channels : tuple of SourceInfo
        Other images of the scan's grid (channels, stains) the deformation was applied to (``unwind straighten
        OTHER --same-grid`` records its image in the session it embeds in the output).
    software, software_version : str
        The program that last wrote the file (set by :func:`save_session`).
    created, modified : str
        ISO 8601 times in UTC (``2025-01-31T12:00:00.000Z``); ``modified`` is set by :func:`save_session`.

    Fields may be reassigned (``session.deformation = d.twist_keyframe(2, 0.1)``); they are checked again on
    :meth:`to_dict` and :func:`save_session`.
    """

    source: SourceInfo
    deformation: Deformation | None = None
    segmentation: Segmentation | None = None
    endpoints: Endpoints | None = None
    notes: str = ""
    software: str = SOFTWARE
    software_version: str = field(default_factory=_current_version)
    created: str = field(default_factory=_utcnow)
    modified: str | None = None
    twist: TwistProfile | None = None
    channels: tuple[SourceInfo, ...] = ()

    def __post_init__(self) -> None:
        for name, kind in (("source", SourceInfo), ("deformation", Deformation), ("segmentation", Segmentation),
                           ("endpoints", Endpoints), ("twist", TwistProfile)):
            value = getattr(self, name)
            if not isinstance(value, kind) and not (value is None and name != "source"):
                raise InvalidInputError(f"session.{name} must be a {kind.__name__}"
                                        f"{'' if name == 'source' else ' or None'}, got {type(value).__name__}")
        self.channels = tuple(self.channels)
        if not all(isinstance(c, SourceInfo) for c in self.channels):
            raise InvalidInputError("session.channels must hold SourceInfo records")
        _string(self.notes, "notes")
        _string(self.software, "software.name")
        _string(self.software_version, "software.version")
        self.created = _timestamp(self.created, "created")
        self.modified = self.created if self.modified is None else _timestamp(self.modified, "modified")

    def to_dict(self) -> dict[str, Any]:
        """The JSON layout of schema :data:`SCHEMA_VERSION` (see the module docstring)."""
        self.__post_init__()  # fields may have been reassigned since construction
        return {
            "schema": SCHEMA_ID,
            "schema_version": SCHEMA_VERSION,
            "software": {"name": self.software, "version": self.software_version},
            "created": self.created,
            "modified": self.modified,
            "source": self.source.to_dict(),
            "deformation": None if self.deformation is None else self.deformation.to_dict(),
            "segmentation": None if self.segmentation is None else self.segmentation.to_dict(),
            "endpoints": None if self.endpoints is None else self.endpoints.to_dict(),
            "notes": self.notes,
            **({} if self.twist is None else {"twist": self.twist.to_dict()}),  # files without it stay as they were
            **({"channels": [c.to_dict() for c in self.channels]} if self.channels else {}),
        }

    def on_scan_grid(self, volume: Any, what: str = "mask") -> tuple[Any, str | None]:
        """A mask (or label image) on the deformation's grid, as the pipeline takes a mask: one of the source scan's
        shape voxel for voxel (the scan's geometry is used, whatever the mask's header says), or a box of that grid
        placed by its origin (:func:`~napari_unwind.io._grid.place_on_grid`, the scan taken as axis-aligned).

        Returns the Volume (with the deformation's spacing, origin and unit where its own differ) and a note saying
        so (None when they agree)."""
        from .io._volume import Volume
        from .warp import _check_geometry

        d = self.deformation
        if d is None or not isinstance(volume, Volume):
            return volume, None
        if tuple(volume.shape) != tuple(self.source.shape):
            import dask.array as da

            from .io._grid import place_on_grid

            scan = Volume(da.zeros(self.source.shape, dtype=np.uint8, chunks=self.source.shape), spacing=d.spacing,
                          origin=d.origin, unit=d.unit)
            return place_on_grid(volume, scan, what=what)
        try:
            _check_geometry(volume, d)
            return volume, None
        except InvalidInputError:
            pass

        def triple(v: Any) -> str:
            return " x ".join(f"{float(x):g}" for x in v)

        note = (f"the {what}'s spacing {triple(volume.spacing)} / origin {triple(volume.origin)} differ from the "
                f"session's scan's {triple(d.spacing)} / {triple(d.origin)}: the scan's are used (same shape, voxel "
                "for voxel)")
        return Volume(volume.data, spacing=d.spacing, origin=d.origin, unit=d.unit), note

    @classmethod
    def from_dict(cls, d: Any) -> Session:
        """Build from a dict of any known schema (older ones are migrated); raises :class:`InvalidInputError`."""
        d = _upgrade(_object(_json.plain(d), "a session"))
        # types, required fields and bounds (napari_unwind/schemas/session.schema.json)
        d = _json.validate(d, "session", hint="correct that value in the file, or make the session again")
        software = d["software"]
        deformation = d.get("deformation")
        if deformation is not None:
            try:
                deformation = Deformation.from_dict(deformation)
            except InvalidInputError as exc:
                message = str(exc)
                raise InvalidInputError(message if message.startswith("malformed deformation:")
                                        else f"deformation: {message}") from None
        segmentation = d.get("segmentation")
        endpoints = d.get("endpoints")
        return cls(
            source=SourceInfo.from_dict(_require(d, "source", "")),
            deformation=deformation,
            segmentation=None if segmentation is None else Segmentation.from_dict(segmentation),
            endpoints=None if endpoints is None else Endpoints.from_dict(endpoints),
            notes=d.get("notes", ""),
            software=_require(software, "name", "software"),
            software_version=_require(software, "version", "software"),
            created=_require(d, "created", ""),
            modified=_require(d, "modified", ""),
            twist=None if d.get("twist") is None else TwistProfile.from_dict(d["twist"]),
            channels=tuple(SourceInfo.from_dict(c) for c in d.get("channels") or ()),
        )


# ------------------------------------------------------------------------------------------------------------------
# schema versions
# ------------------------------------------------------------------------------------------------------------------
def _migrate_0_to_1(old: dict) -> dict:
    """Schema 0 (the flat pre-release layout, see the module docstring) -> schema 1."""
    def need(key: str) -> Any:
        if key not in old:
            raise InvalidInputError(f"the field {key!r} of a schema-0 session is missing")
        return old[key]

    spacing = need("spacing")
    saved = _string(need("saved"), "saved")
    try:
        t = datetime.fromisoformat(saved)
        saved = _format_time(t if t.tzinfo else t.replace(tzinfo=UTC))  # pre-release times were naive UTC
    except ValueError:
        pass  # left for schema 1's check to report
    deformation = None
    if old.get("keyframes"):
        deformation = {"schema": "napari-unwind/deformation/1", "unit": old.get("unit"), "spacing": spacing,
                       "origin": [0.0, 0.0, 0.0], "pad": old.get("pad", [0.0, 0.0]), "keyframes": old["keyframes"]}
    segmentation = {key: old[key] for key in ("k", "level", "selected", "isovalue") if key in old} or None
    endpoints = None
    if "head" in old or "tail" in old:
        endpoints = {"head": need("head"), "tail": need("tail"), "chain": []}
    return {
        "schema": SCHEMA_ID,
        "schema_version": 1,
        "software": {"name": SOFTWARE, "version": str(old.get("napari_unwind_version", "unknown"))},
        "created": saved,
        "modified": saved,
        "source": {"path": need("source_path"), "checksum": None, "size": None, "shape": need("shape"),
                   "dtype": need("dtype"), "spacing": spacing, "unit": old.get("unit"), "format": None},
        "deformation": deformation,
        "segmentation": segmentation,
        "endpoints": endpoints,
        "notes": old.get("notes", ""),
    }


def _migrate_1_to_2(old: dict) -> dict:
    """Schema 1 -> 2: the deformation's keyframes get cage offsets ``(0, 0)`` (deformation schema 2); a keyframe that
    has one already (written by hand, or by a tool that knew schema 2) keeps it."""
    new = dict(old, schema_version=2)
    deformation = old.get("deformation")
    if isinstance(deformation, dict) and deformation.get("schema") == "napari-unwind/deformation/1":
        keyframes = deformation.get("keyframes")
        if isinstance(keyframes, list):  # an offset a schema-1 file carries anyway is kept, never dropped
            keyframes = [{"offset": [0.0, 0.0], **k} if isinstance(k, dict) else k for k in keyframes]
        new["deformation"] = dict(deformation, schema=DEFORMATION_SCHEMA, keyframes=keyframes)
    return new


#: schema version -> function taking a dict of that version to the next one.
_MIGRATIONS: dict[int, Callable[[dict], dict]] = {0: _migrate_0_to_1, 1: _migrate_1_to_2}


def _schema_version(d: dict) -> int:
    if "schema" not in d and "schema_version" not in d:
        if "source_path" in d:
            return 0  # the pre-release layout had no schema key
        raise InvalidInputError(f"this is not a napari-unwind session: it has no 'schema' field "
                                f"(a session file starts with \"schema\": \"{SCHEMA_ID}\")")
    if "schema" not in d:
        raise InvalidInputError(f"this is not a napari-unwind session: it has no 'schema' field "
                                f"(a session file starts with \"schema\": \"{SCHEMA_ID}\")")
    if d.get("schema") != SCHEMA_ID:
        raise InvalidInputError(f"this is not a napari-unwind session: its schema is {_json.short(d.get('schema'))}, "
                                f"not {SCHEMA_ID!r}")
    version = _require(d, "schema_version", "")
    if isinstance(version, bool) or not isinstance(version, int) or version < 0:
        raise InvalidInputError(f"schema_version must be an integer >= 0, got {_json.short(version)}")
    if version > _MAX_SCHEMA_VERSION:  # no napari-unwind will count that far: a lie, not a newer file
        raise InvalidInputError(f"schema_version must be an integer between 0 and {_MAX_SCHEMA_VERSION}, got "
                                f"{_json.short(version)}")
    return version


def _upgrade(d: dict) -> dict:
    """Bring a session dict of any known schema to :data:`SCHEMA_VERSION`."""
    version = _schema_version(d)
    if version > SCHEMA_VERSION:
        software = d.get("software")
        by = f" {software['version'][:64]}" if isinstance(software, dict) and \
            isinstance(software.get("version"), str) else ""
        raise InvalidInputError(
            f"this session was written by a newer napari-unwind{by} (schema {version}); this napari-unwind "
            f"({_current_version()}) reads schemas up to {SCHEMA_VERSION}: upgrade napari-unwind "
            "(pip install -U napari-unwind) to open it"
        )
    while version < SCHEMA_VERSION:
        step = _MIGRATIONS.get(version)
        if step is None:
            known = ", ".join(str(v) for v in sorted(_MIGRATIONS)) or "none"
            raise InvalidInputError(
                f"session schema {version} is too old for this napari-unwind ({_current_version()}), which can "
                f"migrate schemas {known} to {SCHEMA_VERSION}; open and save it with an older napari-unwind first, "
                "or make the session again"
            )
        d = step(d)
        new = d.get("schema_version")
        if not isinstance(new, int) or new <= version:  # pragma: no cover - a broken migration is a bug
            raise RuntimeError(f"migration from schema {version} did not advance the version ({new!r})")
        version = new
    return d


# ------------------------------------------------------------------------------------------------------------------
# files
# ------------------------------------------------------------------------------------------------------------------
def _non_finite(obj: Any, where: str = "") -> tuple[str, float] | None:
    """The dotted location and value of the first NaN or infinity in a JSON-like object."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return where or "(top level)", obj
    if isinstance(obj, dict):
        items: Any = ((f"{where}.{k}" if where else str(k), v) for k, v in obj.items())
    elif isinstance(obj, (list, tuple)):
        items = ((f"{where}[{i}]", v) for i, v in enumerate(obj))
    else:
        return None
    for w, v in items:
        found = _non_finite(v, w)
        if found:
            return found
    return None


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _write_text(path: Path, text: str) -> None:
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())


def save_session(session: Session, path: str | os.PathLike, *, overwrite: bool = True) -> Path:
    """Write a session file atomically (the old file stays whole until the new one is complete).

    Sets ``session.modified`` to now and ``session.software``/``software_version`` to this program.

    Parameters
    ----------
    session : Session
        What to save.
    path : str or path-like
        The file; its name must end with ``.unwind.json``.
    overwrite : bool
        Replace an existing file (default True: saving again is the normal case).

    Returns
    -------
    Path
        The absolute path written.

    Raises
    ------
    InvalidInputError
        A wrong file name, or a NaN or infinite number anywhere in the session (never written).
    OutputError
        The folder does not exist or is not writable, the file exists and ``overwrite`` is False, the disk is full.
    """
    path = Path(path).expanduser()
    lower = path.name.lower()
    if not lower.endswith(SESSION_SUFFIX) or lower == SESSION_SUFFIX:
        stem = re.split(r"\.unwind|\.json", path.name, flags=re.IGNORECASE)[0]
        raise InvalidInputError(f"a session file name must end with {SESSION_SUFFIX}, got {path.name!r}; "
                                f"name it e.g. {(stem or 'fish') + SESSION_SUFFIX!r}")
    if not isinstance(session, Session):
        raise InvalidInputError(f"save_session needs a Session, got {type(session).__name__}")
    stamped = replace(session, modified=_utcnow(), software=SOFTWARE, software_version=_current_version())
    data = stamped.to_dict()
    bad = _non_finite(data)
    if bad is not None:
        raise InvalidInputError(f"cannot save {path.name}: {bad[0]} is {bad[1]}; a session never stores NaN or "
                                "infinity (fix the value first)")
    text = json.dumps(data, sort_keys=True, indent=2, ensure_ascii=False, allow_nan=False,
                      default=_json_default) + "\n"
    try:
        with atomic_output(path, overwrite=overwrite) as tmp:
            _write_text(tmp, text)
    except UnwindError:
        raise
    except OSError as exc:
        raise OutputError(f"cannot write the session {path}: {exc.strerror or exc}") from exc
    session.modified = stamped.modified
    session.software, session.software_version = stamped.software, stamped.software_version
    return path.absolute()


def load_session(path: str | os.PathLike) -> Session:
    """Read a session file, migrating an older schema.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    InvalidInputError
        Not a session (not JSON, truncated, not an object, wrong or missing fields: the message names the file,
        the line and column or the field), or a file written by a newer napari-unwind, or a schema too old to
        migrate.
    """
    path = Path(path).expanduser()
    data = _json.load_file(path, what="a session", max_bytes=_MAX_SESSION_BYTES, suffix_hint=SESSION_SUFFIX,
                           damaged_hint="the file is truncated or damaged (restore it from a backup or from "
                                        "version control)",
                           hint="correct that value in the file, or make the session again")
    if not isinstance(data, dict):
        raise InvalidInputError(f"{path} is not a session: it holds {_json_kind(data)}, not a JSON object")
    try:
        session = Session.from_dict(data)
    except InvalidInputError as exc:
        raise InvalidInputError(f"{path}: {exc}") from None
    if not os.path.isabs(session.source.path):  # a server job's session names its scan: next to the session file
        session.source = replace(session.source, path=str(path.absolute().parent / session.source.path))
    return session


# ------------------------------------------------------------------------------------------------------------------
# the scan behind a session
# ------------------------------------------------------------------------------------------------------------------
def open_source(source: SourceInfo, path: str | os.PathLike | None = None) -> Volume:
    """Open a session's scan (at ``path``, default where the session says): the recorded channel of a
    multi-channel file (``source.channel``), else the whole file."""
    target = Path(source.path if path is None else path)
    if source.channel is None:
        return open_volume(target)
    from .io.channels import channel_index

    return open_volume(target, channel=channel_index(target, source.channel))


def verify_source(
    session: Session,
    path: str | os.PathLike | None = None,
    *,
    volume: Volume | None = None,
    progress: Callable[[Progress], Any] | None = None,
) -> SourceInfo:
    """Check that the scan is where the session says and is the one it was made from.

    Cheap checks come first (shape and voxel type from the header, total size from the file system); only then is
    every byte hashed and compared with the recorded checksum.

    Parameters
    ----------
    session : Session
        The session whose ``source`` is checked.
    path : str or path-like, optional
        Where the scan is now (default ``session.source.path``): for a scan that was moved or renamed.
    volume : Volume, optional
        The scan opened with the options the session used (``series=``, a spacing given by hand). Its spacing
        must then match the session's. Without it the scan is opened here; a different spacing is then accepted
        when the content is identical (the session's spacing was given by hand).
    progress : callable, optional
        Called with the checksum's progress records (bytes).

    Returns
    -------
    SourceInfo
        ``session.source`` with ``path`` set to where the scan was found and ``checksum``/``size`` measured now:
        assign it to ``session.source`` after a move, or to record the checksum of a migrated session.

    Raises
    ------
    SourceMissingError
        Nothing at the path (or a companion data file is missing).
    SourceChangedError
        Another shape, type, size or content.

    Warns
    -----
    UserWarning
        The session records no checksum (migrated from schema 0): only shape, type and spacing were compared.
    """
    if not isinstance(session, Session):
        raise InvalidInputError(f"verify_source needs a Session, got {type(session).__name__}")
    rec = session.source
    target = Path(rec.path) if path is None else Path(os.path.abspath(Path(path).expanduser()))
    if not target.exists():
        moved = "" if path is None or str(target) == rec.path else f" (the session recorded {rec.path})"
        raise SourceMissingError(
            f"the scan this session was made from is missing: expected at {target}{moved}. If it was moved or "
            "renamed, point at its new location: unwind straighten NEW_PATH --session ... on the command line, or "
            "verify_source(session, path=NEW_PATH) in Python"
        )
    members, manifest = _source_files(target)
    size = sum(s for _, _, s in members)

    if volume is None:
        try:
            volume = open_volume(target)
        except (UnwindError, OSError):
            volume = None  # e.g. several DICOM series; the checksum decides
        strict_spacing = False
    else:
        strict_spacing = True
    problems = []
    spacing_note = ""
    if volume is not None:
        if tuple(volume.shape) != rec.shape:
            problems.append(f"its shape is {tuple(volume.shape)}, the session's {rec.shape}")
        if np.dtype(volume.dtype).name != rec.dtype:
            problems.append(f"its voxel type is {np.dtype(volume.dtype).name}, the session's {rec.dtype}")
        if not np.allclose(volume.spacing, rec.spacing, rtol=1e-6, atol=0):
            spacing_note = f"its spacing is {volume.spacing}, the session's {rec.spacing}"
            if strict_spacing:
                problems.append(spacing_note)
    if rec.size is not None and size != rec.size:
        problems.append(f"it holds {size} bytes, the session's scan {rec.size}")
    if not problems:
        digest, size = run(_digest_iter(members, manifest), progress)
        if rec.checksum is None:
            warnings.warn(
                f"the session records no checksum of its scan (it was written by an older napari-unwind): {target} "
                "has the recorded shape and voxel type, but its content cannot be verified; save the session "
                "again to record the checksum",
                UserWarning, stacklevel=2,
            )
        elif digest != rec.checksum:
            problems.append("its content differs (another checksum)" + (f"; {spacing_note}" if spacing_note else ""))
    if problems:
        raise SourceChangedError(
            f"the scan at {target} has changed since this session was made: {'; '.join(problems)}. The session's "
            "deformation and selection belong to the original data, so results would not match. Point at the "
            "original scan (its path as INPUT on the command line, path= in Python) or make a new session on this one"
        )
    return replace(rec, path=str(target), checksum=digest, size=size)
