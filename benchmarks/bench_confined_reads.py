"""What the server's per-read confinement costs: reading whole scans opened under ``confined_reads`` (issue 22).

    .venv/bin/python -m benchmarks.bench_confined_reads                          # this tree
    .venv/bin/python -m benchmarks.bench_confined_reads --before /tmp/head      # and another tree, same run

A scan opened inside :func:`napari_unwind.io._files.confined_reads` (as the server opens every volume) opens each
file again at each read and checks where the opened descriptor lies. This writes, with the project's own writers,
a zlib-compressed TIFF, a DICOM series, a PNG slice stack and a gzip NIfTI of the same voxels, then reads each
whole (``np.asarray(volume.data)``, dask's threads) opened plainly and opened confined, ``--runs`` times (median,
one untimed read first) in a fresh interpreter per tree. ``--before DIR`` measures another tree (a folder holding
another ``napari_unwind``, e.g. ``mkdir /tmp/head && git archive HEAD napari_unwind | tar -x -C /tmp/head``) in the
same run on the same files; the ratios after/before and confined/plain are printed beside the seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks._util import table

CHILD = r"""
import json, os, statistics, sys, time
import numpy as np
from napari_unwind.io import open_volume
from napari_unwind.io._files import ReadConfinement, confined_reads

folder, runs = sys.argv[1], int(sys.argv[2])
confine = ReadConfinement(os.path.realpath(folder), "", "the benchmark's folder")
out = {}
for label, path in json.loads(sys.argv[3]).items():
    for how in ("plain", "confined"):
        with confined_reads(confine if how == "confined" else None):
            vol = open_volume(path)
        np.asarray(vol.data)  # warms the file cache (and builds dask's graph)
        times = []
        for _ in range(runs):
            t0 = time.perf_counter()
            np.asarray(vol.data)
            times.append(time.perf_counter() - t0)
        out[f"{label}|{how}"] = statistics.median(times)
print(json.dumps(out))
"""


def scans(folder: Path, shape: tuple[int, int, int]) -> dict[str, str]:
    """The same uint16 voxels in each format whose reads the confinement checks file by file."""
    from napari_unwind.io import write_volume

    rng = np.random.default_rng(0)
    voxels = (rng.integers(0, 4096, size=shape, dtype=np.uint16) // 64 * 64).astype(np.uint16)  # compressible
    out = {}
    for label, name, options in (("TIFF zlib", "scan.tif", {"compression": "zlib"}),
                                 ("DICOM series", "dicom", {}),
                                 ("PNG slice stack", "stack", {"format": "stack"}),
                                 ("NIfTI .nii.gz", "scan.nii.gz", {})):
        fmt = "dicom" if label.startswith("DICOM") else None
        options = {"format": fmt, **options}
        out[label] = str(write_volume(voxels, folder / name, spacing=(1, 1, 1), **options))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--planes", type=int, default=128)
    parser.add_argument("--before", type=Path, default=None,
                        help="a folder holding another napari_unwind package, measured in the same run")
    args = parser.parse_args()
    shape = (args.planes, 512, 512)
    trees = [("after", None)] + ([("before", args.before)] if args.before else [])
    results: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="bench-confined-") as tmp:
        files = scans(Path(tmp), shape)
        for tree, where in trees:
            env = dict(os.environ)
            if where is not None:
                env["PYTHONPATH"] = os.pathsep.join([str(where.absolute()), env.get("PYTHONPATH", "")])
            code = f"import napari_unwind, sys; print(napari_unwind.__file__, file=sys.stderr)\n{CHILD}"
            r = subprocess.run([sys.executable, "-c", code, tmp, str(args.runs), json.dumps(files)],
                               capture_output=True, text=True, env=env, cwd=tmp)
            if r.returncode:
                raise SystemExit(r.stderr[-3000:])
            located = r.stderr.strip().splitlines()[0]
            if where is not None and not located.startswith(str(where.absolute())):
                raise SystemExit(f"--before {where}: napari_unwind came from {located}")
            print(f"{tree}: napari_unwind from {Path(located).parent}", flush=True)
            results[tree] = json.loads(r.stdout.strip().splitlines()[-1])
    header = ["scan (uint16 " + " x ".join(map(str, shape)) + ")"]
    for tree, _ in trees:
        header += [f"{tree}: plain s", f"{tree}: confined s (x plain)"]
    if args.before:
        header += ["confined after / before"]
    rows = [header]
    for label in files:
        row = [label]
        for tree, _ in trees:
            plain, conf = results[tree][f"{label}|plain"], results[tree][f"{label}|confined"]
            row += [f"{plain:.3f}", f"{conf:.3f} ({conf / plain:.2f}x)"]
        if args.before:
            row.append(f"{results['after'][f'{label}|confined'] / results['before'][f'{label}|confined']:.2f}x")
        rows.append(row)
    print(f"median of {args.runs} whole reads, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
    print(table(rows))


if __name__ == "__main__":
    main()
