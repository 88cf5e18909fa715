"""The remote commands are reachable from the one ``unwind`` command, not only from the thin module entry."""

from __future__ import annotations

import subprocess
import sys

import pytest

from napari_unwind import _cli_remote, cli

# Each command line, the function the parser must hand it to, and the options it must parse to (typed values,
# written out here by hand from the help texts; a default is checked where the command relies on it).
WIRING = [
    (["serve", "--data-root", "/tmp/x", "--port", "0", "--service", "jobs", "--service", "warp", "--workers", "3",
      "--max-jobs-per-user", "2"],
     "cmd_serve", dict(data_root="/tmp/x", port=0, service=["jobs", "warp"], workers=3, max_jobs_per_user=2,
                       listen="127.0.0.1", drain=None, max_message_bytes=64 * 1024**2)),
    (["submit", "scan.tif", "--select", "1,2,3", "--select", "4.5,5,6", "--order", "3", "--pad", "2", "--wait",
      "--server", "h:1", "--token=-abc", "--timeout", "5"],
     "cmd_submit", dict(input="scan.tif", select=[(1.0, 2.0, 3.0), (4.5, 5.0, 6.0)], order=3, pad=2, wait=True,
                        server="h:1", token="-abc", timeout=5.0, batch=None, max_parallel=4, quiet=False)),
    (["jobs", "list"], "cmd_jobs", dict(action="list", job_id=None, limit=50, json=False, token=None)),
    (["jobs", "cancel", "job-7", "--limit", "3", "-q", "--server", "h:2"],
     "cmd_jobs", dict(action="cancel", job_id="job-7", limit=3, quiet=True, server="h:2")),
    (["jobs", "get", "job-8", "--json", "--tls"], "cmd_jobs", dict(action="get", job_id="job-8", json=True, tls=True)),
]


@pytest.mark.parametrize("argv, func, values", WIRING, ids=lambda x: x[0] if isinstance(x, list) else None)
def test_each_remote_command_reaches_its_function_with_its_options(argv, func, values, monkeypatch):
    for name in ("UNWIND_SERVER", "UNWIND_TOKEN", "UNWIND_TOKEN_FILE"):
        monkeypatch.delenv(name, raising=False)
    args = cli.build_parser().parse_args(argv)
    assert args.func is getattr(_cli_remote, func), (argv[0], args.func)
    assert {k: getattr(args, k) for k in values} == values


def test_the_local_commands_reach_their_functions():
    parser = cli.build_parser()
    for argv, func in ((["info", "a.tif"], cli.cmd_info), (["run", "a.tif", "-o", "b.tif"], cli.cmd_run),
                       (["straighten", "a.tif", "--session", "s.json", "-o", "b.tif"], cli.cmd_straighten),
                       (["bend", "a.tif", "--session", "s.json", "-o", "b.tif"], cli.cmd_bend)):
        assert parser.parse_args(argv).func is func, argv[0]


def test_unwind_lists_the_remote_commands():
    out = subprocess.run([sys.executable, "-m", "napari_unwind.cli", "serve", "--help"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "--data-root" in out.stdout


def test_a_message_limit_too_small_for_a_result_is_refused_before_serving(tmp_path):
    out = subprocess.run([sys.executable, "-m", "napari_unwind.cli", "serve", "--data-root", str(tmp_path / "d"),
                          "--port", "0", "--max-message-bytes", "100000"], capture_output=True, text=True, timeout=120)
    assert out.returncode != 0
    assert "max_message_bytes must be at least 262144" in out.stderr and out.stderr.count("\n") == 1, out.stderr
    assert not (tmp_path / "d").exists()


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
