"""napari reader contributions: every scan format :func:`napari_unwind.io.open_volume` knows, and sessions.

A session (``*.unwind.json``, :mod:`napari_unwind.session`) opens as the layers that restore the work on its scan:

- the scan (Image, lazy, with the session's spacing and unit and the deformation's origin);
- the selection (Labels, the selected features of the segmentation the session records, recomputed from the scan;
  left to the Unwind dock when the viewer has one: it rebuilds it in a worker instead of the UI thread);
- the ends (Points named ``"ends"``: head and tail, or every part's start and end for a specimen in pieces);
- the curve of the deformation (a Shapes path named ``"curve"``).

Every coordinate is a world coordinate (physical units: voxel index x spacing + origin), the frame the deformation
lives in. Each layer's ``metadata["napari_unwind"]`` holds ``session_path`` and what the layer restores;
the curve's holds ``deformation`` (:meth:`~napari_unwind.deformation.Deformation.to_dict`) for the Unwind dock.
No napari import: the layers are napari's plain ``(data, meta, type)`` tuples.

A scan's layer (opened alone or by a session) carries ``contrast_limits`` from its voxels
(:func:`contrast_limits`): napari gives lazy float data [0, 1] and lazy integer data its first slice's range, so a CT
in Hounsfield units would open black and white until auto-contrast.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from itertools import product
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidInputError, UnknownFormatError
from ..io import detect_format, open_volume
from ..session import (
    SESSION_SUFFIX,
    Session,
    SourceChangedError,
    SourceMissingError,
    load_session,
    open_source,
)
from ._docks import current_viewer_has_dock

__all__ = ["contrast_limits", "get_reader", "get_session_reader", "read", "read_session", "session_layers"]

#: Most points of the curve path drawn (the deformation itself is in the metadata, exact).
_CURVE_POINTS = 512

#: Contrast limits of a scan: these percentiles of at most ``_CLIM_VOXELS`` voxels of one pyramid level, taken
#: from whole chunks of at most ``_CLIM_READ`` voxels in all (at least one chunk, at most ``_CLIM_CHUNKS``): dask
#: reads a chunk whole however little of it is asked for (a slab of the NRRD reader, a chunk of a compressed store).
_CLIM_PERCENTILES = (0.5, 99.5)
_CLIM_VOXELS = 2**22
_CLIM_READ = 2**25
_CLIM_CHUNKS = 64


def contrast_limits(data: Any, *, max_voxels: int = _CLIM_VOXELS, max_read: int = _CLIM_READ,
                    max_chunks: int = _CLIM_CHUNKS) -> tuple[float, float]:
    """Contrast limits for a scan: the 0.5th and 99.5th percentiles of a bounded sample of its voxels.

    napari gives a lazy float array [0, 1] and a lazy integer one the range of the first slice it draws; its own
    rule for large arrays (:func:`napari.layers.utils.calc_data_range`) reads three planes' minimum and maximum,
    which one bright voxel or the air around a specimen decides.

    Parameters
    ----------
    data : array or sequence of arrays
        The voxels (numpy or dask), or a pyramid finest first (``Volume.levels``). The finest level of at most
        ``max_voxels`` voxels is read whole. When every level is larger, the coarsest is sampled: chunks spread
        over it, as many as ``max_read`` voxels hold (at least one, at most ``max_chunks``), each strided to keep
        ``max_voxels`` values in all. No other chunk is read.
    max_voxels, max_read, max_chunks : int
        The sample's bounds.

    Returns
    -------
    (low, high) : tuple of 2 float
        ``low < high`` always: NaN and infinities are ignored; percentiles that meet fall back to the sample's
        minimum and maximum, a constant ``v`` gives ``(v, v + 1)`` and a sample without a finite value ``(0, 1)``.
    """
    levels = list(data) if isinstance(data, (list, tuple)) else [data]
    sizes = [math.prod(int(n) for n in a.shape) for a in levels]
    fits = [i for i, n in enumerate(sizes) if n <= max_voxels]
    array = levels[fits[0]] if fits else levels[int(np.argmin(sizes))]
    values = _sample(array, int(max_voxels), int(max_read), int(max_chunks))
    values = np.asarray(values, dtype=np.float64).ravel()
    values = values[np.isfinite(values)]
    if values.size == 0:
        return 0.0, 1.0
    low, high = (float(v) for v in np.percentile(values, _CLIM_PERCENTILES))
    if not high > low:
        low, high = float(values.min()), float(values.max())
    if not high > low:  # constant: a range napari can draw (v + 1 == v for |v| >= 2**53)
        high = low + max(1.0, abs(low) * 1e-6)
    return low, high


def _sample(array: Any, max_voxels: int, max_read: int, max_chunks: int) -> np.ndarray:
    """At most ``max_voxels`` voxels of ``array`` from chunks of ``max_read`` voxels in all (at least one chunk)."""
    shape = tuple(int(n) for n in array.shape)
    if math.prod(shape) <= max_voxels:
        return np.asarray(array)
    chunks = getattr(array, "chunks", None)
    chunks = (tuple(tuple(int(c) for c in axis) for axis in chunks) if _is_chunked(chunks, shape)
              else tuple((n,) for n in shape))  # numpy (a memory map reads only what is asked): one chunk
    grid = [len(axis) for axis in chunks]
    chunk_voxels = math.prod(max(axis) for axis in chunks)
    budget = max(1, min(max_chunks, max_read // chunk_voxels))
    # chunks per axis: doubled along the axis with the most chunks per pick while the total stays in the budget
    picks = [1] * len(grid)
    while True:
        free = [ax for ax in range(len(grid)) if picks[ax] < grid[ax]]
        if not free:
            break
        ax = max(free, key=lambda a: grid[a] / picks[a])
        more = min(grid[ax], 2 * picks[ax])
        if math.prod(picks) // picks[ax] * more > budget:
            break
        picks[ax] = more
    indices = [sorted({int((k + 0.5) * g / p) for k in range(p)}) for g, p in zip(grid, picks)]
    starts = [np.concatenate([[0], np.cumsum(axis)[:-1]]).astype(int) for axis in chunks]
    blocks = list(product(*indices))
    per_block = max(1, max_voxels // len(blocks))
    pieces = []
    for block in blocks:
        extent = [chunks[ax][i] for ax, i in enumerate(block)]
        step = max(1, math.ceil((math.prod(extent) / per_block) ** (1 / len(extent))))
        while math.prod(-(-n // step) for n in extent) > per_block:
            step += 1
        pieces.append(array[tuple(
            slice(int(starts[ax][i]) + min(step // 2, n - 1), int(starts[ax][i]) + n, step)
            for ax, (i, n) in enumerate(zip(block, extent)))])
    if hasattr(array, "dask"):
        import dask

        pieces = list(dask.compute(*pieces))
    return np.concatenate([np.asarray(p).ravel() for p in pieces])


def _is_chunked(chunks: Any, shape: tuple[int, ...]) -> bool:
    """Whether ``chunks`` are dask's: per axis, the chunk lengths adding up to the axis' length."""
    try:
        return len(chunks) == len(shape) and all(sum(int(c) for c in axis) == n for axis, n in zip(chunks, shape))
    except TypeError:
        return False


def _single(path: str | list[str]) -> str | None:
    if isinstance(path, (list, tuple)):
        return str(path[0]) if len(path) == 1 else None  # a list of files is a stack napari handles itself
    return str(path)


def get_reader(path: str | list[str]) -> Callable[[Any], list] | None:
    """Return a reader function when napari-unwind can open ``path``, else None (napari then asks others)."""
    path = _single(path)
    if path is None:
        return None
    try:
        detect_format(Path(path))
    except (UnknownFormatError, FileNotFoundError):
        return None
    except InvalidInputError:
        return read  # ours, but unreadable (a named pipe...): reading says why in one line
    return read


def read(path: str | list[str]) -> list:
    """Open one scan as a (multiscale, lazy) Image layer with its spacing, origin and unit."""
    from ._layers import image_layer

    if isinstance(path, list):
        path = path[0]
    from ..io.channels import _count, open_channels

    p = Path(path).expanduser().absolute()
    if p.exists() and _count(p, detect_format(p), {}) > 1:
        # one layer per channel (as napari's channel_axis), each its own Volume: the dock can export them together
        layers = []
        file_name = p.name.rstrip("/")
        for k, volume in enumerate(open_channels(p)):
            name = f"{file_name} [{volume.metadata['channel']}]"
            data, meta, kind = image_layer(volume, name=name, contrast_limits=contrast_limits(volume.levels),
                                           colormap=CHANNEL_COLORMAPS[k % len(CHANNEL_COLORMAPS)],
                                           blending="additive")
            meta["metadata"]["napari_unwind"]["channel"] = volume.metadata["channel"]
            layers.append((data, meta, kind))
        return layers
    volume = open_volume(path)
    return [image_layer(volume, contrast_limits=contrast_limits(volume.levels))]


#: Colormaps of a multi-channel file's layers, in order (napari's own choice for channel_axis starts likewise).
CHANNEL_COLORMAPS = ("green", "magenta", "cyan", "yellow", "red", "blue")


def get_session_reader(path: str | list[str]) -> Callable[[Any], list] | None:
    """Return :func:`read_session` for a ``*.unwind.json`` file, else None."""
    path = _single(path)
    if path is None or not path.lower().endswith(SESSION_SUFFIX):
        return None
    return read_session


def read_session(path: str | list[str]) -> list:
    """Open a session file as the layers that restore it (see the module docstring).

    Raises
    ------
    InvalidInputError
        The file is not a valid session (:func:`~napari_unwind.session.load_session` says why).
    SourceMissingError
        The session's scan is not where the session says.
    SourceChangedError
        The scan there has another shape or voxel type than the session's.
    """
    if isinstance(path, list):
        path = path[0]
    session_path = Path(path).expanduser().absolute()
    # with an Unwind dock in the viewer, the dock rebuilds the selection in a worker (not on the UI thread)
    return session_layers(load_session(session_path), session_path=session_path,
                          selection=not current_viewer_has_dock())


def session_layers(session: Session, *, session_path: str | Path | None = None, selection: bool = True) -> list:
    """The layer-data tuples restoring ``session``: scan, selection (when recorded), ends and curve (when present).

    Parameters
    ----------
    session : Session
        A loaded session.
    session_path : str or path, optional
        Where it was read from; recorded in every layer's metadata and named in errors.
    selection : bool
        Recompute the selected features (default). This runs the segmentation's join tree on its working level:
        0.3 s for the fish phantom, about 20 s for a noisy 256^3 level, all of it blocking the caller (napari's
        readers run on the UI thread). The dock passes False and recomputes it in a worker from the segmentation
        record, which the image layer's metadata then holds as ``"segmentation"``; so does :func:`read_session`
        when napari's current viewer has an Unwind dock.

    Returns
    -------
    list of (data, meta, layer type)
        In this order: ``image``, ``labels`` (when the session records selected features; or its mask file,
        metadata ``selection_mask``), ``points`` (when it
        records ends), ``shapes`` (when it holds a deformation).
    """
    from ._layers import image_layer

    src = session.source
    named = f"the session {session_path}" if session_path else "the session"
    scan_path = Path(src.path)
    if not scan_path.exists():
        raise SourceMissingError(
            f"the scan of {named} is missing: expected at {scan_path}. Put the scan back there, or correct "
            "\"source\" -> \"path\" in the session file to its new location, then open the session again"
        )
    volume = open_source(src, scan_path)
    if tuple(volume.shape) != src.shape or np.dtype(volume.dtype).name != src.dtype:
        raise SourceChangedError(
            f"the scan at {scan_path} is not the one {named} was made from: it holds {tuple(volume.shape)} voxels "
            f"of {np.dtype(volume.dtype).name}, the session's scan {src.shape} of {src.dtype}. Point the session's "
            "\"source\" -> \"path\" at the original scan"
        )
    spacing = np.asarray(src.spacing, dtype=float)  # the session's: it may have been given by hand
    deformation = session.deformation
    origin = np.asarray(deformation.origin if deformation is not None else volume.origin, dtype=float)
    unit = src.unit
    units = {"units": (unit,) * 3} if unit else {}
    common = {"session_path": None if session_path is None else str(session_path), "source": src.path}

    image = image_layer(volume, name=scan_path.name, scale=tuple(spacing), translate=tuple(origin),
                        contrast_limits=contrast_limits(volume.levels), **units)
    image[1]["metadata"]["napari_unwind"].update(common, spacing=tuple(spacing), unit=unit)
    layers: list = [image]

    seg = session.segmentation
    if seg is not None:
        image[1]["metadata"]["napari_unwind"]["segmentation"] = seg.to_dict()
    if selection and seg is not None and seg.k is not None and (seg.selected or seg.seeds):
        layers.append(_selection_layer(volume, session, spacing, origin, units, common))
    if seg is not None and seg.mask is not None:
        layers.append(_mask_layer(volume, seg, named, spacing, origin, units, common))

    if session.endpoints is not None:
        ends = session.endpoints
        if ends.chain:
            voxels = [p for pair in ends.chain for p in pair]
            roles = ["head" if i == 0 else "tail" if i == len(voxels) - 1 else
                     f"part {i // 2 + 1} {'start' if i % 2 == 0 else 'end'}" for i in range(len(voxels))]
        else:
            voxels, roles = [ends.head, ends.tail], ["head", "tail"]
        world = np.asarray(voxels, dtype=float) * spacing + origin
        layers.append((world, {
            "name": "ends", "features": {"end": roles}, "face_color": "yellow", "size": float(4 * spacing.max()),
            "metadata": {"napari_unwind": {**common, "endpoints": ends.to_dict()}}, **units,
        }, "points"))

    if deformation is not None:
        lo, hi = 0.0, deformation.length
        n = int(min(_CURVE_POINTS, max(2, np.ceil((hi - lo) / spacing.min()) + 1)))
        centres, _ = deformation.sample(np.linspace(lo, hi, n))
        layers.append(([centres], {
            "name": "curve", "shape_type": "path", "edge_color": "cyan", "edge_width": float(spacing.max()),
            "metadata": {"napari_unwind": {**common, "deformation": deformation.to_dict()}}, **units,
        }, "shapes"))
    return layers


def _mask_layer(volume: Any, seg: Any, named: str, spacing: np.ndarray, origin: np.ndarray, units: dict,
                common: dict) -> tuple[Any, dict[str, Any], str]:
    """The mask file that was the selection, as a Labels layer on the scan (its metadata names the chosen label)."""
    from ..workflow import read_mask

    path = Path(seg.mask)
    data, notes = read_mask(path, volume, session=named)
    meta = {"name": path.name, "scale": tuple(spacing), "translate": tuple(origin), "opacity": 0.5,
            "metadata": {"napari_unwind": {**common, "source": str(path), "mask_label": seg.mask_label,
                                           "selection_mask": True, "notes": list(notes)}}, **units}
    return data, meta, "labels"


def _selection_layer(volume: Any, session: Session, spacing: np.ndarray, origin: np.ndarray, units: dict,
                     common: dict) -> tuple[Any, dict[str, Any], str]:
    """The selected features, recomputed from the scan as the session's segmentation did (labels = feature ids)."""
    from ..segmentation import segment, selected_ids

    seg = session.segmentation
    features = segment(volume, features=seg.k, level=seg.level)
    # the recorded ids are the choice; seeds only when no id was recorded (a seed may sit in a basin, off the labels)
    ids = selected_ids(features, ids=list(seg.selected)) if seg.selected else selected_ids(features, seeds=seg.seeds)
    labels = np.where(np.isin(features.labels, ids), features.labels, 0).astype(features.labels.dtype)
    scale = np.asarray(features.scale, dtype=float) * spacing  # working voxels in the session's spacing
    translate = origin + (scale - spacing) / 2  # a working voxel's centre is the centre of the block it covers
    meta = {"name": "selection", "scale": tuple(scale), "translate": tuple(translate), "opacity": 0.5,
            "metadata": {"napari_unwind": {**common, "segmentation": seg.to_dict(), "selected": ids,
                                           "level": features.level}}, **units}
    return labels, meta, "labels"
