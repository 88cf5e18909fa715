"""The public I/O entry points: open, write, import."""

from __future__ import annotations

import errno
import os
import shutil
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidInputError, OutputError
from ..progress import Progress, run
from ._atomic import atomic_output, check_not_input, check_writable, final_name
from ._files import _size, check_room
from ._formats import compresses, detect_format, output_format, reader_for, writer_for
from ._volume import Volume

__all__ = ["open_volume", "write_volume", "write_volume_iter", "import_volume", "import_volume_iter", "as_volume",
           "import_slabs_iter", "disk_full_error"]

_FULL = {errno.ENOSPC: "no space left on device", getattr(errno, "EDQUOT", -1): "disk quota exceeded"}


def disk_full_error(exc: BaseException, path: str | os.PathLike,
                    expected_bytes: int | None = None) -> OutputError | None:
    """One-line :class:`OutputError` when ``exc`` comes from a full disk or quota (ENOSPC, EDQUOT), else None.

    Libraries re-raise the operating system's error wrapped in their own (pydicom, tifffile's writer thread), so
    the chain of causes is searched. The message names the final output (never a temporary name), the free space
    in its folder and, when known, the size of the voxels.
    """
    cause: BaseException | None = exc
    for _ in range(20):
        if cause is None or (isinstance(cause, OSError) and cause.errno in _FULL):
            break
        cause = cause.__cause__ or cause.__context__
    if not isinstance(cause, OSError) or cause.errno not in _FULL:
        return None
    path = Path(path)
    path = path.with_name(final_name(path))
    try:
        free = f"{_size(shutil.disk_usage(path.parent).free)} free in {path.parent}"
    except OSError:
        free = f"{path.parent} is full"
    need = f"; the voxels take {expected_bytes:,} bytes ({_size(expected_bytes)}) uncompressed" \
        if expected_bytes else ""
    return OutputError(f"cannot write {path}: {_FULL[cause.errno]} ({free}{need}); "
                       "free some space or write to another disk")


def open_volume(path: str | os.PathLike, *, format: str | None = None, **options: Any) -> Volume:
    """Open a scan lazily, whatever its format.

    Parameters
    ----------
    path : str or path-like
        A file (TIFF, NRRD/NHDR, NIfTI, ``.dat``/``.raw``), a folder (OME-Zarr, DICOM series, numbered 2D slices)
        or one slice of a numbered stack.
    format : str, optional
        Force a reader (a key of ``napari_unwind.io.FORMATS``) instead of detecting it.
    **options
        Passed to the reader, e.g. ``series=`` for DICOM, ``level=`` for OME-Zarr.

    Returns
    -------
    Volume
        Dask-backed voxels in array index order (axis0, axis1, axis2) with spacing, unit and origin.

    Raises
    ------
    FileNotFoundError
        The path does not exist.
    UnknownFormatError
        Nothing recognisable is there.
    InvalidInputError
        The file is recognised but malformed (truncated, inconsistent slices, several DICOM series...).
    """
    if not isinstance(path, str | os.PathLike):
        raise InvalidInputError(f"open_volume needs a path (str or path-like), got {type(path).__name__}; wrap an "
                                "array in memory with as_volume(array, spacing=..., unit=...)")
    # absolute before any lazy graph is built: dask.distributed workers run in other folders
    path = Path(path).expanduser().absolute()
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist")
    fmt = format or detect_format(path)
    if path.is_dir() and fmt in ("tiff", "nrrd", "nifti", "raw"):
        raise InvalidInputError(f"{path} is a folder, but the {fmt} reader opens one file: point at the file, or "
                                "let the format be detected")
    return reader_for(fmt)(path, **options)


def as_volume(data: Any, *, spacing: Any = None, unit: str | None = None, origin: Any = None) -> Volume:
    """Wrap an array (numpy, dask, zarr) or a Volume as a Volume, overriding geometry where given."""
    if isinstance(data, Volume):
        changes: dict[str, Any] = {}
        if spacing is not None:
            changes["spacing"] = spacing
        if unit is not None:
            changes["unit"] = unit
        if origin is not None:
            changes["origin"] = origin
        return data.with_data(data.data, **changes) if changes else data
    import dask.array as da  # here, not at the top: opening a scan and reading its header need no dask

    if not isinstance(data, da.Array):
        arr = data if hasattr(data, "shape") and hasattr(data, "dtype") else np.asarray(data)
        data = da.from_array(arr, chunks=_default_chunks(arr.shape, np.dtype(arr.dtype)))
    return Volume(data, spacing=(1.0, 1.0, 1.0) if spacing is None else spacing, unit=unit,
                  origin=(0.0, 0.0, 0.0) if origin is None else origin)


def _default_chunks(shape: tuple[int, ...], dtype: np.dtype) -> tuple[int, ...]:
    return tuple(min(int(s), 128) for s in shape)


_NONFINITE_FIX = ("replace them with a number first: nan_value=V in Python (write_volume, import_volume), or "
                  "`unwind convert INPUT OUTPUT --nan-value V` on the command line")


def _reject_nonfinite(block: np.ndarray, block_info: dict | None = None) -> np.ndarray:
    bad = ~np.isfinite(block)
    if not bad.any():
        return block
    first = tuple(int(i) for i in np.argwhere(bad)[0])
    if block_info and None in block_info:
        first = tuple(int(lo) + f for (lo, _), f in zip(block_info[None]["array-location"], first, strict=True))
    value = block[tuple(np.argwhere(bad)[0])]
    kind = "NaN" if np.isnan(value) else ("+inf" if value > 0 else "-inf")
    counts = [(int(np.isnan(block).sum()), "NaN"), (int(np.isposinf(block).sum()), "+inf"),
              (int(np.isneginf(block).sum()), "-inf")]
    summary = ", ".join(f"{n} {name}" for n, name in counts if n)
    raise InvalidInputError(
        f"the float data to write hold {kind} at voxel {first} ({summary} in that chunk of "
        f"{block.size} voxels); {_NONFINITE_FIX}"
    )


def _checked(volume: Volume, nan_value: float | None) -> Volume:
    """Reject (or replace) NaN and infinities chunk by chunk while the data stream through; a no-op for integers."""
    if not np.issubdtype(volume.dtype, np.floating):
        return volume
    if nan_value is not None:
        try:
            fill = volume.dtype.type(nan_value)
        except (TypeError, ValueError):
            fill = None
        if fill is None or not np.isfinite(fill):
            raise InvalidInputError(f"nan_value must be a finite number that {volume.dtype} holds, got {nan_value!r}")
        import dask.array as da

        data = da.where(da.isfinite(volume.data), volume.data, fill)
    else:
        data = volume.data.map_blocks(_reject_nonfinite, dtype=volume.dtype)
    return volume.with_data(data)


def write_volume_iter(
    data: Any,
    path: str | os.PathLike,
    *,
    spacing: Any = None,
    unit: str | None = None,
    origin: Any = None,
    format: str | None = None,
    overwrite: bool = False,
    nan_value: float | None = None,
    **options: Any,
) -> Iterator[Progress]:
    """Generator form of :func:`write_volume`: yields progress, returns the written path."""
    fmt = output_format(path, format)
    writer = writer_for(fmt)
    if fmt == "stack" and "{" in Path(path).name:
        # slices/fish_{:04d}.png: the folder is the unit written atomically, the name is the slice pattern
        from .stack import split_stack_target

        path, pattern = split_stack_target(path)
        options.setdefault("pattern", pattern)
    volume = _checked(as_volume(data, spacing=spacing, unit=unit, origin=origin), nan_value)
    target = check_writable(path, overwrite=overwrite)
    # a volume read from a file is never written into, over or around that file (the CLI's rule, for the API too)
    check_not_input([target], [getattr(data, "source", None)] if isinstance(data, Volume) else [])
    check_room(target, volume.nbytes, compressed=compresses(fmt, target, options))
    try:
        with atomic_output(target, overwrite=overwrite) as tmp:  # removes the temporary output on any error
            yield from writer(volume, tmp, **options)
    except OSError as exc:
        full = disk_full_error(exc, target, volume.nbytes)
        if full is None:
            raise
        raise full from None
    return target


def write_volume(
    data: Any,
    path: str | os.PathLike,
    *,
    spacing: Any = None,
    unit: str | None = None,
    origin: Any = None,
    format: str | None = None,
    overwrite: bool = False,
    nan_value: float | None = None,
    progress: Callable[[Progress], Any] | None = None,
    **options: Any,
) -> Path:
    """Write a volume atomically, in the format its path names.

    Parameters
    ----------
    data : Volume or array-like, shape (N0, N1, N2)
        What to write. A :class:`Volume` brings its spacing, unit and origin; the keywords override them.
    path : str or path-like
        Target. The suffix chooses the format: ``.zarr`` (OME-Zarr pyramid), ``.tif``/``.tiff`` (ImageJ hyperstack,
        BigTIFF when large), ``.nrrd``/``.nhdr``, ``.nii``/``.nii.gz``, ``.dat``/``.raw`` (raw + the original
        Unwind header), ``.dicom`` (a folder holding a DICOM series), or a name with ``{}`` and an image suffix
        (a numbered slice stack, e.g. ``slices/fish_{:04d}.png``).
    spacing : sequence of 3 float, optional
        Voxel size in array axis order; default the Volume's, or 1.
    unit : str, optional
        Length unit (``"um"``, ``"mm"``...).
    origin : sequence of 3 float, optional
        Physical position of voxel (0, 0, 0).
    format : str, optional
        Force a format instead of the suffix's.
    overwrite : bool
        Replace an existing output (only once the new one is complete). Default False: refuse.
    nan_value : float, optional
        Replace NaN and infinities by this value; by default they are an error (naming the first, its sign and
        voxel).
    progress : callable, optional
        Called with each :class:`~napari_unwind.progress.Progress` record.
    **options
        Format options (``chunks=``, ``pyramid=``, ``labels=`` for OME-Zarr; ``compression=`` for TIFF...).

    Returns
    -------
    Path
        The absolute path written.
    """
    return run(write_volume_iter(data, path, spacing=spacing, unit=unit, origin=origin, format=format,
                                 overwrite=overwrite, nan_value=nan_value, **options), progress)


def _import_target(dst: str | os.PathLike, compression: str | None,
                   compression_level: int | None) -> tuple[Path, dict[str, Any]]:
    """An import's output (an ``*.zarr`` folder, else an error) and its codec options (None: the writer's defaults,
    napari_unwind.io.ome_zarr.DEFAULT_COMPRESSION, imported only when writing)."""
    dst = Path(dst)
    if not dst.name.lower().endswith(".zarr"):
        raise InvalidInputError(f"import writes an OME-Zarr folder; name the output *.zarr, got {dst}")
    codec = {k: v for k, v in (("compression", compression), ("compression_level", compression_level))
             if v is not None}
    return dst, codec


def import_volume_iter(
    src: Any,
    dst: str | os.PathLike,
    *,
    chunks: Any = None,
    max_side: int = 256,
    overwrite: bool = False,
    nan_value: float | None = None,
    spacing: Any = None,
    unit: str | None = None,
    labels: bool = False,
    compression: str | None = None,
    compression_level: int | None = None,
    **reader_options: Any,
) -> Iterator[Progress]:
    """Generator form of :func:`import_volume`: yields progress, returns the opened result."""
    if not isinstance(src, Volume):
        src = open_volume(src, **reader_options) if isinstance(src, str | os.PathLike) else as_volume(src)
    dst, codec = _import_target(dst, compression, compression_level)
    written = yield from write_volume_iter(src, dst, spacing=spacing, unit=unit, format="ome-zarr",
                                           overwrite=overwrite, nan_value=nan_value, chunks=chunks,
                                           max_side=max_side, labels=labels, pyramid=True, **codec)
    return open_volume(written, format="ome-zarr")


def import_slabs_iter(
    blocks: Iterable[np.ndarray],
    dst: str | os.PathLike,
    *,
    shape: tuple[int, int, int],
    dtype: Any,
    spacing: Any = None,
    unit: str | None = None,
    origin: Any = None,
    chunks: Any = None,
    max_side: int = 256,
    overwrite: bool = False,
    nan_value: float | None = None,
    labels: bool = False,
    compression: str | None = None,
    compression_level: int | None = None,
) -> Iterator[Progress]:
    """:func:`import_volume_iter` for voxels that arrive in order, e.g. an upload: streamed, never held whole.

    ``blocks`` are consecutive runs of planes along axis0 (each of shape ``(k, N1, N2)``, any ``k``, or a whole slab
    as an :class:`~napari_unwind.io.ome_zarr.EncodedSlab` whose chunks are stored as they came); they are
    cut into the store's slabs of ``chunks[0]`` planes as they come (without a copy when they already are), checked
    for NaN and infinities (or have them replaced by ``nan_value``), and written by the same OME-Zarr writer, so
    the store is the one :func:`import_volume` writes from the whole array. Fewer or more planes than ``shape``,
    or blocks of another plane shape or dtype, are an :class:`InvalidInputError`, and nothing is left behind.
    Yields progress, returns ``dst``.
    """
    import dask.array as da

    from .ome_zarr import _normalise_chunks

    dtype = np.dtype(dtype)
    shape = tuple(int(n) for n in shape)
    placeholder = as_volume(da.empty(shape, dtype=dtype, chunks=shape), spacing=spacing, unit=unit, origin=origin)
    checked = _checked(placeholder, nan_value)  # validates nan_value; the placeholder itself is never read
    depth = _normalise_chunks(chunks, shape)[0]
    fill = None if checked is placeholder or nan_value is None else dtype.type(nan_value)

    def slabs() -> Iterator[np.ndarray]:
        z0 = 0

        def ready(slab: np.ndarray) -> np.ndarray:
            nonlocal z0
            if np.issubdtype(dtype, np.floating):
                if fill is None:
                    where = [(z0, z0 + slab.shape[0]), (0, shape[1]), (0, shape[2])]
                    _reject_nonfinite(slab, {None: {"array-location": where}})
                else:
                    slab = np.where(np.isfinite(slab), slab, fill)
            z0 += slab.shape[0]
            return slab

        from .ome_zarr import EncodedSlab

        parts: list[np.ndarray] = []
        have = 0
        for block in blocks:
            if isinstance(block, EncodedSlab) and not parts and block.voxels.dtype == dtype \
                    and block.voxels.shape == (min(depth, shape[0] - z0), *shape[1:]):
                voxels = ready(block.voxels)  # a whole slab whose chunks came encoded (an upload of "chunks")
                yield block if voxels is block.voxels else voxels  # NaN replaced: encoded again
                continue
            if isinstance(block, EncodedSlab):
                block = block.voxels
            block = np.asarray(block)
            if block.ndim != 3 or tuple(block.shape[1:]) != shape[1:] or block.dtype != dtype:
                raise InvalidInputError(f"a block of planes of a {shape} {dtype} volume must have shape "
                                        f"(k, {shape[1]}, {shape[2]}) and dtype {dtype}, got {block.shape} "
                                        f"{block.dtype}")
            while block.shape[0]:
                if not parts and block.shape[0] >= depth:
                    yield ready(block[:depth])
                    block = block[depth:]
                    continue
                take = min(depth - have, block.shape[0])
                parts.append(block[:take])
                have += take
                block = block[take:]
                if have == depth:
                    yield ready(np.concatenate(parts))
                    parts, have = [], 0
        if parts:
            yield ready(np.concatenate(parts))

    dst, codec = _import_target(dst, compression, compression_level)
    return (yield from write_volume_iter(placeholder, dst, format="ome-zarr", overwrite=overwrite, chunks=chunks,
                                         max_side=max_side, labels=labels, pyramid=True, slabs=slabs(), **codec))


def import_volume(
    src: Any,
    dst: str | os.PathLike,
    *,
    chunks: Any = None,
    max_side: int = 256,
    overwrite: bool = False,
    nan_value: float | None = None,
    spacing: Any = None,
    unit: str | None = None,
    labels: bool = False,
    compression: str | None = None,
    compression_level: int | None = None,
    progress: Callable[[Progress], Any] | None = None,
    **reader_options: Any,
) -> Volume:
    """Convert any scan into the working format: an OME-Zarr pyramid (NGFF 0.5, zarr v3).

    Streams chunk by chunk: peak memory is bounded by one slab of ``chunks[0]`` planes, so scans larger than
    RAM import. Level 0 keeps full resolution; each next level halves every axis until all sides are
    ``<= max_side``.

    Parameters
    ----------
    src : path-like, Volume or array
        Anything :func:`open_volume` reads, or an array in memory (numpy, dask, zarr; ``spacing`` and ``unit``
        give its geometry).
    dst : path-like
        The ``*.zarr`` folder to create (atomically).
    chunks : int or tuple of 3 int, optional
        Chunk shape (default 128^3).
    max_side : int
        Pyramid stop size (default 256).
    overwrite : bool
        Replace an existing ``dst``.
    nan_value : float, optional
        Replace NaN and infinities by this value (default: they are an error).
    spacing, unit : optional
        Override the geometry the source file declares (for formats that do not store it, e.g. BMP stacks).
    labels : bool
        The source holds labels: downsample by nearest.
    compression : {"lz4", "zstd", "none"}, optional
        Blosc compressor of the chunks (default lz4: straightening from the store waits mostly for
        decompression, which lz4 does more than twice as fast as zstd, for files 1.1-1.3x larger on CT data; the
        table is in ``benchmarks/RESULTS.md``). Every chunk carries a crc32c checksum. Stores written before
        (blosc zstd) stay readable.
    compression_level : int, optional
        Blosc level 1-9 (default 5 for lz4, 3 for zstd).
    progress : callable, optional
        Called with each progress record.
    **reader_options
        Passed to :func:`open_volume` (``series=`` for DICOM...).

    Returns
    -------
    Volume
        The imported volume, opened lazily from ``dst``, with all pyramid levels.
    """
    return run(import_volume_iter(src, dst, chunks=chunks, max_side=max_side, overwrite=overwrite,
                                  nan_value=nan_value, spacing=spacing, unit=unit, labels=labels,
                                  compression=compression, compression_level=compression_level,
                                  **reader_options), progress)
