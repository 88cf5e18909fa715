"""Candidate specimens: one definition of a specimen, with a reason for every feature that is not one.

:func:`candidates` reads a segmentation (:class:`~._features.Features`) and returns one :class:`Candidate` per
feature (or per part of a feature), each ``"specimen"``, ``"rejected"`` or ``"unresolved"`` (it may be a specimen
but cannot be taken without a click) with a one-line reason. Everything that
decides what a specimen is lives here; :func:`~._features.specimens` (``unwind segment --specimens``) and the
pipeline's ``run --all`` both read it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import ndimage

from .._morphology import depth_map
from ..errors import InvalidInputError
from ._features import Features, FeatureStats, _enclosers

__all__ = ["Candidate", "candidates", "specimen_isovalue", "specimens"]

SPECIMEN = "specimen"
REJECTED = "rejected"
#: A candidate that may be a specimen but is not taken without a click: a curved or coiled tube-like body among
#: other elongated bodies (it may also be two touching at an angle). Not a specimen, and not to be passed over in
#: silence: a run of every specimen that finds one is not a success.
UNRESOLVED = "unresolved"


@dataclass(frozen=True, eq=False)
class Candidate:
    """One candidate specimen: a feature, a part of a feature, or features that make one body.

    Attributes
    ----------
    ids : tuple of int
        The features it is made of (1..k), sorted.
    status : str
        ``"specimen"``, ``"rejected"`` or ``"unresolved"`` (:data:`UNRESOLVED`: it may be a specimen, but only a
        click can say).
    reason : str
        One line: why it was rejected or left unresolved, or how a specimen was made ("" for a plain feature).
    stats : FeatureStats
        Its figures (the feature's own statistics, or those of its mask for a part or a union; ``id`` is
        ``ids[0]``).
    part : int
        0 for whole features; ``1..n_parts`` for one of the touching specimens a feature was split into.
    n_parts : int
        How many parts its features were split into (1 when not split).
    isovalue : float or None
        The isovalue its working mask was cut at (None: the features' own thresholds).
    unclaimed : bool
        True for a body no feature holds (rule 7 of :func:`candidates`): ``ids`` is then the feature whose basin
        holds most of it, not a feature of its own.
    """

    ids: tuple[int, ...]
    status: str
    reason: str
    stats: FeatureStats
    part: int = 0
    n_parts: int = 1
    isovalue: float | None = None
    unclaimed: bool = False
    _box: tuple[int, int, int, int, int, int] | None = field(default=None, repr=False)
    _crop: np.ndarray | None = field(default=None, repr=False)

    @property
    def id(self) -> int:
        """The first (most important) feature id."""
        return int(self.ids[0])

    @property
    def name(self) -> str:
        """A short unique name: ``"3"``, ``"2+5"`` for a union, ``"3.1"`` for part 1 of feature 3."""
        base = "+".join(str(i) for i in self.ids)
        return f"{base}.{self.part}" if self.part else base

    @property
    def is_specimen(self) -> bool:
        return self.status == SPECIMEN

    def working_mask(self, features: Features) -> np.ndarray:
        """Its mask at the features' working resolution (bool, ``features.shape``).

        The union of its features' labels, or, for a part or a body cut at its own isovalue, that mask. Refine it
        to full resolution with :func:`~napari_unwind.segmentation.refine_mask` (``isovalue=self.isovalue``).
        """
        if not isinstance(features, Features):
            raise InvalidInputError(f"working_mask needs the Features the candidate came from, got {type(features)}")
        if self._crop is None:
            return np.isin(features.labels, self.ids)
        box = self._box
        if tuple(box[3:]) > features.shape or any(h > n for h, n in zip(box[3:], features.shape)):
            raise InvalidInputError(f"this candidate's box {box} lies outside the features' shape {features.shape}")
        out = np.zeros(features.shape, dtype=bool)
        out[box[0]:box[3], box[1]:box[4], box[2]:box[5]] = self._crop
        return out


def _number(name: str, value: Any, lo: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a number >= {lo:g}, got {value!r}") from None
    if not np.isfinite(v) or v < lo:
        raise InvalidInputError(f"{name} must be a finite number >= {lo:g}, got {value!r}")
    return v


def _count(name: str, value: Any, lo: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < lo:
        raise InvalidInputError(f"{name} must be an integer >= {lo}, got {value!r}")
    return int(value)


# ------------------------------------------------------------------------------------------------------------------
# geometry helpers (working voxels)
# ------------------------------------------------------------------------------------------------------------------
def _box(mask: np.ndarray, pad: int) -> tuple[slice, ...]:
    """The bounding box of ``mask`` grown by ``pad`` voxels (clipped to the array)."""
    idx = [np.flatnonzero(mask.any(axis=tuple(b for b in range(3) if b != a))) for a in range(3)]
    return tuple(slice(max(int(ix[0]) - pad, 0), min(int(ix[-1]) + 1 + pad, n)) for ix, n in zip(idx, mask.shape))


_OWNED = 0.8  # of a feature's labels in one part: the feature is that part's, its stray pieces follow it
_S26 = np.ones((3, 3, 3), bool)
_REGROW = 24  # working voxels around an unclaimed piece within which what the opening took is grown back (rule 7)
_REGROW_SHARE = 0.1  # of the piece: growing back more than this is not its own tip, and nothing is grown back
_CURVED_MIN_VOXELS = 200  # working voxels: below, no hint is computed
_CURVED_MAX_CHECKS = 3  # rows whose geodesic is computed, the largest first
_CURVED_MIN_SHARE = 0.2  # of the largest row's voxels: smaller rows get no hint
_CURVED_FACTOR = 2.0  # x min_elongation along itself: a clearly curved body, not a lumpy one


# mean cross-section over the largest inscribed disc of a body taken as curved: a tube or a curled fish 1-1.6 (48
# hard phantoms); a curved plate more; a thick body the geodesic wanders through (a chest CT's torso: 0.38) less
_CURVED_SECTION = (0.6, 3.0)
# largest share of a curved body's surface cut through tissue (the voxels just outside it still above its isovalue,
# in another feature's basin) for it to be a specimen: a curled fish, an eel or a vessel is bounded by an intensity
# edge nearly all round; a stretch of a torso's soft tissue, split from the rest at the basins' borders, is not
_CURVED_OPEN = 0.2


def _along_itself(crop: np.ndarray, spacing: np.ndarray) -> tuple[float, float, float]:
    """A body's length along itself (the longest geodesic: two sweeps of Dijkstra on the 26-neighbour graph,
    physical steps), its elongation along itself on the scale of :attr:`FeatureStats.elongation` (that length over
    ``sqrt(3)`` times the largest inscribed radius: a straight cylinder's principal-axes elongation is
    ``L / (sqrt(3) r)``), and its mean cross-section (volume over length) over the largest inscribed disc's area: 1
    for a round tube, 1.7 for a fish's 0.6 ellipse, ``4 w / (pi t)`` for a curved plate ``w`` wide, ``t`` thick.
    A curved or coiled body (a vessel, an eel) is far more elongated along itself than by its principal axes."""
    from ..skeleton._endpoints import _graph, _longest_geodesic  # the 26-neighbour graph, physical edge lengths

    sp = np.asarray(spacing, dtype=float)
    r = float(depth_map(crop, sp).max())
    n = int(np.count_nonzero(crop))
    if n < 2 or r <= 0:
        return 0.0, 0.0, np.inf
    _, b, da = _longest_geodesic(_graph(crop, sp)[0])
    length = float(da[b])
    if length <= 0:
        return 0.0, 0.0, np.inf
    return length / (np.sqrt(3.0) * r), length, n * float(np.prod(sp)) / length / (np.pi * r * r)


def _open_surface(crop: np.ndarray, box: tuple[slice, ...], values: np.ndarray, iso: float) -> float:
    """The share of a body's outer surface (its 6-neighbours outside it, within the scan) that is still above its
    isovalue: where the body was cut from more tissue at a basin's border, not bounded by an intensity edge."""
    lo = [max(b.start - 1, 0) for b in box]
    hi = [min(b.stop + 1, n) for b, n in zip(box, values.shape)]
    big = np.zeros([h - a for a, h in zip(lo, hi)], dtype=bool)
    big[tuple(slice(b.start - a, b.stop - a) for b, a in zip(box, lo))] = crop
    shell = ndimage.binary_dilation(big) & ~big
    n = int(np.count_nonzero(shell))
    if n == 0:
        return 0.0
    return int(np.count_nonzero(shell & (values[tuple(slice(a, h) for a, h in zip(lo, hi))] >= iso))) / n


def _principal(mask: np.ndarray, spacing: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre, eigenvalues (descending) and eigenvectors (columns) of a mask's covariance, physical units,
    the voxel's own extent included (as :attr:`FeatureStats.elongation`)."""
    pts = np.argwhere(mask) * spacing
    centre = pts.mean(axis=0)
    cov = np.cov(pts.T, bias=True).reshape(3, 3) + np.diag(spacing**2 / 12.0)
    ev, vec = np.linalg.eigh(cov)
    return centre, ev[::-1], vec[:, ::-1]


def _hugs_border(mask: np.ndarray, spacing: np.ndarray) -> float:
    """The fraction of a mask's length (along its principal axis) over which it lies on a face of the scan."""
    faces = np.zeros(mask.shape, bool)
    for a in range(3):
        idx = [slice(None)] * 3
        idx[a] = [0, mask.shape[a] - 1]
        faces[tuple(idx)] = True
    on = mask & faces
    if not on.any():
        return 0.0
    centre, _, vec = _principal(mask, spacing)
    t_all = (np.argwhere(mask) * spacing - centre) @ vec[:, 0]
    t_on = (np.argwhere(on) * spacing - centre) @ vec[:, 0]
    lo, hi = float(t_all.min()), float(t_all.max())
    if hi <= lo:
        return 1.0
    bins = np.linspace(lo, hi, 33)  # the length in 32 slabs: the share of slabs where it meets the border
    hit = np.histogram(t_on, bins=bins)[0] > 0
    have = np.histogram(t_all, bins=bins)[0] > 0
    return float(hit.sum() / max(have.sum(), 1))


#: Most voxels :func:`specimen_isovalue` reads from the scan (the box around the features, strided to fit).
SCAN_BUDGET = 1 << 22


def specimen_isovalue(features: Features, ids: Any, *, volume: Any = None) -> float:
    """The isovalue between the medium and a specimen's body: halfway between their levels around features ``ids``.

    The values within a few body thicknesses of the features' labels are histogrammed; the medium is their mode,
    and the body the median of the voxels clearly above the medium (more than 5 noise sigmas, in a component that
    holds the features' labels) two voxels in from their surface (clear of its partial volume): soft tissue, as a
    spine or a bone inside the body is brighter but smaller. The isovalue is halfway between the two (the 50 %
    boundary of CT). Unlike the features' own thresholds (:attr:`FeatureStats.threshold`, which may sit between
    flesh and bone when a bright spine holds the maximum), this keeps the whole body above the medium.

    When the features' labels are only the bright core of their own body (a fish whose flesh touches a tank's
    wall is cut above the saddle where it meets the wall: its spine; the values around the spine are its
    flesh), the levels are read around that body instead: the tissue around the labels is the features' own
    body when at least half of it lies in their basins, and the medium is then the most common value on the
    outer shell of the basins (the rule is ``_own_body``'s; it needs the tree, so features loaded from a label
    file read the levels around their labels only). The soft tissue around a CT's bone spreads over many
    features' basins and stays the medium. When the working values around such a core still show the medium (two
    fish pressed together, each kept as its spine), the scan is read around the body they give (the basins above
    their halfway level, connected to the labels) where it is at least twice the labels.

    With ``volume`` (the scan the features were computed on) the levels are read from the scan itself at full
    resolution, inside the box of the features' labels grown by three body thicknesses (strided when it holds
    more than :data:`SCAN_BUDGET` voxels), the region being the voxels of no other feature: the working level's
    smoothing and downsampling, which darken a thin body's interior (a fish two working voxels wide has no
    voxel at its flesh level there), do not bias it, and the features' tree is not needed (features loaded from
    a label file give the same value, but for labels that are only a body's core, above). Without ``volume``
    the smoothed working values of the features' basins are read (needs the tree).

    Parameters
    ----------
    features : Features
        A segmentation (:func:`segment`, or :func:`load_features` with ``volume``).
    ids : int, sequence of int or Candidate
        The features of one specimen.
    volume : Volume or array_like, optional
        The full-resolution scan (shape ``features.full_shape``).

    Returns
    -------
    float
        An isovalue; the lowest of the features' thresholds when the values show no body above the medium (or,
        without ``volume``, the features were loaded without their tree).

    Raises
    ------
    InvalidInputError
        For something that is not a :class:`Features`, an unknown id or a scan of another shape.
    """
    if not isinstance(features, Features):
        raise InvalidInputError(f"specimen_isovalue needs Features (from segment), got {type(features)}")
    if isinstance(ids, Candidate):
        ids = ids.ids
    ids = [features._check_id(i) for i in np.atleast_1d(np.asarray(ids, dtype=object)).tolist()]
    fallback = float(min(features.stat(i).threshold for i in ids))
    lab = np.isin(features.labels, ids)
    if not lab.any():
        return fallback
    if volume is not None:
        if features.tree is not None and features.feature_of_branch is not None:
            basin_id = features.feature_of_branch[features.tree.branch]
            around = _levels_around(features, ids, lab, basin_id)
            body = _own_body(features, ids, lab, basin_id, around)
            if body is None and around is not None:
                # labels that are a thin core of a body whose surroundings still show the medium (two fish
                # pressed together, each kept as its spine): the scan around the core is mostly flesh, so read
                # it around the body the working levels give (the candidate's body) instead
                box, grown = _working_body(features, ids, lab, basin_id, float(0.5 * (around[0] + around[1])))
                n_lab = np.count_nonzero(lab)
                if n_lab - np.count_nonzero(lab[box]) + np.count_nonzero(grown) >= 2 * n_lab:
                    body = lab.copy()
                    body[box] |= grown
            lab = lab if body is None else body
        levels = _scan_levels(features, ids, lab, volume)
        return fallback if levels is None else float(0.5 * (levels[0] + levels[1]))
    if features.tree is None or features.feature_of_branch is None:
        return fallback
    return _isovalue(features, ids, lab, features.feature_of_branch[features.tree.branch], fallback)


def _scan_levels(features: Features, ids: list[int], lab: np.ndarray, volume: Any,
                 budget: int = SCAN_BUDGET) -> tuple[float, float] | None:
    """:func:`_levels` read from the full-resolution scan (see :func:`specimen_isovalue`)."""
    from ..io._volume import Volume

    data = volume.data if isinstance(volume, Volume) else volume  # numpy, dask or zarr
    if not hasattr(data, "shape"):
        data = np.asarray(data)
    shape = tuple(int(n) for n in getattr(data, "shape", ()))
    if shape != tuple(int(n) for n in features.full_shape):
        raise InvalidInputError(f"the scan has shape {shape}, but these features were computed on a volume of shape "
                                f"{tuple(features.full_shape)}")
    thick = float(depth_map(lab[_box(lab, 0)], (1.0, 1.0, 1.0)).max())  # working voxels
    pad = int(np.ceil(max(4.0, 3.0 * thick)))  # working voxels
    box = _box(lab, pad)
    scale = np.asarray(features.scale, dtype=float)
    lo = [int(np.floor(b.start * s)) for b, s in zip(box, scale)]
    hi = [min(int(np.ceil(b.stop * s)), n) for b, s, n in zip(box, scale, shape)]
    step = 1
    while np.prod([-(-(h - lo_) // step) for lo_, h in zip(lo, hi)]) > budget:
        step += 1
    sl = tuple(slice(a, b, step) for a, b in zip(lo, hi))
    raw = data[sl]
    vals = np.asarray(raw.compute() if hasattr(raw, "compute") else raw, dtype=np.float64)
    # the working masks on the sampled grid (nearest working voxel, as refine_mask upsamples)
    idx = np.ix_(*[np.minimum(np.floor((np.arange(a, b, step) + 0.5) / s).astype(np.int64), n - 1)
                   for a, b, s, n in zip(lo, hi, scale, features.shape)])
    own = lab[idx]
    wdist = ndimage.distance_transform_edt(~lab[box])
    wnear = (wdist <= pad) & np.isin(features.labels[box], [0, *ids])
    origin = [b.start for b in box]
    near = wnear[np.ix_(*[i.ravel() - o for i, o in zip(idx, origin)])]
    return _medium_and_body(vals, near, own=own)


def _working_body(features: Features, ids: list[int], lab: np.ndarray, basin_id: np.ndarray, iso: float
                  ) -> tuple[tuple[slice, ...], np.ndarray]:
    """The features' body at the working level within the box of their basins: the basins' voxels ``>= iso``
    connected to their labels, and the labels (rule 3 of :func:`candidates`). Returns the box and the body in it."""
    basin = basin_id == ids[0] if len(ids) == 1 else np.isin(basin_id, ids)
    box = _box(basin, 0)
    m = basin[box] & (features.tree.values[box] >= iso)
    comp, _ = ndimage.label(m)
    inside = lab[box]
    keep = np.unique(comp[inside])
    return box, np.isin(comp, keep[keep > 0]) | inside


def _isovalue(features: Features, ids: list[int], lab: np.ndarray, basin_id: np.ndarray, fallback: float) -> float:
    levels = _levels(features, ids, lab, basin_id)
    return fallback if levels is None else float(0.5 * (levels[0] + levels[1]))


def _levels(features: Features, ids: list[int], lab: np.ndarray, basin_id: np.ndarray) -> tuple[float, float] | None:
    """The medium around features ``ids`` and their body's level (see :func:`specimen_isovalue`); None when the
    histogram has no second mode. When the labels are only the core of the features' own body
    (:func:`_own_body`), the levels are read around that body instead."""
    levels = _levels_around(features, ids, lab, basin_id)
    body = _own_body(features, ids, lab, basin_id, levels)
    return levels if body is None else _levels_around(features, ids, body, basin_id)


def _levels_around(features: Features, ids: list[int], lab: np.ndarray, basin_id: np.ndarray
                   ) -> tuple[float, float] | None:
    thick = float(depth_map(lab[_box(lab, 0)], (1.0, 1.0, 1.0)).max())  # working voxels
    pad = int(np.ceil(max(4.0, 3.0 * thick)))
    box = _box(lab, pad)
    dist = ndimage.distance_transform_edt(~lab[box])
    near = np.isin(basin_id[box], ids) & (dist <= pad)
    return _medium_and_body(features.tree.values[box], near)


def _own_body(features: Features, ids: list[int], lab: np.ndarray, basin_id: np.ndarray,
              levels: tuple[float, float] | None) -> np.ndarray | None:
    """The features' own body when their labels are only its bright core, else None.

    A fish whose flesh touches a brighter structure (a tank's wall) merges with it in the join tree at its flesh
    level, so its feature (cut above that saddle) is only its spine, and the most common value around the spine
    is its own flesh, not the liquid. The bone of a CT lies in soft tissue the same way, but that tissue is a
    larger body's: it spreads over the basins of many features. So, with ``(m0, m1)`` the levels read around the
    labels (working values): the *lower medium* is the most common value on the outer shell of the features'
    basins (their voxels with a face neighbour in another basin; the scan's faces are not a shell); when it is
    darker than ``m0`` by more than half the contrast ``m1 - m0``, the *tissue* is the connected region of
    voxels from halfway between the lower medium and ``m0`` up to (not including) halfway between ``m0`` and
    ``m1`` that meets the labels (a face neighbour), within the box of the features' basins. When at least half
    of that tissue lies in the features' basins, it is their own body: the returned mask is the tissue inside
    their basins together with the labels (working shape).
    """
    if levels is None:
        return None
    m0, m1 = levels
    if m1 <= m0:
        return None
    basin = np.isin(basin_id, ids)
    box = _box(basin, 0)
    b = basin[box]
    shell = b & ~ndimage.binary_erosion(b, border_value=1)
    vals = features.tree.values[box]
    sv = vals[shell].astype(np.float64)
    if sv.size < 50:
        return None
    lo, hi = np.percentile(sv, [0.5, 99.5])
    lower = _mode(sv, float(lo), float(hi))
    if lower >= m0 - 0.5 * (m1 - m0):
        return None
    band = (vals >= 0.5 * (lower + m0)) & (vals < 0.5 * (m0 + m1))
    comp, _ = ndimage.label(band)
    touch = np.unique(comp[ndimage.binary_dilation(lab[box]) & band])
    tissue = np.isin(comp, touch[touch > 0])
    n = np.count_nonzero(tissue)
    if n == 0 or np.count_nonzero(tissue & b) < 0.5 * n:
        return None
    body = lab.copy()
    body[box] |= tissue & b
    return body


def _medium_and_body(vals: np.ndarray, near: np.ndarray, *, own: np.ndarray | None = None
                     ) -> tuple[float, float] | None:
    """The medium's and the body's levels from the values ``vals`` around a specimen (``near``: where to look;
    ``own``: its labels, whose components alone count as its body); None when the values show no body."""
    v = vals[near].astype(np.float64)
    if v.size < 50:
        return None
    lo, hi = np.percentile(v, [0.5, 99.5])
    if hi <= lo:
        return None
    m0 = _mode(v, lo, hi)  # the medium: the most common value around the specimen
    # its noise, from its lower half down to the valley below its peak (a darker class around it, air or lungs
    # next to a bone near the skin, is another peak, not the medium's noise), and no wider than its peak's half
    # width at half maximum (the smoothed partial volume between air and tissue is a long plateau, not noise)
    low = v[(v <= m0) & (v >= _valley_below(v, lo, hi, m0))]
    sigma = 1.4826 * float(np.median(m0 - low)) if low.size else 0.0
    sigma = min(sigma, _peak_sigma(v, lo, hi))
    # the body: the median of its interior (clearly above the medium, up to two voxels in from its surface, where
    # the partial volume of the surface is gone); soft tissue outweighs a spine or a bone inside it
    above = near & (vals > m0 + max(5.0 * sigma, 0.02 * (hi - m0)))
    if own is not None:
        comp, _ = ndimage.label(above)
        keep = np.unique(comp[own & above])
        above = np.isin(comp, keep[keep > 0])
    core = vals[above]
    for depth in (1, 2):  # as deep as leaves a core
        inner = ndimage.binary_erosion(above, iterations=depth)
        if np.count_nonzero(inner) < max(20, 0.1 * np.count_nonzero(above)):
            break
        core = vals[inner]
    if core.size < 20:
        return None
    return float(m0), float(np.median(core))


#: Depth (working voxels) of the surface layer of a medium's region that :func:`_embedding` reads.
_SHELL_DEPTH = 3
#: Largest bright share of that layer of a larger body (a container's liquid: its wall, most of the layer).
_MAX_SHELL_SHARE = 0.25


def _embedding(features: Features, lab: np.ndarray, m0: float, m1: float) -> tuple[float, float, float, int] | None:
    """Is the medium around a candidate the tissue of a larger body?

    A specimen in a tank lies in a liquid that is either the scan's background itself or, when air is darker
    still, a region bounded by a bright container (its wall). Bones and vessels of a CT lie in soft tissue that is
    far above the scan's background (air, lungs) and bounded by it: skin and lung surfaces, no bright shell. So:
    the background is the mode of the scan's values darker than the medium by more than the candidate's own
    half-contrast (``m0 - (m1 - m0) / 2``; at least 1 % of the scan, else the medium is the background); the
    medium's region is the connected region above halfway between background and medium that holds the
    candidate (pockets of noise filled); its surface layer (:data:`_SHELL_DEPTH` voxels, away from the scan's
    faces, which only cut it) is read for values at least as bright as the candidate's own body (a container's
    wall: glass, a dense tube; a body's skin and lung surfaces are soft tissue, darker than the bone inside).

    Returns
    -------
    (background, bright share, level, most common other feature in the region) or None
        None when the scan has no background darker than the medium, or the region's surface lies on the scan's
        faces only (it cannot be told from a liquid).
    """
    vals = features.tree.values
    contrast = m1 - m0
    if contrast <= 0:
        return None
    dark = vals[vals < m0 - 0.5 * contrast]
    if dark.size < 0.01 * vals.size:
        return None
    lo, hi = np.percentile(dark, [0.5, 99.5])
    bg = _mode(dark, float(lo), float(hi))
    level = 0.5 * (bg + m0)
    comp, _ = ndimage.label(vals >= level)
    own = np.unique(comp[lab])
    region = np.isin(comp, own[own > 0])
    pockets, _ = ndimage.label(~region)
    size = np.bincount(pockets.ravel())
    small = size < max(64, 1e-3 * np.count_nonzero(region))
    small[0] = False
    region |= small[pockets]
    layer = region & ~ndimage.binary_erosion(region, iterations=_SHELL_DEPTH, border_value=1)
    d = _SHELL_DEPTH
    layer[:d], layer[-d:], layer[:, :d], layer[:, -d:], layer[:, :, :d], layer[:, :, -d:] = (False,) * 6
    n = np.count_nonzero(layer)
    if n < 100:
        return None
    share = float(np.count_nonzero(vals[layer] >= m1) / n)
    counts = np.bincount(features.labels[region & ~lab].ravel(), minlength=features.k + 1)
    counts[0] = 0
    return float(bg), share, float(level), int(np.argmax(counts))


def _peak_sigma(v: np.ndarray, lo: float, hi: float, bins: int = 64) -> float:
    """The standard deviation a Gaussian peak at the mode of ``v`` would have, from the half width at half maximum
    of its lower side (in the histogram :func:`_mode` reads; the binning only widens it)."""
    if hi <= lo:
        return float("inf")
    hist = ndimage.gaussian_filter1d(np.histogram(v, bins=bins, range=(lo, hi))[0].astype(float), 1.0)
    j0 = int(np.argmax(hist))
    half = 0.5 * hist[j0]
    j = j0
    while j > 0 and hist[j - 1] > half:
        j -= 1
    if j == 0:
        return float("inf")
    frac = (hist[j] - half) / max(hist[j] - hist[j - 1], 1e-12)  # where it crosses half, between bins j-1 and j
    return float((frac + j0 - j) * (hi - lo) / bins / np.sqrt(2.0 * np.log(2.0)))


def _valley_below(v: np.ndarray, lo: float, hi: float, m0: float, bins: int = 64) -> float:
    """The lowest point of ``v``'s histogram (as :func:`_mode` smooths it) going down from ``m0``: the first local
    minimum below the mode's peak, or ``lo`` when the histogram falls all the way."""
    if hi <= lo:
        return float(lo)
    hist = ndimage.gaussian_filter1d(np.histogram(v, bins=bins, range=(lo, hi))[0].astype(float), 1.0)
    j = min(int((m0 - lo) / (hi - lo) * bins), bins - 1)
    while j > 0 and hist[j - 1] <= hist[j]:
        j -= 1
    return float(lo + j * (hi - lo) / bins)


def _mode(v: np.ndarray, lo: float, hi: float, bins: int = 64) -> float:
    """The mode of ``v`` on ``[lo, hi]`` (a histogram lightly smoothed)."""
    if hi <= lo:
        return float(lo)
    hist = ndimage.gaussian_filter1d(np.histogram(v, bins=bins, range=(lo, hi))[0].astype(float), 1.0)
    return float(lo + (int(np.argmax(hist)) + 0.5) * (hi - lo) / bins)


def _split(body: np.ndarray, spacing: np.ndarray, *, saddle: float, min_share: float) -> tuple[np.ndarray, int]:
    """Touching bodies apart: a watershed of the distance transform seeded by its maxima, regions merged while
    the saddle between them is shallow (``>= saddle`` x the lower of their two peaks) or one is small (below
    ``min_share`` of its neighbour). Returns the part labels (0 outside) and their number."""
    edt = depth_map(body, spacing)
    from skimage.morphology import h_maxima
    from skimage.segmentation import watershed

    h = max(float(spacing.min()), 0.2 * float(edt.max()))
    markers, n = ndimage.label(h_maxima(edt, h) & body, structure=np.ones((3, 3, 3), bool))
    if n <= 1:
        return body.astype(np.int32), int(body.any())
    parts = watershed(-edt, markers, mask=body).astype(np.int32)
    peak = np.asarray(ndimage.maximum(edt, parts, index=np.arange(n + 1)), dtype=float)
    size = np.bincount(parts.ravel(), minlength=n + 1).astype(float)
    pairs: dict[tuple[int, int], list[float]] = {}  # (a, b) -> [highest saddle, contact voxels]
    for a in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[a], hi[a] = slice(None, -1), slice(1, None)
        p, q = parts[tuple(lo)], parts[tuple(hi)]
        sel = (p != q) & (p > 0) & (q > 0)
        if not sel.any():
            continue
        s = np.minimum(edt[tuple(lo)][sel], edt[tuple(hi)][sel])
        for x, y, v in zip(p[sel].tolist(), q[sel].tolist(), s.tolist()):
            key = (min(x, y), max(x, y))
            e = pairs.setdefault(key, [0.0, 0.0])
            e[0] = max(e[0], v)
            e[1] += 1
    root = list(range(n + 1))

    def find(x: int) -> int:
        while root[x] != x:
            root[x] = root[root[x]]
            x = root[x]
        return x

    # shallow saddles first, then small regions into the neighbour they share the most with
    for (x, y), (sad, _) in sorted(pairs.items(), key=lambda kv: -kv[1][0] / max(min(peak[kv[0][0]], peak[kv[0][1]]),
                                                                                   1e-12)):
        rx, ry = find(x), find(y)
        if rx != ry and sad >= saddle * min(peak[rx], peak[ry]):
            root[max(rx, ry)] = min(rx, ry)
            peak[min(rx, ry)] = max(peak[rx], peak[ry])
            size[min(rx, ry)] = size[rx] + size[ry]
    changed = True
    while changed:
        changed = False
        contact: dict[tuple[int, int], float] = {}
        for (x, y), (_, c) in pairs.items():
            rx, ry = find(x), find(y)
            if rx != ry:
                key = (min(rx, ry), max(rx, ry))
                contact[key] = contact.get(key, 0.0) + c
        for r in sorted({find(x) for x in range(1, n + 1)}, key=lambda r: size[r]):
            nbrs = [(c, b if a == r else a) for (a, b), c in contact.items() if r in (a, b)]
            if not nbrs:
                continue
            c, other = max(nbrs)
            if size[r] < min_share * size[other]:
                root[r] = other
                size[other] += size[r]
                changed = True
                break
    lut = np.array([find(x) for x in range(n + 1)])
    roots = np.unique(lut[1:])
    relabel = np.zeros(n + 1, dtype=np.int32)
    relabel[roots] = np.arange(1, len(roots) + 1)
    return relabel[lut][parts], int(len(roots))


def _split_by_features(parts: np.ndarray, n: int, labels: np.ndarray, stats: dict[int, FeatureStats],
                       spacing: np.ndarray, min_elongation: float,
                       basins: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Parts that hold two or more bodies of their own, apart: a part in which several features are each elongated,
    mostly inside it and at least half as large as the largest of them (two fish lying side by side along their
    length, which the distance transform's saddle does not part) is split by a watershed of its distance
    transform seeded by those features' labels. A spine and a head bone of one fish (a small second feature) stay
    one part. A feature's size is the part's tissue in its basin (``basins``: the feature owning each voxel's
    join-tree branch) where given, else its labels in the part: the join tree may keep only a fish's bright core
    as its feature's labels (a fifth of the fish) while its basin holds the whole fish. Returns the new part
    labels and their number."""
    from skimage.segmentation import watershed

    out = np.zeros_like(parts)
    m = 0
    for q in range(1, n + 1):
        part = parts == q
        ids, counts = np.unique(labels[part], return_counts=True)
        own = {int(f): int(c) for f, c in zip(ids, counts) if f > 0 and c >= 0.5 * stats[int(f)].voxel_count
               and stats[int(f)].elongation >= min_elongation}
        if basins is not None and len(own) > 1:
            tissue = np.bincount(basins[part].ravel(), minlength=max(own) + 1)
            own = {f: int(tissue[f]) if f < len(tissue) else 0 for f in own}
        big = [f for f, c in own.items() if c >= 0.5 * max(own.values())] if own else []
        if len(big) < 2:
            m += 1
            out[part] = m
            continue
        markers = np.zeros(parts.shape, np.int32)
        for j, f in enumerate(big, start=1):
            markers[part & (labels == f)] = j
        edt = depth_map(part, spacing)
        sub = watershed(-edt, markers, mask=part)
        for j in range(1, len(big) + 1):
            m += 1
            out[sub == j] = m
    return out, m


def _parts_follow_features(parts: np.ndarray, n: int, labels: np.ndarray) -> np.ndarray:
    """Where the distance transform's split and the features disagree, the feature decides: a piece of a part
    that is a feature's labels (a connected piece, 26-neighbours) while that feature lies mostly (at least
    :data:`_OWNED` of its labels) in another part that the piece touches goes to that part. The distance
    transform has no saddle where a thin tail lies along a thick neighbour (the two bodies' union is as deep there
    as the neighbour), so its watershed gives the tail to the neighbour; the join tree's features follow each
    body's own intensities and keep the tail with its fish. A feature split between parts (two fish in one
    feature) moves nothing. What a move leaves apart from its part's main piece goes to the part it touches
    most. Returns the new part labels (``n`` parts still)."""
    if n < 2:
        return parts
    out = parts.copy()
    inside = np.where(parts > 0, labels, 0)
    moved = False
    for f, box in enumerate(ndimage.find_objects(inside), start=1):
        if box is None:
            continue
        # the feature's box and one voxel around it: its pieces and every voxel they touch
        box = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
        lab = inside[box] == f
        where = np.bincount(parts[box][lab], minlength=n + 1)
        owner = int(np.argmax(where))
        if where[owner] < _OWNED * where.sum() or where[owner] == where.sum():
            continue
        sub = out[box]  # a view: moves are written to ``out``
        stray, m = ndimage.label(lab & (sub != owner), structure=_S26)
        if not m:
            continue
        near = ndimage.binary_dilation(sub == owner, structure=_S26)
        touching = np.unique(stray[near & (stray > 0)])
        if len(touching):
            sub[np.isin(stray, touching)] = owner
            moved = True
    if not moved:
        return out
    for q in range(1, n + 1):  # what a move left apart from its part's main piece
        pieces, m = ndimage.label(out == q, structure=_S26)
        if m < 2:
            continue
        sizes = np.bincount(pieces.ravel())[1:]
        for j in np.flatnonzero(sizes < sizes.max()) + 1:
            piece = pieces == j
            ring = ndimage.binary_dilation(piece, structure=_S26) & ~piece & (out > 0) & (out != q)
            if ring.any():
                out[piece] = int(np.bincount(out[ring]).argmax())
    return out


def _part_stats(features: Features, template: FeatureStats, mask: np.ndarray, iso: float | None,
                spacing: np.ndarray) -> FeatureStats:
    """The figures of a body or a part (its own voxels, box, values, elongation, border)."""
    box = _box(mask, 0)
    lo = np.array([b.start for b in box])
    hi = np.array([b.stop for b in box])
    scale = np.asarray(features.scale)
    full = np.asarray(features.full_shape)
    values = features.tree.values if features.tree is not None else None
    vals = values[mask] if values is not None else None
    if vals is not None and vals.size:
        flat = int(np.argmax(np.where(mask[box], values[box], -np.inf)))
        mx = tuple(int(v) for v in np.add(np.unravel_index(flat, mask[box].shape), lo))
    else:
        mx = template.max_position
    _, ev, _ = _principal(mask[box], spacing)  # in its box: the same covariance
    return replace(
        template,
        voxel_count=int(np.count_nonzero(mask)),
        bbox=tuple(int(v) for v in (*lo, *hi)),
        bbox_full=tuple(int(v) for v in (*np.minimum(np.floor(lo * scale), full), *np.minimum(np.ceil(hi * scale),
                                                                                                full))),
        value_min=float(vals.min()) if vals is not None and vals.size else template.value_min,
        value_max=float(vals.max()) if vals is not None and vals.size else template.value_max,
        threshold=float(iso) if iso is not None else template.threshold,
        max_position=mx,
        max_position_full=tuple(int(min(np.floor(c * sc), n - 1)) for c, sc, n in zip(mx, scale, full)),
        elongation=float(np.sqrt(ev[0] / ev[1])),
        touches_border=bool(np.any(lo == 0) or np.any(hi == np.asarray(mask.shape))),
        container=False,
    )


# ------------------------------------------------------------------------------------------------------------------
# the definition
# ------------------------------------------------------------------------------------------------------------------
def candidates(
    features: Features,
    *,
    min_elongation: float = 3.0,
    min_voxels: int = 1,
    min_size_fraction: float = 0.1,
    min_length_fraction: float = 0.2,
    max_border_share: float = 0.5,
    split_saddle: float = 0.6,
    body: bool = True,
    embedded: bool = True,
) -> tuple[Candidate, ...]:
    """Every feature as a candidate specimen, kept or rejected with its reason: the one definition of a specimen.

    The rules, in order (each rejection's ``reason`` names the rule and its figures):

    1. **Container**: a feature that encloses others (around another feature's maximum it is met on both sides
       along both axes of a plane: a tube, a dish) -- ``"container: encloses features 2, 3"``.
    2. **Wall arc**: a feature that lies on a face of the scan over more than ``max_border_share`` of its length
       (a tube wall that the field of view cuts into arcs runs along the faces it is cut by) -- ``"wall arc cut by
       the field of view"``. A specimen cut by a face only meets it at its cut end: touching the border is not a
       container's mark.
    3. **Body**: each other feature's body is its basin above :func:`specimen_isovalue` (between the medium and
       the soft body, not the bright spine), connected to its labels. Bodies that meet are one group (a spine and
       a head bone of one fish, or two touching fish).
    4. **Split**: a group is split by a watershed of its distance transform seeded by its maxima; regions whose
       saddle is shallow (``>= split_saddle`` x the lower peak) or that are small (under a fifth of a
       neighbour) merge back. A part that still holds several features that are each elongated, mostly inside it
       and at least half as large as the largest of them by the part's tissue in their basins (two fish side by
       side along their length, even where the join tree kept only one fish's bright core as its feature) is split
       again by a watershed of its distance transform seeded by those features' labels. Each part is a candidate
       (``part`` 1..``n_parts``), with the features it holds as ``ids`` -- ``"touching specimens: split into 2 at
       the distance transform's saddle"``.
    5. **Size and shape** of each part: ``"too small: 40 voxels < 200"`` (under ``min_voxels`` or
       ``min_size_fraction`` of the largest elongated part), ``"not elongated: 1.6 < 3"``, ``"too short: ..."`` (its
       length, 4 standard deviations along its principal axis, under ``min_length_fraction`` of the scan's
       largest side). A part not elongated by its principal axes but at least twice ``min_elongation`` along
       itself (its longest geodesic over ``sqrt(3)`` times its largest inscribed radius; computed for the three
       largest such parts) is a curved or coiled body (a vessel, an eel, a curled fish): it is a specimen --
       ``"curved or coiled: 1.3 by its principal axes, 15 along itself"`` -- when it is tube-like (its mean
       section, volume over that length, 0.6-3 times its largest inscribed disc), the scan's faces do not cut it,
       an intensity edge bounds it nearly all round (at most a fifth of the voxels just outside it are still above
       its isovalue: a stretch of a torso's soft tissue, split from the rest where the basins meet, is not) and
       nothing else of a fifth of its size is elongated by its principal axes. Its length is then the
       geodesic's. A tube-like, bounded one that the faces do not cut but that lies among such elongated bodies (it
       may be two of them touching at an angle) is ``"unresolved"``: not taken, and not passed over in silence (a run of
       every specimen that meets one is not a success); its reason says what to do (select it, or give its
       mask). Any other is rejected, its ``"not elongated"`` reason saying why.
    6. **Embedded** (a part that passed 1-5, or a curved one that would be unresolved): ``"part of a larger body:
       embedded in feature 1's tissue; ..."`` when its medium (the most common value around it, as
       :func:`specimen_isovalue` measures) is itself the tissue of a larger body: the scan holds a background darker
       than that medium by more than the candidate's own half-contrast (air, lungs), and the connected region above
       halfway between the two that holds the candidate is bounded by that background, not by a bright container
       (under a quarter of its surface layer, three voxels deep and away from the scan's faces, is as bright as the
       candidate's body). A rib or a vertebra in a CT lies in soft tissue bounded by skin and lungs; a fish lies in
       a liquid that is either the scan's background or held by a tube's wall.
    7. **Unclaimed tissue**: a body that no feature holds is still a candidate. The join tree can merge a specimen
       into a brighter neighbour when the specimen's flesh meets it at the flesh's own level (a fish pressed
       against a dense, noisy wall: its branch is then no higher above that saddle than the wall's noise, and it
       is pruned into the wall's feature). The tissue above the specimens' isovalue (the median feature's) that
       lies two voxels clear of every candidate's mask and every feature's labels -- and of what is brighter than
       a body and connected to a rejected feature's labels, the rest of a dense wall -- is opened, and each piece
       of at least the size floor whose median level is that of a body (not more than 1.5 times the contrast
       over the medium) gets back what the opening took from it within that clear tissue (a thin tail's tip;
       within ``_REGROW`` voxels of the piece), is grown back over the two voxels and split as in rule 4. Each
       part is named after the feature whose basin holds most of it (``"1.1"``) and goes through rules 5-6 --
       ``"tissue outside every feature's labels, in feature 1's basin: ..."``.

    Parameters
    ----------
    features : Features
        A segmentation (:func:`segment`, :meth:`JoinTree.simplify` or :func:`load_features`). Without its tree
        (loaded from a label file) the bodies are the labels themselves.
    min_elongation : float
        Smallest principal-axis ratio of a specimen (default 3: a fish is about 6, a tube about 2, a blob 1-2).
    min_voxels : int
        Smallest voxel count of a specimen at working resolution (default 1).
    min_size_fraction : float
        Smallest voxel count as a fraction of the largest elongated part's (default 0.1: fragments, noise).
    min_length_fraction : float
        Smallest length as a fraction of the scan's largest physical side (default 0.2: bone fragments of a
        chest CT, specks).
    max_border_share : float
        Largest share of its length over which a specimen may lie on a face of the scan (default 0.5).
    split_saddle : float
        Saddle depth that keeps two distance-transform cores apart (default 0.6; 0 never splits).
    body : bool
        Cut each specimen at :func:`specimen_isovalue` (default); False keeps the features' labels.
    embedded : bool
        Apply rule 6 (default; needs the features' tree and ``body``): reject candidates embedded in a larger body.

    Returns
    -------
    tuple of Candidate
        Specimens and rejected candidates by their first feature id; every feature is in at least one
        (a split feature in each of its parts). A candidate's :meth:`Candidate.working_mask` is its mask at the
        working level, :attr:`Candidate.isovalue` the full-resolution isovalue to refine it at.

    Raises
    ------
    InvalidInputError
        For something that is not a :class:`Features` or a bad option (the message holds the value received).
    """
    if not isinstance(features, Features):
        raise InvalidInputError(f"candidates needs Features (from segment or load_features), got {type(features)}")
    min_elongation = _number("min_elongation", min_elongation, 1.0)
    min_voxels = _count("min_voxels", min_voxels, 1)
    min_size_fraction = _number("min_size_fraction", min_size_fraction, 0.0)
    min_length_fraction = _number("min_length_fraction", min_length_fraction, 0.0)
    max_border_share = _number("max_border_share", max_border_share, 0.0)
    split_saddle = _number("split_saddle", split_saddle, 0.0)
    if min_size_fraction > 1 or min_length_fraction > 1 or max_border_share > 1 or split_saddle > 1:
        bad = [f"{n} = {v!r}" for n, v in (("min_size_fraction", min_size_fraction), ("min_length_fraction",
               min_length_fraction), ("max_border_share", max_border_share), ("split_saddle", split_saddle)) if v > 1]
        raise InvalidInputError(f"fractions must lie in [0, 1], got {', '.join(bad)}")
    if not isinstance(body, (bool, np.bool_)):
        raise InvalidInputError(f"body must be True or False, got {body!r}")
    if not isinstance(embedded, (bool, np.bool_)):
        raise InvalidInputError(f"embedded must be True or False, got {embedded!r}")

    spacing = np.asarray(features.spacing, dtype=float)
    labels = features.labels
    stats = {s.id: s for s in features.stats}
    out: list[Candidate] = []

    # 1-2: containers and wall arcs
    enclosed: dict[int, list[int]] = {}
    enc = _enclosers(labels, features.k, [s.max_position for s in features.stats])
    if enc.any():
        for g in features.stats:  # which features each container encloses, for the reason
            for f in np.flatnonzero(_enclosers_of(labels, g)).tolist():
                enclosed.setdefault(f, []).append(g.id)
    rest: list[int] = []
    for s in features.stats:
        if s.voxel_count == 0:
            out.append(Candidate((s.id,), REJECTED, "empty: no voxel above its threshold", s))
        elif enc[s.id]:
            inside = sorted(enclosed.get(s.id, []))
            what = f"encloses feature{'s' if len(inside) > 1 else ''} {', '.join(map(str, inside))}" if inside \
                else "encloses other features"
            out.append(Candidate((s.id,), REJECTED, f"container: {what}", s))
        elif s.voxel_count < min_voxels:
            out.append(Candidate((s.id,), REJECTED, f"too small: {s.voxel_count} voxels < {min_voxels}", s))
        else:
            share = _hugs_border(labels == s.id, spacing) if s.touches_border else 0.0
            if share > max_border_share:
                out.append(Candidate((s.id,), REJECTED, f"wall arc cut by the field of view: it lies on a face of the "
                                     f"scan along {100 * share:.0f} % of its length", s))
            else:
                rest.append(s.id)

    # 3: bodies
    use_body = body and features.tree is not None and features.feature_of_branch is not None
    basin_id = features.feature_of_branch[features.tree.branch] if use_body else None
    iso_of: dict[int, float | None] = {}
    levels_of: dict[int, tuple[float, float] | None] = {}
    union = np.zeros(labels.shape, bool)
    body_of: dict[int, tuple[tuple[slice, ...], np.ndarray]] = {}
    for f in rest:
        lab = labels == f
        if use_body:
            lv = _levels(features, [f], lab, basin_id)
            levels_of[f] = lv
            iso = stats[f].threshold if lv is None else float(0.5 * (lv[0] + lv[1]))
            iso_of[f] = iso
            box, m = _working_body(features, [f], lab, basin_id, iso)
        else:
            iso_of[f] = None
            box = _box(lab, 0)
            m = lab[box]
        body_of[f] = (box, m)
        union[box] |= m

    # 4: groups and parts
    groups, n_groups = ndimage.label(union)
    parts_all = np.zeros(labels.shape, np.int32)
    part_info: list[tuple[int, int, int]] = []  # (part label, group, part index within the group)
    n_parts_of: dict[int, int] = {}
    for gi, sl in enumerate(ndimage.find_objects(groups), start=1):
        if sl is None:
            continue
        g = groups[sl] == gi
        if split_saddle > 0:
            parts, n = _split(g, spacing, saddle=split_saddle, min_share=0.2)
            parts, n = _split_by_features(parts, n, labels[sl], stats, spacing, min_elongation,
                                          None if basin_id is None else basin_id[sl])
            parts = _parts_follow_features(parts, n, labels[sl])
        else:
            parts, n = g.astype(np.int32), 1
        base = len(part_info)
        sub = parts_all[sl]
        sub[parts > 0] = parts[parts > 0] + base
        n_parts_of[gi] = n
        part_info.extend((base + p, gi, p) for p in range(1, n + 1))
    scan_side = float(np.max(np.asarray(labels.shape) * spacing))

    # which features each part holds: its own labels' majority, or a quarter of a feature
    overlap = np.zeros((len(part_info) + 1, features.k + 1), dtype=np.int64)
    np.add.at(overlap, (parts_all.ravel(), labels.ravel().astype(np.int64)), 1)
    members: dict[int, list[int]] = {p: [] for p, _, _ in part_info}
    placed: set[int] = set()
    for f in rest:
        col = overlap[1:, f]
        if col.sum() == 0:
            continue
        best = int(np.argmax(col)) + 1
        for p in range(1, len(part_info) + 1):
            if p == best or col[p - 1] >= 0.25 * stats[f].voxel_count:
                members[p].append(f)
                placed.add(f)
    for f in rest:
        if f not in placed:
            out.append(Candidate((f,), REJECTED, "no body above the medium's isovalue", stats[f]))

    # 5: size and shape of every part (the size floor is a fraction of the largest elongated part)
    rows = []
    for p, gi, idx in part_info:
        ids = tuple(sorted(members[p]))
        if not ids:  # a part with no feature's labels in it: a fragment of a body
            continue
        mask = parts_all == p
        box = _box(mask, 0)
        isos = [iso_of[f] for f in ids if iso_of[f] is not None]
        iso = float(min(isos)) if isos else None
        st = _part_stats(features, stats[ids[0]], mask, iso, spacing)
        _, ev, _ = _principal(mask[box], spacing)
        rows.append((p, gi, idx, ids, box, mask[box], iso, st, 4.0 * float(np.sqrt(ev[0]))))
    floor = max(min_voxels, min_size_fraction * max([r[7].voxel_count for r in rows
                                                     if r[7].elongation >= min_elongation], default=0))
    unclaimed, unclaimed_levels = _unclaimed_rows(features, out, rows, body_of, iso_of, levels_of, basin_id, spacing,
                                                  split_saddle, len(part_info), floor)
    rows += unclaimed
    largest = max([r[7].voxel_count for r in rows if r[7].elongation >= min_elongation], default=0)
    out_names = {i: "+".join(map(str, r[3])) for r in rows for i in r[3]}  # a feature's body, for the reason
    size_floor = max(min_voxels, int(np.ceil(min_size_fraction * largest)))
    # the geodesic of the largest few features' bodies that are not elongated by their principal axes (bounded,
    # not exhaustive; not the unclaimed pieces: in a noisy scan those are mostly specks of the medium)
    biggest = max([r[7].voxel_count for r in rows], default=0)
    curved_check = {r[0] for r in sorted((r for r in rows if r[7].elongation < min_elongation and r[1] >= 0
                                          and r[7].voxel_count >= max(size_floor, _CURVED_MIN_VOXELS,
                                                                      _CURVED_MIN_SHARE * biggest)),
                                         key=lambda r: -r[7].voxel_count)[:_CURVED_MAX_CHECKS]}
    for _p, gi, idx, ids, box, crop, iso, st, length in rows:
        n = n_parts_of[gi] if gi > 0 else 1
        # a curved or coiled body (a vessel, an eel, a curled fish): not elongated by its principal axes, but along
        # itself; a specimen when it is tube-like (not a curved plate, nor a thick body the geodesic wanders through),
        # the scan's faces do not cut it (a torso cut by a CT's field of view is as long along itself), an intensity
        # edge bounds it nearly all round (a stretch of a torso's soft tissue is split from the rest where basins
        # meet) and nothing else in the scan of a fifth of its size is elongated by its principal axes (alone in
        # its scan: among other specimens it could be two touching at an angle)
        geo, curve_len, section = (_along_itself(crop, spacing) if _p in curved_check and st.voxel_count >= size_floor
                                   and st.elongation < min_elongation else (0.0, 0.0, np.inf))
        curved = geo >= _CURVED_FACTOR * min_elongation
        tube_like = _CURVED_SECTION[0] <= section <= _CURVED_SECTION[1]
        cut = any(b.start == 0 or b.stop == m for b, m in zip(box, labels.shape))  # by the field of view
        opened = (_open_surface(crop, box, features.tree.values, iso)
                  if curved and tube_like and features.tree is not None and iso is not None else 0.0)
        bounded = opened <= _CURVED_OPEN  # by an intensity edge, not cut from more tissue
        specimen_like = curved and tube_like and not cut and bounded
        taken = specimen_like and largest < _CURVED_MIN_SHARE * st.voxel_count
        unresolved = specimen_like and not taken  # among elongated bodies: a click must say (unless rule 6 rejects)
        if taken:
            length = curve_len  # its length along itself, not its principal axis's extent
        # rule 6 reads the features' isovalues and levels (unclaimed tissue: its own)
        own_isos, own_levels = ({ids[0]: iso}, {ids[0]: unclaimed_levels}) if gi < 0 else (iso_of, levels_of)
        if st.voxel_count < size_floor:
            why = f"too small: {st.voxel_count} voxels < {size_floor}"
            if size_floor > min_voxels:
                why += f" ({100 * min_size_fraction:g} % of the largest elongated candidate, {largest})"
        elif st.elongation < min_elongation and not taken:
            why = f"not elongated: {st.elongation:.2g} < {min_elongation:g}"
            if curved:
                what = ("a curved or coiled body (a vessel, an eel) cut by the scan's faces, as a CT's view cuts a "
                        "torso"
                        if tube_like and cut else
                        f"curved, but {100 * opened:.0f} % of its surface is cut from more tissue at least as bright "
                        "(a stretch of a larger body's soft tissue), not bounded by an edge all round"
                        if tube_like and not bounded else
                        "a curved or coiled body (a vessel, an eel, a curled fish), or two bodies touching at an "
                        "angle: among other elongated bodies it is not taken without a click"
                        if tube_like else
                        f"a curved plate (its mean section {section:.2g} x its largest inscribed disc)"
                        if section > _CURVED_SECTION[1] else
                        f"a thick body with thin parts, not a tube (its mean section {section:.2g} x its largest "
                        "inscribed disc)")
                why += (f" by its principal axes, but {geo:.2g} along itself: {what}; to straighten it, select it "
                        "(--select A0,A1,A2) or give its mask")
                if unresolved and embedded and use_body:  # rule 6 before "unresolved": a rib
                    inside = _embedded_reason(features, ids, box, crop, own_isos, own_levels, out_names)
                    if inside:
                        why, unresolved = inside, False
        elif length < min_length_fraction * scan_side:
            why = (f"too short: length {length:.3g} < {100 * min_length_fraction:g} % of the scan's largest side "
                   f"({scan_side:.3g})")
        elif embedded and use_body:
            why = _embedded_reason(features, ids, box, crop, own_isos, own_levels, out_names)
        else:
            why = ""
        if gi < 0:
            note = (f"tissue outside every feature's labels, in feature {ids[0]}'s basin: a body the join tree merged "
                    f"into a brighter neighbour")
        elif n > 1:
            note = f"touching specimens: split into {n} at the distance transform's saddle (part {idx})"
        elif len(ids) > 1:
            note = f"features {', '.join(map(str, ids))} make one body"
        else:
            note = ""
        if taken:
            note = (f"curved or coiled: {st.elongation:.2g} by its principal axes, {geo:.2g} along itself"
                    + (f"; {note}" if note else ""))
        reason = f"{why}; {note}" if why and note else (why or note)
        corners = tuple(int(v) for v in (*[b.start for b in box], *[b.stop for b in box]))
        status = SPECIMEN if not why else UNRESOLVED if unresolved else REJECTED
        if status == UNRESOLVED:  # where to click: its deepest voxel, full-resolution index coordinates
            deep = np.unravel_index(int(np.argmax(ndimage.distance_transform_edt(crop, sampling=spacing))),
                                    crop.shape)
            at = [min(int(np.floor((b.start + d + 0.5) * sc)), m - 1)
                  for b, d, sc, m in zip(box, deep, features.scale, features.full_shape)]
            reason += f" (a point inside it: {','.join(map(str, at))})"
        out.append(Candidate(ids, status, reason, st, part=idx if n > 1 or gi < 0 else 0,
                             n_parts=n, isovalue=iso, unclaimed=gi < 0, _box=corners,
                             _crop=np.ascontiguousarray(crop)))
    # a feature whose labels lie in two bodies gives two whole candidates: number them, so that every name (and
    # every output file named after it) is unique
    seen: dict[tuple[int, ...], list[int]] = {}
    for i, c in enumerate(out):
        if c.part == 0:
            seen.setdefault(c.ids, []).append(i)
    for same in seen.values():
        if len(same) > 1:
            top = max([c.part for c in out if c.ids == out[same[0]].ids], default=0)
            for j, i in enumerate(same, start=top + 1):
                out[i] = replace(out[i], part=j)
    out.sort(key=lambda c: (c.ids[0], c.part))
    return tuple(out)


def _unclaimed_rows(features: Features, out: list[Candidate], rows: list[tuple], body_of: dict, iso_of: dict,
                    levels_of: dict, basin_id: np.ndarray | None, spacing: np.ndarray, split_saddle: float,
                    n_parts: int, floor: float) -> tuple[list[tuple], tuple[float, float] | None]:
    """Rule 7's bodies: tissue above the specimens' isovalue that no candidate holds (see :func:`candidates`),
    in pieces of at least ``floor`` voxels (smaller ones are specks, not candidates).

    Returns rows like :func:`candidates`' own, with the group ``-1`` and a part number after every part of the
    same first feature, so that each name is unique, and the levels (medium, body) they were cut at: those of the
    feature whose isovalue is the median of all features' (rule 6 reads them)."""
    with_levels = sorted((v, f) for f, v in iso_of.items() if v is not None and levels_of.get(f) is not None)
    if basin_id is None or not with_levels:
        return [], None
    iso, median_feature = with_levels[(len(with_levels) - 1) // 2]
    levels = levels_of[median_feature]
    m0, m1 = levels
    values = features.tree.values
    claimed = features.labels > 0
    rejected = np.zeros(claimed.shape, bool)
    for c in out:  # rejected so far: their labels (containers, wall arcs, empty features)
        rejected |= c.working_mask(features)
    # and what is brighter than a body and connected to them (a dense wall's noise leaves much of it below its
    # feature's threshold)
    bright, _ = ndimage.label(values >= m1 + 0.5 * (m1 - m0))
    hit = np.unique(bright[rejected])
    claimed |= rejected | np.isin(bright, hit[hit > 0])
    for box, m in body_of.values():
        claimed[box] |= m
    tissue = values >= iso
    # two voxels clear of everything claimed (the partial volume of a neighbour's edge), opened (its slivers)
    clear = tissue & ~ndimage.binary_dilation(claimed, iterations=2)
    left = ndimage.binary_opening(clear)
    comp, n = ndimage.label(left)
    if n == 0:
        return [], levels
    clear_lab, _ = ndimage.label(clear)
    sizes = np.bincount(comp.ravel(), minlength=n + 1)
    used: dict[int, int] = {}
    for r in rows:
        used[r[3][0]] = max(used.get(r[3][0], 0), r[2])
    extra = []
    # grown back over the two voxels it was cut clear by, through unclaimed tissue no brighter than a body
    core = tissue & ~claimed & (values < m1 + 0.5 * (m1 - m0))
    for i, sl in enumerate(ndimage.find_objects(comp), start=1):
        if sl is None or sizes[i] < floor:
            continue
        if np.median(values[sl][comp[sl] == i]) - m0 > 1.5 * (m1 - m0):
            continue  # the unlabelled rest of a brighter structure (a dense wall), not a body
        # what the opening took from its own tissue (a thin tail's tip) back: the clear tissue it lies in, within
        # _REGROW voxels of its box, when that is a small part of it
        near = tuple(slice(max(a.start - _REGROW, 0), min(a.stop + _REGROW, n)) for a, n in zip(sl, comp.shape))
        piece = comp[near] == i
        own = np.unique(clear_lab[near][piece])
        grown = np.isin(clear_lab[near], own[own > 0])
        if np.count_nonzero(grown) > (1.0 + _REGROW_SHARE) * sizes[i]:
            grown = piece  # more than a tip: the web of the medium's noise, or a wall's rim, which the opening cut
        # then in its box, three voxels wider than the two it may grow by (a noisy scan has hundreds of pieces: the
        # whole volume for each took 10 minutes on a 110^3 scan)
        big = tuple(slice(b.start + t.start, b.start + t.stop) for b, t in zip(near, _box(grown, 3)))
        piece = grown[tuple(slice(b.start - a.start, b.stop - a.start) for a, b in zip(near, big))]
        piece = ndimage.binary_dilation(piece, iterations=2, mask=core[big]) | piece
        parts, k = _split(piece, spacing, saddle=split_saddle, min_share=0.2) if split_saddle > 0 else (
            piece.astype(np.int32), 1)
        for q in range(1, k + 1):
            mask = np.zeros(comp.shape, bool)
            mask[big] = parts == q
            owners, counts = np.unique(basin_id[mask], return_counts=True)
            counts[owners == 0] = 0
            if not counts.any():
                continue
            owner = int(owners[int(np.argmax(counts))])
            used[owner] = used.get(owner, 0) + 1
            box = _box(mask, 0)
            st = _part_stats(features, features.stat(owner), mask, iso, spacing)
            _, ev, _ = _principal(mask[box], spacing)
            extra.append((n_parts + len(extra) + 1, -1, used[owner], (owner,), box, mask[box], iso, st,
                          4.0 * float(np.sqrt(ev[0]))))
    return extra, levels


def _embedded_reason(features: Features, ids: tuple[int, ...], box: tuple[slice, ...], crop: np.ndarray,
                     iso_of: dict[int, float | None], levels_of: dict[int, tuple[float, float] | None],
                     names: dict[int, str]) -> str:
    """Rule 6's reason for a candidate embedded in a larger body ("" when it is not, or it cannot be told)."""
    isos = [(iso_of[f], f) for f in ids if iso_of[f] is not None and levels_of.get(f) is not None]
    if not isos:
        return ""
    m0, m1 = levels_of[min(isos)[1]]
    lab = np.zeros(features.shape, bool)
    lab[box] = crop
    found = _embedding(features, lab, m0, m1)
    if found is None:
        return ""
    bg, share, _level, host = found
    if share > _MAX_SHELL_SHARE:
        return ""
    where = f"feature {host}'s tissue" if host else "a larger body's tissue"
    if host and names.get(host, str(host)) != str(host):
        where += f" (candidate {names[host]})"
    return (f"part of a larger body: embedded in {where}; its medium ({m0:.4g}) lies far above the scan's "
            f"background ({bg:.4g}) and is bounded by it, not by a container ({100 * share:.0f} % of its surface "
            f"layer is as bright as this candidate's body)")


def _enclosers_of(labels: np.ndarray, g: FeatureStats) -> np.ndarray:
    """Which features enclose the maximum of feature ``g`` (the rule of :func:`._features._enclosers`)."""
    k = int(labels.max())
    enc = np.zeros(k + 1, dtype=bool)
    m = g.max_position
    halves = []
    for a in range(3):
        idx = list(m)
        idx[a] = slice(None)
        line = labels[tuple(idx)]
        halves.append((set(np.unique(line[: m[a]]).tolist()), set(np.unique(line[m[a] + 1:]).tolist())))
    for a in range(3):
        b, c = [x for x in range(3) if x != a]
        for f in (halves[b][0] & halves[b][1] & halves[c][0] & halves[c][1]) - {0, g.id}:
            enc[f] = True
    return enc


def specimens(features: Features, *, min_elongation: float = 3.0, min_voxels: int = 1) -> tuple[FeatureStats, ...]:
    """The specimen-like features: the statistics of the specimen candidates of :func:`candidates`.

    Parameters
    ----------
    features : Features
        A segmentation (:func:`segment`, :meth:`JoinTree.simplify` or :func:`load_features`).
    min_elongation, min_voxels
        As :func:`~napari_unwind.segmentation.candidates`.

    Returns
    -------
    tuple of FeatureStats
        By id (importance). Features loaded from a file saved before these statistics existed have NaN
        elongations and are never specimens: segment again.

    Raises
    ------
    InvalidInputError
        For something that is not a :class:`Features` or a bad option.
    """
    if not isinstance(features, Features):
        raise InvalidInputError(f"specimens needs Features (from segment or load_features), got {type(features)}")
    return tuple(c.stats for c in candidates(features, min_elongation=min_elongation, min_voxels=min_voxels)
                 if c.is_specimen)
