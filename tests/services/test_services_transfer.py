"""Uploads imported while they stream, downloads without extra copies: a real server in another process."""

from __future__ import annotations

import json
import threading
import time

import dask.array as da
import grpc
import numpy as np
import psutil
import pytest
from _servers import ServerProcess, assert_same_store, leftovers, stored_volume
from google.protobuf.message import DecodeError

from napari_unwind.client import Client, RemoteError
from napari_unwind.io import as_volume, import_volume, open_volume, write_volume
from unwind_services._proto.unwind.v1 import common_pb2 as pb
from unwind_services._proto.unwind.v1 import volume_pb2, volume_pb2_grpc
from unwind_services.ingest import _chunk_reader, chunk_payload, decoder, encode_chunk, encoder


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("transfer")
    srv = ServerProcess(tmp / "data", "--workers", 1)
    yield srv
    srv.stop()


@pytest.mark.parametrize("shape, dtype, labels", [
    ((300, 20, 270), np.uint16, False),  # 3 slabs of the store (128 + 128 + 44 planes), a pyramid level
    ((131, 9, 261), np.float32, False),
    ((260, 7, 9), np.uint8, True),       # labels: the pyramid by nearest
])
def test_a_streamed_upload_stores_what_import_volume_writes(server, tmp_path, shape, dtype, labels):
    rng = np.random.default_rng(3)
    a = rng.normal(500, 100, shape).astype(dtype) if dtype == np.float32 else \
        rng.integers(0, 200 if labels else 60000, shape).astype(dtype)
    with Client(server.address, progress=False) as c:
        info = c.upload(a, spacing=(3, 2, 1), unit="um", origin=(1, 2, 3), labels=labels, name="s")
    ref = import_volume(as_volume(a, spacing=(3, 2, 1), unit="um", origin=(1, 2, 3)), tmp_path / "ref.zarr",
                        labels=labels)
    assert info.levels == len(ref.levels) >= 2
    assert_same_store(stored_volume(server, info.volume_id), tmp_path / "ref.zarr")
    assert not leftovers(server)


def test_downloads_of_every_level_and_of_a_registered_file_are_the_voxels(server, tmp_path):
    """Level 0 and 1 of an uploaded store (read chunk by chunk, edges partial) and a registered TIFF (through dask)."""
    rng = np.random.default_rng(5)
    a = rng.integers(0, 60000, (300, 20, 270), dtype=np.uint16)
    ref = import_volume(as_volume(a), tmp_path / "ref.zarr")
    scans = server.data_root / "scans"
    scans.mkdir(exist_ok=True)
    write_volume(a[:50], scans / "part.tif")
    with Client(server.address, progress=False) as c:
        vid = c.upload(a).volume_id
        for level in (0, 1):
            got = c.open(vid, level=level)
            np.testing.assert_array_equal(got.data.compute(), ref.levels[level].compute())
        reg = c.register("scans/part.tif").volume_id
        np.testing.assert_array_equal(c.open(reg).data.compute(), a[:50])
    # which reader each took: the core's chunk reader for our stores, dask for anything else
    assert _chunk_reader(open_volume(tmp_path / "ref.zarr"), 1) is not None
    assert _chunk_reader(open_volume(scans / "part.tif"), 0) is None


def test_non_contiguous_and_dask_volumes_upload_and_download_intact(server):
    rng = np.random.default_rng(4)
    base = rng.integers(0, 60000, (40, 30, 50), dtype=np.uint16)
    cases = {
        "strided": base[:, ::2, 1::2],  # not C-contiguous
        "transposed": base.transpose(2, 0, 1),
        "big-endian": base.astype(">u2"),
        "dask": da.from_array(base, chunks=(7, 11, 13)),
    }
    with Client(server.address, progress=False) as c:
        for label, data in cases.items():
            info = c.upload(data, name=label)
            back = c.open(info.volume_id).data.compute()
            np.testing.assert_array_equal(back, np.asarray(data), err_msg=label)
            assert back.dtype == np.uint16


def test_a_header_disagreeing_with_chunks_after_whole_slabs_leaves_nothing(server):
    """The import has written slabs already when the stream ends short: the partial store goes."""
    shape = (300, 20, 270)
    header = volume_pb2.UploadRequest(header=volume_pb2.UploadHeader(name="x", shape=list(shape),
                                                                     dtype=pb.DTYPE_UINT16))
    part = volume_pb2.UploadRequest(chunk=b"\1" * (1 << 20))
    with grpc.insecure_channel(server.address) as ch, pytest.raises(grpc.RpcError) as info:
        volume_pb2_grpc.VolumeServiceStub(ch).Upload(iter([header] + [part] * 3), timeout=30)
    assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "promises" in info.value.details()
    assert not leftovers(server)
    with Client(server.address, progress=False) as c:
        assert "x" not in {v.name for v in c.volumes()}


def test_a_cancelled_upload_leaves_no_volume(server):
    shape = (300, 20, 270)
    header = volume_pb2.UploadRequest(header=volume_pb2.UploadHeader(name="cancelled", shape=list(shape),
                                                                     dtype=pb.DTYPE_UINT16))
    sent = threading.Event()

    def messages():
        yield header
        for _ in range(2):
            yield volume_pb2.UploadRequest(chunk=b"\2" * (1 << 20))
        sent.set()
        time.sleep(30)  # the client stalls mid-upload, then gives up

    with grpc.insecure_channel(server.address) as ch:
        fut = volume_pb2_grpc.VolumeServiceStub(ch).Upload.future(messages(), timeout=60)
        assert sent.wait(20)
        time.sleep(0.5)
        assert fut.cancel()
    deadline = time.monotonic() + 15
    while leftovers(server) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not leftovers(server)
    with Client(server.address, progress=False) as c:
        assert "cancelled" not in {v.name for v in c.volumes()}
        c.upload(np.ones((3, 4, 5), np.uint8))  # the worker is free again


def test_nan_in_a_streamed_upload_is_refused_with_its_voxel(server):
    a = np.ones((200, 10, 12), np.float32)
    a[150, 3, 4] = np.nan
    with Client(server.address, progress=False) as c, pytest.raises(RemoteError) as info:
        c.upload(a, name="nan")
    assert info.value.code == "INVALID_ARGUMENT" and "NaN at voxel (150, 3, 4)" in str(info.value)
    assert not leftovers(server)


# ------------------------------------------------------------------------------------------------------------------
# the chunk messages' hand-made encoding, against protobuf's
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [0, 1, 127, 128, 16383, 16384, 2 * 1024 * 1024 + 5])
def test_chunk_messages_encode_and_decode_as_protobuf_does(n):
    payload = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    for cls in (volume_pb2.UploadRequest, volume_pb2.DownloadResponse):
        wire = cls(chunk=payload).SerializeToString()
        assert encode_chunk(memoryview(payload)) == wire
        assert bytes(chunk_payload(wire)) == payload
        assert bytes(decoder(cls)(wire)) == payload
        assert encoder(cls)(wire) is wire


def test_other_messages_go_through_protobuf():
    header = volume_pb2.UploadRequest(header=volume_pb2.UploadHeader(name="h", shape=[1, 2, 3]))
    wire = header.SerializeToString()
    assert chunk_payload(wire) is None
    assert decoder(volume_pb2.UploadRequest)(wire) == header
    assert encoder(volume_pb2.UploadRequest)(header) == wire
    # a chunk followed by another field is not a bare chunk
    assert chunk_payload(encode_chunk(b"ab") + b"\x08\x01") is None
    with pytest.raises(DecodeError, match="UploadRequest"):  # protobuf's own parse error on garbage
        decoder(volume_pb2.UploadRequest)(b"\x12\x05ab")


def test_the_volume_service_registers_every_rpc_of_its_contract():
    from unwind_services.servicers import add_volume_service

    got = {}

    class Recorder:
        def add_generic_rpc_handlers(self, handlers):
            pass

        def add_registered_method_handlers(self, service, handlers):
            got[service] = set(handlers)

    add_volume_service(volume_pb2_grpc.VolumeServiceServicer(), Recorder())
    methods = {m.name for m in volume_pb2.DESCRIPTOR.services_by_name["VolumeService"].methods}
    assert got == {"unwind.v1.VolumeService": methods}


def test_a_server_killed_mid_upload_leaves_no_volume_after_its_restart(server):
    header = volume_pb2.UploadRequest(header=volume_pb2.UploadHeader(name="killed", shape=[300, 20, 270],
                                                                     dtype=pb.DTYPE_UINT16))
    sent = threading.Event()

    def messages():
        yield header
        for _ in range(2):
            yield volume_pb2.UploadRequest(chunk=b"\3" * (1 << 20))
        sent.set()
        time.sleep(30)

    with grpc.insecure_channel(server.address) as ch:
        fut = volume_pb2_grpc.VolumeServiceStub(ch).Upload.future(messages(), timeout=60)
        assert sent.wait(20)
        deadline = time.monotonic() + 10  # the worker has begun the store
        while not any("unwind-tmp" in p for p in leftovers(server)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert any("unwind-tmp" in p for p in leftovers(server))
        children = psutil.Process(server.proc.pid).children(recursive=True)  # job workers, the import's process
        assert children
        server.kill()
        fut.cancel()
    # none outlives the server (an orphan would hold memory and the pipe forever)
    _, alive = psutil.wait_procs(children, timeout=10)
    assert not alive, [p.cmdline() for p in alive]
    server.start()
    assert not leftovers(server)  # the partial store and the pipe were swept at the start
    with Client(server.address, progress=False) as c:
        assert "killed" not in {v.name for v in c.volumes()}


def test_a_stalled_upload_does_not_hold_back_jobs(server):
    """The import of an upload runs in its own worker pool: a client that stops sending mid-upload must not keep
    the (single, here) job worker from running other users' jobs."""
    rng = np.random.default_rng(5)
    small = (rng.random((24, 20, 20)) * 100).astype(np.uint16)
    small[8:16, 8:12, 8:12] = 1000
    with Client(server.address, progress=False) as c:
        vid = c.upload(small, name="small").volume_id
    header = volume_pb2.UploadRequest(header=volume_pb2.UploadHeader(name="stalled", shape=[300, 20, 270],
                                                                     dtype=pb.DTYPE_UINT16))
    sent, release = threading.Event(), threading.Event()

    def messages():
        yield header
        yield volume_pb2.UploadRequest(chunk=b"\1" * (1 << 20))
        sent.set()
        release.wait(60)  # the client stalls mid-upload

    with grpc.insecure_channel(server.address) as ch:
        fut = volume_pb2_grpc.VolumeServiceStub(ch).Upload.future(messages(), timeout=90)
        try:
            assert sent.wait(20)
            time.sleep(1.0)  # the upload's import has started and waits for bytes
            with Client(server.address, progress=False) as c:
                job = c.segment(vid, features=2, wait=False)
                done = c.wait(job.id, timeout=45)
            assert done.state == pb.JOB_STATE_SUCCEEDED, done
            assert not fut.done()  # the stalled upload was still open while the job ran
        finally:
            fut.cancel()
            release.set()


def test_open_receives_the_stored_chunks_and_a_volume_stored_otherwise_raw(server):
    """Our stores come as their chunks (fewer bytes than the voxels for a compressible scan, decoded by the client);
    a registered TIFF comes raw, said in the header."""
    a = np.zeros((200, 40, 150), np.uint16)
    a[:, 10:30, 20:130] = np.arange(110, dtype=np.uint16)
    scans = server.data_root / "scans"
    scans.mkdir(exist_ok=True)
    write_volume(a[:20], scans / "stored-otherwise.tif")
    with Client(server.address, progress=False) as c:
        vid = c.upload(a, name="chunks").volume_id
        header, chunks = c._download_stream(vid, "chunks", 0, 60)  # noqa: SLF001 - what the wire holds
        blobs = [bytes(b) for b in chunks]
        grid = json.loads((stored_volume(server, vid) / "0" / "zarr.json").read_text())["chunk_grid"]
        assert header.format == "chunks" and list(header.chunk_shape) == grid["configuration"]["chunk_shape"]
        counts = [-(-n // g) for n, g in zip(a.shape, header.chunk_shape)]
        assert header.total_bytes == a.nbytes and len(blobs) == np.prod(counts) > 1  # the grid, in C order
        assert sum(map(len, blobs)) < a.nbytes / 10
        np.testing.assert_array_equal(c.open(vid).data.compute(), a)
        reg = c.register("scans/stored-otherwise.tif").volume_id
        header, chunks = c._download_stream(reg, "chunks", 0, 60)  # noqa: SLF001
        assert header.format == "raw" and sum(map(len, chunks)) == a[:20].nbytes
        np.testing.assert_array_equal(c.open(reg).data.compute(), a[:20])


def test_a_chunk_never_written_comes_as_the_fill_value_and_a_corrupt_one_is_data_loss(server, tmp_path):
    rng = np.random.default_rng(8)
    a = rng.integers(1, 60000, (300, 20, 270), dtype=np.uint16)
    scans = server.data_root / "scans"
    scans.mkdir(exist_ok=True)
    store = scans / "holes.zarr"
    import_volume(as_volume(a), store)
    meta = json.loads((store / "zarr.json").read_text())
    meta["attributes"]["unwind"]["all_chunks_written"] = False  # a store that does not claim every chunk
    (store / "zarr.json").write_text(json.dumps(meta))
    (store / "0" / "c" / "1" / "0" / "2").unlink()  # chunk (1, 0, 2): planes 128..255, columns 256..269
    want = a.copy()
    want[128:256, :, 256:] = 0
    with Client(server.address, progress=False) as c:
        reg = c.register("scans/holes.zarr").volume_id
        np.testing.assert_array_equal(c.open(reg).data.compute(), want)
        vid = c.upload(a, name="to-corrupt").volume_id
        chunk = stored_volume(server, vid) / "0" / "c" / "0" / "0" / "1"
        blob = bytearray(chunk.read_bytes())
        blob[len(blob) // 2] ^= 0xFF
        chunk.write_bytes(bytes(blob))
        with pytest.raises(RemoteError) as info:
            c.open(vid)
        assert info.value.code == "DATA_LOSS" and "chunk (0, 0, 1) does not match its checksum" in str(info.value)
