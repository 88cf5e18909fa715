"""`unwind run` on the real scans of ../shared/data with their masks and the suggested ends, no edit (issue 10).

Each run is a subprocess, as a user types it; the session it writes is read back for the figures. The spine's
curve is compared with the manual centreline (an independent expert annotation); the coverage of both masks is
recomputed from the saved deformation by tests/cage_reference.py's own inverse (independent of napari_unwind.warp).
"""

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
pytestmark = pytest.mark.skipif(not (DATA / "aorta_ct.nrrd").exists(), reason="../shared/data is absent")


def _run(tmp_path, scan, mask):
    out = tmp_path / "straight.tif"
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "napari_unwind.cli", "run", str(DATA / scan), "--mask",
                           str(DATA / mask), "-o", str(out)], capture_output=True, text=True, timeout=300)
    return proc, out, time.perf_counter() - t


def _session(out):
    from napari_unwind.session import load_session

    return load_session(out.with_name(out.stem + ".unwind.json"))


def _coverage(deformation, mask_path):
    """Fraction of the mask's voxels (at the physical positions the mask file gives them) that the saved
    deformation's cage holds unfolded, by the inverse written in tests/cage_reference.py (nothing of warp)."""
    from cage_reference import coverage

    from napari_unwind.io import open_volume

    m = open_volume(mask_path)
    return coverage(deformation, np.asarray(m.data), m.spacing, m.origin)


def test_aorta_runs_without_folds_and_keeps_the_mask(tmp_path):
    proc, out, dt = _run(tmp_path, "aorta_ct.nrrd", "aorta_ct_aorta_mask.nrrd")
    assert proc.returncode == 0, proc.stderr
    assert out.exists() and "Traceback" not in proc.stderr
    assert "cage: min Jacobian" in proc.stdout and "coverage" in proc.stdout
    d = _session(out).deformation
    assert not d.folds()
    assert _coverage(d, DATA / "aorta_ct_aorta_mask.nrrd") >= 0.99
    assert dt < 90  # about 15 s alone; the machine is shared


def test_spine_runs_and_follows_the_manual_centreline(tmp_path):
    proc, out, dt = _run(tmp_path, "spine_t2.nrrd", "spine_t2_cord_mask.nrrd")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count("folds") <= 1
    d = _session(out).deformation
    assert not d.folds()
    manual = np.loadtxt(DATA / "spine_t2_centerline_manual.csv", delimiter=",", skiprows=1)
    c, _ = d.sample(np.linspace(*d.s_range, 2000))  # the padded ends included: the mask runs off the scan
    dist, _ = cKDTree(c).query(d.to_physical(manual))
    assert dist.mean() <= 1.0, dist.mean()
    assert _coverage(d, DATA / "spine_t2_cord_mask.nrrd") >= 0.99
    assert dt < 90
