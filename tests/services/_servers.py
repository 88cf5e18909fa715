"""Helpers of the services tests: real servers in separate processes on 127.0.0.1, tokens, raw calls."""

from __future__ import annotations

import os
import re
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import grpc

ROOT = Path(__file__).resolve().parents[2]


class ServerProcess:
    """``python -m napari_unwind.cli serve`` in a child process; restartable on the same port.

    ``scheduler``: the ``--scheduler`` it gets; "threads" by default (no LocalCluster to start: quick), None for
    the server's own default (a LocalCluster), or a cluster address.
    """

    def __init__(self, data_root: Path, *args: str, port: int = 0, log: Path | None = None,
                 scheduler: str | None = "threads"):
        self.data_root, self.args = Path(data_root), [str(a) for a in args]
        if scheduler is not None:
            self.args += ["--scheduler", scheduler]
        self.log = log or self.data_root.parent / f"{self.data_root.name}-server.log"
        self.port = port
        self.proc: subprocess.Popen | None = None
        self.start()

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    def start(self, timeout: float = 90.0) -> None:
        cmd = [sys.executable, "-m", "napari_unwind.cli", "serve", "--data-root", str(self.data_root),
               "--port", str(self.port), *self.args]
        logf = open(self.log, "a")
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=logf, text=True, cwd=ROOT,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        logf.close()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            ready, _, _ = select.select([self.proc.stdout], [], [], 0.5)
            if ready:
                line = self.proc.stdout.readline()
                m = re.search(r"listening on [^:\s]+:(\d+)", line)
                if m:
                    self.port = int(m.group(1))
                    return
            if self.proc.poll() is not None:
                break
        raise RuntimeError(f"the server did not start: {self.log.read_text()[-3000:]}")

    def kill(self) -> None:
        """kill -9: no shutdown code runs."""
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=30)

    def terminate(self, timeout: float = 60.0) -> int:
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(timeout=timeout)

    def restart(self) -> None:
        if self.proc.poll() is None:
            self.terminate()
        self.start()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def healthy(address: str, timeout: float = 5.0) -> bool:
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    with grpc.insecure_channel(address) as ch:
        r = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(), timeout=timeout)
        return r.status == health_pb2.HealthCheckResponse.SERVING


def raw_unary(address: str, method: str, payload: bytes, metadata=(), timeout: float = 10.0) -> bytes:
    """Call ``method`` with bytes that need not parse (identity serializers)."""
    with grpc.insecure_channel(address) as ch:
        call = ch.unary_unary(method, request_serializer=lambda b: b, response_deserializer=lambda b: b)
        return call(payload, metadata=metadata, timeout=timeout)


def status_of(fn, *args, **kwargs) -> grpc.StatusCode | None:
    """The status code a raw gRPC call ends with (None when it succeeds)."""
    try:
        fn(*args, **kwargs)
    except grpc.RpcError as exc:
        return exc.code()
    return None


def wait_for(predicate, timeout: float = 60.0, interval: float = 0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise TimeoutError("condition not met in time")


def stored_volume(srv: ServerProcess, volume_id: str) -> Path:
    """The OME-Zarr store of an uploaded volume under the server's own folder."""
    found = list((srv.data_root / ".unwind").rglob(f"{volume_id}.zarr"))
    assert len(found) == 1, found
    return found[0]


def store_files(store: Path) -> dict[str, bytes]:
    """Every file of a store: its path inside the store -> its bytes."""
    return {str(p.relative_to(store)): p.read_bytes() for p in sorted(store.rglob("*")) if p.is_file()}


def assert_same_store(got: Path, want: Path) -> None:
    """The two OME-Zarr stores hold the same files byte for byte, but for the name in the root attributes (the
    store's folder)."""
    import json

    g_files, w_files = store_files(got), store_files(want)
    assert g_files.keys() == w_files.keys()
    for name in w_files:
        if name == "zarr.json":
            g, w = json.loads(g_files[name]), json.loads(w_files[name])
            for d in (g, w):
                d["attributes"]["ome"]["multiscales"][0].pop("name")
            assert g == w
        else:
            assert g_files[name] == w_files[name], name


def leftovers(srv: ServerProcess) -> list[str]:
    """Partial stores, pipes or staging files anywhere under the server's own folder."""
    private = srv.data_root / ".unwind"
    found = []
    for folder, dirs, files in os.walk(private):  # (os.walk skips what vanishes while it looks)
        for name in dirs + files:
            if "unwind-tmp" in name or name.endswith(".fifo") or Path(folder) == private / "tmp":
                found.append(os.path.relpath(os.path.join(folder, name), private))
    return found
