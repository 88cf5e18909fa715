"""Measurements along the centreline (issue 24 item 2): the cost of a profile against straightening its inputs.

    .venv/bin/python -m benchmarks.bench_measure [--length 1000] [--repeat 3]

A phantom fish of arc length ``--length`` (no noise, no tube; one station per voxel), its true deformation and
mask. Baseline, measured in the same run: straightening the mask and the scan to the same straight grid
(``straighten(...).data.compute()``, what any profile must read). Then ``measure`` with the mask, with the mask and
the scan as a channel. Each after one warm-up call (numba compiles the resampling kernels once per process).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--length", type=float, default=1000.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    from napari_unwind.datasets import fish_phantom
    from napari_unwind.demo import true_deformation
    from napari_unwind.io import Volume
    from napari_unwind.measure import measure
    from napari_unwind.warp import straighten

    fish = fish_phantom(length=args.length, noise=0.0, tube=False, seed=1)
    d = true_deformation(fish)
    mask = Volume(fish.mask.astype(np.uint8), spacing=fish.spacing, unit=fish.unit)
    scan = Volume(fish.volume, spacing=fish.spacing, unit=fish.unit)
    measure(d, mask=mask, channels=scan)  # warm-up

    def best(fn):
        times = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return min(times), times

    base1, _ = best(lambda: straighten(mask, d, max_output=None).data.compute())
    base2, _ = best(lambda: [straighten(v, d, max_output=None).data.compute() for v in (mask, scan)])
    p = measure(d, mask=mask)
    one, t1 = best(lambda: measure(d, mask=mask))
    two, t2 = best(lambda: measure(d, mask=mask, channels=scan))
    print(f"fish {fish.volume.shape}, length {d.length:.0f}, {len(p)} stations, section "
          f"{d.output_shape()[1]} x {d.output_shape()[2]} pixels")
    print("| | straighten only (baseline) | measure | ratio |")
    print("|---|---|---|---|")
    print(f"| mask | {base1:.2f} s | {one:.2f} s | {one / base1:.2f}x |")
    print(f"| mask + scan channel | {base2:.2f} s | {two:.2f} s | {two / base2:.2f}x |")
    print(f"runs: {', '.join(f'{x:.2f}' for x in t1)} / {', '.join(f'{x:.2f}' for x in t2)} s; goal: a 1000-station "
          f"profile <= 2 s")


if __name__ == "__main__":
    main()
