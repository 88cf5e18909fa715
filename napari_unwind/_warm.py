"""Compile the numba kernels of the dock's steps into numba's on-disk cache, in a child process.

numba compiles a kernel at its first call for each set of argument types and keeps the machine code in its cache
(every kernel here is ``cache=True``), so that later processes load it in milliseconds. A first call in napari's own
process compiles there: 0.2-0.4 s in which the compiler's Python, and the garbage collections its many objects set
off on napari's large heap, hold the interpreter, so the UI thread stalls although the step runs in a worker (issue
21: on a fresh install the segment step stalled the UI 221-241 ms while running and 336-415 ms showing its result,
the skeleton step 277 ms showing its preview; 53-77 ms with the cache filled).

The dock runs ``python -m napari_unwind._warm`` once per process in a background thread (``_widget._warm_imports``):
the child runs the same core code as the dock's steps on small synthetic scans (the segmentation, a selection, the
suggested ends, the straight preview and exports for the usual voxel types, points mapped back), which fills the
cache where it is missing and only loads it where it is there. The dock's own first calls then load. Nothing of the
child reaches the user: its output is discarded, and a failure only means the dock's first calls compile as before.
"""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np

__all__ = ["SCAN_DTYPES", "warm", "warm_in_child"]

#: the voxel types of the scans the kernels are compiled for (numba compiles one machine code per type)
SCAN_DTYPES = ("uint8", "uint16", "int16", "float32")
#: seconds the child may take (a fresh cache on a loaded 2-core machine: about 30-60 s)
TIMEOUT = 600.0


def _tube(dtype: str) -> np.ndarray:
    """A bright tube bent in a half wave along axis 0 of a 40 x 24 x 24 scan, in ``dtype``."""
    z, y, x = np.mgrid[:40, :24, :24].astype(float)
    cy = 12 + 4 * np.sin(np.pi * z / 39)
    inside = (y - cy) ** 2 + (x - 12) ** 2 <= 16
    values = np.where(inside, 200.0, 20.0) + 5 * np.sin(x + 2 * y + 3 * z)
    return values.astype(dtype)


def warm() -> None:
    """Run the dock's core steps once on small scans of each of :data:`SCAN_DTYPES` (see the module)."""
    from .deformation import Deformation
    from .io import Volume
    from .preview import preview_volume
    from .progress import run
    from .warp import map_points, straighten
    from .workflow import Workflow

    z = np.arange(2.0, 38.0, 4.0)
    centre = np.stack([z, 12 + 4 * np.sin(np.pi * z / 39), np.full_like(z, 12.0)], axis=1)
    d = Deformation.from_polyline(centre, spacing=1.0, cage_half_extent=6.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for dtype in SCAN_DTYPES:
            volume = Volume(_tube(dtype), spacing=(1.0, 1.0, 1.0))
            wf = Workflow()
            wf.set_scan(volume, name="warm")
            task = wf.segment_task()
            task.apply(run(task.make()))
            if wf.pick(np.round(centre[len(centre) // 2]).astype(int)):
                task = wf.suggest_ends_task()
                task.apply(run(task.make()))
                np.asarray(wf.mask())
            preview_volume(volume, d, min_across=8)
            for order in (0, 1):
                np.asarray(straighten(volume, d, order=order).data.compute())
        mask = Volume((_tube("uint8") > 100).astype("uint8"), spacing=(1.0, 1.0, 1.0))
        np.asarray(straighten(mask, d, order=0).data.compute())
        map_points(centre, d, to="straight", strict=False)


def warm_in_child(timeout: float = TIMEOUT) -> bool:
    """Run :func:`warm` in a child Python (its output discarded); True when it finished without an error."""
    try:
        done = subprocess.run([sys.executable, "-m", "napari_unwind._warm"], stdin=subprocess.DEVNULL,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=timeout, check=False)
    except (OSError, subprocess.SubprocessError):
        return False
    return done.returncode == 0


if __name__ == "__main__":
    import os

    if hasattr(os, "nice"):
        os.nice(10)  # behind the user's own work on the same cores
    warm()
