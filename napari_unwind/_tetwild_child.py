"""fTetWild in a process of its own: ``python -m napari_unwind._tetwild_child FOLDER``.

:func:`napari_unwind._compat.tetrahedralize` starts this with ``FOLDER`` as the current directory, holding
``surface.npz`` (``vertices``, ``faces`` and ``options``, a JSON text of the mesher's arguments); it writes
``tets.npz`` (``V``, ``T``) there, or ``error.txt`` (one line) and exits 1. fTetWild's debug copy of the surface
(``__tracked_surface.stl``) lands in ``FOLDER`` too, and goes with it.
"""

from __future__ import annotations

import json
import os
import sys


def main(folder: str) -> int:
    import numpy as np

    from ._compat import tetwild_extension

    try:
        with np.load(os.path.join(folder, "surface.npz"), allow_pickle=False) as z:
            vertices, faces = z["vertices"], z["faces"]
            o = json.loads(str(z["options"]))
        V, T = tetwild_extension().tetrahedralize_mesh(
            vertices, faces, bool(o["optimize"]), False, float(o["edge_length_fac"]), 0.0, float(o["epsilon"]),
            float(o["stop_energy"]), bool(o["coarsen"]), int(o["num_threads"]), int(o["max_iterations"]), 6, True,
            True, False, np.empty((0, 3), dtype=np.float64), np.empty((0, 4), dtype=np.int32),
            np.empty(0, dtype=np.float64),
        )
        tmp = os.path.join(folder, "tets.tmp.npz")
        np.savez(tmp, V=np.asarray(V, dtype=np.float64), T=np.asarray(T, dtype=np.int32))
        os.replace(tmp, os.path.join(folder, "tets.npz"))
        return 0
    except Exception as e:  # reported to the parent in one line; the parent raises it
        with open(os.path.join(folder, "error.txt"), "w", encoding="utf-8") as f:
            f.write(f"{type(e).__name__}: {e}".splitlines()[0][:500])
        return 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
