"""run_batch outlives a server restart: kill -9 the server while a job runs, restart it on the same data root and
port; the batch resumes, resubmits what the restart interrupted, never reruns what had finished, and every output
the summary names equals what the core writes in this process for the session beside it."""

from __future__ import annotations

import csv
import json
import threading
from collections import Counter

import numpy as np
from _servers import ServerProcess, wait_for

from napari_unwind.client import BatchItem, Client
from napari_unwind.datasets import tank_phantom
from napari_unwind.deformation import Deformation
from napari_unwind.io import open_volume, write_volume
from unwind_services._proto.unwind.v1 import common_pb2 as pb

#: A straight export slow enough to be caught running: one slice per chunk (and step).
EXPORT = dict(spacing=1.0, chunks=(1, 512, 512))


def test_run_batch_resumes_after_the_server_is_killed_and_restarted(tmp_path):
    from napari_unwind.warp import straighten

    t = tank_phantom(n_fish=2, seed=1, length=90)
    scan = write_volume(t.volume, tmp_path / "tank.zarr", spacing=t.spacing, unit=t.unit)
    srv = ServerProcess(tmp_path / "data", "--workers", "2")
    out = tmp_path / "out"
    result: dict = {}
    try:
        with Client(srv.address, progress=False, retry_seconds=120) as c, \
                Client(srv.address, progress=False, retry_seconds=120) as spy:
            vid = c.upload(scan).volume_id  # the items name it: the batch uploads nothing
            items = [BatchItem(scan=vid, select=[f.centerline[len(f.centerline) // 2]], name=name,
                               options=dict(head=f.head, tail=f.tail, **EXPORT))
                     for name, f in (("a", t.fish[0]), ("b", t.fish[1]), ("c", t.fish[0]))]

            def batch():
                try:
                    result["rows"] = c.run_batch(items, max_parallel=2, out_dir=out)
                except BaseException as exc:  # noqa: BLE001 - reported below
                    result["error"] = exc

            runner = threading.Thread(target=batch)
            runner.start()

            def finished_and_running():
                jobs = [j for j in spy.jobs() if j.kind == pb.JOB_KIND_PIPELINE]
                done = [j for j in jobs if j.state == pb.JOB_STATE_SUCCEEDED]
                running = [j for j in jobs if j.state == pb.JOB_STATE_RUNNING and j.progress.stage == "write"]
                return (done, running) if done and running else None

            done, running = wait_for(finished_and_running, timeout=300, interval=0.02)
            srv.kill()
            srv.start()  # the same data root and port
            runner.join(timeout=300)
            assert not runner.is_alive() and "error" not in result, result.get("error")
            jobs = spy.jobs()
    finally:
        srv.stop()

    rows = {r["name"]: r for r in result["rows"]}
    with open(out / "summary.csv") as f:
        table = {r["name"]: r for r in csv.DictReader(f)}
    assert set(rows) == set(table) == {"a", "b", "c"}
    assert all(r["state"] == "succeeded" for r in table.values()), table
    pipeline = [j for j in jobs if j.kind == pb.JOB_KIND_PIPELINE]
    # what the kill interrupted was resubmitted, and the summary says so
    interrupted = [j for j in pipeline if j.interrupted]
    assert {j.id for j in interrupted} >= {j.id for j in running}
    for j in interrupted:
        assert j.state == pb.JOB_STATE_FAILED and "interrupted" in j.error.message
        assert j.id in table[j.name]["resubmitted"].split() and table[j.name]["job"] != j.id
    # what had finished was not run again
    runs = Counter(j.name for j in pipeline)
    for j in done:
        assert runs[j.name] == 1 and table[j.name]["job"] == j.id and not table[j.name]["resubmitted"]
    # every output named equals the core's straightening, here, of the session saved beside it
    volume = open_volume(scan)
    for name, r in table.items():
        session = json.loads((out / f"{name}.unwind.json").read_text())
        d = Deformation.from_dict(session["deformation"])
        expected = straighten(volume, d, spacing=EXPORT["spacing"]).data.compute()
        got = open_volume(r["output"])
        assert got.shape == expected.shape
        np.testing.assert_array_equal(got.data.compute(), expected)
