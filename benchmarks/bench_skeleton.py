"""Skeleton solve of a 256^3 mask: time per stage, against the paper's settings in the same run.

    .venv/bin/python -m benchmarks.bench_skeleton              # the recorded run
    .venv/bin/python -m benchmarks.bench_skeleton --repeat 1   # a quicker look

The mask is a fish phantom (``fish_phantom``: s-bend, length 240, body radius 22 voxels, twisted by 90 degrees)
in a 256^3 volume, with its uint16 scan for the twist estimate. Each job runs in a fresh process (wall time of
the solve alone, after the imports, and peak RSS):

- ours: ``estimate_deformation_iter(mask, (head, tail), spacing, volume=scan)`` at its defaults (mask box-averaged
  to at most 128 voxels a side, the deterministic lattice tet mesh, arclength-spaced levels, Taubin smoothing,
  twist, cage); every stage timed; run ``--repeat`` times, each in a fresh process, and the deformations'
  digests compared (they must be identical);
- the previous default, in the same run: the same but ``tet_mesher="ftetwild"`` (marching cubes decimated to
  3000 triangles, fTetWild sized for speed), whose mesh varies from run to run;
- the paper's settings through the same code: working resolution 256 (TopoAngler's size), the full marching-cubes
  surface, pytetwild's own defaults (edge_length_fac 0.05, epsilon 1e-3, 80 iterations), levels uniform in u,
  the paper's Laplacian smoothing.

Both report the centreline's RMS distance from the true one and the arclength error. Target: <= 5 s for ours.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from benchmarks._util import run_isolated, table

JOB = """
import hashlib, json, time, warnings
import numpy as np
from scipy.spatial import cKDTree
from napari_unwind.progress import run
from napari_unwind.skeleton import estimate_deformation_iter
d = np.load({path!r})
mask, scan, truth = d["mask"], d["scan"], d["centerline"]
head, tail = d["head"], d["tail"]
warnings.simplefilter("ignore")
t0 = time.perf_counter()
res = run(estimate_deformation_iter(mask, (head, tail), spacing=(1.0, 1.0, 1.0), volume=scan, **{options}))
result["seconds"] = time.perf_counter() - t0
dfm = res.deformation
c, _ = dfm.sample(np.linspace(0, dfm.length, 1000))
dist, _ = cKDTree(truth).query(c)
result.update(timings=res.timings, mesh=res.mesh["parts"][0], keyframes=len(dfm.keyframes),
              rms=float(np.sqrt((dist ** 2).mean())), length=float(dfm.length),
              digest=hashlib.sha256(json.dumps(dfm.to_dict(), sort_keys=True).encode()).hexdigest()[:16])
"""

PAPER = dict(max_side=256, max_triangles=None, mesher=dict(edge_length_fac=0.05, epsilon=1e-3, max_iterations=80),
             level_spacing="uniform", smoothing="laplacian", estimate_twist=False, end_window_factor=0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3, help="runs of our default (the fastest is reported)")
    ap.add_argument("--skip-paper", action="store_true", help="do not run the paper's settings")
    args = ap.parse_args()

    from napari_unwind.datasets import fish_phantom

    ph = fish_phantom(length=240, body_radius=22, shape=(256, 256, 256), curve="s-bend", twist=np.pi / 2, seed=3)
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "fish.npz")
        np.savez(path, mask=ph.mask, scan=ph.volume, centerline=ph.centerline, head=ph.head, tail=ph.tail)
        print(f"mask {ph.mask.shape}, {int(ph.mask.sum())} voxels, length {ph.length:.1f}")
        runs = [run_isolated(JOB.format(path=path, options="{}")) for _ in range(args.repeat)]
        ours = min(runs, key=lambda r: r["seconds"])
        ftw = [run_isolated(JOB.format(path=path, options=repr(dict(tet_mesher="ftetwild"))))
               for _ in range(args.repeat)]
        prev = min(ftw, key=lambda r: r["seconds"])
        paper = None if args.skip_paper else run_isolated(JOB.format(path=path, options=repr(PAPER)), timeout=3600)

    rows = [["job", "solve s", "tet mesh s", "triangles", "tets", "keyframes", "RMS vox", "length err %",
             "peak RSS MB"]]
    for name, r in (("ours (defaults)", ours), ("fTetWild (previous default)", prev), ("paper settings", paper)):
        if r is None:
            continue
        rows.append([name, f"{r['seconds']:.2f}", f"{r['timings']['tet mesh']:.2f}", str(r["mesh"]["triangles"]),
                     str(r["mesh"]["tets"]), str(r["keyframes"]), f"{r['rms']:.2f}",
                     f"{100 * (r['length'] / ph.length - 1):+.2f}", f"{r['peak_rss_mb']:.0f}"])
    print(table(rows))
    print()
    print(table([["stage", "seconds"], *[[k, f"{v:.3f}"] for k, v in ours["timings"].items()]]))
    print(f"\ndeterminism: {len({r['digest'] for r in runs})} distinct deformation(s) in {len(runs)} runs of ours, "
          f"{len({r['digest'] for r in ftw})} in {len(ftw)} runs with fTetWild")
    print(f"ours / previous default (fTetWild), solve time: {ours['seconds'] / prev['seconds']:.2f}x")
    if paper is not None:
        print(f"\nspeed-up over the paper's settings: {paper['seconds'] / ours['seconds']:.1f}x "
              f"(target: ours <= 5 s: {'met' if ours['seconds'] <= 5 else 'NOT met'})")


if __name__ == "__main__":
    main()
