"""The remote commands are reachable from the one ``unwind`` command, not only from the thin module entry."""

from __future__ import annotations

import subprocess
import sys

import pytest

from napari_unwind import _cli_remote, cli


def test_unwind_lists_and_parses_the_remote_commands():
    parser = cli.build_parser()
    for argv in (["serve", "--data-root", "/tmp/x", "--port", "0"], ["jobs", "list"]):
        args = parser.parse_args(argv)
        assert callable(args.func)
    out = subprocess.run([sys.executable, "-m", "napari_unwind.cli", "serve", "--help"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "--data-root" in out.stdout


def test_run_with_server_goes_to_the_client(monkeypatch, tmp_path):
    seen = {}

    def fake_remote(args):
        seen["server"] = args.server
        seen["token"] = args.token
        return 0

    monkeypatch.setattr(_cli_remote, "run_remote", fake_remote)
    rc = cli.main(["run", str(tmp_path / "scan.tif"), "--mask", str(tmp_path / "m.tif"), "-o",
                   str(tmp_path / "out.tif"), "--server", "127.0.0.1:1", "--token", "abc"])
    assert rc == 0
    assert seen == {"server": "127.0.0.1:1", "token": "abc"}


def test_run_without_server_stays_local(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(_cli_remote, "run_remote", lambda args: pytest.fail("a local run must not call the server"))
    rc = cli.main(["run", str(tmp_path / "missing.tif"), "--mask", str(tmp_path / "m.tif"), "-o",
                   str(tmp_path / "out.tif")])
    assert rc == 1
    assert "missing.tif" in capsys.readouterr().err


def test_run_with_server_refuses_an_output_over_its_input(tmp_path, capsys):
    scan = tmp_path / "scan.tif"
    scan.write_bytes(b"not read: the check comes first")
    before = scan.read_bytes()
    rc = cli.main(["run", str(scan), "--mask", str(tmp_path / "m.tif"), "-o", str(scan), "--overwrite",
                   "--server", "127.0.0.1:1"])
    assert rc == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scan.tif" in err[0]
    assert scan.read_bytes() == before
