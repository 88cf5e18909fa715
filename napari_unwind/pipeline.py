"""One pipeline for every face: segment -> select -> skeleton -> session -> export, with one set of defaults, one
fold rule, one isovalue rule and one result per specimen.

``unwind run``, ``unwind run --all``, ``unwind demo``, the server's pipeline and skeleton jobs and the client's
pipeline request all call this module; none of them puts the chain together itself. The option objects below hold
every default once.

Statuses of a specimen (:class:`SpecimenResult`)
------------------------------------------------
``ok``
    Straightened to the goals: at least :data:`MIN_COVERAGE` of the mask inside the cage and no fold over the
    specimen. The stretches where the rest (under 1 %) is left out, such as the inner wall of a bend tighter
    than the body is wide, are still listed (``lost``, and a warning from 0.1 % of the mask).
``partial``
    Straightened (the output and session are written) but not to the goals: coverage under
    :data:`MIN_COVERAGE` (the reason lists the lost stretches), or a fold over the specimen exported with
    ``allow_folds``. Not a success: the command line exits :data:`EXIT_PARTIAL`.
``failed``
    An error stopped it (the reason says which); for a batch the other specimens go on.
``rejected``
    A candidate of the segmentation that is not a specimen (a container, not elongated, empty), with the reason.
``unresolved``
    A candidate that may be a specimen but is not taken without a click (a curved or coiled body among other
    elongated bodies: it may be two touching at an angle), with the reason and what to do. Nothing is written
    for it, and it is not passed over in silence: like ``partial``, the command line exits :data:`EXIT_PARTIAL`.

The fold rule (:func:`fold_rule`): a fold over no voxel of the specimen's mask (only empty cage corners) is a
warning and the export goes on; a fold over the specimen (or where that is unknown) is refused unless
``allow_folds``.

This module imports no napari or Qt, and its heavy imports happen inside the functions.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Generator, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from .errors import FoldError, InvalidInputError, NoBodyError, finite_number
from .progress import Progress

__all__ = [
    "EXIT_PARTIAL",
    "MIN_COVERAGE",
    "STATUSES",
    "BatchResult",
    "ExportOptions",
    "FoldVerdict",
    "PipelineOptions",
    "SegmentOptions",
    "Selection",
    "SkeletonOptions",
    "SpecimenResult",
    "candidates",
    "check_mask_label",
    "exit_status",
    "export_step",
    "fold_rule",
    "judge",
    "mask_label_counts",
    "pick_mask_label",
    "run",
    "run_all_iter",
    "run_iter",
    "segment_step",
    "select_step",
    "skeleton_step",
]

#: The statuses of a specimen (or candidate) of a run.
STATUSES = ("ok", "partial", "failed", "rejected", "unresolved")
#: Smallest fraction of the mask inside the cage for a specimen to be ``ok``.
MIN_COVERAGE = 0.99
#: Exit status of the command line when a specimen is only ``partial`` or a candidate ``unresolved`` (``failed``:
#: 1; ``ok``: 0).
EXIT_PARTIAL = 3
#: Features a segmentation keeps when the specimen is picked (by points or ids) and none were asked for.
PICK_FEATURES = 5

_DEFAULT = "default"  # ExportOptions.max_output: the warp's own DEFAULT_MAX_OUTPUT

# The bounds of the options (every face refuses the same values: the command line, the dock and the server, whose
# protos list them field by field). Generous, but finite: a value past them is a typo, not a bigger specimen, and
# would hold a worker for hours.
#: Highest pyramid level to segment.
MAX_LEVEL = 64
#: Largest Gaussian sigma of the segmentation, working voxels.
MAX_SMOOTH = 1000.0
#: Largest smallest elongation of a specimen.
MAX_ELONGATION = 1e6
#: Most level sets of the harmonic field.
MAX_N_LEVELS = 10_000
#: Most curve smoothing iterations.
MAX_SMOOTHING_ITERATIONS = 100_000
#: Largest distance in voxels (cage_radius, tolerance, snap_tolerance).
MAX_VOXELS_DISTANCE = 1e6
#: Largest length in physical units (half_extent, spacing).
MAX_LENGTH = 1e9
#: Largest relative cage margin.
MAX_CAGE_MARGIN = 100.0
#: Most extra slices at each end of the straight volume.
MAX_PAD = 100_000
#: Largest chunk side of the export.
MAX_CHUNK = 4096
#: Most dorsal landmark points.
MAX_DORSAL_POINTS = 1000


# ------------------------------------------------------------------------------------------------------------------
# validators
# ------------------------------------------------------------------------------------------------------------------
def _whole(name: str, value: Any, lo: int, hi: int | None = None) -> int:
    if type(value) is int:  # the defaults: no numpy import (building options must keep the CLI's start quick)
        whole = True
    else:
        import numpy as np

        whole = isinstance(value, np.integer)
    if not whole or value < lo or (hi is not None and value > hi):
        rng = f">= {lo}" if hi is None else f"{lo}..{hi}"
        raise InvalidInputError(f"{name} must be a whole number {rng}, got {value!r}")
    return int(value)


def _points3(name: str, value: Any, most: int, what: str = "") -> tuple[tuple[float, float, float], ...]:
    """``value`` as a tuple of at most ``most`` points of 3 finite numbers (each within +-MAX_LENGTH)."""
    import numpy as np

    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be points of 3 numbers, got {value!r}") from None
    if a.ndim != 2 or a.shape[1] != 3 or len(a) > most or not np.isfinite(a).all() \
            or np.abs(a).max(initial=0) > MAX_LENGTH:
        what = what or f"at most {most} points of 3 finite numbers"
        raise InvalidInputError(f"{name} must be {what} within +-{MAX_LENGTH:g}, got {value!r}"[:300])
    return tuple(tuple(float(c) for c in p) for p in a)


def _positive(name: str, value: Any, *, zero: bool = False, hi: float | None = None) -> float:
    v = finite_number(name, value)
    if v < 0 or (v == 0 and not zero):
        raise InvalidInputError(f"{name} must be a {'non-negative' if zero else 'positive'} number, got {value!r}")
    if hi is not None and v > hi:
        raise InvalidInputError(f"{name} must be at most {hi:g}, got {value!r}")
    return v


# ------------------------------------------------------------------------------------------------------------------
# options: every default once
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SegmentOptions:
    """How the scan is segmented and a selection refined (``unwind segment``, ``select``, ``run``).

    Attributes
    ----------
    features : int or None
        Features the join tree keeps, 1..100. None: :data:`PICK_FEATURES` (5) when the specimen is picked by
        points or ids; every feature above the noise level (at most 100) for :func:`run_all_iter`.
    level : int or None
        Pyramid level to segment, 0..:data:`MAX_LEVEL` (None: the finest with every side <= 256).
    smooth : float
        Gaussian sigma in working voxels, 0..:data:`MAX_SMOOTH` (0: none).
    isovalue : float or None
        Full-resolution threshold of the mask. None: the one rule,
        :func:`napari_unwind.segmentation.default_isovalue` (the covered features' specimen_isovalue, from the scan).
    fill_holes : bool
        Fill cavities of the mask.
    min_elongation : float
        Smallest elongation of a specimen (:func:`napari_unwind.segmentation.specimens`), for :func:`run_all_iter`.
    """

    features: int | None = None
    level: int | None = None
    smooth: float = 1.0
    isovalue: float | None = None
    fill_holes: bool = False
    min_elongation: float = 3.0

    def __post_init__(self) -> None:
        if self.features is not None:
            _whole("features", self.features, 1, 100)
        if self.level is not None:
            _whole("level", self.level, 0, MAX_LEVEL)
        object.__setattr__(self, "smooth", _positive("smooth", self.smooth, zero=True, hi=MAX_SMOOTH))
        if self.isovalue is not None:
            object.__setattr__(self, "isovalue", finite_number("isovalue", self.isovalue))
        if not isinstance(self.fill_holes, bool):
            raise InvalidInputError(f"fill_holes must be True or False, got {self.fill_holes!r}")
        m = finite_number("min_elongation", self.min_elongation)
        if not 1 <= m <= MAX_ELONGATION:
            raise InvalidInputError(f"min_elongation must be a number 1..{MAX_ELONGATION:g}, got "
                                    f"{self.min_elongation!r}")

    @property
    def k(self) -> int:
        """Features to keep when the specimen is picked: ``features`` or :data:`PICK_FEATURES`."""
        return PICK_FEATURES if self.features is None else self.features


@dataclass(frozen=True)
class SkeletonOptions:
    """Options of the skeleton solve (:func:`napari_unwind.skeleton.estimate_deformation_iter`).

    The defaults are the solver's own (a test holds them equal to its signature's).

    Attributes
    ----------
    estimate_twist : bool
        Turn the frames so ``v`` points dorsal (False: parallel transport).
    n_levels : int
        Level sets of the harmonic field (2..10000).
    smoothing_iterations : int
        Curve smoothing iterations (0..100000).
    cage_radius : float
        Half size (voxels, at most :data:`MAX_VOXELS_DISTANCE`) of the box the keyframes must reproduce
        within ``tolerance``.
    tolerance : float
        How far (voxels, at most :data:`MAX_VOXELS_DISTANCE`) the keyframed box may stray from the dense curve's.
    snap_tolerance : float
        Ends outside the mask move onto it when within this many voxels.
    half_extent : tuple of 2 float or None
        Cage half extents (u, v) for every keyframe, physical units, at most :data:`MAX_LENGTH`
        (None: fitted per keyframe and side).
    cage_margin : float
        Relative margin of the fitted cages, 0..:data:`MAX_CAGE_MARGIN` (0.1: 10 %).
    dorsal_points : tuple of (a0, a1, a2) or None
        Points on the dorsal side (full-resolution voxels, at most :data:`MAX_DORSAL_POINTS`): the twist turns
        ``v`` at each and changes linearly between, instead of being estimated.
    dorsal_direction : (a0, a1, a2) or None
        A direction that ``v`` follows wherever the curve crosses it (for a vessel, "anterior"), instead of the
        estimate. At most one of the two.
    context : float
        Physical units (0..:data:`MAX_LENGTH`) added to every side of the fitted cages and to the end padding:
        what surrounds the specimen in the straight volume. Not with ``half_extent``.
    """

    estimate_twist: bool = True
    n_levels: int = 100
    smoothing_iterations: int = 50
    cage_radius: float = 10.0
    tolerance: float = 1.0
    snap_tolerance: float = 5.0
    half_extent: tuple[float, float] | None = None
    cage_margin: float = 0.1
    dorsal_points: tuple[tuple[float, float, float], ...] | None = None
    dorsal_direction: tuple[float, float, float] | None = None
    context: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "context", _positive("context", self.context, zero=True, hi=MAX_LENGTH))
        if self.context and self.half_extent is not None:
            raise InvalidInputError("context widens the fitted cages: give it or a cage (half_extent), not both")
        if self.dorsal_points is not None and self.dorsal_direction is not None:
            raise InvalidInputError("give either dorsal points or a dorsal direction, not both")
        if self.estimate_twist is False and (self.dorsal_points is not None or self.dorsal_direction is not None):
            raise InvalidInputError("dorsal landmarks set the twist, and estimate_twist=False asks for none: give one "
                                    "of them")
        if self.dorsal_points is not None:
            pts = _points3("dorsal_points", self.dorsal_points, MAX_DORSAL_POINTS)
            object.__setattr__(self, "dorsal_points", pts or None)
        if self.dorsal_direction is not None:
            d = _points3("dorsal_direction", [self.dorsal_direction], 1, "3 finite numbers (axis0, axis1, axis2)")[0]
            if not any(d):
                raise InvalidInputError(f"dorsal_direction must not be 0, got {self.dorsal_direction!r}")
            object.__setattr__(self, "dorsal_direction", d)
        if not isinstance(self.estimate_twist, bool):
            raise InvalidInputError(f"estimate_twist must be True or False, got {self.estimate_twist!r}")
        _whole("n_levels", self.n_levels, 2, MAX_N_LEVELS)
        _whole("smoothing_iterations", self.smoothing_iterations, 0, MAX_SMOOTHING_ITERATIONS)
        for name in ("cage_radius", "tolerance"):
            object.__setattr__(self, name, _positive(name, getattr(self, name), hi=MAX_VOXELS_DISTANCE))
        object.__setattr__(self, "snap_tolerance", _positive("snap_tolerance", self.snap_tolerance, zero=True,
                                                             hi=MAX_VOXELS_DISTANCE))
        object.__setattr__(self, "cage_margin", _positive("cage_margin", self.cage_margin, zero=True,
                                                          hi=MAX_CAGE_MARGIN))
        if self.half_extent is not None:
            he = self.half_extent
            if isinstance(he, (int, float)) and not isinstance(he, bool):
                he = (he, he)
            if not isinstance(he, (tuple, list)) or len(he) != 2:
                raise InvalidInputError(f"half_extent must be two positive numbers (u, v), got {self.half_extent!r}")
            object.__setattr__(self, "half_extent", tuple(_positive("half_extent", v, hi=MAX_LENGTH) for v in he))

    def kwargs(self) -> dict[str, Any]:
        """The keywords of :func:`~napari_unwind.skeleton.estimate_deformation_iter`."""
        return asdict(self)


@dataclass(frozen=True)
class ExportOptions:
    """How the straight volume is written (:func:`napari_unwind.warp.export_iter`).

    Attributes
    ----------
    order : int
        Interpolation: 0 nearest (labels), 1 linear, 3 cubic.
    spacing : float or None
        Output voxel size (None: the finest scan spacing).
    pad : int
        Extra slices at both ends, 0..:data:`MAX_PAD`.
    chunks : tuple of 3 int or None
        Output chunk shape, each side 1..:data:`MAX_CHUNK`, computed and (OME-Zarr) stored; None: 64 x the
        cross-section.
    max_output : float, None or "default"
        Refuse a larger output, bytes (None: no limit; "default": ``napari_unwind.warp.DEFAULT_MAX_OUTPUT``).
    allow_folds : bool
        Export even where the deformation folds over the specimen (see :func:`fold_rule`).
    """

    order: int = 1
    spacing: float | None = None
    pad: int = 0
    chunks: tuple[int, int, int] | None = None
    max_output: float | None | str = _DEFAULT
    allow_folds: bool = False

    def __post_init__(self) -> None:
        if self.order not in (0, 1, 3) or isinstance(self.order, bool):
            raise InvalidInputError(f"order must be 0, 1 or 3, got {self.order!r}")
        if self.spacing is not None:
            object.__setattr__(self, "spacing", _positive("spacing", self.spacing, hi=MAX_LENGTH))
        _whole("pad", self.pad, 0, MAX_PAD)
        if self.chunks is not None:
            c = tuple(self.chunks)
            if len(c) != 3:
                raise InvalidInputError(f"chunks must be 3 sizes (axis0, axis1, axis2), got {list(c)}")
            object.__setattr__(self, "chunks", tuple(_whole("chunks", v, 1, MAX_CHUNK) for v in c))
        if self.max_output not in (None, _DEFAULT):
            object.__setattr__(self, "max_output", _positive("max_output", self.max_output))
        if not isinstance(self.allow_folds, bool):
            raise InvalidInputError(f"allow_folds must be True or False, got {self.allow_folds!r}")

    def kwargs(self, path: str | os.PathLike) -> dict[str, Any]:
        """The keywords of :func:`~napari_unwind.warp.export_iter` for the output ``path`` (an OME-Zarr output is
        chunked on disk as computed)."""
        kw: dict[str, Any] = dict(order=self.order, spacing=self.spacing, pad=self.pad, chunks=self.chunks)
        if self.max_output != _DEFAULT:
            kw["max_output"] = self.max_output
        if self.chunks and str(path).rstrip("/").lower().endswith(".zarr"):
            kw["file_chunks"] = self.chunks
        return kw


@dataclass(frozen=True)
class PipelineOptions:
    """The options of the whole chain: :class:`SegmentOptions`, :class:`SkeletonOptions`, :class:`ExportOptions`."""

    segment: SegmentOptions = field(default_factory=SegmentOptions)
    skeleton: SkeletonOptions = field(default_factory=SkeletonOptions)
    export: ExportOptions = field(default_factory=ExportOptions)

    def __post_init__(self) -> None:
        for name, kind in (("segment", SegmentOptions), ("skeleton", SkeletonOptions), ("export", ExportOptions)):
            if not isinstance(getattr(self, name), kind):
                raise InvalidInputError(f"PipelineOptions.{name} must be a {kind.__name__}, got "
                                        f"{type(getattr(self, name)).__name__}")

    @classmethod
    def from_values(cls, **values: Any) -> PipelineOptions:
        """Options from flat keywords (each a field of one of the three), None meaning the default; an unknown
        name is an error. ``PipelineOptions.from_values(features=8, cage_margin=0.2, order=3)``."""
        groups: dict[str, dict[str, Any]] = {"segment": {}, "skeleton": {}, "export": {}}
        owners = {f.name: g for g, kind in (("segment", SegmentOptions), ("skeleton", SkeletonOptions),
                                            ("export", ExportOptions)) for f in fields(kind)}
        for name, value in values.items():
            if name not in owners:
                raise InvalidInputError(f"unknown pipeline option {name!r}; known: {', '.join(sorted(owners))}")
            if value is not None:
                groups[owners[name]][name] = value
        return cls(SegmentOptions(**groups["segment"]), SkeletonOptions(**groups["skeleton"]),
                   ExportOptions(**groups["export"]))


# ------------------------------------------------------------------------------------------------------------------
# the rules
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FoldVerdict:
    """What :func:`fold_rule` decided about a folding deformation.

    Attributes
    ----------
    folds : tuple of (s_start, s_end)
        Where it folds (physical arclength).
    folded : float or None
        Fraction of the specimen's mask in the folds (None: unknown, no mask).
    refused : bool
        The export must not go on.
    message : str
        One line: where it folds, how much of the specimen, what to do.
    """

    folds: tuple[tuple[float, float], ...]
    folded: float | None
    refused: bool
    message: str

    @property
    def over_specimen(self) -> bool:
        """The folds hold voxels of the specimen (or that is unknown)."""
        return self.folded is None or self.folded > 0


def fold_rule(deformation: Any, *, folded: float | None = None, allow_folds: bool = False) -> FoldVerdict | None:
    """The one fold rule of every face. None when the deformation does not fold.

    A fold over no voxel of the specimen's mask (``folded == 0``: only empty cage corners) is a warning and the
    export goes on; a fold over the specimen, or where that is unknown (``folded`` None), is refused unless
    ``allow_folds``.
    """
    from .io._volume import unit_label

    folds = tuple((float(a), float(b)) for a, b in deformation.folds())
    if not folds:
        return None
    where = ", ".join(f"s = {a:.4g}..{b:.4g}" for a, b in folds)
    msg = (f"the deformation folds where the cage is larger than the radius of curvature ({where} "
           f"{unit_label(deformation.unit)})")
    f = None if folded is None or not math.isfinite(float(folded)) else float(folded)
    hint = ("shrink the cage there (unwind skeleton/run --cage RX,RY or --cage-margin M, or Deformation.set_cage in "
            "the session)")
    if f == 0:
        return FoldVerdict(folds, f, False, f"{msg}; {hint}; no voxel of the specimen's mask lies in the folds (only "
                           "empty cage corners), so the export goes ahead")
    if f is not None:
        msg += f"; {100 * f:.2g} % of the specimen's mask lies in the folds"
    msg += "; " + hint
    if allow_folds:
        return FoldVerdict(folds, f, False, msg + "; exported anyway (allow_folds)")
    return FoldVerdict(folds, f, True, msg + ", or allow folds (--allow-folds) to export anyway")


def _num(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def judge(skeleton: Any) -> tuple[str, str]:
    """The status of a straightened specimen from its :class:`~napari_unwind.skeleton.SkeletonResult`:
    ``("ok", "")`` or ``("partial", reason)``.

    ``ok`` needs coverage >= :data:`MIN_COVERAGE`, no fold over the specimen, a mask that does not touch itself
    between the ends (a skipped loop of the body, or a side of it beside the path) and, where the ends were
    suggested, a mask that does not branch (which branch to follow is the user's choice, not the longest path's);
    the lost intervals of an ok specimen (together under 1 % of its mask) stay in its figures.
    """
    from .io._volume import unit_label
    from .skeleton._foldfree import format_lost

    reasons = []
    cov = _num(getattr(skeleton, "coverage", None))
    apart = _num(getattr(skeleton, "apart", None)) or 0.0
    cage_helps = False
    if cov is not None and cov < MIN_COVERAGE:
        lost = tuple(getattr(skeleton, "lost", ()) or ())
        where = f" (lost: {format_lost(lost, unit_label(skeleton.deformation.unit))})" if lost else ""
        reasons.append(f"coverage {100 * cov:.1f} % of the mask inside the cage (goal {100 * MIN_COVERAGE:.0f} %)"
                       + where)
        if apart >= 1.0 - MIN_COVERAGE:  # no cage holds a part the path does not run through
            reasons[-1] += (f"; {100 * apart:.2g} % of the mask lies in separate parts off the path (a mask of this "
                            "specimen alone, or --chain START END through each part)")
        bend = _num(getattr(skeleton, "bend", None)) or 0.0
        if bend >= 1e-3:  # the fold-free construction took the tissue on the inside of a tight bend
            reasons[-1] += (f"; {100 * bend:.2g} % of the mask lies on the inside of bends tighter than the body is "
                            "thick, which no cage holds without folding (a larger one neither)")
        cage_helps = (1.0 - cov) - apart - bend >= 1e-3
    folded = _num(getattr(skeleton, "folded", None))
    if folded and skeleton.deformation.folds():
        reasons.append(f"the deformation folds over {100 * folded:.2g} % of the specimen's mask")
        cage_helps = True
    if reasons and cage_helps:
        reasons[-1] += " (a larger or fitted cage: --cage RX,RY, --cage-margin M)"
    reasons.extend(tuple(getattr(skeleton, "touching", ()) or ()))  # each with what to do
    branches = tuple(getattr(skeleton, "branches", ()) or ())
    if branches and getattr(skeleton, "suggested", False):
        reasons.append(f"the mask branches and the ends were suggested: the path follows its longest way and "
                       f"{len(branches)} other branch(es) are cut off ({'; '.join(branches)}); give the head and "
                       "tail (--head, --tail) at the ends of the branch to straighten")
    if reasons:
        return "partial", "; ".join(reasons)
    return "ok", ""


# ------------------------------------------------------------------------------------------------------------------
# results
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SpecimenResult:
    """One specimen (or rejected candidate) of a run.

    Attributes
    ----------
    status : str
        ``"ok"``, ``"partial"``, ``"failed"``, ``"rejected"`` or ``"unresolved"`` (see the module docstring).
    reason : str
        One line; empty for ``ok``.
    ids : tuple of int
        The feature ids of the specimen (empty with a mask).
    voxels : int or None
        Labelled working-resolution voxels of its features.
    length : float or None
        Centreline length, physical units.
    unit : str or None
        The length unit.
    keyframes : int or None
    min_jacobian, max_tilt, coverage, folded : float or None
        The skeleton's figures (:class:`~napari_unwind.skeleton.SkeletonResult`).
    lost : tuple of (s_start, s_end, fraction)
        Arclength intervals whose mask is left out of the cage.
    output : Path or None
        The straight volume written.
    session_path : Path or None
        The session file written.
    session : Session or None
        The session (deformation, segmentation, endpoints).
    skeleton : SkeletonResult or None
        The skeleton solve's full result.
    warnings : tuple of str
        Warnings of the run, one line each.
    label : str
        The candidate's name when it is not its ids alone (``"3.1"``: part 1 of feature 3, split from a touching
        specimen).
    """

    status: str
    reason: str = ""
    ids: tuple[int, ...] = ()
    voxels: int | None = None
    length: float | None = None
    unit: str | None = None
    keyframes: int | None = None
    min_jacobian: float | None = None
    max_tilt: float | None = None
    coverage: float | None = None
    folded: float | None = None
    lost: tuple[tuple[float, float, float], ...] = ()
    output: Path | None = None
    session_path: Path | None = None
    session: Any = field(default=None, repr=False, compare=False)
    skeleton: Any = field(default=None, repr=False, compare=False)
    warnings: tuple[str, ...] = ()
    label: str = ""

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise InvalidInputError(f"status must be one of {', '.join(STATUSES)}, got {self.status!r}")
        object.__setattr__(self, "reason", " ".join(str(self.reason).split()))

    @classmethod
    def of(cls, skeleton: Any, **fields_: Any) -> SpecimenResult:
        """The result of a skeleton solve (:class:`~napari_unwind.skeleton.SkeletonResult`): its status by
        :func:`judge` and its figures; ``fields_`` set the others (ids, output, session...)."""
        status, reason = judge(skeleton)
        d = skeleton.deformation
        values: dict[str, Any] = dict(
            status=status, reason=reason, length=_num(d.length), unit=d.unit, keyframes=len(d),
            min_jacobian=_num(skeleton.min_jacobian), max_tilt=_num(skeleton.max_tilt),
            coverage=_num(skeleton.coverage), folded=_num(skeleton.folded), lost=tuple(skeleton.lost),
            skeleton=skeleton, warnings=tuple(skeleton.warnings))
        values.update(fields_)
        return cls(**values)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def deformation(self) -> Any:
        """The deformation (None when the skeleton did not run)."""
        if self.session is not None:
            return self.session.deformation
        return None if self.skeleton is None else self.skeleton.deformation

    @property
    def name(self) -> str:
        """``specimen 3`` (``specimen 3+5`` for several features; ``the specimen`` with a mask)."""
        return "specimen " + self._key if self.ids else "the specimen"

    @property
    def _key(self) -> str:
        return self.label or "+".join(map(str, self.ids))

    def row(self) -> dict[str, Any]:
        """Its row of ``specimens.csv`` (:data:`CSV_COLUMNS`)."""
        from .io._volume import unit_label
        from .skeleton._foldfree import format_lost

        return dict(specimen=self.ids[0] if len(self.ids) == 1 and not self.label else self._key,
                    status=self.status, voxels=self.voxels, length=self.length, unit=self.unit,
                    keyframes=self.keyframes, min_jacobian=self.min_jacobian, max_tilt=self.max_tilt,
                    coverage=self.coverage, lost=format_lost(self.lost, unit_label(self.unit)) if self.lost else "",
                    output=None if self.output is None else Path(self.output).name,
                    session=None if self.session_path is None else Path(self.session_path).name, reason=self.reason)

    def summary(self) -> str:
        """One line: the name, status, figures and reason."""
        from .io._volume import unit_label

        parts = [f"{self.name}: {self.status}"]
        if self.length is not None:
            parts.append(f"length {self.length:.4g} {unit_label(self.unit)}, {self.keyframes} keyframes")
        if self.coverage is not None:
            parts.append(f"coverage {self.coverage:.3f}")
        if self.max_tilt is not None:
            parts.append(f"largest tilt {self.max_tilt:.3g} deg")
        if self.output is not None:
            parts.append(f"-> {Path(self.output).name}")
        line = ", ".join(parts)
        return f"{line}: {self.reason}" if self.reason else line


@dataclass
class BatchResult:
    """What :func:`run_all_iter` did.

    Attributes
    ----------
    specimens : list of SpecimenResult
        Every candidate, in the segmentation's order: the specimens (ok, partial, failed), the unresolved and the
        rejected.
    table : Path or None
        The summary CSV.
    features : Features
        The segmentation the candidates came from.
    seconds : float
        Wall time of the whole run.
    """

    specimens: list[SpecimenResult] = field(default_factory=list)
    table: Path | None = None
    features: Any = None
    seconds: float = 0.0

    @property
    def rows(self) -> list[dict[str, Any]]:
        """The rows of the specimens and unresolved candidates (not the rejected), as in ``specimens.csv``."""
        return [r.row() for r in self.specimens if r.status != "rejected"]

    @property
    def failed(self) -> list[dict[str, Any]]:
        """The rows of the specimens that were not straightened to the goals (partial, failed or unresolved)."""
        return [r for r in self.rows if r["status"] != "ok"]

    @property
    def rejected(self) -> list[SpecimenResult]:
        return [r for r in self.specimens if r.status == "rejected"]


def exit_status(results: Sequence[SpecimenResult]) -> int:
    """The command line's exit status for these results: 1 when one failed or there is no specimen at all,
    else :data:`EXIT_PARTIAL` when one is partial or unresolved, else 0 (rejected candidates alone do not count)."""
    found = [r for r in results if r.status != "rejected"]
    if not found or any(r.status == "failed" for r in found):
        return 1
    return EXIT_PARTIAL if any(r.status in ("partial", "unresolved") for r in found) else 0


# ------------------------------------------------------------------------------------------------------------------
# candidates: the adapter to the segmentation's definition of a specimen
# ------------------------------------------------------------------------------------------------------------------
def candidates(features: Any, *, min_elongation: float = 3.0) -> tuple[Any, ...]:
    """Every candidate specimen of ``features``, specimens and rejected alike, each with its reason: the
    segmentation's one definition of a specimen (:func:`napari_unwind.segmentation.candidates`; each
    :class:`~napari_unwind.segmentation.Candidate` has ``ids``, ``status`` ``"specimen"`` or ``"rejected"``,
    ``reason``, ``stats``, and for a part of touching specimens its own working mask). :func:`select_step` refines
    every candidate at the one isovalue rule, whatever isovalue the candidate records.

    The one place the pipeline asks what a specimen is.
    """
    from .segmentation import candidates as _candidates

    return tuple(_candidates(features, min_elongation=min_elongation))


# ------------------------------------------------------------------------------------------------------------------
# the steps (each a generator of Progress; the dock calls them one at a time)
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Selection:
    """The specimen's mask and how it was made (:func:`select_step`).

    Attributes
    ----------
    mask : dask array
        The full-resolution mask (lazy).
    ids : tuple of int
        The features chosen.
    isovalue : float
        The full-resolution threshold used.
    segmentation : Segmentation
        The session's record of it.
    """

    mask: Any
    ids: tuple[int, ...]
    isovalue: float
    segmentation: Any


def segment_step(volume: Any, options: SegmentOptions = SegmentOptions(), *, features: int | None = None
                 ) -> Generator[Progress, None, Any]:
    """Segment ``volume`` (join tree, simplified to ``features`` or ``options.k`` features); returns Features."""
    from .segmentation import segment_iter

    k = options.k if features is None else features
    return (yield from segment_iter(volume, features=k, level=options.level, smooth=options.smooth))


def select_step(volume: Any, features: Any, *, seeds: Any = None, ids: Any = None, candidate: Any = None,
                options: SegmentOptions = SegmentOptions()) -> Generator[Progress, None, Selection]:
    """Choose features by ``seeds`` (full-resolution voxels) and/or ``ids``, or a ``candidate`` of
    :func:`candidates` (its own working mask), and refine them at full resolution at ``options.isovalue`` or the
    one default rule, for clicks and candidates alike (:func:`~napari_unwind.segmentation.default_isovalue` with
    the scan: the contrast between the specimen and the medium, read at full resolution)."""
    import numpy as np

    from .segmentation import default_isovalue, refine_mask_iter, select, selected_ids
    from .session import Segmentation

    if candidate is not None:
        chosen = [int(i) for i in candidate.ids]
        working = candidate.working_mask(features)
    else:
        chosen = selected_ids(features, seeds=seeds, ids=ids)
        working = select(features, ids=chosen, fill_holes=options.fill_holes)
    iso = options.isovalue if options.isovalue is not None else float(
        default_isovalue(features, working, volume=volume))
    mask = yield from refine_mask_iter(volume, working, features=features, isovalue=iso)
    pts = () if seeds is None else tuple(tuple(float(c) for c in p) for p in np.asarray(seeds, float).reshape(-1, 3))
    record = Segmentation(k=features.k, level=features.level, selected=tuple(chosen), seeds=pts, isovalue=iso,
                          fill_holes=options.fill_holes)
    return Selection(mask=mask, ids=tuple(int(i) for i in chosen), isovalue=float(iso), segmentation=record)


def as_label_map(mask: Any) -> Any:
    """The mask as an integer label map (a numpy array), or None: integer masks as they are, float masks whose
    values are all whole and finite (a label map saved as float, as NIfTI tools often do) as int64; bool and other
    float masks are no label map."""
    import numpy as np

    dtype = getattr(mask, "dtype", None)
    if dtype is None:
        return None
    dtype = np.dtype(dtype)
    if np.issubdtype(dtype, np.integer):
        return mask
    if not np.issubdtype(dtype, np.floating):
        return None
    arr = np.asarray(mask)
    if not (np.isfinite(arr).all() and (arr == np.round(arr)).all() and np.abs(arr).max(initial=0) < 2**53):
        return None
    return arr.astype(np.int64)


def mask_label_counts(mask: Any) -> dict[int, int]:
    """The voxel count of each non-zero value of a label map (an integer mask, or a float one of whole values); {}
    for a bool mask or a float one of fractional values.

    Reads the whole mask once (the skeleton solve reads it whole too)."""
    import numpy as np

    mask = as_label_map(mask)
    if mask is None:
        return {}
    arr = np.asarray(mask).reshape(-1)
    if arr.dtype.kind == "u" and arr.dtype.itemsize <= 2:
        counts = np.bincount(arr)
        values = np.flatnonzero(counts)
        counts = counts[values]
    else:
        values, counts = np.unique(arr, return_counts=True)
    return {int(v): int(c) for v, c in zip(values, counts) if v != 0}


def pick_mask_label(mask: Any, label: Any) -> Any:
    """The voxels of one ``label`` of an integer mask (a label map) as a bool array of its shape.

    Raises :class:`InvalidInputError` for a label that is no integer, or that no voxel of the mask holds (the
    message names the labels it does hold)."""
    import numpy as np

    from .io._volume import Volume

    m = mask.data if isinstance(mask, Volume) else mask
    if isinstance(label, bool) or not isinstance(label, (int, np.integer)) or as_label_map(m) is None:
        check_mask_label(m, label)  # says what is wrong
    picked = np.asarray(m) == int(label)
    if not picked.any():
        check_mask_label(m, label)  # names the labels the map holds (counted only on this path)
    return picked


def check_mask_label(mask: Any, label: Any) -> None:
    """Raise :class:`InvalidInputError` unless ``label`` is an integer that some voxel of ``mask`` holds (the
    message names the labels it does hold). A face calls it before any long work; :func:`pick_mask_label` too."""
    import numpy as np

    if isinstance(label, bool) or not isinstance(label, (int, np.integer)):
        raise InvalidInputError(f"the mask's label must be an integer, got {label!r}")
    dtype = np.dtype(getattr(mask, "dtype", float))
    if as_label_map(mask) is None:
        raise InvalidInputError(f"a label was given, but the mask is no label map of integers (dtype {dtype}"
                                f"{'' if dtype == np.bool_ else ' with fractional values'}): give it without a label")
    counts = mask_label_counts(mask)
    if int(label) not in counts:
        held = ", ".join(map(str, sorted(counts)[:12])) + (", ..." if len(counts) > 12 else "")
        raise InvalidInputError(f"no voxel of the mask holds label {int(label)}"
                                + (f"; its labels are {held}: give one of them" if counts else ": it is empty"))


def _labels_note(mask: Any) -> str | None:
    """A warning when the mask is a label map of several labels: all of them are taken as the one specimen."""
    import numpy as np

    arr = as_label_map(mask)
    if arr is None:
        return None
    arr = np.asarray(arr)
    if arr.size == 0 or (arr.min() >= 0 and arr.max() <= 1):  # a 0/1 mask: one label (the common case, read fast)
        return None
    counts = mask_label_counts(arr)
    if len(counts) < 2:
        return None
    total = sum(counts.values())
    top = sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))

    def share(c: int) -> str:
        p = 100 * c / total
        return f"{p:.3g} %" if p >= 0.01 else "< 0.01 %"

    shown = ", ".join(f"label {v}: {share(c)}" for v, c in top[:5]) + (", ..." if len(top) > 5 else "")
    return (f"the mask holds {len(counts)} labels ({shown} of its voxels): all are taken as one specimen; to "
            "straighten one, give its label (--mask-label N, in Python mask_label=N)")


def specimen_mask(mask: Any) -> tuple[Any, str | None]:
    """The specimen's voxels of a mask: the mask itself when it is boolean, integer (non-zero: the specimen) or a
    float mask of whole values (0.0 / 1.0, as NIfTI masks often are); a float mask holding fractional values (a
    probability or partial-volume map: non-zero would be nearly the whole scan) is thresholded at 0.5, or at half its
    maximum when that exceeds 1, and the note says so. NaN is never the specimen.

    Returns ``(mask, note)``: the mask (where it was thresholded: a bool array of the same kind, numpy or dask, or a
    uint8 Volume of the same geometry) and a one-line note (None when the mask is taken as it is)."""
    import numpy as np

    from .io._volume import Volume

    m = mask.data if isinstance(mask, Volume) else mask
    dtype = np.dtype(getattr(m, "dtype", float))
    if not np.issubdtype(dtype, np.floating):
        return mask, None
    import dask.array as da

    xp = da if isinstance(m, da.Array) else np
    arr = m if xp is da else np.asarray(m)
    finite = xp.isfinite(arr)
    vals = xp.where(finite, arr, 0)
    stats = (vals.min(), vals.max(), (vals != xp.round(vals)).any(), (~finite).any())
    lo, hi, fractional, nan = da.compute(*stats) if xp is da else stats
    note = None
    if fractional:
        level = 0.5 if float(hi) <= 1.0 else 0.5 * float(hi)
        kept = vals >= level
        counts = (kept.sum(), (vals != 0).sum())
        n_kept, n_any = da.compute(*counts) if xp is da else counts
        note = (f"the mask holds fractional values ({float(lo):.3g} to {float(hi):.3g}, {dtype}): a probability or "
                f"partial-volume map; its voxels >= {level:.3g} are the specimen ({100 * n_kept / max(n_any, 1):.3g} % "
                "of its non-zero voxels); threshold it yourself to choose another level")
    elif nan:
        kept = vals != 0
    else:
        return mask, None
    if isinstance(mask, Volume):
        kept = Volume(kept.astype(np.uint8), spacing=mask.spacing, origin=mask.origin, unit=mask.unit,
                      source=mask.source)
    return kept, note


def skeleton_step(mask: Any, endpoints: Any = None, *, spacing: Any, origin: Any = None, unit: str | None = None,
                  volume: Any = None, options: SkeletonOptions = SkeletonOptions()
                  ) -> Generator[Progress, None, Any]:
    """The skeleton solve with ``options``; returns the :class:`~napari_unwind.skeleton.SkeletonResult`, whose
    ``warnings`` hold every UserWarning of the solve (one line each; they are not issued again), and a note when
    ``mask`` is a label map of several labels (every non-zero voxel is the specimen: :func:`pick_mask_label`
    takes one) or a map of fractional values (thresholded: :func:`specimen_mask`)."""
    from . import skeleton as _skeleton

    mask, soft = specimen_mask(mask)
    labels = soft or _labels_note(mask)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = yield from _skeleton.estimate_deformation_iter(mask, endpoints, spacing=spacing, origin=origin,
                                                                unit=unit, volume=volume, **options.kwargs())
    messages = ([labels] if labels else []) + list(result.warnings) + [
        str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    messages = [" ".join(m.split()) for m in dict.fromkeys(messages)]
    return replace(result, warnings=tuple(dict.fromkeys(messages)))


def export_step(volume: Any, deformation: Any, output: str | os.PathLike, *,
                options: ExportOptions = ExportOptions(), folded: float | None = None, session: Any = None,
                overwrite: bool = False, scheduler: str | None = None,
                channels: Sequence[Any] | None = None) -> Generator[Progress, None, Path]:
    """Write the straight volume after :func:`fold_rule` (``folded``: the fraction of the specimen's mask in the
    folds, None when unknown). Raises :class:`~napari_unwind.errors.FoldError` when the rule refuses; a fold
    the rule lets through is issued as a UserWarning.

    ``channels``: other images of the scan's grid (Volumes named by ``metadata["channel"]``) straightened with
    ``volume`` (channel 0) in one pass into one multi-channel output
    (:func:`napari_unwind.warp.export_channels_iter`)."""
    from .warp import FoldWarning, export_channels_iter, export_iter

    verdict = fold_rule(deformation, folded=folded, allow_folds=options.allow_folds)
    if verdict is not None and verdict.refused:
        raise FoldError(verdict.message)
    if verdict is not None:
        warnings.warn(verdict.message, UserWarning, stacklevel=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FoldWarning)  # the rule above said it
        if channels:
            written = yield from export_channels_iter([volume, *channels], deformation, output, overwrite=overwrite,
                                                      session=None if session is None else session.to_dict(),
                                                      scheduler=scheduler, **options.kwargs(output))
        else:
            written = yield from export_iter(volume, deformation, output, overwrite=overwrite,
                                             session=None if session is None else session.to_dict(),
                                             scheduler=scheduler, **options.kwargs(output))
    return Path(written)


# ------------------------------------------------------------------------------------------------------------------
# one specimen
# ------------------------------------------------------------------------------------------------------------------
def run_iter(
    volume: Any,
    *,
    mask: Any = None,
    seeds: Any = None,
    ids: Sequence[int] | None = None,
    candidate: Any = None,
    features: Any = None,
    endpoints: Any = None,
    options: PipelineOptions = PipelineOptions(),
    output: str | os.PathLike | None = None,
    session_path: str | os.PathLike | None = None,
    source: Any = None,
    notes: str = "",
    overwrite: bool = False,
    scheduler: str | None = None,
    mask_source: str | os.PathLike | None = None,
    mask_label: int | None = None,
) -> Generator[Progress, None, SpecimenResult]:
    """Straighten one specimen: segment (unless given), select and refine (or a mask), skeleton, session, export.

    Parameters
    ----------
    volume : Volume
        The scan.
    mask : array or Volume, optional
        The specimen's full-resolution mask (same shape as ``volume``, or a Volume that is a box of its grid, placed
        by its origin: :func:`~napari_unwind.io._grid.place_on_grid`); exclusive with ``seeds`` and ``ids``.
    seeds : array_like (N, 3), optional
        Points inside the specimen's features, full-resolution voxels (the scan is segmented unless ``features``).
    ids : sequence of int, optional
        Feature ids of ``features``.
    candidate : Candidate, optional
        A specimen of :func:`candidates` of ``features`` (its own working mask; refined at the one isovalue rule).
    features : Features, optional
        A segmentation of ``volume`` to pick from (default: segmented here with ``options.segment``).
    endpoints : Endpoints or (head, tail), optional
        Full-resolution voxels; None: suggested.
    options : PipelineOptions
    output : path, optional
        The straight volume to write (None: no export).
    session_path : path, optional
        The session file to write (``*.unwind.json``; None: not saved).
    source : SourceInfo, str or path-like, optional
        The session's source: a SourceInfo, or the scan's path (checksummed here). Needed with ``session_path``.
    notes : str
        The session's notes (``; suggested endpoints`` is added when they were).
    overwrite : bool
        Replace existing outputs.
    scheduler : str, optional
        The dask scheduler of the export.
    mask_source : path, optional
        The file ``mask`` was read from: the session records it as its selection (``segmentation.mask``), so that
        ``unwind measure`` and the dock find it again (None: not recorded).
    mask_label : int, optional
        ``mask`` is a label map: its voxels of this label are the specimen (the session records the label).
        None: every non-zero voxel (a label map of several labels is then named in the warnings).

    Returns
    -------
    SpecimenResult
        ``ok`` or ``partial`` (see :func:`judge`); an error raises instead (a refused fold is a
        :class:`~napari_unwind.errors.FoldError`, after the session was saved).
    """
    import numpy as np

    from .session import Session, SourceInfo, save_session

    if not isinstance(options, PipelineOptions):
        raise InvalidInputError(f"options must be PipelineOptions, got {type(options).__name__}")
    has_seeds = seeds is not None and np.asarray(seeds, dtype=float).size > 0
    has_ids = ids is not None and len(ids) > 0
    if (mask is not None) + (has_seeds or has_ids) + (candidate is not None) != 1:
        raise InvalidInputError("say which specimen to straighten with exactly one of: a mask, points inside it "
                                "and/or feature ids (the scan is segmented first), or a candidate")
    if mask_label is not None and mask is None:
        raise InvalidInputError("mask_label picks a label of the mask: give the mask too (mask=...)")
    if candidate is not None and features is None:
        raise InvalidInputError("a candidate needs the features it came from (features=)")
    if session_path is not None and source is None:
        raise InvalidInputError("a session needs its source: the scan's path or a SourceInfo")
    if output is not None:
        from .io._formats import output_format

        output_format(output)  # an unknown suffix fails now, before any work
    ids_out: tuple[int, ...] = ()
    voxels = None
    segmentation = None
    if mask is not None:
        from .io._volume import Volume

        if isinstance(mask, Volume):  # a box of the scan's grid is placed by its origin
            from .io._grid import place_on_grid

            mask = place_on_grid(mask, volume)[0]
        m = mask.data if isinstance(mask, Volume) else mask
        if tuple(m.shape) != tuple(volume.shape):
            raise InvalidInputError(f"the mask has shape {tuple(m.shape)} but the scan has {tuple(volume.shape)}; "
                                    "the mask must lie on the scan's voxel grid (give it as a Volume with its "
                                    "origin to place a box of that grid)")
        mask = m if mask_label is None else pick_mask_label(m, mask_label)
        if mask_source is not None:
            from .session import Segmentation

            segmentation = Segmentation(mask=str(Path(mask_source).absolute()),
                                        mask_label=None if mask_label is None else int(mask_label))
    else:
        if features is None:
            features = yield from segment_step(volume, options.segment)
        sel = yield from select_step(volume, features, seeds=seeds if has_seeds else None,
                                     ids=list(ids) if has_ids else None, candidate=candidate,
                                     options=options.segment)
        mask, segmentation, ids_out = sel.mask, sel.segmentation, sel.ids
        voxels = int(candidate.stats.voxel_count) if candidate is not None else int(
            sum(features.stat(i).voxel_count for i in ids_out))
    result = yield from skeleton_step(mask, endpoints, spacing=volume.spacing, origin=volume.origin,
                                      unit=volume.unit, volume=volume.data, options=options.skeleton)
    d = result.deformation
    session = None
    written_session = None
    if source is not None:
        if not isinstance(source, SourceInfo):
            yield Progress("checksum", 0, 1, "describing the source")
            source = SourceInfo.from_path(source, volume=volume)
            yield Progress("checksum", 1, 1)
        session = Session(source=source, deformation=d, segmentation=segmentation, endpoints=result.endpoints,
                          notes=notes + ("; suggested endpoints" if result.suggested else ""),
                          twist=result.twist_profile())
        if session_path is not None:
            written_session = save_session(session, session_path, overwrite=overwrite)
    messages = [m for m in result.warnings if not (d.folds() and m.startswith("the deformation folds"))]
    written = None
    if output is not None:
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", UserWarning)
                written = yield from export_step(volume, d, output, options=options.export,
                                                 folded=_num(result.folded), session=session, overwrite=overwrite,
                                                 scheduler=scheduler)
            messages += [" ".join(str(w.message).split()) for w in caught if issubclass(w.category, UserWarning)]
        except FoldError as exc:
            if written_session is not None:
                raise FoldError(f"{exc}; the session was saved ({Path(written_session).name}): edit it, or export "
                                "it as it is with unwind straighten --session ... --allow-folds") from None
            raise
    else:
        verdict = fold_rule(d, folded=_num(result.folded), allow_folds=options.export.allow_folds)
        if verdict is not None:
            messages.append(verdict.message)
    return SpecimenResult.of(
        result, ids=ids_out, voxels=voxels, output=written,
        session_path=None if written_session is None else Path(written_session), session=session,
        warnings=tuple(dict.fromkeys(messages)))


def run(volume: Any, *, progress: Any = None, **kwargs: Any) -> SpecimenResult:
    """:func:`run_iter` to the end (``progress`` is called with each :class:`~napari_unwind.progress.Progress`)."""
    from .progress import run as _drive

    return _drive(run_iter(volume, **kwargs), progress)


# ------------------------------------------------------------------------------------------------------------------
# every specimen of a scan
# ------------------------------------------------------------------------------------------------------------------
#: The summary table of a batch (:func:`run_all_iter`) and its columns.
CSV_NAME = "specimens.csv"
CSV_COLUMNS = ("specimen", "status", "voxels", "length", "unit", "keyframes", "min_jacobian", "max_tilt",
               "coverage", "lost", "output", "session", "reason")


def _check_outdir(outdir: Path, overwrite: bool) -> None:
    from .errors import OutputError

    if outdir.exists() and not outdir.is_dir():
        raise OutputError(f"the output folder {outdir} is a file; give a folder for --all (it is created)")
    if outdir.is_dir() and not overwrite:
        taken = sorted(p.name for p in outdir.iterdir() if p.name == CSV_NAME or p.name.startswith("specimen-"))
        if taken:
            raise OutputError(f"{outdir} already holds results of a batch ({', '.join(taken[:3])}"
                              f"{', ...' if len(taken) > 3 else ''}); choose another folder or pass --overwrite")
    if not outdir.is_dir():
        parent = outdir.absolute().parent
        if not parent.is_dir():
            raise OutputError(f"cannot create the output folder {outdir}: {parent} does not exist")
        if not os.access(parent, os.W_OK):
            raise OutputError(f"cannot create the output folder {outdir}: {parent} is not writable")


def _write_table(rows: list[dict[str, Any]], path: Path, columns: Sequence[str] = CSV_COLUMNS, *,
                 overwrite: bool = True) -> Path:
    """``rows`` as CSV (``columns`` in order, floats to 6 significant digits, None empty), written atomically."""
    import csv
    import io

    from .io._atomic import atomic_output

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]))
                    for k in columns})
    with atomic_output(path, overwrite=overwrite) as tmp:
        Path(tmp).write_text(buf.getvalue(), encoding="utf-8")
    return path


def _failure_reason(exc: BaseException) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    return msg if type(exc).__module__.startswith("napari_unwind") else f"{type(exc).__name__}: {msg}"


def run_all_iter(
    scan: Any,
    outdir: str | os.PathLike,
    *,
    options: PipelineOptions = PipelineOptions(),
    overwrite: bool = False,
    reader_options: dict[str, Any] | None = None,
) -> Generator[Progress, None, BatchResult]:
    """Straighten every specimen of a scan with no click (generator: yields progress, returns a
    :class:`BatchResult`).

    The scan is segmented (``options.segment.features`` features, default every one above the noise level);
    every feature is a :class:`Candidate` (:func:`candidates`); a specimen is straightened with suggested ends
    into ``outdir/specimen-<id>.zarr`` and ``specimen-<id>.unwind.json``; ``outdir/specimens.csv`` gets a row per
    candidate (rejected ones too) with its status and reason (see :mod:`napari_unwind.batch`). A specimen's
    failure is its row (``failed``) and the others go on; a candidate that only a click can take is its row
    (``unresolved``), nothing is written for it, and the run is not a success (:func:`exit_status`).

    Parameters
    ----------
    scan : str or path-like
        The scan (any format :func:`~napari_unwind.io.open_volume` reads).
    outdir : str or path-like
        The results' folder (created). Without ``overwrite`` it must not hold results of an earlier batch.
    options : PipelineOptions
        ``options.segment.isovalue`` and ``fill_holes`` do not apply (each specimen takes the default rule).
    overwrite : bool
        Replace results already in ``outdir``.
    reader_options : dict, optional
        Options of :func:`~napari_unwind.io.open_volume` (``format``, ``series``).

    Raises
    ------
    UnwindError
        When the scan cannot be read or segmented, or ``outdir`` cannot be used.
    """
    from .io import open_volume
    from .segmentation import join_tree_iter
    from .segmentation._common import MAX_FEATURES
    from .session import SourceInfo

    t_all = time.perf_counter()
    outdir = Path(outdir)
    _check_outdir(outdir, overwrite)
    seg = options.segment
    volume = open_volume(scan, **(reader_options or {}))
    tree = yield from join_tree_iter(volume, level=seg.level, smooth=seg.smooth)
    k = seg.features if seg.features is not None else int(min(MAX_FEATURES, max(1, int(tree.significant.sum()))))
    k = min(k, tree.n_maxima)
    yield Progress("simplify", 0, 1, f"{k} features")
    feats = tree.simplify(k)
    yield Progress("simplify", 1, 1)
    found = candidates(feats, min_elongation=seg.min_elongation)
    source = SourceInfo.from_path(scan, volume=volume)
    made = not outdir.is_dir()
    outdir.mkdir(exist_ok=True)
    before: dict[Path, tuple[int, int] | None] = {}  # what was at each path this batch writes, before it did
    try:
        result = BatchResult(features=feats)
        picked = replace(options, segment=replace(seg, isovalue=None, fill_holes=False))
        todo = [c for c in found if c.status == "specimen"]
        for c in found:
            voxels = None if c.stats is None else int(c.stats.voxel_count)
            if c.status != "specimen":  # rejected, or unresolved (a click must say)
                result.specimens.append(SpecimenResult(c.status, c.reason, ids=tuple(c.ids), voxels=voxels,
                                                       label=getattr(c, "name", "")))
                continue
            i = todo.index(c)
            name = getattr(c, "name", None) or "+".join(map(str, c.ids))
            yield Progress("specimens", i, len(todo), f"feature {name}")
            session_path = outdir / f"specimen-{name}.unwind.json"
            output = outdir / f"specimen-{name}.zarr"
            before.update({p: _identity(p) for p in (session_path, output)})
            try:
                r = yield from run_iter(volume, features=feats, candidate=c, options=picked,
                                        output=output, session_path=session_path,
                                        source=source, overwrite=overwrite,
                                        notes=f"unwind run --all: feature {name} of {feats.k}")
            except NoBodyError:  # nothing there at full resolution: not a specimen, not a failure
                r = SpecimenResult("rejected", "no body at full resolution: the scan shows no body above the medium "
                                   "around it (a candidate of the segmentation's working level only)",
                                   ids=tuple(c.ids), voxels=voxels, label=name)
            except Exception as exc:  # noqa: BLE001 - one specimen's failure must not stop the others
                r = SpecimenResult("failed", _failure_reason(exc), ids=tuple(c.ids), voxels=voxels, label=name,
                                   session_path=session_path if session_path.exists() else None)
            result.specimens.append(replace(r, voxels=voxels, label=name))
        yield Progress("specimens", len(todo), len(todo))
        before[outdir / CSV_NAME] = _identity(outdir / CSV_NAME)
        result.table = _write_table([r.row() for r in result.specimens], outdir / CSV_NAME)
    except (KeyboardInterrupt, GeneratorExit):
        # interrupted (Ctrl-C, SIGTERM) or abandoned: no half-made batch is left; the folder goes when this batch
        # made it, else what this batch wrote into it (an earlier batch's file it already replaced is gone too)
        from .io._atomic import remove_path

        for p in ([outdir] if made else [p for p, was in before.items() if _identity(p) not in (None, was)]):
            remove_path(p, settle=1.0)
        raise
    result.seconds = time.perf_counter() - t_all
    return result


def _identity(path: Path) -> tuple[int, int] | None:
    """(inode, modification time) of whatever is at ``path``, None when nothing is."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns
