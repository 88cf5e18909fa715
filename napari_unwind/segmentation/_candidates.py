"""Candidate specimens: one definition of a specimen, with a reason for every feature that is not one.

:func:`candidates` reads a segmentation (:class:`~._features.Features`) and returns one :class:`Candidate` per
feature (or per part of a feature), each ``"specimen"`` or ``"rejected"`` with a one-line reason. Everything that
decides what a specimen is lives here; :func:`~._features.specimens` (``unwind segment --specimens``) and the
pipeline's ``run --all`` both read it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InvalidInputError
from ._features import Features, FeatureStats

__all__ = ["Candidate", "candidates", "specimens"]

SPECIMEN = "specimen"
REJECTED = "rejected"


@dataclass(frozen=True, eq=False)
class Candidate:
    """One candidate specimen: a feature, a part of a feature, or features that make one body.

    Attributes
    ----------
    ids : tuple of int
        The features it is made of (1..k), sorted.
    status : str
        ``"specimen"`` or ``"rejected"``.
    reason : str
        One line: why it was rejected, or how a specimen was made ("" for a plain feature).
    stats : FeatureStats
        Its figures (the feature's own statistics, or those of its mask for a part or a union; ``id`` is
        ``ids[0]``).
    part : int
        0 for whole features; ``1..n_parts`` for one of the touching specimens a feature was split into.
    n_parts : int
        How many parts its features were split into (1 when not split).
    isovalue : float or None
        The isovalue its working mask was cut at (None: the features' own thresholds).
    """

    ids: tuple[int, ...]
    status: str
    reason: str
    stats: FeatureStats
    part: int = 0
    n_parts: int = 1
    isovalue: float | None = None
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


def candidates(
    features: Features,
    *,
    min_elongation: float = 3.0,
    min_voxels: int = 1,
) -> tuple[Candidate, ...]:
    """Every feature as a candidate specimen, kept or rejected with its reason.

    Parameters
    ----------
    features : Features
        A segmentation (:func:`segment`, :meth:`JoinTree.simplify` or :func:`load_features`).
    min_elongation : float
        Smallest principal-axis ratio (:attr:`FeatureStats.elongation`) of a specimen (default 3: a fish is
        about 6, a tube about 2, a blob of noise about 1-2).
    min_voxels : int
        Smallest labelled voxel count at working resolution (default 1).

    Returns
    -------
    tuple of Candidate
        By feature id (importance); a rejected candidate's ``reason`` says why.

    Raises
    ------
    InvalidInputError
        For something that is not a :class:`Features` or a bad option (the message holds the value received).
    """
    if not isinstance(features, Features):
        raise InvalidInputError(f"candidates needs Features (from segment or load_features), got {type(features)}")
    min_elongation = _number("min_elongation", min_elongation, 1.0)
    min_voxels = _count("min_voxels", min_voxels, 1)
    out = []
    for s in features.stats:
        if s.voxel_count < min_voxels:
            reason = f"too small: {s.voxel_count} voxels < {min_voxels}"
        elif s.container:
            reason = "container: touches the scan's border or encloses other features"
        elif s.elongation is None or not np.isfinite(s.elongation):
            reason = "no elongation in these statistics (saved by an older version): segment again"
        elif s.elongation < min_elongation:
            reason = f"not elongated: {s.elongation:.2g} < {min_elongation:g}"
        else:
            reason = ""
        out.append(Candidate(ids=(s.id,), status=REJECTED if reason else SPECIMEN, reason=reason, stats=s))
    return tuple(out)


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
