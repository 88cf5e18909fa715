"""Third-party quirks, each solved once, here.

pytetwild
    ``import pytetwild`` fails unless pyvista (and with it VTK, ~150 MB) is importable, although the mesher itself
    is a plain compiled extension taking numpy arrays. :func:`tetrahedralize` loads that extension directly,
    without running the package's ``__init__``, so napari-unwind needs neither pyvista nor VTK. The signature
    of the extension is pinned by the dependency range ``pytetwild>=0.4,<0.5`` and checked by the tests.
"""

from __future__ import annotations

import contextlib
import importlib.machinery
import importlib.util
import os
import sys
import threading
from functools import cache
from types import ModuleType

import numpy as np

__all__ = ["tetrahedralize", "tetwild_extension"]

_TETWILD_LITTER = "__tracked_surface.stl"
_TETWILD_LOCK = threading.Lock()  # fTetWild keeps global state; one mesh at a time


@cache
def tetwild_extension() -> ModuleType:
    """The compiled fTetWild wrapper of pytetwild, imported without importing pyvista."""
    name = "pytetwild.PyfTetWildWrapper"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec("pytetwild")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("pytetwild is not installed; reinstall napari-unwind (pip install napari-unwind)")
    for folder in spec.submodule_search_locations:
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = f"{folder}/PyfTetWildWrapper{suffix}"
            ext_spec = importlib.util.spec_from_file_location(name, path)
            if ext_spec is not None and ext_spec.loader is not None and os.path.exists(path):
                module = importlib.util.module_from_spec(ext_spec)
                ext_spec.loader.exec_module(module)
                sys.modules[name] = module
                return module
    raise ImportError(f"pytetwild's compiled extension was not found in {list(spec.submodule_search_locations)}")


def tetrahedralize(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    edge_length_fac: float = 0.05,
    epsilon: float = 1e-3,
    optimize: bool = True,
    coarsen: bool = False,
    stop_energy: float = 10.0,
    num_threads: int = 0,
    max_iterations: int = 80,
) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedralise a closed triangle surface with fTetWild.

    Parameters
    ----------
    vertices : (N, 3) float array
        Surface vertices.
    faces : (M, 3) int array
        Triangles (indices into ``vertices``).
    edge_length_fac : float
        Target edge length relative to the bounding box diagonal (pytetwild's ``edge_length_fac``).
    epsilon : float
        Envelope size relative to the bounding box diagonal.
    optimize, coarsen, stop_energy, num_threads, max_iterations
        fTetWild's own options (``num_threads=0``: all cores).

    Returns
    -------
    V : (P, 3) float64 array
        Tet mesh vertices.
    T : (Q, 4) int32 array
        Tetrahedra, positively oriented (VTK ordering: every tet has positive signed volume).
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.uint32)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 4:
        raise ValueError(f"vertices must have shape (N>=4, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 4:
        raise ValueError(f"faces must have shape (M>=4, 3), got {faces.shape}")
    ext = tetwild_extension()
    # fTetWild writes a debug copy of the surface, __tracked_surface.stl, into the current folder: remove it
    # again unless it was there before (the user's own file).
    litter = os.path.abspath(_TETWILD_LITTER)
    existed = os.path.exists(litter)
    with _TETWILD_LOCK:
        try:
            V, T = ext.tetrahedralize_mesh(
                vertices, faces, optimize, False, float(edge_length_fac), 0.0, float(epsilon), float(stop_energy),
                coarsen, int(num_threads), int(max_iterations), 6, True, True, False,
                np.empty((0, 3), dtype=np.float64), np.empty((0, 4), dtype=np.int32), np.empty(0, dtype=np.float64),
            )
        finally:
            if not existed:
                with contextlib.suppress(OSError):
                    os.remove(litter)
    return np.asarray(V, dtype=np.float64), np.asarray(T, dtype=np.int32)
