"""The straight preview layer, CPU path: :func:`napari_unwind.preview.preview_volume` recomputed off the UI thread
after each edit, latest edit wins.

Each request gets a generation number. One worker runs at a time; requests that arrive while it runs are coalesced
(only the newest is kept), and a result whose generation is no longer the newest is dropped, so the layer always
ends on the last deformation and never shows an older one after a newer one.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from napari.qt.threading import create_worker
from psygnal import Signal

from ..deformation import Deformation
from ..errors import UnwindError
from ..preview import level_deformation, preview_level, preview_volume

__all__ = ["StraightPreview", "compute_preview", "PREVIEW_NAME"]

PREVIEW_NAME = "straight preview"


def compute_preview(scan: Any, deformation: Deformation, min_across: float = 64
                    ) -> tuple[np.ndarray, float, tuple[float, float, float]]:
    """``(array, spacing, origin)``: the preview and the straight coordinates ``(s, y, x)`` of its voxel (0, 0, 0),
    as :func:`~napari_unwind.warp.straighten` places its output (so the preview lines up with an export)."""
    level = preview_level(scan, deformation, min_across=min_across)
    array, ds = preview_volume(scan, deformation, min_across=min_across, level=level)
    i0, j0 = level_deformation(scan, deformation, level).grid_centre(ds)
    return array, ds, (deformation.s_range[0], -i0 * ds, -j0 * ds)


class StraightPreview:
    """Keeps the viewer's "straight preview" Image layer equal to the preview of the latest requested deformation.

    Parameters
    ----------
    viewer : napari.Viewer
    scan : callable
        Returns the scan (a Volume: its pyramid is used), or None.
    min_across : float
        See :func:`napari_unwind.preview.preview_level`.

    Signals
    -------
    status(str)
        A one-line message: an error of the latest request, or "" when it was shown.
    """

    status = Signal(str)

    def __init__(self, viewer: Any, scan: Callable[[], Any], *, min_across: float = 64) -> None:
        self.viewer = viewer
        self._scan = scan
        self.min_across = min_across
        self.enabled = True
        self.generation = 0          # the newest request
        self.shown_generation = 0    # the request the layer shows
        self.computed = 0            # workers run (fewer than requests when edits are coalesced)
        self._worker: Any = None
        self._pending: tuple[int, Any, Deformation] | None = None
        self._closed = False
        self._coming: Any = None  # the new preview layer while it goes into the viewer (a step a turn)

    def close(self) -> None:
        """Stop for good (the dock is going away): queued requests are dropped and a running worker's result too."""
        self._closed = True
        self._pending = None
        if self._coming is not None:
            from . import _reveal

            _reveal.cancel(self._coming)

    @property
    def idle(self) -> bool:
        """No worker running and none queued, and the layer in the viewer (:mod:`._reveal`)."""
        from . import _reveal

        return self._worker is None and self._pending is None and not (
            self._coming is not None and _reveal.waiting(self._coming))

    @property
    def layer(self) -> Any:
        """The preview layer, or None when there is none in the viewer (or on its way in: :mod:`._reveal`)."""
        from . import _reveal

        coming = self._coming
        if coming is not None and (coming in self.viewer.layers or _reveal.waiting(coming)):
            return coming
        self._coming = None
        return self.viewer.layers[PREVIEW_NAME] if PREVIEW_NAME in self.viewer.layers else None

    def request(self, deformation: Deformation | None = None) -> None:
        """Recompute for ``deformation`` (the newest request wins)."""
        self.generation += 1
        scan = self._scan()
        if self._closed or not self.enabled or deformation is None or scan is None:
            self._pending = None
            return
        job = (self.generation, scan, deformation)
        if self._worker is not None:
            self._pending = job  # coalesce: only the newest waits
            return
        self._start(job)

    def _start(self, job: tuple[int, Any, Deformation]) -> None:
        gen, scan, d = job
        self.computed += 1
        worker = create_worker(_run, gen, scan, d, self.min_across, _start_thread=False)
        worker.returned.connect(self._on_returned)
        worker.finished.connect(self._on_finished)
        self._worker = worker
        worker.start()

    def _on_returned(self, result: tuple[int, Any, Any, Any, str | None]) -> None:
        gen, array, ds, origin, error = result
        if gen != self.generation or self._closed:
            return  # stale: a newer edit is queued or running
        if error is not None:
            self.status.emit(f"straight preview: {error}")
            return
        self._show(array, ds, origin)
        self.shown_generation = gen
        self.status.emit("")

    def _on_finished(self) -> None:
        self._worker = None
        if self._pending is not None:
            job, self._pending = self._pending, None
            self._start(job)

    def _placed(self, array: np.ndarray, ds: float, origin: tuple[float, float, float]) -> tuple[float, ...]:
        """The layer's translate: the straight volume beside the scan (along the last axis, with a gap), not over
        it at the straight coordinates' origin; the straight coordinates stay in the layer's metadata."""
        from ._layers import beside, scan_box, world_box

        box = scan_box(self._scan())
        if box is None:
            return tuple(float(v) for v in origin)
        return tuple(float(v) for v in np.asarray(origin, float) + beside(box, world_box(array.shape, (ds,) * 3,
                                                                                            origin)))

    def _show(self, array: np.ndarray, ds: float, origin: tuple[float, float, float]) -> None:
        layer = self.layer
        scale = (ds, ds, ds)
        translate = self._placed(array, ds, origin)
        meta = {"napari_unwind": {"preview": True, "straight_origin": tuple(float(v) for v in origin)}}
        if layer is None:
            from napari.layers import Image

            from . import _reveal
            from ._layers import scan_units

            # into the viewer and shown on later turns, one step a turn; the user's selection is kept; then the
            # camera takes in the scan and the preview beside it (first shown)
            self._coming = Image(array, name=PREVIEW_NAME, scale=scale, translate=translate, metadata=meta,
                                 **scan_units(self.viewer))
            _reveal.add_layer(self.viewer, self._coming, keep_active=True, now=False, then=self.viewer.reset_view)
            return
        layer.data = array
        layer.scale = scale
        layer.translate = translate
        layer.metadata = {**layer.metadata, **meta}


def _run(gen: int, scan: Any, d: Deformation, min_across: float) -> tuple[int, Any, Any, Any, str | None]:
    try:
        array, ds, origin = compute_preview(scan, d, min_across)
    except UnwindError as e:
        return gen, None, None, None, str(e)
    return gen, array, ds, origin, None
