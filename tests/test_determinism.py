"""Same input, same options, same version: the same bytes (issue 18, item 2).

``unwind run`` twice in separate processes, once with one thread for dask, numba and BLAS and once with two: the
straightened OME-Zarr store (every file) and the session are byte for byte the same when ``SOURCE_DATE_EPOCH``
fixes the timestamps, and the same but for ``created``/``modified`` without it. Reference: the two runs' files,
and the scan and mask unchanged on disk.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess

import pytest

from conftest import UNWIND
from napari_unwind.datasets import fish_phantom
from napari_unwind.io import write_volume


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("determinism")
    ph = fish_phantom(seed=4, curve="s-bend", noise=0.05)
    scan = write_volume(ph.volume, tmp / "scan.nrrd", spacing=ph.spacing)
    mask = write_volume(ph.mask.astype("uint8"), tmp / "mask.nrrd", spacing=ph.spacing)
    return tmp, scan, mask


def _tree(folder):
    """{relative path: sha256} of every file below ``folder``."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _run(scan, mask, out, threads: int, epoch: str | None):
    env = {k: v for k, v in os.environ.items() if k != "SOURCE_DATE_EPOCH"}
    n = str(threads)
    env.update(DASK_NUM_WORKERS=n, OMP_NUM_THREADS=n, OPENBLAS_NUM_THREADS=n, NUMBA_NUM_THREADS=n)
    if epoch is not None:
        env["SOURCE_DATE_EPOCH"] = epoch
    r = subprocess.run([str(UNWIND), "run", str(scan), "--mask", str(mask), "-o", str(out), "-q"], env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return out, out.with_name(out.name.removesuffix(".zarr") + ".unwind.json")


def test_two_runs_with_one_and_two_threads_write_the_same_bytes(inputs):
    tmp, scan, mask = inputs
    before = _tree(tmp)
    a, sa = _run(scan, mask, tmp / "one.zarr", 1, "1700000000")
    b, sb = _run(scan, mask, tmp / "two.zarr", 2, "1700000000")
    ta, tb = _tree(a), _tree(b)
    assert len(ta) > 3 and ta == tb
    assert sa.read_bytes() == sb.read_bytes()
    assert json.loads(sa.read_text())["created"] == "2023-11-14T22:13:20.000Z"
    assert {k: v for k, v in _tree(tmp).items() if k in before} == before  # the inputs are untouched


def test_without_source_date_epoch_only_the_timestamps_differ(inputs):
    tmp, scan, mask = inputs
    _, sa = _run(scan, mask, tmp / "c.zarr", 1, None)
    _, sb = _run(scan, mask, tmp / "d.zarr", 2, None)
    da, db = json.loads(sa.read_text()), json.loads(sb.read_text())
    for d in (da, db):
        d.pop("created"), d.pop("modified")
    assert json.dumps(da, sort_keys=True) == json.dumps(db, sort_keys=True)


def test_a_bad_source_date_epoch_is_one_clear_line(inputs, tmp_path):
    tmp, scan, mask = inputs
    env = dict(os.environ, SOURCE_DATE_EPOCH="yesterday")
    r = subprocess.run([str(UNWIND), "run", str(scan), "--mask", str(mask), "-o", str(tmp_path / "x.zarr"), "-q"],
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert "SOURCE_DATE_EPOCH must be whole seconds since 1970 (UTC), got 'yesterday'" in r.stderr
