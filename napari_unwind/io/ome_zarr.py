"""OME-Zarr (NGFF 0.5 on zarr v3): the project's working format.

A scan is stored as a multiscale pyramid: level 0 at full resolution, each next level halved along every axis
(box average for intensities, nearest for labels) until every side is at most ``max_side`` (256). Every level
is chunked (128^3 by default), compressed with blosc lz4 (byte shuffle; bit shuffle for 8-bit voxels) and
checksummed (the zarr v3 core codec crc32c), and the ``ome`` attributes record axes, units and the scale of each
level, so napari, Fiji (MoBIE/n5-viewer) and ome-zarr-py read it with the right geometry. lz4 was chosen by
measuring (``benchmarks/bench_straighten.py --codecs``, table in ``benchmarks/RESULTS.md``): straightening from the
store waits mostly for decompression, which lz4 does more than twice as fast as zstd level 3 (about 2.0 against
0.85 GB/s per core on a real CT), for files 1.1-1.3x larger on CT data (1.7x on smooth synthetic data). Stores
written before with blosc zstd read as before.

Reading: dask reads one chunk per task. A whole chunk of a store with these codecs (bytes, blosc, crc32c) is read,
checked and decoded straight into its array in the task's thread, without zarr's asynchronous pipeline (about a
third faster); every other read goes through zarr.

Writing streams slab by slab along axis0 in one pass: every level is built from the slabs as they go by and
written chunk-aligned, none is read back. Peak memory is about two slabs of ``chunks[0]`` planes (the one being
written and the one read ahead) plus the pyramid's pending planes (1/8 + 1/64 + ... of a slab), never the whole
volume.

Every chunk is written, also those that hold only the fill value (zarr would skip them), and the ``unwind``
attributes record it (``all_chunks_written: true``). The reader then treats a chunk file missing on disk as damage
(an error naming the file) instead of reading zeros; stores without that record are read as zarr reads them. A
chunk that cannot be decoded is an error naming its file, also inside dask tasks on other threads or machines.
"""

from __future__ import annotations

import contextvars
import itertools
import json
import math
import os
import sys
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr
from numcodecs import Blosc
from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec
from zarr.storage import LocalStore

from ..errors import InvalidInputError, UnknownFormatError
from ..progress import Progress, checkpoint
from ._atomic import final_name
from ._files import ConfinementError, ReadConfinement, check_regular, current_confinement, open_regular
from ._headers import compose_transform
from ._straight_record import straightening_record
from ._units import axis_units
from ._volume import LazyArray, Volume

if TYPE_CHECKING:
    import dask.array as da

__all__ = ["read_ome_zarr", "write_ome_zarr", "pyramid_shapes", "ChunkCodec", "EncodedSlab", "DEFAULT_CHUNKS",
           "DEFAULT_MAX_SIDE"]

DEFAULT_CHUNKS = (128, 128, 128)
DEFAULT_MAX_SIDE = 256
#: The working store's compressor (blosc) and its level; chosen by ``benchmarks/bench_straighten.py --codecs``:
#: lz4 decodes more than twice as fast as zstd 3, which straightening from the store waits for, for files 1.1-1.3x
#: larger on CT data.
DEFAULT_COMPRESSION = "lz4"
DEFAULT_COMPRESSION_LEVEL = {"lz4": 5, "zstd": 3}
COMPRESSIONS = ("lz4", "zstd", "none")
SHUFFLES = ("auto", "byte", "bit", "none")
AXES = ("z", "y", "x")
NGFF_VERSION = "0.5"


# ------------------------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------------------------
def _multiscales(attrs: dict[str, Any]) -> tuple[list[dict], str]:
    if "ome" in attrs and "multiscales" in attrs["ome"]:
        return attrs["ome"]["multiscales"], str(attrs["ome"].get("version", NGFF_VERSION))
    if "multiscales" in attrs:  # NGFF 0.4 on zarr v2
        ms = attrs["multiscales"]
        return ms, str(ms[0].get("version", "0.4"))
    return [], ""


def _affine(transforms: Any, ndim: int, where: str) -> tuple[list[float], list[float]]:
    """(scale, offset) of a list of NGFF coordinate transformations applied in order: x -> x * scale + offset."""
    scale, offset = [1.0] * ndim, [0.0] * ndim
    for t in transforms or []:
        kind = t.get("type")
        if kind == "identity":
            continue
        if kind not in ("scale", "translation") or kind not in t:
            raise InvalidInputError(
                f"{where}: unsupported coordinate transformation {t!r}; napari-unwind reads inline 'scale' and "
                "'translation' transformations"
            )
        values = [float(v) for v in t[kind]]
        if len(values) != ndim or not all(np.isfinite(values)):
            raise InvalidInputError(f"{where}: the {kind} {t[kind]!r} needs {ndim} finite numbers")
        scale, offset = compose_transform(scale, offset, kind, values)
    return scale, offset


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    text = text[0] if text else ""
    text = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


try:  # zarr's crc32c codec computes its checksums with it (a dependency of zarr >= 3.1)
    import google_crc32c
except ImportError:  # pragma: no cover - older zarr: every chunk is read through zarr
    google_crc32c = None

#: numcodecs' blosc decoder: the blosc header names the compressor, so one instance decodes every blosc chunk.
_BLOSC = Blosc()


def _direct_codecs(array: zarr.Array) -> tuple[bool, bool] | None:
    """``(blosc, crc32c)`` when a chunk of ``array`` can be decoded without zarr's codec pipeline, else None.

    That is a zarr v3 array without shards whose codecs are ``bytes`` (native byte order), optionally ``blosc``,
    optionally ``crc32c``: what :func:`write_ome_zarr` writes now and wrote before. Anything else is read by zarr.
    """
    meta = array.metadata
    if google_crc32c is None or meta.zarr_format != 3 or array.shards is not None:
        return None
    if np.dtype(array.dtype).kind not in "biuf":
        return None
    codecs = list(getattr(meta, "codecs", ()))
    if not codecs or not isinstance(codecs[0], BytesCodec):
        return None
    endian = codecs[0].endian
    if np.dtype(array.dtype).itemsize > 1 and (endian is None or endian.value != sys.byteorder):
        return None
    rest = codecs[1:]
    crc = bool(rest) and isinstance(rest[-1], Crc32cCodec)
    if crc:
        rest = rest[:-1]
    blosc = bool(rest) and isinstance(rest[0], BloscCodec)
    if blosc:
        rest = rest[1:]
    return None if rest else (blosc, crc)


class _ZarrChunks:
    """A picklable array-like over one array of a local zarr store, read chunk by chunk by dask.

    A chunk that cannot be decoded is an :class:`~napari_unwind.errors.InvalidInputError` naming its file. When
    the store records that every chunk was written (``complete``: stores this module writes), a chunk missing on
    disk is an error too, instead of reading as the fill value. Existence is checked only for chunks whose values
    all equal the fill value, so intact stores pay nothing but one comparison per voxel.

    A whole chunk of a store with the codecs :func:`write_ome_zarr` writes (bytes, blosc, crc32c) is read
    directly: the file is read, its crc32c checked and blosc decodes it into the result, in the calling thread
    (blosc releases the GIL, so dask's threads decode in parallel). That skips zarr's asynchronous pipeline and
    its copies, about a third of the reading time; anything else goes through zarr.
    """

    def __init__(self, array: zarr.Array, store: str, *, complete: bool):
        self.array = array
        self.store = str(store)
        self.complete = bool(complete)
        self.shape = tuple(int(n) for n in array.shape)
        self.ndim = len(self.shape)
        self.dtype = np.dtype(array.dtype)
        self.grid = tuple(int(c) for c in (array.shards or array.chunks))
        self.fill = array.fill_value
        self.direct = _direct_codecs(array)
        self.confine = getattr(array.store, "confine", None)  # the store's confinement holds for direct reads too

    def chunk_file(self, coords: tuple[int, ...]) -> str:
        """Path of the file holding chunk (or shard) ``coords``."""
        key = self.array.metadata.encode_chunk_key(tuple(int(c) for c in coords))
        return os.path.join(self.store, *[p for p in str(self.array.path).split("/") if p], *key.split("/"))

    def _bounds(self, key: Any) -> list[tuple[int, int, int]] | None:
        """(start, stop, step) per axis of a key of ints and slices; None for anything else."""
        if not isinstance(key, tuple):
            key = (key,)
        key = key + (slice(None),) * (self.ndim - len(key))
        out = []
        for k, n in zip(key, self.shape, strict=True):
            if isinstance(k, slice):
                out.append(k.indices(n))
            elif isinstance(k, int | np.integer):
                i = int(k) % n if n else 0
                out.append((i, i + 1, 1))
            else:
                return None
        return out

    def _chunks_of(self, bounds: list[tuple[int, int, int]]) -> list[tuple[int, ...]]:
        ranges = []
        for (start, stop, _), g in zip(bounds, self.grid, strict=True):
            if stop <= start:
                return []
            ranges.append(range(start // g, (stop - 1) // g + 1))
        return list(itertools.product(*ranges))

    def _whole_chunk(self, key: Any) -> tuple[tuple[int, ...], list[tuple[int, int, int]]] | None:
        """The chunk coordinates when ``key`` selects exactly one whole chunk (as dask's reads do), else None."""
        bounds = self._bounds(key)
        if bounds is None:
            return None
        coords = []
        for (start, stop, step), g, n in zip(bounds, self.grid, self.shape, strict=True):
            c = start // g
            if step != 1 or start != c * g or stop != min(n, (c + 1) * g):
                return None
            coords.append(c)
        return tuple(coords), bounds

    def _read_direct(self, coords: tuple[int, ...], bounds: list[tuple[int, int, int]]) -> np.ndarray:
        """Chunk ``coords`` read, checked and decoded without zarr (see the class docstring)."""
        blosc, crc = self.direct
        path = self.chunk_file(coords)
        part = tuple(slice(0, stop - start) for start, stop, _ in bounds)
        try:
            with open_regular(path, "chunk", confine=self.confine) as fh:
                buf = bytearray(os.fstat(fh.fileno()).st_size)  # writable: the result may be handed out
                got = fh.readinto(buf)
        except FileNotFoundError:
            if self.complete:
                raise self._missing(coords) from None
            return np.full([stop - start for start, stop, _ in bounds], self.fill, dtype=self.dtype)
        except ConfinementError:
            raise  # outside the confinement: one line naming no path
        except OSError as exc:
            raise InvalidInputError(f"{path}: cannot read chunk {'/'.join(map(str, coords))} "
                                    f"({exc.strerror or exc}); check the disk or copy the store again") from None
        data = np.frombuffer(buf, dtype=np.uint8, count=got)
        if crc:
            if got < 4:
                raise self._corrupt_chunk(coords, f"{got} bytes, shorter than its checksum")
            data, stored = data[:-4], int.from_bytes(bytes(data[-4:]), "little")
            if google_crc32c.value(data) != stored:
                raise self._corrupt_chunk(coords, "its crc32c checksum does not match")
        nbytes = math.prod(self.grid) * self.dtype.itemsize
        if not blosc:
            if data.size != nbytes:
                raise self._corrupt_chunk(coords, f"{data.size} bytes instead of {nbytes}")
            return data.view(self.dtype).reshape(self.grid)[part]
        # blosc header: version, versionlz, flags, typesize, then nbytes, blocksize, cbytes (uint32, little endian)
        header = bytes(data[:16])
        if len(header) < 16 or int.from_bytes(header[4:8], "little") != nbytes \
                or int.from_bytes(header[12:16], "little") != data.size:
            raise self._corrupt_chunk(coords, "not a blosc stream of the chunk's size")
        out = np.empty(self.grid, dtype=self.dtype)
        try:
            _BLOSC.decode(data, out=out)
        except Exception as exc:  # noqa: BLE001 - numcodecs raises RuntimeError, ValueError...
            raise self._corrupt_chunk(coords, _first_line(exc)) from None
        return out[part]

    def stored_chunk(self, coords: tuple[int, ...]) -> bytes | None:
        """The bytes of chunk ``coords`` as stored (codecs applied, not decoded), read under the store's confinement;
        None for a chunk never written (the fill value), an error for one missing from a complete store."""
        path = self.chunk_file(coords)
        try:
            with open_regular(path, "chunk", confine=self.confine) as fh:
                return fh.read()
        except FileNotFoundError:
            if self.complete:
                raise self._missing(coords) from None
            return None
        except ConfinementError:
            raise
        except OSError as exc:
            raise InvalidInputError(f"{path}: cannot read chunk {'/'.join(map(str, coords))} "
                                    f"({exc.strerror or exc}); check the disk or copy the store again") from None

    def _corrupt_chunk(self, coords: tuple[int, ...], why: str) -> InvalidInputError:
        return InvalidInputError(f"{self.chunk_file(coords)}: chunk {'/'.join(map(str, coords))} is corrupt "
                                 f"({why}); re-import the scan")

    def _missing(self, coords: tuple[int, ...]) -> InvalidInputError:
        return InvalidInputError(
            f"{self.chunk_file(coords)}: chunk {'/'.join(map(str, coords))} is missing, but {self.store} "
            "records that every chunk was written; the copy is incomplete: copy the store again or "
            "re-import the scan"
        )

    def __getitem__(self, key: Any) -> np.ndarray:
        if self.direct is not None:
            whole = self._whole_chunk(key)
            if whole is not None:
                return self._read_direct(*whole)
        try:
            block = np.asarray(self.array[key])
        except (InvalidInputError, ConfinementError):
            raise  # a chunk that is no regular file or lies outside the confinement (_RegularFileStore)
        except Exception as exc:  # noqa: BLE001 - codecs raise RuntimeError, ValueError, zstd errors...
            raise self._corrupt(key, exc) from None
        if self.complete:
            self._check_present(key, block)
        return block

    def _corrupt(self, key: Any, exc: BaseException) -> InvalidInputError:
        bounds = self._bounds(key)
        for coords in self._chunks_of(bounds) if bounds is not None else []:
            region = tuple(slice(c * g, min(n, (c + 1) * g)) for c, g, n in zip(coords, self.grid, self.shape,
                                                                                   strict=True))
            try:
                self.array[region]
            except Exception as chunk_exc:  # noqa: BLE001
                return self._corrupt_chunk(coords, _first_line(chunk_exc))
        where = os.path.join(self.store, str(self.array.path))
        return InvalidInputError(f"{where}: a chunk is corrupt ({_first_line(exc)}); re-import the scan")

    def _check_present(self, key: Any, block: np.ndarray) -> None:
        fill = self.fill
        if fill is None:
            return
        isfill = np.isnan(block) if isinstance(fill, float | np.floating) and np.isnan(fill) else block == fill
        if not isfill.any():
            return
        bounds = self._bounds(key)
        if bounds is None:
            return
        isfill = isfill.reshape([len(range(*b)) for b in bounds])
        for coords in self._chunks_of(bounds):
            part = []
            for (start, stop, step), c, g in zip(bounds, coords, self.grid, strict=True):
                lo, hi = max(start, c * g), min(stop, (c + 1) * g)
                part.append(slice(-(-(lo - start) // step), -(-(hi - start) // step)))
            if isfill[tuple(part)].all() and not os.path.exists(self.chunk_file(coords)):
                raise self._missing(coords)


def _role(key: str) -> str:
    return "metadata" if key.endswith((".json", ".zarray", ".zgroup", ".zattrs", ".zmetadata")) else "chunk"


def _get_confined(path: Path, prototype: Any, byte_range: Any, confine: ReadConfinement, role: str) -> Any:
    """zarr's LocalStore read of one file, opened by :func:`open_regular` under ``confine``."""
    from zarr.abc.store import OffsetByteRequest, RangeByteRequest, SuffixByteRequest

    with open_regular(path, role, confine=confine) as f:
        if byte_range is None:
            return prototype.buffer.from_bytes(f.read())
        size = f.seek(0, os.SEEK_END)
        if isinstance(byte_range, RangeByteRequest):
            f.seek(byte_range.start)
            return prototype.buffer.from_bytes(f.read(byte_range.end - f.tell()))
        if isinstance(byte_range, OffsetByteRequest):
            f.seek(byte_range.offset)
        elif isinstance(byte_range, SuffixByteRequest):
            f.seek(max(0, size - byte_range.suffix))
        else:
            raise TypeError(f"Unexpected byte_range, got {byte_range}.")
        return prototype.buffer.from_bytes(f.read())


class _RegularFileStore(LocalStore):
    """zarr's LocalStore reading only regular files: a chunk or metadata file that is a named pipe (which would
    block the read for ever), a device or a socket is refused in one line naming it.

    Opened under :func:`~napari_unwind.io._files.confined_reads`, it keeps that confinement (``confine``) and reads
    every key, metadata and chunks, at every read, through a descriptor checked where it really lies."""

    confine: ReadConfinement | None = None

    @classmethod
    def opened(cls, root: Path, confine: ReadConfinement | None) -> _RegularFileStore:
        store = cls(root, read_only=True)
        store.confine = confine
        return store

    def with_read_only(self, read_only: bool = False) -> _RegularFileStore:
        store = type(self)(root=self.root, read_only=read_only)
        store.confine = self.confine
        return store

    async def get(self, key: str, prototype: Any = None, byte_range: Any = None) -> Any:
        if self.confine is None:
            check_regular(self.root / key, _role(key))
            return await super().get(key, prototype, byte_range)
        import asyncio

        from zarr.core.buffer import default_buffer_prototype

        if not self._is_open:
            await self._open()
        try:
            return await asyncio.to_thread(_get_confined, self.root / key, prototype or default_buffer_prototype(),
                                           byte_range, self.confine, _role(key))
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            return None

    async def get_partial_values(self, prototype: Any, key_ranges: Any) -> Any:
        key_ranges = list(key_ranges)
        if self.confine is not None:
            return [await self.get(key, prototype, byte_range) for key, byte_range in key_ranges]
        for key, _ in key_ranges:
            check_regular(self.root / key, "chunk")
        return await super().get_partial_values(prototype, key_ranges)


def _lazy(array: zarr.Array, store: Path, *, complete: bool, index: tuple = ()) -> LazyArray:
    """A dask array over ``array`` (one dask chunk per zarr chunk) whose reads name broken chunk files, indexed by
    ``index`` (slices, or 0 for a non-spatial axis of length 1); built, importing dask, on first use."""
    bad = [c for c in (*array.chunks, *(array.shards or ())) if int(c) < 1]
    if bad:
        raise InvalidInputError(f"{store}: the array {str(array.path) or '/'} declares chunks {tuple(array.chunks)}; "
                                "every chunk side must be at least 1: the store's metadata is damaged (rewrite it with "
                                "unwind convert from the source, or fix its chunk_shape)")
    wrapped = _ZarrChunks(array, str(store), complete=complete)
    try:
        meta_file = os.path.join(wrapped.store, str(array.path), "zarr.json")
        stamp = os.stat(meta_file if os.path.exists(meta_file) else wrapped.store).st_mtime_ns
    except OSError:
        stamp = 0
    keep = [ax for ax in range(array.ndim) if not index or isinstance(index[ax], slice)]

    def build() -> da.Array:
        import dask.array as da
        from dask.base import tokenize

        name = "zarr-" + tokenize(wrapped.store, str(array.path), stamp, complete)
        d = da.from_array(wrapped, chunks=array.chunks, name=name, asarray=False, fancy=False,
                          meta=np.empty((0,) * wrapped.ndim, dtype=wrapped.dtype))
        return d[index] if index else d

    return LazyArray(build, tuple(array.shape[ax] for ax in keep), wrapped.dtype,
                     tuple(array.chunks[ax] for ax in keep))


def read_ome_zarr(path: Path, *, level: int | None = None, channel: int | None = None) -> Volume:
    """Open an OME-Zarr image (NGFF 0.4 or 0.5) or a plain 3D zarr array, lazily.

    Parameters
    ----------
    path : Path
        The zarr folder (the multiscales group, or one array).
    level : int, optional
        Return only this pyramid level and the coarser ones (default: full resolution, all levels kept). The
        volume's spacing and origin are that level's.
    channel : int, optional
        For an image with a channel axis (``c``, or an axis of type ``"channel"``) longer than 1: which channel
        (0-based). Its name (``omero.channels[i].label``) is in ``metadata["channel"]``. See
        :func:`napari_unwind.io.open_channels` for all of them.

    Raises
    ------
    InvalidInputError
        Broken metadata, a level that cannot be opened, non-spatial axes of length > 1. Reading a chunk that
        cannot be decoded raises it too, naming the chunk's file; so does a missing chunk of a store that records
        that every chunk was written (the stores :func:`write_ome_zarr` makes).
    """
    path = Path(path).expanduser().absolute()
    try:
        node = zarr.open(store=_RegularFileStore.opened(path, current_confinement()), mode="r")
        attrs = dict(node.attrs)
    except ConfinementError:
        raise
    except Exception as exc:  # noqa: BLE001 - zarr raises several types for a broken store
        raise InvalidInputError(f"{path} is not a readable zarr store ({_first_line(exc)}); "
                                "is the copy complete?") from None
    unwind_attrs = attrs.get("unwind", {})
    if not isinstance(unwind_attrs, dict):
        unwind_attrs = {}
    complete = unwind_attrs.get("all_chunks_written") is True
    if isinstance(node, zarr.Array):
        if level not in (None, 0):
            raise InvalidInputError(f"{path} is a single zarr array without pyramid levels, got level={level}")
        return Volume(_lazy(node, path, complete=complete), spacing=unwind_attrs.get("spacing", (1.0, 1.0, 1.0)),
                      unit=unwind_attrs.get("unit"), source=str(path), format="ome-zarr", metadata={"attrs": attrs})
    try:
        multiscales, version = _multiscales(attrs)
        if not multiscales:
            arrays = sorted(name for name, _ in node.arrays())
            hint = f" It holds arrays {arrays}; open one of them as {path}/<name>." if arrays else ""
            raise UnknownFormatError(f"{path} is a zarr group without OME-Zarr 'multiscales' metadata.{hint}")
        return _read_multiscales(path, node, multiscales[0], version, level, unwind_attrs, complete, channel,
                                 channel_labels(attrs))
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        if isinstance(exc, InvalidInputError):
            raise
        raise InvalidInputError(
            f"{path}: malformed OME-Zarr 'multiscales' metadata ({_first_line(exc)}); re-import the scan"
        ) from None


def channel_labels(attrs: dict[str, Any]) -> list[str]:
    """The channel names an OME-Zarr image's ``omero`` metadata gives (NGFF 0.4 and 0.5), [] when none."""
    omero = (attrs.get("ome") or {}).get("omero") or attrs.get("omero") or {}
    labels = []
    for c in (omero.get("channels") if isinstance(omero, dict) else None) or []:
        label = c.get("label") if isinstance(c, dict) else None
        labels.append(str(label) if label not in (None, "") else "")
    return labels


def _is_channel_axis(axis: Any) -> bool:
    if isinstance(axis, dict):
        return axis.get("type") == "channel" or (axis.get("type") is None and axis.get("name") == "c")
    return str(axis) == "c"


def _read_multiscales(path: Path, node: Any, ms: dict, version: str, level: int | None, unwind_attrs: dict,
                      complete: bool, channel: int | None = None, labels: list[str] | None = None) -> Volume:
    axes = ms.get("axes", [{"name": a} for a in AXES])
    axis_names = [a["name"] if isinstance(a, dict) else str(a) for a in axes]
    space = [i for i, a in enumerate(axes) if not isinstance(a, dict) or a.get("type", "space") == "space"]
    if len(space) != 3:
        raise InvalidInputError(f"{path} has axes {axis_names}; napari-unwind needs exactly 3 spatial axes")
    try:
        unit, factors = axis_units([axes[a].get("unit") if isinstance(axes[a], dict) else None for a in space])
    except InvalidInputError as exc:
        raise InvalidInputError(f"{path}: {exc}") from None
    global_transforms = ms.get("coordinateTransformations", [])
    levels, spacings, origins = [], [], []
    for ds in ms["datasets"]:
        try:
            arr = node[ds["path"]]
        except ConfinementError:
            raise
        except Exception as exc:  # noqa: BLE001 - a missing or broken zarr.json of one level
            raise InvalidInputError(f"{path}/{ds['path']}: cannot open this pyramid level ({_first_line(exc)}); "
                                    "is the copy complete?") from None
        if not isinstance(arr, zarr.Array):
            raise InvalidInputError(f"{path}/{ds['path']} is not an array")
        if arr.ndim != len(axes):
            raise InvalidInputError(f"{path}/{ds['path']} has {arr.ndim} dimensions but {len(axes)} axes")
        # drop non-spatial axes of length 1 (t, c); pick the channel asked for; refuse time points
        index = []
        for ax in range(arr.ndim):
            if ax in space:
                index.append(slice(None))
            elif channel is not None and _is_channel_axis(axes[ax]):
                if isinstance(channel, bool) or not isinstance(channel, int | np.integer) \
                        or not 0 <= channel < arr.shape[ax]:
                    raise InvalidInputError(f"{path} has channels 0..{arr.shape[ax] - 1}, got channel={channel!r}")
                index.append(int(channel))
            elif arr.shape[ax] == 1:
                index.append(0)
            elif _is_channel_axis(axes[ax]):
                raise InvalidInputError(
                    f"{path} has {arr.shape[ax]} channels (axis {axis_names[ax]!r}); straighten them all with "
                    "`unwind straighten` (napari_unwind.io.open_channels), or pick one with --input-channel NAME "
                "(channel= in Python)"
                )
            else:
                raise InvalidInputError(
                    f"{path} has a non-spatial axis {axis_names[ax]!r} of length {arr.shape[ax]}; "
                    "export one time point as its own 3D image first"
                )
        d = _lazy(arr, path, complete=complete, index=tuple(index))
        # physical = (index * scale + translation) of the dataset, then the multiscale's own transformations
        scale, offset = _affine(ds.get("coordinateTransformations", []), len(axes), f"{path}/{ds['path']}")
        g_scale, g_offset = _affine(global_transforms, len(axes), str(path))
        levels.append(d)
        # axes in different units are brought to the finest (axis 0 in mm, axes 1-2 in um: all in um)
        spacings.append(tuple(scale[a] * g_scale[a] * f for a, f in zip(space, factors, strict=True)))
        origins.append(tuple((offset[a] * g_scale[a] + g_offset[a]) * f for a, f in zip(space, factors, strict=True)))
    if level is not None:
        if not 0 <= level < len(levels):
            raise InvalidInputError(f"{path} has pyramid levels 0..{len(levels) - 1}, got level={level}")
        levels, spacings, origins = levels[level:], spacings[level:], origins[level:]
    return Volume(
        levels[0],
        spacing=spacings[0],
        unit=unit,
        origin=origins[0],
        levels=tuple(levels),
        level_spacings=tuple(spacings),
        level_origins=tuple(origins),
        source=str(path),
        format="ome-zarr",
        metadata={"ngff_version": version, "name": ms.get("name"), "unwind": unwind_attrs,
                  **({} if channel is None else {"channel": _label(labels, int(channel))})},
    )


def _label(labels: list[str] | None, k: int) -> str:
    return labels[k] if labels and k < len(labels) and labels[k] else f"c{k}"


def channel_axis_length(path: Path) -> int:
    """How many channels an OME-Zarr image has along its channel axis (1 when it has none)."""
    path = Path(path).expanduser().absolute()
    try:
        node = zarr.open(store=_RegularFileStore.opened(path, current_confinement()), mode="r")
        attrs = dict(node.attrs)
        if isinstance(node, zarr.Array):
            return 1
        multiscales, _ = _multiscales(attrs)
        ms = multiscales[0]
        axes = ms.get("axes", [])
        arr = node[ms["datasets"][0]["path"]]
    except ConfinementError:
        raise
    except Exception:  # noqa: BLE001 - read_ome_zarr gives the proper error for a broken store
        return 1
    for ax, a in enumerate(axes):
        if _is_channel_axis(a) and ax < arr.ndim:
            return int(arr.shape[ax])
    return 1


# ------------------------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------------------------
def pyramid_shapes(shape: tuple[int, ...], max_side: int = DEFAULT_MAX_SIDE) -> list[tuple[int, ...]]:
    """Shapes of the pyramid levels: halve every axis longer than 1 (rounding up) until all sides <= max_side.

    >>> pyramid_shapes((1000, 300, 40))
    [(1000, 300, 40), (500, 150, 20), (250, 75, 10)]
    """
    if max_side < 1:
        raise InvalidInputError(f"max_side must be >= 1, got {max_side}")
    shapes = [tuple(int(s) for s in shape)]
    while max(shapes[-1]) > max_side:
        shapes.append(tuple((s + 1) // 2 if s > 1 else 1 for s in shapes[-1]))
    return shapes


def _normalise_chunks(chunks: Any, shape: tuple[int, ...]) -> tuple[int, ...]:
    if chunks is None:
        chunks = DEFAULT_CHUNKS
    c = tuple(int(v) for v in np.broadcast_to(np.asarray(chunks), (len(shape),)))
    if any(v < 1 for v in c):
        raise InvalidInputError(f"chunk sizes must be positive, got {chunks!r}")
    return tuple(min(v, s) for v, s in zip(c, shape, strict=True))


#: dtypes whose 2x2x2 mean the compiled kernel computes (wider integers go through numpy's sub-grid sums)
_KERNEL_DTYPES = frozenset(np.dtype(t) for t in ("u1", "i1", "u2", "i2", "u4", "i4", "f4", "f8"))
_MEAN8 = None


def _mean8_kernel() -> Any:
    """The compiled 2x2x2 box mean (numba, imported and compiled on first use; cached on disk)."""
    global _MEAN8
    if _MEAN8 is None:
        from numba import njit

        @njit(cache=True, nogil=True)
        def mean8(block, out, zero, integer):  # pragma: no cover - compiled
            # the same sums in the same order as the numpy path: acc = 0 + v000 + v001 + v010 + ... + v111 in
            # the accumulator's type (zero's), then (acc + 4) // 8 for integers, acc / 8 for floats
            n0, n1, n2 = block.shape
            m0, m1, m2 = out.shape
            for i in range(m0):
                a0, b0 = 2 * i, min(2 * i + 1, n0 - 1)
                for j in range(m1):
                    a1, b1 = 2 * j, min(2 * j + 1, n1 - 1)
                    for k in range(m2):
                        a2, b2 = 2 * k, min(2 * k + 1, n2 - 1)
                        acc = zero
                        acc += block[a0, a1, a2]
                        acc += block[a0, a1, b2]
                        acc += block[a0, b1, a2]
                        acc += block[a0, b1, b2]
                        acc += block[b0, a1, a2]
                        acc += block[b0, a1, b2]
                        acc += block[b0, b1, a2]
                        acc += block[b0, b1, b2]
                        if integer:
                            out[i, j, k] = (acc + 4) // 8
                        else:
                            out[i, j, k] = acc / 8
        _MEAN8 = mean8
    return _MEAN8


def _downsample2(block: np.ndarray, *, labels: bool) -> np.ndarray:
    """Halve every axis longer than 1 (rounding up): box mean for intensities, nearest for labels.

    The mean is a sum of the 8 (or 4, 2) strided sub-grids in a wide accumulator, so no float copy of the whole
    block is made; integers are rounded half up. A 3D block with every side > 1 of the usual voxel types goes
    through a compiled kernel that makes the same sums in the same order in one pass (the same bytes, tested
    against the sub-grid sums; about 3x faster).
    """
    if labels:
        return block[tuple(slice(None, None, 2) if s > 1 else slice(None) for s in block.shape)]
    if block.ndim == 3 and min(block.shape) > 1 and block.dtype in _KERNEL_DTYPES and block.dtype.isnative:
        integer = np.issubdtype(block.dtype, np.integer)
        zero = (np.int32(0) if block.dtype.itemsize < 4 else np.int64(0)) if integer else \
            (np.float64(0) if block.dtype == np.float64 else np.float32(0))
        out = np.empty(tuple((s + 1) // 2 for s in block.shape), dtype=block.dtype)
        _mean8_kernel()(block, out, zero, integer)
        return out
    return _downsample2_numpy(block)


def _downsample2_numpy(block: np.ndarray) -> np.ndarray:
    """The box mean of :func:`_downsample2` as sums of strided sub-grids (any shape and dtype)."""
    pad = [(0, s % 2) if s > 1 else (0, 0) for s in block.shape]
    if any(p[1] for p in pad):
        block = np.pad(block, pad, mode="edge")
    if np.issubdtype(block.dtype, np.integer):
        acc_dtype = np.int64 if block.dtype.itemsize >= 4 else np.int32
    else:
        acc_dtype = np.float64 if block.dtype == np.float64 else np.float32
    offsets = [(0, 1) if s > 1 else (0,) for s in block.shape]
    out_shape = tuple(s // 2 if s > 1 else 1 for s in block.shape)
    acc = np.zeros(out_shape, dtype=acc_dtype)
    n = 0
    for o0 in offsets[0]:
        for o1 in offsets[1]:
            for o2 in offsets[2]:
                view = block[tuple(slice(o, None, 2) if len(offs) > 1 else slice(None)
                                   for o, offs in zip((o0, o1, o2), offsets, strict=True))]
                np.add(acc, view, out=acc, casting="unsafe")
                n += 1
    if np.issubdtype(block.dtype, np.integer):
        acc += n // 2
        acc //= n
        return acc.astype(block.dtype)
    acc /= n
    return acc.astype(block.dtype, copy=False)


#: Threads encoding and writing the chunks of a slab (blosc and file writes release the GIL).
_ENCODE_THREADS = max(2, min(8, os.cpu_count() or 2))
_SHUFFLE_CODE = {"noshuffle": Blosc.NOSHUFFLE, "shuffle": Blosc.SHUFFLE, "bitshuffle": Blosc.BITSHUFFLE}


def _numcodecs_blosc(codecs: list, typesize: int | None = None) -> Blosc | None:
    """numcodecs' Blosc with the settings of the array's BloscCodec (cname, level, shuffle, block size, type size;
    ``typesize``: the voxel size, which an array's codec takes on when it is created)."""
    b = next((c for c in codecs if isinstance(c, BloscCodec)), None)
    return None if b is None else Blosc(cname=b.cname.value, clevel=b.clevel, shuffle=_SHUFFLE_CODE[b.shuffle.value],
                                        blocksize=b.blocksize, typesize=typesize or b.typesize)


class ChunkCodec:
    """Level 0's chunk grid and codecs of a new store, outside the writer: what an import with these options stores.

    A client encodes an upload's chunks with :meth:`encode` (the stored bytes: the blosc stream and its crc32c,
    byte for byte what :func:`write_ome_zarr` writes for the same voxels with the same blosc build), and the server
    checks and decodes each with :meth:`decode` before :func:`write_ome_zarr` stores it as it is
    (:class:`EncodedSlab`).
    """

    def __init__(self, shape: tuple[int, ...], dtype: Any, *, chunks: Any = None,
                 compression: str = DEFAULT_COMPRESSION, compression_level: int | None = None, shuffle: str = "auto"):
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype).newbyteorder("<")
        self.grid = _normalise_chunks(chunks, self.shape)
        codecs = _codecs(compression, compression_level, shuffle, self.dtype)
        self.blosc = _numcodecs_blosc(codecs, self.dtype.itemsize)
        self.counts = tuple(-(-n // g) for n, g in zip(self.shape, self.grid, strict=True))
        self.nbytes = math.prod(self.grid) * self.dtype.itemsize
        #: the largest stored chunk: blosc's worst case (its header and a copy of the bytes) and the crc32c
        self.max_bytes = self.nbytes + (16 + self.nbytes // 64 + 64 if self.blosc is not None else 0) + 4
        #: equal signatures: equal stored bytes for equal voxels (see _DirectWriter)
        self.signature = (self.grid, self.dtype.str, None if self.blosc is None else self.blosc.get_config())
        self._flags = None if self.blosc is None else self.blosc.encode(np.zeros(self.grid, self.dtype))[2]

    def coords(self) -> Iterator[tuple[int, ...]]:
        """Every chunk's grid coordinates, in C order (the order of an upload's chunks)."""
        return itertools.product(*[range(c) for c in self.counts])

    def bounds(self, coords: tuple[int, ...]) -> tuple[slice, ...]:
        return tuple(slice(c * g, min(n, (c + 1) * g)) for c, g, n in zip(coords, self.grid, self.shape, strict=True))

    def chunk(self, part: np.ndarray) -> np.ndarray:
        """The whole chunk holding ``part`` (a chunk's voxels, smaller at the far edges): padded with zeros (the
        fill value), contiguous, little-endian, as the writer encodes it."""
        if part.shape == self.grid:
            return np.ascontiguousarray(part, dtype=self.dtype)
        whole = np.zeros(self.grid, dtype=self.dtype)
        whole[tuple(slice(0, n) for n in part.shape)] = part
        return whole

    def encode(self, chunk: np.ndarray) -> tuple[bytes, bytes]:
        """The stored bytes of a whole chunk (:meth:`chunk`) in two parts: the blosc stream, then its crc32c
        (4 bytes, little-endian)."""
        encoded = self.blosc.encode(chunk) if self.blosc is not None else chunk.tobytes()
        return encoded, google_crc32c.value(encoded).to_bytes(4, "little")

    def decode(self, blob: Any, coords: tuple[int, ...]) -> np.ndarray:
        """The voxels of chunk ``coords`` (the part inside the volume) from its stored bytes, checked: the crc32c,
        a blosc stream of this codec (compressor, shuffle, type size) holding the chunk's size, and zeros beyond
        the volume's edge. Anything else is an :class:`InvalidInputError` naming the chunk."""
        data = np.frombuffer(blob, dtype=np.uint8)
        where = "/".join(map(str, coords))
        if data.size < 4 or google_crc32c.value(data[:-4]) != int.from_bytes(bytes(data[-4:]), "little"):
            raise InvalidInputError(f"chunk {where}: its crc32c checksum does not match")
        data = data[:-4]
        out = np.empty(self.grid, dtype=self.dtype)
        if self.blosc is None:
            if data.size != self.nbytes:
                raise InvalidInputError(f"chunk {where}: {data.size} bytes instead of {self.nbytes}")
            out.reshape(-1).view(np.uint8)[:] = data
        else:
            head = bytes(data[:16])
            if len(head) < 16 or head[3] != self.dtype.itemsize or int.from_bytes(head[4:8], "little") != self.nbytes \
                    or int.from_bytes(head[12:16], "little") != data.size or (head[2] | 0x02) != (self._flags | 0x02):
                raise InvalidInputError(f"chunk {where}: not a blosc stream of this store's codec "
                                        f"({self.blosc.cname}, {self.nbytes} bytes of {self.dtype.name})")
            try:
                _BLOSC.decode(data, out=out)
            except Exception as exc:  # noqa: BLE001 - numcodecs raises RuntimeError, ValueError...
                raise InvalidInputError(f"chunk {where} cannot be decoded ({_first_line(exc)})") from None
        part = tuple(slice(0, b.stop - b.start) for b in self.bounds(coords))
        if any(p.stop < g for p, g in zip(part, self.grid, strict=True)):
            inside = np.zeros(self.grid, dtype=bool)
            inside[part] = True
            if np.any(out[~inside]):
                raise InvalidInputError(f"chunk {where}: the padding beyond the volume's edge is not zeros")
        return out[part]


class EncodedSlab(tuple):
    """A slab of level 0 (``voxels``) with its chunks already encoded (``chunks``: grid coordinates -> the stored
    bytes, from ``codec``, each checked by :meth:`ChunkCodec.decode` into ``voxels``). :func:`write_ome_zarr`
    stores those bytes as they are when ``codec`` is the store's, and encodes the voxels otherwise."""

    def __new__(cls, voxels: np.ndarray, chunks: dict, codec: ChunkCodec):
        return super().__new__(cls, (voxels, chunks, codec))

    voxels = property(lambda self: self[0])
    chunks = property(lambda self: self[1])
    codec = property(lambda self: self[2])


class _DirectWriter:
    """Write chunk-aligned slabs of a new array of this module's codecs (bytes, blosc, crc32c) without zarr.

    The mirror of :class:`_ZarrChunks`' direct read: each chunk (an edge chunk padded with the fill value, as zarr
    stores it) is blosc-encoded with the codec's own settings (cname, level, shuffle, block size, type size), its
    crc32c appended little-endian, and written to the file zarr names it; the bytes are those zarr writes
    (tested), at 4-6x the speed on 2 cores (zarr's asynchronous pipeline copies and schedules every chunk). Chunks
    are encoded on ``pool``'s threads (blosc and the file writes release the GIL).
    """

    def __init__(self, array: zarr.Array, store: str, pool: ThreadPoolExecutor):
        self.locate = _ZarrChunks(array, store, complete=True)
        self.shape, self.grid, self.dtype = self.locate.shape, self.locate.grid, self.locate.dtype
        self.fill = array.fill_value
        self.pool = pool
        codecs = list(array.metadata.codecs)
        self.blosc = _numcodecs_blosc(codecs)
        self.crc = isinstance(codecs[-1], Crc32cCodec)
        self.signature = (self.grid, self.dtype.newbyteorder("<").str,
                          None if self.blosc is None else self.blosc.get_config()) if self.crc else None

    @staticmethod
    def usable(array: zarr.Array) -> bool:
        return _direct_codecs(array) is not None  # (None for a sharded array too)

    def write(self, z0: int, data: np.ndarray, stored: dict | None = None) -> None:
        """Planes ``z0 .. z0 + len(data)`` (``z0`` a multiple of the chunk depth; the end one too, or the array's
        last plane); ``stored``: chunks already encoded with this array's codecs (coordinates -> bytes), written
        as they are."""
        if data.shape[0] == 0:
            return
        c0 = z0 // self.grid[0]
        rows = range(c0, (z0 + data.shape[0] - 1) // self.grid[0] + 1)
        coords = list(itertools.product(rows, *[range(-(-n // g)) for n, g in zip(self.shape[1:], self.grid[1:])]))
        stored = stored or {}
        for _ in self.pool.map(lambda c: self._chunk(c, z0, data, stored.get(c)), coords):
            pass

    def _chunk(self, coords: tuple[int, ...], z0: int, data: np.ndarray, stored: Any = None) -> None:
        if stored is not None:
            self._put(coords, stored)
            return
        lo = [c * g for c, g in zip(coords, self.grid)]
        hi = [min(n, a + g) for a, n, g in zip(lo, self.shape, self.grid)]
        part = data[lo[0] - z0:hi[0] - z0, lo[1]:hi[1], lo[2]:hi[2]]
        if part.shape == self.grid:
            chunk = np.ascontiguousarray(part, dtype=self.dtype.newbyteorder("<"))
        else:
            chunk = np.full(self.grid, self.fill, dtype=self.dtype.newbyteorder("<"))
            chunk[tuple(slice(0, n) for n in part.shape)] = part
        encoded = self.blosc.encode(chunk) if self.blosc is not None else chunk.tobytes()
        self._put(coords, encoded, google_crc32c.value(encoded).to_bytes(4, "little") if self.crc else b"")

    def _put(self, coords: tuple[int, ...], *parts: Any) -> None:
        path = self.locate.chunk_file(coords)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "wb") as fh:
            for part in parts:
                fh.write(part)


class _Cascade:
    """Build every pyramid level from consecutive slabs of level 0, each written once, chunk-aligned.

    Level k keeps (a) planes waiting to fill its next chunk-deep write and (b) at most one plane waiting for its
    partner before 2x2x2 averaging into level k+1. Memory is about 1/8 + 1/64 + ... of the incoming slab.
    """

    def __init__(self, arrays: list, *, labels: bool, writer: ThreadPoolExecutor,
                 direct: list[_DirectWriter | None] | None = None):
        self.arrays = arrays
        self.writer = writer  # level writes run here while the next level is averaged
        self.direct = direct or [None] * len(arrays)  # levels written without zarr's pipeline
        self.labels = labels
        self.pending: list[list[np.ndarray]] = [[] for _ in arrays]  # planes waiting for a chunk-aligned write
        self.carry: list[np.ndarray | None] = [None] * len(arrays)  # an odd plane waiting for its partner
        self.written = [0] * len(arrays)

    def push(self, level: int, block: np.ndarray, *, last: bool, stored: dict | None = None) -> None:
        """``stored``: chunks of ``block`` already encoded (level 0's chunk-aligned slabs only)."""
        arr = self.arrays[level]
        if stored and (self.pending[level] or self.direct[level] is None):
            stored = None  # not chunk-aligned here, or written by zarr: encoded from the voxels
        self.pending[level].append(block)
        have = sum(b.shape[0] for b in self.pending[level])
        depth = arr.chunks[0]
        if have < depth and not last:
            return
        data = np.concatenate(self.pending[level]) if len(self.pending[level]) > 1 else self.pending[level][0]
        n = have if last else (have // depth) * depth
        z0 = self.written[level]
        if self.direct[level] is not None:
            write = self.writer.submit(self.direct[level].write, z0, data[:n], stored if n == have else None)
        else:
            write = self.writer.submit(arr.__setitem__, slice(z0, z0 + n), data[:n])
        try:
            self.written[level] += n
            self.pending[level] = [data[n:]] if n < have else []
            if level + 1 < len(self.arrays):
                self._down(level, data[:n], last=last)
        finally:
            write.result()

    def _down(self, level: int, planes: np.ndarray, *, last: bool) -> None:
        if self.carry[level] is not None:
            planes = np.concatenate([self.carry[level], planes])
            self.carry[level] = None
        halve0 = self.arrays[level].shape[0] > 1
        if halve0 and not last and planes.shape[0] % 2:
            self.carry[level] = planes[-1:].copy()
            planes = planes[:-1]
        if planes.shape[0] == 0:
            if last:  # nothing new, but the next level must still flush what it holds
                nxt = self.arrays[level + 1]
                self.push(level + 1, np.empty((0, *nxt.shape[1:]), dtype=nxt.dtype), last=True)
            return
        self.push(level + 1, _downsample2(planes, labels=self.labels), last=last)


def _ngff_attrs(name: str, unit: str | None, spacings: list[tuple[float, ...]], origin: tuple[float, ...],
                labels: bool) -> dict:
    axes = [{"name": a, "type": "space", **({"unit": unit} if unit else {})} for a in AXES]
    datasets = []
    for i, sp in enumerate(spacings):
        # a level's voxel centre sits at the centre of the 2x2x2 block it averages
        translation = [o + (s - spacings[0][k]) / 2 for k, (o, s) in enumerate(zip(origin, sp, strict=True))]
        datasets.append({
            "path": str(i),
            "coordinateTransformations": [
                {"type": "scale", "scale": [float(v) for v in sp]},
                {"type": "translation", "translation": [float(v) for v in translation]},
            ],
        })
    ms = {
        "name": name,
        "axes": axes,
        "datasets": datasets,
        "type": "nearest" if labels else "mean",
        "metadata": {"method": "napari_unwind.io.ome_zarr._downsample2",
                     "description": "2x2x2 nearest" if labels else "2x2x2 box average"},
    }
    return {"version": NGFF_VERSION, "multiscales": [ms]}


def _codecs(compression: Any, level: Any, shuffle: Any, dtype: np.dtype) -> list:
    """The chunk codecs: blosc (unless ``compression="none"``), then crc32c.

    The checksum comes after compression: a chunk cut short or with flipped bytes is an error, never other values.
    """
    if compression not in COMPRESSIONS:
        raise InvalidInputError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
    if shuffle not in SHUFFLES:
        raise InvalidInputError(f"shuffle must be one of {', '.join(SHUFFLES)}, got {shuffle!r}")
    if compression == "none":
        return [Crc32cCodec()]
    if level is None:
        level = DEFAULT_COMPRESSION_LEVEL[compression]
    if isinstance(level, bool) or not isinstance(level, int | np.integer) or not 1 <= level <= 9:
        raise InvalidInputError(f"compression_level must be a whole number 1..9, got {level!r}")
    if shuffle == "auto":
        shuffle = "bit" if np.dtype(dtype).itemsize == 1 else "byte"  # byte shuffle decodes faster for 16-bit CT
    names = {"byte": "shuffle", "bit": "bitshuffle", "none": "noshuffle"}
    return [BloscCodec(cname=compression, clevel=int(level), shuffle=names[shuffle]), Crc32cCodec()]


def write_ome_zarr(
    volume: Volume,
    path: Path,
    *,
    chunks: Any = None,
    pyramid: bool = True,
    max_side: int = DEFAULT_MAX_SIDE,
    labels: bool = False,
    compression: str = DEFAULT_COMPRESSION,
    compression_level: int | None = None,
    shuffle: str = "auto",
    name: str | None = None,
    attributes: dict[str, Any] | None = None,
    slabs: Iterable[np.ndarray] | None = None,
) -> Iterator[Progress]:
    """Write ``volume`` as an OME-Zarr pyramid (NGFF 0.5, zarr v3), slab by slab.

    Parameters
    ----------
    volume : Volume
        What to write; only ``volume.data`` (level 0) is read, the pyramid is rebuilt.
    path : Path
        The zarr folder to create.
    chunks : int or tuple of 3 int, optional
        Chunk shape of every level (default 128^3, clipped to the level's shape).
    pyramid : bool
        Build the downsampled levels (default True).
    max_side : int
        Stop halving once every side is <= max_side (default 256).
    labels : bool
        The voxels are labels: downsample by nearest, never by averaging.
    compression : {"lz4", "zstd", "none"}
        Blosc compressor of every chunk (default lz4: it decodes more than twice as fast as zstd, and reading
        is what straightening from the store waits for, for files 1.1-1.3x larger on CT data; see
        ``benchmarks/RESULTS.md``). Every chunk carries a crc32c checksum whatever the choice.
    compression_level : int, optional
        Blosc level 1-9 (default 5 for lz4, 3 for zstd).
    shuffle : {"auto", "byte", "bit", "none"}
        Blosc's shuffle filter before compression; "auto" (default): byte shuffle for multi-byte voxels, bit
        shuffle for 8-bit ones.
    name : str, optional
        Image name stored in the metadata.
    attributes : dict, optional
        Extra JSON-serialisable attributes stored under ``"unwind"`` (provenance, the straightening map...).
    slabs : iterable of ndarray, optional
        Level 0 as it arrives (an upload): consecutive slabs along axis0 of ``chunks[0]`` planes each (the last
        may be shorter), in order, instead of reading ``volume.data``, which then only gives the shape, the
        dtype and the geometry. A slab of another shape or dtype, or too few or too many slabs, is an
        :class:`~napari_unwind.errors.InvalidInputError`. The store written is the one ``volume.data`` holding
        the same voxels gives. A slab may be an :class:`EncodedSlab`: its chunks, encoded with the store's codec
        and checked against its voxels, are written as they are (level 0 is then not encoded here).
    """
    shape = volume.shape
    dtype = volume.dtype
    chunk_shape = _normalise_chunks(chunks, shape)
    shapes = pyramid_shapes(shape, max_side) if pyramid else [shape]
    spacings = [tuple(volume.spacing)]
    for lvl in range(1, len(shapes)):  # a halved axis doubles its spacing; an axis of length 1 stops halving
        spacings.append(tuple(sp * (2 if n > 1 else 1) for sp, n in zip(spacings[-1], shapes[lvl - 1], strict=True)))
    try:
        json.dumps(attributes or {})
    except TypeError as exc:
        raise InvalidInputError(f"attributes must be JSON-serialisable: {exc}") from None

    codecs = _codecs(compression, compression_level, shuffle, dtype)
    root = zarr.open_group(store=str(path), mode="w", zarr_format=3)
    arrays = []
    for lvl, shp in enumerate(shapes):
        c = _normalise_chunks(chunk_shape, shp)
        # every chunk is written, even one that is all fill: a chunk missing later is damage, not zeros
        arrays.append(root.create_array(
            str(lvl), shape=shp, chunks=c, dtype=dtype, compressors=codecs, fill_value=0,
            dimension_names=list(AXES), config={"write_empty_chunks": True},
        ))

    # One pass over the source: every level is built from the slabs as they stream by (no level is read back).
    depth = chunk_shape[0]
    starts = list(range(0, shape[0], depth))

    given = None if slabs is None else iter(slabs)

    def read_slab(z0: int) -> np.ndarray:
        if given is None:
            from dask.callbacks import Callback

            # a cancelled job stops between two chunks of the slab (dask's local schedulers call pretask here)
            with Callback(pretask=lambda *_: checkpoint(), posttask=lambda *_: checkpoint()):
                return np.asarray(volume.data[z0:min(shape[0], z0 + depth)].compute())
        want = (min(shape[0], z0 + depth) - z0, *shape[1:])
        slab = next(given, None)
        if isinstance(slab, EncodedSlab):
            encoded = slab
            slab = slab.voxels
            if tuple(slab.shape) == want and slab.dtype == dtype:
                return encoded
        if slab is None or tuple(slab.shape) != want or slab.dtype != dtype:
            got = "nothing" if slab is None else f"shape {tuple(slab.shape)} {slab.dtype}"
            raise InvalidInputError(f"slab {z0 // depth} (planes {z0}-{z0 + want[0] - 1}) of a {shape} {dtype} "
                                    f"volume must have shape {want} and dtype {dtype}, got {got}")
        return slab

    # read the next slab while this one is written
    with ThreadPoolExecutor(max_workers=1) as reader, ThreadPoolExecutor(max_workers=len(arrays)) as writer, \
            ThreadPoolExecutor(max_workers=_ENCODE_THREADS) as encoders:
        direct = [_DirectWriter(a, str(path), encoders) if _DirectWriter.usable(a) else None for a in arrays]
        pyr = _Cascade(arrays, labels=labels, writer=writer, direct=direct)
        # the reader runs in this thread's context: its checkpoints run this thread's cancellation check
        pending = reader.submit(contextvars.copy_context().run, read_slab, starts[0])
        for i, z0 in enumerate(starts):
            slab, stored = pending.result(), None
            if isinstance(slab, EncodedSlab):  # level 0's chunks arrived encoded: stored as they are
                stored = slab.chunks if direct[0] is not None and direct[0].signature == slab.codec.signature else None
                slab = slab.voxels
            if given is not None and i + 1 == len(starts) and next(given, None) is not None:
                raise InvalidInputError(f"more planes than the {shape[0]} of a {shape} {dtype} volume arrived")
            if i + 1 < len(starts):
                pending = reader.submit(contextvars.copy_context().run, read_slab, starts[i + 1])
            pyr.push(0, slab, last=i + 1 == len(starts), stored=stored)
            del slab, stored
            yield Progress("write", i + 1, len(starts), f"planes {z0}-{z0 + depth - 1} of {shape[0]}"
                           if z0 + depth <= shape[0] else f"planes {z0}-{shape[0] - 1} of {shape[0]}")

    root.attrs["ome"] = _ngff_attrs(name or (Path(volume.source).name if volume.source else final_name(path)),
                                    volume.unit, spacings, volume.origin, labels)
    # all_chunks_written: every chunk of every level is on disk, so the reader treats a missing one as damage
    unwind_attrs = {"spacing": list(volume.spacing), "unit": volume.unit, "labels": bool(labels),
                    "all_chunks_written": True}
    if volume.source:
        unwind_attrs["imported_from"] = {"path": volume.source, "format": volume.format}
    record = straightening_record(volume)
    if record is not None:  # a straight volume written (or converted) here; export gives the whole map instead
        unwind_attrs["straightening"] = record
    unwind_attrs.update(attributes or {})
    root.attrs["unwind"] = unwind_attrs

