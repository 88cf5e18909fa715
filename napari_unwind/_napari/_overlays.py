"""The bent view's wireframe layers over the scan: the curve, the keyframes' frames and the cage.

All three are napari Vectors layers in physical (world) coordinates, the scan layer's (``scale`` = spacing,
``translate`` = origin), so they sit on the specimen in 2D and 3D:

- "unwind curve": the centre curve as short segments;
- "unwind frames": at each keyframe its u (red) and v (green) axes, as long as the cage's half-sizes; the
  selected keyframe's are drawn white;
- "unwind cage": each keyframe's cage rectangle and the four corner lines along the curve (cyan), and the cage at
  the editor's current s (yellow).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..deformation import Deformation

__all__ = ["BentOverlays", "curve_vectors", "frame_vectors", "cage_vectors", "OVERLAY_NAMES"]

CURVE, FRAMES, CAGE = "unwind curve", "unwind frames", "unwind cage"
OVERLAY_NAMES = (CURVE, FRAMES, CAGE)
_RED, _GREEN, _WHITE = (1.0, 0.3, 0.3, 1.0), (0.3, 1.0, 0.3, 1.0), (1.0, 1.0, 1.0, 1.0)
_CYAN, _YELLOW, _CURVE = (0.2, 0.9, 1.0, 1.0), (1.0, 0.85, 0.0, 1.0), (1.0, 0.55, 0.1, 1.0)


def _segments(points: np.ndarray) -> np.ndarray:
    """A polyline (n, 3) -> Vectors data (n - 1, 2, 3): start and displacement of each segment."""
    return np.stack([points[:-1], np.diff(points, axis=0)], axis=1)


def _samples(d: Deformation, n: int | None = None) -> np.ndarray:
    n = n or int(np.clip(d.length / min(d.spacing), 16, 400))
    return np.unique(np.concatenate([np.linspace(0.0, d.length, n), d.knots]))


def curve_vectors(d: Deformation) -> np.ndarray:
    """The curve c(s) sampled about one voxel apart (16 to 400 points), as segments."""
    c, _ = d.sample(_samples(d))
    return _segments(c)


def _curve_part(d: Deformation) -> tuple[np.ndarray, np.ndarray]:
    curve = curve_vectors(d)
    return curve, np.tile(_CURVE, (len(curve), 1))


def frame_vectors(d: Deformation, selected: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each keyframe's u and v from its position, as long as its cage's half-sizes; and their colours."""
    pos = d.positions
    frames = d.frames
    he = d.half_extents
    vec = np.concatenate([np.stack([pos, frames[:, 0] * he[:, :1]], axis=1),
                          np.stack([pos, frames[:, 1] * he[:, 1:]], axis=1)])
    colors = np.array([_RED] * len(d) + [_GREEN] * len(d))
    if selected is not None:
        colors[[selected, len(d) + selected]] = _WHITE
    return vec, colors


def _rectangle(c: np.ndarray, r: np.ndarray, b: np.ndarray) -> np.ndarray:
    x_lo, x_hi, y_lo, y_hi = b
    corners = [c + x * r[0] + y * r[1] for x, y in ((x_lo, y_lo), (x_hi, y_lo), (x_hi, y_hi), (x_lo, y_hi))]
    return _segments(np.array([*corners, corners[0]]))


def cage_vectors(d: Deformation, s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The cage as a wireframe: rectangles at the keyframes, corner lines along s; the cage at ``s`` in yellow."""
    parts, colors = [], []
    c, r = d.sample(d.knots)
    for ci, ri, bi in zip(c, r, d.bounds, strict=True):
        parts.append(_rectangle(ci, ri, bi))
        colors += [_CYAN] * 4
    s_all = _samples(d)
    cs, rs = d.sample(s_all)
    bs = d.bounds_at(s_all)
    for xi, yi in ((0, 2), (1, 2), (1, 3), (0, 3)):
        line = cs + bs[:, xi:xi + 1] * rs[:, 0] + bs[:, yi:yi + 1] * rs[:, 1]
        parts.append(_segments(line))
        colors += [_CYAN] * (len(line) - 1)
    if s is not None:
        s = float(np.clip(s, 0.0, d.length))
        c1, r1 = d.sample([s])
        parts.append(_rectangle(c1[0], r1[0], d.bounds_at(s)[0]))
        colors += [_YELLOW] * 4
    return np.concatenate(parts), np.array(colors)


class BentOverlays:
    """Keeps the three wireframe layers in ``viewer`` up to date with a deformation (added on first use)."""

    def __init__(self, viewer: Any) -> None:
        self.viewer = viewer

    def missing(self) -> bool:
        """Some of the three layers is not in the viewer (the next update adds it)."""
        return any(name not in self.viewer.layers for name in OVERLAY_NAMES)

    def _put(self, name: str, data: np.ndarray, colors: np.ndarray, width: float) -> None:
        layers = self.viewer.layers
        if name in layers:
            layer = layers[name]
            if layer.data.shape == data.shape and np.array_equal(layer.data, data):
                if not np.array_equal(layer.edge_color, colors):
                    layer.edge_color = colors
                return  # unchanged (the curve during a twist): setting it costs ~10 ms of napari's bookkeeping
            layer.data = data
            layer.edge_color = colors
        else:
            from napari.layers import Vectors

            from . import _reveal
            from ._layers import scan_units

            # into the viewer hidden, shown on a later turn (:mod:`._reveal`); the user's selection is kept
            _reveal.add_layer(self.viewer, Vectors(data, name=name, edge_color=colors, edge_width=width,
                                                   vector_style="line", metadata={"napari_unwind": {"overlay": True}},
                                                   **scan_units(self.viewer)), keep_active=True)

    def update(self, d: Deformation | None, s: float | None = None, keyframe: int | None = None, *,
               new_layers: int | None = None) -> bool:
        """Redraw for deformation ``d`` at position ``s`` with keyframe ``keyframe`` selected (None: remove).

        At most ``new_layers`` of the three layers are added in this call (None: all): napari's cost of adding a
        layer is 85-100 ms on software GL, so the dock adds one per turn of the event loop and calls again.
        Returns True when all three are in the viewer and up to date."""
        if d is None:
            self.remove()
            return True
        width = float(max(d.spacing))
        budget = 3 if new_layers is None else int(new_layers)
        parts = ((CURVE, lambda: _curve_part(d), width), (FRAMES, lambda: frame_vectors(d, keyframe), width),
                 (CAGE, lambda: cage_vectors(d, s), 0.5 * width))
        for name, make, w in parts:
            if name not in self.viewer.layers:
                if budget <= 0:
                    return False
                budget -= 1
            self._put(name, *make(), w)
        return True

    def remove(self) -> None:
        for name in OVERLAY_NAMES:
            if name in self.viewer.layers:
                self.viewer.layers.remove(name)
