"""Uploads of format "chunks": the client sends the store's encoded chunks, the server checks them and stores
their bytes as they are. A real server in another process; the chunks of the hostile cases are made here with
numcodecs' Blosc and google_crc32c directly (not with the code under test)."""

from __future__ import annotations

import contextlib
import itertools
import time

import google_crc32c
import grpc
import numpy as np
import pytest
from _servers import ServerProcess, assert_same_store, leftovers, store_files, stored_volume, wait_for
from numcodecs import Blosc

from napari_unwind.client import Client, RemoteError
from napari_unwind.io import as_volume, import_volume
from unwind_services._proto.unwind.v1 import common_pb2 as pb
from unwind_services._proto.unwind.v1 import volume_pb2, volume_pb2_grpc

SHAPE = (200, 20, 150)  # 2 x 1 x 2 chunks of 128^3 (clipped to 20 along axis 1), edges partial
GRID = (128, 20, 128)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("upload-chunks")
    srv = ServerProcess(tmp / "data", "--workers", 1)
    yield srv
    srv.stop()


def _volume(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    smooth = np.linspace(0, 3000, SHAPE[2])[None, None, :] + np.linspace(0, 2000, SHAPE[1])[None, :, None]
    return (smooth + rng.normal(0, 30, SHAPE)).astype(np.uint16)


def _stored(chunk: np.ndarray, *, cname: str = "lz4", typesize: int = 2, shuffle: int = Blosc.SHUFFLE,
            clevel: int = 5) -> bytes:
    enc = Blosc(cname=cname, clevel=clevel, shuffle=shuffle, typesize=typesize).encode(np.ascontiguousarray(chunk))
    return enc + google_crc32c.value(enc).to_bytes(4, "little")


def _chunks(a: np.ndarray, **codec) -> list[bytes]:
    """Every chunk of ``a`` as the store holds it, padded with zeros, in C order of the grid."""
    out = []
    for c in itertools.product(*[range(-(-n // g)) for n, g in zip(a.shape, GRID, strict=True)]):
        part = a[tuple(slice(i * g, (i + 1) * g) for i, g in zip(c, GRID, strict=True))]
        whole = np.zeros(GRID, a.dtype)
        whole[tuple(slice(0, n) for n in part.shape)] = part
        out.append(_stored(whole, **codec))
    return out


def _upload(srv: ServerProcess, chunks: list[bytes], *, shape=SHAPE, grid=GRID, fmt="chunks",
            dtype=pb.DTYPE_UINT16, name="hostile"):
    header = volume_pb2.UploadHeader(name=name, shape=list(shape), dtype=dtype, format=fmt, chunk_shape=list(grid))
    msgs = [volume_pb2.UploadRequest(header=header)] + [volume_pb2.UploadRequest(chunk=c) for c in chunks]
    opts = [("grpc.max_send_message_length", 64 * 2**20)]
    with grpc.insecure_channel(srv.address, opts) as ch:
        return volume_pb2_grpc.VolumeServiceStub(ch).Upload(iter(msgs), timeout=60)


@pytest.mark.parametrize("fmt", ["chunks", "raw"])
def test_both_formats_store_what_import_volume_writes(server, tmp_path, fmt):
    a = _volume()
    with Client(server.address, progress=False) as c:
        info = c.upload(a, spacing=(3, 2, 1), unit="um", name="s", format=fmt)
        np.testing.assert_array_equal(c.open(info.volume_id).data.compute(), a)
    import_volume(as_volume(a, spacing=(3, 2, 1), unit="um"), tmp_path / "ref.zarr")
    assert_same_store(stored_volume(server, info.volume_id), tmp_path / "ref.zarr")
    assert not leftovers(server)


def test_chunks_made_apart_are_stored_byte_for_byte(server):
    """The level-0 files are the bytes sent, made here by numcodecs (not the client's encoder)."""
    a = _volume(1)
    sent = _chunks(a)
    info = _upload(server, sent, name="apart")
    store = stored_volume(server, info.volume_id)
    coords = itertools.product(*[range(-(-n // g)) for n, g in zip(SHAPE, GRID, strict=True)])
    for c, blob in zip(coords, sent, strict=True):
        assert (store / "0" / "c" / "/".join(map(str, c))).read_bytes() == blob


def test_chunks_encoded_otherwise_give_the_store_import_volume_writes(server, tmp_path):
    """Same voxels, same bytes, whoever uploads them: valid chunks of the store's compressor made with other settings
    (here blosc level 9: another block size, other bytes) are decoded and the store is encoded by the server, byte
    for byte what import_volume writes (without the check the client's bytes were stored)."""
    a = _volume(2)
    sent = _chunks(a, clevel=9)
    assert sent != _chunks(a)  # the precondition: other bytes for the same voxels
    info = _upload(server, sent, name="otherwise")
    got = store_files(stored_volume(server, info.volume_id))
    import_volume(as_volume(a), tmp_path / "ref.zarr")
    want = store_files(tmp_path / "ref.zarr")
    assert got.keys() == want.keys()
    assert all(got[k] == want[k] for k in want if k != "zarr.json")
    with Client(server.address, progress=False) as c:
        np.testing.assert_array_equal(c.open(info.volume_id).data.compute(), a)


def _flip(blob: bytes, at: int) -> bytes:
    b = bytearray(blob)
    b[at] ^= 0xFF
    return bytes(b)


def _recrc(blob: bytes) -> bytes:
    return blob[:-4] + google_crc32c.value(blob[:-4]).to_bytes(4, "little")


def _hostile_cases() -> dict:
    a = _volume(2)
    good = _chunks(a)
    padded = a.copy()
    big = np.full((256, 20, 256), 7, np.uint16)
    big[:SHAPE[0], :, :SHAPE[2]] = a  # the edge chunks' padding is 7, not zeros
    bad_padding = [_stored(big[tuple(slice(i * g, (i + 1) * g) for i, g in zip(c, GRID, strict=True))])
                   for c in itertools.product(range(2), range(1), range(2))]
    del padded
    return {
        "crc flipped": ([_flip(good[0], len(good[0]) - 1)] + good[1:], "crc32c"),
        "block offsets broken, crc made again": ([_recrc(good[0][:16] + b"\xff" * 4 + good[0][20:-4] + b"0000")]
                                                  + good[1:], "chunk 0/0/0 cannot be decoded"),
        "another compressor": (_chunks(a, cname="zstd"), "codec"),
        "another type size": (_chunks(a, typesize=1), "codec"),
        "bit shuffle": (_chunks(a, shuffle=Blosc.BITSHUFFLE), "codec"),
        "not blosc": ([_recrc(b"\0" * 64)] + good[1:], "codec"),
        "edge padding not zeros": (bad_padding, "padding"),
        "a chunk missing": (good[:-1], "chunks"),
        "a chunk too many": (good + good[:1], "chunks"),
        "an empty chunk": ([b""] + good[1:], "bytes"),
    }


CASES = _hostile_cases()


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_chunk_is_invalid_argument_and_leaves_nothing(server, case):
    chunks, words = CASES[case]
    with pytest.raises(grpc.RpcError) as info:
        _upload(server, chunks, name=case.replace(" ", "_").replace(",", ""))
    assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT, info.value.details()
    details = info.value.details()
    assert words in details and "\n" not in details and str(server.data_root) not in details, details
    assert not leftovers(server)
    with Client(server.address, progress=False) as c:
        assert case.replace(" ", "_").replace(",", "") not in {v.name for v in c.volumes()}


@pytest.mark.parametrize("header, words", [
    (dict(grid=(64, 20, 128)), "chunk_shape must be [128, 20, 128]"),
    (dict(grid=()), "chunk_shape must be"),
    (dict(fmt="tiff"), "format must be"),
])
def test_a_bad_chunks_header_is_invalid_argument(server, header, words):
    with pytest.raises(grpc.RpcError) as info:
        _upload(server, _chunks(_volume()), **header)
    assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT and words in info.value.details()
    assert not leftovers(server)


def test_nan_in_an_upload_of_chunks_is_refused_with_its_voxel(server):
    a = np.ones((200, 10, 12), np.float32)
    a[150, 3, 4] = np.nan
    with Client(server.address, progress=False) as c, pytest.raises(RemoteError) as info:
        c.upload(a, name="nan", format="chunks")
    assert info.value.code == "INVALID_ARGUMENT" and "NaN at voxel (150, 3, 4)" in str(info.value)
    assert not leftovers(server)


def test_a_client_falls_back_to_raw_when_the_server_counts_the_chunks_as_voxels(server, monkeypatch):
    """A server of before (raw uploads only) ignores the header's format and counts the chunks' bytes as voxels; the
    client then sends raw. Emulated by clearing the format of the header on the wire, as that server's parser does."""
    import unwind_services.ingest as ingest

    sent = []
    real = ingest.encoder

    def old_wire(message_type):
        encode = real(message_type)

        def strip(message):
            if not isinstance(message, bytes) and message.WhichOneof("part") == "header":
                sent.append(message.header.format or "raw")
                message = volume_pb2.UploadRequest(header=volume_pb2.UploadHeader(
                    **{f.name: getattr(message.header, f.name) for f in message.header.DESCRIPTOR.fields
                       if f.name not in ("format", "chunk_shape")}))
            return encode(message)

        return strip

    monkeypatch.setattr(ingest, "encoder", old_wire)
    a = _volume(3)
    with Client(server.address, progress=False) as c:
        info = c.upload(a, name="fallback")
        np.testing.assert_array_equal(c.open(info.volume_id).data.compute(), a)
    assert sent == ["chunks", "raw"]


def test_a_server_whose_message_limit_is_below_a_chunk_gets_the_upload_raw(tmp_path):
    srv = ServerProcess(tmp_path / "data", "--workers", 1, "--max-message-bytes", 4 * 2**20)
    try:
        a = np.random.default_rng(4).integers(0, 4000, (130, 130, 130), dtype=np.uint16)  # 4 MiB chunks of 128^3
        with pytest.raises(grpc.RpcError) as info:
            _upload(srv, [], shape=a.shape, grid=(128, 128, 128))
        assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "upload it raw" in info.value.details()
        with Client(srv.address, progress=False) as c:
            info = c.upload(a, name="small-limit")
            np.testing.assert_array_equal(c.open(info.volume_id).data.compute(), a)
    finally:
        srv.stop()


def test_an_upload_gRPC_cut_does_not_hold_the_users_slot_while_its_handler_ends(tmp_path, monkeypatch):
    """gRPC ends an upload itself on a message over the server's limit, while the handler may still be busy (here:
    5 s late to read the header, as on a loaded machine); the client, told at once, uploads again and must not be
    refused for the upload it has just seen end. And a client falling back to raw after a refused chunked upload
    waits for a server that holds the slot until the handler ends (an earlier version's)."""
    from unwind_services import fairness, servicers
    from unwind_services.catalog import Limits
    from unwind_services.server import ServerConfig, UnwindServer

    real = servicers.upload_framing

    def late(header, *args, **kwargs):
        time.sleep({"cut": 5.0, "late": 1.5}.get(header.name, 0.0))
        return real(header, *args, **kwargs)

    monkeypatch.setattr(servicers, "upload_framing", late)
    holding, real_hold = [], fairness.UserSlots.hold

    @contextlib.contextmanager
    def counted(self, user, alive=None):
        with real_hold(self, user, alive):
            holding.append(self.what)
            try:
                yield
            finally:
                holding.remove(self.what)

    monkeypatch.setattr(fairness.UserSlots, "hold", counted)
    srv = UnwindServer(ServerConfig(data_root=tmp_path / "data", port=0, workers=1, scheduler="threads",
                                    limits=Limits(max_message_bytes=3 * 2**20)))
    srv.start()
    try:
        a = np.random.default_rng(5).integers(0, 4000, (130, 130, 130), dtype=np.uint16)  # chunks of 128^3: 4 MiB
        head = volume_pb2.UploadHeader(name="cut", shape=list(a.shape), dtype=pb.DTYPE_UINT16)
        big = volume_pb2.UploadRequest(chunk=b"\0" * (3 * 2**20 + 1))
        with grpc.insecure_channel(srv.address, [("grpc.max_send_message_length", 64 * 2**20)]) as ch:
            with pytest.raises(grpc.RpcError) as info:
                volume_pb2_grpc.VolumeServiceStub(ch).Upload(iter([volume_pb2.UploadRequest(header=head), big]),
                                                             timeout=30)
            assert info.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED  # gRPC's own limit, told at once
        with Client(srv.address, progress=False) as c:
            got = c.upload(a, name="again", format="raw")  # at once: the cut upload's handler is still busy
            np.testing.assert_array_equal(c.open(got.volume_id).data.compute(), a)
        wait_for(lambda: "uploads" not in holding, 30)  # the cut upload's handler has ended
        # a server that counts the cut upload until its handler ends: the client's raw fallback waits for it
        monkeypatch.setattr(fairness.UserSlots, "_counts", staticmethod(lambda alive: True))
        with Client(srv.address, progress=False) as c:
            got = c.upload(a, name="late")  # chunks, cut by gRPC (4 MiB messages), then raw
            np.testing.assert_array_equal(c.open(got.volume_id).data.compute(), a)
    finally:
        srv.stop(0)


def test_a_server_whose_message_limit_is_below_a_raw_message_gets_smaller_ones(tmp_path):
    """The client's raw messages carry 2 MiB; a server whose limit is below that (here 512 KiB) refuses them
    through gRPC, which names its limit: the client uploads again in messages under it, and the voxels arrive."""
    from unwind_services.catalog import Limits
    from unwind_services.server import ServerConfig, UnwindServer

    srv = UnwindServer(ServerConfig(data_root=tmp_path / "data", port=0, workers=1, scheduler="threads",
                                    limits=Limits(max_message_bytes=512 * 2**10)))
    srv.start()
    try:
        a = np.random.default_rng(6).integers(0, 4000, (70, 90, 110), dtype=np.uint16)  # 1.3 MiB
        with Client(srv.address, progress=False) as c:
            for fmt in ("chunks", "raw"):
                got = c.upload(a, name=f"low-{fmt}", format=fmt)
                np.testing.assert_array_equal(c.open(got.volume_id).data.compute(), a)
    finally:
        srv.stop(0)
