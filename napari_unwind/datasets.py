"""Synthetic specimens with exact ground truth: a bent cylinder, a bent and twisted fish, a tank of fish, and a
family of hard specimens drawn from a seed (tight S-bends, coils, helices: :func:`hard_fish_phantom`).

These phantoms are the embedded sample of ``unwind demo``, napari's sample data and the reference of every
accuracy test. Each one is built from an analytic density defined in *straight* coordinates and an analytic
deformation, so the straight ground truth is exact and does not depend on any straightening code of the
project.

Conventions
-----------
Bent volume
    An array of shape (N0, N1, N2) in array index order (axis0, axis1, axis2). Voxel index ``p`` sits at the
    physical position ``p * spacing`` (origin 0). Lengths are in ``unit`` (``"micrometer"``).
Deformation
    The straight box maps to the bent scan by ``f(x, y, s) = c(s) + x u(s) + y v(s)`` with ``s`` the arclength
    along the centreline in ``[0, L]`` (physical units, head at ``s = 0``). The frame ``(u, v, n)`` is
    orthonormal and right-handed (``u x v = n``) with ``n = dc/ds``. In the fish phantoms ``v`` points DORSAL
    (towards the dorsal fin) and ``u`` is lateral. Frames are unit vectors in physical space, components in
    array axis order.
Twist
    The frame is the parallel-transport (rotation-minimising) frame of the centreline, rotated about ``n`` by
    the twist angle ``theta(s)``: ``u = cos(theta) u_pt + sin(theta) v_pt``, ``v = -sin(theta) u_pt +
    cos(theta) v_pt``. ``theta(0) = 0`` and ``theta(L)`` is the total twist; :attr:`Phantom.twist` holds it
    along the centreline. The head frame of the fish has ``v`` as close as possible to ``-axis1`` ("up" in a
    napari slice view), turned about ``n`` by ``roll``.
Straight ground truth
    Shape (Ns, Ny, Nx) with isotropic spacing ``ds`` (default: the finest input spacing). Voxel ``(k, i, j)``
    is the point ``s = k ds``, ``y = (i - (Ny - 1) / 2) ds``, ``x = (j - (Nx - 1) / 2) ds``: axis0 is ``s``
    (head at ``k = 0``), axis1 is ``y`` (dorsal towards larger ``i``), axis2 is ``x``. ``Ns = floor(L / ds) + 1``,
    ``Ny = 2 ceil(ry / ds) + 1`` and ``Nx = 2 ceil(rx / ds) + 1`` with the cage half extent ``(rx, ry)`` that
    holds the whole specimen, fin included.
Values (uint16)
    background ~100, flesh ~1000, spine ~2500, fin ~900, tube wall ~1800. Noise (Gaussian, slightly smoothed)
    is added to the bent ``volume`` only; ``straight_volume`` is noise-free and holds the specimen alone.
    A voxel is in a mask iff the specimen fills at least half of it (the soft edge's midpoint).
Layout
    The cylinder runs along axis2 (the paper's experiment). Fish run along axis0 as in a scanner tube; the
    tube wall is a cylinder around an axis parallel to axis0 and clears every fish (and, for a single fish,
    its whole cage), so straightening the noise-free volume reproduces ``straight_volume``. In a tank the
    heads may point either way along axis0; ``head``/``tail`` say which.

Rendering
---------
Each bent voxel near the curve is mapped to straight coordinates by the nearest point of the centreline:
nearest knot of a dense arclength-uniform polyline (``cKDTree``), then Newton steps on
``(p - c(s)) . c'(s) = 0`` with the analytic derivatives of the arclength cubic spline ``c``, then
``x = (p - c) . u`` and ``y = (p - c) . v``. The map is unique because the curve's radius of curvature is
checked to stay larger than the cage (``rx |u.k| + ry |v.k| < 0.9`` with ``k`` the curvature vector, so the
map does not fold) and the curve never comes back near itself. Points whose
``s`` falls outside ``[0, L]`` are outside the body. The hard phantoms bend tighter than their cage and come
back near themselves: there every foot of each voxel on the curve is found (the curve cut into pieces that
turn by at most 60 degrees) and only the body, not its cage, is checked not to fold or overlap itself.
Partial volume at the surfaces comes from an approximate
signed distance (soft edge one voxel wide); the masks are the exact indicator evaluated at voxel centres.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import dask.array as da
import numpy as np
from scipy import ndimage
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .errors import InvalidInputError, finite_number
from .io._volume import Volume, check_spacing

__all__ = [
    "AIR_HU",
    "BACKGROUND",
    "BodyScan",
    "CURVES",
    "FIN",
    "FLESH",
    "HARD_KINDS",
    "HARD_SPACINGS",
    "HardTank",
    "SPINE",
    "TUBE",
    "UNIT",
    "WATER_LIFT",
    "Phantom",
    "Tank",
    "air_tank_phantom",
    "body_phantom",
    "cylinder_phantom",
    "fish_phantom",
    "hard_fish_phantom",
    "hard_tank_phantom",
    "tank_phantom",
]

#: Intensities of the phantoms (uint16 grey values).
BACKGROUND = 100
FLESH = 1000
SPINE = 2500
FIN = 900
TUBE = 1800
#: The length unit of every phantom.
UNIT = "micrometer"
#: Names of the built-in fish centrelines.
CURVES = ("s-bend", "c-bend", "helix")

_FOLD_LIMIT = 0.9  # max of (rx |u.k| + ry |v.k|): the cage stays 10 % inside the radius of curvature
_UP = np.array([0.0, -1.0, 0.0])  # "up" in a napari slice: towards smaller axis1


# ------------------------------------------------------------------------------------------------------------------
# the result types
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Phantom:
    """A synthetic specimen with its exact ground truth (plain arrays, see the module docstring).

    Attributes
    ----------
    name : str
        ``"cylinder"``, ``"fish"`` or ``"tank-fish-<i>"``.
    volume : ndarray of uint16, shape (N0, N1, N2)
        The bent scan (with noise if asked). For a fish of a tank it is the whole tank volume (shared).
    mask : ndarray of bool, shape (N0, N1, N2)
        The specimen (body, fin and spine) in the bent volume.
    spacing : tuple of 3 float
        Voxel size along axis0, axis1, axis2, in ``unit``.
    unit : str
        ``"micrometer"``.
    centerline : ndarray of float, shape (K, 3)
        Dense samples of ``c(s)`` in voxel index coordinates, head first, uniform in ``s``.
    centerline_physical : ndarray of float, shape (K, 3)
        The same points in physical units (``centerline * spacing``).
    arclength : ndarray of float, shape (K,)
        ``s`` of each sample, from 0 to ``length``.
    frames : ndarray of float, shape (K, 3, 3)
        ``frames[k]`` has the rows ``u, v, n`` (physical unit vectors, array axis order) at sample ``k``.
    twist : ndarray of float, shape (K,)
        The twist angle (radians) about ``n`` relative to the parallel-transport frame.
    length : float
        ``L``, the arclength of the centreline in ``unit``.
    half_extent : tuple of 2 float
        The cage half extent ``(rx, ry)`` in ``unit``: the specimen lies in ``|x| <= rx, |y| <= ry``.
    straight_spacing : float
        ``ds``, the isotropic spacing of the straight ground truth.
    straight_volume : ndarray of uint16, shape (Ns, Ny, Nx)
        The noise-free specimen density on the straight grid (this specimen only, no tube, no neighbours).
    straight_mask : ndarray of bool, shape (Ns, Ny, Nx)
        The specimen on the straight grid.
    head, tail : ndarray of float, shape (3,)
        Voxel index coordinates of ``c(0)`` and ``c(L)``.
    tube_radii : tuple of 2 float or None
        Inner and outer radius of the tube wall (physical), None without a tube.
    tube_center : tuple of 2 float or None
        Physical (axis1, axis2) position of the tube axis, which is parallel to axis0.
    seed : int or None
        The seed of the noise (and of the random layout for a tank).
    mask_arclength : ndarray of float32, shape (N0, N1, N2), or None
        Hard phantoms only: the arclength ``s`` of the centreline point each mask voxel belongs to (NaN outside
        the mask), to tell the turns of a coil apart.
    info : dict or None
        Hard phantoms only: what was drawn and measured (see :func:`hard_fish_phantom`).
    """

    name: str
    volume: np.ndarray
    mask: np.ndarray
    spacing: tuple[float, float, float]
    unit: str
    centerline: np.ndarray
    centerline_physical: np.ndarray
    arclength: np.ndarray
    frames: np.ndarray
    twist: np.ndarray
    length: float
    half_extent: tuple[float, float]
    straight_spacing: float
    straight_volume: np.ndarray
    straight_mask: np.ndarray
    head: np.ndarray
    tail: np.ndarray
    tube_radii: tuple[float, float] | None = None
    tube_center: tuple[float, float] | None = None
    seed: int | None = None
    mask_arclength: np.ndarray | None = None
    info: dict[str, Any] | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        """Shape of the bent volume."""
        return tuple(int(n) for n in self.volume.shape)  # type: ignore[return-value]

    @property
    def straight_shape(self) -> tuple[int, int, int]:
        """Shape (Ns, Ny, Nx) of the straight ground truth."""
        return tuple(int(n) for n in self.straight_volume.shape)  # type: ignore[return-value]

    def straight_grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The straight coordinates of the ground-truth grid.

        Returns
        -------
        s : ndarray, shape (Ns,)
        y : ndarray, shape (Ny,)
        x : ndarray, shape (Nx,)
            Physical coordinates of the grid lines along axis0, axis1 and axis2 of ``straight_volume``.
        """
        ns, ny, nx = self.straight_shape
        ds = self.straight_spacing
        return np.arange(ns) * ds, (np.arange(ny) - (ny - 1) / 2) * ds, (np.arange(nx) - (nx - 1) / 2) * ds

    def straight_to_bent(self, points_xys: Any, *, physical: bool = False) -> np.ndarray:
        """Map straight coordinates to positions in the bent volume: ``f(x, y, s) = c(s) + x u(s) + y v(s)``.

        Uses the stored dense centreline and frames, interpolated linearly along ``s`` (the frame is
        re-orthonormalised), so it only needs the plain arrays of this object.

        Parameters
        ----------
        points_xys : array_like, shape (..., 3)
            Straight coordinates ``(x, y, s)`` in physical units.
        physical : bool
            Return physical positions instead of voxel index coordinates.

        Returns
        -------
        ndarray, shape (..., 3)
            Bent positions in array axis order.
        """
        pts = np.asarray(points_xys, dtype=float)
        if pts.shape[-1:] != (3,):
            raise InvalidInputError(f"points_xys must have shape (..., 3) holding (x, y, s), got {pts.shape}")
        flat = pts.reshape(-1, 3)
        x, y, s = flat[:, 0], flat[:, 1], flat[:, 2]
        c, u, v, _ = _interpolate_frames(self.arclength, self.centerline_physical, self.frames, s)
        out = c + x[:, None] * u + y[:, None] * v
        if not physical:
            out = out / np.asarray(self.spacing)
        return out.reshape(pts.shape)

    def __repr__(self) -> str:
        return (
            f"Phantom(name={self.name!r}, shape={self.shape}, spacing={self.spacing}, unit={self.unit!r}, "
            f"length={self.length:.4g}, twist={float(self.twist[-1]):.4g}, half_extent="
            f"({self.half_extent[0]:.4g}, {self.half_extent[1]:.4g}), straight_shape={self.straight_shape})"
        )

    def to_volume(self) -> Volume:
        """The bent scan as a :class:`napari_unwind.io.Volume` (dask-backed, with spacing and unit)."""
        return Volume(
            data=da.from_array(self.volume, chunks=(64, 128, 128)),
            spacing=self.spacing,
            unit=self.unit,
            source=f"napari_unwind.datasets:{self.name}",
            format=None,
            metadata={"phantom": self.name, "seed": self.seed},
        )

    def layer_data(self) -> list[tuple[np.ndarray, dict[str, Any], str]]:
        """napari layer data tuples (image and mask labels) with scale and units; no napari import."""
        meta = {"scale": self.spacing, "units": (self.unit,) * 3, "axis_labels": ("z", "y", "x")}
        return [
            (self.volume, {"name": self.name, "colormap": "gray", **meta}, "image"),
            (self.mask.astype(np.uint8), {"name": f"{self.name} mask", "opacity": 0.4, **meta}, "labels"),
        ]


@dataclass(frozen=True, eq=False)
class Tank:
    """Several fish in one tube, each with its ground truth in the tank's coordinates.

    Attributes
    ----------
    volume : ndarray of uint16, shape (N0, N1, N2)
        The scan of the tank.
    labels : ndarray of int32, shape (N0, N1, N2)
        0 for background (tube included), ``i + 1`` for the voxels of fish ``i``.
    fish : tuple of Phantom
        One ground truth per fish; ``fish[i].mask == (labels == i + 1)`` and ``fish[i].volume is volume``.
    spacing : tuple of 3 float
    unit : str
    tube_radii : tuple of 2 float
        Inner and outer radius of the tube wall (physical units).
    tube_center : tuple of 2 float
        Physical (axis1, axis2) position of the tube axis (parallel to axis0).
    min_distance : float
        The smallest distance between voxel centres of two different fish, in voxel index units (inf for one
        fish).
    seed : int or None
    """

    volume: np.ndarray
    labels: np.ndarray
    fish: tuple[Phantom, ...]
    spacing: tuple[float, float, float]
    unit: str
    tube_radii: tuple[float, float]
    tube_center: tuple[float, float]
    min_distance: float
    seed: int | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.volume.shape)  # type: ignore[return-value]

    def __repr__(self) -> str:
        return (
            f"Tank(n_fish={len(self.fish)}, shape={self.shape}, spacing={self.spacing}, unit={self.unit!r}, "
            f"tube_radii=({self.tube_radii[0]:.4g}, {self.tube_radii[1]:.4g}), "
            f"min_distance={self.min_distance:.3g})"
        )

    def to_volume(self) -> Volume:
        """The tank scan as a :class:`napari_unwind.io.Volume`."""
        return Volume(
            data=da.from_array(self.volume, chunks=(64, 128, 128)),
            spacing=self.spacing,
            unit=self.unit,
            source="napari_unwind.datasets:tank",
            format=None,
            metadata={"phantom": "tank", "n_fish": len(self.fish), "seed": self.seed},
        )

    def layer_data(self) -> list[tuple[np.ndarray, dict[str, Any], str]]:
        """napari layer data tuples (image and fish labels) with scale and units; no napari import."""
        meta = {"scale": self.spacing, "units": (self.unit,) * 3, "axis_labels": ("z", "y", "x")}
        return [
            (self.volume, {"name": "tank", "colormap": "gray", **meta}, "image"),
            (self.labels, {"name": "tank fish", "opacity": 0.4, **meta}, "labels"),
        ]


# ------------------------------------------------------------------------------------------------------------------
# validation helpers
# ------------------------------------------------------------------------------------------------------------------
def _positive(name: str, value: Any, *, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        need = "zero or positive" if allow_zero else "positive"
        raise InvalidInputError(f"{name} must be finite and {need}, got {value!r}")
    return v


def _shape3(shape: Any) -> tuple[int, int, int]:
    try:
        vals = tuple(int(n) for n in shape)
        ok = len(vals) == 3 and all(float(n) == int(n) for n in shape)
    except (TypeError, ValueError):
        ok = False
    if not ok or min(vals) < 8:
        raise InvalidInputError(f"shape must be 3 integers >= 8 (axis0, axis1, axis2), got {shape!r}")
    return vals  # type: ignore[return-value]


def _seed(seed: Any) -> int | None:
    if seed is None:
        return None
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidInputError(f"seed must be a non-negative integer or None, got {seed!r}")
    return int(seed)


# ------------------------------------------------------------------------------------------------------------------
# the curve: arclength cubic spline, parallel transport frame, twist
# ------------------------------------------------------------------------------------------------------------------
def _rotate_about(u: np.ndarray, v: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotate the pair (u, v) about n = u x v by theta (right-hand rule)."""
    ct, st = np.cos(theta)[..., None], np.sin(theta)[..., None]
    return ct * u + st * v, -st * u + ct * v


def _interpolate_frames(
    arclength: np.ndarray, points: np.ndarray, frames: np.ndarray, s: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation of a dense centreline and its frames at ``s``; frames re-orthonormalised."""
    s = np.asarray(s, dtype=float)
    idx = np.clip(np.searchsorted(arclength, s) - 1, 0, len(arclength) - 2)
    s0, s1 = arclength[idx], arclength[idx + 1]
    lam = ((s - s0) / (s1 - s0))[:, None]
    c = (1 - lam) * points[idx] + lam * points[idx + 1]
    fr = (1 - lam[:, :, None]) * frames[idx] + lam[:, :, None] * frames[idx + 1]
    n = fr[:, 2] / np.linalg.norm(fr[:, 2], axis=1, keepdims=True)
    v = fr[:, 1] - np.sum(fr[:, 1] * n, axis=1, keepdims=True) * n
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    u = np.cross(v, n)
    return c, u, v, n


class _Curve:
    """A smooth centreline parametrised by arclength, with its twisted parallel-transport frame.

    ``fn(t)`` (vectorised, returns (N, 3) physical points) is sampled densely for ``t`` in ``[t0, t1]``; with
    ``length`` given the curve is scaled about the origin so that its arclength is exactly ``length``. The
    curve proper is the cubic spline through knots spaced ``h`` apart in arclength.
    """

    def __init__(
        self,
        fn: Callable[[np.ndarray], np.ndarray],
        t0: float,
        t1: float,
        *,
        h: float,
        length: float | None = None,
        twist: float = 0.0,
        roll: float = 0.0,
        up: np.ndarray = _UP,
    ) -> None:
        t = np.linspace(t0, t1, 40001)
        pts = np.asarray(fn(t), dtype=float)
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        if not cum[-1] > 0:
            raise InvalidInputError("the centreline has zero length; give control points that are not all equal")
        scale = 1.0 if length is None else float(length) / cum[-1]
        self.length = L = float(cum[-1] * scale)
        k = max(int(np.ceil(L / h)), 8) + 1
        self.h = L / (k - 1)
        self.knots_s = np.linspace(0.0, L, k)
        tk = np.interp(self.knots_s / scale, cum, t)
        self.knots = np.asarray(fn(tk), dtype=float) * scale
        self._build(twist, roll, up)

    def _build(self, twist: float, roll: float, up: np.ndarray) -> None:
        self.C = CubicSpline(self.knots_s, self.knots, axis=0)
        self.dC = self.C.derivative(1)
        self.ddC = self.C.derivative(2)
        n = self.dC(self.knots_s)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        # head frame: v as close as possible to "up", then turned by roll about n
        v0 = up - np.dot(up, n[0]) * n[0]
        if np.linalg.norm(v0) < 1e-3:  # the head points along "up": take another axis
            alt = np.array([1.0, 0.0, 0.0])
            v0 = alt - np.dot(alt, n[0]) * n[0]
        v0 /= np.linalg.norm(v0)
        u0 = np.cross(v0, n[0])
        _, v0 = _rotate_about(u0, v0, np.asarray(roll))
        # parallel transport of v by the double reflection method (Wang et al. 2008)
        x = self.knots
        vs = np.empty_like(x)
        vs[0] = v0
        for i in range(len(x) - 1):
            d1 = x[i + 1] - x[i]
            c1 = d1 @ d1
            rl = vs[i] - (2.0 / c1) * (d1 @ vs[i]) * d1
            tl = n[i] - (2.0 / c1) * (d1 @ n[i]) * d1
            d2 = n[i + 1] - tl
            c2 = d2 @ d2
            r = rl - (2.0 / c2) * (d2 @ rl) * d2 if c2 > 1e-30 else rl
            r -= (r @ n[i + 1]) * n[i + 1]
            vs[i + 1] = r / np.linalg.norm(r)
        self.V = CubicSpline(self.knots_s, vs, axis=0)
        self.total_twist = float(twist)
        self._make_tree()

    def _make_tree(self) -> None:
        # a coarser copy of the knots (about 4 h apart) is enough to seed Newton and queries faster
        self._tree_step = step = max(1, min(4, (len(self.knots_s) - 1) // 8))
        self.tree = cKDTree(self.knots[::step])

    def translated(self, shift: np.ndarray) -> _Curve:
        """The same curve moved by ``shift`` (physical); frames and twist unchanged."""
        new = object.__new__(_Curve)
        new.__dict__.update(self.__dict__)
        new.knots = self.knots + np.asarray(shift, dtype=float)
        new.C = CubicSpline(self.knots_s, new.knots, axis=0)
        new.dC = new.C.derivative(1)
        new.ddC = new.C.derivative(2)
        new._make_tree()
        return new

    def theta(self, s: np.ndarray) -> np.ndarray:
        """The twist angle at ``s``: smooth, 0 at the head and ``total_twist`` at the tail."""
        sig = np.clip(np.asarray(s, dtype=float) / self.length, 0.0, 1.0)
        return self.total_twist * 0.5 * (1.0 - np.cos(np.pi * sig))

    def frames(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``u, v, n`` (each (N, 3)) at arclengths ``s`` (N,), twist included."""
        s = np.asarray(s, dtype=float)
        n = self.dC(s)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        v = self.V(s)
        v -= np.sum(v * n, axis=1, keepdims=True) * n
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        u = np.cross(v, n)
        u, v = _rotate_about(u, v, self.theta(s))
        return u, v, n

    def curvature(self, s: np.ndarray) -> np.ndarray:
        """Curvature vectors (N, 3) at ``s``."""
        d1, d2 = self.dC(s), self.ddC(s)
        sp2 = np.sum(d1 * d1, axis=1, keepdims=True)
        t = d1 / np.sqrt(sp2)
        return (d2 - np.sum(d2 * t, axis=1, keepdims=True) * t) / sp2

    def cage_corners(self, rx: float, ry: float) -> np.ndarray:
        """Corners of the cage cross-sections at every knot, shape (4 * K, 3), physical."""
        u, v, _ = self.frames(self.knots_s)
        c = self.C(self.knots_s)
        return np.concatenate([c + a * rx * u + b * ry * v for a in (-1, 1) for b in (-1, 1)])

    def check_no_fold(self, rx: float, ry: float, spacing: Sequence[float], what: str) -> None:
        """Raise InvalidInputError where the cage of half extent (rx, ry) would fold or touch itself."""
        s = self.knots_s
        u, v, _ = self.frames(s)
        k = self.curvature(s)
        load = rx * np.abs(np.sum(u * k, axis=1)) + ry * np.abs(np.sum(v * k, axis=1))
        worst = int(np.argmax(load))
        if load[worst] >= _FOLD_LIMIT:
            kappa = float(np.linalg.norm(k[worst]))
            radius = 1.0 / kappa if kappa > 0 else np.inf
            where = np.round(self.C(s[worst]) / np.asarray(spacing), 1)
            raise InvalidInputError(
                f"{what}: the centreline bends too sharply for the body: its radius of curvature is "
                f"{radius:.3g} at s = {s[worst]:.3g} (voxel {tuple(where.tolist())}) but the cross-section "
                f"reaches {max(rx, ry):.3g} from the centreline, so the straightening map would fold there; "
                "use a gentler curve (smaller bends, larger length) or a thinner body"
            )
        reach = 2.0 * float(np.hypot(rx, ry))
        pairs = cKDTree(self.knots).query_pairs(reach, output_type="ndarray")
        if len(pairs):
            gap = np.abs(s[pairs[:, 0]] - s[pairs[:, 1]])
            bad = gap > np.pi * reach / 2.0
            if np.any(bad):
                i, j = pairs[np.argmax(np.where(bad, gap, -1.0))]
                raise InvalidInputError(
                    f"{what}: the centreline comes back within {reach:.3g} of itself (s = {s[i]:.3g} and "
                    f"s = {s[j]:.3g}), so two parts of the body would overlap; spread the curve out or use a "
                    "thinner body"
                )

    def project(self, p: np.ndarray, bound: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Straight coordinates of physical points ``p`` (N, 3) within ``bound`` of the knots.

        Returns ``sel`` (indices of the points within reach whose Newton iteration converged) and their
        ``x, y, s``.
        """
        d, idx = self.tree.query(p, k=1, distance_upper_bound=bound, workers=-1)
        sel = np.flatnonzero(np.isfinite(d))
        p = p[sel]
        s = self.knots_s[:: self._tree_step][idx[sel]]
        lo, hi = -2.0 * self.h, self.length + 2.0 * self.h
        for _ in range(5):
            r = p - self.C(s)
            d1, d2 = self.dC(s), self.ddC(s)
            g = np.sum(r * d1, axis=1)
            gp = np.sum(r * d2, axis=1) - np.sum(d1 * d1, axis=1)
            step = np.where(gp < -0.05, -g / np.minimum(gp, -0.05), g)
            lim = (self._tree_step + 1) * self.h
            s = np.clip(s + np.clip(step, -lim, lim), lo, hi)
        r = p - self.C(s)
        u, v, n = self.frames(s)
        resid = np.abs(np.sum(r * n, axis=1))
        ok = resid < 1e-6 * max(1.0, self.h)
        # points past the ends (s clipped) do not converge: they are outside the body anyway
        return sel[ok], np.sum(r * u, axis=1)[ok], np.sum(r * v, axis=1)[ok], s[ok]


# ------------------------------------------------------------------------------------------------------------------
# the bodies: analytic densities in straight coordinates
# ------------------------------------------------------------------------------------------------------------------
def _soft(sd: np.ndarray, w: float) -> np.ndarray:
    """Partial-volume occupancy of a voxel of size w at signed distance sd (negative inside)."""
    return np.clip(0.5 - sd / w, 0.0, 1.0)


def _ellipse_sd(x: np.ndarray, y: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """First-order signed distance to the ellipse (x/a)^2 + (y/b)^2 = 1 (exact sign)."""
    q = (x / a) ** 2 + (y / b) ** 2
    grad = 2.0 * np.sqrt((x / a**2) ** 2 + (y / b**2) ** 2)
    return (q - 1.0) / np.maximum(grad, 1e-9)


class _Cylinder:
    """A round cylinder of radius r along s in [0, L], flat ends."""

    kind = "cylinder"

    def __init__(self, length: float, radius: float, pad: float) -> None:
        self.L, self.r = float(length), float(radius)
        self.rx = self.ry = self.r + pad
        self.ext = self.r

    def evaluate(self, x: np.ndarray, y: np.ndarray, s: np.ndarray, w: float) -> tuple[np.ndarray, np.ndarray]:
        sd = np.maximum(np.hypot(x, y) - self.r, np.maximum(-s, s - self.L))
        return (BACKGROUND + (FLESH - BACKGROUND) * _soft(sd, w)).astype(np.float32), sd <= 0


class _Fish:
    """A fish body: tapered elliptic cross-section, dorsal fin on +y, spine rod nearer the dorsal side."""

    kind = "fish"
    aspect = 0.6  # half width / half height
    head_frac, head_tip = 0.2, 0.3  # rounded head over the first 20 % of L, blunt tip at 30 % of R
    tail_start, tail_tip = 0.45, 0.25  # tapering from 45 % of L to 25 % of R at the tail
    fin_range, fin_height = (0.3, 0.65), 0.6  # dorsal fin (fraction of L) and its height (fraction of R)
    spine_range, spine_offset, spine_radius = (0.04, 0.96), 0.3, 0.14

    def __init__(self, length: float, radius: float, voxel: float, pad: float) -> None:
        self.L, self.R = float(length), float(radius)
        self.fin_half = max(0.12 * self.R, voxel)  # at least two voxels thick
        self.spine_min = 0.6 * voxel
        sig = np.linspace(0.0, 1.0, 2001)
        b = self.half_height(sig)
        top = self.fin_top(sig, b)
        self.ext = float(np.max(np.hypot(self.fin_half, np.maximum(b, top))))
        self.rx = float(max(self.aspect * b.max(), self.fin_half) + pad)
        self.ry = float(np.max(np.maximum(b, top)) + pad)

    def half_height(self, sig: np.ndarray) -> np.ndarray:
        sig = np.clip(sig, 0.0, 1.0)
        hf, b0, ts, b1 = self.head_frac, self.head_tip, self.tail_start, self.tail_tip
        z = np.clip(1.0 - sig / hf, 0.0, 1.0)
        head = np.sqrt(b0**2 + (1.0 - b0**2) * (1.0 - z**2))
        tau = np.clip((sig - ts) / (1.0 - ts), 0.0, 1.0)
        tail = b1 + (1.0 - b1) * 0.5 * (1.0 + np.cos(np.pi * tau))
        return self.R * head * tail

    def fin_top(self, sig: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Top of the dorsal fin (y), -inf outside the fin."""
        f0, f1 = self.fin_range
        tau = (sig - f0) / (f1 - f0)
        a = self.aspect * b
        base = b * np.sqrt(np.clip(1.0 - (self.fin_half / a) ** 2, 0.0, 1.0))  # ellipse height at |x| = fin_half
        h = (b - base + self.fin_height * self.R) * np.sin(np.pi * np.clip(tau, 0.0, 1.0))
        return np.where((tau > 0) & (tau < 1), base + h, -np.inf)

    def evaluate(self, x: np.ndarray, y: np.ndarray, s: np.ndarray, w: float) -> tuple[np.ndarray, np.ndarray]:
        sig = s / self.L
        b = self.half_height(sig)
        a = self.aspect * b
        cap = np.maximum(-s, s - self.L)
        sd_body = np.maximum(_ellipse_sd(x, y, a, b), cap)
        top = self.fin_top(sig, b)
        sd_fin = np.maximum.reduce([np.abs(x) - self.fin_half, -y, y - top, cap])
        f0, f1 = self.spine_range
        rs = np.clip(self.spine_radius * b, self.spine_min, None)
        sd_spine = np.maximum.reduce([np.hypot(x, y - self.spine_offset * b) - rs, f0 * self.L - s, s - f1 * self.L])
        # the material (fin, flesh, spine) blended by partial volume, then faded into the background by the
        # occupancy of the whole specimen: a voxel is in the mask iff that occupancy is >= 0.5
        o_fin = _soft(sd_fin, w) * (1.0 - _soft(sd_body, w))
        o_body = _soft(sd_body, w)
        weight = o_fin + o_body
        material = np.where(weight > 0, (FIN * o_fin + FLESH * o_body) / np.maximum(weight, 1e-12), FLESH)
        material += (SPINE - material) * _soft(sd_spine, w)
        sd_all = np.minimum(np.minimum(sd_body, sd_fin), sd_spine)
        val = BACKGROUND + (material - BACKGROUND) * _soft(sd_all, w)
        return val.astype(np.float32), sd_all <= 0


# ------------------------------------------------------------------------------------------------------------------
# rendering
# ------------------------------------------------------------------------------------------------------------------
def _render_into(
    excess: np.ndarray,
    mask: np.ndarray,
    curve: _Curve,
    body: _Cylinder | _Fish,
    spacing: tuple[float, float, float],
) -> None:
    """Add the body's density above background to ``excess`` and its indicator to ``mask`` (in place)."""
    sp = np.asarray(spacing)
    corners = curve.cage_corners(body.rx, body.ry)
    lo = np.maximum(np.floor(corners.min(axis=0) / sp).astype(int) - 2, 0)
    hi = np.minimum(np.ceil(corners.max(axis=0) / sp).astype(int) + 3, np.asarray(excess.shape))
    if np.any(hi <= lo):
        return
    grids = [np.arange(lo[d], hi[d]) * sp[d] for d in range(3)]
    p = np.stack(np.meshgrid(*grids, indexing="ij"), axis=-1).reshape(-1, 3)
    bound = body.ext + 2.0 * float(sp.max()) + curve.h
    sel, x, y, s = curve.project(p, bound)
    val, inside = body.evaluate(x, y, s, float(np.mean(sp)))
    box = tuple(slice(lo[d], hi[d]) for d in range(3))
    sub_shape = tuple(hi - lo)
    sub = np.zeros(int(np.prod(sub_shape)), dtype=np.float32)
    sub[sel] = val - BACKGROUND
    excess[box] += sub.reshape(sub_shape)
    msub = np.zeros(sub.shape, dtype=bool)
    msub[sel] = inside
    mask[box] |= msub.reshape(sub_shape)


def _straight_truth(body: _Cylinder | _Fish, ds: float) -> tuple[np.ndarray, np.ndarray]:
    ns = int(np.floor(body.L / ds + 1e-9)) + 1
    ny = 2 * int(np.ceil(body.ry / ds - 1e-9)) + 1
    nx = 2 * int(np.ceil(body.rx / ds - 1e-9)) + 1
    s = np.arange(ns) * ds
    y = (np.arange(ny) - (ny - 1) / 2) * ds
    x = (np.arange(nx) - (nx - 1) / 2) * ds
    S, Y, X = np.meshgrid(s, y, x, indexing="ij")
    val, inside = body.evaluate(X, Y, S, ds)
    return np.round(val).astype(np.uint16), inside


def _tube_excess(
    shape: tuple[int, int, int], spacing: Sequence[float], center: tuple[float, float], r_in: float, r_out: float
) -> np.ndarray:
    """Excess density of the tube wall in one (axis1, axis2) plane, shape (N1, N2)."""
    y = np.arange(shape[1]) * spacing[1] - center[0]
    x = np.arange(shape[2]) * spacing[2] - center[1]
    rho = np.hypot(y[:, None], x[None, :])
    sd = np.maximum(r_in - rho, rho - r_out)
    return ((TUBE - BACKGROUND) * _soft(sd, float(np.mean(spacing[1:])))).astype(np.float32)


def _finish(clean: np.ndarray, noise: float, seed: int | None) -> np.ndarray:
    """Add slightly smoothed Gaussian noise of standard deviation ``noise`` and convert to uint16."""
    if noise > 0:
        rng = np.random.default_rng(seed)
        g = rng.standard_normal(clean.shape, dtype=np.float32)
        g = ndimage.gaussian_filter(g, sigma=0.7, output=np.float32)
        g *= noise / max(float(g.std()), 1e-12)
        clean = clean + g
    return np.clip(np.round(clean), 0, np.iinfo(np.uint16).max).astype(np.uint16)


def _phantom(
    name: str,
    volume: np.ndarray,
    mask: np.ndarray,
    curve: _Curve,
    body: _Cylinder | _Fish,
    spacing: tuple[float, float, float],
    ds: float,
    *,
    tube: tuple[tuple[float, float], tuple[float, float]] | None,
    seed: int | None,
    straight: tuple[np.ndarray, np.ndarray] | None = None,
) -> Phantom:
    sp = np.asarray(spacing)
    k = int(np.ceil(curve.length / (0.5 * sp.min()))) + 1
    s = np.linspace(0.0, curve.length, k)
    c = curve.C(s)
    u, v, n = curve.frames(s)
    sv, sm = straight if straight is not None else _straight_truth(body, ds)
    return Phantom(
        name=name,
        volume=volume,
        mask=mask,
        spacing=tuple(float(a) for a in spacing),  # type: ignore[arg-type]
        unit=UNIT,
        centerline=c / sp,
        centerline_physical=c,
        arclength=s,
        frames=np.stack([u, v, n], axis=1),
        twist=curve.theta(s),
        length=float(curve.length),
        half_extent=(float(body.rx), float(body.ry)),
        straight_spacing=float(ds),
        straight_volume=sv,
        straight_mask=sm,
        head=c[0] / sp,
        tail=c[-1] / sp,
        tube_radii=None if tube is None else tube[0],
        tube_center=None if tube is None else tube[1],
        seed=seed,
    )


def _check_fits(corners: np.ndarray, shape: Sequence[int], spacing: np.ndarray, what: str) -> None:
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    size = (np.asarray(shape) - 1) * spacing
    if np.any(lo < 0) or np.any(hi > size):
        need = np.ceil((hi - lo) / spacing).astype(int) + 1
        raise InvalidInputError(
            f"{what} does not fit in a volume of shape {tuple(int(n) for n in shape)}: it needs at least "
            f"{tuple(need.tolist())} voxels; give a larger shape (or shape=None), a shorter length or a smaller "
            "bend"
        )


def _straight_spacing(straight_spacing: Any, spacing: tuple[float, float, float]) -> float:
    if straight_spacing is None:
        return float(min(spacing))
    return _positive("straight_spacing", straight_spacing)


# ------------------------------------------------------------------------------------------------------------------
# public constructors
# ------------------------------------------------------------------------------------------------------------------
def cylinder_phantom(
    *,
    shape: Sequence[int] = (64, 64, 160),
    radius: float = 6.0,
    amplitude: float = 12.0,
    wavelength: float | None = None,
    spacing: float | Sequence[float] = 1.0,
    noise: float = 0.0,
    seed: int | None = 0,
    straight_spacing: float | None = None,
) -> Phantom:
    """A round cylinder bent along a sine wave in a plane (the paper's synthetic experiment).

    The centreline runs along axis2 at the middle of axis0 and is displaced along axis1 by
    ``amplitude * sin(2 pi t / wavelength)``; the cylinder's ends are cut perpendicular to it. The straight
    ground truth is a straight cylinder of the same radius and length.

    Parameters
    ----------
    shape : tuple of 3 int
        Shape (N0, N1, N2) of the bent volume.
    radius : float
        Cylinder radius, physical units.
    amplitude : float
        Sine amplitude along axis1, physical units (0 gives a straight cylinder).
    wavelength : float, optional
        Sine wavelength along axis2, physical units. Default: the length of the curve along axis2 (one full
        period).
    spacing : float or tuple of 3 float
        Voxel size (axis0, axis1, axis2).
    noise : float
        Standard deviation of the added noise (grey values), 0 for none.
    seed : int or None
        Seed of the noise.
    straight_spacing : float, optional
        Spacing ``ds`` of the straight ground truth; default the finest of ``spacing``.

    Returns
    -------
    Phantom
        ``volume`` (uint16, shape ``shape``): background 100, cylinder 1000.

    Raises
    ------
    InvalidInputError
        For a non-positive radius, a shape too small for the cylinder, or a bend sharper than the radius.
    """
    shape = _shape3(shape)
    radius = _positive("radius", radius)
    amplitude = _positive("amplitude", amplitude, allow_zero=True)
    spacing = check_spacing(spacing)
    noise = _positive("noise", noise, allow_zero=True)
    seed = _seed(seed)
    ds = _straight_spacing(straight_spacing, spacing)
    sp = np.asarray(spacing)
    pad = 2.0 * float(sp.max())
    body_r = radius + pad
    margin = body_r + 2.0 * float(sp[2])
    t0, t1 = margin, (shape[2] - 1) * sp[2] - margin
    if t1 - t0 <= 2 * radius:
        raise InvalidInputError(
            f"shape {shape} is too short along axis2 for a cylinder of radius {radius}: make axis2 longer than "
            f"{int(np.ceil(2 * margin / sp[2] + 2 * radius / sp[2]))} voxels or the radius smaller"
        )
    wl = (t1 - t0) if wavelength is None else _positive("wavelength", wavelength)
    c0 = (shape[0] - 1) * sp[0] / 2.0
    c1 = (shape[1] - 1) * sp[1] / 2.0

    def fn(t: np.ndarray) -> np.ndarray:
        return np.stack([np.full_like(t, c0), c1 + amplitude * np.sin(2.0 * np.pi * (t - t0) / wl), t], axis=-1)

    curve = _Curve(fn, t0, t1, h=0.25 * float(sp.min()))
    body = _Cylinder(curve.length, radius, pad)
    curve.check_no_fold(body.rx, body.ry, spacing, "cylinder_phantom")
    _check_fits(curve.cage_corners(body.rx, body.ry), shape, sp, f"a cylinder of radius {radius} bent by {amplitude}")
    excess = np.zeros(shape, dtype=np.float32)
    mask = np.zeros(shape, dtype=bool)
    _render_into(excess, mask, curve, body, spacing)
    excess += BACKGROUND
    volume = _finish(excess, noise, seed)
    return _phantom("cylinder", volume, mask, curve, body, spacing, ds, tube=None, seed=seed)


def _named_curve(name: str) -> Callable[[np.ndarray], np.ndarray]:
    """Unit-scale centrelines along axis0 (sigma in [0, 1]); scaled to the fish length afterwards."""
    if name == "s-bend":
        return lambda t: np.stack([t, 0.045 * np.sin(np.pi * t), 0.09 * np.sin(2 * np.pi * t)], axis=-1)
    if name == "c-bend":
        phi = 1.5  # the arc turns by 1.5 rad, plus a small out-of-plane wave
        return lambda t: np.stack(
            [np.sin(phi * (t - 0.5)) / phi, 0.03 * np.sin(2 * np.pi * t), (1 - np.cos(phi * (t - 0.5))) / phi],
            axis=-1,
        )
    if name == "helix":
        rho, w = 0.05, 2 * np.pi * 1.25  # 1.25 turns around axis0
        return lambda t: np.stack([t, rho * np.cos(w * t) - rho, rho * np.sin(w * t)], axis=-1)
    raise InvalidInputError(f"curve must be one of {', '.join(CURVES)} or an (M, 3) array, got {name!r}")


def _control_point_curve(points: np.ndarray, spacing: np.ndarray) -> tuple[Callable, float, float]:
    """A C2 spline through control points (voxel index coordinates), chord-length parametrised."""
    phys = points * spacing
    chord = np.linalg.norm(np.diff(phys, axis=0), axis=1)
    if np.any(chord <= 0):
        raise InvalidInputError("curve control points must be distinct consecutive points")
    t = np.concatenate([[0.0], np.cumsum(chord)])
    if len(points) == 2:
        return (lambda tt: phys[0] + (tt / t[-1])[:, None] * (phys[1] - phys[0])), 0.0, float(t[-1])
    bc = "not-a-knot" if len(points) > 3 else "natural"
    spl = CubicSpline(t, phys, axis=0, bc_type=bc)
    return spl, 0.0, float(t[-1])


def _build_fish(
    *,
    fn: Callable[[np.ndarray], np.ndarray],
    t0: float,
    t1: float,
    length: float | None,
    body_radius: float,
    twist: float,
    roll: float,
    spacing: tuple[float, float, float],
    what: str,
) -> tuple[_Curve, _Fish]:
    sp = np.asarray(spacing)
    curve = _Curve(fn, t0, t1, h=0.25 * float(sp.min()), length=length, twist=twist, roll=roll)
    if length is None and curve.length <= 2 * body_radius:
        raise InvalidInputError(
            f"{what}: the curve is {curve.length:.3g} long, shorter than the body's diameter {2 * body_radius:.3g}"
        )
    body = _Fish(curve.length, body_radius, float(sp.max()), 2.0 * float(sp.max()))
    curve.check_no_fold(body.rx, body.ry, spacing, what)
    return curve, body


def fish_phantom(
    *,
    length: float | None = None,
    curve: str | Any = "s-bend",
    twist: float = np.pi / 2,
    roll: float = 0.0,
    body_radius: float = 8.0,
    noise: float = 40.0,
    tube: bool = True,
    spacing: float | Sequence[float] = 1.0,
    seed: int | None = 0,
    shape: Sequence[int] | None = None,
    straight_spacing: float | None = None,
) -> Phantom:
    """A fish-like specimen bent in 3D along a smooth curve and twisted about it, with its ground truth.

    The body is tapered (rounded blunt head, thin tail) with an elliptic cross-section taller dorsoventrally
    (half width 0.6 of the half height ``body_radius``), a thin dorsal fin (a plate on the +v side over the
    middle of the body), and a dense spine (a rod nearer the dorsal side). Its centreline runs along axis0,
    head at small axis0. With ``tube`` a dense cylindrical tube wall around axis0 surrounds the fish without
    touching it (nor its cage).

    Parameters
    ----------
    length : float, optional
        Arclength ``L`` of the fish, physical units. Default 160 for the named curves; for control points
        the curve's own length (then ``length`` must be None).
    curve : {"s-bend", "c-bend", "helix"} or array_like, shape (M, 3)
        A named centreline, or control points (voxel index coordinates of the bent volume, head first) of
        a C2 cubic spline.
    twist : float
        Total twist (radians) about the centreline from head to tail, distributed smoothly
        (``theta(s) = twist (1 - cos(pi s / L)) / 2``).
    roll : float
        Rotation (radians) of the head frame about the centreline; the dorsal side faces ``-axis1`` at 0.
    body_radius : float
        Largest half height of the body, physical units.
    noise : float
        Standard deviation of the added noise (grey values), 0 for none.
    tube : bool
        Draw a tube wall around axis0.
    spacing : float or tuple of 3 float
        Voxel size (axis0, axis1, axis2).
    seed : int or None
        Seed of the noise.
    shape : tuple of 3 int, optional
        Shape of the bent volume. Default: just large enough for the fish and the tube (167 x 75 x 75 for
        the defaults). A named curve is centred in it. Control points are kept where they are; the tube is
        then centred in the volume and may be cut by its sides.
    straight_spacing : float, optional
        Spacing ``ds`` of the straight ground truth; default the finest of ``spacing``.

    Returns
    -------
    Phantom
        ``volume`` (uint16): background 100, flesh 1000, spine 2500, fin 900, tube 1800, plus noise.

    Raises
    ------
    InvalidInputError
        For invalid numbers, an unknown curve, a fish that does not fit in ``shape``, or a curve whose
        radius of curvature is smaller than the cross-section (the map would fold).
    """
    spacing = check_spacing(spacing)
    sp = np.asarray(spacing)
    body_radius = _positive("body_radius", body_radius)
    twist = finite_number("twist", twist)
    roll = finite_number("roll", roll)
    noise = _positive("noise", noise, allow_zero=True)
    seed = _seed(seed)
    ds = _straight_spacing(straight_spacing, spacing)
    if shape is not None:
        shape = _shape3(shape)
    named = isinstance(curve, str)
    if named:
        fn = _named_curve(curve)
        length = 160.0 if length is None else _positive("length", length)
        if length <= 2 * body_radius:
            raise InvalidInputError(
                f"length ({length}) must be larger than the body's diameter (2 * body_radius = {2 * body_radius})"
            )
        t0, t1 = 0.0, 1.0
    else:
        pts = np.asarray(curve, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2 or not np.all(np.isfinite(pts)):
            raise InvalidInputError(
                f"curve must be one of {', '.join(CURVES)} or an (M, 3) array of finite control points with "
                f"M >= 2, got an array of shape {pts.shape}"
            )
        if length is not None:
            raise InvalidInputError("give length=None with control points: the curve's own length is used")
        fn, t0, t1 = _control_point_curve(pts, sp)
    what = "fish_phantom"
    crv, body = _build_fish(
        fn=fn,
        t0=t0,
        t1=t1,
        length=length,
        body_radius=body_radius,
        twist=twist,
        roll=roll,
        spacing=spacing,
        what=what,
    )
    corners = crv.cage_corners(body.rx, body.ry)
    gap, wall, margin = 2.0 * sp.max(), 3.0 * sp[1:].max(), 2.0 * sp.max()
    if named:
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        centre = (lo + hi) / 2.0
        if tube:
            r_in = float(np.max(np.hypot(corners[:, 1] - centre[1], corners[:, 2] - centre[2]))) + gap
            half = np.array([(hi[0] - lo[0]) / 2.0 + margin, r_in + wall + margin, r_in + wall + margin])
        else:
            half = (hi - lo) / 2.0 + margin
        if shape is None:
            shape = tuple(int(n) for n in np.ceil(2.0 * half / sp).astype(int) + 1)
        target = (np.asarray(shape) - 1) * sp / 2.0
        crv = crv.translated(target - centre)
        corners = corners + (target - centre)
    elif shape is None:
        hi = corners.max(axis=0)
        shape = tuple(int(n) for n in np.ceil((hi + margin) / sp).astype(int) + 1)
    _check_fits(corners, shape, sp, f"a fish of length {crv.length:.4g} and body radius {body_radius:.4g}")
    excess = np.zeros(shape, dtype=np.float32)
    mask = np.zeros(shape, dtype=bool)
    _render_into(excess, mask, crv, body, spacing)
    tube_info = None
    if tube:
        ctr = ((shape[1] - 1) * sp[1] / 2.0, (shape[2] - 1) * sp[2] / 2.0)
        r_in = float(np.max(np.hypot(corners[:, 1] - ctr[0], corners[:, 2] - ctr[1]))) + gap
        r_out = r_in + wall
        excess += _tube_excess(shape, sp, ctr, r_in, r_out)[None]
        tube_info = ((float(r_in), float(r_out)), (float(ctr[0]), float(ctr[1])))
    excess += BACKGROUND
    volume = _finish(excess, noise, seed)
    return _phantom("fish", volume, mask, crv, body, spacing, ds, tube=tube_info, seed=seed)


# ------------------------------------------------------------------------------------------------------------------
# the tank
# ------------------------------------------------------------------------------------------------------------------
def _random_fish_curve(rng: np.random.Generator, axial: float, amp: float) -> Callable[[np.ndarray], np.ndarray]:
    """A smooth random 3D centreline along axis0 (axial length ``axial``), lateral excursion <= ``amp``."""
    dirs = rng.uniform(0, 2 * np.pi, size=3)
    phases = rng.uniform(0, 2 * np.pi, size=3)
    weights = rng.uniform(0.3, 1.0, size=3) * np.array([1.0, 0.6, 0.25])
    freqs = np.array([0.5, 1.0, 1.5]) * 2 * np.pi  # half, one and one and a half waves along the fish
    t = np.linspace(0.0, 1.0, 512)

    def lateral(tt: np.ndarray) -> np.ndarray:
        acc = np.zeros((len(tt), 2))
        for d, ph, wgt, f in zip(dirs, phases, weights, freqs):
            acc += wgt * np.sin(f * tt + ph)[:, None] * np.array([np.cos(d), np.sin(d)])[None]
        return acc

    lat = lateral(t)
    mean = lat.mean(axis=0)
    scale = amp / max(float(np.max(np.linalg.norm(lat - mean, axis=1))), 1e-12)

    def fn(tt: np.ndarray) -> np.ndarray:
        lt = (lateral(tt) - mean) * scale
        return np.column_stack([tt * axial, lt])

    return fn


def _reversed(fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    """The same curve run the other way (head and tail swapped), for t in [0, 1]."""
    return lambda tt: fn(1.0 - tt)


def _lane_offsets(lanes: np.ndarray, alpha: float) -> np.ndarray:
    """Offsets (n, 3) of the fish for the lattice lanes (n, 2) scaled by alpha."""
    return np.column_stack([np.zeros(len(lanes)), alpha * lanes])


def _hex_lanes(n: int, pitch: float) -> np.ndarray:
    """``n`` points of a triangular lattice of the given pitch, packed around their centre, shape (n, 2)."""
    m = int(np.ceil(np.sqrt(n))) + 2
    ij = np.array([(i, j) for i in range(-m, m + 1) for j in range(-m, m + 1)], dtype=float)
    pts = np.column_stack([ij[:, 0] + 0.5 * ij[:, 1], ij[:, 1] * np.sqrt(3) / 2]) * pitch
    ref = np.array([0.5, np.sqrt(3) / 6]) * pitch  # the centre of a lattice triangle
    order = np.lexsort((pts[:, 1], pts[:, 0], np.round(np.linalg.norm(pts - ref, axis=1), 9)))
    chosen = pts[order[:n]]
    return chosen - (chosen.min(axis=0) + chosen.max(axis=0)) / 2.0


def _boundary_points(mask: np.ndarray) -> np.ndarray:
    edge = mask & ~ndimage.binary_erosion(mask)
    return np.argwhere(edge).astype(float)


def _surface_points(curve: _Curve, mask: np.ndarray, ds: float) -> np.ndarray:
    """Physical positions of the boundary voxels of a straight mask, mapped by the curve's deformation."""
    k, i, j = np.nonzero(mask & ~ndimage.binary_erosion(mask, border_value=0))
    _, ny, nx = mask.shape
    s, y, x = k * ds, (i - (ny - 1) / 2) * ds, (j - (nx - 1) / 2) * ds
    u, v, _ = curve.frames(s)
    return curve.C(s) + x[:, None] * u + y[:, None] * v


def _min_pair_distance(
    trees: Sequence[cKDTree], points: Sequence[np.ndarray], offsets: np.ndarray, reach: np.ndarray, need: float
) -> float:
    """Smallest distance between the point clouds of different fish moved by ``offsets`` (n, 3).

    Distances of ``need`` or more are not resolved: the result is then inf.
    """
    best = np.inf
    n = len(points)
    for i in range(n):
        for j in range(i + 1, n):
            if np.linalg.norm(offsets[i] - offsets[j]) > reach[i] + reach[j] + need:
                continue
            d, _ = trees[i].query(points[j] + (offsets[j] - offsets[i]), k=1, distance_upper_bound=need)
            best = min(best, float(d.min()))
    return best


def tank_phantom(
    *,
    n_fish: int = 3,
    seed: int | None = 0,
    length: float = 140.0,
    body_radius: float = 8.0,
    noise: float = 40.0,
    spacing: float | Sequence[float] = 1.0,
    gap: float = 3.0,
    max_tries: int = 20,
    straight_spacing: float | None = None,
    wall_value: float = TUBE,
    wall_thickness: float = 3.0,
    wall_noise: float = 0.0,
) -> Tank:
    """Several fish, roughly parallel to axis0, packed in one tube; apart, or touching with ``gap=0``.

    Each fish gets its own random smooth 3D bend, twist (uniform in [-pi, pi]), roll, length (within 10 % of
    ``length``), body radius (within 10 % of ``body_radius``), axial offset and head direction (towards smaller
    or larger axis0). The fish are laid in the lanes of a triangular lattice that is then shrunk until the
    closest fish are about ``gap + 2`` voxels apart; the separations are verified on the rendered masks (and
    the layout is drawn again if one fails).

    Parameters
    ----------
    n_fish : int
        Number of fish (>= 1).
    seed : int or None
        Seed of the layout, the fish and the noise.
    length : float
        Typical fish length (arclength), physical units.
    body_radius : float
        Typical largest half height of a fish body, physical units.
    noise : float
        Standard deviation of the added noise (grey values), 0 for none.
    spacing : float or tuple of 3 float
        Voxel size (axis0, axis1, axis2).
    gap : float
        Smallest allowed distance, in voxels (index units), between voxel centres of two fish and between a
        fish and the tube wall. 0: the closest fish touch each other and the wall (surfaces about one voxel
        apart, masks adjacent; the soft edges meet well above the background).
    max_tries : int
        Layouts drawn before giving up.
    straight_spacing : float, optional
        Spacing ``ds`` of each fish's straight ground truth; default the finest of ``spacing``.
    wall_value : float
        Grey value of the tube wall (default 1800, brighter than flesh; a dense wall: 2500 or more).
    wall_thickness : float
        Thickness of the tube wall in voxels (of the coarsest of axis1/axis2), >= 1 (default 3).
    wall_noise : float
        Standard deviation (grey values) of extra noise inside the wall (slightly smoothed like ``noise``), as
        CT noise grows with the attenuation of a dense wall: the wall then holds many maxima separated by
        noise-level saddles. 0 (default): the wall has the scan's noise only.

    Returns
    -------
    Tank
        The volume, the labels and one :class:`Phantom` per fish (in the tank's coordinates).

    Raises
    ------
    InvalidInputError
        For invalid numbers, or when no valid layout was found in ``max_tries`` draws.
    """
    if isinstance(n_fish, (bool, np.bool_)) or not isinstance(n_fish, (int, np.integer)) or n_fish < 1:
        raise InvalidInputError(f"n_fish must be a positive integer, got {n_fish!r}")
    if isinstance(max_tries, (bool, np.bool_)) or not isinstance(max_tries, (int, np.integer)) or max_tries < 1:
        raise InvalidInputError(f"max_tries must be a positive integer, got {max_tries!r}")
    n_fish, max_tries = int(n_fish), int(max_tries)
    seed = _seed(seed)
    length = _positive("length", length)
    body_radius = _positive("body_radius", body_radius)
    if length <= 4 * body_radius:
        raise InvalidInputError(f"length ({length}) must be larger than 4 * body_radius ({4 * body_radius})")
    noise = _positive("noise", noise, allow_zero=True)
    gap = _positive("gap", gap, allow_zero=True)
    wall_value = _positive("wall_value", wall_value)
    wall_thickness = _positive("wall_thickness", wall_thickness)
    if wall_thickness < 1.0:
        raise InvalidInputError(f"wall_thickness must be at least 1 voxel, got {wall_thickness}")
    wall_noise = _positive("wall_noise", wall_noise, allow_zero=True)
    spacing = check_spacing(spacing)
    sp = np.asarray(spacing)
    vox = float(sp.max())
    ds = _straight_spacing(straight_spacing, spacing)
    rng = np.random.default_rng(seed)
    # surface samples apart by this keep the rendered masks >= gap voxels apart (gap 0: about one voxel, touching)
    need = (gap + 2.0) * vox if gap > 0 else vox
    wall, margin = wall_thickness * float(sp[1:].max()), 2.0 * vox
    last_error = "no draw had bends gentle enough"
    for _attempt in range(max_tries):
        fish = []
        for i in range(n_fish):
            L_i = length * rng.uniform(0.9, 1.1)
            R_i = body_radius * rng.uniform(0.9, 1.1)
            fn = _random_fish_curve(rng, L_i, rng.uniform(0.03, 0.06) * L_i)
            twist_i, roll_i = rng.uniform(-np.pi, np.pi), rng.uniform(0, 2 * np.pi)
            if rng.integers(2):
                fn = _reversed(fn)
            axial = rng.uniform(-4.0, 4.0) * float(sp[0])
            try:
                crv, body = _build_fish(
                    fn=fn,
                    t0=0.0,
                    t1=1.0,
                    length=L_i,
                    body_radius=R_i,
                    twist=twist_i,
                    roll=roll_i,
                    spacing=spacing,
                    what=f"tank fish {i}",
                )
            except InvalidInputError as exc:  # too sharp a random bend: draw again
                last_error = str(exc)
                break
            straight = _straight_truth(body, ds)
            surf = _surface_points(crv, straight[1], ds)
            lane = crv.knots[:, 1:].mean(axis=0)
            surf = surf - np.array([0.0, lane[0], lane[1]]) + np.array([axial, 0.0, 0.0])
            reach = float(np.max(np.linalg.norm(surf[:, 1:], axis=1)))
            fish.append((crv, body, straight, surf, reach, np.array([axial, -lane[0], -lane[1]])))
        if len(fish) < n_fish:
            continue
        reach = np.array([f[4] for f in fish])
        lanes = _hex_lanes(n_fish, 2.0 * reach.max() + need)[rng.permutation(n_fish)]
        trees = [cKDTree(f[3]) for f in fish]
        pts = [f[3] for f in fish]

        lo_a, hi_a = 0.0, 1.0
        if _min_pair_distance(trees, pts, _lane_offsets(lanes, hi_a), reach, need) < need:
            last_error = "the lattice lanes were too close"
            continue
        for _ in range(14):  # bisection on the lattice scale: pack the fish as tightly as allowed
            mid = 0.5 * (lo_a + hi_a)
            if _min_pair_distance(trees, pts, _lane_offsets(lanes, mid), reach, need) >= need:
                hi_a = mid
            else:
                lo_a = mid
        lat = _lane_offsets(lanes, hi_a)[:, 1:]
        lat -= (lat.min(axis=0) + lat.max(axis=0)) / 2.0
        rho = max(float(np.max(np.linalg.norm(f[3][:, 1:] + o, axis=1))) for f, o in zip(fish, lat))
        r_in = rho + need
        r_out = r_in + wall
        lo0 = min(float(f[3][:, 0].min()) for f in fish) - 2.0 * vox
        hi0 = max(float(f[3][:, 0].max()) for f in fish) + 2.0 * vox
        shape = (
            int(np.ceil((hi0 - lo0 + 2 * margin) / sp[0])) + 1,
            int(np.ceil(2 * (r_out + margin) / sp[1])) + 1,
            int(np.ceil(2 * (r_out + margin) / sp[2])) + 1,
        )
        ctr = ((shape[1] - 1) * sp[1] / 2.0, (shape[2] - 1) * sp[2] / 2.0)
        excess = np.zeros(shape, dtype=np.float32)
        labels = np.zeros(shape, dtype=np.int32)
        curves, masks, overlap = [], [], False
        for i, ((crv, body, straight, _, _, base), o) in enumerate(zip(fish, lat)):
            shift = base + np.array([margin - lo0, ctr[0] + o[0], ctr[1] + o[1]])
            crv = crv.translated(shift)
            m = np.zeros(shape, dtype=bool)
            _render_into(excess, m, crv, body, spacing)
            overlap |= bool(np.any(labels[m]))
            labels[m] = i + 1
            curves.append((crv, body, straight))
            masks.append(m)
        # verify the separations on the rendered masks (index units)
        bpts = [_boundary_points(m) for m in masks]
        dmin = np.inf
        for i in range(n_fish):
            tree = cKDTree(bpts[i])
            for j in range(i + 1, n_fish):
                dmin = min(dmin, float(tree.query(bpts[j], k=1, workers=-1)[0].min()))
        tube_plane = _tube_excess(shape, sp, ctr, r_in, r_out) * np.float32(
            (wall_value - BACKGROUND) / (TUBE - BACKGROUND))
        tube_rho = np.argwhere(tube_plane >= (wall_value - BACKGROUND) / 2.0) * sp[1:] - np.asarray(ctr)
        fish_rho = max(float(np.max(np.hypot(p[:, 1] * sp[1] - ctr[0], p[:, 2] * sp[2] - ctr[1]))) for p in bpts)
        tube_gap = (float(np.min(np.hypot(tube_rho[:, 0], tube_rho[:, 1]))) - fish_rho) / vox
        if overlap or dmin < gap or tube_gap < gap:
            last_error = f"fish {dmin:.3g} voxels apart and {tube_gap:.3g} voxels from the tube (need {gap})"
            continue
        excess += tube_plane[None]
        if wall_noise > 0:  # the dense wall is noisier (as CT noise grows with attenuation)
            lumps = rng.standard_normal(shape, dtype=np.float32)
            lumps = ndimage.gaussian_filter(lumps, sigma=0.7, output=np.float32)
            lumps *= np.float32(wall_noise / max(float(lumps.std()), 1e-12))
            excess += lumps * (tube_plane[None] / np.float32(wall_value - BACKGROUND))
        excess += BACKGROUND
        volume = _finish(excess, noise, seed)
        tube_info = ((float(r_in), float(r_out)), (float(ctr[0]), float(ctr[1])))
        phantoms = tuple(
            _phantom(
                f"tank-fish-{i}",
                volume,
                masks[i],
                crv,
                body,
                spacing,
                ds,
                tube=tube_info,
                seed=seed,
                straight=straight,
            )
            for i, (crv, body, straight) in enumerate(curves)
        )
        return Tank(
            volume=volume,
            labels=labels,
            fish=phantoms,
            spacing=spacing,
            unit=UNIT,
            tube_radii=tube_info[0],
            tube_center=tube_info[1],
            min_distance=dmin,
            seed=seed,
        )
    raise InvalidInputError(
        f"no valid layout of {n_fish} fish found in {max_tries} tries (last: {last_error}); use fewer fish, "
        "a smaller gap, a larger max_tries or another seed"
    )


# ------------------------------------------------------------------------------------------------------------------
# hard specimens: tight S-bends, coils and helices
# ------------------------------------------------------------------------------------------------------------------
#: The kinds of :func:`hard_fish_phantom`.
HARD_KINDS = ("s-bend", "coil", "helix")
#: The voxel spacings :func:`hard_fish_phantom` draws from when none is given.
HARD_SPACINGS = ((1.0, 1.0, 1.0), (1.5, 1.0, 1.0), (1.0, 0.7, 0.7))
_BODY_LOAD = 0.85  # the body's own Jacobian stays >= 0.15 everywhere (its cage may fold, the body never does)
_MAX_SIDE = 160  # voxels
_MIN_GAP = 3.0  # voxels (of the coarsest spacing) between parts of a body that are far apart along it


def _body_support(body: _Fish, s: np.ndarray, ca: np.ndarray, sa: np.ndarray) -> np.ndarray:
    """The largest ``x ca + y sa`` over the body's cross-section at arclength ``s`` (fin and spine included)."""
    sig = np.asarray(s, dtype=float) / body.L
    b = body.half_height(sig)
    out = np.hypot(body.aspect * b * ca, b * sa)
    top = body.fin_top(sig, b)
    fin = body.fin_half * np.abs(ca) + np.maximum(np.where(np.isfinite(top), top, 0.0) * sa, 0.0)
    out = np.maximum(out, np.where(np.isfinite(top), fin, -np.inf))
    f0, f1 = body.spine_range
    spine = body.spine_offset * b * sa + np.clip(body.spine_radius * b, body.spine_min, None)
    return np.maximum(out, np.where((sig >= f0) & (sig <= f1), spine, -np.inf))


def _body_load(curve: _Curve, body: _Fish, s: np.ndarray) -> np.ndarray:
    """``1 - min J`` over the body's cross-section at ``s``: the curvature times the body's extent towards the
    centre of curvature (1 or more: the body itself folds)."""
    u, v, _ = curve.frames(s)
    k = curve.curvature(s)
    ku, kv = np.sum(k * u, axis=1), np.sum(k * v, axis=1)
    kap = np.hypot(ku, kv)
    safe = np.maximum(kap, 1e-300)
    return kap * _body_support(body, s, ku / safe, kv / safe)


def _self_gap(points: np.ndarray, s: np.ndarray, apart: float, cap: float) -> float:
    """Smallest distance between points whose arclengths ``s`` differ by more than ``apart`` (pairs up to 12 %
    further apart along the curve may be left out); inf when none come within ``cap``."""
    w = apart / 8.0
    bins = np.floor(s / w).astype(int)
    best = np.inf
    for b in np.unique(bins):
        far = bins >= b + 9
        if not far.any():
            break
        d, _ = cKDTree(points[bins == b]).query(points[far], k=1, distance_upper_bound=cap)
        best = min(best, float(d.min()))
    return best


def _integrated(length: float, kappa: np.ndarray, psi: np.ndarray, frame0: np.ndarray) -> CubicSpline:
    """The curve of arclength ``length`` (from the origin, along ``frame0[0]``) whose curvature vector is
    ``kappa (cos(psi) N1 + sin(psi) N2)`` in its parallel-transport frame (T, N1, N2), which starts at the rows of
    ``frame0``; ``kappa`` and ``psi`` are sampled uniformly in ``s``. Returns a C2 spline of ``s``."""
    n = len(kappa)
    s = np.linspace(0.0, length, n)
    h = s[1] - s[0]
    km, pm = 0.5 * (kappa[1:] + kappa[:-1]), 0.5 * (psi[1:] + psi[:-1])
    # T' = k1 N1 + k2 N2, N1' = -k1 T, N2' = -k2 T: the frame turns about its own axis (0, -k2, k1)
    steps = Rotation.from_rotvec(np.column_stack([np.zeros(n - 1), -km * np.sin(pm), km * np.cos(pm)]) * h)
    mats = steps.as_matrix()
    rot = np.asarray(frame0, dtype=float).T.copy()  # columns T, N1, N2
    tangents = np.empty((n, 3))
    tangents[0] = rot[:, 0]
    for i in range(n - 1):
        rot = rot @ mats[i]
        tangents[i + 1] = rot[:, 0]
    pts = np.vstack([np.zeros(3), np.cumsum(0.5 * (tangents[1:] + tangents[:-1]) * h, axis=0)])
    return CubicSpline(s, pts, axis=0)


def _aligned(make: Callable[[float], _Curve], s_ref: float, angle: float) -> _Curve:
    """``make(roll)`` with the roll that puts the curvature vector at ``s_ref`` at ``angle`` from u (0: along +u,
    so the body bends sideways there)."""
    crv = make(0.0)
    u, v, _ = crv.frames(np.array([s_ref]))
    k = crv.curvature(np.array([s_ref]))[0]
    return make(float(np.arctan2(k @ v[0], k @ u[0])) - angle)


def _render_pieces(
    shape: tuple[int, int, int], curve: _Curve, body: _Fish, spacing: Sequence[float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The body's density above background, its mask and the arclength of each mask voxel, from every foot of
    every voxel on the curve.

    The curve is cut into pieces that turn by at most 60 degrees. In each piece every voxel within reach is
    projected on the piece (Newton steps on ``(p - c(s)) . c'(s) = 0`` from the piece's nearest knot) and kept
    when its foot lies in the piece, so a voxel near two turns of a coil is seen from both. The density is the
    largest over the feet, the mask holds the voxels inside the body through any foot. Also returns the number
    of voxels inside the body through two feet or more (0 unless the body overlaps itself).
    """
    sp = np.asarray(spacing, dtype=float)
    L, h = curve.length, curve.h
    kmax = float(np.max(np.linalg.norm(curve.curvature(curve.knots_s), axis=1)))
    n_pieces = max(2, int(np.ceil(L * kmax / (np.pi / 3))))
    edges = np.linspace(0.0, L, n_pieces + 1)
    bound = body.ext + 2.0 * float(sp.max()) + h
    excess = np.zeros(shape, dtype=np.float32)
    mask = np.zeros(shape, dtype=bool)
    arc = np.full(shape, np.nan, dtype=np.float32)
    count = np.zeros(shape, dtype=np.uint8)
    w = float(np.mean(sp))
    for i in range(n_pieces):
        a, b = edges[i], edges[i + 1]
        last = i == n_pieces - 1
        lo_s, hi_s = (-2.0 * h if i == 0 else a), (L + 2.0 * h if last else b)
        near = (curve.knots_s >= a - h) & (curve.knots_s <= b + h)
        kn, ks = curve.knots[near], curve.knots_s[near]
        lo = np.maximum(np.floor((kn.min(axis=0) - bound) / sp).astype(int), 0)
        hi = np.minimum(np.ceil((kn.max(axis=0) + bound) / sp).astype(int) + 1, np.asarray(shape))
        if np.any(hi <= lo):
            continue
        grids = [np.arange(lo[d], hi[d]) * sp[d] for d in range(3)]
        p = np.stack(np.meshgrid(*grids, indexing="ij"), axis=-1).reshape(-1, 3)
        dist, idx = cKDTree(kn).query(p, k=1, distance_upper_bound=bound, workers=-1)
        sel = np.flatnonzero(np.isfinite(dist))
        q, s = p[sel], ks[idx[sel]]
        reach = 0.5 * (b - a)
        todo = np.arange(len(s))
        for _ in range(8):  # Newton steps on the points that still move
            st = s[todo]
            r = q[todo] - curve.C(st)
            d1, d2 = curve.dC(st), curve.ddC(st)
            g = np.sum(r * d1, axis=1)
            gp = np.sum(r * d2, axis=1) - np.sum(d1 * d1, axis=1)
            step = np.clip(np.where(gp < -0.05, -g / np.minimum(gp, -0.05), g), -4.0 * h, 4.0 * h)
            s[todo] = np.clip(st + step, lo_s - reach, hi_s + reach)
            todo = todo[np.abs(step) > 1e-9 * h]
            if not len(todo):
                break
        r = q - curve.C(s)
        u, v, n = curve.frames(s)
        ok = (np.abs(np.sum(r * n, axis=1)) < 1e-6 * max(1.0, h)) & (s >= lo_s) & (s <= hi_s) & ((s < hi_s) | last)
        val, inside = body.evaluate(np.sum(r * u, axis=1)[ok], np.sum(r * v, axis=1)[ok], s[ok], w)
        box = tuple(slice(lo[d], hi[d]) for d in range(3))
        sub_shape = tuple(int(x) for x in hi - lo)
        flat = sel[ok]
        ex = np.zeros(int(np.prod(sub_shape)), dtype=np.float32)
        ex[flat] = val - BACKGROUND
        np.maximum(excess[box], ex.reshape(sub_shape), out=excess[box])
        ins = np.zeros(ex.shape, dtype=bool)
        ins[flat] = inside
        where = np.full(ex.shape, np.nan, dtype=np.float32)
        where[flat[inside]] = s[ok][inside]
        ins = ins.reshape(sub_shape)
        mask[box] |= ins
        count[box] += ins
        arc[box] = np.where(ins, where.reshape(sub_shape), arc[box])
    return excess, mask, arc, int(np.count_nonzero(count > 1))


def _bisect(gap_of: Callable[[float], float], target: float, lo: float, hi: float) -> float | None:
    """The smallest parameter in [lo, hi] (to 0.5 %) whose gap is at least ``target``; None when even ``hi``'s is
    smaller."""
    if gap_of(hi) < target:
        return None
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        if gap_of(mid) >= target:
            hi = mid
        else:
            lo = mid
        if hi - lo < 0.005 * hi:
            break
    return hi


def _draw_sbend(rng: np.random.Generator, sp: np.ndarray, twist: float, h: float) -> tuple[_Curve, _Fish, dict] | str:
    """Two or three bends of alternating sense; the first, where the body is widest, 0.8-1.2 half heights tight."""
    unit = float(sp.min())
    L = rng.uniform(120.0, 150.0) * unit
    body = _Fish(L, rng.uniform(8.0, 11.0) * unit, float(sp.max()), 2.0 * float(sp.max()))
    m = int(rng.integers(2, 4))
    centre = (np.linspace(0.27, 0.78, m) + rng.uniform(-0.03, 0.03, m)) * L
    rho = rng.uniform(0.8, 2.0, m) * body.half_height(centre / L)
    rho[0] = rng.uniform(0.8, 1.2) * body.half_height(centre[0] / L)
    stops = np.concatenate([[0.0], centre, [L]])
    room = np.minimum(np.diff(stops)[:-1], np.diff(stops)[1:])
    width = np.minimum(np.radians(rng.uniform(60.0, 150.0, m)) * rho, 0.48 * room)  # half widths of the bends
    psi0, drift = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(-0.8, 0.8)  # the bends' plane turns slowly
    frame0 = Rotation.random(random_state=rng).as_matrix().T
    side = rng.choice([0.0, np.pi]) + np.radians(rng.uniform(-15.0, 15.0))
    s = np.linspace(0.0, L, 4001)
    for _ in range(6):
        kap = np.zeros_like(s)
        for k in range(m):
            z = (s - centre[k]) / width[k]
            kap += (-1) ** k / rho[k] * np.where(np.abs(z) < 1, 0.5 * (1.0 + np.cos(np.pi * z)), 0.0)
        fn = _integrated(L, kap, psi0 + drift * s / L, frame0)
        crv = _aligned(lambda roll, fn=fn: _Curve(fn, 0.0, L, h=h, length=L, twist=twist, roll=roll), centre[0],
                       side)
        load = _body_load(crv, body, crv.knots_s)
        peak = np.array([load[np.abs(crv.knots_s - c) <= w].max() for c, w in zip(centre, width)])
        if peak.max() <= _BODY_LOAD:
            return crv, body, {"bends": m}
        rho = np.where(peak > _BODY_LOAD, rho * peak / (0.97 * _BODY_LOAD), rho)  # the twist turned it the wrong way
    return "a bend stayed too sharp for the body's own cross-section"


def _spiral(r0: float, pitch: float, length: float, frame: np.ndarray, head_inside: bool
            ) -> tuple[Callable[[np.ndarray], np.ndarray], float]:
    """A flat spiral ``r = r0 + pitch phi / (2 pi)`` of the given arclength in the plane of ``frame[0:2]``; returns
    it as a function of ``phi`` (run from the outside in unless ``head_inside``) and its total angle."""
    a = pitch / (2.0 * np.pi)
    phi_hi = 1.1 * (np.sqrt(r0**2 + 2.0 * a * length) - r0) / a + 1.0
    phi = np.linspace(0.0, phi_hi, 20001)
    speed = np.hypot(r0 + a * phi, a)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(phi))])
    total = float(np.interp(length, cum, phi))

    def fn(t: np.ndarray) -> np.ndarray:
        ph = t if head_inside else total - t
        return (r0 + a * ph)[:, None] * (np.cos(ph)[:, None] * frame[0] + np.sin(ph)[:, None] * frame[1])

    return fn, total


def _draw_turns(
    kind: str, rng: np.random.Generator, sp: np.ndarray, twist: float, h: float, ds: float
) -> tuple[_Curve, _Fish, dict] | str:
    """A coil (flat spiral) or a helix whose neighbouring turns come within a drawn gap of each other."""
    unit = float(sp.min())
    L = rng.uniform(130.0, 150.0) * unit
    R = rng.uniform(6.0, 8.5) * unit if kind == "coil" else rng.uniform(7.0, 10.0) * unit
    body = _Fish(L, R, float(sp.max()), 2.0 * float(sp.max()))
    radius = rng.uniform(1.1, 1.4) * R if kind == "coil" else rng.uniform(1.0, 1.5) * R
    frame = Rotation.random(random_state=rng).as_matrix().T
    flag = bool(rng.integers(2))  # coil: head inside; helix: left-handed
    width = 2.0 * body.aspect * R
    gap = rng.uniform(_MIN_GAP * float(sp.max()), width)
    side = rng.choice([0.0, np.pi]) + np.radians(rng.uniform(-15.0, 15.0))
    _, straight = _straight_truth(body, ds)
    s_surf = np.nonzero(straight & ~ndimage.binary_erosion(straight, border_value=0))[0] * ds

    def build(pitch: float) -> tuple[_Curve, float]:
        if kind == "coil":
            fn, t1 = _spiral(radius, pitch, L, frame, flag)
        else:
            c, hand = pitch / (2.0 * np.pi), (-1.0 if flag else 1.0)
            t1 = L / np.hypot(radius, c)

            def fn(t: np.ndarray) -> np.ndarray:
                return (c * t)[:, None] * frame[2] + radius * (
                    np.cos(hand * t)[:, None] * frame[0] + np.sin(hand * t)[:, None] * frame[1])

        return _aligned(lambda roll: _Curve(fn, 0.0, t1, h=h, length=L, twist=twist, roll=roll), 0.5 * L, side), t1

    def gap_of(pitch: float) -> float:
        return _self_gap(_surface_points(build(pitch)[0], straight, ds), s_surf, np.pi * body.ext, 2.0 * width)

    for _ in range(4):
        pitch = _bisect(gap_of, gap, 0.3 * R, 8.0 * R)
        if pitch is None:
            return f"no {kind} pitch up to {8 * R:.3g} keeps its turns {gap:.3g} apart"
        crv, t1 = build(pitch)
        load = float(_body_load(crv, body, crv.knots_s).max())
        if load <= _BODY_LOAD:
            turns = t1 / (2.0 * np.pi)
            if turns < 1.15:
                return f"the {kind} makes only {turns:.2f} turns"
            return crv, body, {"turns": float(turns), "gap_target": float(gap), "pitch": float(pitch),
                               "turn_radius": float(radius)}
        radius *= load / (0.97 * _BODY_LOAD)  # the twist turned the body's tall side towards the centre
    return f"the {kind}'s turns stayed too tight for the body's own cross-section"


def hard_fish_phantom(
    seed: int | None = 0,
    *,
    kind: str | None = None,
    spacing: float | Sequence[float] | None = None,
    noise: float = 40.0,
    straight_spacing: float | None = None,
    max_tries: int = 20,
) -> Phantom:
    """A random hard specimen with its exact ground truth: a tight S-bend, a coil or a helix, twisted.

    Everything is drawn from ``seed`` (the same seed gives the same phantom):

    - ``"s-bend"``: two or three bends of alternating sense whose plane turns slowly. The first, where the body
      is widest, has a radius of curvature of 0.8 to 1.2 times the body's half height there, and the body bends
      sideways there (within 15 degrees), the way a fish bends.
    - ``"coil"``: a flat spiral of more than 1.15 turns.
    - ``"helix"``: a helix of more than 1.15 turns.
    - In coils and helices the surfaces of neighbouring turns come within a gap drawn between 3 voxels and the
      body's width (``2 * 0.6 * body_radius``).
    - A twist drawn in [-200, 200] degrees, a random orientation, and (unless ``spacing`` is given) a spacing
      drawn from :data:`HARD_SPACINGS`: isotropic, (1.5, 1, 1) or (1, 0.7, 0.7). Lengths are 120-150 and body
      radii 6-11 of the finest spacing; no side of the volume exceeds 160 voxels.

    The cage ``half_extent`` (the specimen's bounding box in straight coordinates) may fold in these bends and
    reach into neighbouring turns; the body itself never does. Every draw is checked, and drawn again if it
    fails: the body's own Jacobian stays at least 0.15 over its cross-section (the curvature times the body's
    extent towards the centre of curvature is at most 0.85); no voxel lies inside the body through two points
    of the centreline; parts of the body further apart along it than ``pi`` times its reach stay at least 3
    voxels apart. The straight ground truth is the analytic body (as in :func:`fish_phantom`) and the bent
    volume is rendered from every foot of each voxel on the centreline, so ``straight_mask`` is the exact
    straight image of ``mask``.

    Parameters
    ----------
    seed : int
        Seed of the draw and of the noise.
    kind : {"s-bend", "coil", "helix"}, optional
        The kind of specimen; default drawn from the seed.
    spacing : float or tuple of 3 float, optional
        Voxel size (axis0, axis1, axis2); default drawn from the seed.
    noise : float
        Standard deviation of the added noise (grey values), 0 for none.
    straight_spacing : float, optional
        Spacing ``ds`` of the straight ground truth; default the finest of ``spacing``.
    max_tries : int
        Draws before giving up.

    Returns
    -------
    Phantom
        Named ``"hard-<kind>-<seed>"``, no tube, with ``mask_arclength`` (the ``s`` of each mask voxel) and
        ``info``: ``kind``, ``seed``, ``attempt`` (draws that failed before), ``twist_deg``, ``body_radius``,
        ``length``, ``tightest_radius`` (the smallest radius of curvature), ``radius_to_half_height`` (the
        smallest ratio of the radius of curvature to the body's half height, at ``radius_there`` and
        ``half_height_there``), ``min_gap`` (between parts of the surface further apart along the body than
        ``pi`` times its reach; inf if none come within two body widths), ``body_width``, ``max_body_load`` and
        ``min_body_jacobian`` (1 minus it); S-bends add ``bends``, coils and helices ``turns``, ``gap_target``,
        ``pitch`` and ``turn_radius``. Lengths are physical.

    Raises
    ------
    InvalidInputError
        For an invalid seed, kind, spacing or number, or when no valid draw was found in ``max_tries``.
    """
    seed = _seed(seed)
    if kind is not None and kind not in HARD_KINDS:
        raise InvalidInputError(f"kind must be one of {', '.join(HARD_KINDS)} or None, got {kind!r}")
    if isinstance(max_tries, (bool, np.bool_)) or not isinstance(max_tries, (int, np.integer)) or max_tries < 1:
        raise InvalidInputError(f"max_tries must be a positive integer, got {max_tries!r}")
    noise = _positive("noise", noise, allow_zero=True)
    rng = np.random.default_rng(seed)
    drawn_kind = HARD_KINDS[int(rng.integers(len(HARD_KINDS)))]
    drawn_spacing = HARD_SPACINGS[int(rng.integers(len(HARD_SPACINGS)))]
    kind = drawn_kind if kind is None else kind
    spacing = check_spacing(drawn_spacing if spacing is None else spacing)
    sp = np.asarray(spacing)
    ds = _straight_spacing(straight_spacing, spacing)
    h = 0.25 * float(sp.min())
    reason = ""
    for attempt in range(int(max_tries)):
        twist = float(np.radians(rng.uniform(-200.0, 200.0)))
        drawn = _draw_sbend(rng, sp, twist, h) if kind == "s-bend" else _draw_turns(kind, rng, sp, twist, h, ds)
        if isinstance(drawn, str):
            reason = drawn
            continue
        crv, body, extra = drawn
        straight = _straight_truth(body, ds)
        surf = _surface_points(crv, straight[1], ds)
        s_surf = np.nonzero(straight[1] & ~ndimage.binary_erosion(straight[1], border_value=0))[0] * ds
        width = 2.0 * body.aspect * body.R
        gap = _self_gap(surf, s_surf, np.pi * body.ext, 2.0 * width)
        if gap < _MIN_GAP * float(sp.max()):
            reason = f"two parts of the body came {gap:.3g} apart"
            continue
        margin = 3.0 * float(sp.max())
        lo, hi = surf.min(axis=0) - margin, surf.max(axis=0) + margin
        shape = tuple(int(n) for n in np.ceil((hi - lo) / sp).astype(int) + 1)
        if max(shape) > _MAX_SIDE:
            reason = f"the volume would be {shape} voxels"
            continue
        crv = crv.translated(-lo)
        excess, mask, arc, overlap = _render_pieces(shape, crv, body, spacing)
        if overlap:
            reason = f"the body overlaps itself in {overlap} voxels"
            continue
        s = crv.knots_s
        radius = 1.0 / np.maximum(np.linalg.norm(crv.curvature(s), axis=1), 1e-300)
        b = body.half_height(s / body.L)
        k = int(np.argmin(radius / b))
        load = float(_body_load(crv, body, s).max())
        info = {"kind": kind, "seed": seed, "attempt": attempt, "twist_deg": float(np.degrees(twist)),
                "body_radius": float(body.R), "length": float(crv.length), "tightest_radius": float(radius.min()),
                "radius_to_half_height": float(radius[k] / b[k]), "radius_there": float(radius[k]),
                "half_height_there": float(b[k]), "min_gap": float(gap), "body_width": float(width),
                "max_body_load": load, "min_body_jacobian": 1.0 - load, **extra}
        volume = _finish(excess + np.float32(BACKGROUND), noise, seed)
        ph = _phantom(f"hard-{kind}-{seed}", volume, mask, crv, body, spacing, ds, tube=None, seed=seed,
                      straight=straight)
        return replace(ph, mask_arclength=arc, info=info)
    raise InvalidInputError(
        f"no valid hard {kind} phantom found for seed {seed} in {max_tries} draws (last: {reason}); use another "
        "seed or a larger max_tries"
    )


# ------------------------------------------------------------------------------------------------------------------
# hard tanks: walls cut by the field of view, touching fish, fish cut by a face of the scan
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class HardTank:
    """A tank scanned with a field of view that cuts its wall into arcs and its fish at a face, with ground truth.

    Attributes
    ----------
    volume : ndarray of uint16, shape (N0, N1, N2)
        The scan (bright spines inside softer bodies, a dense noisy wall).
    labels : ndarray of int32, shape (N0, N1, N2)
        0 for background and wall, ``i + 1`` for the voxels of fish ``i`` (the whole body: flesh, fin and spine).
    spine : ndarray of bool, shape (N0, N1, N2)
        The bright spines: fish voxels at least half the way from the flesh to the spine value.
    wall : ndarray of bool, shape (N0, N1, N2)
        The voxels of the tube wall (its inner to outer radius), whatever of it the field of view keeps.
    n_fish : int
    spacing : tuple of 3 float
    unit : str
    touching : tuple of (int, int)
        The pairs of fish labels whose masks touch (a voxel of one is a 26-neighbour of a voxel of the other).
    wall_cut : bool
        The field of view cuts the wall into arcs (False: the whole tube ring is in the scan).
    cut_fish : tuple of int
        Labels of the fish that the field of view cuts (their mask reaches a face of the scan).
    seed : int
    """

    volume: np.ndarray
    labels: np.ndarray
    spine: np.ndarray
    wall: np.ndarray
    n_fish: int
    spacing: tuple[float, float, float]
    unit: str
    touching: tuple[tuple[int, int], ...]
    wall_cut: bool
    cut_fish: tuple[int, ...]
    seed: int

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.volume.shape)  # type: ignore[return-value]

    def __repr__(self) -> str:
        return (f"HardTank(seed={self.seed}, n_fish={self.n_fish}, shape={self.shape}, touching={self.touching}, "
                f"wall_cut={self.wall_cut}, cut_fish={self.cut_fish})")

    def to_volume(self) -> Volume:
        """The scan as a :class:`napari_unwind.io.Volume`."""
        return Volume(data=da.from_array(self.volume, chunks=(64, 128, 128)), spacing=self.spacing, unit=self.unit,
                      source="napari_unwind.datasets:hard_tank", format=None,
                      metadata={"phantom": "hard_tank", "n_fish": self.n_fish, "seed": self.seed})


def _touching_pairs(labels: np.ndarray, n: int) -> tuple[tuple[int, int], ...]:
    pairs = set()
    for i in range(1, n + 1):
        grown = ndimage.binary_dilation(labels == i, structure=np.ones((3, 3, 3), bool))
        for j in np.unique(labels[grown]).tolist():
            if j > i:
                pairs.add((i, int(j)))
    return tuple(sorted(pairs))


def hard_tank_phantom(
    seed: int,
    *,
    n_fish: int | None = None,
    touching: bool | None = None,
    wall_cut: bool | None = None,
    face_cut: bool | None = None,
    length: float = 110.0,
    body_radius: float = 6.0,
) -> HardTank:
    """A tank drawn from ``seed``: 3 to 12 fish, a dense wall that the field of view cuts into arcs, fish touching
    each other and cut by a face of the scan.

    The tank is :func:`tank_phantom` with a dense, noisy wall (3000 +- 600, five voxels thick), scanned through a
    field of view that (when ``wall_cut``) is a square around the fish in (axis1, axis2), narrower than the tube
    so the ring falls apart into four arcs in the corners, and (when ``face_cut``) stops short of the fish's
    upper ends along axis0 (10-30 % of one fish's length lies outside). Each fish has a bright spine (2500)
    inside a softer body (flesh 1000, medium 100). With ``touching`` the fish are packed until the closest are
    about one voxel apart (usually one or two touching pairs; :attr:`HardTank.touching` lists them).

    Parameters
    ----------
    seed : int
        Seed of every draw below (not given options are drawn from it too).
    n_fish : int, optional
        Number of fish, 1..12 (default: drawn in 3..12).
    touching : bool, optional
        Pack the fish until some touch (default: drawn, 2 in 3 tanks).
    wall_cut : bool, optional
        Cut the wall into arcs by the field of view (default: drawn, 3 in 4 tanks).
    face_cut : bool, optional
        Cut the fish at the upper face along axis0 (default: drawn, 1 in 2 tanks).
    length, body_radius : float
        Typical fish length and half height (voxels; unit spacing).

    Returns
    -------
    HardTank
        The scan and its ground truth (fish labels, spines, wall).

    Raises
    ------
    InvalidInputError
        For a bad option.
    """
    seed = _seed(seed)
    if seed is None:
        raise InvalidInputError("hard_tank_phantom needs an integer seed, got None")
    rng = np.random.default_rng([seed, 18])
    if n_fish is None:
        n_fish = int(rng.integers(3, 13))
    if isinstance(n_fish, (bool, np.bool_)) or not isinstance(n_fish, (int, np.integer)) or not 1 <= n_fish <= 12:
        raise InvalidInputError(f"n_fish must be an integer in 1..12, got {n_fish!r}")
    draws = rng.random(3)
    touching = bool(draws[0] < 2 / 3) if touching is None else bool(touching)
    wall_cut = bool(draws[1] < 3 / 4) if wall_cut is None else bool(wall_cut)
    face_cut = bool(draws[2] < 1 / 2) if face_cut is None else bool(face_cut)
    tank = tank_phantom(n_fish=int(n_fish), seed=seed, length=length, body_radius=body_radius,
                        gap=0.0 if touching else float(rng.uniform(2.0, 3.0)), wall_value=3000.0,
                        wall_thickness=5.0, wall_noise=600.0, max_tries=40)
    labels = tank.labels
    # the wall, from the tank's radii (unit spacing)
    (c1, c2), _, rho, wall = _tube_wall(tank)
    lo = [0, 0, 0]
    hi = list(tank.shape)
    if wall_cut:  # a square field of view just around the fish: the ring shows in its corners only
        fish_any = labels.any(axis=0)
        pts = np.argwhere(fish_any)
        h = float(np.max(np.maximum(np.abs(pts[:, 0] - c1), np.abs(pts[:, 1] - c2)))) + 1.0
        h += float(rng.uniform(0.0, 2.0))
        for a, c in ((1, c1), (2, c2)):
            lo[a] = max(int(np.floor(c - h)), 0)
            hi[a] = min(int(np.ceil(c + h)) + 1, tank.shape[a])
    if face_cut:  # the upper face along axis0 cuts one fish by 10-30 % of its length (and its neighbours with it)
        hi[0] = _face_cut(labels, int(n_fish), rng)
    volume, labels, wall, spine, cut = _crop_tank(tank.volume, labels, wall, lo, hi, 0.0)
    return HardTank(volume=volume, labels=labels, spine=spine, wall=wall, n_fish=int(n_fish),
                    spacing=tuple(float(v) for v in tank.spacing), unit=tank.unit,
                    touching=_touching_pairs(labels, int(n_fish)), wall_cut=wall_cut, cut_fish=cut, seed=seed)



# ------------------------------------------------------------------------------------------------------------------
# embedded bones and tanks in air: a body CT (no specimen) and its opposite (fish in a tube, air around it)
# ------------------------------------------------------------------------------------------------------------------
#: Hounsfield-like values of :func:`body_phantom`.
AIR_HU, LUNG_HU, FAT_HU, TISSUE_HU, DISC_HU, CANCELLOUS_HU, CORTEX_HU = -1000, -850, -100, 40, 80, 350, 800


@dataclass(frozen=True, eq=False)
class BodyScan:
    """An axial body CT: a soft-tissue body in air, cut by the first and last planes along axis0, with curved ribs
    and a vertebral column inside (and lungs, drawn). Its ground truth has no specimen: every bone is part of the
    body.

    Attributes
    ----------
    volume : ndarray of int16, shape (N0, N1, N2)
        Hounsfield-like values (air -1000, lung -850, fat -100, tissue 40, bone 350-800).
    body : ndarray of bool
        The body (skin inwards).
    bones : ndarray of int32
        0 elsewhere, ``1..n_ribs`` the ribs, ``n_ribs + 1`` the vertebral column.
    n_ribs : int
    lungs : bool
        The body holds two lungs (air-like, beside the ribs).
    spacing : tuple of 3 float
    unit : str
    seed : int
    """

    volume: np.ndarray
    body: np.ndarray
    bones: np.ndarray
    n_ribs: int
    lungs: bool
    spacing: tuple[float, float, float]
    unit: str
    seed: int

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.volume.shape)  # type: ignore[return-value]

    def __repr__(self) -> str:
        return f"BodyScan(seed={self.seed}, shape={self.shape}, n_ribs={self.n_ribs}, lungs={self.lungs})"


def body_phantom(seed: int, *, lungs: bool | None = None, noise: float = 15.0) -> BodyScan:
    """A chest-like axial CT drawn from ``seed``: an elliptic soft-tissue body (a fat layer under the skin) in air,
    cut by the first and last planes along axis0, with 3-5 levels of rib pairs (curved arcs just inside the body,
    sloping along axis0) and a vertebral column (vertebral bodies, discs, arches and spinous processes) along
    axis0, cut by the same planes. Spacing 1.5 mm.

    Parameters
    ----------
    seed : int
        Seed of every draw.
    lungs : bool, optional
        Two lungs inside the ribs (default: drawn, 1 in 2).
    noise : float
        Standard deviation of the added (slightly smoothed) noise, HU.

    Returns
    -------
    BodyScan
        The scan and its ground truth (no specimen; the bones' labels).

    Raises
    ------
    InvalidInputError
        For a bad seed or noise.
    """
    seed = _seed(seed)
    if seed is None:
        raise InvalidInputError("body_phantom needs an integer seed, got None")
    noise = _positive("noise", noise, allow_zero=True)
    rng = np.random.default_rng([seed, 28])
    n0, n1, n2 = int(rng.integers(80, 105)), int(rng.integers(100, 120)), int(rng.integers(130, 156))
    lungs = bool(rng.random() < 0.5) if lungs is None else bool(lungs)
    c1, c2 = n1 / 2.0 + rng.uniform(-2, 2), n2 / 2.0 + rng.uniform(-2, 2)
    a1, a2 = rng.uniform(0.36, 0.42) * n1, rng.uniform(0.40, 0.45) * n2  # AP (axis1) and LR (axis2) half axes
    fat = rng.uniform(2.0, 4.0)
    z = np.arange(n0, dtype=np.float32)[:, None, None]
    y = (np.arange(n1, dtype=np.float32) - c1)[None, :, None]
    x = (np.arange(n2, dtype=np.float32) - c2)[None, None, :]
    wob = 1.0 + 0.04 * np.sin(2 * np.pi * z / n0 + rng.uniform(0, 2 * np.pi))  # the body's girth along axis0
    sd_body = _ellipse_sd(y, x, a1 * wob, a2 * wob)
    vol = AIR_HU + (FAT_HU - AIR_HU) * _soft(sd_body, 1.0) + (TISSUE_HU - FAT_HU) * _soft(sd_body + fat, 1.5)
    body = np.broadcast_to(sd_body <= 0, (n0, n1, n2)).copy()
    inset = fat + rng.uniform(4.0, 6.0)  # the ribs' centrelines, from the skin
    if lungs:
        for side in (-1, 1):
            sd_l = _ellipse_sd(y - (-0.1 * a1), x - side * 0.45 * a2, 0.62 * a1 * wob, (0.45 * a2 - inset - 4) * wob)
            vol = vol + (LUNG_HU - TISSUE_HU) * _soft(sd_l, 1.5)
    # the vertebral column: posterior (towards larger axis1), along axis0
    tip = a1 - fat - rng.uniform(5.0, 8.0)  # the spinous processes' tips (axis1, from the centre)
    canal_r, arch = rng.uniform(3.5, 4.5), rng.uniform(2.0, 3.0)
    canal_c = tip - rng.uniform(7.0, 9.0) - arch - canal_r
    rv = rng.uniform(8.0, 11.0)
    body_c = canal_c - canal_r - arch - rv
    height, disc = rng.uniform(13.0, 16.0), rng.uniform(3.0, 4.0)
    phase = (z + rng.uniform(0, height + disc)) % (height + disc)
    in_vert = phase < height  # a vertebra's rows along axis0 (else a disc)
    rho_b = np.hypot(y - body_c, x)
    rho_c = np.hypot(y - canal_c, x)
    sd_vb = rho_b - rv
    sd_arch = np.maximum(canal_r - rho_c, rho_c - canal_r - arch)
    sd_arch = np.maximum(sd_arch, -(y - (canal_c - canal_r)))  # the arch behind the canal's front
    sd_proc = np.maximum(np.abs(x) - 1.8, np.maximum(canal_c + canal_r - y, y - tip))
    sd_post = np.minimum(sd_arch, sd_proc)
    column = np.zeros((n0, n1, n2), np.float32)
    column += np.where(in_vert, CANCELLOUS_HU - TISSUE_HU + (CORTEX_HU - CANCELLOUS_HU) * _soft(-(sd_vb + 1.5), 1.0),
                       DISC_HU - TISSUE_HU) * _soft(sd_vb, 1.0)
    column += np.where(in_vert, CORTEX_HU - TISSUE_HU, 0.0) * _soft(sd_post, 1.0) * (1 - _soft(sd_vb, 1.0))
    vol = vol + column
    bones = np.zeros((n0, n1, n2), np.int32)
    # ribs: arcs on the ellipse inset from the skin, from beside the column to the front, sloping along axis0
    pitch = rng.uniform(17.0, 22.0)
    levels = np.arange(rng.uniform(4.0, 10.0), n0 - 8.0, pitch)
    pts, ids, radii = [], [], {}
    n_ribs = 0
    for zk in levels:
        for side in (-1, 1):
            n_ribs += 1
            th0, th1 = rng.uniform(0.30, 0.40), rng.uniform(2.0, 2.5)  # 0: posterior (+axis1)
            th = np.linspace(th0, th1, 400)
            drop = rng.uniform(6.0, 14.0)
            pz = zk + drop * (th - th0) / (th1 - th0)
            py = c1 + (a1 - inset) * np.cos(th)
            px = c2 + side * (a2 - inset) * np.sin(th)
            pts.append(np.stack([pz, py, px], axis=1))
            ids.append(np.full(th.size, n_ribs))
            radii[n_ribs] = rng.uniform(2.2, 3.0)
    seeds = np.zeros((n0, n1, n2), np.int32)
    p = np.concatenate(pts)
    q = np.round(p).astype(int)
    ok = np.all((q >= 0) & (q < np.array([n0, n1, n2])), axis=1)
    seeds[tuple(q[ok].T)] = np.concatenate(ids)[ok]
    dist, ind = ndimage.distance_transform_edt(seeds == 0, return_indices=True)
    rib_id = seeds[tuple(ind)]
    r_of = np.zeros(n_ribs + 1, np.float32)
    r_of[1:] = [radii[i] for i in range(1, n_ribs + 1)]
    sd_rib = dist - r_of[rib_id]
    occ = _soft(sd_rib, 1.0)
    vol = vol + occ * (CANCELLOUS_HU - TISSUE_HU + (CORTEX_HU - CANCELLOUS_HU) * _soft(-(sd_rib + 1.0), 1.0))
    bones[occ >= 0.5] = rib_id[occ >= 0.5]
    col = (_soft(np.where(in_vert, np.minimum(sd_vb, sd_post), np.inf), 1.0) >= 0.5) | (in_vert & (sd_vb <= 0))
    bones[col & (bones == 0)] = n_ribs + 1
    if noise > 0:
        g = np.random.default_rng([seed, 28, 1]).standard_normal(vol.shape, dtype=np.float32)
        g = ndimage.gaussian_filter(g, sigma=0.7, output=np.float32)
        vol = vol + g * np.float32(noise / max(float(g.std()), 1e-12))
    volume = np.clip(np.round(vol), -1024, 3071).astype(np.int16)
    return BodyScan(volume=volume, body=body, bones=bones, n_ribs=n_ribs, lungs=lungs, spacing=(1.5, 1.5, 1.5),
                    unit="millimeter", seed=seed)


#: How much brighter than the air around the tube its water is in :func:`air_tank_phantom`.
WATER_LIFT = 1000


def _tube_wall(tank: Any) -> tuple[tuple[float, float], tuple[float, float], np.ndarray, np.ndarray]:
    """A tank's tube: its centre and radii (axes 1, 2), the distance ``rho`` of every (axis1, axis2) column from its
    axis, and its wall (bool, the tank's shape)."""
    c1, c2 = tank.tube_center
    r_in, r_out = tank.tube_radii
    jj, kk = np.mgrid[: tank.shape[1], : tank.shape[2]]
    rho = np.hypot(jj - c1, kk - c2)
    return (c1, c2), (r_in, r_out), rho, np.broadcast_to(((rho >= r_in) & (rho <= r_out))[None], tank.shape)


def _face_cut(labels: np.ndarray, n_fish: int, rng: np.random.Generator) -> int:
    """The upper bound along axis0 that cuts one fish (drawn) by 10-30 % of its length."""
    ext = [np.flatnonzero((labels == i + 1).any(axis=(1, 2))) for i in range(n_fish)]
    f = int(rng.integers(n_fish))
    a, b = int(ext[f][0]), int(ext[f][-1])
    return b + 1 - int(round(rng.uniform(0.1, 0.3) * (b - a + 1)))


def _crop_tank(volume: np.ndarray, labels: np.ndarray, wall: np.ndarray, lo: list[int], hi: list[int],
               lift: float) -> tuple[np.ndarray, ...]:
    """A tank cropped to the field of view ``lo:hi``: its volume (uint16), labels, wall, spine (the fish's voxels
    above halfway between flesh and spine, ``lift`` added) and the fish that a face of the view cuts."""
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    labels = np.ascontiguousarray(labels[box])
    volume = np.ascontiguousarray(np.round(volume[box]).astype(np.uint16))
    wall = np.ascontiguousarray(wall[box])
    spine = (labels > 0) & (volume >= lift + (FLESH + SPINE) / 2.0)
    faces = np.zeros(labels.shape, bool)
    faces[[0, -1]] = True
    faces[:, [0, -1]] = True
    faces[:, :, [0, -1]] = True
    cut = tuple(int(i) for i in np.unique(labels[faces]) if i > 0)
    return volume, labels, wall, spine, cut


def air_tank_phantom(seed: int, *, n_fish: int | None = None, face_cut: bool | None = None) -> HardTank:
    """The opposite of :func:`body_phantom`: fish in water inside a dense tube, in air, scanned through a field of
    view that every side face of the scan cuts through the tube (its wall or its water; the corners show air
    beyond the wall), and the first and last planes along axis0 through its water.

    The tank is :func:`tank_phantom` (fish apart, a dense noisy wall 5 voxels thick) with the inside of the tube
    lifted by :data:`WATER_LIFT` above the air around it: air 100, water 1100, flesh 2000, spine 3500, wall about
    4000. The water is far above the scan's background, as a body's tissue is; only the container around it
    tells the two apart.

    Parameters
    ----------
    seed : int
        Seed of every draw.
    n_fish : int, optional
        1..8 (default: drawn in 3..8).
    face_cut : bool, optional
        The upper face along axis0 also cuts the fish (default: drawn, 1 in 2).

    Returns
    -------
    HardTank
        The scan and its ground truth (``wall_cut`` True; ``touching`` empty).

    Raises
    ------
    InvalidInputError
        For a bad option.
    """
    seed = _seed(seed)
    if seed is None:
        raise InvalidInputError("air_tank_phantom needs an integer seed, got None")
    rng = np.random.default_rng([seed, 28, 2])
    if n_fish is None:
        n_fish = int(rng.integers(3, 9))
    if isinstance(n_fish, (bool, np.bool_)) or not isinstance(n_fish, (int, np.integer)) or not 1 <= n_fish <= 8:
        raise InvalidInputError(f"n_fish must be an integer in 1..8, got {n_fish!r}")
    face_cut = bool(rng.random() < 0.5) if face_cut is None else bool(face_cut)
    tank = tank_phantom(n_fish=int(n_fish), seed=seed, length=110.0, body_radius=6.0, gap=float(rng.uniform(2, 3)),
                        wall_value=3000.0, wall_thickness=5.0, wall_noise=600.0, max_tries=40)
    (c1, c2), (r_in, r_out), rho, wall = _tube_wall(tank)
    lift = (WATER_LIFT * _soft(rho - r_out, 1.0)).astype(np.float32)
    volume = np.clip(tank.volume.astype(np.float32) + lift[None], 0, np.iinfo(np.uint16).max)
    labels = tank.labels
    h = float(rng.uniform(r_in + 2.0, r_out - 1.0))  # every side face cuts the tube; air shows in the corners
    lo, hi = [0, 0, 0], list(tank.shape)
    for a, c in ((1, c1), (2, c2)):
        lo[a] = max(int(np.floor(c - h)), 0)
        hi[a] = min(int(np.ceil(c + h)) + 1, tank.shape[a])
    if face_cut:
        hi[0] = _face_cut(labels, int(n_fish), rng)
    volume, labels, wall, spine, cut = _crop_tank(volume, labels, wall, lo, hi, WATER_LIFT)
    return HardTank(volume=volume, labels=labels, spine=spine, wall=wall, n_fish=int(n_fish),
                    spacing=tuple(float(v) for v in tank.spacing), unit=tank.unit, touching=(), wall_cut=True,
                    cut_fish=cut, seed=seed)
