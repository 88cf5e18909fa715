"""Where a job's chunked dask work runs: the server's own LocalCluster (the default), or an external cluster.

References: the core run in this process on dask's threads (the cluster must change no voxel), and the
cluster's own record of the tasks it ran (its task stream), so "it ran on the cluster" is observed, not assumed.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from types import SimpleNamespace

import dask
import numpy as np
import psutil
import pytest
from _servers import ROOT, ServerProcess, healthy, wait_for

from napari_unwind.client import Client
from napari_unwind.datasets import tank_phantom
from napari_unwind.io import as_volume
from unwind_services._proto.unwind.v1 import common_pb2 as pb


@pytest.fixture(scope="module")
def tank():
    t = tank_phantom(n_fish=2, seed=1, length=90)
    return t, t.fish[0]


def _prepare(c, t, fish):
    """Upload the scan and the fish's mask; a session from a skeleton job with given ends (quick)."""
    vid = c.upload(t.volume, spacing=t.spacing, unit=t.unit, name="tank").volume_id
    mid = c.upload(fish.mask.astype(np.uint8), spacing=t.spacing, unit=t.unit, name="mask").volume_id
    sk = c.skeleton(mid, volume_id=vid, head=fish.head, tail=fish.tail)
    return vid, mid, sk


def _tasks_since(dc, start: float) -> list[str]:
    """Names of the tasks the cluster ran since ``start`` (the scheduler's task stream)."""
    return [r["key"] if isinstance(r["key"], str) else str(r["key"]) for r in dc.get_task_stream(start=start)]


def _descendants(pid: int) -> list[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def _all_gone(procs: list[psutil.Process]) -> bool:
    return not [p for p in procs if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]


def _scheduler_address(log_path) -> str:
    return wait_for(lambda: (m := re.search(r"dask LocalCluster at (tcp://[\d.]+:\d+)", log_path.read_text()))
                    and m.group(1), timeout=30)


# ------------------------------------------------------------------------------------------------------------------
# the default: a LocalCluster in the server
# ------------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def default_server(tmp_path_factory, tank):
    """``unwind serve`` without --scheduler, a scan, a mask, a session; a dask client of its LocalCluster."""
    from distributed import Client as DaskClient

    t, fish = tank
    srv = ServerProcess(tmp_path_factory.mktemp("default") / "data", "--workers", "1", scheduler=None)
    address = _scheduler_address(srv.log)
    with DaskClient(address, timeout=30, set_as_default=False) as dc, Client(srv.address, progress=False) as c:
        dc.get_task_stream()  # the scheduler records every task from now on
        yield srv, dc, c, _prepare(c, t, fish)
    srv.stop()


def test_the_default_serve_starts_a_local_cluster_in_a_child_process(default_server):
    srv, dc, c, _ = default_server
    workers = dc.scheduler_info()["workers"]
    assert len(workers) == 1  # one worker process, a thread per core
    assert [w["nthreads"] for w in workers.values()] == [os.cpu_count()]
    pids = set(dc.run(os.getpid).values())
    assert pids <= {p.pid for p in _descendants(srv.proc.pid)} and os.getpid() not in pids


def test_straighten_runs_on_the_local_cluster_and_writes_the_threads_result(default_server, tank):
    from napari_unwind.warp import straighten

    srv, dc, c, (vid, mid, sk) = default_server
    t, fish = tank
    start = time.time()
    st = c.straighten(vid, sk.result.session_id, output_name="fish.zarr", spacing=0.5)
    ran = _tasks_since(dc, start)
    assert any("straighten" in k for k in ran), ran[:20]  # the export's blocks ran on the cluster
    d = Client.session(sk).deformation
    with dask.config.set(scheduler="threads"):
        expected = straighten(as_volume(t.volume, spacing=t.spacing, unit=t.unit), d, spacing=0.5).data.compute()
    np.testing.assert_array_equal(c.open(st.result.volume_id).data.compute(), expected)


def test_select_refines_on_the_local_cluster_and_writes_the_threads_result(default_server, tank):
    from napari_unwind.segmentation import refine_mask, segment, select

    srv, dc, c, (vid, mid, sk) = default_server
    t, fish = tank
    seg = c.segment(vid, features=5).result.segmentation_id
    click = fish.centerline[len(fish.centerline) // 2]
    start = time.time()
    sel = c.select(seg, seeds=[click], output_name="mask.zarr")
    ran = _tasks_since(dc, start)
    # refine_mask_iter writes refine_mask(...).astype(uint8): dask fuses the refine blocks into that last layer
    assert any(k.startswith("astype-") for k in ran), sorted({k.split("-")[0] for k in ran})
    scan = as_volume(t.volume, spacing=t.spacing, unit=t.unit)
    with dask.config.set(scheduler="threads"):
        features = segment(scan, features=5)
        local = refine_mask(scan, select(features, seeds=[click]), features=features).compute()
    np.testing.assert_array_equal(c.open(sel.result.volume_id).data.compute().astype(bool), local)


def test_sigterm_drains_the_job_on_the_cluster_then_stops_the_cluster(default_server):
    """The last test of this server: SIGTERM while an export runs on the cluster. The job is drained (or, past
    --drain, interrupted), never left running, and then the cluster's processes are gone."""
    from unwind_services.paths import DataRoot
    from unwind_services.store import Store

    srv, dc, c, (vid, mid, sk) = default_server
    procs = _descendants(srv.proc.pid)
    job = c.straighten(vid, sk.result.session_id, wait=False, spacing=0.5, chunks=(1, 512, 512),
                       output_name="slow.zarr")
    wait_for(lambda: c.job(job.id).progress.stage == "write", timeout=60, interval=0.02)
    assert srv.terminate(timeout=60) == 0
    assert wait_for(lambda: _all_gone(procs), timeout=30), [p.cmdline() for p in procs if p.is_running()]
    store = Store(DataRoot(srv.data_root).database)
    try:
        row = store.get_job("local", job.id)
    finally:
        store.close()
    assert row.state == pb.JOB_STATE_SUCCEEDED or (row.state == pb.JOB_STATE_FAILED and row.interrupted), row


def test_kill_9_of_the_default_server_leaves_no_cluster_process(tmp_path):
    srv = ServerProcess(tmp_path / "data", scheduler=None)
    try:
        _scheduler_address(srv.log)
        procs = wait_for(lambda: len(p := _descendants(srv.proc.pid)) >= 2 and p, timeout=30)
        srv.kill()
        assert wait_for(lambda: _all_gone(procs), timeout=30), [p.cmdline() for p in procs if p.is_running()]
    finally:
        srv.stop()


# ------------------------------------------------------------------------------------------------------------------
# an external cluster (the processes deploy/local.sh starts)
# ------------------------------------------------------------------------------------------------------------------
class DaskProcesses:
    """A dask scheduler and workers as separate processes (``python -m distributed.cli...``, as deploy/local.sh)."""

    def __init__(self, tmp, n_workers: int, env: dict | None = None):
        self.tmp, self.env = tmp, {**os.environ, **(env or {})}
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs = {}
        self._start("scheduler", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
                    "--no-dashboard")
        self.address = wait_for(lambda: (m := re.search(r"Scheduler at:\s+(tcp://[\d.]+:\d+)",
                                                        self.logs["scheduler"].read_text())) and m.group(1),
                                timeout=60)
        self.n_workers = n_workers
        for i in range(n_workers):
            self._start(f"worker-{i}", "distributed.cli.dask_worker", self.address, "--host", "127.0.0.1",
                        "--nthreads", "1", "--no-nanny", "--no-dashboard", "--name", f"worker-{i}")

    def wait_for_workers(self):
        for i in range(self.n_workers):
            wait_for(lambda i=i: "Registered to" in self.logs[f"worker-{i}"].read_text(), timeout=60)

    def _start(self, name, module, *args):
        self.logs[name] = self.tmp / f"{name}.log"
        with open(self.logs[name], "w") as log:
            self.procs[name] = subprocess.Popen([sys.executable, "-m", module, *args], stdout=log, stderr=log,
                                                cwd=ROOT, env=self.env)

    def pid_of(self, name: str) -> int:
        return self.procs[name].pid

    def stop(self):
        for p in self.procs.values():
            if p.poll() is None:
                p.terminate()
        for p in self.procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_a_worker_killed_mid_export_fails_the_job_clearly_and_leaves_nothing_that_looks_whole(tmp_path, tank):
    """allowed-failures 0: the first worker death fails the task (KilledWorker) instead of retrying it, so the job
    must fail, say so, and keep nothing; the server goes on. (With dask's default allowed-failures the export goes
    on on the other worker: tests/services/test_services_deploy.py.)"""
    from distributed import Client as DaskClient

    t, fish = tank
    dask = DaskProcesses(tmp_path, 2, env={"DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "0"})
    srv = None
    try:
        srv = ServerProcess(tmp_path / "data", "--workers", "1", scheduler=dask.address)  # while workers start
        dask.wait_for_workers()
        with DaskClient(dask.address, timeout=30, set_as_default=False) as dc, Client(srv.address, progress=False) as c:
            vid, mid, sk = _prepare(c, t, fish)
            slow = dict(spacing=0.5, chunks=(1, 512, 512), output_name="slow.zarr")
            job = c.straighten(vid, sk.result.session_id, wait=False, **slow)
            busy = wait_for(lambda: [a for a, tasks in dc.processing().items() if tasks], timeout=60, interval=0.005)
            name = dc.scheduler_info()["workers"][busy[0]]["name"]
            os.kill(dask.pid_of(name), signal.SIGKILL)
            done = c.wait(job.id, timeout=60, check=False)
            assert done.state == pb.JOB_STATE_FAILED and done.error.code == "UNAVAILABLE", done
            assert "lost this work" in done.error.message and "KilledWorker" in done.error.message
            assert "Traceback" not in done.error.message
            user = srv.data_root / ".unwind" / "users" / "local"
            assert not (user / job.id).exists() and not [p for p in user.rglob("*") if "unwind-tmp" in p.name]
            assert healthy(srv.address)
    finally:
        if srv is not None:
            srv.stop()
        dask.stop()


# ------------------------------------------------------------------------------------------------------------------
# use_scheduler itself (a LocalCluster of threads in this process: quick)
# ------------------------------------------------------------------------------------------------------------------
def test_use_scheduler_reuses_an_enclosing_connection_and_names_lost_work():
    import dask.array as da
    from distributed import KilledWorker, LocalCluster

    from napari_unwind.scheduler import SchedulerError, use_scheduler

    x = da.arange(1000, chunks=100)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        address = cluster.scheduler_address

        def clients() -> int:  # connected clients besides the scheduler's own
            return len([c for c in cluster.scheduler.clients if not c.startswith("fire-and-forget")])

        with use_scheduler(address):
            assert clients() == 1
            with use_scheduler(address):  # an export inside a job: no second connection
                assert clients() == 1 and int(x.sum().compute()) == 499500
            assert clients() == 1 and int(x.sum().compute()) == 499500  # the inner exit kept it open
        wait_for(lambda: clients() == 0, timeout=10)
        with pytest.raises(SchedulerError, match=r"lost this work \(KilledWorker: .*\).*Run it again"):
            with use_scheduler(address), use_scheduler(address):
                raise KilledWorker("straighten-abc", SimpleNamespace(address="tcp://127.0.0.1:1"), 0)
        wait_for(lambda: clients() == 0, timeout=10)


def test_serve_refuses_a_scheduler_it_cannot_use(tmp_path):
    cmd = [sys.executable, "-m", "napari_unwind.cli", "serve", "--data-root", str(tmp_path / "d"), "--port", "0"]
    r = subprocess.run([*cmd, "--scheduler", "nonsense"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 1 and "unwind: error: --scheduler must be 'threads' or a dask scheduler address" in r.stderr
    assert "Traceback" not in r.stderr
