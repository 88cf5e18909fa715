"""Faults on a real server: cancel, timeouts and deadlines, kill -9 mid-export, graceful restart, reconnects."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from _servers import ServerProcess, healthy, wait_for

from napari_unwind.client import Client, RemoteError
from napari_unwind.datasets import tank_phantom
from unwind_services._proto.unwind.v1 import common_pb2 as pb

#: A straight export slow enough to catch in the middle: 2x finer than the scan, one slice per chunk (and step).
SLOW = dict(spacing=0.5, chunks=(1, 512, 512), output_name="slow.zarr")


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """A server, a scan, and a session made by a skeleton job (given ends, so it is quick)."""
    tmp = tmp_path_factory.mktemp("faults")
    t = tank_phantom(n_fish=2, seed=1, length=90)
    fish = t.fish[0]
    srv = ServerProcess(tmp / "data", "--workers", "2", "--drain", "30")
    with Client(srv.address, progress=False) as c:
        vid = c.upload(t.volume, spacing=t.spacing, unit=t.unit, name="tank").volume_id
        mid = c.upload(fish.mask.astype(np.uint8), spacing=t.spacing, unit=t.unit, name="mask").volume_id
        sk = c.skeleton(mid, volume_id=vid, head=fish.head, tail=fish.tail)
    yield srv, vid, sk.result.session_id
    srv.stop()


def _user_dir(srv):
    return srv.data_root / ".unwind" / "users" / "local"


def _temp_outputs(srv, job_id=None):
    base = _user_dir(srv) / job_id if job_id else _user_dir(srv)
    return [p for p in base.rglob("*") if "unwind-tmp" in p.name] if base.exists() else []


def _start_slow(c, vid, sid):
    job = c.straighten(vid, sid, wait=False, **SLOW)
    wait_for(lambda: _temp_outputs_of(c, job.id), timeout=60)
    return job


def _temp_outputs_of(c, job_id):
    srv = c._srv  # noqa: SLF001 - set by the fixture below
    return _temp_outputs(srv, job_id)


@pytest.fixture
def client(env):
    srv, vid, sid = env
    if srv.proc.poll() is not None:
        srv.start()
    c = Client(srv.address, progress=False, retry_seconds=90)
    c._srv = srv
    yield c
    c.close()


def test_cancel_stops_between_steps_and_removes_the_temporary_output(env, client):
    srv, vid, sid = env
    job = _start_slow(client, vid, sid)
    assert client.job(job.id).state == pb.JOB_STATE_RUNNING
    client.cancel(job.id)
    done = wait_for(lambda: (j := client.job(job.id)).state not in (pb.JOB_STATE_RUNNING,) and j, timeout=30)
    assert done.state == pb.JOB_STATE_CANCELLED and done.error.code == "CANCELLED"
    assert _temp_outputs(srv) == [] and not (_user_dir(srv) / job.id).exists()
    with pytest.raises(RemoteError) as info:
        client.wait(job.id)
    assert info.value.code == "CANCELLED"
    assert healthy(srv.address)


def test_a_job_past_its_timeout_fails_with_deadline_exceeded(env, client):
    srv, vid, sid = env
    from unwind_services._proto.unwind.v1 import jobs_pb2, warp_pb2

    request = jobs_pb2.SubmitRequest(straighten=warp_pb2.StraightenRequest(
        volume_id=vid, session_id=sid, options=client._export_options(**SLOW)))
    with pytest.raises(RemoteError) as info:
        client.submit(request, timeout_seconds=0.3)
    job = info.value.job
    assert info.value.code == "DEADLINE_EXCEEDED" and job.state == pb.JOB_STATE_FAILED
    assert "timeout" in job.error.message
    assert _temp_outputs(srv) == []


def test_a_call_past_its_deadline_is_deadline_exceeded_and_the_server_goes_on(env, client):
    srv, vid, sid = env
    job = _start_slow(client, vid, sid)
    with pytest.raises(RemoteError) as info:
        client.wait(job.id, timeout=0.3)
    assert info.value.code == "DEADLINE_EXCEEDED"
    assert healthy(srv.address)
    client.cancel(job.id)


def test_kill_9_mid_export_leaves_no_whole_output_and_the_job_interrupted(env, client):
    srv, vid, sid = env
    job = _start_slow(client, vid, sid)
    assert _temp_outputs(srv, job.id)  # mid-export: the partial output is there, under a temporary name
    srv.kill()
    # whether the worker, ending after the server, removes its temporary in time or the next start does (both seen),
    # no whole output is ever there
    assert not (_user_dir(srv) / job.id / "slow.zarr").exists()
    srv.start()
    after = client.job(job.id)
    assert after.state == pb.JOB_STATE_FAILED and after.interrupted and after.error.code == "UNAVAILABLE"
    assert "interrupted" in after.error.message
    assert _temp_outputs(srv) == [] and not (_user_dir(srv) / job.id / "slow.zarr").exists()
    again = client.resubmit(job.id, wait=True)
    assert again.state == pb.JOB_STATE_SUCCEEDED and again.id != job.id
    assert client.info(again.result.volume_id).name == "slow.zarr"


def test_sigterm_drains_the_running_job_and_the_client_resumes_watching(env, client):
    srv, vid, sid = env
    job = _start_slow(client, vid, sid)
    seen: dict = {}

    def follow():
        try:
            seen["job"] = client.wait(job.id)
        except Exception as exc:  # noqa: BLE001 - reported below
            seen["error"] = exc

    follower = threading.Thread(target=follow)
    follower.start()
    wait_for(lambda: client.job(job.id).progress.seq > 0, timeout=30)
    assert srv.terminate(timeout=120) == 0  # graceful: the running job finishes within --drain
    srv.start()
    follower.join(timeout=120)
    assert "error" not in seen, seen.get("error")
    assert seen["job"].state == pb.JOB_STATE_SUCCEEDED and not seen["job"].interrupted
    assert _temp_outputs(srv) == []
