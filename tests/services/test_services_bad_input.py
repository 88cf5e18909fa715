"""Bad input against a real server in another process: each gets its status code, and the server keeps serving."""

from __future__ import annotations

import os
from datetime import UTC, datetime, timedelta

import grpc
import numpy as np
import pytest
from _servers import ServerProcess, healthy, raw_unary, status_of, wait_for

from napari_unwind.client import Client, RemoteError
from napari_unwind.io import open_volume, write_volume
from unwind_services._proto.unwind.v1 import common_pb2 as pb
from unwind_services._proto.unwind.v1 import (
    jobs_pb2,
    jobs_pb2_grpc,
    segmentation_pb2,
    volume_pb2,
    volume_pb2_grpc,
    warp_pb2,
    warp_pb2_grpc,
)
from unwind_services.auth import add_token, hash_token

C = grpc.StatusCode
MAX_MESSAGE = 1024 * 1024


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bad_input")
    data = tmp / "data"
    (data / "scans").mkdir(parents=True)
    rng = np.random.default_rng(0)
    write_volume(rng.integers(0, 1000, (12, 10, 8), dtype=np.uint16), data / "scans" / "small.tif",
                 spacing=(2, 1, 1), unit="um")
    (tmp / "outside").mkdir()
    write_volume(np.zeros((4, 4, 4), np.uint8), tmp / "outside" / "secret.tif")
    os.symlink(tmp / "outside", data / "scans" / "escape")
    tokens = tmp / "tokens"
    alice, bob = add_token(tokens, "alice"), add_token(tokens, "bob")
    past = (datetime.now(UTC) - timedelta(hours=1)).strftime("%Y-%m-%dT%H:%M:%SZ")
    with open(tokens, "a") as f:
        f.write(f"carol {hash_token('expired-token')} expires={past}\n")
    srv = ServerProcess(data, "--tokens", tokens, "--max-message-bytes", MAX_MESSAGE, "--max-voxels", 100_000,
                        "--max-jobs-per-user", 1, "--workers", 1)
    yield srv, {"alice": alice, "bob": bob}
    srv.stop()


@pytest.fixture(autouse=True)
def still_serving(server):
    yield
    srv, tokens = server
    assert srv.proc.poll() is None, "the server died"
    assert healthy(srv.address)
    with Client(srv.address, token=tokens["alice"], progress=False) as c:
        c.volumes()


def md(token):
    return (("authorization", f"Bearer {token}"),)


def stubs(address):
    ch = grpc.insecure_channel(address)
    return (ch, volume_pb2_grpc.VolumeServiceStub(ch), jobs_pb2_grpc.JobServiceStub(ch),
            warp_pb2_grpc.WarpServiceStub(ch))


def header(shape=(4, 5, 6), dtype=pb.DTYPE_UINT16, name="x"):
    return volume_pb2.UploadRequest(header=volume_pb2.UploadHeader(name=name, shape=list(shape), dtype=dtype,
                                                                   spacing=[1, 1, 1], unit="um"))


def chunk(n):
    return volume_pb2.UploadRequest(chunk=b"\0" * n)


# ------------------------------------------------------------------------------------------------------------------
def test_missing_unknown_and_expired_tokens_are_unauthenticated(server):
    srv, tokens = server
    ch, vol, jobs, _ = stubs(srv.address)
    with ch:
        for metadata in ((), md("not-a-token"), md("expired-token"), (("authorization", "Basic abc"),)):
            assert status_of(vol.List, volume_pb2.ListVolumesRequest(), metadata=metadata, timeout=10) \
                == C.UNAUTHENTICATED
        with pytest.raises(grpc.RpcError) as info:
            jobs.List(jobs_pb2.ListJobsRequest(), metadata=md("expired-token"), timeout=10)
        assert "expired" in info.value.details() and "carol" in info.value.details()
        assert status_of(vol.List, volume_pb2.ListVolumesRequest(), metadata=md(tokens["bob"]), timeout=10) is None
    assert healthy(srv.address)  # health needs no token


def test_malformed_messages_are_invalid_argument(server):
    srv, tokens = server
    for method in ("/unwind.v1.VolumeService/Info", "/unwind.v1.JobService/Submit", "/unwind.v1.WarpService/MapPoints"):
        assert status_of(raw_unary, srv.address, method, b"\x0a\xff\xff\xff\x0f", md(tokens["alice"])) \
            == C.INVALID_ARGUMENT


def test_an_oversized_message_is_resource_exhausted(server):
    srv, tokens = server
    ch, vol, _, _ = stubs(srv.address)
    with ch:
        # a header for enough voxels, then one chunk over the message limit
        code = status_of(vol.Upload, iter([header((40, 40, 40)), chunk(MAX_MESSAGE + 1024)]),
                         metadata=md(tokens["alice"]), timeout=20)
        assert code == C.RESOURCE_EXHAUSTED


@pytest.mark.parametrize("messages, code, words", [
    ([header(), chunk(100)], C.INVALID_ARGUMENT, "promises 240 bytes"),
    ([header(), chunk(200), chunk(100)], C.INVALID_ARGUMENT, "more bytes"),
    ([chunk(240)], C.INVALID_ARGUMENT, "starts with a header"),
    ([], C.INVALID_ARGUMENT, "starts with a header"),
    ([header(), chunk(120), header(), chunk(120)], C.INVALID_ARGUMENT, "only the first"),
    ([header(shape=(4, 5))], C.INVALID_ARGUMENT, "3 positive sizes"),
    ([header(shape=(4, 0, 5))], C.INVALID_ARGUMENT, "3 positive sizes"),
    ([header(dtype=pb.DTYPE_UNSPECIFIED)], C.INVALID_ARGUMENT, "dtype"),
    ([header(name="../evil")], C.INVALID_ARGUMENT, "plain file name"),
    ([header(shape=(100, 100, 100))], C.RESOURCE_EXHAUSTED, "limit"),
])
def test_an_upload_whose_header_disagrees_with_its_chunks_is_refused(server, messages, code, words):
    srv, tokens = server
    ch, vol, _, _ = stubs(srv.address)
    with ch, pytest.raises(grpc.RpcError) as info:
        vol.Upload(iter(messages), metadata=md(tokens["alice"]), timeout=20)
    assert info.value.code() == code and words in info.value.details(), info.value.details()
    assert not list((srv.data_root / ".unwind" / "tmp").iterdir())  # the staging file is gone


def test_nan_voxels_are_refused(server):
    srv, tokens = server
    with Client(srv.address, token=tokens["alice"], progress=False) as c, pytest.raises(RemoteError) as info:
        a = np.ones((4, 5, 6), np.float32)
        a[1, 2, 3] = np.nan
        c.upload(a)
    assert info.value.code == "INVALID_ARGUMENT" and "NaN" in str(info.value)


def test_an_upload_and_its_download_round_trip_for_its_owner_only(server, tmp_path):
    srv, tokens = server
    rng = np.random.default_rng(1)
    a = rng.integers(0, 60000, (9, 7, 5), dtype=np.uint16)
    with Client(srv.address, token=tokens["alice"], progress=False) as c:
        info = c.upload(a, spacing=(3, 2, 1), unit="mm", name="rand")
        assert list(info.shape) == [9, 7, 5] and list(info.spacing) == [3, 2, 1] and info.unit == "millimeter"
        back = c.open(info.volume_id)
        np.testing.assert_array_equal(back.data.compute(), a)
        assert back.spacing == (3, 2, 1)
        for suffix in (".tif", ".nrrd", ".zarr"):
            out = c.download(info.volume_id, tmp_path / f"rand{suffix}")
            v = open_volume(out)
            np.testing.assert_array_equal(v.data.compute(), a)
            assert v.spacing == pytest.approx((3, 2, 1))
        assert info.volume_id in {v.volume_id for v in c.volumes()}
    with Client(srv.address, token=tokens["bob"], progress=False) as c:
        assert info.volume_id not in {v.volume_id for v in c.volumes()}
        for call in (lambda: c.info(info.volume_id), lambda: c.open(info.volume_id)):
            with pytest.raises(RemoteError) as err:
                call()
            assert err.value.code == "NOT_FOUND"


@pytest.mark.parametrize("path, code", [
    ("../outside/secret.tif", C.PERMISSION_DENIED),
    ("scans/../../outside/secret.tif", C.PERMISSION_DENIED),
    ("/etc/passwd", C.PERMISSION_DENIED),
    ("scans/escape/secret.tif", C.PERMISSION_DENIED),
    (".unwind/unwind.sqlite", C.PERMISSION_DENIED),
    ("scans/nothing.tif", C.NOT_FOUND),
    ("", C.INVALID_ARGUMENT),
])
def test_register_confines_paths_to_the_data_root(server, path, code):
    srv, tokens = server
    ch, vol, _, _ = stubs(srv.address)
    with ch, pytest.raises(grpc.RpcError) as info:
        vol.Register(volume_pb2.RegisterRequest(path=path), metadata=md(tokens["alice"]), timeout=10)
    assert info.value.code() == code, info.value.details()
    assert str(srv.data_root) not in info.value.details()


def test_register_a_scan_inside_the_data_root(server):
    srv, tokens = server
    with Client(srv.address, token=tokens["alice"], progress=False) as c:
        info = c.register("scans/small.tif")
        assert list(info.shape) == [12, 10, 8] and info.origin_kind == "register"
        np.testing.assert_array_equal(c.open(info.volume_id).data.compute(),
                                      open_volume(srv.data_root / "scans" / "small.tif").data.compute())


def test_nan_coordinates_are_invalid_argument(server):
    srv, tokens = server
    nan = pb.Point(axis0=float("nan"), axis1=1, axis2=2)
    ch, _, jobs, warp = stubs(srv.address)
    with ch:
        for call, request in (
            (warp.MapPoints, warp_pb2.MapPointsRequest(session_id="ses-x", points=[nan])),
            (jobs.Submit, jobs_pb2.SubmitRequest(pipeline=jobs_pb2.PipelineRequest(volume_id="v", select=[nan]))),
            (jobs.Submit, jobs_pb2.SubmitRequest(select=segmentation_pb2.SelectRequest(segmentation_id="s",
                                                                                       seeds=[nan]))),
        ):
            with pytest.raises(grpc.RpcError) as info:
                call(request, metadata=md(tokens["alice"]), timeout=10)
            assert info.value.code() == C.INVALID_ARGUMENT and "finite" in info.value.details()


@pytest.mark.parametrize("method", ["Get", "Cancel", "Resubmit"])
def test_unknown_job_ids_are_not_found(server, method):
    srv, tokens = server
    ch, _, jobs, _ = stubs(srv.address)
    with ch:
        for job_id in ("job-000000000000", "", "'; DROP TABLE jobs; --"):
            assert status_of(getattr(jobs, method), jobs_pb2.JobRef(job_id=job_id), metadata=md(tokens["alice"]),
                             timeout=10) == C.NOT_FOUND
        assert status_of(lambda: list(jobs.Watch(jobs_pb2.WatchRequest(job_id="job-x"), metadata=md(tokens["alice"]),
                                                 timeout=10))) == C.NOT_FOUND


def test_another_users_job_and_volume_are_not_found_and_limits_hold(server):
    srv, tokens = server
    with Client(srv.address, token=tokens["alice"], progress=False) as alice, \
            Client(srv.address, token=tokens["bob"], progress=False) as bob:
        rng = np.random.default_rng(2)
        vid = alice.upload(rng.integers(0, 1000, (24, 24, 24), dtype=np.uint16)).volume_id
        first = alice.segment(vid, features=2, wait=False)
        with pytest.raises(RemoteError) as info:  # one job per user on this server
            alice.segment(vid, features=2, wait=False)
        assert info.value.code == "RESOURCE_EXHAUSTED" and "limit" in str(info.value)
        for call in (lambda: bob.job(first.id), lambda: bob.cancel(first.id), lambda: bob.wait(first.id),
                     lambda: bob.resubmit(first.id), lambda: bob.segment(vid, wait=False)):
            with pytest.raises(RemoteError) as info:
                call()
            assert info.value.code == "NOT_FOUND", str(info.value)
        assert first.id not in {j.id for j in bob.jobs()}
        done = alice.wait(first.id)
        assert done.state == pb.JOB_STATE_SUCCEEDED and done.result.segmentation_id
        wait_for(lambda: alice.job(first.id).state == pb.JOB_STATE_SUCCEEDED)
        seg = done.result.segmentation_id
        with pytest.raises(RemoteError) as info:
            bob.segmentation(seg)
        assert info.value.code == "NOT_FOUND"
        with pytest.raises(RemoteError) as info:
            alice.simplify(seg, 0)
        assert info.value.code == "INVALID_ARGUMENT"
