"""The cylindrical deformation: a keyframed curve with frames that maps a straight box into the bent scan.

A straight box ``(x, y, s)``, ``s`` the arclength in ``[0, L]``, maps into the bent specimen by

    f(x, y, s) = c(s) + x u(s) + y v(s)

(docs/design.md section 3, the paper's "Cylindrical Deformation" with its typo corrected).

- Keyframes ``i = 0..m-1`` hold a position ``e_i``, an orthonormal right-handed frame ``R_i = (u_i, v_i, n_i)``
  (``u x v = n``, ``n`` along the curve), the cage half-extents ``(rx_i, ry_i)`` and the cage's in-plane centre
  offset ``(ox_i, oy_i)``: the cage is ``x in [ox - rx, ox + rx]``, ``y in [oy - ry, oy + ry]`` (per-side extents,
  so that a bend's inner side can be thinner than its outer side). Both are interpolated linearly in ``s``.
- ``d_0 = 0``, ``d_{i+1} = d_i + |e_{i+1} - e_i|``, ``L = d_{m-1}``. On ``[d_k, d_{k+1}]`` the centre moves linearly
  and the whole frame (bend and twist) is interpolated by quaternion SLERP, so both are smooth across keyframes.
- Padding extends the box beyond both ends along the end normals (``s < 0`` and ``s > L``).

Everything here is in physical units (index x spacing, in ``unit``), components in array axis order (axis0, axis1,
axis2). Conversions to voxels happen at the edges only, with the ``spacing`` and ``origin`` of the scan.

A :class:`Deformation` is immutable: every edit returns a new one (cheap undo for the GUI) and it serialises to a
plain dict (:meth:`Deformation.to_dict`) for session files and the services.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .errors import InvalidInputError
from .io._volume import check_spacing, normalise_unit, unit_label

__all__ = ["Keyframe", "Deformation", "InverseResult", "parallel_transport_frames", "SCHEMA"]

#: Identifies the dict layout of :meth:`Deformation.to_dict`.
SCHEMA = "napari-unwind/deformation/2"
#: Older dict layouts :meth:`Deformation.from_dict` still reads (schema 1: no cage offsets, taken as zero).
OLD_SCHEMAS = ("napari-unwind/deformation/1",)



def _orthonormalise(frame: np.ndarray) -> np.ndarray:
    """Nearest rotation (rows u, v, n) to a 3x3 matrix, by SVD; raises on a reflection or a degenerate frame."""
    m = np.asarray(frame, dtype=float).reshape(3, 3)
    if not np.isfinite(m).all():
        raise InvalidInputError(f"a keyframe frame must be finite, got {m.tolist()}")
    if np.abs(m @ m.T - np.eye(3)).max() < 1e-12 and np.linalg.det(m) > 0:
        return m.copy()  # already a rotation: keep it bit for bit (exact serialisation round trips)
    u, s, vt = np.linalg.svd(m)
    if s.min() < 1e-6 * max(s.max(), 1e-300):
        raise InvalidInputError(f"a keyframe frame is degenerate (rows u, v, n are not independent): {m.tolist()}")
    r = u @ vt
    if np.linalg.det(r) < 0:
        raise InvalidInputError("a keyframe frame must be right-handed (u x v = n); this one is a reflection")
    return r


@dataclass(frozen=True)
class Keyframe:
    """One keyframe of the curve.

    Attributes
    ----------
    position : ndarray, shape (3,)
        Centre of the cross-section, physical units, array axis order.
    frame : ndarray, shape (3, 3)
        Rows ``u, v, n``: orthonormal and right-handed. ``n`` points along the curve (towards the tail), ``v`` is
        the straightened specimen's "up" (axis1 of the straight volume), ``u`` its axis2.
    half_extent : tuple of 2 float
        Cage half-sizes ``(rx, ry)`` along ``u`` and ``v``, physical units.
    offset : tuple of 2 float
        Centre ``(ox, oy)`` of the cage box in the cross-section plane (default ``(0, 0)``, the curve point): the
        cage spans ``x in [ox - rx, ox + rx]`` and ``y in [oy - ry, oy + ry]``.
    """

    position: np.ndarray
    frame: np.ndarray
    half_extent: tuple[float, float]
    offset: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        p = np.asarray(self.position, dtype=float).reshape(-1)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise InvalidInputError(f"a keyframe position must be 3 finite numbers, got {self.position!r}")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "frame", _orthonormalise(self.frame))
        he = tuple(float(v) for v in np.broadcast_to(np.asarray(self.half_extent, dtype=float), (2,)))
        if not all(np.isfinite(v) and v > 0 for v in he):
            raise InvalidInputError(f"cage half-extents must be positive, got {self.half_extent!r}")
        object.__setattr__(self, "half_extent", he)
        off = tuple(float(v) for v in np.broadcast_to(np.asarray(self.offset, dtype=float), (2,)))
        if not all(np.isfinite(v) for v in off):
            raise InvalidInputError(f"a cage offset must be 2 finite numbers, got {self.offset!r}")
        object.__setattr__(self, "offset", off)
        self.position.flags.writeable = False
        self.frame.flags.writeable = False

    @property
    def u(self) -> np.ndarray:
        return self.frame[0]

    @property
    def v(self) -> np.ndarray:
        return self.frame[1]

    @property
    def n(self) -> np.ndarray:
        return self.frame[2]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """The cage's sides ``(x_lo, x_hi, y_lo, y_hi)`` in the cross-section plane."""
        (rx, ry), (ox, oy) = self.half_extent, self.offset
        return (ox - rx, ox + rx, oy - ry, oy + ry)

    @classmethod
    def from_bounds(cls, position: np.ndarray, frame: np.ndarray, bounds: Sequence[float]) -> Keyframe:
        """A keyframe whose cage spans ``x in [x_lo, x_hi]``, ``y in [y_lo, y_hi]`` (``bounds``, 4 numbers)."""
        b = np.asarray(bounds, dtype=float).reshape(-1)
        if b.shape != (4,) or not np.isfinite(b).all() or not (b[1] > b[0] and b[3] > b[2]):
            raise InvalidInputError(f"cage bounds must be 4 finite numbers (x_lo, x_hi, y_lo, y_hi) with x_lo < x_hi "
                                    f"and y_lo < y_hi, got {bounds!r}")
        return cls(position, frame, ((b[1] - b[0]) / 2, (b[3] - b[2]) / 2), ((b[0] + b[1]) / 2, (b[2] + b[3]) / 2))

    def to_dict(self) -> dict[str, Any]:
        return {
            "position": [float(x) for x in self.position],
            "frame": [[float(x) for x in row] for row in self.frame],
            "half_extent": list(self.half_extent),
            "offset": list(self.offset),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Keyframe:
        return cls(np.asarray(d["position"], float), np.asarray(d["frame"], float), tuple(d["half_extent"]),
                   tuple(d.get("offset", (0.0, 0.0))))


@dataclass(frozen=True)
class InverseResult:
    """Straight coordinates of points of the bent scan (:meth:`Deformation.inverse`).

    Attributes
    ----------
    xys : ndarray, shape (N, 3)
        ``(x, y, s)`` of each point; NaN where no cross-section plane holds the point.
    inside : ndarray of bool, shape (N,)
        The point lies in the cage: ``-pad_start <= s <= L + pad_end``, ``|x - ox(s)| <= rx(s)`` and
        ``|y - oy(s)| <= ry(s)``.
    residual : ndarray, shape (N,)
        ``|f(x, y, s) - p|`` after the Newton steps (physical units).
    """

    xys: np.ndarray
    inside: np.ndarray
    residual: np.ndarray


def parallel_transport_frames(points: np.ndarray, *, up: Sequence[float] | None = None) -> np.ndarray:
    """Rotation-minimising frames along a polyline.

    Parameters
    ----------
    points : ndarray, shape (K, 3)
        Curve points (physical units), K >= 2, consecutive points distinct.
    up : sequence of 3 float, optional
        World direction that the first frame's ``v`` should follow (projected onto the plane normal to the first
        tangent). Default: the world axis least aligned with the first tangent.

    Returns
    -------
    frames : ndarray, shape (K, 3, 3)
        Rows ``u, v, n`` per point; ``n`` by central differences (one-sided at the ends), each next frame the
        minimal rotation of the previous one taking its ``n`` to the new ``n``.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
        raise InvalidInputError(f"a curve needs at least 2 points of 3 coordinates, got shape {pts.shape}")
    seg = np.diff(pts, axis=0)
    seglen = np.linalg.norm(seg, axis=1)
    if (seglen <= 1e-12).any():
        i = int(np.argmax(seglen <= 1e-12))
        raise InvalidInputError(f"curve points {i} and {i + 1} coincide ({pts[i].tolist()}); remove duplicates")
    tangents = np.empty_like(pts)
    tangents[0] = seg[0] / seglen[0]
    tangents[-1] = seg[-1] / seglen[-1]
    if len(pts) > 2:
        central = pts[2:] - pts[:-2]
        tangents[1:-1] = central / np.linalg.norm(central, axis=1, keepdims=True)
    n0 = tangents[0]
    if up is None:
        up_v = np.eye(3)[int(np.argmin(np.abs(n0)))]
    else:
        up_v = np.asarray(up, dtype=float).reshape(3)
    v0 = up_v - np.dot(up_v, n0) * n0
    if np.linalg.norm(v0) < 1e-8:
        raise InvalidInputError(f"'up' {up_v.tolist()} is parallel to the curve's first direction; choose another")
    v0 /= np.linalg.norm(v0)
    u0 = np.cross(v0, n0)
    frames = np.empty((len(pts), 3, 3))
    frames[0] = (u0, v0, n0)
    for i in range(1, len(pts)):
        rot = _min_rotation(frames[i - 1, 2], tangents[i])
        u = rot @ frames[i - 1, 0]
        n = tangents[i]
        u -= np.dot(u, n) * n
        u /= np.linalg.norm(u)
        frames[i] = (u, np.cross(n, u), n)
    return frames


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation matrix of smallest angle taking unit vector ``a`` to unit vector ``b``."""
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    c = float(np.clip(np.dot(a, b), -1.0, 1.0))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # opposite: rotate by pi about any axis normal to a
        perp = np.eye(3)[int(np.argmin(np.abs(a)))]
        perp = perp - np.dot(perp, a) * a
        perp /= np.linalg.norm(perp)
        return Rotation.from_rotvec(np.pi * perp).as_matrix()
    return Rotation.from_rotvec(axis / s * math.atan2(s, c)).as_matrix()


def _rotation(frame: np.ndarray) -> Rotation:
    """Frame rows (u, v, n) -> the rotation taking local (x, y, z) to world: matrix with columns u, v, n."""
    return Rotation.from_matrix(np.asarray(frame).T)


@dataclass(frozen=True)
class Deformation:
    """A keyframed cylindrical deformation (see the module docstring).

    Attributes
    ----------
    keyframes : tuple of Keyframe
        At least two, consecutive positions distinct.
    pad : tuple of 2 float
        Extra length before ``s = 0`` and after ``s = L`` (physical units), extended along the end normals.
    spacing : tuple of 3 float
        Voxel spacing of the scan the deformation belongs to (for conversions from and to voxel coordinates).
    origin : tuple of 3 float
        Physical position of voxel (0, 0, 0) of that scan.
    unit : str or None
        Length unit of every physical quantity.
    """

    keyframes: tuple[Keyframe, ...]
    pad: tuple[float, float] = (0.0, 0.0)
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    unit: str | None = None
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        kfs = tuple(self.keyframes)
        if len(kfs) < 2:
            raise InvalidInputError(f"a deformation needs at least 2 keyframes, got {len(kfs)}")
        if not all(isinstance(k, Keyframe) for k in kfs):
            raise InvalidInputError("keyframes must be Keyframe objects")
        object.__setattr__(self, "keyframes", kfs)
        pos = np.array([k.position for k in kfs])
        seg = np.linalg.norm(np.diff(pos, axis=0), axis=1)
        if (seg <= 1e-9).any():
            i = int(np.argmax(seg <= 1e-9))
            raise InvalidInputError(f"keyframes {i} and {i + 1} are at the same position {pos[i].tolist()}")
        pad = tuple(float(p) for p in np.broadcast_to(np.asarray(self.pad, dtype=float), (2,)))
        if not all(np.isfinite(p) and p >= 0 for p in pad):
            raise InvalidInputError(f"padding must be >= 0 at both ends, got {self.pad!r}")
        object.__setattr__(self, "pad", pad)
        object.__setattr__(self, "spacing", check_spacing(self.spacing))
        origin = tuple(float(o) for o in np.broadcast_to(np.asarray(self.origin, dtype=float), (3,)))
        if not all(np.isfinite(o) for o in origin):
            raise InvalidInputError(f"the origin must be 3 finite numbers, got {self.origin!r}")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "unit", normalise_unit(self.unit))

    # ------------------------------------------------------------------------------------------------------------
    # constructors
    # ------------------------------------------------------------------------------------------------------------
    @classmethod
    def from_keyframes(
        cls,
        positions: np.ndarray,
        frames: np.ndarray,
        half_extents: np.ndarray | Sequence[float] | float,
        *,
        pad: Sequence[float] | float = 0.0,
        spacing: Sequence[float] | float = 1.0,
        origin: Sequence[float] | float = 0.0,
        unit: str | None = None,
        offsets: np.ndarray | Sequence[float] | float = 0.0,
    ) -> Deformation:
        """Build from arrays.

        Parameters
        ----------
        positions : ndarray, shape (m, 3)
            Keyframe centres, physical units.
        frames : ndarray, shape (m, 3, 3)
            Rows ``u, v, n`` per keyframe.
        half_extents : float, (2,) or (m, 2)
            Cage half-sizes ``(rx, ry)``, physical units; one pair for all or one per keyframe.
        pad, spacing, origin, unit
            See the class attributes.
        offsets : float, (2,) or (m, 2)
            Cage centre offsets ``(ox, oy)`` in the cross-section planes (default 0), see :class:`Keyframe`.
        """
        positions = np.asarray(positions, dtype=float)
        frames = np.asarray(frames, dtype=float)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise InvalidInputError(f"positions must have shape (m, 3), got {positions.shape}")
        if frames.shape != (len(positions), 3, 3):
            raise InvalidInputError(f"frames must have shape ({len(positions)}, 3, 3), got {frames.shape}")
        he = np.broadcast_to(np.asarray(half_extents, dtype=float), (len(positions), 2))
        off = np.broadcast_to(np.asarray(offsets, dtype=float), (len(positions), 2))
        kfs = tuple(Keyframe(p, f, tuple(h), tuple(o)) for p, f, h, o in zip(positions, frames, he, off, strict=True))
        return cls(kfs, pad=pad, spacing=spacing, origin=origin, unit=unit)

    @classmethod
    def from_polyline(
        cls,
        points: np.ndarray,
        *,
        spacing: Sequence[float] | float,
        cage_half_extent: Sequence[float] | float,
        up: Sequence[float] | None = None,
        origin: Sequence[float] | float = 0.0,
        unit: str | None = None,
        pad: Sequence[float] | float = 0.0,
    ) -> Deformation:
        """Keyframes at the points of a polyline, with parallel-transported frames.

        Parameters
        ----------
        points : ndarray, shape (K, 3)
            Curve points in array index order (axis0, axis1, axis2), in **voxels** of the scan.
        spacing : float or sequence of 3 float
            Voxel spacing of the scan.
        cage_half_extent : float or (2,)
            Cage half-sizes ``(rx, ry)``, physical units.
        up : sequence of 3 float, optional
            World direction (array axis order) the first frame's ``v`` should follow.
        origin, unit, pad
            See the class attributes.
        """
        sp = np.asarray(check_spacing(spacing))
        org = np.broadcast_to(np.asarray(origin, dtype=float), (3,))
        pts = np.asarray(points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InvalidInputError(f"points must have shape (K, 3) in voxel coordinates, got {pts.shape}")
        phys = pts * sp + org
        frames = parallel_transport_frames(phys, up=up)
        return cls.from_keyframes(phys, frames, cage_half_extent, pad=pad, spacing=tuple(sp), origin=tuple(org),
                                  unit=unit)

    # ------------------------------------------------------------------------------------------------------------
    # derived quantities (cached: the object is immutable)
    # ------------------------------------------------------------------------------------------------------------
    @property
    def positions(self) -> np.ndarray:
        """Keyframe centres, shape (m, 3)."""
        if "pos" not in self._cache:
            self._cache["pos"] = np.array([k.position for k in self.keyframes])
        return self._cache["pos"]

    @property
    def frames(self) -> np.ndarray:
        """Keyframe frames, shape (m, 3, 3), rows u, v, n."""
        if "frames" not in self._cache:
            self._cache["frames"] = np.array([k.frame for k in self.keyframes])
        return self._cache["frames"]

    @property
    def half_extents(self) -> np.ndarray:
        """Keyframe cage half-sizes, shape (m, 2)."""
        return np.array([k.half_extent for k in self.keyframes])

    @property
    def offsets(self) -> np.ndarray:
        """Keyframe cage centre offsets ``(ox, oy)``, shape (m, 2)."""
        return np.array([k.offset for k in self.keyframes])

    @property
    def bounds(self) -> np.ndarray:
        """Keyframe cage sides ``(x_lo, x_hi, y_lo, y_hi)``, shape (m, 4)."""
        return np.array([k.bounds for k in self.keyframes])

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """The union of the cages over ``s``: ``(x_lo, x_hi, y_lo, y_hi)`` (the sides are linear between keyframes,
        so their extremes are at keyframes)."""
        b = self.bounds
        return (float(b[:, 0].min()), float(b[:, 1].max()), float(b[:, 2].min()), float(b[:, 3].max()))

    @property
    def knots(self) -> np.ndarray:
        """Arclength ``d_i`` of each keyframe, shape (m,), ``d_0 = 0``."""
        if "knots" not in self._cache:
            seg = np.linalg.norm(np.diff(self.positions, axis=0), axis=1)
            self._cache["knots"] = np.concatenate([[0.0], np.cumsum(seg)])
        return self._cache["knots"]

    @property
    def length(self) -> float:
        """Curve length ``L`` (without padding)."""
        return float(self.knots[-1])

    @property
    def s_range(self) -> tuple[float, float]:
        """The arclength interval the straight box covers, padding included."""
        return (-self.pad[0], self.length + self.pad[1])

    @property
    def max_half_extent(self) -> tuple[float, float]:
        """The largest ``|x|`` and ``|y|`` any cage reaches (for a centred cage, the largest half-extents)."""
        x0, x1, y0, y1 = self.extent
        return (max(-x0, x1), max(-y0, y1))

    def __len__(self) -> int:
        return len(self.keyframes)

    def _slerp(self) -> Slerp:
        if "slerp" not in self._cache:
            self._cache["slerp"] = Slerp(self.knots, Rotation.concatenate([_rotation(k.frame) for k in self.keyframes]))
        return self._cache["slerp"]

    def _segment_rates(self) -> np.ndarray:
        """Per segment k, the SLERP angular velocity in the local frame: log(R_k^-1 R_{k+1}) / (d_{k+1} - d_k)."""
        if "rates" not in self._cache:
            rots = [_rotation(k.frame) for k in self.keyframes]
            dd = np.diff(self.knots)
            self._cache["rates"] = np.array(
                [(rots[k].inv() * rots[k + 1]).as_rotvec() / dd[k] for k in range(len(dd))]
            )
        return self._cache["rates"]

    def segment_of(self, s: np.ndarray) -> np.ndarray:
        """Index k of the segment ``[d_k, d_{k+1}]`` holding each ``s`` (clamped to the end segments)."""
        return np.clip(np.searchsorted(self.knots, np.asarray(s, dtype=float), side="right") - 1, 0, len(self) - 2)

    # ------------------------------------------------------------------------------------------------------------
    # evaluation
    # ------------------------------------------------------------------------------------------------------------
    def sample(self, s: np.ndarray | Sequence[float] | float) -> tuple[np.ndarray, np.ndarray]:
        """Centre and frame at arclengths ``s``.

        Parameters
        ----------
        s : array_like, shape (K,)
            Arclengths; values below 0 or above ``L`` extend the end keyframes along their normals (padding).

        Returns
        -------
        centres : ndarray, shape (K, 3)
        frames : ndarray, shape (K, 3, 3)
            Rows u, v, n.
        """
        s = np.atleast_1d(np.asarray(s, dtype=float))
        if not np.isfinite(s).all():
            raise InvalidInputError("arclengths must be finite")
        knots = self.knots
        sc = np.clip(s, 0.0, knots[-1])
        frames = self._slerp()(sc).as_matrix().transpose(0, 2, 1)  # columns -> rows (u, v, n)
        k = self.segment_of(sc)
        d0, d1 = knots[k], knots[k + 1]
        lam = ((sc - d0) / (d1 - d0))[:, None]
        pos = self.positions
        centres = (1 - lam) * pos[k] + lam * pos[k + 1]
        before, after = s < 0, s > knots[-1]
        if before.any():
            centres[before] = pos[0] + s[before, None] * self.frames[0, 2]
        if after.any():
            centres[after] = pos[-1] + (s[after, None] - knots[-1]) * self.frames[-1, 2]
        return centres, frames

    def half_extent_at(self, s: np.ndarray | float) -> np.ndarray:
        """Cage half-sizes ``(rx, ry)`` at arclengths ``s`` (linear between keyframes), shape (K, 2)."""
        s = np.clip(np.atleast_1d(np.asarray(s, dtype=float)), 0, self.length)
        he = self.half_extents
        return np.stack([np.interp(s, self.knots, he[:, 0]), np.interp(s, self.knots, he[:, 1])], axis=1)

    def offset_at(self, s: np.ndarray | float) -> np.ndarray:
        """Cage centre offsets ``(ox, oy)`` at arclengths ``s`` (linear between keyframes), shape (K, 2)."""
        s = np.clip(np.atleast_1d(np.asarray(s, dtype=float)), 0, self.length)
        off = self.offsets
        return np.stack([np.interp(s, self.knots, off[:, 0]), np.interp(s, self.knots, off[:, 1])], axis=1)

    def bounds_at(self, s: np.ndarray | float) -> np.ndarray:
        """Cage sides ``(x_lo, x_hi, y_lo, y_hi)`` at arclengths ``s``, shape (K, 4)."""
        he, off = self.half_extent_at(s), self.offset_at(s)
        return np.stack([off[:, 0] - he[:, 0], off[:, 0] + he[:, 0], off[:, 1] - he[:, 1], off[:, 1] + he[:, 1]],
                        axis=1)

    def forward(self, xys: np.ndarray) -> np.ndarray:
        """Map straight coordinates to the bent scan: ``f(x, y, s) = c(s) + x u(s) + y v(s)``.

        Parameters
        ----------
        xys : ndarray, shape (N, 3)
            ``(x, y, s)`` per point, physical units.

        Returns
        -------
        ndarray, shape (N, 3)
            Physical positions in the scan (array axis order).
        """
        xys = np.asarray(xys, dtype=float)
        if xys.ndim != 2 or xys.shape[1] != 3:
            raise InvalidInputError(f"straight points must have shape (N, 3) as (x, y, s), got {xys.shape}")
        c, r = self.sample(xys[:, 2])
        return c + xys[:, :1] * r[:, 0] + xys[:, 1:2] * r[:, 1]

    def inverse(self, points: np.ndarray, *, max_iter: int = 20, tol: float = 1e-9) -> InverseResult:
        """Map points of the bent scan to straight coordinates ``(x, y, s)``.

        For each point the candidate cross-sections are seeded from the nearest points of the centre polyline
        (the three nearest segments, and both padded ends); Newton steps then solve
        ``g(s) = (p - c(s)) . n(s) = 0`` with the exact derivative of the SLERP frame, and the candidate whose
        cross-section holds the point nearest the curve wins.

        Parameters
        ----------
        points : ndarray, shape (N, 3)
            Physical positions in the scan (array axis order).
        max_iter : int
            Newton steps at most.
        tol : float
            Stop when ``|g| < tol`` (physical units).

        Returns
        -------
        InverseResult
        """
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise InvalidInputError(f"points must have shape (N, 3), got {p.shape}")
        n_pts = len(p)
        knots = self.knots
        pos = self.positions
        lo, hi = self.s_range
        # segments: the real ones plus the two padded end pieces (straight lines along the end normals)
        starts = np.vstack([pos[0] - self.pad[0] * self.frames[0, 2], pos[:-1], pos[-1]])
        ends = np.vstack([pos[0], pos[1:], pos[-1] + self.pad[1] * self.frames[-1, 2]])
        s0 = np.concatenate([[lo], knots[:-1], [knots[-1]]])
        s1 = np.concatenate([[0.0], knots[1:], [hi]])
        valid = (s1 - s0) > 1e-12
        starts, ends, s0, s1 = starts[valid], ends[valid], s0[valid], s1[valid]
        seg = ends - starts
        seg_len2 = np.einsum("ij,ij->i", seg, seg)
        best = np.full((n_pts, 3), np.nan)
        best_res = np.full(n_pts, np.inf)
        best_r = np.full(n_pts, np.inf)
        n_cand = min(3, len(seg))
        # distance from every point to every segment, in blocks to bound memory
        block = max(1, 2_000_000 // max(1, len(seg)))
        for b0 in range(0, n_pts, block):
            pb = p[b0:b0 + block]
            t = np.clip(np.einsum("pij,ij->pi", pb[:, None, :] - starts[None], seg) / seg_len2, 0, 1)
            closest = starts[None] + t[..., None] * seg[None]
            dist = np.linalg.norm(pb[:, None, :] - closest, axis=2)
            order = np.argsort(dist, axis=1)[:, :n_cand]
            for c in range(n_cand):
                idx = order[:, c]
                s_init = s0[idx] + t[np.arange(len(pb)), idx] * (s1[idx] - s0[idx])
                xys, res = self._newton(pb, s_init, max_iter=max_iter, tol=tol)
                r = np.hypot(xys[:, 0], xys[:, 1])
                ok = np.isfinite(r) & (res < 1e-6 * max(1.0, self.length)) & (r < best_r[b0:b0 + block])
                sl = slice(b0, b0 + len(pb))
                best[sl][ok] = xys[ok]
                best_res[sl][ok] = res[ok]
                best_r[sl][ok] = r[ok]
        b = self.bounds_at(np.nan_to_num(best[:, 2]))
        with np.errstate(invalid="ignore"):
            inside = (
                np.isfinite(best[:, 2])
                & (best[:, 2] >= lo - 1e-9)
                & (best[:, 2] <= hi + 1e-9)
                & (best[:, 0] >= b[:, 0] - 1e-9) & (best[:, 0] <= b[:, 1] + 1e-9)
                & (best[:, 1] >= b[:, 2] - 1e-9) & (best[:, 1] <= b[:, 3] + 1e-9)
            )
        return InverseResult(best, inside, np.where(np.isfinite(best_res), best_res, np.nan))

    def _newton(self, p: np.ndarray, s: np.ndarray, *, max_iter: int, tol: float) -> tuple[np.ndarray, np.ndarray]:
        """Solve (p - c(s)) . n(s) = 0 from ``s``; returns (x, y, s) and the residual |f(x, y, s) - p|."""
        lo, hi = self.s_range
        s = s.astype(float).copy()
        knots = self.knots
        rates = self._segment_rates()
        seg_dir = np.diff(self.positions, axis=0) / np.diff(knots)[:, None]
        for _ in range(max_iter):
            c, r = self.sample(s)
            d = p - c
            n = r[:, 2]
            g = np.einsum("ij,ij->i", d, n)
            if np.all(np.abs(g) < tol):
                break
            inside_curve = (s >= 0) & (s <= knots[-1])
            k = self.segment_of(s)
            # c'(s): the segment direction inside, the end normal in the padding
            dc = np.where(inside_curve[:, None], seg_dir[k], r[:, 2])
            # n'(s) = R(s) (w x e_z) inside (SLERP at constant rate w), zero in the padding
            w = np.where(inside_curve[:, None], rates[k], 0.0)
            local = np.stack([w[:, 1], -w[:, 0], np.zeros(len(w))], axis=1)  # w x e_z
            dn = np.einsum("kji,kj->ki", r, local)  # R(s) @ local, with r holding rows u, v, n
            dg = -np.einsum("ij,ij->i", dc, n) + np.einsum("ij,ij->i", d, dn)
            step = np.where(np.abs(dg) > 1e-12, g / np.where(np.abs(dg) > 1e-12, dg, 1.0), 0.0)
            s = np.clip(s - step, lo, hi)
        c, r = self.sample(s)
        d = p - c
        x = np.einsum("ij,ij->i", d, r[:, 0])
        y = np.einsum("ij,ij->i", d, r[:, 1])
        res = np.linalg.norm(c + x[:, None] * r[:, 0] + y[:, None] * r[:, 1] - p, axis=1)
        return np.stack([x, y, s], axis=1), res

    # ------------------------------------------------------------------------------------------------------------
    # validity
    # ------------------------------------------------------------------------------------------------------------
    def jacobian_min(self, s: np.ndarray) -> np.ndarray:
        """Smallest Jacobian determinant of ``f`` over the cage's cross-section at each ``s`` (shape (K,)).

        With a linear centre and a SLERP frame of rate ``w`` (local) on a segment,
        ``det J(x, y, s) = n . c' + (y w_x - x w_y)``, smallest at a corner of the cage
        ``[x_lo, x_hi] x [y_lo, y_hi]``. It is 1 for a straight cage and reaches 0 where the cage's inner side
        reaches the local centre of curvature: there the map folds.
        """
        s = np.atleast_1d(np.asarray(s, dtype=float))
        sc = np.clip(s, 0, self.length)
        _, r = self.sample(sc)
        k = self.segment_of(sc)
        seg_dir = np.diff(self.positions, axis=0) / np.diff(self.knots)[:, None]
        w = self._segment_rates()[k]
        b = self.bounds_at(sc)
        base = np.einsum("ij,ij->i", r[:, 2], seg_dir[k])
        det = (base + np.minimum(b[:, 2] * w[:, 0], b[:, 3] * w[:, 0])
               - np.maximum(b[:, 0] * w[:, 1], b[:, 1] * w[:, 1]))
        outside = (s < 0) | (s > self.length)
        return np.where(outside, 1.0, det)

    def jacobian(self, xys: np.ndarray) -> np.ndarray:
        """The Jacobian determinant of ``f`` at straight points ``(x, y, s)`` (shape (N, 3)): ``n . c' + y w_x - x w_y``
        inside the curve's arclength, 1 in the padding (a translation along the end normals)."""
        xys = np.asarray(xys, dtype=float)
        if xys.ndim != 2 or xys.shape[1] != 3:
            raise InvalidInputError(f"straight points must have shape (N, 3) as (x, y, s), got {xys.shape}")
        s = xys[:, 2]
        sc = np.clip(np.nan_to_num(s), 0, self.length)
        _, r = self.sample(sc)
        k = self.segment_of(sc)
        seg_dir = np.diff(self.positions, axis=0) / np.diff(self.knots)[:, None]
        w = self._segment_rates()[k]
        det = np.einsum("ij,ij->i", r[:, 2], seg_dir[k]) + xys[:, 1] * w[:, 0] - xys[:, 0] * w[:, 1]
        return np.where((s < 0) | (s > self.length), 1.0, det)

    def folds(self, *, threshold: float = 0.0, step: float | None = None) -> list[tuple[float, float]]:
        """Arclength intervals where the map folds (the cage is larger than the local radius of curvature).

        Parameters
        ----------
        threshold : float
            Report where the smallest Jacobian determinant is ``<= threshold`` (0: strict folding; e.g. 0.2 to
            warn where the cage is compressed to a fifth).
        step : float, optional
            Sampling step in arclength (default: a tenth of the finest spacing).

        Returns
        -------
        list of (s_start, s_end)
        """
        step = step or min(self.spacing) / 10
        s = np.union1d(np.arange(0.0, self.length, step), self.knots)
        bad = self.jacobian_min(s) <= threshold
        intervals = []
        i = 0
        while i < len(s):
            if bad[i]:
                j = i
                while j + 1 < len(s) and bad[j + 1]:
                    j += 1
                intervals.append((float(s[max(i - 1, 0)] if i else s[i]), float(s[min(j + 1, len(s) - 1)])))
                i = j + 1
            else:
                i += 1
        return intervals

    # ------------------------------------------------------------------------------------------------------------
    # straight output grid
    # ------------------------------------------------------------------------------------------------------------
    def output_shape(self, spacing: float | None = None) -> tuple[int, int, int]:
        """Shape (Ns, Ny, Nx) of the straight volume at isotropic ``spacing`` (default: finest scan spacing).

        Raises :class:`InvalidInputError` when a side would exceed ``2**62`` voxels (a spacing absurdly small for
        the deformation's size), so that the shape's product stays a number that can be reported.
        """
        return self._grid(spacing)[0]

    def grid_centre(self, spacing: float | None = None) -> tuple[int, int]:
        """Pixel ``(row, column)`` of the straight grid at ``x = 0, y = 0`` (the curve): ``y = (i - row) ds`` and
        ``x = (j - column) ds``. The grid covers the union of the cages over ``s`` with the curve on a pixel
        centre; for centred cages the curve is the middle pixel, ``((Ny - 1) / 2, (Nx - 1) / 2)``."""
        return self._grid(spacing)[1]

    def _grid(self, spacing: Any) -> tuple[tuple[int, int, int], tuple[int, int]]:
        ds = self._ds(spacing)
        lo, hi = self.s_range
        x0, x1, y0, y1 = self.extent
        sides = ((hi - lo) / ds, max(-y0, 0.0) / ds, max(y1, 0.0) / ds, max(-x0, 0.0) / ds, max(x1, 0.0) / ds)
        if not all(math.isfinite(v) and v < 2**61 for v in sides):
            rx, ry = self.max_half_extent
            raise InvalidInputError(
                f"output spacing {ds!r} is absurdly small for this deformation (length {hi - lo:.6g}, cage half "
                f"extents {rx:.6g} x {ry:.6g} {unit_label(self.unit)}): the straight grid would have about "
                f"{sides[0]:.3g} x {sides[1] + sides[2]:.3g} x {sides[3] + sides[4]:.3g} voxels; choose a spacing "
                f"near the scan's ({min(self.spacing):g})"
            )
        n = [int(math.ceil(v - 1e-9)) for v in sides[1:]]
        return ((int(math.floor(sides[0] + 1e-9)) + 1, n[0] + n[1] + 1, n[2] + n[3] + 1), (n[0], n[2]))

    def _ds(self, spacing: Any) -> float:
        """The output spacing ``ds``: ``spacing`` checked (a finite positive number), default the finest scan's."""
        if spacing is None:
            return float(min(self.spacing))
        try:
            if isinstance(spacing, (bool, str, bytes)):
                raise TypeError
            ds = float(spacing)
        except (TypeError, ValueError):
            raise InvalidInputError(f"output spacing must be a positive number, got {spacing!r}") from None
        if not (math.isfinite(ds) and ds > 0):
            raise InvalidInputError(f"output spacing must be finite and positive, got {spacing!r}")
        return ds

    def slice_geometry(self, spacing: float | None = None, *, voxels: bool = True
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per output slice k, the affine map of its pixels: ``p(k, i, j) = base_k + i dv_k + j du_k``.

        This is the whole deformation as the resamplers (and the GL shader) see it: 9 numbers per slice.

        Parameters
        ----------
        spacing : float, optional
            Output spacing ``ds`` (default: finest scan spacing).
        voxels : bool
            Express the result in voxel coordinates of the scan (``(p - origin) / spacing``); else physical.

        Returns
        -------
        base : ndarray, shape (Ns, 3)
            Position of pixel (i, j) = (0, 0) of each slice.
        dv : ndarray, shape (Ns, 3)
            Step for one row (``+ds`` along v).
        du : ndarray, shape (Ns, 3)
            Step for one column (``+ds`` along u).
        """
        ds = self._ds(spacing)
        (ns, _, _), (i0, j0) = self._grid(ds)
        s = self.s_range[0] + ds * np.arange(ns)
        c, r = self.sample(s)
        base = c - i0 * ds * r[:, 1] - j0 * ds * r[:, 0]
        dv = ds * r[:, 1]
        du = ds * r[:, 0]
        if voxels:
            sp = np.asarray(self.spacing)
            base = (base - np.asarray(self.origin)) / sp
            dv = dv / sp
            du = du / sp
        return base, dv, du

    # ------------------------------------------------------------------------------------------------------------
    # edits: each returns a new Deformation
    # ------------------------------------------------------------------------------------------------------------
    def _with(self, keyframes: Sequence[Keyframe], **changes: Any) -> Deformation:
        return replace(self, keyframes=tuple(keyframes), **changes)

    def _check_index(self, i: int) -> int:
        if not -len(self) <= i < len(self):
            raise InvalidInputError(f"keyframe index {i} is out of range (there are {len(self)} keyframes)")
        return i % len(self)

    def add_keyframe(self, s: float) -> Deformation:
        """Insert a keyframe at arclength ``s`` (0 < s < L) on the current curve; the map does not change."""
        s = float(s)
        if not 0 < s < self.length:
            raise InvalidInputError(f"a keyframe can be added at 0 < s < {self.length:g}, got s={s:g}")
        if np.min(np.abs(self.knots - s)) < 1e-9 * max(1.0, self.length):
            raise InvalidInputError(f"there is a keyframe at s={s:g} already; edit it instead")
        c, r = self.sample([s])
        he = tuple(self.half_extent_at(s)[0])
        off = tuple(self.offset_at(s)[0])
        k = int(self.segment_of([s])[0])
        kfs = list(self.keyframes)
        kfs.insert(k + 1, Keyframe(c[0], r[0], he, off))
        return self._with(kfs)

    def index_at(self, s: float) -> int:
        """Index of the keyframe at arclength ``s``; one is inserted by :meth:`add_keyframe` when needed."""
        d = np.abs(self.knots - float(s))
        i = int(np.argmin(d))
        if d[i] > 1e-9 * max(1.0, self.length):
            raise InvalidInputError(f"no keyframe at s={s:g}; add one first (add_keyframe)")
        return i

    def delete_keyframe(self, i: int) -> Deformation:
        """Remove keyframe ``i`` (at least two remain)."""
        i = self._check_index(i)
        if len(self) <= 2:
            raise InvalidInputError("a deformation needs at least 2 keyframes; this one cannot lose another")
        kfs = list(self.keyframes)
        del kfs[i]
        return self._with(kfs)

    def move_keyframe(self, i: int, dx: float, dy: float) -> Deformation:
        """Move keyframe ``i``'s centre within its cross-section plane by ``dx`` along u and ``dy`` along v."""
        i = self._check_index(i)
        k = self.keyframes[i]
        kfs = list(self.keyframes)
        kfs[i] = Keyframe(k.position + float(dx) * k.u + float(dy) * k.v, k.frame, k.half_extent, k.offset)
        return self._with(kfs)

    def twist_keyframe(self, i: int, angle: float) -> Deformation:
        """Rotate keyframe ``i``'s u and v about n by ``angle`` radians (counter-clockwise seen from the tail)."""
        return self._rotate(i, 2, angle)

    def tilt_keyframe(self, i: int, angle: float, *, axis: str = "u") -> Deformation:
        """Rotate keyframe ``i``'s frame about its ``u`` or ``v`` axis by ``angle`` radians (tilts n)."""
        if axis not in ("u", "v"):
            raise InvalidInputError(f"tilt axis must be 'u' or 'v', got {axis!r}")
        return self._rotate(i, 0 if axis == "u" else 1, angle)

    def _rotate(self, i: int, about: int, angle: float) -> Deformation:
        i = self._check_index(i)
        k = self.keyframes[i]
        rot = Rotation.from_rotvec(float(angle) * k.frame[about]).as_matrix()
        kfs = list(self.keyframes)
        kfs[i] = Keyframe(k.position, (rot @ k.frame.T).T, k.half_extent, k.offset)
        return self._with(kfs)

    def set_frame(self, i: int, frame: np.ndarray) -> Deformation:
        """Replace keyframe ``i``'s frame (rows u, v, n)."""
        i = self._check_index(i)
        k = self.keyframes[i]
        kfs = list(self.keyframes)
        kfs[i] = Keyframe(k.position, frame, k.half_extent, k.offset)
        return self._with(kfs)

    def resize_keyframe(self, i: int | None, half_extent: Sequence[float] | float) -> Deformation:
        """Set the cage half-sizes ``(rx, ry)`` of keyframe ``i`` (``None``: of every keyframe), keeping the cage
        centre offsets."""
        idx = range(len(self)) if i is None else [self._check_index(i)]
        kfs = list(self.keyframes)
        he = tuple(np.broadcast_to(np.asarray(half_extent, dtype=float), (2,)))
        for j in idx:
            kfs[j] = Keyframe(kfs[j].position, kfs[j].frame, he, kfs[j].offset)
        return self._with(kfs)

    def set_cage(self, i: int | None, bounds: Sequence[float]) -> Deformation:
        """Set the cage sides ``(x_lo, x_hi, y_lo, y_hi)`` of keyframe ``i`` (``None``: of every keyframe)."""
        idx = range(len(self)) if i is None else [self._check_index(i)]
        kfs = list(self.keyframes)
        for j in idx:
            kfs[j] = Keyframe.from_bounds(kfs[j].position, kfs[j].frame, bounds)
        return self._with(kfs)

    def with_pad(self, before: float, after: float) -> Deformation:
        """Extend the straight box by ``before`` ahead of the head and ``after`` past the tail (physical)."""
        return replace(self, pad=(before, after))

    # ------------------------------------------------------------------------------------------------------------
    # points in voxels
    # ------------------------------------------------------------------------------------------------------------
    def to_physical(self, voxels: np.ndarray) -> np.ndarray:
        """Voxel coordinates of the scan (N, 3) -> physical positions (N, 3)."""
        return np.asarray(voxels, dtype=float) * np.asarray(self.spacing) + np.asarray(self.origin)

    def to_voxels(self, physical: np.ndarray) -> np.ndarray:
        """Physical positions (N, 3) -> voxel coordinates of the scan (N, 3)."""
        return (np.asarray(physical, dtype=float) - np.asarray(self.origin)) / np.asarray(self.spacing)

    # ------------------------------------------------------------------------------------------------------------
    # serialisation
    # ------------------------------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict (see :data:`SCHEMA`)."""
        return {
            "schema": SCHEMA,
            "unit": self.unit,
            "spacing": list(self.spacing),
            "origin": list(self.origin),
            "pad": list(self.pad),
            "keyframes": [k.to_dict() for k in self.keyframes],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Deformation:
        """Inverse of :meth:`to_dict`; raises :class:`InvalidInputError` on anything malformed."""
        from . import _json

        if not isinstance(d, dict) or d.get("schema") not in (SCHEMA, *OLD_SCHEMAS):
            got = d.get("schema") if isinstance(d, dict) else type(d).__name__
            raise InvalidInputError(f"not a deformation of schema {SCHEMA!r} (got {_json.short(got)})")

        # types, required fields and bounds (napari_unwind/schemas/deformation.schema.json), as plain JSON
        d = _json.validate(d, "deformation", root="deformation", prefix="malformed deformation: ",
                           hint="correct that value, or make the deformation again")
        if d["schema"] != SCHEMA and any("offset" in k for k in d["keyframes"]):
            raise InvalidInputError(f"a deformation of schema {d['schema']!r} has no cage offsets, but this one has; "
                                    f"label it {SCHEMA!r}")
        try:
            kfs = tuple(Keyframe.from_dict(k) for k in d["keyframes"])
            return cls(kfs, pad=tuple(d.get("pad", (0, 0))), spacing=tuple(d["spacing"]),
                       origin=tuple(d.get("origin", (0, 0, 0))), unit=d.get("unit"))
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InvalidInputError):
                raise
            raise InvalidInputError(f"malformed deformation: {exc!r}") from None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Deformation):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(repr(self.to_dict()))

    def __repr__(self) -> str:
        return (f"Deformation({len(self)} keyframes, length={self.length:.4g} {unit_label(self.unit)}, "
                f"pad={self.pad}, cage={self.extent})")
