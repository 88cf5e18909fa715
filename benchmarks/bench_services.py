"""The gRPC services under load, and their transfer rates against raw gRPC streaming of the same bytes.

    .venv/bin/python -m benchmarks.bench_services                    # the recorded run
    .venv/bin/python -m benchmarks.bench_services --clients 4 --mib 64   # a quick look
    .venv/bin/python -m benchmarks.bench_services --mib 0 --clients 28 --misbehave all   # issue 22's load test

Everything runs in one invocation, each server in its own process on 127.0.0.1:

1. Transfer: a ``--mib`` MiB uint16 volume (smooth + noise) uploaded with ``Client.upload`` (the server imports it
   into an OME-Zarr pyramid while it streams; the default format "chunks", where the client encodes the store's
   chunks, and format "raw", where the server does) and downloaded with ``Client.open`` (level 0 as the store's
   chunks, decoded by the client), against a bare gRPC server that only receives / sends the same number of bytes in
   the same 2 MiB messages (identity serializers, no protobuf, no disk). Two more rows bound the upload: the
   client's own messages (``Client.upload``'s, from the same array) into the bare server, i.e. the transfer without
   the server's work, and the same ``import_volume`` alone in this process: a streamed upload cannot be faster
   than either.
2. Load: ``--clients`` concurrent clients, each a user of its own (a server with a tokens file and its default
   per-user limits), uploading its own small scan (a 2-fish tank phantom, 100 x 65 x 65) and running the whole
   pipeline (segment, select, skeleton, straighten) as a job it watches; meanwhile a prober in a process of its own
   calls the health service every 20 ms. Reports pipeline latency p50/p99, throughput, and health p50/p99/max.
3. With ``--misbehave all`` (issue 22's load test), four more users misbehave, each in a process of its own, for as
   long as the good clients run: one keeps two uploads open that send a header and then nothing, one submits jobs
   with huge parameters (``levels=2**31-1``, NaN timeouts), one lists its volumes in bursts of 200 concurrent
   calls, and one keeps its queue full of slow straight exports. What the misbehaving users were answered is
   counted by status code; the good clients' figures are the verdict.
"""

from __future__ import annotations

import argparse
import inspect
import re
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks._util import table

CHUNK = 2 * 1024 * 1024
MiB = 1024 * 1024


# ------------------------------------------------------------------------------------------------------------------
# the raw baseline: a gRPC server that only moves bytes
# ------------------------------------------------------------------------------------------------------------------
def raw_server(port: int) -> None:
    import grpc

    def sink(request_iterator, context):
        n = 0
        for msg in request_iterator:
            n += len(msg)
        return n.to_bytes(8, "little")

    def source(request, context):
        total = int.from_bytes(request, "little")
        block = np.random.default_rng(0).integers(0, 256, CHUNK, dtype=np.uint8).tobytes()
        sent = 0
        while sent < total:
            k = min(CHUNK, total - sent)
            yield block if k == CHUNK else block[:k]
            sent += k

    ident = lambda b: b  # noqa: E731
    handler = grpc.method_handlers_generic_handler("raw.Bytes", {
        "Sink": grpc.stream_unary_rpc_method_handler(sink, request_deserializer=ident, response_serializer=ident),
        "Source": grpc.unary_stream_rpc_method_handler(source, request_deserializer=ident, response_serializer=ident),
    })
    from concurrent.futures import ThreadPoolExecutor as Pool

    opts = [("grpc.max_receive_message_length", 64 * MiB), ("grpc.max_send_message_length", 64 * MiB)]
    server = grpc.server(Pool(8), options=opts)
    server.add_generic_rpc_handlers((handler,))
    bound = server.add_insecure_port(f"127.0.0.1:{port}")
    server.start()
    print(f"listening on 127.0.0.1:{bound}", flush=True)
    signal.signal(signal.SIGTERM, lambda *a: server.stop(0))
    server.wait_for_termination()


def _start(cmd: list[str], timeout: float = 120, stderr=subprocess.DEVNULL) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=stderr, text=True)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if select.select([proc.stdout], [], [], 0.5)[0]:
            m = re.search(r"listening on (\S+)", proc.stdout.readline())
            if m:
                return proc, m.group(1)
        if proc.poll() is not None:
            break
    raise RuntimeError(f"{cmd} did not start")


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()


def _raw_rates(address: str, nbytes: int, repeats: int) -> tuple[float, float]:
    import grpc

    opts = [("grpc.max_receive_message_length", 64 * MiB), ("grpc.max_send_message_length", 64 * MiB)]
    block = np.random.default_rng(1).integers(0, 256, CHUNK, dtype=np.uint8).tobytes()
    up, down = [], []
    with grpc.insecure_channel(address, opts) as ch:
        sink = ch.stream_unary("/raw.Bytes/Sink", request_serializer=lambda b: b, response_deserializer=lambda b: b)
        source = ch.unary_stream("/raw.Bytes/Source", request_serializer=lambda b: b,
                                 response_deserializer=lambda b: b)

        def messages():
            sent = 0
            while sent < nbytes:
                k = min(CHUNK, nbytes - sent)
                yield bytes(block[:k])  # a fresh bytes object per message, as the client builds them
                sent += k

        for _ in range(repeats):
            t0 = time.perf_counter()
            assert int.from_bytes(sink(messages(), timeout=600), "little") == nbytes
            up.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            got = bytearray(nbytes)
            pos = 0
            for c in source(nbytes.to_bytes(8, "little"), timeout=600):
                got[pos:pos + len(c)] = c
                pos += len(c)
            assert pos == nbytes
            down.append(time.perf_counter() - t0)
    return nbytes / MiB / min(up), nbytes / MiB / min(down)


def _client_messages_rate(address: str, vol: np.ndarray, repeats: int) -> float:
    """MiB/s of ``Client.upload``'s own messages (header, then the encoded chunks) into the bare gRPC server."""
    import grpc

    from napari_unwind.client import Client

    class Sink:  # Client.upload makes its call on its channel: give it the bare server's method instead
        def __init__(self, channel):
            self.channel = channel

        def stream_unary(self, method, request_serializer, response_deserializer):
            return self.channel.stream_unary("/raw.Bytes/Sink", request_serializer=request_serializer,
                                             response_deserializer=lambda b: b)

        def close(self):
            self.channel.close()

    opts = [("grpc.max_receive_message_length", 64 * MiB), ("grpc.max_send_message_length", 64 * MiB)]
    best = float("inf")
    with grpc.insecure_channel(address, opts) as ch, Client(address, progress=False) as c:
        c._channel = Sink(ch)
        for _ in range(repeats):
            t0 = time.perf_counter()
            c.upload(vol, name="sink")
            best = min(best, time.perf_counter() - t0)
    return vol.nbytes / MiB / best


def transfer(address: str, raw_address: str, mib: int, repeats: int, tmp: Path) -> list[list[str]]:
    from napari_unwind.client import Client
    from napari_unwind.io import as_volume, import_volume

    side = int(round((mib * MiB / 2) ** (1 / 3)))
    z = int(mib * MiB / 2 / side / side)
    rng = np.random.default_rng(0)
    smooth = np.linspace(0, 3000, side, dtype=np.float32)[None, None, :] + np.linspace(0, 3000, side)[None, :, None]
    vol = (np.broadcast_to(smooth, (z, side, side)) + rng.normal(0, 30, (z, side, side))).astype(np.uint16)
    nbytes = vol.nbytes
    raw_up, raw_down = _raw_rates(raw_address, nbytes, repeats)
    client_up = _client_messages_rate(raw_address, vol, repeats)
    up, up_raw, down, imp = [], [], [], []
    formats = "format" in inspect.signature(Client.upload).parameters  # the code of before (--before) has none
    with Client(address, progress=False, timeout=600) as c:
        c.upload(vol[:8], name="warm-up")  # the job worker's first task loads its imports
        if formats:
            c.upload(vol[:8], name="warm-up", format="raw")
        for i in range(repeats):
            t0 = time.perf_counter()
            vid = c.upload(vol, name=f"bench{i}").volume_id
            up.append(time.perf_counter() - t0)
            if formats:  # the raw voxels, imported (encoded) by the server
                t0 = time.perf_counter()
                c.upload(vol, name=f"bench{i}-raw", format="raw")
                up_raw.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            back = c.open(vid)
            down.append(time.perf_counter() - t0)
            assert back.data.shape == vol.shape and np.array_equal(back.data.compute()[::97], vol[::97])
    for i in range(repeats):
        t0 = time.perf_counter()
        import_volume(as_volume(vol), tmp / f"import{i}.zarr")
        imp.append(time.perf_counter() - t0)
    size = nbytes / MiB
    up_s, down_s, imp_s = min(up), min(down), min(imp)
    rows = [["stream", "ours MiB/s", "raw gRPC MiB/s", "ratio"],
            ["upload, including the OME-Zarr import (streamed; Client.upload's default format)", f"{size / up_s:.0f}",
             f"{raw_up:.0f}", f"{size / up_s / raw_up:.2f}"],
            *([["upload of format raw (the server encodes)", f"{size / min(up_raw):.0f}", f"{raw_up:.0f}",
                f"{size / min(up_raw) / raw_up:.2f}"]] if up_raw else []),
            ["upload transfer: Client.upload's messages into the bare server", f"{client_up:.0f}", f"{raw_up:.0f}",
             f"{client_up / raw_up:.2f}"],
            ["import_volume alone (same array, in this process)", f"{size / imp_s:.0f}", f"{raw_up:.0f}",
             f"{size / imp_s / raw_up:.2f}"],
            ["download of level 0, Client.open (the stored chunks, decoded by the client)", f"{size / down_s:.0f}",
             f"{raw_down:.0f}", f"{size / down_s / raw_down:.2f}"]]
    print(f"volume {vol.shape} uint16, {size:.0f} MiB; best of {repeats}; load average "
          f"{open('/proc/loadavg').read().split()[0]}")
    return rows


# ------------------------------------------------------------------------------------------------------------------
# load
# ------------------------------------------------------------------------------------------------------------------
def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def _probe(address: str, stop, out) -> None:
    """A process of its own (as a cluster's health checker is): the health service every 20 ms until ``stop``;
    puts (latencies in seconds, failures) on ``out``."""
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    health: list[float] = []
    failures: list[str] = []
    with grpc.insecure_channel(address) as ch:
        stub = health_pb2_grpc.HealthStub(ch)
        while not stop.is_set():
            t0 = time.perf_counter()
            try:
                r = stub.Check(health_pb2.HealthCheckRequest(), timeout=5)
                assert r.status == health_pb2.HealthCheckResponse.SERVING
                health.append(time.perf_counter() - t0)
            except Exception as exc:  # noqa: BLE001 - counted as a failure
                failures.append(f"health: {exc}")
            time.sleep(0.02)
    out.put((health, failures))


def load(address: str, clients: int, tokens: dict[str, str], bad: list[str]) -> tuple[list[list[str]], dict]:
    """``clients`` concurrent pipelines, client i as user ``good{i}`` (``tokens``: user -> token); the users in
    ``bad`` (of ``stall``, ``huge``, ``burst`` and ``hog``) misbehave (see :class:`_Misbehaving`), each in a process
    of its own, until the good clients are done. The health prober runs in a process of its own too, so that its
    figures are the server's, not this process's threads'."""
    import multiprocessing

    from napari_unwind.client import Client
    from napari_unwind.datasets import tank_phantom

    t = tank_phantom(n_fish=2, seed=1, length=90)
    fish = t.fish[0]
    click = fish.centerline[len(fish.centerline) // 2]
    failures: list[str] = []
    mp = multiprocessing.get_context("spawn")
    stop, out = mp.Event(), mp.Queue()

    def one(i: int) -> float:
        with Client(address, token=tokens[f"good{i}"], progress=False, timeout=120) as c:
            t0 = time.perf_counter()
            vid = c.upload(t.volume, spacing=t.spacing, unit=t.unit, name=f"tank{i}").volume_id
            job = c.pipeline(vid, select=[click], output_name=f"fish{i}.zarr")
            assert job.result.volume_id
            return time.perf_counter() - t0

    procs = [mp.Process(target=_probe, args=(address, stop, out))]
    procs += [mp.Process(target=_misbehave, args=(address, tokens[u], u, stop, out)) for u in bad]
    for proc in procs:
        proc.start()
    answers: dict[str, dict[str, int]] = {}
    for _ in bad:  # every misbehaving user under way (the hog with its session) before the good clients start
        got = out.get(timeout=600)
        if isinstance(got, dict):  # stopped before it was ready
            answers.update(got)
    time.sleep(1.0)
    t_all = time.perf_counter()
    latencies: list[float] = []
    with ThreadPoolExecutor(max_workers=clients) as pool:
        for f in [pool.submit(one, i) for i in range(clients)]:
            try:
                latencies.append(f.result())
            except Exception as exc:  # noqa: BLE001
                failures.append(f"pipeline: {exc}")
    wall = time.perf_counter() - t_all
    stop.set()
    health: list[float] = []
    for _ in range(len(procs) - len(answers)):
        got = out.get(timeout=120)
        if isinstance(got, tuple):
            health, lost = got
            failures += lost
        else:
            answers.update(got)
    for proc in procs:
        proc.join(timeout=30)
    rows = [["measure", "value"],
            ["clients (each: upload + segment + select + skeleton + straighten)", str(clients)],
            ["pipelines succeeded", f"{len(latencies)} of {clients}"],
            ["pipeline latency p50 / p99 (s)", f"{_pct(latencies, 50):.1f} / {_pct(latencies, 99):.1f}"],
            ["throughput (pipelines / min)", f"{len(latencies) / wall * 60:.1f}"],
            ["wall time (s)", f"{wall:.1f}"],
            ["health checks during load", str(len(health))],
            ["health p50 / p99 / max (ms)", f"{_pct(health, 50) * 1e3:.1f} / {_pct(health, 99) * 1e3:.1f} / "
                                            f"{max(health) * 1e3:.1f}"]]
    for who, codes in sorted(answers.items()):
        rows.append([f"misbehaving user {who!r}: answers", ", ".join(f"{k} {v}" for k, v in sorted(codes.items()))])
    return rows, {"failures": failures}


def _misbehave(address: str, token: str, user: str, stop, out) -> None:
    """A process of its own: ``user``'s misbehaviour until ``stop``; puts ``user`` on ``out`` when it is ready to
    start (the hog has its session), then {user: {answer: count}} when it stops."""
    bad = _Misbehaving(address, token, stop, ready=lambda: out.put(user))
    try:
        getattr(bad, user)()
    except Exception as exc:  # noqa: BLE001 - reported with the answers
        bad.count(f"stopped: {type(exc).__name__}: {str(exc)[:200]}")
    out.put({user: bad.answers})


class _Misbehaving:
    """What the misbehaving users do, each until ``stop`` is set; the server's answers counted in ``answers``."""

    USERS = ("stall", "huge", "burst", "hog")

    def __init__(self, address: str, token: str, stop, ready: Callable[[], None]):
        import grpc

        self.address, self.token, self.stop, self.ready = address, token, stop, ready
        self.answers: dict[str, int] = {}
        self.meta = (("authorization", f"Bearer {token}"),)
        self._grpc = grpc

    def count(self, what: str) -> None:
        self.answers[what] = self.answers.get(what, 0) + 1

    def code(self, exc: BaseException) -> str:
        c = getattr(exc, "code", None)
        c = c() if callable(c) else c
        return getattr(c, "name", None) or str(c or type(exc).__name__)

    def stall(self) -> None:
        """Two uploads at a time that send their header, then nothing (the server's idle limit ends them; the
        second is over the limit of uploads in progress)."""
        from unwind_services._proto.unwind.v1 import common_pb2 as pb
        from unwind_services._proto.unwind.v1 import volume_pb2, volume_pb2_grpc

        with self._grpc.insecure_channel(self.address) as ch:
            stub = volume_pb2_grpc.VolumeServiceStub(ch)

            def messages():
                yield volume_pb2.UploadRequest(header=volume_pb2.UploadHeader(
                    name="stalled", shape=[256, 256, 256], dtype=pb.DTYPE_UINT8))
                self.stop.wait(600)

            self.ready()
            while not self.stop.is_set():
                calls = [stub.Upload.future(messages(), metadata=self.meta, timeout=600) for _ in range(2)]
                for call in calls:
                    try:
                        call.result()
                        self.count("OK")
                    except self._grpc.RpcError as exc:
                        self.count(self.code(exc))

    def huge(self) -> None:
        """Submits with parameters out of bounds, as fast as they are answered."""
        from unwind_services._proto.unwind.v1 import jobs_pb2, jobs_pb2_grpc, skeleton_pb2

        with self._grpc.insecure_channel(self.address) as ch:
            stub = jobs_pb2_grpc.JobServiceStub(ch)
            bad = [jobs_pb2.SubmitRequest(pipeline=jobs_pb2.PipelineRequest(
                       volume_id="v", skeleton=skeleton_pb2.SkeletonOptions(levels=2**31 - 1))),
                   jobs_pb2.SubmitRequest(pipeline=jobs_pb2.PipelineRequest(
                       volume_id="v", skeleton=skeleton_pb2.SkeletonOptions(smoothing_iterations=2**31 - 1,
                                                                            has_smoothing_iterations=True))),
                   jobs_pb2.SubmitRequest(pipeline=jobs_pb2.PipelineRequest(volume_id="v"),
                                          timeout_seconds=float("nan"))]
            k = 0
            self.ready()
            while not self.stop.is_set():
                try:
                    stub.Submit(bad[k % len(bad)], metadata=self.meta, timeout=30)
                    self.count("OK")
                except self._grpc.RpcError as exc:
                    self.count(self.code(exc))
                k += 1
                time.sleep(0.01)

    def burst(self) -> None:
        """Bursts of 200 concurrent listings, one after the other."""
        from unwind_services._proto.unwind.v1 import volume_pb2, volume_pb2_grpc

        with self._grpc.insecure_channel(self.address) as ch:
            stub = volume_pb2_grpc.VolumeServiceStub(ch)
            self.ready()
            while not self.stop.is_set():
                calls = [stub.List.future(volume_pb2.ListVolumesRequest(limit=1000), metadata=self.meta,
                                          timeout=30) for _ in range(200)]
                for call in calls:
                    try:
                        call.result()
                        self.count("OK")
                    except self._grpc.RpcError as exc:
                        self.count(self.code(exc))

    def hog(self) -> None:
        """Keeps its queue full of slow straight exports (2x finer than the scan, one slice per chunk)."""
        from napari_unwind.client import Client, RemoteError
        from napari_unwind.datasets import tank_phantom
        from unwind_services._proto.unwind.v1 import common_pb2 as pb

        t = tank_phantom(n_fish=2, seed=1, length=90)
        fish = t.fish[0]
        with Client(self.address, token=self.token, progress=False, timeout=120) as c:
            vid = c.upload(t.volume, spacing=t.spacing, unit=t.unit, name="hog").volume_id
            mid = c.upload(fish.mask.astype(np.uint8), spacing=t.spacing, unit=t.unit, name="mask").volume_id
            sid = c.skeleton(mid, volume_id=vid, head=fish.head, tail=fish.tail).result.session_id
            k = 0
            self.ready()
            while not self.stop.is_set():
                try:
                    c.straighten(vid, sid, wait=False, output_name=f"hog{k}.zarr", spacing=0.5, chunks=(1, 512, 512))
                    self.count("OK (queued)")
                    k += 1
                except RemoteError as exc:
                    self.count(exc.code)
                    self.stop.wait(1.0)
            for j in c.jobs():
                if j.state in (pb.JOB_STATE_QUEUED, pb.JOB_STATE_RUNNING):
                    c.cancel(j.id)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clients", type=int, default=16)
    p.add_argument("--mib", type=int, default=256, help="size of the transfer volume (MiB)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--workers", type=int, default=2, help="server job workers")
    p.add_argument("--misbehave", default="", metavar="USERS",
                   help="misbehaving users beside the clients: 'all' or some of stall,huge,burst,hog (comma-separated)")
    p.add_argument("--log-level", default="warning", help="the server's log level (info: upload timings)")
    p.add_argument("--raw-server", type=int, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.raw_server is not None:
        raw_server(args.raw_server)
        return 0
    tmp = Path(tempfile.mkdtemp(prefix="bench-services-"))
    server = raw = None
    serve = [sys.executable, "-m", "napari_unwind.cli", "serve", "--data-root", str(tmp / "data"), "--port", "0",
             "--workers", str(args.workers), "--log-level", args.log_level]
    stderr = None if args.log_level == "info" else subprocess.DEVNULL
    try:
        if args.mib:
            server, address = _start(serve + ["--max-jobs-per-user", "0"], stderr=stderr)
            raw, raw_address = _start([sys.executable, "-m", "benchmarks.bench_services", "--raw-server", "0"])
            print(f"## Transfer ({args.mib} MiB)\n")
            print(table(transfer(address, raw_address, args.mib, args.repeats, tmp)))
        if not args.clients:
            return 0
        bad = list(_Misbehaving.USERS) if args.misbehave == "all" else [u for u in args.misbehave.split(",") if u]
        if set(bad) - set(_Misbehaving.USERS):
            p.error(f"--misbehave: unknown users {sorted(set(bad) - set(_Misbehaving.USERS))}")
        # a server of its own with a tokens file and its default per-user limits, a user per client
        from unwind_services.auth import add_token

        if server is not None:
            _stop(server)
        users = [f"good{i}" for i in range(args.clients)] + bad
        tokens = {u: add_token(tmp / "tokens", u) for u in users}
        serve[serve.index(str(tmp / "data"))] = str(tmp / "data-users")
        server, address = _start(serve + ["--tokens", str(tmp / "tokens")], stderr=stderr)
        print(f"\n## Load ({args.clients} clients{f', misbehaving: {bad}' if bad else ''})\n")
        rows, extra = load(address, args.clients, tokens, bad)
        print(table(rows))
        if extra["failures"]:
            print("\nfailures:\n" + "\n".join(extra["failures"][:20]))
        return 1 if extra["failures"] else 0
    finally:
        for proc in (server, raw):
            if proc is not None:
                _stop(proc)
        shutil.rmtree(tmp, ignore_errors=True)

if __name__ == "__main__":
    sys.exit(main())
