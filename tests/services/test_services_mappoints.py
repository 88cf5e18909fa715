"""MapPoints on a real server (issue 22, item 2): many points stream, the unary call is capped, and the server's
work for a call stops when the client's deadline passes.

References: the core's ``map_points`` in this process on the same session (the same bytes), and the server's CPU
time read from /proc (independent of the code under test).
"""

from __future__ import annotations

import json
import os
import time
import warnings

import grpc
import numpy as np
import pytest
from _servers import ServerProcess

from napari_unwind.client import MAP_BATCH, Client, RemoteError
from napari_unwind.datasets import tank_phantom
from napari_unwind.session import Session
from napari_unwind.warp import map_points
from unwind_services._proto.unwind.v1 import warp_pb2, warp_pb2_grpc
from unwind_services.servicers import MAX_MAP_POINTS


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mappoints")
    t = tank_phantom(n_fish=2, seed=1, length=90)
    fish = t.fish[0]
    srv = ServerProcess(tmp / "data", "--workers", "1")
    c = Client(srv.address, progress=False)
    mid = c.upload(fish.mask.astype(np.uint8), spacing=t.spacing, unit=t.unit, name="mask").volume_id
    job = c.skeleton(mid, head=fish.head, tail=fish.tail)
    session = Session.from_dict(json.loads(job.result.session_json))
    yield srv, c, job.result.session_id, session.deformation, t.volume.shape
    c.close()
    srv.stop()


def _points(shape, n, seed=0):
    """Points over the scan's box: some inside the cage, most outside (NaN)."""
    return np.random.default_rng(seed).uniform(0, np.asarray(shape) - 1, size=(n, 3))


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process and its threads, from /proc."""
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_many_points_stream_and_match_the_core(env):
    srv, c, sid, deformation, shape = env
    pts = _points(shape, 2 * MAP_BATCH + 123)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = map_points(pts, deformation)
    got = c.map_points(sid, pts)  # three messages of MapPointsStream
    assert got.shape == pts.shape
    assert np.array_equal(got, want, equal_nan=True)
    assert 0.01 < np.isfinite(got[:, 0]).mean() < 0.99  # both kinds of point were carried
    back = c.map_points(sid, got[np.isfinite(got[:, 0])][:1000], to="scan")  # a small one: the unary call
    np.testing.assert_allclose(back, pts[np.isfinite(got[:, 0])][:1000], atol=1e-6)


def test_the_unary_call_is_capped_and_names_the_stream(env):
    srv, c, sid, _, shape = env
    pts = _points(shape, MAX_MAP_POINTS + 1)
    with grpc.insecure_channel(srv.address) as ch:
        stub = warp_pb2_grpc.WarpServiceStub(ch)
        with pytest.raises(grpc.RpcError) as info:
            stub.MapPoints(warp_pb2.MapPointsRequest(session_id=sid, coords=pts.ravel().tolist()), timeout=60)
    assert info.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "MapPointsStream" in info.value.details() and "\n" not in info.value.details()


def test_a_stream_of_points_all_outside_is_invalid_argument(env):
    _, c, sid, _, shape = env
    far = np.full((MAP_BATCH + 1, 3), -1000.0)
    with pytest.raises(RemoteError) as info:
        c.map_points(sid, far)
    assert info.value.code == "INVALID_ARGUMENT" and "outside the cage" in str(info.value)


def _cpu_in(srv, start, seconds):
    """CPU seconds the server spends from ``start`` (monotonic) for ``seconds``."""
    time.sleep(max(0.0, start - time.monotonic()))
    before = _cpu_seconds(srv.proc.pid)
    time.sleep(seconds)
    return _cpu_seconds(srv.proc.pid) - before


def _settled_cpu(srv, quiet=0.05, every=0.5, limit=60.0):
    """The server's CPU seconds once it has gone quiet (under ``quiet`` s of CPU in ``every`` s), or after ``limit``."""
    end = time.monotonic() + limit
    last = _cpu_seconds(srv.proc.pid)
    while time.monotonic() < end:
        time.sleep(every)
        now = _cpu_seconds(srv.proc.pid)
        if now - last < quiet:
            return now
        last = now
    return last


def test_the_server_stops_a_unary_call_when_its_deadline_passes(env):
    srv, c, sid, _, shape = env
    pts = _points(shape, MAX_MAP_POINTS, seed=1)  # the most a call carries: its work is short, but not nothing
    request = warp_pb2.MapPointsRequest(session_id=sid, coords=pts.ravel().tolist())
    calls = 12
    with grpc.insecure_channel(srv.address) as ch:
        stub = warp_pb2_grpc.WarpServiceStub(ch)
        stub.MapPoints(request, timeout=60)  # warm
        before = _settled_cpu(srv)
        stub.MapPoints(request, timeout=60)
        whole = _settled_cpu(srv) - before  # the server's CPU for one whole call: the baseline of this run
        codes = []
        for _ in range(calls):  # one after another, each given up by the client after 0.05 s
            with pytest.raises(grpc.RpcError) as info:
                stub.MapPoints(request, timeout=0.05)
            codes.append(info.value.code())
        spent = _settled_cpu(srv) - before - whole
    assert codes == [grpc.StatusCode.DEADLINE_EXCEEDED] * calls
    # CPU time, not the clock: a loaded machine stretches when the work is done, not how much of it there is. A
    # server that worked on spends ``calls`` x ``whole``; one that stops spends each call's check interval (0.05 s)
    # and its batch of points at most.
    assert calls * whole > 2.0, f"the work ({calls} x {whole:.2f} s of CPU) is too short to tell"
    assert spent < 0.4 * calls * whole, (f"the server spent {spent:.2f} s of CPU on {calls} calls given up after "
                                         f"0.05 s; a whole call takes {whole:.2f} s")


def test_the_server_stops_a_stream_when_its_deadline_passes(env):
    srv, c, sid, _, shape = env
    pts = _points(shape, 40 * MAP_BATCH, seed=2)  # 2 million points: tens of seconds
    t0 = time.monotonic() + 1.0
    with pytest.raises(RemoteError) as info:
        c.map_points(sid, pts, timeout=1.0)
    assert info.value.code == "DEADLINE_EXCEEDED"
    spent = _cpu_in(srv, t0 + 0.5, 2.0)
    assert spent < 0.2, f"the server spent {spent:.2f} s of CPU in the 2 s after the deadline"


def test_a_server_whose_message_limit_is_below_a_batch_gets_smaller_batches(tmp_path):
    """A batch of MAP_BATCH points is 1.2 MB; a server whose message limit is 512 KiB refuses it through gRPC,
    which names the limit: the client maps the points in batches within it, and they match the core's."""
    from unwind_services.catalog import Limits
    from unwind_services.server import ServerConfig, UnwindServer

    srv = UnwindServer(ServerConfig(data_root=tmp_path / "data", port=0, workers=1, scheduler="threads",
                                    limits=Limits(max_message_bytes=512 * 2**10)))
    srv.start()
    try:
        t = tank_phantom(n_fish=2, seed=1, length=90)
        fish = t.fish[0]
        with Client(srv.address, progress=False) as low:
            mid = low.upload(fish.mask.astype(np.uint8), spacing=t.spacing, unit=t.unit, name="mask").volume_id
            job = low.skeleton(mid, head=fish.head, tail=fish.tail)
            here = Session.from_dict(json.loads(job.result.session_json)).deformation
            for n in (30_000, MAP_BATCH + 7):  # over the limit in one call; and in a stream
                pts = _points(t.volume.shape, n, seed=n)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    want = map_points(pts, here)
                got = low.map_points(job.result.session_id, pts)
                assert np.array_equal(got, want, equal_nan=True)
    finally:
        srv.stop(0)
