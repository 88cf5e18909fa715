"""Shared fixtures. Compute tests need no viewer; Qt tests use napari's ``make_napari_viewer``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real scans in ../shared/data; tests using them skip cleanly where the folder is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real scans not available ({SHARED_DATA} is absent)")
    return SHARED_DATA


def no_leftovers(folder: Path) -> list[Path]:
    """Temporary outputs of atomic writes left in ``folder`` (there must be none after an error)."""
    return [p for p in folder.rglob("*") if "unwind-tmp" in p.name]


#: The installed ``unwind`` command next to the interpreter running the tests.
UNWIND = Path(sys.executable).with_name("unwind")


def fish_case(folder: Path):
    """A phantom fish (seed 2, no noise, no tube) written as ``fish.zarr`` in ``folder`` with a session of its true
    deformation (``fish.unwind.json``): returns (fish, scan, session path, deformation)."""
    from napari_unwind.datasets import fish_phantom
    from napari_unwind.demo import true_deformation
    from napari_unwind.io import write_volume
    from napari_unwind.session import Session, SourceInfo, save_session

    fish = fish_phantom(seed=2, noise=0.0, tube=False)
    scan = write_volume(fish.volume, folder / "fish.zarr", spacing=fish.spacing, unit=fish.unit)
    d = true_deformation(fish)
    session = save_session(Session(source=SourceInfo.from_path(scan), deformation=d), folder / "fish.unwind.json")
    return fish, scan, session, d


def write_segment_crop(mask, spacing, path: Path):
    """``mask`` (array order, origin 0) cropped to its non-zero box and written with pynrrd as 3D Slicer saves a
    segment (``.seg.nrrd``): the box's voxels, the scan's directions and the ``space origin`` that places it.
    Returns (path, the box's first voxel in the scan, the crop)."""
    import nrrd
    import numpy as np

    sp = np.asarray(spacing, dtype=float)
    idx = np.argwhere(mask)
    lo, hi = idx.min(axis=0), idx.max(axis=0) + 1
    crop = np.asarray(mask)[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.uint8)
    nrrd.write(str(path), np.ascontiguousarray(crop.transpose(2, 1, 0)),
               {"space": "left-posterior-superior", "space directions": np.diag(sp[::-1]),
                "space origin": (lo * sp)[::-1], "kinds": ["domain"] * 3, "space units": ["mm"] * 3})
    return path, lo, crop


def run_unwind(*args) -> tuple[int, str, str]:
    """Run ``unwind ARGS...`` as a user would; returns (exit status, stdout, stderr)."""
    r = subprocess.run([str(UNWIND), *map(str, args)], capture_output=True, text=True)
    return r.returncode, r.stdout, r.stderr


@pytest.fixture(autouse=True)
def _qt_deletions_done_before_each_test():
    """Deliver the Qt deletions an earlier test left pending before this test starts.

    pytest-qt closes a test's widgets with ``deleteLater``; the deletion then runs inside the next test's event
    loop (``qtbot.waitUntil``). A vispy canvas deleted there takes its GL context with it and leaves no context
    current, while vispy still reports a current canvas, so napari's GL queries (``get_gl_extensions`` when the
    next Image layer is added) read None: ``tests/_napari/test_editor_canvas.py`` then ``test_workflow.py`` failed
    with "'NoneType' object has no attribute 'decode'" when the workflow opened its scan (issue 19).
    """
    if "qtpy.QtCore" in sys.modules:  # Qt already loaded by an earlier test; nothing to do otherwise
        from qtpy.QtCore import QCoreApplication, QEvent

        if QCoreApplication.instance() is not None:
            QCoreApplication.sendPostedEvents(None, QEvent.Type.DeferredDelete)
            QCoreApplication.processEvents()
    yield
