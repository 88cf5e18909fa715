"""One server per data root (issue 22 item 3): a second ``unwind serve`` on a root in use refuses to start in one
line naming the holder, and touches nothing of the first (its running job, its store); the root is free again
after the first stops, also after ``kill -9``."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from _servers import ROOT, ServerProcess

from napari_unwind.client import Client
from napari_unwind.errors import UnwindError


def _serve(root, timeout=120):
    return subprocess.run([sys.executable, "-m", "napari_unwind.cli", "serve", "--data-root", str(root), "--port",
                           "0", "--scheduler", "threads"], capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def test_a_second_server_on_the_same_root_refuses_and_the_first_keeps_serving(tmp_path):
    root = tmp_path / "data"
    first = ServerProcess(root)
    try:
        with Client(first.address, progress=False) as c:
            before = c.volumes()
        second = _serve(root)
        assert second.returncode != 0
        lines = [ln for ln in second.stderr.strip().splitlines() if ln.strip()]
        assert len(lines) == 1, second.stderr
        assert f"pid {first.proc.pid}" in lines[0] and first.address in lines[0] and "--data-root" in lines[0]
        assert "Traceback" not in second.stderr
        with Client(first.address, progress=False) as c:  # the first is untouched and still serves
            assert c.volumes() == before
        first.kill()  # kill -9: the kernel frees the lock; the next server starts
        first.start()
        with Client(first.address, progress=False) as c:
            c.volumes()
    finally:
        first.stop()
    after = ServerProcess(root)  # a clean stop frees it too
    after.stop()


def test_the_lock_is_per_root_and_freed_by_stop_in_process(tmp_path):
    from unwind_services.server import ServerConfig, UnwindServer

    a = UnwindServer(ServerConfig(data_root=tmp_path / "a", port=0, scheduler="threads"))
    try:
        with pytest.raises(UnwindError, match=rf"another napari-unwind server \(pid {os.getpid()}, host .*"
                                              rf"address 127\.0\.0\.1:{a.port}"):
            UnwindServer(ServerConfig(data_root=tmp_path / "a", port=0, scheduler="threads"))
        b = UnwindServer(ServerConfig(data_root=tmp_path / "b", port=0, scheduler="threads"))  # another root
        b.stop(0)
    finally:
        a.stop(0)
    again = UnwindServer(ServerConfig(data_root=tmp_path / "a", port=0, scheduler="threads"))
    again.stop(0)
