"""deploy/local.sh: the compose topology as processes (server + dask scheduler + two workers); kill -9 a worker."""

from __future__ import annotations

import os
import re
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
from _servers import ROOT, wait_for

from napari_unwind.client import Client
from napari_unwind.datasets import tank_phantom
from napari_unwind.io import as_volume
from unwind_services._proto.unwind.v1 import common_pb2 as pb

LOCAL = ROOT / "deploy" / "local.sh"


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    root = tmp_path_factory.mktemp("local_sh") / "data"
    env = {**os.environ, "UNWIND_PORT": "0", "DASK_PORT": "0"}
    r = subprocess.run(["bash", str(LOCAL), "start", str(root)], capture_output=True, text=True, env=env,
                       timeout=300)
    if r.returncode != 0:
        subprocess.run(["bash", str(LOCAL), "stop", str(root)], timeout=120)
        raise RuntimeError(f"local.sh start failed: {r.stdout}\n{r.stderr}")
    address = re.search(r"^server (\S+)$", r.stdout, re.M).group(1)
    yield root, address
    subprocess.run(["bash", str(LOCAL), "stop", str(root)], timeout=120, check=True)
    status = subprocess.run(["bash", str(LOCAL), "status", str(root)], capture_output=True, text=True).stdout
    assert "running" not in status


@pytest.mark.slow
def test_an_export_survives_kill_9_of_a_worker(cluster):
    from napari_unwind.warp import straighten

    root, address = cluster
    t = tank_phantom(n_fish=2, seed=1, length=90)
    fish = t.fish[0]
    with Client(address, progress=False) as c:
        assert c.health() == "SERVING"
        vid = c.upload(t.volume, spacing=t.spacing, unit=t.unit, name="tank").volume_id
        mid = c.upload(fish.mask.astype(np.uint8), spacing=t.spacing, unit=t.unit, name="mask").volume_id
        sk = c.skeleton(mid, volume_id=vid, head=fish.head, tail=fish.tail)
        job = c.straighten(vid, sk.result.session_id, wait=False, spacing=0.5, chunks=(2, 512, 512),
                           output_name="fish0.zarr")
        # kill -9 a worker while it holds tasks of this export
        from distributed import Client as DaskClient

        sched = (root / ".local-run" / "scheduler.address").read_text().strip()
        with DaskClient(sched, timeout=30, set_as_default=False) as dc:
            busy = wait_for(lambda: [a for a, tasks in dc.processing().items() if tasks], timeout=120, interval=0.01)
            name = dc.scheduler_info()["workers"][busy[0]]["name"]
            os.kill(int(Path(root / ".local-run" / f"{name}.pid").read_text()), signal.SIGKILL)
            wait_for(lambda: busy[0] not in dc.scheduler_info()["workers"], timeout=60)
        done = c.wait(job.id, timeout=300)
        assert done.state == pb.JOB_STATE_SUCCEEDED
        # the work went on on the other worker: the output is whole and what the core computes here
        d = Client.session(sk).deformation
        expected = straighten(as_volume(t.volume, spacing=t.spacing, unit=t.unit), d, spacing=0.5).data.compute()
        np.testing.assert_array_equal(c.open(done.result.volume_id).data.compute(), expected)
