"""Several channels of one scan grid: open them, check they share the grid, write them as one multi-channel image.

A scan's channels come as a channel axis of one file (OME-Zarr with a ``c`` axis, an ImageJ hyperstack ``ZCYX``
or an OME-TIFF ``CZYX``) or as several files of the same grid (one per stain). :func:`open_channels` gives each
as its own lazy 3D :class:`~napari_unwind.io.Volume` (``metadata["channel"]`` holds its name); channels of one
OME-Zarr file share the file's dask chunks, so a computation over all of them reads each chunk once.

:func:`write_channels_iter` writes channels of one grid as one image: OME-Zarr with a ``c`` axis (chunks of one
channel, a pyramid per channel, the names in ``omero.channels``) or an ImageJ hyperstack ``ZCYX`` (the names as
slice labels). Each slab of planes is computed for every channel at once (one ``dask.compute``), so channels
computed by one task (:func:`napari_unwind.warp.straighten_channels`) are computed once.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidInputError
from ..progress import Progress
from ._volume import Volume

__all__ = ["open_channels", "channel_names", "check_same_grid", "write_channels_iter", "CHANNEL_FORMATS"]

#: Output formats that hold several channels in one image.
CHANNEL_FORMATS = ("ome-zarr", "tiff")


def _count(path: Path, fmt: str, options: dict[str, Any]) -> int:
    if fmt == "ome-zarr":
        from .ome_zarr import channel_axis_length

        return channel_axis_length(path)
    if fmt == "tiff" and path.is_file():
        from .tiff import tiff_channel_count

        try:
            return tiff_channel_count(path, int(options.get("series", 0)))
        except Exception:  # noqa: BLE001 - the reader gives the proper error for a broken file
            return 1
    return 1


def _stem(path: Path) -> str:
    name = path.name.rstrip("/")
    for suffix in (".ome.zarr", ".ome.tiff", ".ome.tif", ".nii.gz", ".zarr", ".tiff", ".tif", ".nrrd", ".nhdr",
                   ".nii", ".dat", ".raw"):
        if name.lower().endswith(suffix):
            return name[: -len(suffix)] or name
    return path.stem or name


def open_channels(paths: str | os.PathLike | Sequence[str | os.PathLike], *, names: Sequence[str] | None = None,
                  **options: Any) -> list[Volume]:
    """Open every channel of a scan, each as a lazy 3D volume.

    Parameters
    ----------
    paths : path or sequence of paths
        One file with a channel axis (OME-Zarr ``c`` axis, multi-channel TIFF), one single-channel scan, or several
        files of the same grid (each may itself hold several channels).
    names : sequence of str, optional
        One name per channel, in order (default: the file's channel names, else ``c<k>`` for a channel axis and
        the file's name for a single-channel file; a repeated default name gets ``-2``, ``-3``...).
    **options
        Passed to every reader (``level=``, ``series=``...).

    Returns
    -------
    list of Volume, each shape (N0, N1, N2)
        One per channel; ``metadata["channel"]`` is its name. All share shape, spacing, origin and unit.

    Raises
    ------
    InvalidInputError
        No paths; the channels do not share one grid (the message names both grids); ``names`` of the wrong
        length or with repeats.
    """
    from ._api import open_volume
    from ._formats import detect_format

    items = [paths] if isinstance(paths, str | os.PathLike) else list(paths)
    if not items:
        raise InvalidInputError("open_channels needs at least one path, got none")
    volumes: list[Volume] = []
    defaults: list[str] = []
    for item in items:
        path = Path(item).expanduser().absolute()
        if not path.exists():
            raise FileNotFoundError(f"{path} does not exist")
        fmt = options.get("format") or detect_format(path)
        count = _count(path, fmt, options)
        if count > 1:
            for k in range(count):
                v = open_volume(path, channel=k, **options)
                volumes.append(v)
                defaults.append(str(v.metadata.get("channel") or f"c{k}"))
        else:
            volumes.append(open_volume(path, **options))
            defaults.append(_stem(path))
    if names is None:
        chosen, seen = [], {}
        for n in defaults:
            seen[n] = seen.get(n, 0) + 1
            chosen.append(n if seen[n] == 1 else f"{n}-{seen[n]}")
    else:
        chosen = [str(n) for n in names]
        if len(chosen) != len(volumes):
            raise InvalidInputError(f"{len(volumes)} channels were opened but {len(chosen)} names were given "
                                    f"({chosen}); give one name per channel")
        if len(set(chosen)) != len(chosen) or any(not n for n in chosen):
            raise InvalidInputError(f"channel names must be distinct and not empty, got {chosen}")
    check_same_grid(volumes, [str(v.source or n) for v, n in zip(volumes, chosen, strict=True)])
    return [replace(v, metadata={**v.metadata, "channel": n}) if v.metadata.get("channel") != n else v
            for v, n in zip(volumes, chosen, strict=True)]  # levels kept


def channel_index(path: str | os.PathLike, channel: str | int, **options: Any) -> int:
    """The 0-based index of ``channel`` (a name or an index) in the file's channel axis.

    Raises
    ------
    InvalidInputError
        The file has no channel axis, or no such channel (the message lists its channels).
    """
    from ._formats import detect_format

    path = Path(path).expanduser().absolute()
    count = _count(path, options.get("format") or detect_format(path), options)
    if count <= 1:
        raise InvalidInputError(f"{path} has no channel axis: leave out the channel ({channel!r})")
    names = [str(v.metadata.get("channel")) for v in open_channels(path, **options)]
    text = str(channel)
    if text in names:
        return names.index(text)
    if text.isdigit() and int(text) < count:
        return int(text)
    raise InvalidInputError(f"{path} has no channel {text!r}; its channels are {', '.join(names)} (or 0-{count - 1})")


def channel_names(volumes: Sequence[Volume]) -> list[str]:
    """The channels' names (``metadata["channel"]``, else ``c<k>``)."""
    return [str(v.metadata.get("channel") or f"c{k}") for k, v in enumerate(volumes)]


def _close(a: Sequence[float], b: Sequence[float], scale: Sequence[float]) -> bool:
    return all(abs(x - y) <= 1e-6 * max(abs(s), 1e-30) for x, y, s in zip(a, b, scale, strict=True))


def check_same_grid(volumes: Sequence[Volume], what: Sequence[str] | None = None) -> None:
    """Refuse channels that do not share one grid: shape, spacing and origin (to 1e-6 of a voxel), unit.

    ``what`` names each (a file); the message names the first that differs from the first channel.
    """
    if not volumes:
        raise InvalidInputError("no channels were given")
    what = list(what) if what is not None else [f"channel {k}" for k in range(len(volumes))]
    ref = volumes[0]
    for v, name in zip(volumes[1:], what[1:], strict=True):
        if tuple(v.shape) != tuple(ref.shape):
            raise InvalidInputError(f"{name} has shape {tuple(v.shape)} but {what[0]} has {tuple(ref.shape)}: "
                                    "channels must share one scan grid; resample it onto the first one's grid")
        if v.unit != ref.unit and v.unit and ref.unit:
            raise InvalidInputError(f"{name} is in {v.unit} but {what[0]} in {ref.unit}: channels must share one "
                                    "scan grid; convert one of them")
        if not _close(v.spacing, ref.spacing, ref.spacing) or not _close(v.origin, ref.origin, ref.spacing):
            raise InvalidInputError(
                f"{name} has spacing {tuple(v.spacing)} and origin {tuple(v.origin)} but {what[0]} has "
                f"{tuple(ref.spacing)} and {tuple(ref.origin)}: channels must share one scan grid")


def _stacked(volumes: Sequence[Volume]) -> Any:
    """The channels as one dask array (C, N0, N1, N2): slicing it computes every channel of the slab at once."""
    import dask.array as da

    common = np.result_type(*[v.dtype for v in volumes])
    return da.stack([v.data if v.dtype == common else v.data.astype(common) for v in volumes], axis=0)


def write_channels_iter(volumes: Sequence[Volume], path: str | os.PathLike, *, format: str | None = None,
                        overwrite: bool = False, attributes: dict[str, Any] | None = None,
                        **options: Any) -> Iterator[Progress]:
    """Write channels of one grid as one multi-channel image, atomically; yields progress, returns the path.

    Parameters
    ----------
    volumes : sequence of Volume, each shape (N0, N1, N2)
        The channels (names from ``metadata["channel"]``), sharing shape, spacing, origin and unit; channels of
        different voxel types are written in their common type (numpy's ``result_type``).
    path : str or path-like
        ``.zarr`` (OME-Zarr, axes ``c, z, y, x``) or ``.tif``/``.tiff`` (ImageJ hyperstack ``ZCYX``; uint8, uint16
        or float32 below 4 GB). Other formats hold one channel: refused.
    attributes : dict, optional
        OME-Zarr: extra JSON attributes stored under ``"unwind"`` (the straightening record...).
    **options
        OME-Zarr: ``chunks`` (3 ints, per channel), ``compression``, ``compression_level``, ``shuffle``,
        ``pyramid``, ``max_side``. TIFF: ``compression``, ``compression_level``.
    """
    from ._atomic import atomic_output, check_not_input, check_writable
    from ._files import check_room
    from ._formats import output_format

    volumes = list(volumes)
    fmt = output_format(path, format)
    if fmt not in CHANNEL_FORMATS:
        raise InvalidInputError(f"{Path(path).name}: {fmt} holds one channel; write {len(volumes)} channels as "
                                "OME-Zarr (.zarr) or an ImageJ hyperstack (.tif), or straighten one channel at a time")
    names = channel_names(volumes)
    check_same_grid(volumes, names)
    target = check_writable(path, overwrite=overwrite)
    check_not_input([target], [v.source for v in volumes])
    nbytes = sum(v.nbytes for v in volumes)
    check_room(target, nbytes, compressed=fmt == "ome-zarr" and options.get("compression", "lz4") != "none")
    with atomic_output(target, overwrite=overwrite) as tmp:
        if fmt == "ome-zarr":
            yield from _write_zarr(volumes, names, tmp, attributes=attributes, **options)
        else:
            if attributes:
                raise InvalidInputError("attributes are stored in OME-Zarr outputs only")
            yield from _write_hyperstack(volumes, names, tmp, **options)
    return target


class _ChannelLevel:
    """One channel of a 4D zarr array (c, z, y, x), seen as the 3D array :class:`ome_zarr._Cascade` writes."""

    def __init__(self, array: Any, c: int):
        self.array, self.c = array, c
        self.shape = tuple(array.shape[1:])
        self.chunks = tuple(array.chunks[1:])
        self.dtype = array.dtype

    def __setitem__(self, key: Any, value: np.ndarray) -> None:
        self.array[(self.c, key)] = value


def _write_zarr(volumes: list[Volume], names: list[str], path: Path, *, attributes: dict[str, Any] | None = None,
                chunks: Any = None, pyramid: bool = True, max_side: int | None = None, compression: str | None = None,
                compression_level: int | None = None, shuffle: str = "auto") -> Iterator[Progress]:
    import json
    from concurrent.futures import ThreadPoolExecutor

    import zarr

    from . import ome_zarr as oz
    from ._straight_record import straightening_record

    first = volumes[0]
    shape, dtype = tuple(first.shape), np.result_type(*[v.dtype for v in volumes])
    chunk_shape = oz._normalise_chunks(chunks, shape)
    shapes = oz.pyramid_shapes(shape, oz.DEFAULT_MAX_SIDE if max_side is None else max_side) if pyramid else [shape]
    spacings = [tuple(first.spacing)]
    for lvl in range(1, len(shapes)):
        spacings.append(tuple(sp * (2 if n > 1 else 1) for sp, n in zip(spacings[-1], shapes[lvl - 1], strict=True)))
    try:
        json.dumps(attributes or {})
    except TypeError as exc:
        raise InvalidInputError(f"attributes must be JSON-serialisable: {exc}") from None
    codecs = oz._codecs(compression or oz.DEFAULT_COMPRESSION, compression_level, shuffle, dtype)
    nc = len(volumes)
    root = zarr.open_group(store=str(path), mode="w", zarr_format=3)
    arrays = []
    for lvl, shp in enumerate(shapes):
        c = oz._normalise_chunks(chunk_shape, shp)
        arrays.append(root.create_array(
            str(lvl), shape=(nc, *shp), chunks=(1, *c), dtype=dtype, compressors=codecs, fill_value=0,
            dimension_names=["c", *oz.AXES], config={"write_empty_chunks": True},
        ))
    stack = _stacked(volumes)
    depth = chunk_shape[0]
    starts = list(range(0, shape[0], depth))
    with ThreadPoolExecutor(max_workers=max(1, len(arrays))) as writer:
        cascades = [oz._Cascade([_ChannelLevel(a, k) for a in arrays], labels=False, writer=writer)
                    for k in range(nc)]
        for i, z0 in enumerate(starts):
            z1 = min(shape[0], z0 + depth)
            slab = np.asarray(stack[:, z0:z1].compute())  # every channel of the slab in one computation
            for k in range(nc):
                cascades[k].push(0, np.ascontiguousarray(slab[k]), last=i + 1 == len(starts))
            del slab
            yield Progress("write", i + 1, len(starts), f"planes {z0}-{z1 - 1} of {shape[0]}, {nc} channels")
    name = Path(first.source).name if first.source else oz.final_name(path)  # as write_ome_zarr names one channel
    ngff = oz._ngff_attrs(name, first.unit, spacings, first.origin, False)
    ms = ngff["multiscales"][0]
    ms["axes"] = [{"name": "c", "type": "channel"}, *ms["axes"]]
    for ds in ms["datasets"]:
        for t in ds["coordinateTransformations"]:
            t[t["type"]] = [1.0 if t["type"] == "scale" else 0.0, *t[t["type"]]]
    ngff["omero"] = {"channels": [{"label": n, "active": True} for n in names], "version": oz.NGFF_VERSION}
    root.attrs["ome"] = ngff
    unwind_attrs: dict[str, Any] = {"spacing": list(first.spacing), "unit": first.unit, "labels": False,
                                    "all_chunks_written": True, "channels": names}
    sources = [v.source for v in volumes if v.source]
    if sources:
        unwind_attrs["imported_from"] = {"paths": sources}
    record = straightening_record(first)
    if record is not None:
        unwind_attrs["straightening"] = record
    unwind_attrs.update(attributes or {})
    root.attrs["unwind"] = unwind_attrs


def _write_hyperstack(volumes: list[Volume], names: list[str], path: Path, *, compression: str | None = None,
                      compression_level: int | None = None) -> Iterator[Progress]:
    from . import tiff

    first = volumes[0]
    nz, ny, nx = first.shape
    nc = len(volumes)
    dtype = np.result_type(*[v.dtype for v in volumes])
    if dtype not in tiff.IMAGEJ_DTYPES:
        raise InvalidInputError(f"an ImageJ hyperstack holds uint8, uint16 or float32, not {dtype}: write "
                                f"{Path(path).name} as OME-Zarr (.zarr) instead")
    if nc * first.nbytes > tiff.BIGTIFF_THRESHOLD:
        raise InvalidInputError(f"{nc} channels of {first.nbytes / 2**30:.1f} GiB exceed the 4 GB of an ImageJ "
                                "hyperstack: write OME-Zarr (.zarr) instead")
    options = tiff.imagej_options(first)
    options.pop("imagej")
    options["metadata"] = {**options["metadata"], "axes": "ZCYX", "hyperstack": True,
                           "mode": "composite" if nc > 1 else "grayscale", "Labels": names * nz}
    codec = tiff._compression(compression)
    if codec is not None:
        options["compression"] = codec
        if compression_level is not None:
            options["compressionargs"] = {"level": int(compression_level)}
    stack = _stacked(volumes)
    pages = Volume(stack.transpose(1, 0, 2, 3).reshape(nz * nc, ny, nx), spacing=first.spacing, unit=first.unit,
                   origin=first.origin)

    def slab(p0: int, p1: int) -> np.ndarray:
        block = np.asarray(stack[:, p0 // nc:p1 // nc].compute())  # (C, dz, Y, X): all channels at once
        return block.transpose(1, 0, 2, 3).reshape(-1, ny, nx)

    yield from tiff._write_pages(path, pages, bigtiff=False, imagej=True, options=options, shape=(nz, nc, ny, nx),
                                 slab=slab)
