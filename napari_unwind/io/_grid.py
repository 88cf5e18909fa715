"""A mask on its scan's voxel grid: the scan's shape, or a box of that grid placed by the file's origin.

Segmentation tools often save a mask cropped to the segment's bounding box (3D Slicer's ``.seg.nrrd``, ITK-SNAP
crops, a mask cut out of a larger one): the same voxel size and orientation as the scan, a smaller shape, and a
``space origin`` (NIfTI: an affine) that says where the box lies. :func:`place_on_grid` puts such a box back into
the scan's shape (lazily: a padded dask array) so that every face takes it as it takes a full mask.

Where the box lies
------------------
The offset of the box's voxel (0, 0, 0) in the scan's grid is read from the two files' origins:

- both NRRD with ``space directions`` (the same ``space``), or both NIfTI with an affine: in the files' own world
  (directions with signs or a rotation included), the two orientations must agree;
- otherwise along the array axes (``origin + index x spacing``, as every reader of this package gives them), which
  needs any orientation a file states to be the plain one (a positive diagonal).

The offset must be a whole number of voxels (within 0.01), and no voxel of the mask may lie beyond the scan. A
mask whose file states no origin (TIFF, raw) cannot be placed: only a mask of the scan's shape is taken then.
A mask of the scan's shape is taken voxel for voxel, whatever its header says (a note names a header that differs).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InvalidInputError
from ._volume import Volume

__all__ = ["place_array", "place_on_grid"]

_WHOLE = 0.01  # voxels: how far a box's origin may lie off the scan's grid
_SAME_DIRECTION = 1e-4  # relative: two orientations that agree


def _triple(v: Any) -> str:
    return " x ".join(f"{float(x):g}" for x in v)


def _name(vol: Volume, what: str) -> str:
    from pathlib import Path

    return f"the {what} {Path(vol.source).name}" if vol.source else f"the {what}"


def _frame(vol: Volume) -> tuple[str, np.ndarray, np.ndarray] | None:
    """(kind, M, w0): world = M @ index + w0 in the file's own world, index in array order (axis0, axis1, axis2);
    None when the file states no orientation."""
    md = vol.metadata if isinstance(vol.metadata, dict) else {}
    origin = np.asarray(vol.origin, dtype=float)[::-1]  # the readers reverse the file's world order
    if vol.format == "nrrd":
        vecs = [v for v in (md.get("space directions") or []) if v is not None]
        if len(vecs) == 3:
            return f"nrrd:{md.get('space')}", np.asarray(vecs[::-1], dtype=float).T, origin
    if vol.format == "nifti" and md.get("affine") is not None:
        a = np.asarray(md["affine"], dtype=float)
        return "nifti", a[:3, :3][:, ::-1], origin
    return None


def _states_origin(vol: Volume) -> bool:
    """Whether the file says where its voxel (0, 0, 0) lies."""
    md = vol.metadata if isinstance(vol.metadata, dict) else {}
    if vol.format == "nrrd":
        return (md.get("header") or {}).get("space origin") is not None
    if vol.format == "nifti":
        return int(md.get("sform_code") or 0) > 0 or int(md.get("qform_code") or 0) > 0
    if vol.format in ("ome-zarr", "dicom"):
        return True
    return False


def _plain(frame: tuple[str, np.ndarray, np.ndarray] | None, spacing: np.ndarray) -> bool:
    """No orientation stated, or the plain one: world axis k along array axis 2 - k, positive."""
    return frame is None or np.allclose(frame[1][::-1], np.diag(spacing), atol=_SAME_DIRECTION * spacing.max())


def _offset(mask: Volume, scan: Volume, name: str) -> np.ndarray:
    """The box's voxel (0, 0, 0) in the scan's grid, array order (floats, not yet checked to be whole)."""
    fm, fs = _frame(mask), _frame(scan)
    sp = np.asarray(scan.spacing, dtype=float)
    if fm is not None and fs is not None and fm[0] == fs[0]:
        if not np.allclose(fm[1], fs[1], atol=_SAME_DIRECTION * sp.max()):
            raise InvalidInputError(
                f"{name} has another orientation than the scan (space directions {np.round(fm[1].T, 4).tolist()} "
                f"against {np.round(fs[1].T, 4).tolist()}): resample the mask onto the scan's grid")
        return np.linalg.solve(fs[1], fm[2] - fs[2])
    if not (_plain(fm, sp) and _plain(fs, sp)):
        raise InvalidInputError(
            f"{name}'s orientation cannot be matched to the scan's (one is not axis-aligned and they are not both "
            "NRRD or both NIfTI): resample the mask onto the scan's grid, or give it the scan's shape")
    return (np.asarray(mask.origin, dtype=float) - np.asarray(scan.origin, dtype=float)) / sp


def _grid(name: str, shape: Any, spacing: Any, scan: Volume) -> str:
    return (f"{name} has shape {_triple(shape)} and voxel size {_triple(spacing)}, the scan {_triple(scan.shape)} "
            f"and {_triple(scan.spacing)}")


def _same_voxel_size(name: str, shape: Any, spacing: Any, scan: Volume) -> None:
    if not np.allclose(spacing, scan.spacing, rtol=1e-4):
        ratio = np.asarray(spacing, dtype=float) / np.asarray(scan.spacing, dtype=float)
        coarser = bool(np.all(ratio > 1.5) and np.allclose(ratio, np.round(ratio), rtol=1e-3))
        todo = ("refine it at the scan's resolution (unwind select ... --full-resolution SCAN)" if coarser
                else "resample the mask onto the scan")
        raise InvalidInputError(f"{_grid(name, shape, spacing, scan)}: a mask must lie on the scan's voxel grid (its "
                                f"shape, or a box of it with the same voxel size, placed by its origin); {todo}")


def _embed(data: Any, off: np.ndarray, scan: Volume, name: str) -> tuple[Any, str]:
    """``data`` (a box whose voxel 0 lies at voxel ``off`` of the scan, floats) padded to the scan's shape (dask)."""
    import dask.array as da

    shape, target = np.array(data.shape), np.array(scan.shape)
    whole = np.round(off)
    if np.abs(off - whole).max() > _WHOLE:
        raise InvalidInputError(f"{name}'s origin lies {_triple(np.round(off - whole, 3))} voxels off the scan's "
                                "grid: resample the mask onto the scan")
    lo = whole.astype(np.int64)
    hi = lo + shape
    a = np.maximum(-lo, 0)  # the part of the box inside the scan, in the mask's indices
    b = shape - np.maximum(hi - target, 0)
    if (a >= b).any():
        raise InvalidInputError(f"{name} (shape {_triple(shape)}) lies outside the scan: its origin puts it at voxel "
                                f"{_triple(lo)} of a scan of {_triple(target)}; it is not this scan's mask, or its "
                                "origin is wrong")
    if (a > 0).any() or (b < shape).any():
        inside = data[a[0]:b[0], a[1]:b[1], a[2]:b[2]]
        beyond = int(np.count_nonzero(np.asarray(data))) - int(np.count_nonzero(np.asarray(inside)))
        if beyond:
            raise InvalidInputError(
                f"{beyond} voxels of {name} lie beyond the scan (its box spans voxels {_triple(lo)} to "
                f"{_triple(hi - 1)} of a scan of {_triple(target)}): it is not this scan's mask, or its origin is "
                "wrong")
        data = inside
    start = np.maximum(lo, 0)
    pad = [(int(start[k]), int(target[k] - start[k] - data.shape[k])) for k in range(3)]
    placed = da.pad(da.asarray(data), pad, mode="constant", constant_values=0)
    return placed, (f"{name} (shape {_triple(shape)}) is a box of the scan's grid: placed at voxel {_triple(lo)} by "
                    "its origin")


def place_array(data: Any, scan: Volume, *, spacing: Any, origin: Any,
                name: str = "the mask") -> tuple[Any, str | None]:
    """An array (a napari Labels layer's data, any dtype) whose voxel 0 lies at ``origin`` with voxels of
    ``spacing`` (array order, the scan's orientation) on the scan's grid, as :func:`place_on_grid` places a file.

    Returns the data (``data`` itself when it has the scan's shape, else a lazily padded dask array) and the note.
    """
    shape = np.array(data.shape)
    if tuple(shape) == tuple(scan.shape):
        return data, None
    sp = np.asarray(spacing, dtype=float)
    _same_voxel_size(name, shape, sp, scan)
    off = (np.asarray(origin, dtype=float) - np.asarray(scan.origin, dtype=float)) / np.asarray(scan.spacing)
    return _embed(data, off, scan, name)


def place_on_grid(mask: Volume, scan: Volume, *, what: str = "mask") -> tuple[Volume, str | None]:
    """The mask (or label image) on the scan's voxel grid: the scan's shape, spacing, origin and unit.

    Parameters
    ----------
    mask : Volume, shape (M0, M1, M2)
        The mask as read from its file: the scan's shape (taken voxel for voxel), or a box of the scan's grid (the
        same voxel size and orientation) whose file states its origin.
    scan : Volume, shape (N0, N1, N2)
        The scan.
    what : str
        What the mask is, in messages (``"mask"``, ``"label image"``).

    Returns
    -------
    placed : Volume, shape (N0, N1, N2)
        The mask's voxels (dtype kept; zero outside the box), lazily padded, with the scan's geometry.
    note : str or None
        What was done when it was more than taking the voxels (a box placed; a header that differs from the
        scan's), one line; None otherwise.

    Raises
    ------
    InvalidInputError
        Another voxel size or orientation, a box off the scan's grid or reaching beyond the scan with voxels of the
        mask there, or a smaller shape whose file states no origin.
    """
    if not isinstance(mask, Volume) or not isinstance(scan, Volume):
        raise InvalidInputError(f"place_on_grid takes two Volumes, got {type(mask).__name__} and "
                                f"{type(scan).__name__}")
    name = _name(mask, what)
    shape, target = np.array(mask.shape), np.array(scan.shape)
    msp, ssp = np.asarray(mask.spacing, dtype=float), np.asarray(scan.spacing, dtype=float)
    if tuple(shape) == tuple(target):
        same = (np.allclose(msp, ssp, rtol=1e-6)
                and np.allclose(mask.origin, scan.origin, atol=1e-6 * float(ssp.max())))
        placed = Volume(mask.data, spacing=scan.spacing, origin=scan.origin, unit=scan.unit, source=mask.source,
                        format=mask.format, metadata=mask.metadata)
        note = None if same else (
            f"{name}'s spacing {_triple(msp)} / origin {_triple(mask.origin)} differ from the scan's "
            f"{_triple(ssp)} / {_triple(scan.origin)}: the scan's are used (same shape, voxel for voxel)")
        return placed, note
    if tuple(shape[::-1]) == tuple(target):
        raise InvalidInputError(f"{name} has shape {_triple(shape)}, the scan's {_triple(target)} reversed: its axes "
                                "were written in the other order (x, y, z against z, y, x; pynrrd's default "
                                "index_order 'F' for an array read with 'C'); write it in the scan's axis order")
    if not _states_origin(mask):
        raise InvalidInputError(f"{_grid(name, shape, msp, scan)}, and its file does not say where it lies in the scan "
                                "(no origin): give a mask of the scan's shape, or save it with its origin (NRRD, "
                                "NIfTI, OME-Zarr)")
    _same_voxel_size(name, shape, msp, scan)
    placed, note = _embed(mask.data, _offset(mask, scan, name), scan, name)
    return Volume(placed, spacing=scan.spacing, origin=scan.origin, unit=scan.unit, source=mask.source,
                  format=mask.format, metadata=mask.metadata), note
