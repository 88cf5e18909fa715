"""Start-up time of ``import napari_unwind``, ``unwind --version`` and ``unwind info`` (issue 18: <= 0.3 s).

    .venv/bin/python -m benchmarks.bench_startup                       # this tree
    .venv/bin/python -m benchmarks.bench_startup --before /tmp/head    # and another source tree, same run

Every command runs in a fresh interpreter, ``--runs`` times (default 5), and its median wall time is printed
with its ratios to two baselines measured in the same run: ``python -c pass`` (the interpreter alone) and
``python -c "import numpy"`` (the machine's speed and load change from run to run; the ratios change less).
``unwind info`` opens the shared aorta CT (gzip NRRD) and the same voxels written to a temporary folder by the
project's own writers (raw NRRD, NIfTI .nii.gz, TIFF, OME-Zarr); NRRD, NIfTI and OME-Zarr take the header-only
fast path (napari_unwind.io._headers, no numpy), TIFF the full reader. The run's ``PYTHONDONTWRITEBYTECODE`` is
printed: set, every module is compiled from source in every run (slower than an installed package, whose modules
are compiled once).
``--before DIR`` runs every command a second time with ``DIR`` (a folder holding another ``napari_unwind``, e.g.
``mkdir /tmp/head && git archive HEAD napari_unwind | tar -x -C /tmp/head``) first on ``sys.path``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks._util import table

AORTA = Path("/work/shared/data/aorta_ct.nrrd")

#: the ``unwind`` command without the console script's own overhead differing between trees
UNWIND = "import sys; from napari_unwind.cli import main; sys.exit(main())"


def wall(argv: list[str], *, runs: int, env: dict[str, str], cwd: str) -> float:
    """Median wall time of ``argv`` over ``runs`` runs (one untimed run first warms the file cache)."""
    subprocess.run(argv, capture_output=True, check=True, env=env, cwd=cwd)
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run(argv, capture_output=True, check=True, env=env, cwd=cwd)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def scans(folder: Path) -> dict[str, Path]:
    """The aorta CT and its voxels written by napari-unwind's writers in ``folder``."""
    from napari_unwind.io import open_volume, write_volume

    vol = open_volume(AORTA)
    out = {"NRRD gzip (aorta_ct.nrrd)": AORTA}
    for label, name, options in (("NRRD raw", "aorta_raw.nrrd", {"encoding": "raw"}),
                                 ("NIfTI gzip", "aorta.nii.gz", {}), ("TIFF", "aorta.tif", {}),
                                 ("OME-Zarr", "aorta.zarr", {})):
        out[label] = write_volume(vol, folder / name, **options)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--before", type=Path, default=None,
                        help="a folder holding another napari_unwind package, measured in the same run")
    args = parser.parse_args()
    py = sys.executable
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp:
        commands = [("python -c pass (baseline)", [py, "-c", "pass"]),
                    ("python -c 'import numpy' (baseline)", [py, "-c", "import numpy"]),
                    ("python -c 'import napari_unwind'", [py, "-c", "import napari_unwind"]),
                    ("unwind --version", [py, "-c", UNWIND, "--version"])]
        commands += [(f"unwind info: {label}", [py, "-c", UNWIND, "info", str(path)])
                     for label, path in scans(Path(tmp)).items()]
        trees = [("after", None)] + ([("before", args.before)] if args.before else [])
        env0 = dict(os.environ)
        results: dict[str, dict[str, float]] = {}
        for tree, where in trees:
            env = dict(env0)
            if where is not None:
                env["PYTHONPATH"] = os.pathsep.join([str(where.absolute()), env0.get("PYTHONPATH", "")])
            # run outside the source tree: ``python -c`` puts the working folder first on sys.path
            located = subprocess.run([py, "-c", "import napari_unwind; print(napari_unwind.__file__)"],
                                     capture_output=True, text=True, check=True, env=env, cwd=tmp).stdout.strip()
            if where is not None and not located.startswith(str(where.absolute())):
                raise SystemExit(f"--before {where}: napari_unwind came from {located}")
            print(f"{tree}: napari_unwind from {Path(located).parent}", flush=True)
            results[tree] = {label: wall(argv, runs=args.runs, env=env, cwd=tmp) for label, argv in commands}
    bare = {tree: r[commands[0][0]] for tree, r in results.items()}
    base = {tree: r[commands[1][0]] for tree, r in results.items()}
    header = ["command"] + [f"{tree}: s (x pass, x numpy)" for tree, _ in trees]
    rows = [header] + [[label] + [f"{results[tree][label]:.3f} ({results[tree][label] / bare[tree]:.2f}x, "
                                  f"{results[tree][label] / base[tree]:.2f}x)" for tree, _ in trees]
                       for label, _ in commands]
    print(f"median of {args.runs} runs, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}, "
          f"PYTHONDONTWRITEBYTECODE={os.environ.get('PYTHONDONTWRITEBYTECODE', '(unset)')}")
    print(table(rows))


if __name__ == "__main__":
    main()
