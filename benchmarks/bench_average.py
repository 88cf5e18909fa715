"""The average straight specimen (issue 24 item 3): its time against reading the batch.

    .venv/bin/python -m benchmarks.bench_average [--count 20] [--side 128]

A seeded family of straight fish (tests/test_average.py's template, each scaled 0.85-1.15, rolled, shifted, its own
gain; about ``side`` stations long and ``side / 3`` across, float32), written as OME-Zarr. Baseline in the same run:
reading every volume into memory. Goal: the average within 2x the time of reading them. Best of ``--repeat``
each, alternating, after one warm-up average of two small specimens (numba loads its compiled kernels once per
process).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--count", type=int, default=20)
    ap.add_argument("--side", type=int, default=128)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--scheduler", default=None, help="run the average on this dask scheduler (e.g. synchronous)")
    args = ap.parse_args()
    import test_average as fam

    from napari_unwind.average import average
    from napari_unwind.io import open_volume, write_volume

    fam.NS0, fam.NY0 = args.side, args.side // 3
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for i in range(args.count):
            v = fam.member(rng.uniform(0.85, 1.15), rng.uniform(-40, 40), rng.uniform(-3, 3, 2),
                           rng.uniform(0.5, 2), rng.uniform(0, 300), rng)
            paths.append(write_volume(v, Path(tmp) / f"fish{i:02d}.ome.zarr"))
        voxels = sum(int(np.prod(open_volume(p).shape)) for p in paths)
        average([str(p) for p in paths[:2]], scheduler=args.scheduler)           # warm-up
        read, avg = [], []
        for _ in range(args.repeat):
            t = time.perf_counter()
            for p in paths:
                np.asarray(open_volume(p).data)
            read.append(time.perf_counter() - t)
            t = time.perf_counter()
            res = average([str(p) for p in paths], scheduler=args.scheduler)
            avg.append(time.perf_counter() - t)
        read, avg = min(read), min(avg)
    print(f"{args.count} straight fish, {voxels / 1e6:.0f} M voxels in all, average {res.mean.shape}")
    print("| reading them (baseline) | average | ratio |")
    print("|---|---|---|")
    print(f"| {read:.2f} s | {avg:.2f} s | {avg / read:.1f}x |")


if __name__ == "__main__":
    main()
