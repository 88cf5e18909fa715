"""Selecting features as a specimen mask, refining it at full resolution, and label files."""

from __future__ import annotations

import os
from collections.abc import Generator
from pathlib import Path
from typing import Any

import dask.array as da
import numpy as np
from scipy import ndimage

from ..errors import InvalidInputError, NoBodyError
from ..progress import Progress, run
from ._features import Features

__all__ = [
    "check_segmentation_output",
    "load_features",
    "refine_mask",
    "refine_mask_iter",
    "refine_mask_to",
    "save_features",
    "save_features_iter",
    "select",
    "selected_ids",
]

_SEGMENTATION_KEY = "segmentation"


def _check_isovalue(isovalue: Any) -> float | None:
    if isovalue is None:
        return None
    try:
        v = float(isovalue)
    except (TypeError, ValueError):
        raise InvalidInputError(f"isovalue must be a number, got {isovalue!r}") from None
    if not np.isfinite(v):
        raise InvalidInputError(f"isovalue must be finite, got {isovalue!r}")
    return v


def selected_ids(features: Features, *, seeds: Any = None, ids: Any = None, basins: bool = False) -> list[int]:
    """The feature ids chosen by seeds (full-resolution voxel coordinates) and/or ids, sorted, unique.

    With ``basins`` (needs the tree) a seed chooses the feature whose basin holds it, even where the label volume
    is background.

    Raises
    ------
    InvalidInputError
        Neither seeds nor ids; a seed outside the volume; a seed on the background (the message names the
        nearest feature, its distance and where to click); an unknown id.
    """
    if seeds is None and ids is None:
        raise InvalidInputError("choose features by seeds= (points in full-resolution voxels) or by ids=")
    chosen: set[int] = set()
    if ids is not None:
        raw = np.atleast_1d(np.asarray(ids))
        if raw.ndim != 1 or raw.size == 0:
            raise InvalidInputError(f"ids must be a non-empty list of feature ids 1..{features.k}, got {ids!r}")
        for i in raw.tolist():
            chosen.add(features._check_id(i))
    if seeds is not None:
        from ._features import _seed_array

        pts = _seed_array(seeds)
        found = features.basin_ids_at(pts) if basins else features.ids_at(pts)
        for p, f in zip(pts, found):
            if f == 0:
                near, dist, where = features.nearest_feature(p)
                seed = tuple(float(c) for c in p)
                if near == 0:
                    raise InvalidInputError(f"seed {seed} is in the background and there is no feature at all")
                raise InvalidInputError(
                    f"seed {seed} is in the background; the nearest feature is {near}, {dist:.3g} full-resolution "
                    f"voxels away (e.g. at {where}); click on a feature"
                )
            chosen.add(int(f))
    return sorted(chosen)


def select(
    features: Features,
    *,
    seeds: Any = None,
    ids: Any = None,
    isovalue: float | None = None,
    fill_holes: bool = False,
) -> np.ndarray:
    """The mask of the chosen features at working resolution.

    Parameters
    ----------
    features : Features
        A segmentation (:func:`segment` or :meth:`JoinTree.simplify`).
    seeds : array_like, shape (n, 3) or (3,), optional
        Points in FULL-resolution voxel coordinates (array axis order); each chooses the feature under it.
    ids : int or sequence of int, optional
        Feature ids (1..k) to choose as well.
    isovalue : float, optional
        Instead of the label volume's per-feature thresholds, keep the voxels of the chosen features' basins
        (everything they claim, down to the lowest values) whose working value is ``>= isovalue``; a seed then
        chooses the feature whose basin holds it, so it may lie below the labels' cut (e.g. in a thrombus).
        Needs the tree.
    fill_holes : bool
        Fill the cavities of the mask (``scipy.ndimage.binary_fill_holes``).

    Returns
    -------
    ndarray of bool, shape (M0, M1, M2)
        The selection at working resolution (``features.labels.shape``).

    Raises
    ------
    InvalidInputError
        See :func:`selected_ids`; and an isovalue without a tree.
    """
    if not isinstance(features, Features):
        raise InvalidInputError(f"select needs Features (from segment or JoinTree.simplify), got {type(features)}")
    isovalue = _check_isovalue(isovalue)
    if isovalue is not None and features.tree is None:
        features.basins([])  # raises the explanation
    chosen = selected_ids(features, seeds=seeds, ids=ids, basins=isovalue is not None)
    if isovalue is None:
        mask = np.isin(features.labels, chosen)
    else:
        mask = features.basins(chosen)
        mask &= features.tree.values >= isovalue
    if fill_holes:
        mask = ndimage.binary_fill_holes(mask)
    return mask


# ------------------------------------------------------------------------------------------------------------------
# full resolution
# ------------------------------------------------------------------------------------------------------------------
def _working_index(start: int, stop: int, scale: float, n: int) -> np.ndarray:
    return np.minimum(np.floor((np.arange(start, stop) + 0.5) / scale).astype(np.int64), n - 1)


def _refine_block(block: np.ndarray, *, allowed: np.ndarray, scale: tuple[float, ...], iso: float,
                  block_info: dict | None = None) -> np.ndarray:
    loc = block_info[0]["array-location"]
    idx = [_working_index(a, b, s, n) for (a, b), s, n in zip(loc, scale, allowed.shape)]
    sub = allowed[np.ix_(*idx)]
    return sub & (block >= iso)


def _resolve_level(volume: Any, mask: np.ndarray, level: Any, features: Features | None) -> int:
    if level is None:
        matches = [i for i, lvl in enumerate(volume.levels) if tuple(lvl.shape) == mask.shape]
        if not matches:
            raise InvalidInputError(
                f"the mask's shape {mask.shape} matches no pyramid level of the volume "
                f"({[tuple(lv.shape) for lv in volume.levels]}); pass level="
            )
        return matches[0]
    if isinstance(level, (bool, np.bool_)) or not isinstance(level, (int, np.integer)):
        raise InvalidInputError(f"level must be an integer, got {level!r}")
    if not 0 <= int(level) < len(volume.levels):
        raise InvalidInputError(f"level {level} does not exist: the volume has levels 0..{len(volume.levels) - 1}")
    if tuple(volume.levels[int(level)].shape) != mask.shape:
        raise InvalidInputError(
            f"the mask's shape {mask.shape} differs from level {level}'s shape {tuple(volume.levels[int(level)].shape)}"
        )
    return int(level)


def _refine(
    volume: Any,
    mask: Any,
    *,
    features: Features | None,
    isovalue: float | None,
    level: int | None,
    chunks: Any,
) -> tuple[da.Array, float]:
    """:func:`refine_mask` that also returns the isovalue used."""
    from ..io._volume import Volume

    if not isinstance(volume, Volume):
        raise InvalidInputError(f"refine_mask needs a Volume (open_volume / import_volume), got {type(volume)}")
    mask = np.asarray(mask)
    if mask.ndim != 3:
        raise InvalidInputError(f"the mask must be 3D, got shape {mask.shape}")
    mask = mask.astype(bool, copy=False)
    isovalue = _check_isovalue(isovalue)
    if features is not None and not isinstance(features, Features):
        raise InvalidInputError(f"features must be Features, got {type(features)}")
    if features is not None:
        # the features know the scale to full resolution: the volume needs no pyramid (the original scan will do)
        if features.shape != mask.shape:
            raise InvalidInputError(f"the mask's shape {mask.shape} differs from the features' {features.shape}")
        if tuple(features.full_shape) != volume.shape:
            raise InvalidInputError(
                f"these features were computed on a volume of shape {tuple(features.full_shape)}, not {volume.shape}"
            )
        if level is not None and int(level) != features.level:
            raise InvalidInputError(f"the features are at level {features.level}, not level {level}")
        scale = tuple(float(s) for s in features.scale)
    else:
        lvl = _resolve_level(volume, mask, level, None)
        scale = tuple(float(s) / float(f) for s, f in zip(volume.level_spacings[lvl], volume.spacing))
    if not mask.any():
        raise InvalidInputError("the mask is empty: select at least one feature")
    if isovalue is None:
        if features is None:
            raise InvalidInputError("give isovalue= or the features= the mask came from (for their thresholds)")
        isovalue = default_isovalue(features, mask, volume=volume)
    allowed = ndimage.binary_dilation(mask, structure=np.ones((3, 3, 3), bool))
    if features is not None:
        allowed &= mask | (features.labels == 0)
    data = volume.data if chunks is None else volume.data.rechunk(chunks)
    iso = isovalue
    if np.issubdtype(data.dtype, np.integer):  # compare integers exactly: v >= iso <=> v >= ceil(iso)
        iso = float(np.ceil(isovalue))
    return data.map_blocks(_refine_block, allowed=allowed, scale=scale, iso=iso, dtype=bool), isovalue


def default_isovalue(features: Features, mask: Any, *, volume: Any = None) -> float:
    """The full-resolution threshold a working-resolution ``mask`` is refined at by default: the lowest
    :func:`~napari_unwind.segmentation.specimen_isovalue` of the features it covers (with ``fill_holes`` that
    includes a feature enclosed by the selection), each halfway between the medium around it and its body.

    With ``volume`` (the scan; :func:`refine_mask` passes its own) the two levels are read from the scan at full
    resolution, so the working level does not bias them and features loaded from a label file (no tree) give
    the same value as the segmentation itself. Where the values show no body above the medium, the smallest
    threshold of the covered features (the features' own cut). A mask that covers no feature (a body no feature
    holds: rule 7 of :func:`~napari_unwind.segmentation.candidates`) is read around itself, and needs ``volume``.

    One rule for the dock, ``unwind select``, ``unwind run`` and the server's jobs.

    Parameters
    ----------
    features : Features
        The segmentation the mask came from.
    mask : ndarray of bool, shape ``features.shape``
        The selection at working resolution (:func:`select`).
    volume : Volume or array_like, optional
        The full-resolution scan the features were computed on.
    """
    from ._candidates import specimen_isovalue

    mask = np.asarray(mask, dtype=bool)
    if mask.shape != features.labels.shape:
        raise InvalidInputError(f"the mask has shape {mask.shape} but the features {features.labels.shape}; select "
                                "the mask from these features")
    covered = np.unique(features.labels[mask])
    covered = covered[covered > 0]
    if covered.size == 0:
        # a body no feature holds (candidates' rule 7): its levels read from the scan around the mask itself
        from ._candidates import _scan_levels

        levels = None if volume is None or not mask.any() else _scan_levels(features, [], mask, volume)
        if levels is None and volume is None:
            raise InvalidInputError("the mask covers no feature; give isovalue=")
        if levels is None:
            raise NoBodyError("the mask covers no feature and the scan shows no body above the medium around it; "
                              "give isovalue=")
        return float(0.5 * (levels[0] + levels[1]))
    # the lowest of the features' own, as candidates() cuts a body of several features: a dimmer feature the
    # selection encloses (fill_holes) stays in
    return float(min(specimen_isovalue(features, [int(i)], volume=volume) for i in covered))


def refine_mask(
    volume: Any,
    mask: Any,
    *,
    features: Features | None = None,
    isovalue: float | None = None,
    level: int | None = None,
    chunks: Any = None,
) -> da.Array:
    """The full-resolution mask of a working-resolution selection, as a lazy dask array.

    Each full-resolution chunk takes the working mask, dilated by one working voxel (but never into another
    feature when ``features`` is given), upsampled by nearest, AND the chunk's voxels ``>= isovalue``. Nothing
    is computed here; compute or store it chunk by chunk (:func:`refine_mask_iter` writes it).

    Parameters
    ----------
    volume : Volume
        The scan with its pyramid (``volume.data`` is full resolution).
    mask : ndarray of bool, shape (M0, M1, M2)
        The selection at working resolution (:func:`select`).
    features : Features, optional
        The segmentation the mask came from: gives the level, the default isovalue and keeps the dilation out
        of unselected features.
    isovalue : float, optional
        Full-resolution threshold. Default: :func:`default_isovalue` of the features the mask covers, read
        from ``volume``.
    level : int, optional
        Without ``features``: the pyramid level of ``mask`` (default: the level whose shape matches), which gives
        the scale to full resolution. With ``features`` their own scale is used, so ``volume`` may be the
        original scan without a pyramid.
    chunks : int or tuple, optional
        Rechunk the full-resolution data to this before refining (default: its own chunks).

    Returns
    -------
    dask.array.Array of bool, shape ``volume.shape``
    """
    return _refine(volume, mask, features=features, isovalue=isovalue, level=level, chunks=chunks)[0]


def refine_mask_iter(
    volume: Any,
    mask: Any,
    *,
    features: Features | None = None,
    isovalue: float | None = None,
    level: int | None = None,
    chunks: Any = None,
    output: str | os.PathLike | None = None,
    overwrite: bool = False,
) -> Generator[Progress, None, Any]:
    """Refine a working-resolution selection at full resolution, chunk by chunk.

    Without ``output``: returns the lazy dask bool array of :func:`refine_mask`. With ``output``: writes it (as
    0/1 uint8; OME-Zarr outputs as a label pyramid) atomically with :func:`napari_unwind.io.write_volume`,
    yielding its progress, and returns the written path. The full-resolution mask is never held whole.

    Parameters are those of :func:`refine_mask`, plus ``output`` and ``overwrite``.
    """
    from ..io import write_volume_iter
    from ..io._formats import output_format

    yield Progress("refine", 0, 1)
    lazy, iso = _refine(volume, mask, features=features, isovalue=isovalue, level=level, chunks=chunks)
    if output is None:
        yield Progress("refine", 1, 1, "lazy")
        return lazy
    options: dict[str, Any] = {}
    if output_format(output) == "ome-zarr":
        options["labels"] = True
        options["attributes"] = {"refined_mask": {"isovalue": float(iso), "source": volume.source}}
    written = yield from write_volume_iter(lazy.astype(np.uint8), output, spacing=volume.spacing, unit=volume.unit,
                                           origin=volume.origin, overwrite=overwrite, **options)
    return written


def refine_mask_to(volume: Any, mask: Any, output: str | os.PathLike, *, progress=None, **kwargs: Any) -> Path:
    """Run :func:`refine_mask_iter` with ``output``; return the written path."""
    return run(refine_mask_iter(volume, mask, output=output, **kwargs), progress)


# ------------------------------------------------------------------------------------------------------------------
# label files
# ------------------------------------------------------------------------------------------------------------------
def check_segmentation_output(path: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Check up front that a segmentation can be saved at ``path`` (a ``*.zarr`` in a writable folder)."""
    from ..io._atomic import check_writable
    from ..io._formats import output_format

    if output_format(path) != "ome-zarr":
        raise InvalidInputError(f"a segmentation is saved as OME-Zarr labels; name the output *.zarr, got {path}")
    return check_writable(path, overwrite=overwrite)


def save_features_iter(
    features: Features, path: str | os.PathLike, *, overwrite: bool = False
) -> Generator[Progress, None, Path]:
    """Generator form of :func:`save_features`."""
    from ..io import write_volume_iter

    if not isinstance(features, Features):
        raise InvalidInputError(f"save_features needs Features, got {type(features)}")
    check_segmentation_output(path, overwrite=overwrite)
    written = yield from write_volume_iter(
        features.labels, path, spacing=features.spacing, unit=features.unit, origin=features.working_origin,
        overwrite=overwrite, labels=True, attributes={_SEGMENTATION_KEY: features.to_attributes()},
    )
    return written


def save_features(features: Features, path: str | os.PathLike, *, overwrite: bool = False, progress=None) -> Path:
    """Write the label volume (working resolution) and the statistics to an OME-Zarr labels folder.

    The metadata (``unwind.segmentation``) holds ``k``, the level, the scale to full resolution and the
    statistics, so :func:`load_features` gives features that :func:`select` and :func:`refine_mask` accept
    (without the tree: no working-resolution isovalue).
    """
    return run(save_features_iter(features, path, overwrite=overwrite), progress)


def load_features(path: str | os.PathLike) -> Features:
    """Open a segmentation written by :func:`save_features`."""
    from ..io import open_volume

    vol = open_volume(path)
    attrs = (vol.metadata.get("unwind") or {}).get(_SEGMENTATION_KEY)
    if not attrs:
        raise InvalidInputError(f"{path} is not a segmentation written by 'unwind segment' (no segmentation metadata)")
    return Features.from_labels(np.asarray(vol.data.compute()), attrs)
