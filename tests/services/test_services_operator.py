"""What an operator and a user of a server meet (issue 22 item 6): a session a server job wrote works on the user's
computer; a listen beyond loopback without TLS is said at start; a certificate and key that do not belong together
are one line before anything binds; an unreachable server is reported within ``--timeout``; reflection answers on
v1 as on v1alpha.

References: the server's own straight output (the local straighten must write the same voxels), openssl's keys,
the wall clock, and the services the server was asked to serve.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
import sys
import time

import grpc
import numpy as np
import pytest
from _servers import ROOT, ServerProcess

from napari_unwind import cli
from napari_unwind.client import Client
from napari_unwind.datasets import tank_phantom
from napari_unwind.io import open_volume, write_volume
from napari_unwind.session import load_session, verify_source
from unwind_services.auth import add_token

needs_openssl = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")


def _cert(folder, name: str):
    key, cert = folder / f"{name}.key", folder / f"{name}.crt"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out",
                    str(cert), "-days", "1", "-subj", "/CN=localhost", "-addext", "subjectAltName=IP:127.0.0.1"],
                   check=True, capture_output=True)
    return cert, key


def _serve(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """``unwind serve ARGS`` that is expected to stop by itself (a refused configuration)."""
    return subprocess.run([sys.executable, "-m", "napari_unwind.cli", "serve", "--port", "0", *map(str, args)],
                          capture_output=True, text=True, cwd=ROOT, timeout=timeout)


# ------------------------------------------------------------------------------------------------------------------
# a server job's session on the user's computer
# ------------------------------------------------------------------------------------------------------------------
def test_a_session_a_server_job_wrote_straightens_the_downloaded_scan_locally(tmp_path, monkeypatch):
    t = tank_phantom(n_fish=1, seed=1, length=90)
    data = tmp_path / "data"
    (data / "scans").mkdir(parents=True)
    write_volume(t.volume, data / "scans" / "tank.zarr", spacing=t.spacing, unit=t.unit)
    fish = t.fish[0]
    click = fish.centerline[len(fish.centerline) // 2]
    local = tmp_path / "laptop"
    local.mkdir()
    srv = ServerProcess(data)
    try:
        with Client(srv.address, progress=False) as c:
            vid = c.register("scans/tank.zarr").volume_id
            job = c.pipeline(vid, select=[tuple(click)], output_name="fish.zarr")
            text = job.result.session_json
            (local / "fish.unwind.json").write_text(text)
            c.download(vid, local / "tank.zarr")  # the scan, as the user fetches it
            c.download(job.result.volume_id, local / "server-fish.nrrd")
    finally:
        srv.stop()
    # the session names the scan, not where the server keeps it
    assert str(tmp_path) not in text and str(data) not in text, text[:400]
    assert Client.session(job).source.path == "tank.zarr"
    shutil.move(data, tmp_path / "gone")  # the server's disk is not this computer's
    session = load_session(local / "fish.unwind.json")
    assert session.source.path == str(local / "tank.zarr")
    verify_source(session)  # found next to the session, and it is the very scan (the server's checksum)
    monkeypatch.chdir(tmp_path)  # anywhere but the session's folder
    assert cli.main(["straighten", str(local / "tank.zarr"), "--session", str(local / "fish.unwind.json"),
                     "-o", str(local / "fish.nrrd"), "-q"]) == 0
    a, b = open_volume(local / "fish.nrrd"), open_volume(local / "server-fish.nrrd")
    assert a.shape == b.shape and a.spacing == b.spacing
    np.testing.assert_array_equal(np.asarray(a.data), np.asarray(b.data))


# ------------------------------------------------------------------------------------------------------------------
# TLS and listening
# ------------------------------------------------------------------------------------------------------------------
@needs_openssl
def test_a_certificate_and_a_key_that_do_not_belong_together_are_one_line_before_binding(tmp_path):
    cert, key = _cert(tmp_path, "server")
    _, other_key = _cert(tmp_path, "other")
    not_pem = tmp_path / "notes.txt"
    not_pem.write_text("not a certificate\n")
    for c, k, words in ((cert, other_key, "is not the key of the certificate"),
                        (not_pem, key, "is not a PEM certificate or key"),
                        (cert, tmp_path / "missing.key", "does not exist")):
        root = tmp_path / f"data-{k.stem}-{c.stem}"
        out = _serve("--data-root", root, "--tls-cert", c, "--tls-key", k)
        assert out.returncode != 0 and "Traceback" not in out.stderr, out.stderr
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("unwind: error: ") and words in lines[0], lines
        assert "bind" not in lines[0] and not root.exists()  # refused before the root, the lock or a port


def _warnings_at_start(caplog, tmp_path, name: str, **config) -> list[str]:
    from unwind_services.server import ServerConfig, UnwindServer

    tokens = tmp_path / "tokens"
    if not tokens.exists():
        add_token(tokens, "alice")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="unwind_services"):
        srv = UnwindServer(ServerConfig(data_root=tmp_path / name, port=0, scheduler="threads", tokens=tokens,
                                        **config))
        srv.start()
        srv.stop(0)
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


@needs_openssl
def test_listening_beyond_loopback_without_tls_is_one_warning_at_start(caplog, tmp_path):
    said = _warnings_at_start(caplog, tmp_path, "open", listen="0.0.0.0")
    assert len([w for w in said if "without TLS" in w]) == 1 and "\n" not in said[0], said
    cert, key = _cert(tmp_path, "server")
    assert not [w for w in _warnings_at_start(caplog, tmp_path, "tls", listen="0.0.0.0", tls_cert=cert,
                                              tls_key=key) if "TLS" in w]
    assert not [w for w in _warnings_at_start(caplog, tmp_path, "loop") if "TLS" in w]  # 127.0.0.1 by default


# ------------------------------------------------------------------------------------------------------------------
# the client's deadline
# ------------------------------------------------------------------------------------------------------------------
def test_an_unreachable_server_is_reported_within_the_timeout(tmp_path):
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "UNWIND_TOKEN": "", "UNWIND_TOKEN_FILE": ""}
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "napari_unwind.cli", "jobs", "list", "--server",
                          f"127.0.0.1:{port}", "--timeout", "2"], capture_output=True, text=True, cwd=ROOT, env=env,
                         timeout=120)
    took = time.monotonic() - t0
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 1 and len(lines) == 1 and "unavailable" in lines[0], out.stderr
    # 2 s of deadline and the interpreter's start-up (about 1 s here), far from the 60 s of retries before
    with Client(f"127.0.0.1:{port}", progress=False, timeout=2) as c:
        t1 = time.monotonic()
        with pytest.raises(Exception, match="unavailable"):
            c.jobs()
        in_process = time.monotonic() - t1
    assert in_process <= 2.5, in_process
    assert took <= 2 + 3.0, took


# ------------------------------------------------------------------------------------------------------------------
# reflection
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("version", ["v1", "v1alpha"])
def test_reflection_answers_on_v1_and_v1alpha(tmp_path, version):
    from grpc_reflection.v1alpha import reflection_pb2

    from unwind_services.server import ServerConfig, UnwindServer

    srv = UnwindServer(ServerConfig(data_root=tmp_path / "data", port=0, scheduler="threads"))
    srv.start()
    try:
        with grpc.insecure_channel(srv.address) as ch:
            call = ch.stream_stream(f"/grpc.reflection.{version}.ServerReflection/ServerReflectionInfo",
                                    request_serializer=reflection_pb2.ServerReflectionRequest.SerializeToString,
                                    response_deserializer=reflection_pb2.ServerReflectionResponse.FromString)
            requests = [reflection_pb2.ServerReflectionRequest(list_services=""),
                        reflection_pb2.ServerReflectionRequest(file_containing_symbol="unwind.v1.VolumeService")]
            listed, files = list(call(iter(requests), timeout=10))
        names = {s.name for s in listed.list_services_response.service}
        assert set(srv.service_names) <= names and "grpc.health.v1.Health" in names, names
        assert {"grpc.reflection.v1.ServerReflection", "grpc.reflection.v1alpha.ServerReflection"} <= names
        from google.protobuf import descriptor_pb2

        protos = [descriptor_pb2.FileDescriptorProto.FromString(b)
                  for b in files.file_descriptor_response.file_descriptor_proto]
        assert any(s.name == "VolumeService" for p in protos for s in p.service), [p.name for p in protos]
    finally:
        srv.stop(0)
