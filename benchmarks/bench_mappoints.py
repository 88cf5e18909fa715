"""MapPoints of many points through a real server (issue 22, item 2): time and the server's memory growth.

    .venv/bin/python -m benchmarks.bench_mappoints [--points 2000000] [--workdir DIR]

A server in a child process (``unwind serve``, one worker), a session from a skeleton job on the tank phantom's
first fish; then ``Client.map_points`` with N points spread over the scan's box (MapPointsStream, batches of
50000). Reports the call's seconds and the server process's RSS before, its peak (``VmHWM``) and RSS after,
read from /proc.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "services"))


def _mib(pid: int, field: str) -> float:
    for line in open(f"/proc/{pid}/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise KeyError(field)


def main(argv: list[str] | None = None) -> int:
    from _servers import ServerProcess

    from napari_unwind.client import Client
    from napari_unwind.datasets import tank_phantom

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--points", type=int, default=2_000_000)
    p.add_argument("--workdir", default=None)
    args = p.parse_args(argv)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench-mappoints-"))
    t = tank_phantom(n_fish=2, seed=1, length=90)
    fish = t.fish[0]
    srv = ServerProcess(work / "data", "--workers", "1")
    try:
        with Client(srv.address, progress=False) as c:
            mid = c.upload(fish.mask.astype(np.uint8), spacing=t.spacing, unit=t.unit, name="mask").volume_id
            sid = c.skeleton(mid, head=fish.head, tail=fish.tail).result.session_id
            pts = np.random.default_rng(0).uniform(0, np.asarray(t.volume.shape) - 1, size=(args.points, 3))
            c.map_points(sid, pts[:1000])  # warm the compiled map
            pid = srv.proc.pid
            before, hwm0 = _mib(pid, "VmRSS"), _mib(pid, "VmHWM")
            t0 = time.perf_counter()
            out = c.map_points(sid, pts, timeout=3600)
            dt = time.perf_counter() - t0
            peak, after = _mib(pid, "VmHWM"), _mib(pid, "VmRSS")
        inside = float(np.isfinite(out[:, 0]).mean())
        print(f"{args.points} points ({100 * inside:.1f} % inside the cage): {dt:.1f} s "
              f"({args.points / dt / 1e3:.0f} k points/s)")
        print(f"server RSS before {before:.0f} MiB, peak {peak:.0f} MiB (peak before the call {hwm0:.0f}), "
              f"after {after:.0f} MiB: peak growth {max(0.0, peak - before):.0f} MiB")
    finally:
        srv.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
