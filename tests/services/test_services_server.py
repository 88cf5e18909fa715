"""The server alone (in this process, threads only): one service, reflection, health, TLS, and the CLI commands."""

from __future__ import annotations

import argparse
import shutil
import subprocess

import grpc
import pytest

from napari_unwind._cli_remote import add_remote_commands
from napari_unwind.cli import main as remote_main
from napari_unwind.client import Client, RemoteError
from napari_unwind.errors import InvalidInputError
from unwind_services.server import ServerConfig, UnwindServer


@pytest.fixture
def make_server(tmp_path):
    servers = []

    def make(**kw):
        srv = UnwindServer(ServerConfig(data_root=tmp_path / "data", port=0, **kw))
        srv.start()
        servers.append(srv)
        return srv

    yield make
    for s in servers:
        s.stop(0)


def test_one_service_alone_with_health_and_reflection(make_server):
    from grpc_health.v1 import health_pb2, health_pb2_grpc
    from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

    srv = make_server(services=["warp"])
    with grpc.insecure_channel(srv.address) as ch:
        health = health_pb2_grpc.HealthStub(ch)
        assert health.Check(health_pb2.HealthCheckRequest(service="unwind.v1.WarpService"), timeout=5).status == 1
        with pytest.raises(grpc.RpcError) as info:
            health.Check(health_pb2.HealthCheckRequest(service="unwind.v1.VolumeService"), timeout=5)
        assert info.value.code() == grpc.StatusCode.NOT_FOUND
        stub = reflection_pb2_grpc.ServerReflectionStub(ch)
        reply = next(stub.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(list_services="")]),
                                               timeout=5))
        names = {s.name for s in reply.list_services_response.service}
        assert {"unwind.v1.WarpService", "unwind.v1.JobService", "grpc.health.v1.Health"} <= names
        assert "unwind.v1.VolumeService" not in names
    with Client(srv.address, progress=False) as c, pytest.raises(RemoteError) as err:
        c.volumes()
    assert err.value.code == "UNIMPLEMENTED"


def test_the_server_refuses_unsafe_configurations(tmp_path):
    for kw, words in ((dict(listen="0.0.0.0"), "needs --tokens"), (dict(services=["nope"]), "unknown service"),
                      (dict(tls_cert=tmp_path / "c.pem"), "both --tls-cert and --tls-key")):
        with pytest.raises(InvalidInputError, match=words):
            UnwindServer(ServerConfig(data_root=tmp_path / "d", port=0, **kw))


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
def test_tls(make_server, tmp_path):
    key, cert = tmp_path / "key.pem", tmp_path / "cert.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out",
                    str(cert), "-days", "1", "-subj", "/CN=localhost", "-addext", "subjectAltName=IP:127.0.0.1"],
                   check=True, capture_output=True)
    srv = make_server(tls_cert=cert, tls_key=key)
    with Client(srv.address, tls=cert, progress=False) as c:
        assert c.health() == "SERVING" and c.volumes() == []
    with Client(srv.address, progress=False, retry_seconds=1) as c, pytest.raises(RemoteError) as err:
        c.volumes()  # plaintext against TLS
    assert err.value.code == "UNAVAILABLE"


def test_the_remote_commands_parse_and_report_errors_in_one_line(make_server, tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="unwind")
    add_remote_commands(parser.add_subparsers())
    args = parser.parse_args(["serve", "--data-root", "d", "--port", "0", "--service", "warp", "--listen", "::1"])
    assert args.service == ["warp"] and args.port == 0 and args.func.__name__ == "cmd_serve"
    args = parser.parse_args(["submit", "scan.tif", "--select", "1,2,3", "--server", "h:1"])
    assert args.select == [(1.0, 2.0, 3.0)] and args.func.__name__ == "cmd_submit"
    tokens = tmp_path / "tokens"
    assert remote_main(["serve", "--tokens", str(tokens), "--add-token", "alice"]) == 0
    token = capsys.readouterr().out.splitlines()[-1]
    assert token not in tokens.read_text() and "alice sha256:" in tokens.read_text()
    srv = make_server(tokens=tokens)
    assert remote_main(["jobs", "list", "--server", srv.address, "--token", token]) == 0
    for argv, words in ((["jobs", "get", "job-nope", "--server", srv.address, "--token", token], "no job"),
                        (["jobs", "list", "--server", srv.address, "--token", "wrong"], "unknown token"),
                        (["jobs", "cancel", "--server", srv.address, "--token", token], "needs a job id"),
                        (["submit", "--server", srv.address, "--token", token], "give a scan")):
        capsys.readouterr()
        assert remote_main(argv) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("unwind: error: ") and words in err[0], err


def test_run_on_a_server_checks_its_options_before_any_upload(tmp_path, capsys):
    from napari_unwind.io import write_volume

    scan = write_volume(__import__("numpy").zeros((4, 4, 4), "uint8"), tmp_path / "scan.tif")
    for extra, words in (([], "--select"), (["--mask", str(scan), "--select", "1,2,3"], "not both"),
                         (["--mask", str(scan), "--features", "3"], "do not apply with --mask")):
        capsys.readouterr()
        code = remote_main(["run", str(scan), "-o", str(tmp_path / "x.nrrd"), "--server", "127.0.0.1:9", *extra])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 1 and len(err) == 1 and words in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.tif"]
