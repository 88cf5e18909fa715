"""Features: the join tree simplified to ``k`` branches, as a label volume with statistics.

Which voxels a feature gets
---------------------------
Basins
    During the sweep every voxel joins the basin of its highest already-swept neighbour (steepest ascent), so
    every maximum grows a basin and the basins tile the volume. At a saddle the dying branches' basins *attach*
    to the basin of the saddle's highest neighbour on the elder's side (:attr:`JoinTree.attach`).
Feature
    After pruning, a pruned branch's basin goes to the feature of the basin it attaches to (followed until a
    survivor): a feature is a surviving branch's basin plus the basins that were pruned into it. This is the
    flood a watershed from the surviving maxima would give, read off the tree in one pass; the elder of the join
    tree is often far away (after two objects meet, every later merge goes to the older one).
Threshold
    A basin reaches down to the lowest values, so each feature is cut at its *threshold*: the half-maximum
    between the typical value around it and its typical own value (the classic 50 % boundary of CT), found as the
    fixed point ``t = (median below t + median above t) / 2`` over the feature's voxels above its *base*. The base
    is its saddle (where it meets the rest), and for the root (the global maximum's branch) the saddle where the
    most important other branch joins, the same for every ``k``. A feature whose saddle lies inside its
    neighbour's object (above that neighbour's threshold: a bright inclusion such as a spine or stent strut) is
    part of that object and is cut at the neighbour's threshold when that is lower.
Ids
    Importance ranks: 1 is the root, 2 the last pruned branch, and so on (hypervolume order, noise-level branches
    last; see :mod:`._jointree`). The features of ``k`` keep their ids for ``k + 1``.

(The first draft cut every feature at its own saddle, the root at the highest saddle of its children: a single
noise maximum surviving on the root's own object then cut the root down to a few voxels, and the saddle level,
close to the background, gave every feature a halo of background noise.)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numba import njit

from ..errors import InvalidInputError
from ._common import check_features_count

__all__ = ["Features", "FeatureStats", "simplify"]

_NBINS = 1024  # histogram bins per feature for its threshold


# ------------------------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _representatives(attach, rank, k):
    """Feature id (1..k) of every branch's basin: its own rank + 1 if it survives, else that of the basin it
    attaches to at its saddle (followed until a survivor; the attachments form a tree rooted at branch 0)."""
    nb = attach.shape[0]
    fid = np.zeros(nb, dtype=np.int32)
    stack = np.empty(nb, dtype=np.int64)
    for b in range(nb):
        if fid[b] != 0:
            continue
        sp = 0
        c = b
        while fid[c] == 0 and rank[c] >= k:
            stack[sp] = c
            sp += 1
            c = attach[c]
        if fid[c] == 0:
            fid[c] = rank[c] + 1
        f = fid[c]
        for q in range(sp):
            fid[stack[q]] = f
    return fid


@njit(cache=True, nogil=True)
def _basin_histograms(values, branch, fid, base, top, nbins):
    """Histogram of the values ``> base[f]`` of each feature's basin on ``nbins`` bins spanning ``[base, top]``."""
    k1 = base.shape[0]
    hist = np.zeros((k1, nbins), dtype=np.int64)
    for x in range(values.shape[0]):
        f = fid[branch[x]]
        v = values[x]
        if v > base[f]:
            width = top[f] - base[f]
            b = int((v - base[f]) / width * nbins) if width > 0 else 0
            if b >= nbins:
                b = nbins - 1
            hist[f, b] += 1
    return hist


def _isodata(hist: np.ndarray, lo: float, hi: float) -> float:
    """The self-consistent midpoint ``t = (median below t + median above t) / 2`` of a histogram on ``[lo, hi]``.

    Ridler & Calvard's isodata iteration with medians instead of means, started halfway between ``lo`` and the
    mean, stopped when a bin repeats: for an object on a background it is the half-maximum boundary between the
    typical background and the typical object value, and a small very bright part (a spine, a stent) does not
    pull it up the way it pulls a mean.
    """
    nb = hist.shape[0]
    if hi <= lo:
        return float(lo)
    width = (hi - lo) / nb
    w = hist.astype(np.float64)
    total = w.sum()
    if total == 0:
        return float(lo)
    cw = np.cumsum(w)
    centres = lo + (np.arange(nb) + 0.5) * width

    def quantile_between(a: float, b: float) -> float:  # median of the counts in cumulative range (a, b]
        return float(centres[min(int(np.searchsorted(cw, 0.5 * (a + b), side="left")), nb - 1)])

    t = 0.5 * (lo + float((w * centres).sum() / total))
    seen = set()
    for _ in range(100):
        i = int(np.clip(np.floor((t - lo) / width), 0, nb - 1))  # the bins 0..i are below t
        if i in seen:
            break
        seen.add(i)
        n_lo = cw[i]
        med_lo = quantile_between(0.0, n_lo) if n_lo > 0 else lo
        med_hi = quantile_between(n_lo, total) if total > n_lo else hi
        t = 0.5 * (med_lo + med_hi)
    return float(t)


@njit(cache=True, nogil=True)
def _label(values, branch, fid, thr, shape, labels, stats_i, stats_f):
    """Labels and per-feature statistics in one pass.

    ``stats_i[f]`` = (count, lo0, lo1, lo2, hi0, hi1, hi2) with exclusive ``hi``; ``stats_f[f]`` = (min, max).
    """
    n1 = shape[1]
    n2 = shape[2]
    plane = n1 * n2
    for x in range(values.shape[0]):
        f = fid[branch[x]]
        v = values[x]
        if not v > thr[f]:
            f = 0
        labels[x] = f
        if f > 0:
            i = x // plane
            r = x - i * plane
            j = r // n2
            kk = r - j * n2
            s = stats_i[f]
            if s[0] == 0:
                s[1] = i
                s[2] = j
                s[3] = kk
                s[4] = i + 1
                s[5] = j + 1
                s[6] = kk + 1
                stats_f[f, 0] = v
                stats_f[f, 1] = v
            else:
                if i < s[1]:
                    s[1] = i
                if j < s[2]:
                    s[2] = j
                if kk < s[3]:
                    s[3] = kk
                if i + 1 > s[4]:
                    s[4] = i + 1
                if j + 1 > s[5]:
                    s[5] = j + 1
                if kk + 1 > s[6]:
                    s[6] = kk + 1
                if v < stats_f[f, 0]:
                    stats_f[f, 0] = v
                if v > stats_f[f, 1]:
                    stats_f[f, 1] = v
            s[0] += 1


@njit(cache=True, nogil=True)
def _moments(labels, shape, k1):
    """Per label: (count, sum i, sum j, sum k, sum ii, sum jj, sum kk, sum ij, sum ik, sum jk)."""
    n1 = shape[1]
    n2 = shape[2]
    plane = n1 * n2
    m = np.zeros((k1, 10), dtype=np.float64)
    for x in range(labels.shape[0]):
        f = labels[x]
        if f == 0:
            continue
        i = x // plane
        r = x - i * plane
        j = r // n2
        kk = r - j * n2
        row = m[f]
        row[0] += 1.0
        row[1] += i
        row[2] += j
        row[3] += kk
        row[4] += i * i
        row[5] += j * j
        row[6] += kk * kk
        row[7] += i * j
        row[8] += i * kk
        row[9] += j * kk
    return m


def _elongations(moments: np.ndarray, spacing: Any) -> np.ndarray:
    """Principal-axis ratio of every label from its moments (physical units), NaN when empty."""
    sp = np.asarray(spacing, dtype=float)
    out = np.full(moments.shape[0], np.nan)
    for f, row in enumerate(moments):
        n = row[0]
        if f == 0 or n == 0:
            continue
        mean = row[1:4] / n
        c = np.empty((3, 3))
        c[0, 0], c[1, 1], c[2, 2] = row[4:7] / n - mean**2
        c[0, 1] = c[1, 0] = row[7] / n - mean[0] * mean[1]
        c[0, 2] = c[2, 0] = row[8] / n - mean[0] * mean[2]
        c[1, 2] = c[2, 1] = row[9] / n - mean[1] * mean[2]
        c *= np.outer(sp, sp)
        ev = np.sort(np.linalg.eigvalsh(c + np.diag(sp**2 / 12.0)))[::-1]  # + the voxel's own extent
        out[f] = float(np.sqrt(ev[0] / ev[1]))
    return out


def _enclosers(labels: np.ndarray, k: int, max_positions: list[tuple[int, int, int]]) -> np.ndarray:
    """``enc[f]`` True when feature ``f`` encloses another feature (see :class:`FeatureStats`)."""
    enc = np.zeros(k + 1, dtype=bool)
    for g, m in enumerate(max_positions, start=1):
        halves = []  # per axis: the labels before and after the maximum along the line through it
        for a in range(3):
            idx = list(m)
            idx[a] = slice(None)
            line = labels[tuple(idx)]
            halves.append((set(np.unique(line[: m[a]]).tolist()), set(np.unique(line[m[a] + 1:]).tolist())))
        for a in range(3):  # the plane normal to axis a: met on both sides along both of its axes
            b, c = [x for x in range(3) if x != a]
            around = halves[b][0] & halves[b][1] & halves[c][0] & halves[c][1]
            for f in around - {0, g}:
                enc[f] = True
    return enc


# ------------------------------------------------------------------------------------------------------------------
# results
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FeatureStats:
    """Statistics of one feature.

    Attributes
    ----------
    id : int
        Label value (1..k, 1 the most important).
    voxel_count : int
        Labelled voxels at working resolution.
    bbox : tuple of 6 int
        ``(lo0, lo1, lo2, hi0, hi1, hi2)`` in working voxels, ``hi`` exclusive (all 0 for an empty feature).
    bbox_full : tuple of 6 int
        The same box in full-resolution voxels (the full-resolution voxels the working box covers).
    value_min, value_max : float
        Range of the (smoothed) working values of the labelled voxels.
    hypervolume : float
        Persistence x voxel count when the branch would be pruned (its importance; the root's runs to the
        global minimum over the whole volume).
    persistence : float
        ``birth - base``.
    threshold : float
        The half-maximum cut of the label volume (see the module docstring); the default isovalue of a refinement.
    base : float
        The saddle where the feature merges into its parent (for the root: the saddle of feature 2).
    birth : float
        The feature's maximum value.
    parent : int
        The feature it merges into (0 for the root).
    max_position : tuple of 3 int
        Working voxel of the maximum.
    max_position_full : tuple of 3 int
        A full-resolution voxel inside the working voxel of the maximum (its first corner).
    elongation : float
        Principal-axis ratio of the labelled voxels in physical units: the square root of the largest over the
        second-largest eigenvalue of their covariance (1 for a ball, about 6 for a fish; NaN when empty).
    touches_border : bool
        The labelled voxels reach a face of the scan (the specimen may run off it).
    container : bool
        Touches the border, or encloses another feature: around that feature's maximum, this feature is met on
        both sides along both axes of some plane (a tube around fish, a dish, a wall). Specimens are not
        containers (:func:`specimens`).
    """

    id: int
    voxel_count: int
    bbox: tuple[int, int, int, int, int, int]
    bbox_full: tuple[int, int, int, int, int, int]
    value_min: float
    value_max: float
    hypervolume: float
    persistence: float
    threshold: float
    base: float
    birth: float
    parent: int
    max_position: tuple[int, int, int]
    max_position_full: tuple[int, int, int]
    elongation: float = float("nan")
    touches_border: bool = False
    container: bool = False


@dataclass(frozen=True, eq=False)
class Features:
    """A segmentation into ``k`` features (working resolution), with the tree it came from.

    Attributes
    ----------
    labels : ndarray of uint16, shape (M0, M1, M2)
        0 for background, 1..k for the features (1 = the most important, the root of the tree).
    k : int
        Number of features.
    stats : tuple of FeatureStats
        ``stats[i]`` describes feature ``i + 1``.
    tree : JoinTree or None
        The tree (None for features loaded from a label file: then only ``labels`` and ``stats`` are known and
        an isovalue selection is not possible).
    scale : tuple of 3 float
        Full-resolution voxels per working voxel.
    full_shape : tuple of 3 int
        Shape of the full-resolution volume.
    level : int
        The pyramid level of ``labels``.
    spacing : tuple of 3 float
        Voxel size of ``labels``.
    full_spacing : tuple of 3 float
        Voxel size at full resolution.
    origin : tuple of 3 float
        Physical position of full-resolution voxel (0, 0, 0).
    unit : str or None
        Length unit.
    feature_of_branch : ndarray of int32, shape (B,) or None
        Feature id of every branch of ``tree``.
    """

    labels: np.ndarray
    k: int
    stats: tuple[FeatureStats, ...]
    tree: Any  # the JoinTree (the tree module imports this one, not the other way round), or None
    scale: tuple[float, float, float]
    full_shape: tuple[int, int, int]
    level: int = 0
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    full_spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    unit: str | None = None
    feature_of_branch: np.ndarray | None = None
    source: str | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.labels.shape)  # type: ignore[return-value]

    @property
    def ids(self) -> np.ndarray:
        """The feature ids, ``1..k``."""
        return np.arange(1, self.k + 1)

    @property
    def thresholds(self) -> np.ndarray:
        """Threshold of each feature, shape (k + 1,), index = id (entry 0 is NaN)."""
        return np.array([np.nan] + [s.threshold for s in self.stats])

    @property
    def working_origin(self) -> tuple[float, float, float]:
        """Physical position of working voxel (0, 0, 0)."""
        return tuple(o + (s - f) / 2 for o, s, f in zip(self.origin, self.spacing, self.full_spacing))  # type: ignore

    def stat(self, fid: int) -> FeatureStats:
        """The statistics of feature ``fid``."""
        return self.stats[self._check_id(fid) - 1]

    def _check_id(self, fid: Any) -> int:
        if isinstance(fid, (bool, np.bool_)) or not isinstance(fid, (int, np.integer)):
            raise InvalidInputError(f"a feature id must be an integer between 1 and {self.k}, got {fid!r}")
        if not 1 <= int(fid) <= self.k:
            raise InvalidInputError(f"there is no feature {int(fid)}: the ids are 1..{self.k}")
        return int(fid)

    # -- coordinates ---------------------------------------------------------------------------------------------
    def to_working(self, seeds: Any) -> np.ndarray:
        """Map full-resolution voxel coordinates (array axis order) to working voxels, shape (n, 3) int.

        A coordinate ``p`` names the full-resolution voxel ``floor(p + 0.5)``; it lies in working voxel
        ``floor((voxel + 0.5) / scale)``.

        Raises
        ------
        InvalidInputError
            For a malformed seed or one outside the full-resolution volume (the message names both).
        """
        pts = _seed_array(seeds)
        vox = np.floor(pts + 0.5)
        full = np.asarray(self.full_shape)
        for p, v in zip(pts, vox):
            if np.any(v < 0) or np.any(v >= full):
                raise InvalidInputError(
                    f"seed {tuple(float(c) for c in p)} is outside the volume of shape {tuple(self.full_shape)} "
                    "(full-resolution voxel coordinates in array axis order, from 0 to shape - 1)"
                )
        w = np.floor((vox + 0.5) / np.asarray(self.scale)).astype(np.int64)
        return np.minimum(w, np.asarray(self.shape) - 1)

    def ids_at(self, seeds: Any) -> np.ndarray:
        """Feature id under each full-resolution seed, shape (n,) (0: background)."""
        w = self.to_working(seeds)
        return self.labels[w[:, 0], w[:, 1], w[:, 2]].astype(np.int64)

    def basin_ids_at(self, seeds: Any) -> np.ndarray:
        """Feature whose basin holds each full-resolution seed, shape (n,) (never 0; needs the tree)."""
        w = self.to_working(seeds)
        self.basins([])  # raises without the tree
        b = self.tree.branch[w[:, 0], w[:, 1], w[:, 2]]
        return self.feature_of_branch[b].astype(np.int64)

    def nearest_feature(self, seed: Any) -> tuple[int, float, tuple[int, int, int]]:
        """The feature closest to a full-resolution seed.

        Returns
        -------
        id : int
            The nearest feature (0 if there is none).
        distance : float
            Distance in full-resolution voxels between the seed's working voxel and the nearest labelled working
            voxel (centre to centre, scaled to full resolution).
        position : tuple of 3 int
            A full-resolution voxel inside that nearest labelled working voxel (click there).
        """
        w = self.to_working(seed)[0]
        return _nearest_labelled(self.labels, w, np.asarray(self.scale))

    # -- basins --------------------------------------------------------------------------------------------------
    def basins(self, ids: Any) -> np.ndarray:
        """The basins of the features ``ids`` (every voxel they claim, down to the lowest), bool, working shape.

        Needs the tree (see the module docstring).
        """
        if self.tree is None or self.feature_of_branch is None:
            raise InvalidInputError(
                "these features were loaded without their join tree, so an isovalue cannot be applied at working "
                "resolution; select by label only, or refine at full resolution with an isovalue"
            )
        ids = [self._check_id(i) for i in np.atleast_1d(np.asarray(ids, dtype=object)).tolist()]
        chosen = np.zeros(self.k + 1, dtype=bool)
        chosen[ids] = True
        return chosen[self.feature_of_branch[self.tree.branch]]

    # -- persistence of a segmentation (for label files) ---------------------------------------------------------
    def to_attributes(self) -> dict[str, Any]:
        """The JSON-serialisable description saved next to the label volume (everything but the arrays)."""
        return {
            "k": int(self.k),
            "level": int(self.level),
            "scale": [float(v) for v in self.scale],
            "full_shape": [int(v) for v in self.full_shape],
            "spacing": [float(v) for v in self.spacing],
            "full_spacing": [float(v) for v in self.full_spacing],
            "origin": [float(v) for v in self.origin],
            "unit": self.unit,
            "source": self.source,
            "smooth": None if self.tree is None else float(self.tree.smooth),
            "connectivity": None if self.tree is None else int(self.tree.connectivity),
            "stats": [_jsonable(asdict(s)) for s in self.stats],
        }

    @classmethod
    def from_labels(cls, labels: Any, attributes: dict[str, Any]) -> Features:
        """Rebuild (tree-less) features from a label volume and :meth:`to_attributes` output."""
        try:
            stats = tuple(
                FeatureStats(**{key: tuple(v) if isinstance(v, list) else v for key, v in s.items()})
                for s in attributes["stats"]
            )
            k = int(attributes["k"])
            lab = np.asarray(labels)
            if lab.ndim != 3:
                raise InvalidInputError(f"a label volume must be 3D, got shape {lab.shape}")
            if len(stats) != k:
                raise InvalidInputError(f"the segmentation metadata lists {len(stats)} features but k = {k}")
            if lab.size and int(lab.max()) > k:
                raise InvalidInputError(f"the label volume holds label {int(lab.max())} but only {k} features")
            return cls(
                labels=lab.astype(np.uint16, copy=False),
                k=k,
                stats=stats,
                tree=None,
                scale=tuple(float(v) for v in attributes["scale"]),
                full_shape=tuple(int(v) for v in attributes["full_shape"]),
                level=int(attributes.get("level", 0)),
                spacing=tuple(float(v) for v in attributes.get("spacing", (1.0, 1.0, 1.0))),
                full_spacing=tuple(float(v) for v in attributes.get("full_spacing", (1.0, 1.0, 1.0))),
                origin=tuple(float(v) for v in attributes.get("origin", (0.0, 0.0, 0.0))),
                unit=attributes.get("unit"),
                source=attributes.get("source"),
            )
        except (KeyError, TypeError) as exc:
            raise InvalidInputError(f"the segmentation metadata is incomplete or malformed ({exc})") from None

    def __repr__(self) -> str:
        return f"Features(k={self.k}, shape={self.shape}, level={self.level}, scale={self.scale})"


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for key, v in d.items():
        if isinstance(v, tuple):
            out[key] = [x.item() if hasattr(x, "item") else x for x in v]
        elif isinstance(v, float) and not np.isfinite(v):
            out[key] = None if np.isnan(v) else (1e308 if v > 0 else -1e308)
        else:
            out[key] = v.item() if hasattr(v, "item") else v
    return out


def _seed_array(seeds: Any) -> np.ndarray:
    try:
        pts = np.asarray(seeds, dtype=float)
    except (TypeError, ValueError):
        raise InvalidInputError(
            f"seeds must be points (a0, a1, a2) in full-resolution voxel coordinates, got {seeds!r}"
        ) from None
    if pts.ndim == 1:
        pts = pts[None]
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise InvalidInputError(
            f"seeds must have shape (n, 3): points (a0, a1, a2) in array axis order, got shape {pts.shape}"
        )
    if not np.isfinite(pts).all():
        raise InvalidInputError(f"seeds must be finite numbers, got {pts.tolist()}")
    return pts


def _nearest_labelled(labels: np.ndarray, w: np.ndarray, scale: np.ndarray) -> tuple[int, float, tuple[int, ...]]:
    """Nearest labelled working voxel to ``w`` (distances scaled by ``scale``), by growing windows."""
    shape = np.asarray(labels.shape)
    if not labels.any():
        return 0, float("inf"), (-1, -1, -1)
    r = 4
    while True:
        lo = np.maximum(w - r, 0)
        hi = np.minimum(w + r + 1, shape)
        win = labels[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        pts = np.argwhere(win > 0)
        covers_all = bool(np.all(lo == 0) and np.all(hi == shape))
        if len(pts):
            pts = pts + lo
            d = np.sqrt((((pts - w) * scale) ** 2).sum(axis=1))
            i = int(np.argmin(d))
            # every voxel outside the window is more than r working voxels away along some axis
            if covers_all or d[i] <= r * float(scale.min()):
                p = pts[i]
                full = tuple(int(np.floor(c * s)) for c, s in zip(p, scale))
                return int(labels[tuple(p)]), float(d[i]), full
        r *= 2


# ------------------------------------------------------------------------------------------------------------------
# simplification
# ------------------------------------------------------------------------------------------------------------------
def simplify(tree: Any, k: int = 5) -> Features:
    """Keep the ``k`` features of largest hypervolume of ``tree`` (see :meth:`JoinTree.simplify`)."""
    k = check_features_count(k)
    if k > tree.n_maxima:
        raise InvalidInputError(
            f"only {tree.n_maxima} maxima in this volume; ask for at most {tree.n_maxima} features"
        )
    rank = tree.rank
    fid = _representatives(tree.attach, rank, k)
    survivors = np.empty(k, dtype=np.int64)  # branch of feature i + 1
    survivors[rank[rank < k]] = np.flatnonzero(rank < k)
    gmin = float(tree.death[0])
    base = np.empty(k + 1, dtype=np.float64)
    base[0] = np.inf
    base[1:] = tree.death[survivors]
    if tree.n_maxima > 1:
        base[1] = float(tree.death[tree.prune_order[-1]])  # the root: where the most important other branch joins
    else:
        base[1] = np.nextafter(gmin, -np.inf)  # a single maximum: the whole volume
    fparent = np.zeros(k + 1, dtype=np.int32)
    for f in range(2, k + 1):
        fparent[f] = fid[tree.attach[survivors[f - 1]]]
    values = tree.values.ravel()
    branch = tree.branch.ravel()
    top = np.empty(k + 1, dtype=np.float64)
    top[0] = np.inf
    top[1:] = tree.birth[survivors]
    hist = _basin_histograms(values, branch, fid, base, top, _NBINS)
    thr = np.full(k + 1, np.inf)
    for f in range(1, k + 1):
        thr[f] = max(base[f], _isodata(hist[f], base[f], top[f]))
    # a feature that meets its neighbour inside that neighbour's object (saddle above its threshold) is part of
    # that object: it is cut where the object is cut, if that is lower
    changed = True
    while changed:
        changed = False
        for f in range(2, k + 1):
            p = fparent[f]
            if base[f] > thr[p] and thr[p] < thr[f]:
                thr[f] = thr[p]
                changed = True
    labels = np.empty(values.shape[0], dtype=np.uint16)
    stats_i = np.zeros((k + 1, 7), dtype=np.int64)
    stats_f = np.zeros((k + 1, 2), dtype=np.float64)
    _label(values, branch, fid, thr, np.array(tree.shape, dtype=np.int64), labels, stats_i, stats_f)

    labels = labels.reshape(tree.shape)
    elong = _elongations(_moments(labels.ravel(), np.array(tree.shape, dtype=np.int64), k + 1), tree.spacing)
    max_pos = [tuple(int(v) for v in np.unravel_index(int(tree.max_voxel[b]), tree.shape)) for b in survivors]
    encloses = _enclosers(labels, k, max_pos)
    scale = np.asarray(tree.scale)
    full = np.asarray(tree.full_shape)
    hyp_of = np.empty(tree.n_maxima, dtype=np.float64)
    hyp_of[tree.prune_order] = tree.prune_hypervolume
    hyp_of[0] = (float(tree.birth[0]) - gmin) * values.shape[0]
    stats = []
    for f in range(1, k + 1):
        b = int(survivors[f - 1])
        s = stats_i[f]
        lo, hi = s[1:4], s[4:7]
        lo_full = np.minimum(np.floor(lo * scale), full).astype(int)
        hi_full = np.minimum(np.ceil(hi * scale), full).astype(int)
        mx = np.unravel_index(int(tree.max_voxel[b]), tree.shape)
        border = bool(s[0] > 0 and (np.any(lo == 0) or np.any(hi == np.asarray(tree.shape))))
        stats.append(FeatureStats(
            id=f,
            voxel_count=int(s[0]),
            bbox=tuple(int(v) for v in (*lo, *hi)),
            bbox_full=tuple(int(v) for v in (*lo_full, *hi_full)),
            value_min=float(stats_f[f, 0]) if s[0] else float("nan"),
            value_max=float(stats_f[f, 1]) if s[0] else float("nan"),
            hypervolume=float(hyp_of[b]),
            persistence=float(tree.birth[b] - base[f]),
            threshold=float(thr[f]),
            base=float(base[f]),
            birth=float(tree.birth[b]),
            parent=int(fparent[f]),
            max_position=tuple(int(v) for v in mx),
            max_position_full=tuple(int(min(np.floor(c * sc), n - 1)) for c, sc, n in zip(mx, scale, full)),
            elongation=float(elong[f]),
            touches_border=border,
            container=bool(border or encloses[f]),
        ))
    return Features(
        labels=labels,
        k=k,
        stats=tuple(stats),
        tree=tree,
        scale=tree.scale,
        full_shape=tree.full_shape,
        level=tree.level,
        spacing=tree.spacing,
        full_spacing=tree.full_spacing,
        origin=tree.origin,
        unit=tree.unit,
        feature_of_branch=fid,
        source=tree.source,
    )
