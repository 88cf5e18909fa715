"""The live straight view: napari's own volume ray caster draws the straight specimen from the scan's texture.

A napari Image layer ("straight view") holds one pyramid level of the scan; napari uploads it once as the 3D
texture of its vispy ``VolumeVisual``. The visual's sampling function (the ``$get_data`` slot) is replaced by a
vispy ``Function`` (:mod:`._shaders`) that maps a point of the straight box to the scan's voxel coordinate through
a small float texture of per-slice frames, and the ray box is set to the straight shape (:mod:`._private` holds all
of this private access). An edit, :meth:`StraightView.update`, re-uploads only that frame texture (3 x Ns texels)
and, when the arclength changed, the box's 8 vertices; the scan texture is never re-uploaded or resampled.

Because the scan texture is the node's own, the straight/bent toggle (:meth:`StraightView.set_straight`) flips the
same layer between the straight box and the plain scan: one texture serves both. The transfer function (colormap,
contrast limits, gamma, rendering mode, linear/nearest interpolation) stays napari's.

Where float textures are missing or the shader fails to compile, ``available`` is False, ``reason`` says why (one
line, also logged), and the CPU preview (:class:`._preview.StraightPreview`) shows the straight volume instead.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from psygnal import Signal
from vispy.gloo import Texture2D
from vispy.visuals.shaders import Function

from ..deformation import Deformation
from ..errors import InvalidInputError
from ..preview import _levels, level_deformation
from . import _private
from ._shaders import FRAMES_UNIFORM, STRAIGHT_LOOKUP, uniform_lookup

__all__ = ["StraightView", "choose_level", "LAYER_NAME", "DEFAULT_MEMORY_BUDGET"]

LAYER_NAME = "straight view"
DEFAULT_MEMORY_BUDGET = 1 << 30   # bytes of GPU memory the scan texture may take
_log = logging.getLogger(__name__)


def choose_level(shapes: Sequence[Sequence[int]], itemsize: int, *, max_texture_size: int | None,
                 memory_budget: int) -> int:
    """The finest pyramid level whose every side fits the 3D texture limit and whose bytes fit the budget.

    Parameters
    ----------
    shapes : sequence of (N0, N1, N2)
        Level shapes, finest first.
    itemsize : int
        Bytes per voxel on the GPU.
    max_texture_size : int or None
        GL_MAX_3D_TEXTURE_SIZE (None: no limit known).
    memory_budget : int
        Bytes the texture may take.

    Returns
    -------
    int
        The level index. Raises :class:`InvalidInputError` when even the coarsest level does not fit.
    """
    if isinstance(memory_budget, bool) or not isinstance(memory_budget, (int, np.integer)) or memory_budget <= 0:
        raise InvalidInputError(f"memory_budget must be a positive number of bytes, got {memory_budget!r}")
    for i, shape in enumerate(shapes):
        if max_texture_size is not None and max(shape) > max_texture_size:
            continue
        if int(np.prod(shape, dtype=np.int64)) * itemsize > memory_budget:
            continue
        return i
    last = tuple(shapes[-1])
    raise InvalidInputError(
        f"no pyramid level fits the GPU: the coarsest is {last} ({int(np.prod(last)) * itemsize / 2**20:.0f} MiB), "
        f"the 3D texture limit is {max_texture_size} and the memory budget {memory_budget / 2**20:.0f} MiB; "
        f"import the scan with more pyramid levels or raise the budget"
    )


class StraightView:
    """The straight view layer of a scan, drawn through a deformation by the GPU.

    Parameters
    ----------
    viewer : napari.Viewer
        A shown viewer (napari draws nothing into a hidden one).
    scan : Volume or array_like, shape (N0, N1, N2)
        The scan (a bare array is one level on the deformation's voxel grid).
    max_texture_size : int, optional
        Override the GL 3D texture limit (default: queried from GL).
    memory_budget : int
        Bytes of GPU memory the scan texture may take (default 1 GiB).
    disable : str, optional
        Do not use the shader, for this reason (the CPU preview is used): testing, or a user setting.
    frames : {"auto", "uniform", "texture"}
        Where the shader reads the frame table: a uniform array (faster on llvmpipe; "auto" uses it while the
        table fits GL_MAX_FRAGMENT_UNIFORM_VECTORS) or an rgb32f texture (any length).

    Signals
    -------
    status(str)
        One line for the dock: the level on screen, or why the CPU preview is used.
    """

    status = Signal(str)

    def __init__(self, viewer: Any, scan: Any, *, max_texture_size: int | None = None,
                 memory_budget: int = DEFAULT_MEMORY_BUDGET, disable: str | None = None,
                 frames: str = "auto") -> None:
        if frames not in ("auto", "uniform", "texture"):
            raise InvalidInputError(f"frames must be 'auto', 'uniform' or 'texture', got {frames!r}")
        self.frames = frames
        self._capacity = 0
        self._table: np.ndarray | None = None
        self.viewer = viewer
        self.scan = scan
        levels, _, _, _, _ = _levels(scan)
        self.max_texture_size = max_texture_size if max_texture_size is not None else _private.max_3d_texture_size()
        itemsize = 4  # napari uploads float32 (r32f) for float data; a safe bound for the others
        self.level = choose_level([tuple(lv.shape) for lv in levels], itemsize,
                                  max_texture_size=self.max_texture_size, memory_budget=memory_budget)
        self.layer: Any = None
        self.node: Any = None
        self.straight = True
        self.deformation: Deformation | None = None
        self.frame_uploads = 0
        self.enabled = True
        self._preview: Any = None
        self._shape: tuple[int, int, int] | None = None
        self._frames: Texture2D | None = None
        self._lookup: Function | None = None
        self.reason = disable or self._gl_problem()
        self.available = self.reason is None
        self._level_data = levels[self.level]
        self._levels = levels
        self._memory_budget = memory_budget
        self._start = (0, 0, 0)            # the crop's first voxel on its level (focus)

    # -- setup -------------------------------------------------------------------------------------------------
    @staticmethod
    def _gl_problem() -> str | None:
        try:
            ext = _private.gl_extensions() or ""
        except Exception as exc:  # no GL context at all
            return f"no OpenGL context ({exc})"
        if "GL_ARB_texture_float" not in ext and "GL_OES_texture_float" not in ext:
            return "the OpenGL context has no float textures"
        return None

    @property
    def level_text(self) -> str:
        """The line the dock shows: which level is on screen, or why the CPU preview is used."""
        if not self.available:
            return f"straight view: CPU preview ({self.reason})"
        shape = "x".join(str(v) for v in self._level_data.shape)
        crop = f", crop from voxel {tuple(int(v) for v in self._start)}" if any(self._start) else ""
        return f"straight view: GPU shader, pyramid level {self.level} ({shape}{crop}, 3D texture limit " \
               f"{self.max_texture_size})"

    def _fail(self, reason: str) -> None:
        self.available = False
        self.reason = reason
        _log.warning("napari-unwind: %s", self.level_text)
        if self.node is not None:
            _private.uninstall(self.node)
        if self.layer is not None and self.layer in self.viewer.layers:
            self.viewer.layers.remove(self.layer)
        self.layer = self.node = None
        self.status.emit(self.level_text)

    def _ensure_layer(self) -> None:
        if self.layer is not None:
            return
        data = np.asarray(self._level_data)
        if data.dtype == np.float64:
            data = data.astype(np.float32)
        from ._layers import scan_units

        self.layer = self.viewer.add_image(data, name=LAYER_NAME, metadata={"napari_unwind": {"straight": True}},
                                           **scan_units(self.viewer))
        self.node = _private.volume_node(self.viewer, self.layer)
        self._frames = Texture2D(np.zeros((3, 1, 3), np.float32), internalformat="rgb32f", interpolation="linear",
                                 wrapping="clamp_to_edge")
        self._scan_shape = tuple(float(v) for v in data.shape)

    def _make_lookup(self, ns: int) -> bool:
        """(Re)build the sampling Function when the table's home changes; True when it is a new Function."""
        capacity = 0
        if self.frames != "texture":
            limit = _private.max_fragment_uniform_vectors() or 0
            cap = 256 * -(-ns // 256)          # rounded up: a length edit rarely recompiles
            if 3 * cap + 256 <= limit:          # leave room for napari's own uniforms
                capacity = cap
            elif self.frames == "uniform":
                raise InvalidInputError(f"a frame table of {ns} slices does not fit GL_MAX_FRAGMENT_UNIFORM_VECTORS "
                                        f"({limit}); use frames='texture' or 'auto'")
        if self._lookup is not None and capacity == self._capacity:
            return False
        self._capacity = capacity
        self._lookup = Function(uniform_lookup(capacity) if capacity else STRAIGHT_LOOKUP)
        if not capacity:
            self._lookup["frames"] = self._frames
        self._lookup["fill"] = 0.0
        self._lookup["scan_shape"] = self._scan_shape
        return True

    # -- edits -------------------------------------------------------------------------------------------------
    def update(self, deformation: Deformation) -> None:
        """Show ``deformation``: uploads the frame table (and the box's vertices when the length changed) only."""
        if not isinstance(deformation, Deformation):
            raise InvalidInputError(f"deformation must be a Deformation, got {type(deformation).__name__}")
        self.deformation = deformation
        if not self.available:
            self._cpu_preview(deformation)
            return
        self._ensure_layer()
        d = self._on_texture(deformation)
        ds = self._ds = float(min(d.spacing))
        self._level_spacing = tuple(float(v) for v in d.spacing)
        base, dv, du = d.slice_geometry(ds, voxels=True)
        shape = d.output_shape(ds)
        new = self._make_lookup(int(shape[0]))
        if self._capacity:
            table = np.zeros((3 * self._capacity, 3), np.float32)
            table[:3 * shape[0]] = np.stack([base, dv, du], axis=1).reshape(-1, 3)   # slice k: rows 3k, 3k+1, 3k+2
        else:
            self._frames.set_data(np.ascontiguousarray(np.stack([base, dv, du]).astype(np.float32)))  # (3, Ns, 3)
        self.frame_uploads += 1
        self._lookup["nslices"] = float(shape[0])
        self._lookup["box"] = (float(shape[2]), float(shape[1]), float(shape[0]))
        self._table = table if self._capacity else None
        if not np.allclose(self.layer.scale, ds):
            self.layer.scale = (ds, ds, ds)  # napari re-slices (re-uploads) on a new scale: only when it changed
        first = self._shape is None
        self._shape = tuple(int(v) for v in shape)
        if not self.straight:
            return
        if first or new:
            _private.install(self.node, self._lookup, self._shape)
        else:
            _private.set_box(self.node, self._shape)
        self._set_table()
        if first:
            self.frame()
            problem = self._try_draw()
            if problem is not None:
                self._fail(problem)
                self._cpu_preview(deformation)
                return
            self.status.emit(self.level_text)

    def _set_table(self) -> None:
        if self._table is not None:
            _private.set_uniform(self.node, FRAMES_UNIFORM, self._table)

    def _on_texture(self, deformation: Deformation) -> Deformation:
        """``deformation`` on the uploaded texture's voxel grid: the level's, shifted by the crop's start."""
        d = level_deformation(self.scan, deformation, self.level)
        if any(self._start):
            sp = np.asarray(d.spacing, dtype=float)
            d = replace(d, origin=tuple(np.asarray(d.origin, dtype=float) + np.asarray(self._start) * sp))
        return d

    def focus(self, *, margin: int = 2) -> int:
        """Upload the finest level on which a crop around the current deformation fits the texture limit and the
        memory budget (the region the straight grid samples, plus ``margin`` voxels); returns the level.

        This re-uploads the scan texture once (an explicit request, not an edit). Edits that later move the grid
        beyond the crop show the fill there until the next ``focus``.
        """
        if self.deformation is None or not self.available:
            return self.level
        for level in range(len(self._levels)):
            d = level_deformation(self.scan, self.deformation, level)
            ds = float(min(d.spacing))
            base, dv, du = d.slice_geometry(ds, voxels=True)
            _, ny, nx = d.output_shape(ds)
            corners = np.concatenate([base, base + (ny - 1) * dv, base + (nx - 1) * du,
                                      base + (ny - 1) * dv + (nx - 1) * du])
            shape = np.asarray(self._levels[level].shape)
            lo = np.clip(np.floor(corners.min(axis=0)).astype(int) - margin, 0, shape)
            hi = np.clip(np.ceil(corners.max(axis=0)).astype(int) + margin + 1, 0, shape)
            size = hi - lo
            if (size <= 0).any():
                continue
            if self.max_texture_size is not None and size.max() > self.max_texture_size:
                continue
            if int(np.prod(size)) * 4 > self._memory_budget:
                continue
            break
        else:
            return self.level
        self.level = level
        self._start = tuple(int(v) for v in lo)
        self._level_data = self._levels[level][tuple(slice(a, b) for a, b in zip(lo, hi))]
        data = np.asarray(self._level_data)
        self.layer.data = data.astype(np.float32) if data.dtype == np.float64 else data
        self._scan_shape = tuple(float(v) for v in data.shape)
        self._lookup["scan_shape"] = self._scan_shape
        self.update(self.deformation)
        self.status.emit(self.level_text)
        return level

    def _try_draw(self) -> str | None:
        try:
            _private.scene_canvas(self.viewer).render()
        except Exception as exc:  # vispy raises on a shader that does not compile or link
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            return f"the straight-view shader failed: {first}"
        return None

    def set_straight(self, straight: bool) -> None:
        """Toggle the same layer between the straight view and the bent scan (one texture for both)."""
        straight = bool(straight)
        if straight == self.straight or self.node is None:
            self.straight = straight
            return
        self.straight = straight
        if straight:
            _private.install(self.node, self._lookup, self._shape)
            self._set_table()
        else:
            _private.uninstall(self.node)
        # the straight box is drawn at the isotropic ds, the scan at its level spacing: napari re-uploads the
        # texture when the scale changes, so an anisotropic scan costs one upload per toggle (isotropic: none)
        # the bent view sits where the scan (the level, the crop) is: the texture's voxel 0 at its origin
        scale = (self._ds,) * 3 if straight else tuple(self._level_spacing)
        translate = (0.0, 0.0, 0.0) if straight else tuple(self._on_texture(self.deformation).origin)
        if not np.allclose(self.layer.scale, scale):
            self.layer.scale = scale
        if not np.allclose(self.layer.translate, translate):
            self.layer.translate = translate
        if straight:
            self.frame()
        else:
            self.viewer.reset_view()

    def frame(self) -> None:
        """Camera on the straight specimen from its side: its long axis (axis0) across the screen, the box
        fitted to the canvas (napari's default 3D view looks end-on down axis0)."""
        if self.layer is None or self._shape is None:
            return
        from ._layers import frame_side_view, world_box

        frame_side_view(self.viewer, world_box(self._shape, self.layer.scale, self.layer.translate))

    @property
    def scan_texture(self) -> Any:
        """The scan's GL texture (for tests: it must not be re-uploaded by an edit)."""
        return None if self.node is None else _private.scan_texture(self.node)

    # -- fallback ----------------------------------------------------------------------------------------------
    def _cpu_preview(self, deformation: Deformation) -> None:
        if self._preview is None:
            from ._preview import StraightPreview

            scan = self.scan
            self._preview = StraightPreview(self.viewer, lambda: scan)
            self.status.emit(self.level_text)
        self._preview.request(deformation)

    # -- the StraightPreview interface (the Refine panel can hold either) ---------------------------------------
    def request(self, deformation: Deformation | None = None) -> None:
        """Show ``deformation`` (default: the last one) unless disabled; the shader path is synchronous."""
        d = deformation if deformation is not None else self.deformation
        if d is not None and self.enabled:
            self.update(d)

    @property
    def idle(self) -> bool:
        """Nothing pending (the shader draws on napari's next paint; the CPU preview may still be working)."""
        return self._preview is None or self._preview.idle

    @property
    def preview(self) -> Any:
        """The CPU preview used when the shader is not available (None otherwise)."""
        return self._preview

    def close(self) -> None:
        """Remove the layer (or stop the CPU preview)."""
        if self._preview is not None:
            self._preview.close()
        if self.layer is not None and self.layer in self.viewer.layers:
            self.viewer.layers.remove(self.layer)
        self.layer = self.node = None
