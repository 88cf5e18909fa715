"""OME-Zarr (NGFF 0.5 on zarr v3): the project's working format.

A scan is stored as a multiscale pyramid: level 0 at full resolution, each next level halved along every axis
(box average for intensities, nearest for labels) until every side is at most ``max_side`` (256). Every level
is chunked (128^3 by default) and zstd-compressed, and the ``ome`` attributes record axes, units and the scale
of each level, so napari, Fiji (MoBIE/n5-viewer) and ome-zarr-py read it with the right geometry.

Writing streams slab by slab along axis0 in one pass: every level is built from the slabs as they go by and
written chunk-aligned, none is read back. Peak memory is about two slabs of ``chunks[0]`` planes (the one being
written and the one read ahead) plus the pyramid's pending planes (1/8 + 1/64 + ... of a slab), never the whole
volume.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import dask.array as da
import numpy as np
import zarr
from zarr.codecs import BloscCodec

from ..errors import InvalidInputError, UnknownFormatError
from ..progress import Progress
from ._volume import Volume

__all__ = ["read_ome_zarr", "write_ome_zarr", "pyramid_shapes", "DEFAULT_CHUNKS", "DEFAULT_MAX_SIDE"]

DEFAULT_CHUNKS = (128, 128, 128)
DEFAULT_MAX_SIDE = 256
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


def _scale_translation(transforms: list[dict], ndim: int) -> tuple[list[float], list[float]]:
    scale = [1.0] * ndim
    translation = [0.0] * ndim
    for t in transforms or []:
        if t.get("type") == "scale":
            scale = [float(v) for v in t["scale"]]
        elif t.get("type") == "translation":
            translation = [float(v) for v in t["translation"]]
    return scale, translation


def read_ome_zarr(path: Path, *, level: int | None = None) -> Volume:
    """Open an OME-Zarr image (NGFF 0.4 or 0.5) or a plain 3D zarr array, lazily.

    Parameters
    ----------
    path : Path
        The zarr folder (the multiscales group, or one array).
    level : int, optional
        Return only this pyramid level as the volume (default: full resolution, all levels kept).
    """
    try:
        node = zarr.open(store=str(path), mode="r")
    except Exception as exc:  # zarr raises several types for a broken store
        raise InvalidInputError(f"{path} is not a readable zarr store ({exc}); is the copy complete?") from None
    if isinstance(node, zarr.Array):
        data = da.from_zarr(node)
        attrs = dict(node.attrs)
        spacing = attrs.get("unwind", {}).get("spacing", (1.0, 1.0, 1.0))
        return Volume(data, spacing=spacing, unit=attrs.get("unwind", {}).get("unit"), source=str(path),
                      format="ome-zarr", metadata={"attrs": attrs})
    attrs = dict(node.attrs)
    multiscales, version = _multiscales(attrs)
    if not multiscales:
        arrays = sorted(name for name, _ in node.arrays())
        hint = f" It holds arrays {arrays}; open one of them as {path}/<name>." if arrays else ""
        raise UnknownFormatError(f"{path} is a zarr group without OME-Zarr 'multiscales' metadata.{hint}")
    ms = multiscales[0]
    axes = ms.get("axes", [{"name": a} for a in AXES])
    axis_names = [a["name"] if isinstance(a, dict) else str(a) for a in axes]
    space = [i for i, a in enumerate(axes) if not isinstance(a, dict) or a.get("type", "space") == "space"]
    if len(space) != 3:
        raise InvalidInputError(f"{path} has axes {axis_names}; napari-unwind needs exactly 3 spatial axes")
    unit = next((a.get("unit") for a in axes if isinstance(a, dict) and a.get("type", "space") == "space"), None)
    global_scale, global_translation = _scale_translation(ms.get("coordinateTransformations", []), len(axes))
    levels, spacings = [], []
    origin = (0.0, 0.0, 0.0)
    for i, ds in enumerate(ms["datasets"]):
        arr = node[ds["path"]]
        if arr.ndim != len(axes):
            raise InvalidInputError(f"{path}/{ds['path']} has {arr.ndim} dimensions but {len(axes)} axes")
        d = da.from_zarr(arr)
        # drop non-spatial axes of length 1 (t, c); refuse real channels or time points
        index = []
        for ax in range(arr.ndim):
            if ax in space:
                index.append(slice(None))
            elif arr.shape[ax] == 1:
                index.append(0)
            else:
                raise InvalidInputError(
                    f"{path} has a non-spatial axis {axis_names[ax]!r} of length {arr.shape[ax]}; "
                    "export one channel/time point as its own 3D image first"
                )
        d = d[tuple(index)]
        scale, translation = _scale_translation(ds.get("coordinateTransformations", []), len(axes))
        sp = tuple(scale[a] * global_scale[a] for a in space)
        if i == 0:
            origin = tuple(translation[a] + global_translation[a] for a in space)
        levels.append(d)
        spacings.append(sp)
    if level is not None:
        if not 0 <= level < len(levels):
            raise InvalidInputError(f"{path} has pyramid levels 0..{len(levels) - 1}, got level={level}")
        levels, spacings = levels[level:], spacings[level:]
    unwind_attrs = attrs.get("unwind", {})
    return Volume(
        levels[0],
        spacing=spacings[0],
        unit=unit,
        origin=origin,
        levels=tuple(levels),
        level_spacings=tuple(spacings),
        source=str(path),
        format="ome-zarr",
        metadata={"ngff_version": version, "name": ms.get("name"), "unwind": unwind_attrs},
    )


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


def _downsample2(block: np.ndarray, *, labels: bool) -> np.ndarray:
    """Halve every axis longer than 1 (rounding up): box mean for intensities, nearest for labels.

    The mean is a sum of the 8 (or 4, 2) strided sub-grids in a wide accumulator, so no float copy of the whole
    block is made; integers are rounded half up.
    """
    if labels:
        return block[tuple(slice(None, None, 2) if s > 1 else slice(None) for s in block.shape)]
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


class _Cascade:
    """Build every pyramid level from consecutive slabs of level 0, each written once, chunk-aligned.

    Level k keeps (a) planes waiting to fill its next chunk-deep write and (b) at most one plane waiting for its
    partner before 2x2x2 averaging into level k+1. Memory is about 1/8 + 1/64 + ... of the incoming slab.
    """

    def __init__(self, arrays: list, *, labels: bool, writer: ThreadPoolExecutor):
        self.arrays = arrays
        self.writer = writer  # level writes run here while the next level is averaged
        self.labels = labels
        self.pending: list[list[np.ndarray]] = [[] for _ in arrays]  # planes waiting for a chunk-aligned write
        self.carry: list[np.ndarray | None] = [None] * len(arrays)  # an odd plane waiting for its partner
        self.written = [0] * len(arrays)

    def push(self, level: int, block: np.ndarray, *, last: bool) -> None:
        arr = self.arrays[level]
        self.pending[level].append(block)
        have = sum(b.shape[0] for b in self.pending[level])
        depth = arr.chunks[0]
        if have < depth and not last:
            return
        data = np.concatenate(self.pending[level]) if len(self.pending[level]) > 1 else self.pending[level][0]
        n = have if last else (have // depth) * depth
        z0 = self.written[level]
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


def write_ome_zarr(
    volume: Volume,
    path: Path,
    *,
    chunks: Any = None,
    pyramid: bool = True,
    max_side: int = DEFAULT_MAX_SIDE,
    labels: bool = False,
    compression_level: int = 3,
    name: str | None = None,
    attributes: dict[str, Any] | None = None,
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
    compression_level : int
        zstd level (1-9); 3 is a good balance of speed and size.
    name : str, optional
        Image name stored in the metadata.
    attributes : dict, optional
        Extra JSON-serialisable attributes stored under ``"unwind"`` (provenance, the straightening map...).
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

    root = zarr.open_group(store=str(path), mode="w", zarr_format=3)
    shuffle = "bitshuffle" if dtype.itemsize == 1 else "shuffle"  # byte shuffle is faster for 16-bit CT here
    codec = BloscCodec(cname="zstd", clevel=int(compression_level), shuffle=shuffle)
    arrays = []
    for lvl, shp in enumerate(shapes):
        c = _normalise_chunks(chunk_shape, shp)
        arrays.append(root.create_array(
            str(lvl), shape=shp, chunks=c, dtype=dtype, compressors=codec, fill_value=0,
            dimension_names=list(AXES),
        ))

    # One pass over the source: every level is built from the slabs as they stream by (no level is read back).
    depth = chunk_shape[0]
    starts = list(range(0, shape[0], depth))

    def read_slab(z0: int) -> np.ndarray:
        return np.asarray(volume.data[z0:min(shape[0], z0 + depth)].compute())

    # read the next slab while this one is written
    with ThreadPoolExecutor(max_workers=1) as reader, ThreadPoolExecutor(max_workers=len(arrays)) as writer:
        pyr = _Cascade(arrays, labels=labels, writer=writer)
        pending = reader.submit(read_slab, starts[0])
        for i, z0 in enumerate(starts):
            slab = pending.result()
            if i + 1 < len(starts):
                pending = reader.submit(read_slab, starts[i + 1])
            pyr.push(0, slab, last=i + 1 == len(starts))
            del slab
            yield Progress("write", i + 1, len(starts), f"planes {z0}-{z0 + depth - 1} of {shape[0]}"
                           if z0 + depth <= shape[0] else f"planes {z0}-{shape[0] - 1} of {shape[0]}")

    root.attrs["ome"] = _ngff_attrs(name or Path(volume.source or path).name, volume.unit, spacings,
                                    volume.origin, labels)
    unwind_attrs = {"spacing": list(volume.spacing), "unit": volume.unit, "labels": bool(labels)}
    if volume.source:
        unwind_attrs["imported_from"] = {"path": volume.source, "format": volume.format}
    unwind_attrs.update(attributes or {})
    root.attrs["unwind"] = unwind_attrs

