"""From a mask and two clicks to a :class:`~napari_unwind.deformation.Deformation` (docs/design.md section 4)."""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np
from scipy import ndimage as ndi

from .._morphology import depth_map
from ..deformation import Deformation, Keyframe, parallel_transport_frames
from ..errors import InvalidInputError
from ..io._volume import Volume, check_spacing, normalise_unit, unit_label
from ..progress import Progress, ProgressGenerator, checkpoint, run
from ..session import Endpoints
from ._curve import arclength, regularise_ends, resample_curve, select_keyframes, smooth_curve
from ._foldfree import coverage, format_lost, held_points, max_tilt, unfold
from ._harmonic import (
    decimate_surface,
    harmonic_field,
    lattice_tet_mesh,
    level_set_centroids,
    surface_mesh,
    tet_mesh,
)

__all__ = ["estimate_deformation", "estimate_deformation_iter", "SkeletonResult", "WorkingMask", "working_mask"]

_STRUCT26 = np.ones((3, 3, 3), dtype=bool)
_APART_SAID = 0.01  # separate parts off the path holding this share of the mask are said (the coverage goal's rest)
_MAX_FILL = 0.9  # of the scan: a mask filling more is refused (a body fills at most pi / 4 of its own box; inverted?)


@dataclass(frozen=True)
class SkeletonResult:
    """Everything :func:`estimate_deformation_iter` found, besides the deformation itself.

    Attributes
    ----------
    deformation : Deformation
        The keyframed deformation (physical units, the scan's spacing and origin).
    endpoints : Endpoints
        The endpoints used, in full-resolution voxels (snapped into the mask, or suggested).
    suggested : bool
        The head and tail were suggested (none were given).
    curve : ndarray, shape (K, 3)
        The dense centreline (smoothed, resampled), full-resolution voxel coordinates.
    frames : ndarray, shape (K, 3, 3)
        Its frames (rows u, v, n; twist applied when estimated).
    twist : ndarray, shape (K,)
        Twist (radians) of ``frames`` relative to parallel transport (zeros without twist estimation).
    context : float or None
        With ``context`` asked: the least distance (physical) any cage side lies beyond the mask's own sections.
    twist_confidence : ndarray, shape (K,)
        Where the twist was estimated: 1 where the cross-sections' orientation was followed, 0 where the frames
        follow parallel transport (round stretches, the tips, a round specimen, no estimation), a smooth blend
        between. Empty when unknown.
    keyframe_indices : ndarray of int
        Indices into ``curve`` of the keyframes.
    factor : int
        Box-averaging factor from the mask to the working resolution.
    mesh : dict
        Sizes of the meshes per part: triangles, vertices, tets.
    timings : dict of str to float
        Seconds spent per stage.
    warnings : tuple of str
        Handled-but-suspicious conditions (also issued as UserWarning).
    min_jacobian : float
        Smallest Jacobian determinant of the deformation over its cages (dense in s): > 0 means no fold.
    max_tilt : float
        Largest angle (degrees) between a cross-section's normal and the curve.
    coverage : float
        Fraction of the mask's voxels (at the working resolution) inside the cage where the map does not fold.
    lost : tuple of (s_start, s_end, fraction)
        Arclength intervals (physical units) whose mask voxels are left out of the cage, with the fraction of the
        mask each loses.
    folded : float
        Fraction of the mask's voxels (working resolution) where the map folds: 0 when every fold lies in empty
        corners of the cage.
    touching : tuple of str
        Each a reason the result is partial, with what to do, as the status gives it: where the mask touches
        itself between the ends (a hairpin or coil whose sides touch): the path crosses there and the loop of body
        it skips is left out, or the stretch it skips between two such places stays beside the path, not
        straightened; or two sides of the body lie side by side along the path, one of them not followed; or a
        part cut off that may be either a branch or the body running into itself (where the path turns sharply at
        its junction, or next to an end).
    left_out : float
        Fraction of the whole mask that the branches and loops cut off leave outside the straight volume (0 when
        nothing was cut); ``coverage`` is of the mask between the ends.
    branches : tuple of str
        The other branches cut off at a junction between the ends (length, share left out, where it joins). With
        suggested ends the result is partial: the path between them is one guess among the mask's branches.
    apart : float
        Fraction of the mask (between the ends) in separate parts that the path does not run through and that the
        straight volume leaves out (another specimen in the mask, a piece cut off by the scan's face); part of the
        ``1 - coverage`` that no cage would hold.
    bend : float
        Fraction of the mask (between the ends) left out on the inside of bends tighter than the body is thick,
        where the fold-free construction shrank the cage to the tissue or into it: part of ``1 - coverage`` that a
        larger cage does not give back (0 when the cage was given).
    """

    deformation: Deformation
    endpoints: Endpoints
    suggested: bool
    curve: np.ndarray
    frames: np.ndarray
    twist: np.ndarray
    keyframe_indices: np.ndarray
    factor: int
    mesh: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    min_jacobian: float = float("nan")
    max_tilt: float = float("nan")
    coverage: float = float("nan")
    lost: tuple[tuple[float, float, float], ...] = ()
    folded: float = 0.0
    twist_confidence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    twist_source: str = "none"
    context: float | None = None
    touching: tuple[str, ...] = ()
    left_out: float = 0.0
    branches: tuple[str, ...] = ()
    apart: float = 0.0
    bend: float = 0.0

    def twist_report(self) -> str:
        """One line: the twist's range, what set it and over how much of the length."""
        deg = np.degrees(np.asarray(self.twist, dtype=float))
        conf = np.asarray(self.twist_confidence, dtype=float)
        if self.twist_source == "none" or not len(deg) or not np.any(conf > 0):
            return "twist: none (frames by parallel transport)"
        s = arclength(self.curve * np.asarray(self.deformation.spacing))
        ds = np.gradient(s) if len(s) > 1 else np.ones(1)
        share = float((conf * ds).sum() / max(ds.sum(), 1e-300))
        how = "set by the dorsal landmarks" if self.twist_source == "landmarks" else "estimated"
        return (f"twist: {deg.min():.1f} to {deg.max():.1f} degrees along the body (relative to parallel transport), "
                f"{how} over {100 * share:.0f} % of the length (elsewhere the frames follow parallel transport)")

    def twist_profile(self) -> Any:
        """The :class:`~napari_unwind.session.TwistProfile` for the session: the twist (degrees) and its
        confidence at up to ``TWIST_STATIONS`` stations evenly spread along the curve."""
        from ..session import TWIST_STATIONS, TwistProfile

        s = arclength(self.curve * np.asarray(self.deformation.spacing))
        k = len(s)
        conf = np.asarray(self.twist_confidence, dtype=float)
        conf = conf if len(conf) == k else np.zeros(k)
        idx = np.unique(np.linspace(0, k - 1, min(k, TWIST_STATIONS)).round().astype(int))
        return TwistProfile(s=tuple(np.round(s[idx], 6)), angle=tuple(np.round(np.degrees(self.twist[idx]), 4)),
                            confidence=tuple(np.round(np.clip(conf[idx], 0, 1), 4)), source=self.twist_source)

    def report(self) -> str:
        """One line: minimum Jacobian, largest tilt, coverage and where mask is lost."""
        from ._foldfree import format_lost

        unit = unit_label(self.deformation.unit)
        of = "of the mask" if not self.left_out else \
            f"of the mask between the ends ({100 * self.left_out:.2g} % of the whole cut off: see the warnings)"
        return (f"cage: min Jacobian {self.min_jacobian:.3g} ({'no fold' if self.min_jacobian > 0 else 'FOLDS'}), "
                f"max tilt {self.max_tilt:.3g} deg, coverage {100 * self.coverage:.2f} % {of}, lost: "
                f"{format_lost(self.lost, unit)}")


@dataclass(frozen=True)
class WorkingMask:
    """The mask cropped to its bounding box and box-averaged to the working resolution.

    Attributes
    ----------
    occupancy : ndarray of float32
        Fraction of mask voxels in each working voxel.
    binary : ndarray of bool
        ``occupancy >= 0.5``.
    volume : ndarray of float32 or None
        The intensities box-averaged the same way (when a volume was given).
    factor : int
        Box size.
    start, stop : tuple of 3 int
        Full-resolution bounding box of the mask (``stop`` exclusive).
    spacing : tuple of 3 float
        Full-resolution spacing; the working spacing is ``factor * spacing``.
    shape : tuple of 3 int
        Full-resolution shape of the mask.
    """

    occupancy: np.ndarray
    binary: np.ndarray
    volume: np.ndarray | None
    factor: int
    start: tuple[int, int, int]
    stop: tuple[int, int, int]
    spacing: tuple[float, float, float]
    shape: tuple[int, int, int]

    @property
    def working_spacing(self) -> tuple[float, float, float]:
        return tuple(self.factor * s for s in self.spacing)  # type: ignore[return-value]

    @property
    def offset(self) -> np.ndarray:
        """Physical position (origin 0) of working voxel (0, 0, 0)."""
        return (np.asarray(self.start, float) + (self.factor - 1) / 2.0) * np.asarray(self.spacing)

    def to_working(self, voxels: np.ndarray) -> np.ndarray:
        """Full-resolution voxel coordinates -> working voxel coordinates."""
        return (np.asarray(voxels, float) - np.asarray(self.start) - (self.factor - 1) / 2.0) / self.factor

    def from_working(self, working: np.ndarray) -> np.ndarray:
        """Working voxel coordinates -> full-resolution voxel coordinates."""
        return np.asarray(working, float) * self.factor + np.asarray(self.start) + (self.factor - 1) / 2.0


def _as_array(data: Any, what: str) -> Any:
    """numpy or dask array of 3 dimensions (not copied)."""
    import dask.array as da

    if isinstance(data, Volume):
        data = data.data
    if not isinstance(data, (np.ndarray, da.Array)):
        try:
            data = np.asarray(data) if not hasattr(data, "chunks") else da.from_array(data)
        except Exception as exc:  # noqa: BLE001 - report what we got
            raise InvalidInputError(f"the {what} must be an array, got {type(data).__name__}") from exc
    if data.ndim != 3:
        raise InvalidInputError(f"the {what} must be 3-dimensional (axis0, axis1, axis2), got shape {data.shape}")
    if 0 in data.shape:
        raise InvalidInputError(f"the {what} has an empty dimension: shape {data.shape}")
    return data


def _box_average(block: Any, factor: int) -> np.ndarray:
    """Mean over factor^3 boxes (zero padded at the far sides), as float32 numpy."""
    import dask.array as da

    if factor == 1:
        out = block.astype(np.float32)
        return np.asarray(out.compute() if isinstance(out, da.Array) else out)
    pad = [(0, (-n) % factor) for n in block.shape]
    if isinstance(block, da.Array):
        b = da.pad(block.astype(np.float32), pad)
        b = b.rechunk(tuple(max(factor, (c // factor) * factor) for c in (64, 64, 64)))
        return np.asarray(da.coarsen(np.mean, b, {0: factor, 1: factor, 2: factor}).compute(), dtype=np.float32)
    b = np.pad(np.asarray(block, dtype=np.float32), pad)
    s = b.shape
    return b.reshape(s[0] // factor, factor, s[1] // factor, factor, s[2] // factor, factor).mean(axis=(1, 3, 5))


def working_mask(
    mask: Any, *, spacing: Sequence[float] | float, volume: Any = None, max_side: int = 128, factor: int | None = None,
) -> WorkingMask:
    """Crop a mask to its bounding box and box-average it so its longest side is at most ``max_side``
    (or by exactly ``factor``, when given).

    The mask may be numpy or dask (a full-resolution scan never needs to fit in memory: only the crop is
    averaged, chunk by chunk). ``volume``, when given, is averaged over the same boxes.
    """
    import dask.array as da

    m = _as_array(mask, "mask")
    sp = check_spacing(spacing)
    if max_side < 8:
        raise InvalidInputError(f"max_side must be at least 8 voxels, got {max_side}")
    nz = m != 0
    if isinstance(nz, da.Array):
        *axes, count = da.compute(*(nz.any(axis=tuple(j for j in range(3) if j != i)) for i in range(3)), nz.sum())
    else:
        axes = [nz.any(axis=tuple(j for j in range(3) if j != i)) for i in range(3)]
        count = np.count_nonzero(nz)
    if not all(a.any() for a in axes):
        raise InvalidInputError("the mask is empty (no nonzero voxel); select the specimen first "
                                "(unwind select, or the plugin's pick) and pass its mask")
    fill = int(count) / math.prod(m.shape)
    if fill > _MAX_FILL:
        raise InvalidInputError(
            f"the mask's non-zero voxels fill {100 * fill:.3g} % of the scan: that is no specimen's mask (a body fills "
            "at most about 79 % of its own box); is it inverted (the background non-zero)? give a mask whose "
            "non-zero voxels are the specimen alone")
    lo = tuple(int(np.argmax(a)) for a in axes)
    hi = tuple(int(len(a) - np.argmax(a[::-1])) for a in axes)
    if factor is None:
        factor = max(1, math.ceil(max(h - low for low, h in zip(lo, hi, strict=True)) / max_side))
    elif not (isinstance(factor, (int, np.integer)) and factor >= 1):
        raise InvalidInputError(f"factor must be an integer >= 1, got {factor!r}")
    crop = tuple(slice(low, h) for low, h in zip(lo, hi, strict=True))
    occ = _box_average(nz[crop], factor)
    vol = None
    if volume is not None:
        v = _as_array(volume, "volume")
        if tuple(v.shape) != tuple(m.shape):
            raise InvalidInputError(f"the volume's shape {tuple(v.shape)} differs from the mask's {tuple(m.shape)}; "
                                    "pass the scan the mask was made from (same resolution level)")
        vol = _box_average(v[crop], factor)
    return WorkingMask(occ, occ >= 0.5, vol, factor, lo, hi, sp, tuple(int(n) for n in m.shape))


def _border_sides(wm: WorkingMask) -> list[str]:
    sides = []
    for ax in range(3):
        if wm.start[ax] == 0:
            sides.append(f"axis{ax} start")
        if wm.stop[ax] >= wm.shape[ax]:
            sides.append(f"axis{ax} end")
    return sides


_MIN_ACROSS = 6  # working voxels across the body's thickest section, at least
_MAX_WORKING_VOXELS = 256 ** 3  # the working mask's bounding box, at most (memory and meshing time)


_LINE_ACROSS = 3.5  # full-resolution voxels: a mask thinner than this at its thickest is a line, not a body
_LINE_TUBE = 2.0  # a line mask is solved as the tube of this many (coarsest) voxels around it


def _across(wm: WorkingMask) -> float:
    """The thickest section of the working mask, in full-resolution voxels (twice the largest inscribed radius)."""
    if not wm.binary.any():
        return 0.0
    return 2.0 * float(depth_map(wm.binary, (1.0, 1.0, 1.0)).max()) * wm.factor


def _slender_working_mask(mask: Any, sp: np.ndarray, volume: Any, max_side: int) -> WorkingMask:
    """The working mask at ``max_side``, made finer where the body is slender (an eel keeps >= 6 working voxels
    across, however long it is: :func:`_thin_factor`)."""
    wm = working_mask(mask, spacing=tuple(sp), volume=volume, max_side=max_side)
    thin = _thin_factor(wm)
    return working_mask(mask, spacing=tuple(sp), volume=volume, factor=thin) if thin < wm.factor else wm


def _thin_factor(wm: WorkingMask) -> int:
    """The working factor that keeps :data:`_MIN_ACROSS` working voxels across the body's widest section.

    The widest section is twice the largest inscribed radius, measured on the occupancy (a slender body
    averaged down to less than a voxel still shows there); the factor never drops so far that the working box
    exceeds :data:`_MAX_WORKING_VOXELS`.
    """
    if wm.factor == 1:
        return 1
    occ = np.pad(wm.occupancy >= 0.25, 1)
    across = 2.0 * float(ndi.distance_transform_edt(occ).max()) * wm.factor  # full-resolution voxels
    need = max(1, int(math.floor(across / _MIN_ACROSS)))
    box = float(np.prod(np.subtract(wm.stop, wm.start), dtype=float))
    floor_ = max(1, math.ceil((box / _MAX_WORKING_VOXELS) ** (1 / 3)))
    return int(min(wm.factor, max(need, floor_)))


def _cut_face_end(mask: Any, end: np.ndarray, wm: WorkingMask, spacing: np.ndarray) -> np.ndarray:
    """A suggested end moved to the centre of the cut face it lies at, if the mask runs off the scan there.

    The longest geodesic ends on the rim of a cut face (its farthest corner), not at its centre: the curve
    then hooks sideways. For each face of the scan that the mask touches, the mask's section on that face is
    labelled; when the end lies within that section's radius (plus 2 working voxels) of its centroid, the end
    becomes the centroid. Full-resolution voxels in and out.
    """
    import dask.array as da

    data = _as_array(mask, "mask")
    best, best_d = end, np.inf
    for ax in range(3):
        for at in (0, wm.shape[ax] - 1):
            if (at == 0 and wm.start[ax] != 0) or (at > 0 and wm.stop[ax] < wm.shape[ax]):
                continue
            face = data[tuple(at if a == ax else slice(None) for a in range(3))] != 0
            face = np.asarray(face.compute() if isinstance(face, da.Array) else face)
            labels, n = ndi.label(face)
            if n == 0:
                continue
            other = [a for a in range(3) if a != ax]
            for lab in range(1, n + 1):
                pts = np.argwhere(labels == lab).astype(float)
                centre = np.empty(3)
                centre[ax] = at
                centre[other] = pts.mean(axis=0)
                radius = math.sqrt(len(pts) * float(np.prod(spacing[other])) / math.pi)
                dist = float(np.linalg.norm((centre - end) * spacing))
                if dist <= radius + 2 * wm.factor * float(spacing.max()) and dist < best_d:
                    best, best_d = centre, dist
    return best


def _describe_part(labels: np.ndarray, lab: int, wm: WorkingMask) -> str:
    idx = np.argwhere(labels == lab)
    lo = wm.from_working(idx.min(axis=0)).round().astype(int).tolist()
    hi = wm.from_working(idx.max(axis=0)).round().astype(int).tolist()
    return f"part {lab} ({len(idx) * wm.factor ** 3} voxels, from {lo} to {hi})"


def _snap(point_vox: np.ndarray, wm: WorkingMask, tolerance: float, what: str, unit: str | None) -> np.ndarray:
    """A full-resolution voxel point moved into the working mask (if within ``tolerance`` physical)."""
    p = np.asarray(point_vox, dtype=float)
    shape = np.asarray(wm.shape)
    if (p < -0.5).any() or (p > shape - 0.5).any():
        raise InvalidInputError(f"the {what} {p.tolist()} lies outside the volume of shape {tuple(wm.shape)}; "
                                "give it in array index order (axis0, axis1, axis2), full-resolution voxels")
    w = wm.to_working(p)
    wi = np.clip(np.round(w).astype(int), 0, np.asarray(wm.binary.shape) - 1)
    if wm.binary[tuple(wi)] and np.all(np.abs(w - wi) <= 0.5):
        return p
    cand = np.argwhere(wm.binary)
    wsp = np.asarray(wm.working_spacing)
    d = np.linalg.norm((cand - w) * wsp, axis=1)
    k = int(np.argmin(d))
    if d[k] > tolerance:
        u = unit_label(unit)
        vox = min(wm.spacing)
        raise InvalidInputError(
            f"the {what} {np.round(p, 2).tolist()} is {d[k]:.3g} {u} ({d[k] / vox:.3g} voxels) from the mask, more "
            f"than the snapping tolerance of {tolerance / vox:.3g} voxels; click inside the specimen, or raise the "
            "tolerance (snap_tolerance, --snap-tolerance)")
    return wm.from_working(cand[k])


def _stage(name: str, timings: dict[str, float], t0: float) -> float:
    t = time.perf_counter()
    timings[name] = timings.get(name, 0.0) + (t - t0)
    return t


def _normalise_endpoints(endpoints: Any) -> Endpoints | None:
    if endpoints is None or isinstance(endpoints, Endpoints):
        return endpoints
    if isinstance(endpoints, dict):
        return Endpoints.from_dict(endpoints)
    try:
        head, tail = endpoints
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"endpoints must be an Endpoints, a (head, tail) pair or None, got {endpoints!r}"
                                ) from exc
    return Endpoints(head=tuple(head), tail=tuple(tail))


def _part_curve(
    wm: WorkingMask, labels: np.ndarray, head_w: np.ndarray, tail_w: np.ndarray, *, what: str, chained: bool,
    n_levels: int, level_spacing: str, timings: dict[str, float], mesh_info: list[dict[str, int]],
    note: Any, max_triangles: int | None, mesher: dict[str, Any], tet_mesher: str, lattice_nodes: int,
) -> ProgressGenerator[np.ndarray]:
    """Centroid curve (physical, origin 0) of the part of the working mask holding ``head_w`` and ``tail_w``."""
    t = time.perf_counter()
    wsp = np.asarray(wm.working_spacing)
    hi_w, ti_w = (tuple(np.clip(np.round(x).astype(int), 0, np.asarray(labels.shape) - 1)) for x in (head_w, tail_w))
    lh, lt = int(labels[hi_w]), int(labels[ti_w])
    occupancy = None
    if lh == lt and lh > 0:
        part = labels == lh
        occupancy = np.where(ndi.binary_dilation(part, _STRUCT26), wm.occupancy, 0.0)
    else:
        # the paper's connectivity step: dilate (up to 3 working voxels) until both ends are in one component
        for r in (1, 2, 3):
            ball = np.linalg.norm(np.mgrid[-r:r + 1, -r:r + 1, -r:r + 1], axis=0) <= r + 1e-9
            dil = ndi.binary_dilation(wm.binary, ball)
            lab2, _ = ndi.label(dil, _STRUCT26)
            if lab2[hi_w] > 0 and lab2[hi_w] == lab2[ti_w]:
                occupancy = (lab2 == lab2[hi_w]).astype(np.float32)
                note(f"the {what}'s mask is in pieces; dilation by {r} working voxel(s) joined them (the paper's "
                     "connectivity step)")
                break
        if occupancy is None:
            parts = ", ".join(_describe_part(labels, lab, wm) for lab in sorted({lh, lt}) if lab > 0)
            hint = ("give endpoints for every part, in order from head to tail (Endpoints.chain, or --chain "
                    "START END per part on the command line)") if not chained else "check the chain's points"
            raise InvalidInputError(
                f"the {what} start and end lie in different parts of the mask that dilation by 3 working voxels "
                f"does not join: start in part {lh}, end in part {lt} ({parts}); {hint}")
    if tet_mesher == "lattice":
        yield Progress("tet mesh", 0, 1, what)
        cell = max(1.0, (float(np.count_nonzero(occupancy >= 0.5)) / lattice_nodes) ** (1 / 3))
        mesh = lattice_tet_mesh(occupancy, spacing=tuple(wsp), offset=tuple(wm.offset), cell=cell)
        t = _stage("tet mesh", timings, t)
        mesh_info.append({"mesher": "lattice", "cell": round(cell, 6), "triangles": int(len(mesh.surface[1])),
                          "vertices": int(len(mesh.vertices)), "tets": int(len(mesh.tets))})
    else:  # the paper's: marching cubes, decimation, fTetWild (its mesh varies from run to run)
        yield Progress("surface", 0, 1, what)
        verts, faces = surface_mesh(occupancy, spacing=tuple(wsp), offset=tuple(wm.offset))
        n_mc = len(faces)
        if max_triangles:
            verts, faces = decimate_surface(verts, faces, max_faces=max_triangles)
        t = _stage("surface", timings, t)
        yield Progress("tet mesh", 0, 1, f"{what}: {len(faces)} triangles")
        mesh = tet_mesh(verts, faces, **mesher)
        t = _stage("tet mesh", timings, t)
        mesh_info.append({"mesher": "ftetwild", "marching_cubes_triangles": int(n_mc), "triangles": int(len(faces)),
                          "vertices": int(len(mesh.vertices)), "tets": int(len(mesh.tets))})
    yield Progress("harmonic", 0, 1, f"{what}: {len(mesh.vertices)} vertices, {len(mesh.tets)} tets")
    head = wm.from_working(head_w) * np.asarray(wm.spacing)
    tail = wm.from_working(tail_w) * np.asarray(wm.spacing)
    u = harmonic_field(mesh, head, tail, anchor_radius=1.5 * float(wsp.min()))
    t = _stage("harmonic", timings, t)
    yield Progress("level sets", 0, 2, what)
    levels = (np.arange(n_levels) + 0.5) / n_levels
    cents, _ = level_set_centroids(mesh, u, levels)
    ok = np.isfinite(cents[:, 0])
    if level_spacing == "arclength" and ok.sum() >= 2:
        # second pass: isovalues placed evenly along the first curve, so the level sets are evenly spaced
        # along the body instead of crowding at the ends, where a point-like Dirichlet end makes u change fast
        pts = np.vstack([head, cents[ok], tail])
        uu = np.concatenate([[0.0], levels[ok], [1.0]])
        cum = arclength(pts)
        levels = np.interp((np.arange(n_levels) + 0.5) / n_levels * cum[-1], cum, uu)
        yield Progress("level sets", 1, 2, what)
        cents, _ = level_set_centroids(mesh, u, levels)
        ok = np.isfinite(cents[:, 0])
    _stage("level sets", timings, t)
    yield Progress("level sets", 2, 2, what)
    return np.vstack([head, cents[ok], tail])


_TISSUE_JACOBIAN = 0.25  # of min_jacobian: the tissue's own sides are shrunk only where J would fall below this


def _fold_free_cages(wm: WorkingMask, curve: np.ndarray, frames: np.ndarray, idx: np.ndarray, eps: float,
                     margin: float, context: float = 0.0, *, twist: np.ndarray | None = None,
                     confidence: np.ndarray | None = None
                     ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """Keyframe frames and cage sides ``(m, 4)``: cages fitted per side to the sections, their margins given up
    where a bend would fold them, and the keyframes' normals tilted where that is not enough (docs/design.md section
    3, ways 1 and 2; the caller shrinks what still folds, way 3).

    The tilt: each keyframe's normal is the dense tangent smoothed over a Gaussian window ``sigma`` (0: no
    tilt), so that consecutive sections fan out. Every window of a ladder is tried over the whole curve; a
    keyframe whose two segments keep ``det J >= eps`` untilted (margins given up) keeps ``sigma = 0``; another
    takes the smallest window that reaches ``eps`` (or, when none does, the one that gets closest, if it beats
    no tilt), and the windows are then made to vary no faster than the arclength so that neighbouring normals
    stay consistent. ``context`` (physical) is added to every side beyond the margins, given up like them.
    Returns ``(frames, sides, tissue)`` (the keyframe frames, the cage sides and the tissue's own sides per
    keyframe) for the tilt chosen, and the same for no tilt (the caller keeps whichever holds more of the mask
    once the last fold is shrunk away: on a helix whose curvature never eases the tilt can cost coverage).
    ``twist`` and ``confidence`` (dense): the keyframes' ``u`` are carried along their own normals (see
    :func:`~._foldfree.tilted_frames`).
    """
    from ._cage import fit_cages
    from ._foldfree import tilted_frames, unfold

    sc = arclength(curve)
    step = float(max(wm.working_spacing))
    ladder = [0.0] + [step * 1.5 ** i for i in range(12) if step * 1.5 ** i < sc[-1] / 2]
    a = sc[idx]

    def build(sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        kf = tilted_frames(frames, sc, idx, sigma, twist=twist, confidence=confidence)
        d = Deformation.from_keyframes(curve[idx], kf, 1.0)
        # the sections as the deformation cuts them: its own centres and SLERP frames at the dense arclengths
        s_dense = np.union1d(np.clip(sc, 0, d.length), d.knots)
        c, fr = d.sample(s_dense)
        keys = np.searchsorted(s_dense, d.knots)
        b = fit_cages(wm.binary, c, fr, keys, spacing=wm.working_spacing, margin=margin,
                      min_margin=2.0 * step + context)
        tissue = fit_cages(wm.binary, c, fr, keys, spacing=wm.working_spacing, margin=0.0, min_margin=0.0)
        d = Deformation(tuple(Keyframe.from_bounds(k.position, k.frame, bb) for k, bb in zip(d.keyframes, b,
                                                                                               strict=True)))
        d = unfold(d, eps=eps, floor=tissue)
        seg = np.array([d.jacobian_min(np.linspace(d.knots[k], d.knots[k + 1], 5)).min() for k in range(len(idx) - 1)])
        # a keyframe's figure: the worse of its two segments
        key = np.minimum(np.concatenate([[np.inf], seg]), np.concatenate([seg, [np.inf]]))
        return kf, d.bounds, key, tissue

    chosen = np.full(len(idx), -1)
    best_key = np.full(len(idx), -np.inf)
    best_level = np.zeros(len(idx), dtype=int)
    untilted = None
    for level, sg in enumerate(ladder):
        checkpoint()
        kf_l, b_l, key, tissue_l = build(np.full(len(idx), sg))
        if level == 0:
            untilted = (kf_l, b_l, tissue_l)
        better = key > best_key + 0.05  # a tilt must pay for itself
        best_key = np.where(better, key, best_key)
        best_level = np.where(better, level, best_level)
        chosen = np.where((chosen < 0) & (key >= eps), level, chosen)
        if (chosen >= 0).all():
            break
    sigma = np.asarray(ladder)[np.where(chosen >= 0, chosen, best_level)]
    sigma = np.max(sigma[None, :] - np.abs(a[:, None] - a[None, :]), axis=1).clip(min=0)
    if not sigma.any():
        return untilted, untilted
    kf, b, _, tissue = build(sigma)
    return (kf, b, tissue), untilted


_BRANCH_SLACK = 2.5  # inscribed radii: a voxel whose detour off the head-to-tail geodesic is larger is off the path
_BRANCH_MIN_LENGTH = 0.2  # of the path's length: shorter side parts (fins, a caudal lobe) are kept
_BRANCH_MIN_SHARE = 0.05  # of the mask: smaller side parts are kept
_BRANCH_BACK = 1.0  # inscribed radii: a branch is cut where its detour exceeds this (back towards the junction)
_BRANCH_RISE = 1.2  # of its base's radius: a dead end reaching less far past the slack is a kink's outer corner
_KINK_TURN = 35.0  # degrees: ... where the path turns at least this much at its junction (a kink, not a fork)
_DOUBT_TURN = 35.0  # degrees: a branch where the path turns this much at its junction is in doubt (a contact)
_END_NEAR = 3.3  # inscribed radii along the path: a branch leaving it nearer one of its ends is in doubt
_SEPARATE = ": separate the touching sides in the mask"  # what a reason in ``touching`` of two sides touching advises


_RIDGE = 0.8  # of a section's deepest point: the depth above which a section's core lies
_TWO_SIDED = 0.4  # of a cut part or of the kept mask: more than this in sections with two cores is the body doubled
_THICK_PIECES = 1.7  # a cut part whose shell pieces hold, in the median, this many times a tube as deep is doubled
_APART = 0.5  # of a part that is no dead end: at least this in shell pieces apart from the path's is a skipped stretch


def _shell_pieces(region: np.ndarray, dist: np.ndarray, radius: float, spacing: Sequence[float],
                  edt: np.ndarray | None = None
                  ) -> tuple[tuple[slice, ...], np.ndarray, int, np.ndarray, np.ndarray]:
    """``region`` (bool, working voxels) cut in shells of the geodesic distance from the head (``dist``), one
    inscribed radius thick, and each shell into its 26-connected pieces of at least a tenth of a shell of the tube.
    ``edt``: the region's ``depth_map`` when the caller has it (the same array shape as ``region``).

    Returns ``(box, labels, count, doubled, edt)``: the region's bounding box, the pieces' labels 1..count within it
    (0: outside or too small), the voxels (within the box) of the pieces with two cores, and ``depth_map`` of the
    region within the box. A piece has two cores where the region's own distance to its outline passes
    :data:`_RIDGE` of the piece's deepest in two places parted by a waist: two tubes side by side (a branch's
    section, round or flattened, has one core). A piece with a tunnel (a ring: the wall of a hollow tube, whose
    ridge runs all round) is not counted.
    """
    from skimage.measure import euler_number

    inside = np.argwhere(region)
    box = tuple(slice(int(a), int(b) + 1) for a, b in zip(inside.min(0), inside.max(0)))
    region, dist = region[box], dist[box]
    d = dist[region]
    voxel = float(np.prod(spacing))
    band = np.zeros(region.shape, dtype=np.int64)
    band[region] = np.floor((d - d.min()) / radius).astype(np.int64) + 1
    min_size = 0.1 * math.pi * radius**3 / voxel
    # the distance to the outline, which lies half a voxel beyond the last voxel inside (the transform's own
    # distance, to the first voxel outside, joins the cores of two sides that meet 1.5 radii apart along an axis)
    edt = depth_map(region, spacing) if edt is None else edt[box]
    depth = edt - 0.5 * min(spacing)
    labels = np.zeros(region.shape, dtype=np.int64)
    doubled = np.zeros(region.shape, dtype=bool)
    count = 0
    for b in range(1, int(band.max()) + 1):
        lab, n = ndi.label(band == b, _STRUCT26)
        if n == 0:
            continue
        sizes = np.bincount(lab.ravel())[1:]
        big = np.flatnonzero(sizes >= min_size) + 1
        keep = np.isin(lab, big)
        remap = np.zeros(n + 1, dtype=np.int64)
        remap[big] = count + 1 + np.arange(len(big))
        labels[keep] = remap[lab[keep]]
        count += len(big)
        boxes = ndi.find_objects(lab)
        for k in big:
            piece = lab[boxes[k - 1]] == k
            deep = depth[boxes[k - 1]]
            # a ring (the section of a hollow tube's wall) has its ridge all round and breaks into cores too:
            # two tubes side by side are a solid piece, a ring has a tunnel (Euler number 0, not 1)
            if ndi.label(piece & (deep >= _RIDGE * deep[piece].max()), _STRUCT26)[1] >= 2 and \
                    euler_number(np.pad(piece, 1), connectivity=3) == 1:
                doubled[boxes[k - 1]] |= piece
    return box, labels, count, doubled, edt


def _along(kept: np.ndarray, head_w: np.ndarray, spacing: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The geodesic distance (physical, on the 26-neighbour graph of ``kept``; 0 outside it and where unreached)
    from the voxel of ``kept`` nearest ``head_w``, and ``depth_map`` of ``kept``."""
    from scipy.sparse import csgraph
    from scipy.spatial import cKDTree

    from ._endpoints import _graph

    wsp = np.asarray(spacing, dtype=float)
    dist = np.zeros(kept.shape)
    if kept.any():
        graph, coords = _graph(kept, wsp)
        head = int(cKDTree(coords * wsp).query(np.asarray(head_w) * wsp)[1])
        d = csgraph.dijkstra(graph, directed=False, indices=[head])[0]
        dist[tuple(coords.T)] = np.where(np.isfinite(d), d, 0.0)
    return dist, depth_map(kept, wsp)


def _doubled_along(kept: np.ndarray, dist: np.ndarray, edt: np.ndarray, spacing: Sequence[float]
                   ) -> tuple[float, np.ndarray | None]:
    """The share of ``kept`` (bool, working voxels: the mask the path is straightened in) in sections with two cores
    (:func:`_shell_pieces`, shells of ``dist``, the geodesic distance from the head over ``kept``; ``edt`` its
    ``depth_map``: both as :func:`_cut_branches` hands them over), and the working voxel amid them (None when
    there are none).

    Where two sides of the body touch, the geodesic from the head crosses between them: a path that runs up one
    side and stops at the turn (ends suggested at the far points of a hairpin) keeps the other side within its
    sections, beside it in the straight volume and never followed. Measured: 0.45-0.63 of the kept mask on such
    hairpins; at most 0.26 on fish, coils, tubes that touch themselves, Y and graft phantoms and the real scans
    (benchmarks/RESULTS.md).
    """
    if not kept.any():
        return 0.0, None
    wsp = np.asarray(spacing, dtype=float)
    box, _, _, doubled, _ = _shell_pieces(kept, dist, float(edt.max()), wsp, edt)
    if not doubled.any():
        return 0.0, None
    at = np.argwhere(doubled)
    depth = dist[box][doubled]
    middle = at[int(np.argmin(np.abs(depth - np.median(depth))))]
    return float(doubled.sum()) / float(kept.sum()), middle + np.array([b.start for b in box])


def _thick_pieces(edt: np.ndarray, labels: np.ndarray, count: int, radius: float, spacing: Sequence[float]
                  ) -> float:
    """The median, over the shell pieces of a part (:func:`_shell_pieces`'s ``labels`` and ``edt``, the part's
    ``depth_map``, within its box), of a piece's volume over that of a round tube as deep as the piece, one shell
    (``radius``) long: about 1 on a branch, round or not too flat, about 2 where two sides of the body lie side by side,
    even so close that the distance to the outline has one core across them (sides 1.5 radii apart at a radius of 3
    voxels, where the transform's steps join the cores). The pieces under half the median piece's volume (the part's
    first and last shells, cut short) are left out; 0 for a part of fewer than three pieces."""
    if count < 3:
        return 0.0
    sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:].astype(float)
    deepest = np.asarray(ndi.maximum(edt, labels, index=np.arange(1, count + 1)))
    whole = sizes >= 0.5 * np.median(sizes)
    tube = radius * math.pi * np.maximum(deepest, 1e-12) ** 2
    return float(np.median(sizes[whole] * float(np.prod(spacing)) / tube[whole]))


def _loops_back(region: np.ndarray, dist: np.ndarray, radius: float, spacing: Sequence[float],
                kept: np.ndarray | None = None) -> bool:
    """Whether ``region`` (a part hanging off the path) is the body coming back on itself, not a branch.

    The part is cut in shells of the geodesic distance from the head (:func:`_shell_pieces`); the pieces and
    their contacts from one shell to the next make a graph (the part's Reeb graph). A branch, even one that forks
    again, is a tree; a stretch of the body that leaves where its two sides touch and comes back there (a loop,
    the turns of a coil that touch) splits into two legs that meet again at its far end: a cycle. With ``kept``
    (the mask the path keeps) the graph has one more node, joined once to each group of touching pieces that lie
    against it: a loop whose legs part before the cut (its sides touch at one place) meets the kept mask in two
    groups, a branch in one (also where it runs along the path for a while). A hairpin whose
    two sides touch all along has no cycle (its shells cross both sides at once) but its pieces are two tubes side
    by side, with two cores each. More than :data:`_TWO_SIDED` of the part's volume in such pieces is the body
    doubled: 0.56-0.85 of it on hairpins whose sides' centrelines lie 1.5-2 radii apart, at most 0.29 on the legs
    of 112 Y and graft phantoms (tests/skeleton/test_branches.py, benchmarks/RESULTS.md). Where the sides are so
    thin that the distance transform's steps join their cores, the pieces' size tells: more than
    :data:`_THICK_PIECES` times a round tube as deep (:func:`_thick_pieces`; two discs 1.17 radii apart or more
    cover 1.7 discs) is the body doubled: 1.71-2.25 on 70 such hairpins, at most 1.62 on 116 Y and graft legs.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if not region.any() or radius <= 0:
        return False
    box, labels, count, doubled, edt = _shell_pieces(region, dist, radius, spacing)
    if doubled.sum() > _TWO_SIDED * int(region.sum()) or _thick_pieces(edt, labels, count, radius,
                                                                         spacing) > _THICK_PIECES:
        return True
    edges = set()
    pad = np.pad(labels, 1)
    core = tuple(slice(1, -1) for _ in range(3))
    for off in [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) > (0, 0, 0)]:
        other = pad[tuple(slice(1 + o, pad.shape[i] - 1 + o) for i, o in enumerate(off))]
        here = pad[core]
        both = (here > 0) & (other > 0) & (here != other)
        edges.update(zip(np.minimum(here[both], other[both]).tolist(), np.maximum(here[both], other[both]).tolist()))
    if kept is not None and count:  # node 0: the kept mask, joined to one piece of each group lying against it
        grown = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
        near = ndi.binary_dilation(kept[grown], _STRUCT26)
        near = near[tuple(slice(b.start - g.start, b.start - g.start + (b.stop - b.start)) for b, g in zip(box, grown))]
        against = np.unique(labels[near & (labels > 0)])
        if len(against) > 1:
            aset = set(against.tolist())
            inner = np.array([e for e in edges if e[0] in aset and e[1] in aset]).reshape(-1, 2)
            index = {int(k): n for n, k in enumerate(against)}
            sub = coo_matrix((np.ones(len(inner)), ([index[a] for a in inner[:, 0]], [index[b] for b in inner[:, 1]])),
                             shape=(len(against), len(against)))
            _, group = connected_components(sub, directed=False)
            against = against[np.unique(group, return_index=True)[1]]
        edges.update((0, int(k)) for k in against)
    if not edges:
        return False
    e = np.array(sorted(edges))
    nodes = count + 1  # node 0 (the kept mask, when given) and the pieces 1..count
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nodes, nodes))
    n_comp = connected_components(graph, directed=False)[0] - (0 if kept is not None else 1)  # node 0 unused
    return len(e) - (nodes if kept is not None else count) + n_comp > 0  # independent cycles


class _Cut(NamedTuple):
    """What :func:`_cut_branches` gives: the working mask kept, the branches cut off ``(length, junction, loop,
    voxels, doubt)``, the stretches skipped ``(share of the mask, a working voxel on it farthest from the path)``, and
    the kept mask's geodesic distance from the head and depth (:func:`_along`)."""

    wm: WorkingMask
    branches: list[tuple[float, np.ndarray, bool, np.ndarray, str]]
    skipped: list[tuple[float, np.ndarray]]
    dist: np.ndarray
    edt: np.ndarray


def _rise(part: np.ndarray, binary: np.ndarray, detour_max: float, slack: float, spacing: np.ndarray) -> float:
    """How far a part off the path reaches past the slack (half its largest detour beyond it), over the radius of
    its base: the disc as large as the rest of the mask's voxels that touch it (26-neighbours; area by the voxels'
    mean face). A branch is a tube that leaves through a neck about as wide as itself and runs on (at least 1.33 on
    240 cut parts of Y, graft and hairpin phantoms, but for a short leg that never parts from the other, 1.11); the
    outer corner of a tube that kinks tighter than its own radius is a cap on a base as wide as the bend
    (0.33-1.07 on 56 kinked tubes turning 70-147 degrees)."""
    base = int((ndi.binary_dilation(part, _STRUCT26) & ~part & binary).sum())
    if not base:
        return float("inf")
    area = base * float(np.prod(spacing)) ** (2.0 / 3.0)
    return (detour_max - slack) / 2.0 / float(np.sqrt(area / np.pi))


def _turn_at(coords: np.ndarray, d_head: np.ndarray, on_path: np.ndarray, q: float, radius: float,
             spacing: np.ndarray) -> float:
    """How far (degrees) the path turns where its geodesic distance from the head is ``q``: between the chords
    from the centroid of its voxels 2-4 ``radius`` before to those within one radius, and from there to those 2-4
    after (``coords`` the mask's voxels, ``d_head`` their distances, ``on_path`` the path's). 0 when a window is
    empty (the path's ends)."""
    def centre(lo: float, hi: float) -> np.ndarray | None:
        sel = on_path & (d_head >= q + lo * radius) & (d_head <= q + hi * radius)
        return coords[sel].mean(axis=0) * spacing if sel.any() else None

    a, c, b = centre(-4.0, -2.0), centre(-1.0, 1.0), centre(2.0, 4.0)
    if a is None or b is None or c is None:
        return 0.0
    u, v = c - a, b - c
    nu, nv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
    if nu == 0 or nv == 0:
        return 0.0
    return float(np.degrees(np.arccos(np.clip(np.dot(u, v) / (nu * nv), -1.0, 1.0))))


def _cut_branches(wm: WorkingMask, head_w: np.ndarray, tail_w: np.ndarray) -> _Cut:
    """The working mask without the branches off the path between the two ends, each branch cut off as
    ``(length, junction in working voxels, loop, its working voxels (M, 3))``, the stretches of body the path
    skips (:class:`_Cut`), and :func:`_along` of what is kept (taken from this function's own when nothing was cut).

    A voxel's detour is ``d_head + d_tail - L`` (geodesic distances on the 26-neighbour graph, physical): about
    0 along the path and at most a few radii across it, twice the distance along a side branch from where it
    leaves. The parts whose detour exceeds :data:`_BRANCH_SLACK` inscribed radii are the candidates; one is a
    branch when its length (half its largest detour, plus the slack) is at least :data:`_BRANCH_MIN_LENGTH` of L,
    it holds :data:`_BRANCH_MIN_SHARE` of the mask (so that fins and a forked tail stay), it is a dead end
    (``d_head - d_tail`` nearly constant over it) and it reaches past the slack at least :data:`_BRANCH_RISE` times
    the radius of its base (:func:`_rise`) or the path turns less than :data:`_KINK_TURN` there (:func:`_turn_at`):
    the outer corner of a kink tighter than the tube reaches less, where the path turns, and stays.
    A part as long and as large that is no dead end is a stretch of
    the body that the geodesic skipped where two turns touch (it meets the path at both its ends): it stays, and is
    reported as skipped (the straight volume holds it beside the path, not straightened). A branch
    is cut back to where its detour passes :data:`_BRANCH_BACK` radii, with whatever the cut leaves hanging; its
    voxels are all it took (part of them, near the junction, may still lie in the path's cage).
    ``loop`` is True when what was cut comes back on itself (:func:`_loops_back`): the body touches itself there
    and the part left out is the body's own, not a branch. ``doubt`` ('' or why) says where a branch cannot be
    told from the body running into itself: where the path turns :data:`_DOUBT_TURN` degrees or more at its
    junction (a fork's legs leave the trunk gently: at most 20.6 degrees on 124 Y and graft legs; where a tube's
    turns touch, the path jumps from one to the other: 36-62 degrees), or where it leaves the path within
    :data:`_END_NEAR` radii of one of its ends (its junction's geodesic distance from that end less half its
    detour): an end that touches the body further along sends the path straight into that stretch, and the
    stretch between hangs off it like a branch (0.2-2.9 radii on six random tubes), where a fork's chosen leg runs
    on past the junction (at least 3.7 radii on 80 Y and graft phantoms, 5.1 on 60 more never tuned to).
    """
    from scipy.sparse import csgraph
    from scipy.spatial import cKDTree

    from ._endpoints import _graph

    binary = wm.binary
    if not binary.any():
        return _Cut(wm, [], [], *_along(binary, head_w, wm.working_spacing))
    wsp = np.asarray(wm.working_spacing)
    graph, coords = _graph(binary, wsp)
    ends = [int(i) for i in cKDTree(coords * wsp).query(np.array([head_w, tail_w]) * wsp)[1]]  # nearest voxels
    d = csgraph.dijkstra(graph, directed=False, indices=ends)
    dist = np.zeros(binary.shape)
    dist[tuple(coords.T)] = np.where(np.isfinite(d[0]), d[0], 0.0)
    edt = depth_map(binary, wsp)
    total = float(d[0, ends[1]])
    if not np.isfinite(total) or total <= 0:
        return _Cut(wm, [], [], dist, edt)
    detour = d[0] + d[1] - total
    radius = float(edt.max())
    slack = _BRANCH_SLACK * radius
    off = np.zeros(binary.shape, dtype=bool)
    far = np.isfinite(detour) & (detour > slack)
    off[tuple(coords[far].T)] = True
    lab, n = ndi.label(off, _STRUCT26)
    if n == 0:
        return _Cut(wm, [], [], dist, edt)
    det = np.zeros(binary.shape)
    det[tuple(coords.T)] = np.where(np.isfinite(detour), detour, 0.0)
    dq = np.zeros(binary.shape)
    dq[tuple(coords.T)] = np.where(np.isfinite(detour), d[0] - d[1], 0.0)
    cut = np.zeros(binary.shape, dtype=bool)
    found = []
    skipped = []
    count = int(binary.sum())
    for k, box in enumerate(ndi.find_objects(lab), start=1):
        part = lab[box] == k
        length = float(det[box][part].max()) / 2 + slack / 2
        share = float(part.sum()) / count
        # a side branch leaves the path in one place: along it d_head and d_tail grow together, so their
        # difference stays that of its junction; a stretch of body that the geodesic skipped (two turns of a coil
        # touching) meets the path at both its ends, and the difference runs from one end's to the other's
        q = dq[box][part]
        dead_end = float(np.percentile(q, 95) - np.percentile(q, 5)) <= 2.0 * slack
        if length >= _BRANCH_MIN_LENGTH * total and share >= _BRANCH_MIN_SHARE:
            at = np.argwhere(part)[np.argmin(det[box][part])] + np.array([b.start for b in box])  # its junction
            turn = _turn_at(coords, d[0], detour <= _BRANCH_BACK * radius, dist[tuple(at)], radius, wsp
                            ) if dead_end else 0.0
            if (dead_end and turn >= _KINK_TURN
                    and _rise(part, binary[box], float(det[box][part].max()), slack, wsp) < _BRANCH_RISE):
                pass  # the outer corner of a kink: the body's own, kept (the fold-free cage holds it)
            elif dead_end:
                cut[lab == k] = True
                # where along the path it leaves: its junction's distances from the ends less half its detour
                to_head = float(dist[tuple(at)] - det[tuple(at)] / 2)
                to_tail = float(dist[tuple(at)] - dq[tuple(at)] - det[tuple(at)] / 2)
                from_end = max(min(to_head, to_tail), 0.0) / radius
                doubt = (f"where the path turns {turn:.0f} degrees" if turn >= _DOUBT_TURN else
                         f"{from_end:.2g} radii from the path's {'head' if to_head <= to_tail else 'tail'}"
                         if from_end < _END_NEAR else "")
                found.append((k, length, at.astype(float), doubt))
            else:  # the farthest point from the path: one to chain through
                far_at = np.argwhere(part)[np.argmax(det[box][part])] + np.array([b.start for b in box])
                skipped.append((k, share, far_at))
    if skipped:
        # a stretch the path skips lies apart from it in the shells of the geodesic distance from the head; the far
        # side of a tall body along a tight coil is no dead end either, but it lies in the path's own shell pieces
        sbox, pieces, _, _, _ = _shell_pieces(binary, dist, radius, wsp, edt)
        path = np.zeros(binary.shape, dtype=bool)
        path[tuple(coords[np.isfinite(detour) & (detour <= _BRANCH_BACK * radius)].T)] = True
        apart = (pieces > 0) & ~np.isin(pieces, np.unique(pieces[path[sbox]]))
        kept_apart = []
        for k, share, at in skipped:
            part = (lab == k)[sbox]
            if float(apart[part].sum()) >= _APART * max(int(part.sum()), 1):
                kept_apart.append((share, at))
        skipped = kept_apart
    if not found:
        return _Cut(wm, [], skipped, dist, edt)
    # back to the junction: the parts off the path by a smaller detour that touch a branch go with it (the stub
    # a branch leaves within the slack would pull the sections' centroids towards it)
    near = np.zeros(binary.shape, dtype=bool)
    near[tuple(coords[np.isfinite(detour) & (detour > _BRANCH_BACK * radius)].T)] = True
    lab3, _ = ndi.label(near, _STRUCT26)
    touched = np.unique(lab3[cut])
    cut |= np.isin(lab3, touched[touched > 0])
    kept = binary & ~cut
    lab2, _ = ndi.label(kept, _STRUCT26)  # what the cut leaves hanging (beyond the branch) goes with it
    kept &= lab2 == lab2[tuple(coords[ends[0]])]
    skipped = [(share, at) for share, at in skipped if kept[tuple(at)]]  # not gone with a branch
    # each branch with all it took (its cut-back stub and what hangs beyond), as reported
    gone, _ = ndi.label(binary & ~kept, _STRUCT26)
    branches = []
    for k, length, where, doubt in found:
        ids = np.unique(gone[lab == k])
        region = np.isin(gone, ids[ids > 0])
        branches.append((length, where, _loops_back(region, dist, radius, wsp, kept), np.argwhere(region), doubt))
    rim = ndi.binary_dilation(kept, _STRUCT26)  # the kept part's partial voxels stay with it
    return _Cut(replace(wm, binary=kept, occupancy=np.where(rim, wm.occupancy, 0.0).astype(wm.occupancy.dtype)),
                branches, skipped, *_along(kept, head_w, wsp))


def _beyond_tissue(bounds: np.ndarray, tissue: np.ndarray) -> np.ndarray:
    """Per keyframe and side (m, 4): how far the cage's side lies beyond the tissue's own (negative: inside it)."""
    return np.stack([tissue[:, 0] - bounds[:, 0], bounds[:, 1] - tissue[:, 1],
                     tissue[:, 2] - bounds[:, 2], bounds[:, 3] - tissue[:, 3]], axis=1)


def _bend_lost(bounds: np.ndarray, tissue: np.ndarray | None, knots: np.ndarray,
               lost: tuple[tuple[float, float, float], ...], vox: float
               ) -> tuple[float, tuple[tuple[float, float, float], ...]]:
    """The lost intervals on the inside of bends tighter than the body is thick: those that meet the two segments
    of a keyframe whose cage the fold-free construction shrank to the tissue or into it (a side less than half of
    ``vox``, a working voxel, beyond the tissue's own extent, where the fitted cage lies two voxels beyond it at
    least). There it gave the margins up, or the tissue too, so that the sections do not fold: a larger cage is
    given up the same way and does not help. Returns the share of the mask they lose and the intervals (none when
    the cage was given, ``tissue`` None)."""
    if tissue is None or not lost:
        return 0.0, ()
    taken = np.flatnonzero(_beyond_tissue(bounds, np.asarray(tissue, dtype=float)).min(axis=1) < 0.5 * vox)
    if not len(taken):
        return 0.0, ()
    lo = knots[np.maximum(taken - 1, 0)]
    hi = knots[np.minimum(taken + 1, len(knots) - 1)]
    at = tuple(iv for iv in lost if np.any((lo <= iv[1]) & (hi >= iv[0])))
    return float(sum(f for *_, f in at)), at


def _context_given(bounds: np.ndarray, tissue: np.ndarray, knots: np.ndarray, asked: float, vox: float,
                   unit: str | None, note: Any) -> float:
    """The context the cages give: per keyframe and side, how far the side lies beyond the tissue's own (the
    least of them); a note says where it is less than ``asked`` (the fold-free construction gave it up)."""
    beyond = _beyond_tissue(bounds, tissue)
    least = float(beyond.min())
    short = beyond.min(axis=1) < asked - 0.5 * vox
    if short.any():
        u = unit_label(unit)
        where = ", ".join(f"{knots[i]:.4g}" for i in np.flatnonzero(short)[:8])
        note(f"context: {asked:.4g} {u} asked, at least {max(least, 0.0):.3g} {u} given; the cage gives it up on "
             f"the inner side of bends that would fold it, at the keyframes at s = {where} {u}")
    return least


def _landmarks(points: Any) -> np.ndarray:
    """Dorsal points (full-resolution voxels, array index order) as an (M, 3) float array, checked."""
    try:
        a = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        raise InvalidInputError(f"dorsal_points must be points of 3 numbers (voxels), got {points!r}") from None
    a = a.reshape(1, 3) if a.shape == (3,) else a
    if a.ndim != 2 or a.shape[1] != 3 or not len(a) or not np.isfinite(a).all():
        raise InvalidInputError(f"dorsal_points must be one or more points of 3 finite numbers (voxels), got an "
                                f"array of shape {a.shape}")
    return a


def estimate_deformation_iter(
    mask: Any,
    endpoints: Any = None,
    *,
    spacing: Sequence[float] | float | None = None,
    n_levels: int = 100,
    smoothing_iterations: int = 50,
    cage_radius: float = 10.0,
    estimate_twist: bool = True,
    volume: Any = None,
    smoothing: str = "taubin",
    level_spacing: str = "arclength",
    tolerance: float = 1.0,
    half_extent: Sequence[float] | float | None = None,
    pad: Sequence[float] | float | None = None,
    max_side: int = 128,
    snap_tolerance: float = 5.0,
    up: Sequence[float] | None = None,
    origin: Sequence[float] | float | None = None,
    unit: str | None = None,
    max_triangles: int | None = 3000,
    mesher: dict[str, Any] | None = None,
    tet_mesher: str = "lattice",
    lattice_nodes: int = 8000,
    end_window_factor: float = 2.0,
    fold_free: bool = True,
    cage_margin: float = 0.1,
    min_jacobian: float = 0.2,
    dorsal_points: Any = None,
    dorsal_direction: Sequence[float] | None = None,
    context: float = 0.0,
) -> ProgressGenerator[SkeletonResult]:
    """Generator form of :func:`estimate_deformation`: yields :class:`Progress` per stage, returns a
    :class:`SkeletonResult` (its ``deformation`` is what :func:`estimate_deformation` returns).

    See :func:`estimate_deformation` for the parameters.
    """
    from ._cage import propose_cage
    from ._endpoints import suggest_endpoints
    from ._twist import apply_twist, landmark_twist
    from ._twist import estimate_twist as twist_angles

    timings: dict[str, float] = {}
    t = time.perf_counter()
    if spacing is None:
        if isinstance(mask, Volume):
            spacing, origin = mask.spacing, mask.origin if origin is None else origin
            unit = mask.unit if unit is None else unit
        else:
            raise InvalidInputError("spacing is required (the voxel size along axis0, axis1, axis2) unless the "
                                    "mask is a Volume")
    sp = np.asarray(check_spacing(spacing))
    org = np.broadcast_to(np.asarray(0.0 if origin is None else origin, dtype=float), (3,))
    unit = normalise_unit(unit)
    for name, value, lo in (("n_levels", n_levels, 2), ("smoothing_iterations", smoothing_iterations, 0)):
        if not isinstance(value, (int, np.integer)) or value < lo:
            raise InvalidInputError(f"{name} must be an integer >= {lo}, got {value!r}")
    for name, value in (("cage_radius", cage_radius), ("tolerance", tolerance), ("snap_tolerance", snap_tolerance)):
        if not (isinstance(value, (int, float, np.number)) and np.isfinite(value) and value > 0):
            raise InvalidInputError(f"{name} must be a positive number (voxels), got {value!r}")
    if not (isinstance(end_window_factor, (int, float, np.number)) and 0 <= end_window_factor < np.inf):
        raise InvalidInputError(f"end_window_factor must be a number >= 0, got {end_window_factor!r}")
    if not (isinstance(cage_margin, (int, float, np.number)) and 0 <= cage_margin < np.inf):
        raise InvalidInputError(f"cage_margin must be a number >= 0 (0.1: 10 %), got {cage_margin!r}")
    if not (isinstance(context, (int, float, np.number)) and 0 <= context < np.inf):
        raise InvalidInputError(f"context must be a number >= 0 (physical units), got {context!r}")
    if context > 0 and (half_extent is not None or not fold_free):
        raise InvalidInputError("context widens the fitted cages: give it without fixed cage half extents")
    if not (isinstance(min_jacobian, (int, float, np.number)) and 0 < min_jacobian < 1):
        raise InvalidInputError(f"min_jacobian must be a number in (0, 1), got {min_jacobian!r}")
    if level_spacing not in ("arclength", "uniform"):
        raise InvalidInputError(f"level_spacing must be 'arclength' or 'uniform', got {level_spacing!r}")
    if tet_mesher not in ("lattice", "ftetwild"):
        raise InvalidInputError(f"tet_mesher must be 'lattice' or 'ftetwild', got {tet_mesher!r}")
    if not isinstance(lattice_nodes, (int, np.integer)) or lattice_nodes < 1000:
        raise InvalidInputError(f"lattice_nodes must be an integer >= 1000, got {lattice_nodes!r}")
    if smoothing not in ("taubin", "laplacian"):
        raise InvalidInputError(f"smoothing must be 'taubin' or 'laplacian', got {smoothing!r}")
    ends = _normalise_endpoints(endpoints)
    vox = float(sp.min())
    notes: list[str] = []
    touching: list[str] = []
    left_out = None  # the working voxels of the branches (and loops) cut off
    cut_off: list = []
    uncut_count = 0

    def note(msg: str) -> None:
        notes.append(msg)
        warnings.warn(msg, UserWarning, stacklevel=3)

    yield Progress("working mask", 0, 1, "cropping and averaging")
    wm = _slender_working_mask(mask, sp, volume, max_side)
    across = _across(wm)
    line_voxels = None
    if across < _LINE_ACROSS:  # a centreline drawn as a mask: no cross-section to fit a cage or a twist to
        unit_name = unit_label(unit)
        if half_extent is None:
            raise InvalidInputError(
                f"the mask is a line, at most {across:.1f} voxels thick: a centreline, not the specimen's body, so "
                f"there is no cross-section to fit the cage to; give the cage's half extents (--cage RX,RY in "
                f"{unit_name}, half_extent=) to straighten around the line, or the specimen's own mask")
        tube = _LINE_TUBE * float(sp.max())
        note(f"the mask is a line, at most {across:.1f} voxels thick: the curve runs along it (a tube of "
             f"{tube:.3g} {unit_name} around it), the cage is the one given, and the twist is not estimated")
        line = np.asarray(mask.data if isinstance(mask, Volume) else mask)
        line_voxels = np.argwhere(line != 0).astype(float)
        mask = ndi.distance_transform_edt(line == 0, sampling=sp) <= tube
        estimate_twist = False
        wm = _slender_working_mask(mask, sp, volume, max_side)
    sides = _border_sides(wm)
    if sides:
        note(f"the mask touches the volume's border ({', '.join(sides)}): the specimen may be cut off by the scan's "
             "field of view; the curve ends where the mask does")
    labels, nlab = ndi.label(wm.binary, _STRUCT26)
    t = _stage("working mask", timings, t)
    yield Progress("working mask", 1, 1, f"factor {wm.factor}, {wm.binary.shape}, {nlab} part(s)")

    suggested = False
    if ends is None:
        yield Progress("endpoints", 0, 1, "suggesting head and tail")
        h, tl = suggest_endpoints(wm.binary, spacing=wm.working_spacing, volume=wm.volume)
        h, tl = wm.from_working(np.asarray(h)), wm.from_working(np.asarray(tl))
        if sides:  # an end where the mask runs off the scan: the centre of the cut face, not a point of its rim
            h, tl = _cut_face_end(mask, h, wm, sp), _cut_face_end(mask, tl, wm, sp)
        if line_voxels is not None:  # the line's own ends, not the tube's caps beyond them
            from scipy.spatial import cKDTree

            h, tl = line_voxels[cKDTree(line_voxels * sp).query(np.array([h, tl]) * sp)[1]]
        ends = Endpoints(head=tuple(h), tail=tuple(tl))
        suggested = True
        t = _stage("endpoints", timings, t)
    tol = snap_tolerance * vox
    chain = list(ends.chain) or [(ends.head, ends.tail)]
    if ends.chain:
        if np.linalg.norm(np.subtract(chain[0][0], ends.head)) > 1e-6 or \
                np.linalg.norm(np.subtract(chain[-1][1], ends.tail)) > 1e-6:
            raise InvalidInputError("the chain must start at the head and end at the tail: its first pair starts at "
                                    f"{list(chain[0][0])} (head {list(ends.head)}) and its last ends at "
                                    f"{list(chain[-1][1])} (tail {list(ends.tail)})")
    snapped = []
    for i, (a, b) in enumerate(chain):
        what = "specimen" if len(chain) == 1 else f"part {i + 1} of the chain"
        pa = _snap(np.asarray(a), wm, tol, f"start of the {what}" if len(chain) > 1 else "head", unit)
        pb = _snap(np.asarray(b), wm, tol, f"end of the {what}" if len(chain) > 1 else "tail", unit)
        if np.linalg.norm((pa - pb) * sp) < 2 * wm.factor * vox:
            raise InvalidInputError(f"the start {np.round(pa, 2).tolist()} and end {np.round(pb, 2).tolist()} of the "
                                    f"{what} are (nearly) the same point; click the two ends of the specimen")
        snapped.append((pa, pb))
    t = _stage("endpoints", timings, t)
    if len(snapped) == 1:
        # a specimen that branches between its ends (a Y-shaped graft, a vessel's side branch): the path between
        # the ends is kept, the other branches are cut off at the junction and left out of the cage
        uncut = wm.binary
        cut = _cut_branches(wm, wm.to_working(snapped[0][0]), wm.to_working(snapped[0][1]))
        wm, cut_off, kept_dist, kept_edt = cut.wm, cut.branches, cut.dist, cut.edt
        for share, at in cut.skipped:  # a stretch of body skipped where two turns touch: not straightened
            where = np.round(wm.from_working(at), 1).tolist()
            fact = (f"the mask touches itself between the ends: the path crosses where two turns touch and skips a "
                    f"stretch of the body through {where} (voxels), {100 * share:.2g} % of the mask, which lies in the "
                    "straight volume beside the path, not straightened")
            touching.append(fact + _SEPARATE)
            note(fact + "; separate the touching turns in the mask, or straighten it as a chain of two "
                 f"parts through that point (--chain HEAD P --chain P TAIL, P = {where})")
        if cut_off:
            left_out = uncut & ~wm.binary
            uncut_count = int(uncut.sum())
        # and what is kept: two sides of the body side by side along the path (one of them never followed)
        doubled_share, doubled_at = _doubled_along(wm.binary, kept_dist, kept_edt, wm.working_spacing)
        if doubled_share > _TWO_SIDED:
            where = np.round(wm.from_working(doubled_at), 1).tolist()
            fact = (f"the mask touches itself along the path at {where} (voxels): {100 * doubled_share:.2g} % of the "
                    "mask straightened lies where two sides of the body run side by side, one of them not followed "
                    "by the path")
            touching.append(fact + _SEPARATE)
            note(fact + "; separate the touching sides in the mask")
        t = _stage("branches", timings, t)

    # the ends of every part: a quadratic over about one body width instead of the kinks that the point-like
    # Dirichlet ends give the level-set centroids (the cage folds at such kinks)
    body_depth = kept_edt if len(snapped) == 1 else depth_map(wm.binary, wm.working_spacing)
    end_window = end_window_factor * float(body_depth.max())
    pieces = []
    mesh_info: list[dict[str, int]] = []
    for i, (pa, pb) in enumerate(snapped):
        what = "specimen" if len(snapped) == 1 else f"part {i + 1} of the chain"
        pts = yield from _part_curve(wm, labels, wm.to_working(pa), wm.to_working(pb), what=what,
                                     chained=len(snapped) > 1, n_levels=int(n_levels), level_spacing=level_spacing,
                                     timings=timings, mesh_info=mesh_info, note=note,
                                     max_triangles=max_triangles, mesher=dict(mesher or {}),
                                     tet_mesher=tet_mesher, lattice_nodes=int(lattice_nodes))
        t = time.perf_counter()
        yield Progress("smoothing", i, len(snapped), what)
        piece = resample_curve(smooth_curve(pts, iterations=int(smoothing_iterations), method=smoothing),
                               min_step=0.5 * vox)
        pieces.append(regularise_ends(piece, end_window) if end_window > 0 else piece)
        t = _stage("smoothing", timings, t)
    # parts are joined by the straight segments between one part's end and the next one's start
    curve = resample_curve(np.vstack(pieces), min_step=0.5 * vox)
    frames = parallel_transport_frames(curve, up=up)
    t = _stage("frames", timings, t)
    yield Progress("frames", 1, 1, f"{len(curve)} points")

    curve_w = curve - wm.offset  # physical, origin at working voxel 0 (the helpers' convention)
    theta = np.zeros(len(curve))
    theta_conf = np.zeros(len(curve))
    twist_source = "none"
    if dorsal_points is not None or dorsal_direction is not None:
        yield Progress("twist", 0, 1, "through the dorsal landmarks")
        theta, theta_conf = landmark_twist(
            curve, frames, dorsal_direction=dorsal_direction,
            dorsal_points=None if dorsal_points is None else _landmarks(dorsal_points) * sp)
        frames = apply_twist(frames, theta)
        twist_source = "landmarks"
        t = _stage("twist", timings, t)
    elif estimate_twist:
        yield Progress("twist", 0, 1, "orienting the cross-sections")
        # The orientation of a cross-section needs it several voxels across: at the working resolution a
        # slender body is only a few voxels wide (the twist error doubled on the phantoms). The sections are
        # read from a finer copy, box-averaged only as much as keeps the body's half-width >= 8 voxels.
        tw = wm
        if wm.factor > 1:
            rough_he, _ = propose_cage(wm.binary, curve_w, frames, spacing=wm.working_spacing, margin=0.0,
                                       min_margin=0.0)
            tf = int(max(1, min(wm.factor, math.floor(min(rough_he) / (8.0 * vox)))))
            if tf < wm.factor:
                tw = working_mask(mask, spacing=tuple(sp), volume=volume, factor=tf)
        exclude = left_out
        if left_out is not None and tw is not wm:  # the cut, read at the finer copy's voxel centres
            scale = np.asarray(tw.working_spacing) / np.asarray(wm.working_spacing)
            exclude = ndi.affine_transform(left_out.astype(np.uint8), scale,
                                           offset=(tw.offset - wm.offset) / np.asarray(wm.working_spacing),
                                           output_shape=tw.binary.shape, order=0, mode="constant",
                                           cval=0).astype(bool)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            # the scan's faces in the crop's working index coordinates (a crop's own faces cut nothing)
            fov = np.array([-np.asarray(tw.start) / tw.factor - 0.5,
                            (np.asarray(tw.shape) - np.asarray(tw.start)) / tw.factor - 0.5])
            theta, twist_info = twist_angles(curve - tw.offset, frames, mask=tw.binary,
                                             spacing=tw.working_spacing, volume=tw.volume, exclude=exclude,
                                             field_of_view=fov, return_info=True)
        theta = np.asarray(theta, dtype=float)
        theta_conf = np.zeros(len(curve)) if twist_info["round"] else np.asarray(twist_info["confidence"], float)
        twist_source = "none" if twist_info["round"] else "estimated"
        for w in caught:
            note(str(w.message))
        # the tips are a few voxels across: their sections carry no orientation, keep the body's
        sc = arclength(curve)
        hold = min(end_window / max(end_window_factor, 1e-9), sc[-1] / 4.0) if end_window > 0 else 0.0
        if hold > 0:
            theta = np.where(sc < hold, np.interp(hold, sc, theta), theta)
            theta = np.where(sc > sc[-1] - hold, np.interp(sc[-1] - hold, sc, theta), theta)
            theta_conf = np.where((sc < hold) | (sc > sc[-1] - hold), 0.0, theta_conf)
        frames = apply_twist(frames, theta)
        t = _stage("twist", timings, t)
    yield Progress("cage", 0, 1, "cross-section extent")
    auto_he, auto_pad = propose_cage(wm.binary, curve_w, frames, spacing=wm.working_spacing, margin=cage_margin)
    auto_pad = np.asarray(auto_pad, dtype=float) + float(context)
    he = auto_he if half_extent is None else half_extent
    pd = auto_pad if pad is None else pad
    length = float(arclength(curve)[-1])
    width = 2.0 * float(np.max(auto_he))
    if length < 1.5 * width:
        note(f"the specimen is nearly spherical (length {length:.3g} against a width of about {width:.3g}): there is "
             "no clear axis to straighten along; the curve runs between the given ends")
    t = _stage("cage", timings, t)
    yield Progress("keyframes", 0, 1, "prism subdivision")
    idx = select_keyframes(curve, frames, radius=cage_radius * vox, tolerance=tolerance * vox)
    offsets = 0.0
    if fold_free and half_extent is None:
        yield Progress("keyframes", 0, 1, "per-side cages, tilting the sections where a bend would fold them")
        tilted, untilted = _fold_free_cages(wm, curve_w, frames, idx, float(min_jacobian), float(cage_margin),
                                            float(context), twist=theta, confidence=theta_conf)
        candidates = [tilted] if tilted is untilted else [tilted, untilted]
    else:
        from ._foldfree import tilted_frames

        # untilted; u carried along the keyframes' normals where the twist is not read (tilted_frames)
        candidates = [(tilted_frames(frames, arclength(curve), idx, np.zeros(len(idx)), twist=theta,
                                     confidence=theta_conf), None, None)]
    mask_pts = wm.from_working(np.argwhere(wm.binary)) * sp + org
    best = None
    for key_frames, b, tissue_c in candidates:
        if b is not None:
            he = np.stack([(b[:, 1] - b[:, 0]) / 2, (b[:, 3] - b[:, 2]) / 2], axis=1)
            offsets = np.stack([(b[:, 1] + b[:, 0]) / 2, (b[:, 3] + b[:, 2]) / 2], axis=1)
        d_c = Deformation.from_keyframes(curve[idx] + org, key_frames, he, pad=pd, spacing=tuple(sp),
                                         origin=tuple(org), unit=unit, offsets=offsets)
        if fold_free:
            # where the inner side still reaches the centre of curvature: shrink it (the third way out), margins
            # first down to min_jacobian, the tissue itself only where holding it would take J under a quarter of it
            if tissue_c is not None:
                d_c = unfold(d_c, eps=float(min_jacobian), floor=tissue_c)
            d_c = unfold(d_c, eps=_TISSUE_JACOBIAN * float(min_jacobian), least="area")
        cov_c = coverage(d_c, mask_pts, bin_width=2 * float(max(wm.working_spacing))) if len(candidates) > 1 \
            else None
        if best is None or cov_c.fraction > best[0].fraction + 1e-4:  # the tilted cages unless no tilt holds more
            best = (cov_c, d_c, tissue_c)
    cov, deformation, tissue = best
    context_given = None
    if context > 0:
        context_given = _context_given(deformation.bounds, tissue, deformation.knots, float(context),
                                       float(vox), unit, note)
    folds = deformation.folds()
    if folds:
        where = ", ".join(f"{a:.4g}-{b:.4g}" for a, b in folds)
        note(f"the deformation folds (the cage is wider than the bend's radius) at s = {where} {unit_label(unit)}: "
             "give a smaller cage (--cage RX,RY, or half_extent=) or shrink the cages of the keyframes there in the "
             "session (Deformation.set_cage)")
    t = _stage("keyframes", timings, t)
    yield Progress("keyframes", 1, 1, f"{len(idx)} keyframes")
    yield Progress("coverage", 0, 1, "mapping the mask into the straight box")
    s_dense = np.union1d(np.arange(0.0, deformation.length, vox / 2), deformation.knots)
    jmin = float(deformation.jacobian_min(s_dense).min())
    tilt = max_tilt(deformation)
    if cov is None:
        cov = coverage(deformation, mask_pts, bin_width=2 * float(max(wm.working_spacing)))
    apart, n_apart = _apart_from_path(wm, curve_w, deformation, sp, org)
    if apart >= _APART_SAID:
        note(f"{n_apart} separate part(s) of the mask, {100 * apart:.2g} % of it, lie off the path between the ends "
             "and outside the straight volume: give a mask of this specimen alone, or straighten the parts as one "
             "chain (--chain START END for each part, head to tail)")
    bend, bend_at = _bend_lost(deformation.bounds, tissue, deformation.knots, cov.lost,
                               float(max(wm.working_spacing)))
    if bend >= 1e-3:
        note(f"the cage leaves {100 * bend:.2g} % of the mask out on the inside of bends tighter than the body is "
             f"thick ({format_lost(bend_at, unit_label(unit))}): no cage holds it there without folding, a larger "
             "one neither")
    other = tuple(iv for iv in cov.lost if iv not in bend_at)
    if other and sum(f for *_, f in other) >= 1e-3 and (1 - cov.fraction) - bend - apart >= 1e-3:
        lost_at = format_lost(other, unit_label(unit))
        note(f"the cage leaves {100 * (1 - cov.fraction - bend):.2g} % of the mask out ({lost_at}): give a larger "
             "cage (--cage RX,RY or --cage-margin), or edit the keyframes there in the session (Deformation.set_cage)")
    left_out_share = 0.0
    said: list[str] = []  # the branches cut off, as reported
    if cut_off:  # what each cut-off part leaves outside the straight volume, as a share of the whole mask
        u = unit_label(unit)
        for length, at, loop, region, doubt in cut_off:
            out = len(region) * (1.0 - coverage(deformation, wm.from_working(region) * sp + org).fraction)
            left_out_share += out / uncut_count
            where = np.round(wm.from_working(at), 1).tolist()
            if doubt and not loop:
                fact = (f"a part of the mask, {100 * out / uncut_count:.2g} % of it, is cut off at {where} (voxels), "
                        f"{doubt}: a branch, or the body running into itself there (its two sides touching read as a "
                        "fork), which the mask cannot tell")
                touching.append(fact + ": check the straight volume")
                note(fact + "; check the straight volume: a branch is left out as it should be, the body "
                     "touching itself is not straightened there: separate the touching sides in the mask, or "
                     "straighten it as a chain of two parts that meet on the part (--chain HEAD P --chain P TAIL, "
                     "P a point on the part)")
            elif loop:
                fact = (f"the mask touches itself at {where} (voxels): the path between the ends crosses there and "
                        f"the loop or fold of the body it skips, {100 * out / uncut_count:.2g} % of the mask, is left "
                        "out")
                touching.append(fact + _SEPARATE)
                note(fact + "; separate the touching sides in the mask, or straighten it as a chain of two "
                     "parts that meet on the loop (--chain HEAD P --chain P TAIL, P a point on the loop)")
            else:
                said.append(f"{length:.3g} {u} long, {100 * out / uncut_count:.2g} % of the mask left out, joining at "
                            f"{where} (voxels)")
        if said:
            note(f"the mask branches between the ends: {len(said)} other branch(es) cut off at the junction and "
                 f"left out of the cage ({'; '.join(said)}); give the end of another branch as the tail to straighten "
                 "along it. A specimen without branches touches itself there (a fold whose two sides run into one "
                 "another reads as a branch): separate the touching sides in the mask")
    _stage("coverage", timings, t)
    yield Progress("coverage", 1, 1, f"{100 * cov.fraction:.2f} %")
    used = Endpoints(head=tuple(snapped[0][0]), tail=tuple(snapped[-1][1]),
                     chain=tuple((tuple(a), tuple(b)) for a, b in snapped) if len(snapped) > 1 else ())
    return SkeletonResult(
        deformation=deformation, endpoints=used, suggested=suggested, curve=curve / sp, frames=frames,
        twist=theta, keyframe_indices=idx, factor=wm.factor,
        mesh={"parts": mesh_info}, timings=timings, warnings=tuple(notes), min_jacobian=jmin, max_tilt=tilt,
        coverage=cov.fraction, lost=cov.lost, folded=cov.folded, twist_confidence=theta_conf,
        twist_source=twist_source, context=context_given, touching=tuple(touching),
        left_out=float(min(left_out_share, 1.0)), branches=tuple(said), apart=float(apart), bend=float(bend))


def _apart_from_path(wm: Any, curve_w: np.ndarray, deformation: Deformation, sp: np.ndarray,
                     org: np.ndarray) -> tuple[float, int]:
    """The share of the (working) mask in separate parts that the path does not run through (nor pass within two
    working voxels of) and that the straight volume leaves out, and how many such parts hold any of it: another
    specimen in the mask, or a piece of this one cut off by the scan's face (a fin broken off beside the body lies
    in the cage and counts nothing)."""
    labels, n = ndi.label(wm.binary, _STRUCT26)
    if n < 2:
        return 0.0, 0
    idx = np.round(np.asarray(curve_w) / np.asarray(wm.working_spacing, dtype=float)).astype(int)
    off = np.stack(np.meshgrid(*[np.arange(-2, 3)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    near = (idx[:, None, :] + off[None]).reshape(-1, 3)
    near = near[((near >= 0) & (near < np.asarray(labels.shape))).all(axis=1)]
    untouched = np.ones(n + 1, dtype=bool)
    untouched[np.unique(labels[tuple(near.T)])] = False
    untouched[0] = False
    if not untouched.any():
        return 0.0, 0
    apart_labels = labels * untouched[labels]
    vox = np.argwhere(apart_labels)
    outside = ~held_points(deformation, wm.from_working(vox) * sp + org)[0]  # lost as coverage counts a voxel lost
    lost_parts = np.unique(apart_labels[tuple(vox[outside].T)])
    return float(outside.sum() / max(int(wm.binary.sum()), 1)), int(len(lost_parts))


def estimate_deformation(
    mask: Any,
    endpoints: Any = None,
    *,
    spacing: Sequence[float] | float | None = None,
    n_levels: int = 100,
    smoothing_iterations: int = 50,
    cage_radius: float = 10.0,
    estimate_twist: bool = True,
    volume: Any = None,
    **options: Any,
) -> Deformation:
    """Estimate the straightening deformation of a specimen from its mask and its two ends.

    The paper's pipeline (docs/design.md section 4): the mask at a working resolution, connectivity by dilation, a
    tet mesh of the body (a deterministic lattice cut at the mask's isosurface, where the paper has fTetWild on a
    marching-cubes surface; ``tet_mesher="ftetwild"`` for that), the cotangent-Laplacian harmonic function with
    ``u = 0`` at the head and ``u = 1`` at the tail, ``n_levels`` level sets by marching tets with area-weighted
    centroids, smoothing, resampling by arclength, parallel-transport frames and the fewest keyframes (prism
    subdivision).
    Beyond the paper: the twist from the specimen's own cross-sections, suggested endpoints, and the cage and
    end padding from the cross-section extent.

    Parameters
    ----------
    mask : ndarray, dask array or Volume, shape (N0, N1, N2)
        The specimen (nonzero voxels). Only its bounding box is read, box-averaged to at most ``max_side``
        voxels along its longest side.
    endpoints : Endpoints, (head, tail) pair, or None
        Head and tail in full-resolution voxel coordinates (array index order); for a specimen in pieces an
        :class:`~napari_unwind.session.Endpoints` with its ``chain`` of (start, end) pairs, head to tail. A point
        just outside the mask is snapped to the nearest mask voxel (within ``snap_tolerance`` voxels). None: the
        ends of the longest geodesic are suggested, the thicker end taken as the head.
    spacing : float or sequence of 3 float
        Voxel size (axis0, axis1, axis2); optional when ``mask`` is a Volume.
    n_levels : int
        Number of level sets (the paper's k = 100).
    smoothing_iterations : int
        Smoothing iterations (the paper's s = 50).
    cage_radius : float
        Half-size r of the box (voxels) whose corners the keyframes must reproduce within ``tolerance`` voxels
        (the paper's r = 10).
    estimate_twist : bool
        Turn each frame about the curve so ``v`` points dorsal, from the cross-sections' principal axes.
    volume : array, optional
        The scan's intensities (same shape as the mask), used by the twist estimate and endpoint suggestion.
    **options
        ``smoothing`` ("taubin" or the paper's "laplacian"), ``level_spacing`` ("arclength" or the paper's
        "uniform"), ``tolerance`` (1 voxel), ``half_extent`` and ``pad`` (physical; default proposed from the
        cross-sections), ``max_side`` (128), ``snap_tolerance`` (5 voxels), ``up`` (world direction for the first
        frame's v without twist estimation), ``origin``, ``unit``, ``tet_mesher`` ("lattice", the default: the
        deterministic :func:`lattice_tet_mesh` of the working occupancy, about ``lattice_nodes`` (8000) nodes
        inside the body; "ftetwild": the paper's marching cubes + fTetWild, whose mesh varies from run to run
        even on one thread, so its results are not reproducible), ``max_triangles`` (fTetWild only, 3000: the
        marching-cubes surface is decimated to this many triangles before meshing, None for no decimation),
        ``mesher`` (fTetWild only: options of :func:`tet_mesh`, e.g. ``edge_length_fac``) and
        ``end_window_factor`` (2: the curve's ends, over this many times the largest inscribed radius, are
        replaced by a quadratic fit, see :func:`~napari_unwind.skeleton.regularise_ends`; 0 keeps them),
        ``fold_free`` (True: each keyframe's cage fitted per side to the sections there, and inner sides shrunk
        where the Jacobian would fall below ``min_jacobian``, 0.2, the margins only: the tissue's own extent is
        cut only where holding it would take the Jacobian under a quarter of ``min_jacobian``; False: one centred
        cage for the whole body, as before), ``cage_margin`` (0.1: the cage's relative margin; 2 working voxels
        are added besides),
        ``context`` (0: physical units added to every side of the fitted cages and to the end padding, so that
        the straight volume shows what surrounds the specimen; given up where a bend would fold the cage, and
        reported),
        ``dorsal_points`` (points on the dorsal side, full-resolution voxels: the twist turns ``v`` at them and
        changes linearly between, instead of being estimated) or ``dorsal_direction`` (a direction, axis0, axis1,
        axis2, that ``v`` follows wherever the curve crosses it; for a vessel, "anterior"): see
        :func:`~napari_unwind.skeleton._twist.landmark_twist`.

    Returns
    -------
    Deformation

    Raises
    ------
    InvalidInputError
        Empty mask, head = tail, an end too far from the mask, ends in parts that cannot be joined (the message
        names the parts), invalid options.
    """
    gen = estimate_deformation_iter(mask, endpoints, spacing=spacing, n_levels=n_levels,
                                    smoothing_iterations=smoothing_iterations, cage_radius=cage_radius,
                                    estimate_twist=estimate_twist, volume=volume, **options)
    return run(gen).deformation
