"""Import throughput and peak memory: ``import_volume`` of a slice stack against a naive baseline.

    .venv/bin/python -m benchmarks.bench_import --gib 4.0        # the recorded run (>= 4 GB stack)
    .venv/bin/python -m benchmarks.bench_import --gib 0.25       # a quick look

Both jobs run in fresh processes on the same stack of uint16 TIFF slices, in the same invocation:
- baseline: ``tifffile.imread`` of every slice into one array, then one ``zarr`` v3 array write (zstd, 128^3
  chunks), level 0 only; memory grows with the scan.
- napari-unwind: ``import_volume`` (lazy stack reader, slab-streamed OME-Zarr writing, full pyramid).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._util import run_isolated, table


def make_stack(folder: Path, n_slices: int, side: int) -> None:
    import tifffile

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:side, :side]
    disc = ((yy - side / 2) ** 2 + (xx - side / 2) ** 2 < (0.4 * side) ** 2).astype(np.uint16) * 1000
    noise = rng.integers(0, 200, size=(side, side), dtype=np.uint16)
    for i in range(n_slices):
        tifffile.imwrite(folder / f"slice_{i:05d}.tif", disc + np.roll(noise, i, axis=1))


BASELINE = """
import glob, tifffile, zarr
from zarr.codecs import BloscCodec
files = sorted(glob.glob(r"{src}/*.tif"))
t0 = time.perf_counter()
data = tifffile.imread(files)
z = zarr.create_array(store=r"{dst}", shape=data.shape, chunks=(128, 128, 128), dtype=data.dtype,
                      compressors=BloscCodec(cname="zstd", clevel=3, shuffle="shuffle"), zarr_format=3)
z[:] = data
result["seconds"] = time.perf_counter() - t0
result["nbytes"] = data.nbytes
"""

OURS = """
from napari_unwind import import_volume
t0 = time.perf_counter()
v = import_volume(r"{src}", r"{dst}", spacing=(1, 1, 1))
result["seconds"] = time.perf_counter() - t0
result["nbytes"] = v.nbytes
result["levels"] = len(v.levels)
"""


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gib", type=float, default=4.0, help="stack size in GiB (default 4)")
    ap.add_argument("--side", type=int, default=1024, help="slice side in pixels (default 1024)")
    ap.add_argument("--workdir", default=None, help="where to put the stack (default: a temporary folder)")
    args = ap.parse_args(argv)

    n_slices = max(1, int(args.gib * 2**30 / (args.side * args.side * 2)))
    work = Path(args.workdir or tempfile.mkdtemp(prefix="unwind-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    src = work / "stack"
    try:
        src.mkdir(exist_ok=True)
        t = time.perf_counter()
        make_stack(src, n_slices, args.side)
        gib = n_slices * args.side * args.side * 2 / 2**30
        print(f"stack: {n_slices} slices of {args.side}x{args.side} uint16 = {gib:.2f} GiB "
              f"(made in {time.perf_counter() - t:.0f} s)")
        base = run_isolated(BASELINE.format(src=src, dst=work / "baseline.zarr"))
        shutil.rmtree(work / "baseline.zarr", ignore_errors=True)
        ours = run_isolated(OURS.format(src=src, dst=work / "ours.zarr"))
        shutil.rmtree(work / "ours.zarr", ignore_errors=True)
    finally:
        if args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)

    def mbs(r: dict) -> float:
        return r["nbytes"] / r["seconds"] / 2**20

    rows = [
        ["job", "seconds", "MiB/s", "peak RSS (MiB)", "peak RSS / scan size"],
        ["baseline: tifffile.imread + zarr write (level 0 only)", f"{base['seconds']:.1f}", f"{mbs(base):.0f}",
         f"{base['peak_rss_mb']:.0f}", f"{base['peak_rss_mb'] / (gib * 1024):.2f}"],
        [f"napari-unwind import_volume ({ours['levels']} levels)", f"{ours['seconds']:.1f}", f"{mbs(ours):.0f}",
         f"{ours['peak_rss_mb']:.0f}", f"{ours['peak_rss_mb'] / (gib * 1024):.2f}"],
    ]
    print(table(rows))
    print(f"throughput ratio (ours / baseline): {mbs(ours) / mbs(base):.2f}")
    print(f"peak RSS ratio (ours / baseline):   {ours['peak_rss_mb'] / base['peak_rss_mb']:.3f}")


if __name__ == "__main__":
    main()
