"""Volumes as napari layer-data tuples (plain data and dicts, no napari import at module level: the core stays
Qt-free), the 3D stand-ins of a Labels layer (:class:`LabelsIn3D`) and of a large Image (:class:`ImageIn3D`), and
where the straight specimen is placed and framed (:func:`beside`, :func:`frame_side_view`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..io import Volume

__all__ = ["image_layer", "labels_layer", "labels_surface", "LabelsIn3D", "labels_in_3d", "ImageIn3D", "image_in_3d",
           "block_reduce", "coarse_step", "in_3d"]


def _geometry(spacing: Any, unit: str | None, origin: Any = (0.0, 0.0, 0.0)) -> dict[str, Any]:
    kwargs: dict[str, Any] = {
        "scale": tuple(float(s) for s in spacing),
        "translate": tuple(float(o) for o in origin),
        "axis_labels": ("axis0", "axis1", "axis2"),
    }
    if unit:
        kwargs["units"] = (unit,) * 3
    return kwargs


def image_layer(volume: Volume, *, name: str | None = None, **kwargs: Any) -> tuple[Any, dict[str, Any], str]:
    """An Image layer tuple: multiscale when the volume has a pyramid, lazy (dask) either way."""
    data: Any = list(volume.levels) if len(volume.levels) > 1 else volume.data
    meta = {
        "name": name or (volume.source and volume.source.rstrip("/").split("/")[-1]) or "volume",
        "multiscale": len(volume.levels) > 1,
        "metadata": {"napari_unwind": {"source": volume.source, "format": volume.format,
                                       "spacing": volume.spacing, "unit": volume.unit}},
        **_geometry(volume.spacing, volume.unit, volume.origin),
    }
    meta.update(kwargs)
    return data, meta, "image"


def labels_layer(labels: np.ndarray, *, spacing: Any, unit: str | None, name: str,
                 **kwargs: Any) -> tuple[Any, dict[str, Any], str]:
    """A Labels layer tuple with the same geometry conventions as :func:`image_layer`."""
    meta = {"name": name, **_geometry(spacing, unit)}
    meta.update(kwargs)
    return labels, meta, "labels"


def scan_units(viewer: Any) -> dict[str, Any]:
    """``{"units": ...}`` of the viewer's scan (its first Image layer with a physical unit), or ``{}``: the layers
    added over the scan take them, since napari stops using units when the layers' units disagree."""
    for layer in viewer.layers:
        units = getattr(layer, "units", None)
        if layer.__class__.__name__ == "Image" and units is not None and {str(u) for u in units} != {"pixel"}:
            return {"units": tuple(units)}
    return {}


# -- Labels in 3D: a coarse Surface instead of napari's volume ray caster ------------------------------------------
SURFACE_3D_SUFFIX = " (3D)"
SURFACE_3D_STEP = 2          # marching-cubes step (voxels): the 3D stand-in is this much coarser than the labels


def labels_surface(labels: Any, *, step: int = SURFACE_3D_STEP, min_voxels: int = 8
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(vertices, faces, label_of_vertex)`` of every label's boundary (marching cubes at ``step`` voxels, each
    label on its own bounding box), vertices in the labels' voxel coordinates; None when no label has
    ``min_voxels`` voxels."""
    from scipy import ndimage
    from skimage.measure import marching_cubes

    data = np.asarray(labels)
    step = max(1, int(step))
    verts: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    values: list[np.ndarray] = []
    count = 0
    boxes = ndimage.find_objects(data) if np.issubdtype(data.dtype, np.integer) and data.min() >= 0 else None
    if boxes is None:
        return None
    for index, box in enumerate(boxes, start=1):
        if box is None:
            continue
        mask = data[box] == index
        if int(mask.sum()) < min_voxels:
            continue
        padded = np.pad(mask, step).astype(np.float32)   # closed surfaces where a label touches its box's side
        try:
            v, f, _, _ = marching_cubes(padded, 0.5, step_size=step, allow_degenerate=False)
        except (RuntimeError, ValueError):   # too small for this step
            continue
        verts.append(v - step + np.array([s.start for s in box], dtype=np.float32))
        faces.append(f + count)
        values.append(np.full(len(v), index, dtype=np.float32))
        count += len(v)
    if not verts:
        return None
    return np.concatenate(verts).astype(np.float32), np.concatenate(faces), np.concatenate(values)


class _In3D:
    """What both 3D stand-ins share: the layer they draw, and closing when it leaves the viewer.

    A subclass connects its own events in ``__init__`` (after ``super().__init__``) and undoes them in
    ``_release``; ``close()`` runs that once.
    """

    def __init__(self, viewer: Any, layer: Any) -> None:
        self.viewer = viewer
        self.layer = layer
        self._closed = False
        viewer.layers.events.removed.connect(self._on_removed)

    def _on_removed(self, event: Any) -> None:
        if event.value is self.layer:
            self.close()

    def _release(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        """Disconnect and give napari its own 3D drawing of the layer back."""
        if self._closed:
            return
        self._closed = True
        self.viewer.layers.events.removed.disconnect(self._on_removed)
        self._release()

    @classmethod
    def attach(cls, viewer: Any, layer: Any, **kwargs: Any) -> Any:
        """The stand-in of ``layer`` (made on the first call; the viewer's and the layer's events keep it alive)."""
        existing = getattr(layer, "_napari_unwind_3d", None)
        if isinstance(existing, cls) and not existing._closed:
            return existing
        helper = cls(viewer, layer, **kwargs)
        object.__setattr__(layer, "_napari_unwind_3d", helper)
        return helper


class LabelsIn3D(_In3D):
    """Draws a Labels layer in 3D as a Surface layer (``"<name> (3D)"``) instead of napari's volume ray caster.

    napari draws a Labels layer in 3D by ray casting its whole volume; on software GL (Mesa llvmpipe) one frame of
    a few hundred voxels per side takes seconds and the first one tens of seconds, so switching to 3D froze the
    viewer (issue 21). Here the layer's own 3D volume node draws nothing, and while the viewer is in 3D a Surface
    of the labels' boundaries (marching cubes at ``step`` voxels, coloured with the layer's label colours) stands
    in for it; it follows the layer's data, visibility, opacity, blending, scale and translate. In 2D the stand-in
    is removed and the layer is exactly as before. The layer stays the one clicks reach (napari's ``get_value``
    along the view ray reads the layer's data, not what is drawn), and the layer selection is kept.

    ``close()`` disconnects and gives the layer its volume rendering back.
    """

    def __init__(self, viewer: Any, layer: Any, *, step: int = SURFACE_3D_STEP) -> None:
        super().__init__(viewer, layer)
        self.step = int(step)
        self.surface: Any = None
        self.builds = 0                    # marching-cubes runs on the UI thread (tests: data edits in 2D cost none)
        self.prefetches = 0                # marching-cubes runs in the background while in 2D
        self._key: Any = None
        self._node: Any = None
        self._ahead: tuple[Any, Any] | None = None   # (key, Future) of the mesh built ahead in the background
        self._mesh_data: Any = None
        viewer.dims.events.ndisplay.connect(self._sync)
        for name in ("data", "visible", "opacity", "blending", "scale", "translate"):
            getattr(layer.events, name).connect(self._sync)
        self._sync()

    def _data_key(self) -> Any:
        data = self.layer.data
        return (id(data), getattr(data, "shape", None), self.step)

    def _build_ahead(self) -> None:
        """In 2D, the mesh of the current data is made in a background thread, so that the switch to 3D finds it
        ready (its marching cubes were a third of the switch on a 440 x 148 x 148 tank)."""
        key = self._data_key()
        if self._key == key or (self._ahead is not None and self._ahead[0] == key):
            return
        if self._ahead is not None:
            self._ahead[1].cancel()  # an older data's mesh not started yet (the slider moved on): never made
        self.prefetches += 1
        self._ahead = (key, _mesh_pool().submit(labels_surface, self.layer.data, step=self.step))

    def _mesh(self, key: Any) -> Any:
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead[0] == key:
            try:
                return ahead[1].result()
            except Exception:  # noqa: BLE001 - made again here, where an error reaches the user
                pass
        self.builds += 1
        return labels_surface(self.layer.data, step=self.step)

    # the layer's own 3D node: napari resets its visibility on every ndisplay / visible change, so its draw is
    # replaced instead (it is drawn in 3D only; the 2D image node is untouched)
    def _silence_volume(self) -> None:
        from . import _private

        try:
            node = _private.volume_node(self.viewer, self.layer)
        except (KeyError, AttributeError, RuntimeError):
            return  # not on a canvas (a headless viewer): nothing is ray cast
        if node is not self._node:
            self._restore_volume()
            object.__setattr__(node, "draw", lambda *args, **kwargs: None)
            self._node = node

    def _restore_volume(self) -> None:
        if self._node is not None:
            try:
                object.__delattr__(self._node, "draw")
            except AttributeError:
                pass
            self._node = None

    @property
    def active(self) -> bool:
        """The stand-in is shown (the viewer is in 3D and the layer is in it)."""
        return self.surface is not None and self.surface in self.viewer.layers

    def _sync(self, event: Any = None) -> None:
        if self._closed:
            return
        layers = self.viewer.layers
        if self.layer in layers:
            # silenced in 2D already (the node draws in 3D only): napari's own handlers of the switch run before
            # any plugin's, and its layer controls make Qt paint the canvas there, in 3D (that paint ray cast every
            # Labels layer: 1.7 s of a 2.2 s switch on a 440 x 148 x 148 tank)
            self._silence_volume()
        if self.layer not in layers or self.viewer.dims.ndisplay != 3:
            self._remove_surface()
            if self.layer in layers:
                self._build_ahead()
            return
        layer = self.layer
        key = self._data_key()
        if self._key != key:
            self._mesh_data = self._mesh(key)
            self._key = key
        mesh = self._mesh_data
        if mesh is None:  # no label (an empty selection): nothing to draw, and no layer for it (a layer costs ~0.25 s)
            self._remove_surface()
            return
        props = {"visible": bool(layer.visible), "opacity": float(layer.opacity),
                 "blending": layer.blending, "scale": tuple(layer.scale), "translate": tuple(layer.translate)}
        verts, faces, values = mesh
        ids, inverse = np.unique(values.astype(np.int64), return_inverse=True)
        rgba = [layer.get_color(int(i)) for i in ids]  # None for the background (an empty selection's mesh)
        colors = np.asarray([(0, 0, 0, 0) if c is None else c for c in rgba], dtype=np.float32).reshape(-1, 4)
        colors = colors[inverse.reshape(-1)]
        if self.surface is None or self.surface not in layers:
            from napari.layers import Surface

            self.surface = Surface((verts, faces, values), vertex_colors=colors, shading="flat",
                                   name=f"{layer.name}{SURFACE_3D_SUFFIX}", units=tuple(layer.units),
                                   metadata={"napari_unwind": {"surface_of": layer.name}}, **props)
            active, selected = layers.selection.active, set(layers.selection)
            layers.insert(layers.index(layer) + 1, self.surface)
            layers.selection.clear()
            layers.selection.update(selected)   # adding a layer selects it: keep the user's (clicks reach it)
            layers.selection.active = active
            return
        s = self.surface
        if s.data[0] is not verts:
            s.vertex_colors = None            # napari checks the colours against the vertices on each assignment
            s.data = (verts, faces, values)
            s.vertex_colors = colors
        for name, value in props.items():
            if getattr(s, name) != value if name in ("visible", "opacity", "blending") \
                    else not np.allclose(getattr(s, name), value):
                setattr(s, name, value)

    def _remove_surface(self) -> None:
        if self.surface is not None and self.surface in self.viewer.layers:
            layers = self.viewer.layers
            active, selected = layers.selection.active, set(layers.selection) - {self.surface}
            layers.remove(self.surface)
            layers.selection.clear()
            layers.selection.update({x for x in selected if x in layers})
            if active is not None and active in layers:
                layers.selection.active = active
        self.surface = None

    def _release(self) -> None:
        """Remove the stand-in; the layer is ray cast in 3D again."""
        self.viewer.dims.events.ndisplay.disconnect(self._sync)
        for name in ("data", "visible", "opacity", "blending", "scale", "translate"):
            getattr(self.layer.events, name).disconnect(self._sync)
        self._remove_surface()
        self._restore_volume()


_POOL: Any = None


def _mesh_pool() -> Any:
    """One background thread for the meshes built ahead (numpy and scikit-image release the GIL in their loops)."""
    global _POOL
    if _POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="unwind-mesh")
    return _POOL


def labels_in_3d(viewer: Any, layer: Any, *, step: int = SURFACE_3D_STEP) -> LabelsIn3D:
    """The hook the dock calls once per Labels layer it adds: a :class:`LabelsIn3D` for it (the viewer's and the
    layer's events keep it alive); calling it again for the same layer returns the first one."""
    return LabelsIn3D.attach(viewer, layer, step=step)


# -- a large Image in 3D: napari's ray caster on a block-reduced copy -----------------------------------------------
# On Mesa llvmpipe a ray-cast frame costs (pixels covered) x (samples along a ray): the samples follow the texture's
# side along the view (napari's first 3D view looks along axis0, the tank's long side), and the texture's size
# matters far less (an 8x smaller copy of the tank at the same samples per ray draws no faster). So the copy is
# bounded by its longest side, IMAGE_3D_MAX_SIDE samples (about a 128^3 cube, also the texture napari's
# interactive examples ray cast), and the stand-in starts above IMAGE_3D_MIN_VOXELS (2M voxels, that cube) so
# images small enough to ray cast fast stay exactly as napari draws them. The sample tank's scan (440 x 148 x 148,
# 9.6M voxels) took ~4 s to switch and 1.2 s a frame; its copy at step 4 (110 x 37 x 37) see benchmarks/RESULTS.md.
IMAGE_3D_MIN_VOXELS = 2_000_000
IMAGE_3D_MAX_SIDE = 128


def coarse_step(shape: Any, min_voxels: int = IMAGE_3D_MIN_VOXELS, max_side: int = IMAGE_3D_MAX_SIDE) -> int:
    """The block side of the 3D copy of a volume of ``shape``: 1 (none) when it has at most ``min_voxels`` voxels,
    else the smallest integer step that brings the copy's longest side to ``max_side`` or less and its voxel count
    to ``min_voxels`` or less (the same step on every axis)."""
    shape = [max(int(n), 1) for n in shape]
    if int(np.prod(shape, dtype=np.int64)) <= min_voxels:
        return 1
    step = max(2, -(-max(shape) // max(int(max_side), 1)))
    while int(np.prod([-(-n // step) for n in shape], dtype=np.int64)) > min_voxels and step < max(shape):
        step += 1
    return step


def block_reduce(data: Any, step: int, how: str = "mean") -> np.ndarray:
    """``data`` reduced over ``step``-sided blocks (``how``: "mean", "max" or "min"); the last block on an axis is
    the partial one that is left (no padding), and the result keeps the data's dtype."""
    out = np.asarray(data)
    dtype = out.dtype
    if step <= 1:
        return out
    for axis, n in enumerate(out.shape):
        starts = np.arange(0, n, step)
        if how == "max":
            out = np.maximum.reduceat(out, starts, axis=axis)
        elif how == "min":
            out = np.minimum.reduceat(out, starts, axis=axis)
        else:
            acc = np.float32 if dtype.kind == "f" and dtype.itemsize <= 4 else np.float64
            sums = np.add.reduceat(out.astype(acc, copy=False), starts, axis=axis)
            counts = np.diff(np.append(starts, n)).astype(acc)
            out = sums / counts.reshape([-1 if a == axis else 1 for a in range(out.ndim)])
    if how == "mean" and dtype.kind in "iub":
        info = np.iinfo(dtype) if dtype.kind != "b" else None
        out = np.rint(out)
        if info is not None:
            out = np.clip(out, info.min, info.max)
    return out.astype(dtype, copy=False)


# what stands for a block, by rendering: its maximum where napari shows a maximum intensity projection (thin bright
# structures stay), its minimum for the minimum one, its mean otherwise (iso surfaces, translucent, average)
_REDUCE_BY_RENDERING = {"mip": "max", "attenuated_mip": "max", "minip": "min"}


class ImageIn3D(_In3D):
    """Draws a large 3D Image layer in 3D from a block-reduced copy, with napari's own ray caster.

    napari ray casts an Image layer's whole volume in 3D; on software GL (Mesa llvmpipe) the sample tank's scan
    (440 x 148 x 148) took about 4 s to switch to 3D and 1.2 s a frame. Here, while the layer is shown in 3D and
    its 3D slice has more than ``min_voxels`` voxels, napari's volume node is given a copy reduced over
    ``step``-sided blocks (:func:`coarse_step`: at most ``max_side`` voxels a side; :func:`block_reduce`: the
    block's maximum for the MIP renderings, its minimum for minip, its mean otherwise), and the layer's
    ``tile2data`` transform scales it by ``step`` with the block centres where they belong
    (``_private.coarse_3d_texture``). No layer is added: the layer's contrast limits, colormap, gamma, rendering,
    opacity, blending, visibility, attenuation, iso threshold, scale and translate apply to the copy through
    napari itself, the selection and the layer list are untouched, and clicks read the layer's full data
    (napari's ``get_value`` reads the slice, not the texture). In 2D napari draws the layer exactly as before
    (each new slice resets ``tile2data``). Multiscale layers are left alone (napari draws their coarsest level).

    Known differences from the full volume: attenuated MIP attenuates per sample, so fewer samples attenuate less;
    a bounding-box overlay of the layer is drawn in the copy's frame. ``close()`` (also when the layer is removed)
    gives napari its own upload back.
    """

    def __init__(self, viewer: Any, layer: Any, *, min_voxels: int = IMAGE_3D_MIN_VOXELS,
                 max_side: int = IMAGE_3D_MAX_SIDE) -> None:
        from . import _private

        self.min_voxels = int(min_voxels)
        self.max_side = int(max_side)
        self.builds = 0                 # block reductions run (tests)
        self.step = 1                   # the step of the copy last uploaded (1: the full slice)
        self._cache: tuple[Any, int, str, np.ndarray] | None = None
        super().__init__(viewer, layer)
        try:
            self._vl = _private.coarse_3d_texture(viewer, layer, self._coarsen)
        except (KeyError, AttributeError):  # not on a canvas (a headless viewer)
            self._closed = True
            viewer.layers.events.removed.disconnect(self._on_removed)
            raise
        layer.events.rendering.connect(self._on_rendering)

    def _how(self) -> str:
        return _REDUCE_BY_RENDERING.get(str(getattr(self.layer.rendering, "value", self.layer.rendering)), "mean")

    def _coarsen(self, data: Any) -> tuple[np.ndarray, tuple[int, ...]] | None:
        step = coarse_step(data.shape, self.min_voxels, self.max_side)
        if step <= 1 or self._closed:
            self.step = 1
            return None
        how = self._how()
        cache = self._cache
        if cache is not None and cache[0] is data and cache[1] == step and cache[2] == how:
            small = cache[3]
        else:
            small = block_reduce(data, step, how)
            self.builds += 1
            self._cache = (data, step, how, small)
        self.step = step
        return small, (step,) * 3

    @property
    def active(self) -> bool:
        """napari draws the layer from the coarse copy (in 3D, over the budget)."""
        from . import _private

        return not self._closed and self.step > 1 and _private.ndisplay_of(self.layer) == 3

    def _on_rendering(self, event: Any = None) -> None:
        cache = self._cache
        if self.active and cache is not None and cache[2] != self._how():
            from . import _private

            _private.refresh_3d_texture(self._vl)

    def _release(self) -> None:
        """napari uploads the layer's full slice again (at once when it is shown in 3D)."""
        self.layer.events.rendering.disconnect(self._on_rendering)
        self._cache = None
        self.step = 1
        from . import _private

        if self.layer in self.viewer.layers:
            _private.restore_3d_texture(self._vl)
        else:
            self._vl.__dict__.pop("downsample_texture", None)


def image_in_3d(viewer: Any, layer: Any, *, min_voxels: int = IMAGE_3D_MIN_VOXELS,
                max_side: int = IMAGE_3D_MAX_SIDE) -> ImageIn3D | None:
    """The hook for a 3D grey-value Image layer: an :class:`ImageIn3D` for it (None for RGB, multiscale or 2D
    layers, and on a viewer without a canvas); calling it again for the same layer returns the first one."""
    if getattr(layer, "rgb", False) or getattr(layer, "multiscale", False) or getattr(layer, "ndim", 0) < 3:
        return None
    try:
        return ImageIn3D.attach(viewer, layer, min_voxels=min_voxels, max_side=max_side)
    except (KeyError, AttributeError):
        return None  # not on a canvas (a headless viewer): nothing is ray cast


def in_3d(viewer: Any, layer: Any) -> Any:
    """The hook the dock calls for each layer it adds or takes as the scan: a 3D stand-in where napari's own 3D
    drawing is too slow on software GL (Labels: :func:`labels_in_3d`; a 3D grey-value Image: :func:`image_in_3d`,
    which draws from a coarse copy when the volume has more than ``IMAGE_3D_MIN_VOXELS`` voxels); None for a layer
    drawn as it is."""
    from napari.layers import Image, Labels

    if isinstance(layer, Labels):
        return labels_in_3d(viewer, layer)
    if isinstance(layer, Image):
        return image_in_3d(viewer, layer)
    return None


# -- where the straight specimen goes, and the camera on it ---------------------------------------------------------
def world_box(shape: Any, scale: Any, translate: Any) -> np.ndarray:
    """``(2, 3)`` world corners (low, high) of a volume's voxels, each voxel a box of ``scale`` around its centre."""
    n = np.asarray(tuple(shape)[-3:], dtype=float)
    s = np.asarray(tuple(scale)[-3:], dtype=float)
    t = np.asarray(tuple(translate)[-3:], dtype=float)
    return np.stack([t - s / 2, t + (n - 0.5) * s])


def beside(scan_box: np.ndarray, box: np.ndarray, *, gap: float | None = None) -> np.ndarray:
    """The shift that puts ``box`` next to ``scan_box`` along the last axis: its low side ``gap`` beyond the scan's
    high side (default: a tenth of the scan's width there), its axis0 start on the scan's, centred on axis1."""
    scan_box, box = np.asarray(scan_box, float), np.asarray(box, float)
    if gap is None:
        gap = 0.1 * float(scan_box[1, 2] - scan_box[0, 2])
    shift = np.empty(3)
    shift[0] = scan_box[0, 0] - box[0, 0]
    shift[1] = scan_box.mean(axis=0)[1] - box.mean(axis=0)[1]
    shift[2] = scan_box[1, 2] + max(float(gap), 0.0) - box[0, 2]
    return shift


def scan_box(scan: Any) -> np.ndarray | None:
    """The world box of a scan (a Volume: its spacing and origin; a bare array: unit voxels at 0), or None."""
    shape = getattr(scan, "shape", None)
    if shape is None or len(shape) < 3:
        return None
    return world_box(shape, getattr(scan, "spacing", (1.0,) * 3), getattr(scan, "origin", (0.0,) * 3))


def frame_side_view(viewer: Any, box: np.ndarray, *, margin: float = 0.9, across: int = 0, along: int = 2) -> None:
    """3D camera on ``box`` (world low/high corners): looking along axis ``along`` with the third axis up, so axis
    ``across`` (a straight specimen's long axis0 by default) runs across the screen; centred on the box and zoomed
    so it fits the canvas."""
    box = np.asarray(box, float)
    up = 3 - across - along
    camera = viewer.scene.camera
    if viewer.dims.ndisplay == 3:
        view, up_direction = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        view[along], up_direction[up] = 1.0, -1.0
        camera.set_view_direction(tuple(view), up_direction=tuple(up_direction))
    camera.center = tuple(box.mean(axis=0))
    size = np.maximum(box[1] - box[0], 1e-9)
    height, width = (float(v) for v in viewer.canvas.size)   # (rows, columns) of the canvas
    camera.zoom = margin * min(width / size[across], height / size[up])


#: napari's own first 3D view: looking down axis0 (``Camera.angles`` of a new viewer).
_NAPARI_3D_ANGLES = (0.0, 0.0, 0.0)


def side_view_in_3d(viewer: Any, layer: Any) -> None:
    """When the viewer first goes to 3D with ``layer`` (the scan) shown and the camera still in napari's own first
    view, look at the scan from its side instead: its longest world axis across the screen, along its shortest.

    napari's first 3D view looks down axis0, which for a scan of fish in a tube is end-on down the tube: the fish
    are seen head-on, and on software GL every ray crosses the scan's longest side (the switch to 3D of a 440 x 148
    x 148 tank took 2.3 s through the dock, 1.0-1.15 s seen from the side). A camera the user turned is kept.
    """
    def on_ndisplay(event: Any = None) -> None:
        if layer not in viewer.layers:  # the scan is gone: forget it
            viewer.dims.events.ndisplay.disconnect(on_ndisplay)
            return
        if viewer.dims.ndisplay != 3 or not layer.visible:
            return
        if not np.allclose(tuple(viewer.scene.camera.angles), _NAPARI_3D_ANGLES):
            return
        box = world_box(layer.data.shape[-3:], tuple(layer.scale)[-3:], tuple(layer.translate)[-3:])
        size = box[1] - box[0]
        across, along = int(np.argmax(size)), int(np.argmin(size))
        if across == along:  # a cube: napari's view is as good as any
            return
        frame_side_view(viewer, box, across=across, along=along)

    if getattr(layer, "_napari_unwind_side_view", None) is None:
        object.__setattr__(layer, "_napari_unwind_side_view", on_ndisplay)
        viewer.dims.events.ndisplay.connect(on_ndisplay, position="last")  # after napari resets the view
