"""Automatic twist: turn the frames about the curve so that ``v`` points dorsal.

The parallel-transport frames of a centreline follow its bends but know nothing of the specimen's own
orientation. A fish, however, is laterally compressed: its cross-sections are taller (dorsoventral) than wide, so
the major principal axis of each cross-section is the dorsoventral axis. This module measures that axis along
the curve and returns, per point, the angle ``theta`` that turns the frame about ``n`` so that ``v`` lies along it
(``u' = cos(theta) u + sin(theta) v``, ``v' = -sin(theta) u + cos(theta) v``, ``n`` unchanged).

Method
------
1. Cross-sections. At each curve point (or at a subset of them, about one per voxel, when the curve is denser)
   the mask is sampled with bilinear interpolation (``scipy.ndimage.map_coordinates``, order 1) on a disc of
   ``(x, y)`` positions in the plane spanned by ``u`` and ``v``. A section is the part of the body connected to
   its centre: samples whose nearest curve point is not (about) the section's own belong to another part of the
   body curling through the plane and are dropped, and so is every part of the disc not connected to the centre
   (another turn of a coil, the tail beside the head), which, far from the centre, would dominate the moments.
   With a volume, the mask's one-voxel boundary band is read as the part of each voxel the body fills, the
   intensity between the medians of the mask's interior and of the shell beyond the band (clipped to [0, 1]):
   a section a few voxels across is, as a binary mask, a staircase whose axis is pulled toward the grid's.
   Only the bounding box of the discs is read from the mask and the volume. (With ``radius=None`` the mask's voxels are
   listed once to find the default radius.)
2. Orientation. The second moments of each section give the major-axis angle ``phi`` (relative to ``u``) and the
   anisotropy ``e = (l1 - l2) / (l1 + l2)`` of the section (0 for a disc; 0.47 for a 0.6 ellipse). The blur of
   the trilinear interpolation (a tent of variance h^2 / 6 per array axis, anisotropic for anisotropic voxels)
   is removed from the moments first. Each section contributes the doubled-angle vector ``e w exp(2 i phi)``
   (an orientation modulo pi), ``w`` its reliability: 1 for a section of at least 50 voxels, proportionally
   less for smaller ones, whose orientation is dominated by the voxel staircase.
3. Continuity and confidence. The doubled-angle vectors are smoothed along the arclength by a Gaussian-weighted
   local linear fit (no bias at the ends). The length of the smoothed vector, the orientation strength, is the
   anisotropy that survives averaging: sections whose major axes disagree along s (a round vessel's noise, the
   90-degree flip of a near-round section) cancel in it, although each alone may look elongated. Divided by the
   local mean reliability (at least 0.1: a 5-voxel section), it is the agreement the confidence reads: a thin
   tail's small sections weigh less in the estimate, but where they agree the estimate is followed. The
   confidence is 0 below half of ``min_anisotropy`` and 1 from twice it (a smoothstep between). It is weighed by the
   precision of the smoothed angle: its standard error, from the sections' scatter about the local fit and the
   fit's equivalent kernel (large at a thin tail's tip, where a few small sections, each off by tens of degrees,
   carry a line extrapolated from one side), scales the confidence by ``(2 degrees / error)^2`` where it exceeds 2
   degrees (an inverse-variance weight: such a stretch is smoothed more, not dropped). The twist is the blend
   (a tridiagonal least-squares solve, see :func:`_blend`) that follows the unwrapped estimate where the
   confidence is 1 and keeps the twist rate 0 (the minimal-rotation frames) where it is 0, constant between two
   confident stretches, smooth everywhere: never a jump.
   A specimen whose strength reaches 0.25 (about 1.3:1 sections agreeing along s) over less than
   ``min_oriented`` of its length is taken as round as a whole: a fish's trunk reaches 0.4-0.5 over 80-98 % of
   its length, the shared aorta over 2 % (at most 0.28; the warning names the share).
4. One global sign (``v`` or ``-v``) for the whole specimen, from its dorsoventral asymmetry:

   - ``"density"`` (needs ``volume``): in each section, the centroid of the densest material (the intensity
     excess over a robust threshold, median + 3 MAD of the section) relative to the section's centroid. The
     vertebral column lies dorsal of the body's centroid along the whole trunk (the abdominal cavity is
     ventral), so this cue is anatomical and does not depend on how much of the fins the segmentation kept.
     This is the preferred cue.
   - ``"shape"`` (mask only): the skewness of each section along its major axis. The dorsal fin sticks out on
     the dorsal side, so the sections are skewed dorsally. This is weaker on real scans: segmentations often
     lose thin fins, and the anal and pelvic fins stick out ventrally.

   With ``cue="auto"`` the density cue decides when a volume is given and its score is clear, otherwise the
   shape cue; when neither is clear a warning says that the dorsal side is a guess (a twist of pi fixes it).

A specimen that is round (a cylinder, a vessel, an eel-like body) has no orientation to find: the angles are then
all 0 (the parallel-transport frames are kept) and a warning says so.

Accuracy: on the fish phantoms (true centreline, one point per voxel) v is within 5 degrees of the true dorsal
direction everywhere but the last and first 3 % of the length, median under 1 degree. It degrades where the
sections are only a few voxels across: a 5-7 voxel section's angle errs by about 16 degrees rms from the mask
alone and 6 with the intensities (averaging along s brings a thin tail within about 6 degrees, with the
intensities within 5); where the sections disagree the angle is held from the nearest reliable stretch. Orient on
the finest mask affordable, with the volume (this costs about a second at 256^3).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..errors import InvalidInputError
from ..io._volume import check_spacing

__all__ = ["estimate_twist", "apply_twist", "landmark_twist"]

_MAX_SECTIONS = 400  # cross-sections actually sampled (the angles are then evaluated at every point)
_MAX_GRID = 49  # samples across the disc diameter
_FULL_SECTION = 50.0  # voxels in a cross-section for its orientation to count fully
_CUT_FULL, _CUT_NONE = 0.1, 0.3  # share of a section's outline along excluded voxels: counted fully / not at all
_MIN_RELIABLE = 0.1  # reliability (a 5-voxel section) below which a section's agreement counts less
_ANGLE_ERROR = 2.0  # degrees: a smoothed angle whose standard error is larger is followed by (this / it)^2
_MAX_RADIUS_VOXELS = 50_000  # mask voxels used to estimate the default radius
_CUES = ("auto", "density", "shape")
_ORIENTED = 0.25  # orientation strength of a clearly oriented stretch (a fish's trunk: 0.4-0.5; a 0.8 ellipse: 0.22)
_AXES = ("major", "minor")


# ------------------------------------------------------------------------------------------------------------------
# validation helpers (shared with the other skeleton helpers of this package)
# ------------------------------------------------------------------------------------------------------------------
def _check_mask(mask: Any, name: str = "mask") -> Any:
    if not hasattr(mask, "shape") or not hasattr(mask, "__getitem__"):
        mask = np.asarray(mask)
    if len(mask.shape) != 3:
        raise InvalidInputError(f"{name} must be a 3D array (axis0, axis1, axis2), got shape {tuple(mask.shape)}")
    if min(mask.shape) < 1:
        raise InvalidInputError(f"{name} is empty (shape {tuple(mask.shape)})")
    return mask


def _check_points(points: Any, name: str = "points") -> np.ndarray:
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
        raise InvalidInputError(f"{name} must have shape (K, 3) with K >= 2 (physical units), got {pts.shape}")
    if not np.isfinite(pts).all():
        raise InvalidInputError(f"{name} must be finite numbers")
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    if (seg <= 1e-12).any():
        i = int(np.argmax(seg <= 1e-12))
        raise InvalidInputError(f"{name} {i} and {i + 1} coincide ({pts[i].tolist()}); remove duplicate points")
    return pts


def _check_frames(frames: Any, k: int) -> np.ndarray:
    fr = np.asarray(frames, dtype=float)
    if fr.shape != (k, 3, 3):
        raise InvalidInputError(f"frames must have shape ({k}, 3, 3) (rows u, v, n per point), got {fr.shape}")
    if not np.isfinite(fr).all():
        raise InvalidInputError("frames must be finite numbers")
    err = np.abs(np.einsum("kij,klj->kil", fr, fr) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(fr)
    bad = np.flatnonzero((err > 1e-3) | (det < 0))
    if len(bad):
        raise InvalidInputError(
            f"frames must be orthonormal and right-handed (rows u, v, n with u x v = n); frame {int(bad[0])} is "
            f"not: {np.round(fr[bad[0]], 4).tolist()}"
        )
    return fr


def _arclength(pts: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])


def _as_uint8(block: Any) -> np.ndarray:
    """A mask block as uint8 0/1 without copying a bool numpy array."""
    arr = np.asarray(block)
    if arr.dtype == bool:
        return arr.view(np.uint8)
    return (arr != 0).view(np.uint8)


def _mask_voxels(mask: Any, max_voxels: int) -> np.ndarray:
    """Index coordinates (N, 3) of mask voxels, an even subsample of them if there are more than ``max_voxels``."""
    idx = np.nonzero(_as_uint8(mask))
    n = len(idx[0])
    if n > max_voxels:
        step = int(math.ceil(n / max_voxels))
        idx = tuple(a[::step] for a in idx)
    return np.stack(idx, axis=1)


# ------------------------------------------------------------------------------------------------------------------
# public API
# ------------------------------------------------------------------------------------------------------------------
def apply_twist(frames: np.ndarray, angles: np.ndarray | Sequence[float] | float) -> np.ndarray:
    """Rotate frames about their own ``n`` by ``angles`` (right-hand rule about ``n``).

    Parameters
    ----------
    frames : ndarray, shape (K, 3, 3)
        Rows ``u, v, n`` per point.
    angles : float or ndarray, shape (K,)
        Twist angles in radians.

    Returns
    -------
    frames : ndarray, shape (K, 3, 3)
        ``u' = cos(t) u + sin(t) v``, ``v' = -sin(t) u + cos(t) v``, ``n' = n``.
    """
    fr = np.asarray(frames, dtype=float)
    if fr.ndim != 3 or fr.shape[1:] != (3, 3):
        raise InvalidInputError(f"frames must have shape (K, 3, 3) (rows u, v, n), got {fr.shape}")
    t = np.asarray(angles, dtype=float)
    try:
        t = np.broadcast_to(t, (len(fr),))
    except ValueError:
        raise InvalidInputError(f"angles must be a number or have shape ({len(fr)},), got {t.shape}") from None
    if not np.isfinite(t).all():
        raise InvalidInputError("twist angles must be finite")
    c, s = np.cos(t)[:, None], np.sin(t)[:, None]
    out = fr.copy()
    out[:, 0] = c * fr[:, 0] + s * fr[:, 1]
    out[:, 1] = -s * fr[:, 0] + c * fr[:, 1]
    return out


def estimate_twist(
    points: np.ndarray,
    frames: np.ndarray,
    *,
    mask: Any,
    spacing: Sequence[float] | float,
    volume: Any = None,
    radius: float | None = None,
    smoothing: float | None = None,
    dorsal_axis: str = "major",
    cue: str = "auto",
    min_anisotropy: float = 0.08,
    min_oriented: float = 0.25,
    exclude: Any = None,
    field_of_view: Any = None,
    return_info: bool = False,
) -> np.ndarray | tuple[np.ndarray, dict[str, Any]]:
    """Twist angles that turn the frames' ``v`` towards the specimen's dorsal side.

    See the module docstring for the method and the choice of the dorsal side.

    Parameters
    ----------
    points : ndarray, shape (K, 3)
        Curve points, physical units (voxel index x spacing, origin 0), head first, consecutive points distinct.
        Dense (about one per voxel) or coarser.
    frames : ndarray, shape (K, 3, 3)
        Rows ``u, v, n`` at each point (parallel-transport frames), orthonormal and right-handed.
    mask : ndarray of bool, shape (N0, N1, N2)
        The specimen. Any array supporting slicing works (numpy, memmap, dask, zarr): only the bounding box of
        the cross-sections is read (plus the whole mask once when ``radius`` is None). Non-bool arrays are read
        as ``mask != 0``.
    spacing : float or sequence of 3 float
        Voxel size of ``mask`` (and ``volume``) along axis0, axis1, axis2.
    volume : ndarray, shape (N0, N1, N2), optional
        Intensities (any real dtype, e.g. uint16 CT): the partial volume of the mask's boundary voxels (module
        docstring, step 1) and the density cue of the dorsal side. Only the bounding box of the cross-sections
        is read.
    radius : float, optional
        Half-size of the cross-section discs, physical units. Default: 1.5 times the 99.5th percentile of the
        distance from the mask voxels to the curve.
    smoothing : float, optional
        Standard deviation (arclength, physical units) of the Gaussian weights of the local linear fit along the
        curve. Default: the largest of 3 % of the curve length, 2 voxels and 1.5 point spacings.
    dorsal_axis : {"major", "minor"}
        Which principal axis of the cross-sections is dorsoventral: ``"major"`` for laterally compressed
        specimens (most fish: taller than wide), ``"minor"`` for depressed ones (rays, catfish heads).
    cue : {"auto", "density", "shape"}
        How the dorsal side is told from the ventral one (module docstring). ``"density"`` needs ``volume``.
    min_anisotropy : float
        Orientation strength (the anisotropy left after smoothing the sections' orientations along the curve)
        around which a stretch counts as round: below half of it the frames follow the minimal-rotation
        frames; the estimate is trusted fully from twice it, with a smooth blend between.
    min_oriented : float
        The fraction of the length whose orientation strength reaches 0.25 (sections about 1.3:1 whose major
        axes agree along the curve) below which the whole specimen is taken as round (a vessel, an eel-like
        body): all angles 0 and a warning.
    exclude : ndarray of bool, shape (N0, N1, N2), optional
        Voxels of the body that are not this specimen's (a branch cut off at its junction, a loop the path
        skips): left out of the sections, and a section whose outline runs along them (cut rather than ending
        at the specimen's boundary) counts less, fully from a tenth of its outline to nothing at 30 %.
    field_of_view : array_like, shape (2, 3), optional
        The scan's extent in index coordinates of ``mask`` (the faces' positions, ``lo`` and ``hi`` along each
        axis): beyond it the specimen is not known, and a section whose outline runs along a face (where the scan
        cut the specimen: a vessel running beside the face is a half-disc there) counts less, as a section cut
        along ``exclude`` does. Default: ``mask``'s own array, ``(-0.5, N - 0.5)`` along each axis (give it when
        ``mask`` is a crop of the scan).
    return_info : bool
        Also return a dict of diagnostics.

    Returns
    -------
    angles : ndarray, shape (K,)
        Radians, continuous along the curve; ``apply_twist(frames, angles)`` gives frames whose ``v`` is dorsal.
    info : dict
        Only with ``return_info``: ``"anisotropy"`` (K,) the smoothed anisotropy in [0, 1]; ``"strength"`` (K,)
        the orientation strength; ``"angle_error"`` (K,) the standard error (degrees) of the smoothed angle;
        ``"confidence"`` (K,) in [0, 1], how much the estimate was followed;
        ``"oriented"`` the fraction of the length with strength >= 0.25; ``"sign_cue"`` the
        cue that chose the dorsal side (``"density"``, ``"shape"`` or ``"none"``); ``"scores"`` the score of
        each cue (positive: ``v`` was dorsal before the sign choice); ``"radius"``, ``"smoothing"``;
        ``"round"`` True when the specimen was found round.

    Raises
    ------
    InvalidInputError
        For malformed points, frames, mask, volume, spacing or options, or an empty mask.

    Warns
    -----
    UserWarning
        When the specimen is round (angles 0), or when the dorsal side could not be told reliably.
    """
    pts = _check_points(points)
    k_pts = len(pts)
    fr = _check_frames(frames, k_pts)
    mask = _check_mask(mask)
    sp = np.asarray(check_spacing(spacing))
    if volume is not None:
        if not hasattr(volume, "shape") or not hasattr(volume, "__getitem__"):
            volume = np.asarray(volume)
        if tuple(volume.shape) != tuple(mask.shape):
            raise InvalidInputError(
                f"volume must have the mask's shape {tuple(mask.shape)}, got {tuple(volume.shape)}"
            )
    if dorsal_axis not in _AXES:
        raise InvalidInputError(f"dorsal_axis must be one of {_AXES}, got {dorsal_axis!r}")
    if cue not in _CUES:
        raise InvalidInputError(f"cue must be one of {_CUES}, got {cue!r}")
    if cue == "density" and volume is None:
        raise InvalidInputError("cue='density' needs the intensities: pass volume=..., or use cue='shape'/'auto'")
    for name, value in (("radius", radius), ("smoothing", smoothing)):
        if value is not None and not (np.isscalar(value) and np.isfinite(value) and float(value) > 0):
            raise InvalidInputError(f"{name} must be a positive number (physical units) or None, got {value!r}")
    if not (np.isscalar(min_anisotropy) and 0 < float(min_anisotropy) < 0.5):
        raise InvalidInputError(f"min_anisotropy must be a number in (0, 0.5), got {min_anisotropy!r}")
    if not (np.isscalar(min_oriented) and 0 <= float(min_oriented) <= 1):
        raise InvalidInputError(f"min_oriented must be a number in [0, 1], got {min_oriented!r}")
    if exclude is not None:
        exclude = _check_mask(exclude, "exclude")
        if tuple(exclude.shape) != tuple(mask.shape):
            raise InvalidInputError(
                f"exclude must have the mask's shape {tuple(mask.shape)}, got {tuple(exclude.shape)}"
            )

    if field_of_view is None:
        fov = np.array([[-0.5] * 3, [n - 0.5 for n in mask.shape]], dtype=float)
    else:
        fov = np.asarray(field_of_view, dtype=float) if np.ndim(field_of_view) == 2 else np.zeros(0)
        if fov.shape != (2, 3) or not np.all(np.isfinite(fov)) or np.any(fov[0] >= fov[1]):
            raise InvalidInputError(f"field_of_view must be the scan's (lo, hi) index extent along the 3 axes, lo < "
                                    f"hi, got {field_of_view!r}")

    s_all = _arclength(pts)
    length = float(s_all[-1])
    tree = cKDTree(pts)
    if radius is None:
        radius = _default_radius(mask, pts, tree, sp)
    radius = float(radius)
    vox = float(sp.min())
    if smoothing is None:
        step = float(np.median(np.diff(s_all)))
        smoothing = max(0.03 * length, 2.0 * float(sp.max()), 1.5 * step)
    smoothing = float(smoothing)

    # -- sections: a subset of the points about one (finest) voxel apart, at most _MAX_SECTIONS
    sec = _section_indices(s_all, max(vox, length / _MAX_SECTIONS))
    xs, ys, w, inside, dense, cell, cut = _sample_sections(pts, fr, sec, s_all, tree, mask, volume, sp, radius,
                                                           exclude, fov)

    # -- per-section moments
    m0 = w.sum(axis=1)
    ok = m0 > 0
    if not ok.any():
        raise InvalidInputError(
            f"none of the {len(sec)} cross-sections (radius {radius:.3g}) meets the mask: the curve lies away from "
            "the specimen; give the points in physical units (voxel index x spacing) of this mask's grid"
        )
    safe = np.where(ok, m0, 1.0)
    mx = (w * xs).sum(axis=1) / safe
    my = (w * ys).sum(axis=1) / safe
    dx, dy = xs - mx[:, None], ys - my[:, None]
    cxx = (w * dx * dx).sum(axis=1) / safe
    cyy = (w * dy * dy).sum(axis=1) / safe
    cxy = (w * dx * dy).sum(axis=1) / safe
    # trilinear interpolation blurs the voxelised mask by a tent of variance h^2 / 6 along each array axis:
    # remove that (anisotropic for anisotropic voxels) blur from the section's second moments
    # (kept only where the corrected moments stay clearly positive: tiny sections alias too much for it)
    blur = sp**2 / 6.0
    pu, pv = fr[sec, 0], fr[sec, 1]
    bxx, byy, bxy = (pu * pu) @ blur, (pv * pv) @ blur, (pu * pv) @ blur
    fix = (_min_eig(cxx - bxx, cyy - byy, cxy - bxy) >= 0.25 * _min_eig(cxx, cyy, cxy)) & ok
    cxx = np.where(fix, cxx - bxx, cxx)
    cyy = np.where(fix, cyy - byy, cyy)
    cxy = np.where(fix, cxy - bxy, cxy)
    tr = cxx + cyy
    ecc = np.where(ok & (tr > 0), np.hypot(cxx - cyy, 2 * cxy) / np.where(tr > 0, tr, 1.0), 0.0)
    phi2 = np.arctan2(2 * cxy, cxx - cyy)  # doubled major-axis angle from u
    if dorsal_axis == "minor":
        phi2 = phi2 + np.pi
    # reliability: a section a few voxels across has an orientation dominated by the voxel staircase; full
    # weight from _FULL_SECTION voxels (about 8 voxels across)
    area = m0 * cell  # physical
    n_vox = area * (np.abs(fr[sec, 2]) @ sp) / float(np.prod(sp))
    rel = np.clip(n_vox / _FULL_SECTION, 0.0, 1.0)
    # a section cut where a branch was taken off has a straight edge there that is not the specimen's: it counts
    # less (in the estimate and in its agreement, unlike a small section)
    whole = 1.0 - _smoothstep(cut, _CUT_FULL, _CUT_NONE)
    conf = ecc * rel * whole
    z = conf * np.exp(1j * phi2)

    # -- smooth along s (local linear fit of the doubled-angle vectors), evaluated at every point
    s_sec = s_all[sec]
    zhat, (conf_s, rel_s), zerr = _local_linear(s_sec, z, np.stack([conf, rel]), s_all, smoothing)
    # -- confidence: the smoothed doubled-angle vector's length is the anisotropy that survives averaging the
    # orientations along s; sections that disagree (a round vessel's noise, the flip of a near-round section's
    # major axis) cancel in it although each alone may look elongated
    strength = np.abs(zhat)
    # the confidence reads the agreement per unit of reliability: small sections weigh less in the estimate, but
    # where they all agree (a thin tail) their agreement is not less; below _MIN_RELIABLE it fades with their size
    agreement = strength / np.maximum(rel_s, _MIN_RELIABLE)
    # -- and its precision: the standard error of the smoothed angle (half that of the doubled angle), from the
    # sections' scatter about the local fit and how many carry it; large at a thin tail's tip, where a few small
    # sections, each erring by tens of degrees, carry a fit extrapolated from one side; beyond _ANGLE_ERROR the
    # confidence falls as its inverse variance, so that such a stretch is smoothed into its neighbours, not dropped
    angle_error = np.degrees(0.5 * zerr / np.maximum(strength, 1e-12))
    precise = np.minimum(1.0, (_ANGLE_ERROR / np.maximum(angle_error, 1e-12)) ** 2)
    confidence = _smoothstep(agreement, 0.5 * min_anisotropy, 2.0 * min_anisotropy) * precise
    ds = np.gradient(s_all) if k_pts > 1 else np.ones(1)
    oriented = float(ds[strength >= _ORIENTED].sum() / max(ds.sum(), 1e-300))
    info: dict[str, Any] = {"radius": radius, "smoothing": smoothing, "anisotropy": conf_s, "strength": strength,
                            "angle_error": angle_error,
                            "confidence": confidence, "oriented": oriented, "round": False, "sign_cue": "none",
                            "scores": {}}
    if oriented < min_oriented:
        warnings.warn(
            f"the specimen's cross-sections show a consistent dorsoventral axis over only {100 * oriented:.0f} % of "
            f"its length (orientation strength >= {_ORIENTED}, about 1.3:1 sections agreeing along the curve; "
            f"{100 * min_oriented:.0f} % needed): it is taken as round (a vessel, an eel-like body), so the frames "
            "follow the minimal-rotation frames (no twist); give dorsal points or an up direction to set the roll",
            UserWarning,
            stacklevel=2,
        )
        info["round"] = True
        angles = np.zeros(k_pts)
        return (angles, info) if return_info else angles
    good = confidence > 0
    two_phi = _unwrapped_interp(s_all, np.angle(zhat), good)
    estimate = 0.5 * two_phi - 0.5 * np.pi  # v' = -sin(t) u + cos(t) v lies along the axis at angle phi from u
    # follow the estimate where it is confident, the minimal-rotation frames (a constant twist) elsewhere
    theta = _blend(s_all, estimate, confidence, smoothing)

    # -- the dorsal side: one sign for the whole specimen
    conf_sec = np.interp(s_sec, s_all, confidence)
    th_sec = np.interp(s_sec, s_all, theta)
    scores = _sign_scores(xs, ys, w, inside, dense, th_sec, area * conf_sec)
    info["scores"] = scores
    sign, used = _choose_sign(scores, cue)
    info["sign_cue"] = used
    if sign < 0:
        theta = theta + np.pi
    theta -= 2 * np.pi * np.round(theta[0] / (2 * np.pi))
    return (theta, info) if return_info else theta


def landmark_twist(
    points: np.ndarray,
    frames: np.ndarray,
    *,
    dorsal_points: Any = None,
    dorsal_direction: Sequence[float] | None = None,
    smoothing: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Twist angles set by the user instead of estimated: ``v`` through dorsal points, or along a direction.

    Parameters
    ----------
    points : ndarray, shape (K, 3)
        Curve points, physical units, head first.
    frames : ndarray, shape (K, 3, 3)
        Rows ``u, v, n`` (parallel-transport frames), orthonormal and right-handed.
    dorsal_points : array_like, shape (M, 3), optional
        Points on the specimen's dorsal side, physical units (the frame of ``points``). Each sets the twist at
        the curve point nearest to it so that ``v`` points at it; between them the twist changes linearly along
        s by the smaller turn, and it is held beyond the first and the last.
    dorsal_direction : sequence of 3 float, optional
        One direction (axis0, axis1, axis2) that ``v`` follows wherever the curve crosses it: ``v`` is its part
        in each cross-section's plane. Where the curve runs nearly along it (that part under half its length)
        the frames follow parallel transport, with a smooth blend.
    smoothing : float, optional
        For ``dorsal_direction``: the length (physical units) of the blend; default 3 % of the curve's length.

    Returns
    -------
    angles : ndarray, shape (K,)
        Radians, for :func:`apply_twist`.
    confidence : ndarray, shape (K,)
        1 where the landmarks set the twist, 0 where the frames follow parallel transport.

    Raises
    ------
    InvalidInputError
        Neither or both of ``dorsal_points`` and ``dorsal_direction``; a malformed or non-finite point or
        direction; a zero direction; a dorsal point on the curve itself.
    """
    pts = _check_points(points)
    fr = _check_frames(frames, len(pts))
    if (dorsal_points is None) == (dorsal_direction is None):
        raise InvalidInputError("give either dorsal points or a dorsal direction, not both or neither")
    s = _arclength(pts)
    if dorsal_direction is not None:
        d = np.asarray(dorsal_direction, dtype=float)
        if d.shape != (3,) or not np.isfinite(d).all() or not np.linalg.norm(d) > 0:
            raise InvalidInputError(f"the dorsal direction must be 3 finite numbers (axis0, axis1, axis2), not all 0, "
                                    f"got {dorsal_direction!r}")
        d = d / np.linalg.norm(d)
        x, y = fr[:, 0] @ d, fr[:, 1] @ d
        confidence = _smoothstep(np.hypot(x, y), 0.25, 0.5)
        if not np.any(confidence > 0):
            return np.zeros(len(pts)), confidence
        estimate = np.interp(s, s[confidence > 0], np.unwrap(np.arctan2(-x, y)[confidence > 0]))
        sm = 0.03 * float(s[-1]) if smoothing is None else float(smoothing)
        return _blend(s, estimate, confidence, max(sm, 1e-9)), confidence
    marks = np.asarray(dorsal_points, dtype=float)
    if marks.ndim != 2 or marks.shape[1] != 3 or not len(marks) or not np.isfinite(marks).all():
        raise InvalidInputError(f"dorsal points must be one or more points of 3 finite coordinates, got an array of "
                                f"shape {marks.shape}")
    _, idx = cKDTree(pts).query(marks)
    off = marks - pts[idx]
    x, y = np.einsum("ij,ij->i", off, fr[idx, 0]), np.einsum("ij,ij->i", off, fr[idx, 1])
    if np.any(np.hypot(x, y) < 1e-9):
        raise InvalidInputError("a dorsal point lies on the centreline: give points on the dorsal surface")
    order = np.argsort(s[idx], kind="stable")
    at, theta = s[idx][order], np.unwrap(np.arctan2(-x, y)[order])
    return np.interp(s, at, theta), np.ones(len(pts))


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """0 below ``lo``, 1 above ``hi``, the cubic smoothstep between (C1: no kink where a stretch turns confident)."""
    t = np.clip((np.asarray(x, dtype=float) - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _blend(s: np.ndarray, estimate: np.ndarray, confidence: np.ndarray, smoothing: float) -> np.ndarray:
    """The twist that minimises ``sum c_i (theta_i - estimate_i)^2 ds_i + (smoothing / 2)^2 sum (dtheta/ds)^2 ds``.

    Where the confidence ``c`` is 1 the twist follows the (already smoothed) estimate; where it is 0 the twist
    rate is 0 (the minimal-rotation frames) or, between two confident stretches, constant (the least roll rate
    that joins them); in between it moves smoothly from one to the other. A tridiagonal solve, O(K).
    """
    from scipy.linalg import solve_banded

    k = len(s)
    if k < 2:
        return np.asarray(estimate, dtype=float).copy()
    h = np.maximum(np.diff(s), 1e-12)
    ds = np.empty(k)
    ds[0], ds[-1] = h[0] / 2, h[-1] / 2
    ds[1:-1] = (h[:-1] + h[1:]) / 2
    data = np.asarray(confidence, dtype=float) * ds
    stiff = 0.25 * smoothing * smoothing / h  # half the estimate's own smoothing: little lag where it is followed
    diag = data.copy()
    diag[:-1] += stiff
    diag[1:] += stiff
    ab = np.zeros((3, k))
    ab[0, 1:] = -stiff
    ab[1] = diag + 1e-12 * (stiff.max() if len(stiff) else 1.0)  # a specimen with no confident point stays put
    ab[2, :-1] = -stiff
    return solve_banded((1, 1), ab, data * np.asarray(estimate, dtype=float))


# ------------------------------------------------------------------------------------------------------------------
# internals
# ------------------------------------------------------------------------------------------------------------------
def _default_radius(mask: Any, pts: np.ndarray, tree: cKDTree, sp: np.ndarray) -> float:
    """1.5 x the 99.5th percentile of the distance from mask voxels (ends excluded) to the curve."""
    vox = _mask_voxels(mask, _MAX_RADIUS_VOXELS)
    if len(vox) == 0:
        raise InvalidInputError("the mask is empty: there is no specimen to orient; check the segmentation")
    d, j = tree.query(vox * sp, workers=-1)
    keep = (j > 0) & (j < len(pts) - 1) if len(pts) > 4 else np.ones(len(d), bool)
    if keep.sum() < 8:
        keep = np.ones(len(d), bool)
    r = float(np.percentile(d[keep], 99.5))
    return 1.5 * max(r, 2.0 * float(sp.max()))


def _section_indices(s: np.ndarray, step: float) -> np.ndarray:
    """Indices of points about ``step`` apart in arclength (first and last included)."""
    if len(s) <= 2:
        return np.arange(len(s))
    n = max(2, int(round(s[-1] / step)) + 1)
    if n >= len(s):
        return np.arange(len(s))
    idx = np.unique(np.searchsorted(s, np.linspace(0.0, s[-1], n)).clip(0, len(s) - 1))
    return idx


def _disc(radius: float, vox: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Sample positions on a disc of ``radius`` (about half a voxel apart, at most _MAX_GRID across) and the
    area each one stands for."""
    n = int(min(_MAX_GRID, max(21, 2 * math.ceil(radius / (0.5 * vox)) + 1)))
    g = np.linspace(-radius, radius, n)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    keep = gx**2 + gy**2 <= radius**2 * (1 + 1e-9)
    return gx[keep], gy[keep], float(g[1] - g[0]) ** 2


def _grid_index(gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The square grid the disc samples were cut from (:func:`_disc`), as its coordinates along one side, and each
    sample's row and column on it."""
    g = np.unique(gx)
    return g, np.searchsorted(g, gx), np.searchsorted(g, gy)


def _cut_share(w: np.ndarray, ex: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Per section (rows of ``w``), the share of the kept part's outline (4-neighbour edges of ``w >= 0.5``)
    that borders excluded samples (``ex >= 0.5``) rather than the specimen's boundary."""
    g, ix, iy = _grid_index(gx, gy)
    ix, iy, n = ix + 1, iy + 1, len(g) + 2  # a margin of one sample: the disc's edge is an outline too
    kept = np.zeros((len(w), n, n), dtype=bool)
    gone = np.zeros((len(w), n, n), dtype=bool)
    kept[:, ix, iy] = w >= 0.5
    gone[:, ix, iy] = ex >= 0.5
    edge = np.zeros(len(w))
    cut = np.zeros(len(w))
    for axis in (1, 2):
        for shift in (1, -1):
            out = kept & ~np.roll(kept, shift, axis=axis)
            edge += out.sum(axis=(1, 2))
            cut += (out & np.roll(gone, shift, axis=axis)).sum(axis=(1, 2))
    return cut / np.maximum(edge, 1.0)


def _centre_part(w: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Keep, in each section, only the part of the mask connected to the centre (with its partial-volume rim).

    Other parts of the body that cross the plane (another turn of a coil, the head beside the tail) are not this
    cross-section, whatever curve point they are nearest to; far from the centre they would dominate the second
    moments. The part kept is the 8-connected component of ``w >= 0.5`` at the centre, or the one nearest it.
    """
    g, ix, iy = _grid_index(gx, gy)
    n = len(g)
    grid = np.zeros((len(w), n, n))
    grid[:, ix, iy] = w
    core = grid >= 0.5
    struct = np.zeros((3, 3, 3), dtype=bool)
    struct[1] = True  # 8-connected within a section, never across sections
    labels, count = ndimage.label(core, structure=struct)
    if count == 0:
        return w
    # per section, the label nearest the centre
    d2 = (g[:, None] ** 2 + g[None, :] ** 2)
    lab = labels.reshape(len(w), -1)
    dist = np.where(lab > 0, np.broadcast_to(d2.reshape(1, -1), lab.shape), np.inf)
    best = np.argmin(dist, axis=1)
    keep_label = lab[np.arange(len(w)), best]
    keep = labels == keep_label[:, None, None]
    keep &= (keep_label > 0)[:, None, None]
    keep = ndimage.binary_dilation(keep, structure=struct)  # the partial-volume rim around the part
    return np.where(keep[:, ix, iy], w, 0.0)


def _bbox(coords: np.ndarray, shape: Sequence[int]) -> tuple[tuple[slice, ...], np.ndarray] | None:
    """The slices of the voxels a bilinear interpolation at ``coords`` (N, 3) (index units) reads."""
    lo = np.maximum(np.floor(coords.min(axis=0)).astype(int), 0)
    hi = np.minimum(np.floor(coords.max(axis=0)).astype(int) + 2, np.asarray(shape))
    if np.any(hi <= lo):
        return None
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi)), lo


def _sample_sections(
    pts: np.ndarray,
    fr: np.ndarray,
    sec: np.ndarray,
    s_all: np.ndarray,
    tree: cKDTree,
    mask: Any,
    volume: Any,
    sp: np.ndarray,
    radius: float,
    exclude: Any = None,
    fov: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, float, np.ndarray]:
    """Sample the mask (and the volume) on a disc in each section plane (``fov``: the scan's (lo, hi) index extent,
    beyond which the samples count as cut away; default the mask's array).

    Returns ``xs, ys`` (S, P) in-plane coordinates, ``w`` (S, P) the mask occupancy in [0, 1] (0 for samples that
    belong to another part of the curve or are excluded), ``inside`` (S, P) bool ``w >= 0.5``, ``dense`` (S, P)
    the volume intensities at the samples inside (NaN elsewhere) or None without a volume, the area of one
    sample, and ``cut`` (S,) the share of each section's outline that borders excluded samples.
    """
    gx, gy, cell = _disc(radius, float(sp.min()))
    u, v = fr[sec, 0], fr[sec, 1]
    phys = pts[sec, None, :] + gx[None, :, None] * u[:, None, :] + gy[None, :, None] * v[:, None, :]
    idx = phys / sp
    shape = tuple(int(n) for n in mask.shape)
    n_sec, n_smp = len(sec), len(gx)
    xs = np.broadcast_to(gx, (n_sec, n_smp))
    ys = np.broadcast_to(gy, (n_sec, n_smp))
    w = np.zeros((n_sec, n_smp))
    flat = idx.reshape(-1, 3)
    box = _bbox(flat, shape)
    values = None  # the volume over the same box, read once
    ex = None  # the excluded voxels at the samples
    if box is not None:
        slices, lo = box
        block = _as_uint8(mask[slices])
        if volume is not None:
            values = _real_block(volume[slices])
            block = _partial_volume(block, values)
        # grid-constant: the mask is 0 beyond its array and interpolated up to it (a tight crop keeps its edge rims)
        w = ndimage.map_coordinates(block, (flat - lo).T, order=1, mode="grid-constant", cval=0.0,
                                    output=np.float32)
        w = w.astype(float).reshape(n_sec, n_smp)
        if exclude is not None:
            ex = ndimage.map_coordinates(_as_uint8(exclude[slices]), (flat - lo).T, order=1, mode="grid-constant",
                                         cval=0.0, output=np.float32).astype(float).reshape(n_sec, n_smp)
            w *= 1.0 - ex
    # A sample belongs to this section only when this section's curve point is (about) its nearest: within the
    # radius of curvature every point of the plane is, while a part of the body that curls back through the plane
    # (a tight coil, a fold of the tail), even a short way along, is nearer its own curve points.
    hit = np.flatnonzero(w.reshape(-1) > 0)
    if len(hit):
        _, j = tree.query(flat[hit] * sp, workers=-1)
        step = float(np.median(np.diff(s_all))) if len(s_all) > 1 else 0.0
        own = max(2.0 * float(sp.max()), 2.0 * step)
        far = np.abs(s_all[j] - np.repeat(s_all[sec], n_smp)[hit]) > min(own, radius)
        w.reshape(-1)[hit[far]] = 0.0
    w = _centre_part(w, gx, gy)
    # beyond the scan's faces the mask is not known: an outline along a face is where the scan cut the specimen
    # (a vessel running beside the face is a half-disc there), not its boundary; it counts as cut, like a branch's
    if fov is None:
        fov = np.array([[-0.5] * 3, [n - 0.5 for n in shape]])
    beyond = ((flat < fov[0]) | (flat > fov[1])).any(axis=1).reshape(n_sec, n_smp)
    if beyond.any():
        ex = beyond.astype(float) if ex is None else np.maximum(ex, beyond)
    cut = _cut_share(w, ex, gx, gy) if ex is not None else np.zeros(n_sec)
    inside = w >= 0.5
    dense = None
    if values is not None and inside.any():
        sel = flat[inside.reshape(-1)]
        dense = np.full(n_sec * n_smp, np.nan)
        dense[np.flatnonzero(inside.reshape(-1))] = ndimage.map_coordinates(
            values, (sel - lo).T, order=1, mode="nearest", output=np.float64)
        dense = dense.reshape(n_sec, n_smp)
    return xs, ys, w, inside, dense, cell, cut


def _real_block(block: Any) -> np.ndarray:
    """A block of the volume as a numpy array of real numbers (a bool block viewed as uint8)."""
    arr = np.asarray(block)
    if arr.dtype == bool:
        return arr.view(np.uint8)
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise InvalidInputError(f"volume must hold real numbers, got dtype {arr.dtype}")
    return arr


def _partial_volume(block: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The mask's occupancy refined by the intensities in its one-voxel boundary band, shape of ``block``.

    A body a few voxels across is, as a binary mask, a staircase whose orientation is pulled toward the grid's
    axes (on thin fish tails the sections' angles were biased by 5-9 degrees over a fifth of the length). The
    intensities of the voxels on its boundary hold the part of each voxel the body fills: there the occupancy is
    ``(I - background) / (body - background)`` clipped to [0, 1], the two levels the medians of the mask's
    interior (beneath the band) and of the shell just beyond the band. Beneath the band the occupancy stays 1 (a
    swim bladder is no hole in the body), beyond it 0 (another bright body next to it is not this one). Where
    the mask does not stand out from its shell (the levels closer than twice the shell's robust spread: a hand
    mask on uniform tissue), the binary mask is returned unchanged.
    """
    inside = block.astype(bool)
    near = ndimage.binary_dilation(inside)
    core = ndimage.binary_erosion(inside)
    shell = ndimage.binary_dilation(near) & ~near
    if shell.sum() < 8 or inside.sum() < 8:
        return block
    body = float(np.median(values[core] if core.sum() >= 8 else values[inside]))
    out = values[shell].astype(np.float64)
    background = float(np.median(out))
    spread = 1.4826 * float(np.median(np.abs(out - background)))
    if not abs(body - background) > 2.0 * spread:
        return block
    band = near & ~core
    occ = block.astype(np.float32)
    occ[band] = np.clip((values[band].astype(np.float32) - background) / (body - background), 0.0, 1.0)
    return occ


def _min_eig(cxx: np.ndarray, cyy: np.ndarray, cxy: np.ndarray) -> np.ndarray:
    return 0.5 * (cxx + cyy) - np.hypot(0.5 * (cxx - cyy), cxy)


def _local_linear(
    s_in: np.ndarray, z: np.ndarray, c: np.ndarray, s_out: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussian-weighted local linear fit of ``z(s_in)`` evaluated at ``s_out``, the local mean of ``c``
    (shape (len(s_in),), or (m, len(s_in)) for m quantities averaged with the same weights), and the standard error
    of the fit's value at each ``s_out`` (the same units as ``z``).

    The fit's value is ``a = sum_i l_i z_i`` with the local linear (equivalent kernel) weights ``l_i``; its standard
    error is ``sqrt(sum_i l_i^2 |r_i|^2)`` with ``r_i`` the residual of ``z_i`` about the local line, scaled by
    ``n / (n - 2)`` for the two fitted coefficients (``n`` the window's effective number of samples). It is large
    where few samples carry the fit or where they scatter, and at the ends, where the line is extrapolated from one
    side."""
    c = np.asarray(c, dtype=float)
    out_z = np.empty(len(s_out), dtype=complex)
    out_e = np.empty(len(s_out))
    out_c = np.empty(c.shape[:-1] + (len(s_out),))
    block = max(1, 2_000_000 // max(1, len(s_in)))
    for b0 in range(0, len(s_out), block):
        so = s_out[b0:b0 + block]
        d = (s_in[None, :] - so[:, None]) / sigma
        g = np.exp(-0.5 * d * d)
        s0 = g.sum(axis=1)
        s1 = (g * d).sum(axis=1)
        s2 = (g * d * d).sum(axis=1)
        det = s0 * s2 - s1 * s1
        lin = det > 1e-9 * np.maximum(s0 * s2, 1e-300)
        safe = np.where(lin, det, 1.0)[:, None]
        # equivalent kernels of the intercept and of the slope (the window's mean where no line is determined)
        lw = np.where(lin[:, None], g * (s2[:, None] - s1[:, None] * d) / safe, g / np.maximum(s0, 1e-300)[:, None])
        mw = np.where(lin[:, None], g * (s0[:, None] * d - s1[:, None]) / safe, 0.0)
        a = lw @ z
        b = mw @ z
        r2 = np.abs(z[None, :] - a[:, None] - b[:, None] * d) ** 2
        n_eff = s0 * s0 / np.maximum((g * g).sum(axis=1), 1e-300)
        out_z[b0:b0 + block] = a
        out_e[b0:b0 + block] = np.sqrt((lw * lw * r2).sum(axis=1) * n_eff / np.maximum(n_eff - 2.0, 1.0))
        out_c[..., b0:b0 + block] = (c @ g.T) / np.maximum(s0, 1e-300)
    return out_z, out_c, out_e


def _unwrapped_interp(s: np.ndarray, angle: np.ndarray, good: np.ndarray) -> np.ndarray:
    """Unwrap ``angle`` (period 2 pi) over the ``good`` points and interpolate the others along ``s``."""
    gi = np.flatnonzero(good)
    unwrapped = np.unwrap(angle[gi])
    return np.interp(s, s[gi], unwrapped)


def _sign_scores(
    xs: np.ndarray,
    ys: np.ndarray,
    w: np.ndarray,
    inside: np.ndarray,
    dense: np.ndarray | None,
    theta: np.ndarray,
    weight: np.ndarray,
) -> dict[str, float]:
    """Scores (positive: the current ``v'`` is dorsal) of the shape and the density cues."""
    # coordinate along v' = -sin(t) u + cos(t) v
    yv = -np.sin(theta)[:, None] * xs + np.cos(theta)[:, None] * ys
    m0 = w.sum(axis=1)
    safe = np.where(m0 > 0, m0, 1.0)
    mu = (w * yv).sum(axis=1) / safe
    dy = yv - mu[:, None]
    var = (w * dy**2).sum(axis=1) / safe
    m3 = (w * dy**3).sum(axis=1) / safe
    sd = np.sqrt(np.maximum(var, 0.0))
    wt = np.where(m0 > 0, weight, 0.0)
    scores: dict[str, float] = {}
    den = float((wt * sd**3).sum())
    scores["shape"] = float((wt * m3).sum() / den) if den > 0 else 0.0
    if dense is not None:
        vals = np.where(inside & (wt > 0)[:, None], dense, np.nan)
        count = np.sum(np.isfinite(vals), axis=1)
        has = count >= 8
        vals = vals[has]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows are excluded by ``has`` already
            med = np.nanmedian(vals, axis=1)
            mad = 1.4826 * np.nanmedian(np.abs(vals - med[:, None]), axis=1)
        exc = np.nan_to_num(np.clip(vals - (med + 3.0 * mad)[:, None], 0.0, None))
        tot_e = exc.sum(axis=1)
        use = (tot_e > 0) & (sd[has] > 0)
        offs = ((exc * yv[has]).sum(axis=1) / np.where(use, tot_e, 1.0) - mu[has]) / np.where(use, sd[has], 1.0)
        wd = np.where(use, wt[has], 0.0)
        tot = float(wd.sum())
        scores["density"] = float((wd * offs).sum() / tot) if tot > 0 else 0.0
    return scores


_CLEAR = {"density": 0.1, "shape": 0.05}


def _choose_sign(scores: dict[str, float], cue: str) -> tuple[int, str]:
    """+1 to keep ``v'``, -1 to flip it, and the cue used."""
    dens, shape = scores.get("density"), scores["shape"]
    if cue == "density":
        if abs(dens) < _CLEAR["density"]:
            _warn_unclear(scores)
        return (1 if dens >= 0 else -1), "density"
    if cue == "shape":
        if abs(shape) < _CLEAR["shape"]:
            _warn_unclear(scores)
        return (1 if shape >= 0 else -1), "shape"
    if dens is not None and abs(dens) >= _CLEAR["density"]:
        if abs(shape) >= _CLEAR["shape"] and np.sign(shape) != np.sign(dens):
            warnings.warn(
                f"the specimen's dense material says its up side is one way (score {dens:+.2f}) and the shape of its "
                f"cross-sections the other way (score {shape:+.2f}); following the density; check that the side "
                "you expect up (a fish's dorsal side) is up in the straightened volume and twist by pi if not",
                UserWarning,
                stacklevel=3,
            )
        return (1 if dens > 0 else -1), "density"
    if abs(shape) >= _CLEAR["shape"]:
        return (1 if shape > 0 else -1), "shape"
    _warn_unclear(scores)
    best = dens if dens is not None and abs(dens) >= abs(shape) else shape
    return (1 if best >= 0 else -1), "none"


def _warn_unclear(scores: dict[str, float]) -> None:
    detail = ", ".join(f"{k} {v:+.2f} (clear from {_CLEAR[k]})" for k, v in scores.items())
    warnings.warn(
        f"the specimen's up side could not be told from its down side (cue scores: {detail}): "
        "the twist aligns v with the cross-sections' long axis but v may point down (for a fish: ventral); check "
        "the straightened volume and twist by pi if it is upside down",
        UserWarning,
        stacklevel=4,
    )
