"""Uploads of format "chunks" return once level 0 is stored and checked; the other pyramid levels are built
afterwards in the import pool (ingest.PyramidBuilds): a real server in another process.

The server's pyramid builds wait while the file named by ``UNWIND_TEST_PYRAMID_GATE`` does not exist
(ingest.PYRAMID_GATE), so these tests see a volume whose pyramid is pending for as long as they need, without
timing anything.
"""

from __future__ import annotations

import os
import threading
import time

import grpc
import numpy as np
import pytest
from _servers import ServerProcess, assert_same_store, leftovers, pyramid_pending, stored_volume, wait_for_pyramid

from napari_unwind.client import Client
from napari_unwind.io import as_volume, import_volume
from unwind_services._proto.unwind.v1 import common_pb2 as pb
from unwind_services._proto.unwind.v1 import volume_pb2
from unwind_services.ingest import PYRAMID_GATE

SHAPE = (300, 20, 270)  # level 1 (150, 10, 135) is the segmentation's working level (sides <= 256)


def _gated_server(tmp, gate):
    os.environ[PYRAMID_GATE] = str(gate)
    try:
        return ServerProcess(tmp / "data", "--workers", 1, "--imports", 2)
    finally:
        del os.environ[PYRAMID_GATE]  # a restart (ServerProcess.start) builds at once


@pytest.fixture()
def gated(tmp_path):
    gate = tmp_path / "gate"
    srv = _gated_server(tmp_path, gate)
    yield srv, gate
    gate.touch()
    srv.stop()


def _scan(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 60000, SHAPE).astype(np.uint16)


def _reference(a: np.ndarray, tmp_path):
    return import_volume(as_volume(a, spacing=(3, 2, 1), unit="um"), tmp_path / "ref.zarr")


def test_the_upload_returns_before_the_pyramid_and_its_levels_wait_for_it(gated, tmp_path):
    """Level 0 is listed and downloadable at once; a download of level 1 waits for the build (UNAVAILABLE when the
    client's deadline comes first) and then gets it; the finished store is import_volume's byte for byte."""
    srv, gate = gated
    a = _scan()
    ref = _reference(a, tmp_path)
    with Client(srv.address, progress=False) as c:
        info = c.upload(a, spacing=(3, 2, 1), unit="um", name="later")
        assert info.levels == 1
        store = stored_volume(srv, info.volume_id, complete=False)
        assert pyramid_pending(store)
        assert info.volume_id in [v.volume_id for v in c.volumes()]
        np.testing.assert_array_equal(c.open(info.volume_id).data.compute(), a)

        stub = c.volumes_stub
        with pytest.raises(grpc.RpcError) as err:
            list(stub.Download(volume_pb2.DownloadRequest(volume_id=info.volume_id, level=1), timeout=3,
                               metadata=c._metadata))
        assert err.value.code() == grpc.StatusCode.UNAVAILABLE
        assert err.value.details() == "the volume's pyramid is still being built; retry"

        got: dict = {}
        waiting = threading.Thread(target=lambda: got.update(level1=c.open(info.volume_id, level=1)))
        waiting.start()
        gate.touch()
        waiting.join(120)
        np.testing.assert_array_equal(got["level1"].data.compute(), ref.levels[1].compute())
        wait_for_pyramid(store)
        assert c.info(info.volume_id).levels == len(ref.levels)
    assert_same_store(store, tmp_path / "ref.zarr")
    assert not leftovers(srv)


def test_a_job_on_a_volume_whose_pyramid_is_pending_waits_for_it(gated):
    """A segmentation picks its working level from the pyramid: it must not run on level 0 alone."""
    srv, gate = gated
    with Client(srv.address, progress=False) as c:
        vid = c.upload(_scan(1), name="seg").volume_id
        job = c.segment(vid, features=2, wait=False)
        for _ in range(1200):  # until a worker runs it (the first job waits for the worker's imports)
            if c.job(job.id).state != pb.JOB_STATE_QUEUED:
                break
            time.sleep(0.1)
        assert c.job(job.id).state == pb.JOB_STATE_RUNNING and pyramid_pending(stored_volume(srv, vid, complete=False))
        gate.touch()
        done = c.wait(job.id, progress=False, timeout=300)
        assert c.segmentation(done.result.segmentation_id).level == 1


def test_a_server_killed_during_the_build_builds_the_pyramid_at_its_next_start(gated, tmp_path):
    srv, gate = gated
    a = _scan(2)
    _reference(a, tmp_path)
    with Client(srv.address, progress=False) as c:
        vid = c.upload(a, spacing=(3, 2, 1), unit="um").volume_id
    store = stored_volume(srv, vid, complete=False)
    srv.kill()
    assert pyramid_pending(store)
    srv.start()  # without the gate
    wait_for_pyramid(store)
    assert_same_store(store, tmp_path / "ref.zarr")
    with Client(srv.address, progress=False) as c:
        assert c.info(vid).levels == 2
        np.testing.assert_array_equal(c.open(vid, level=1).data.compute(),
                                      import_volume(as_volume(a), tmp_path / "r.zarr").levels[1].compute())
    assert not leftovers(srv)


def test_a_build_that_fails_is_unavailable_at_once_and_built_again_at_the_next_start(gated, tmp_path):
    """A level-0 chunk removed under the build: the build fails, a download of level 1 is UNAVAILABLE without
    waiting, and the next start builds the pyramid (once the chunk is back)."""
    srv, gate = gated
    a = _scan(3)
    _reference(a, tmp_path)
    with Client(srv.address, progress=False) as c:
        vid = c.upload(a, spacing=(3, 2, 1), unit="um").volume_id
        store = stored_volume(srv, vid, complete=False)
        chunk = store / "0" / "c" / "1" / "0" / "1"
        kept = chunk.read_bytes()
        chunk.unlink()
        gate.touch()
        stub = c.volumes_stub
        with pytest.raises(grpc.RpcError) as err:  # (the server must not wait until the deadline for a failed build)
            list(stub.Download(volume_pb2.DownloadRequest(volume_id=vid, level=1), timeout=60,
                               metadata=c._metadata))
        assert err.value.code() == grpc.StatusCode.UNAVAILABLE
        assert "could not be built" in err.value.details()
        assert pyramid_pending(store)
    chunk.write_bytes(kept)
    srv.restart()
    wait_for_pyramid(store)
    assert_same_store(store, tmp_path / "ref.zarr")
