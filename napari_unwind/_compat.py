"""Third-party quirks, each solved once, here.

pytetwild
    ``import pytetwild`` fails unless pyvista (and with it VTK, ~150 MB) is importable, although the mesher itself
    is a plain compiled extension taking numpy arrays. :func:`tetrahedralize` loads that extension directly,
    without running the package's ``__init__``, so napari-unwind needs neither pyvista nor VTK. The signature
    of the extension is pinned by the dependency range ``pytetwild>=0.4,<0.5`` and checked by the tests.

    fTetWild runs in a process of its own (:mod:`napari_unwind._tetwild_child`): its first call in a process
    resets the C-level SIGINT handler to the default (geogram's initialisation calls ``signal(SIGINT, SIG_DFL)``)
    behind Python's back, after which Ctrl-C killed the process outright (status -2, no cleanup), and during that
    call a SIGINT taken by any other thread (numpy's OpenBLAS threads) did the same; Python cannot block signals
    in threads it did not start. In a child, the caller's handlers are never touched, an interrupt stops the
    child, a crash of the mesher is an error instead of the end of the caller, and the debug file fTetWild writes
    into the current folder lands in the child's own temporary folder.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import json
import os
import signal
import subprocess
import sys
import tempfile
from functools import cache
from types import ModuleType

import numpy as np

from .progress import checkpoint

__all__ = ["tetrahedralize", "tetwild_extension"]


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

    Notes
    -----
    The mesher runs in a child process (see the module's notes); an interrupt while it runs stops the child and
    propagates. A mesher that fails or crashes raises RuntimeError with one line.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.uint32)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 4:
        raise ValueError(f"vertices must have shape (N>=4, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 4:
        raise ValueError(f"faces must have shape (M>=4, 3), got {faces.shape}")
    if not np.isfinite(vertices).all():
        raise ValueError(f"vertices must be finite, got {int((~np.isfinite(vertices)).any(axis=1).sum())} with NaN "
                         "or infinity")
    if faces.max() >= len(vertices):
        raise ValueError(f"faces must index the {len(vertices)} vertices, got index {int(faces.max())}")
    options = {"edge_length_fac": float(edge_length_fac), "epsilon": float(epsilon), "optimize": bool(optimize),
               "coarsen": bool(coarsen), "stop_energy": float(stop_energy), "num_threads": int(num_threads),
               "max_iterations": int(max_iterations)}
    with tempfile.TemporaryDirectory(prefix="unwind-tetwild-") as folder:
        np.savez(os.path.join(folder, "surface.npz"), vertices=vertices, faces=faces,
                 options=np.array(json.dumps(options)))
        code = _run_child(folder)
        result = os.path.join(folder, "tets.npz")
        if code == 0 and os.path.exists(result):
            with np.load(result, allow_pickle=False) as z:
                return np.asarray(z["V"], dtype=np.float64), np.asarray(z["T"], dtype=np.int32)
        error = os.path.join(folder, "error.txt")
        if os.path.exists(error):
            with open(error, encoding="utf-8") as f:
                raise RuntimeError(f"fTetWild failed on a surface of {len(faces)} triangles: {f.read().strip()}")
        how = f"status {code}"
        if code < 0 and -code in signal.valid_signals():
            how = f"signal {signal.Signals(-code).name}"
        raise RuntimeError(f"fTetWild ended with {how} on a surface of {len(faces)} triangles; "
                           "tet_mesher='lattice' meshes without it")


def _run_child(folder: str) -> int:
    """Run :mod:`napari_unwind._tetwild_child` on ``folder`` and return its status; an interrupt (or any
    exception) while waiting stops the child before it propagates."""
    package_parent = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_parent, env.get("PYTHONPATH")) if p)
    with open(os.path.join(folder, "output.txt"), "wb") as output:
        proc = subprocess.Popen([sys.executable, "-m", "napari_unwind._tetwild_child", folder], cwd=folder,
                                stdin=subprocess.DEVNULL, stdout=output, stderr=output, env=env)
        try:
            while True:  # a cancelled job (progress.checkpoint raises) stops the child below
                try:
                    return proc.wait(timeout=0.1)
                except subprocess.TimeoutExpired:
                    checkpoint()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
