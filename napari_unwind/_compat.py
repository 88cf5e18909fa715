"""Third-party quirks, each solved once, here.

pytetwild
    ``import pytetwild`` fails unless pyvista (and with it VTK, ~150 MB) is importable, although the mesher itself
    is a plain compiled extension taking numpy arrays. :func:`tetrahedralize` loads that extension directly,
    without running the package's ``__init__``, so napari-unwind needs neither pyvista nor VTK. The signature
    of the extension is pinned by the dependency range ``pytetwild>=0.4,<0.5`` and checked by the tests.

    The first call in a process resets the C-level SIGINT handler to the default (geogram's initialisation,
    inside fTetWild, calls ``signal(SIGINT, SIG_DFL)``), behind Python's back: ``signal.getsignal`` still names
    Python's handler, but Ctrl-C now kills the process outright (status -2, no cleanup). :func:`tetrahedralize`
    runs the mesher inside :func:`signals_kept`, which puts the handlers back after the call and holds the
    signals pending during it.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.machinery
import importlib.util
import os
import signal
import sys
import threading
from collections.abc import Iterator
from functools import cache
from types import ModuleType

import numpy as np

__all__ = ["signals_kept", "tetrahedralize", "tetwild_extension"]

_TETWILD_LITTER = "__tracked_surface.stl"
_TETWILD_LOCK = threading.Lock()  # fTetWild keeps global state; one mesh at a time


#: The signals whose C-level handling a native call must leave as it found it: the ones the command line handles
#: (SIGINT, SIGTERM, SIGHUP) and the ones Python itself sets at start-up (SIGPIPE and SIGXFSZ ignored).
KEPT_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGPIPE", "SIGXFSZ")
                     if hasattr(signal, name))
_SIGACTION_BYTES = 512  # more than any libc's struct sigaction: it is saved and put back as it is, never read


@cache
def _libc() -> ctypes.CDLL | None:
    if os.name != "posix":
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.sigaction.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
        return libc
    except (OSError, AttributeError):
        return None


def c_sigaction(signum: int) -> bytes | None:
    """The process's C-level handling of ``signum`` (libc's ``struct sigaction``, as raw bytes), or None where
    it cannot be read. Unlike ``signal.getsignal``, this sees a change made by compiled code.

    Only :func:`c_handler` of it is compared: glibc fills the unused tail of ``sa_mask`` from its stack."""
    libc = _libc()
    if libc is None:
        return None
    buf = ctypes.create_string_buffer(_SIGACTION_BYTES)
    if libc.sigaction(int(signum), None, buf) != 0:
        return None
    return buf.raw


def c_handler(signum: int) -> int | None:
    """The address of the C-level handler of ``signum`` (0: SIG_DFL, 1: SIG_IGN; ``sa_handler`` is the first
    field of ``struct sigaction`` in glibc, musl and macOS), or None where it cannot be read."""
    raw = c_sigaction(signum)
    return None if raw is None else int.from_bytes(raw[:ctypes.sizeof(ctypes.c_void_p)], sys.byteorder)


def _set_c_sigaction(signum: int, raw: bytes) -> None:
    libc = _libc()
    if libc is not None:
        libc.sigaction(int(signum), ctypes.create_string_buffer(raw, _SIGACTION_BYTES), None)


@contextlib.contextmanager
def signals_kept(signums: tuple[int, ...] = KEPT_SIGNALS) -> Iterator[None]:
    """Run a native call that may change the process's signal handlers behind Python's back.

    Before: the C-level handlers of ``signums`` are saved, and the signals are blocked in this thread (threads
    the call starts inherit that). After: a handler the call changed is put back as it was, then the signals are
    unblocked, so one that arrived meanwhile is delivered now, to Python's handler (KeyboardInterrupt, the
    command line's SIGTERM handler) instead of killing the process. Left open: a signal the kernel hands, during
    the call, to another thread that does not block it meets whatever handler is set at that moment (during
    fTetWild's first call, SIG_DFL for SIGINT: numpy's OpenBLAS thread takes it and the process dies).
    """
    saved = {s: (c_sigaction(s), c_handler(s)) for s in signums}
    mask = None
    if hasattr(signal, "pthread_sigmask"):
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, signums)
    try:
        yield
    finally:
        for s, (raw, handler) in saved.items():
            if raw is not None and c_handler(s) != handler:
                _set_c_sigaction(s, raw)
        if mask is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)


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
    with _TETWILD_LOCK, signals_kept():
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
