"""The average on a dask.distributed cluster (issue 24 item 3): the same bytes as on this process's threads, and
the same whatever the specimens' storage chunks.

The specimens are files (the workers read them), a small seeded family of tests/test_average.py; the cluster is
in-process (one worker, no separate processes) so the test stays quick."""
from __future__ import annotations

import numpy as np
import pytest
from test_average import member

from napari_unwind.average import average
from napari_unwind.io import write_volume

distributed = pytest.importorskip("distributed")


def test_the_average_on_a_cluster_equals_the_local_one_exactly(tmp_path):
    import test_average as fam

    rng = np.random.default_rng(11)
    old = fam.NS0, fam.NY0
    fam.NS0, fam.NY0 = 60, 21
    try:
        members = [member(z, th, rng.uniform(-2, 2, 2), rng.uniform(0.5, 2), rng.uniform(0, 200), rng)
                   for z, th in [(0.9, -20.0), (1.0, 0.0), (1.1, 15.0), (0.95, 30.0)]]
        paths = [str(write_volume(m, tmp_path / f"fish{i}.ome.zarr", chunks=(16, 11, 11)))
                 for i, m in enumerate(members)]
    finally:
        fam.NS0, fam.NY0 = old
    local = average(paths, chunk=8)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cl:
        remote = average(paths, chunk=8, scheduler=cl.scheduler_address)
        ran = set(cl.scheduler.task_prefixes)
    assert {"block_stats", "average_chunk"} <= ran, ran                   # the cluster did the work
    for what in ("mean", "median", "std", "roll", "shift", "scale", "rms", "correlation"):
        a, b = getattr(local, what), getattr(remote, what)
        assert a.dtype == b.dtype and np.array_equal(a, b), what
    # the same voxels stored in other chunks (here: in memory, one block) give the same bytes
    in_memory = average(members, chunk=8)
    assert np.array_equal(in_memory.mean, local.mean) and np.array_equal(in_memory.median, local.median)
    assert np.array_equal(in_memory.correlation, local.correlation)
    # and the threads' result is the synchronous one (one task at a time, in order)
    sync = average(paths, chunk=8, scheduler="synchronous")
    assert np.array_equal(sync.mean, local.mean) and np.array_equal(sync.median, local.median)
