"""Join tree segmentation of a 256^3 tank: tree build, re-simplification, and ``skimage.morphology.max_tree``.

    .venv/bin/python -m benchmarks.bench_segmentation            # the recorded run (256^3, 12 fish)
    .venv/bin/python -m benchmarks.bench_segmentation --fish 4   # a quicker look

The volume is a phantom tank (``tank_phantom`` with 12 fish of length 235 and radius 14 voxels, noise sigma 40
grey values, slightly smoothed), cropped along axis0 and padded across with noisy background to 256^3 uint16.
Every job runs in a fresh process (wall time and peak RSS) in this invocation, on the same array:

- ours, default: ``join_tree(volume)`` (Gaussian sigma 1, 6-connectivity; the stages are timed), then
  ``tree.simplify(k)`` for k in 1, 5, 20, 100; the fish whose true mask matches one feature (Dice >= 0.9) at
  k = 20 are counted as a sanity check;
- ours, no smoothing: ``join_tree(volume, smooth=0)`` on the raw voxels, the like-for-like comparison;
- ``skimage.morphology.max_tree(volume, connectivity=1)`` (the max-tree / component tree of the raw voxels),
  given ``--maxtree-timeout`` seconds (its time grows faster than the voxel count: about 20 s at 96^3 here);
- both raw-voxel trees again on the central 128^3 crop, where max_tree finishes quickly, for a second ratio.

Targets: build <= 10 s, re-simplify <= 0.5 s. TopoAngler reported 87 s for loading plus contour tree.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._util import run_isolated, table

SIDE = 256

WARM = """
import numpy as np
from napari_unwind.segmentation import join_tree
join_tree(np.random.default_rng(0).random((6, 7, 8)).astype(np.float32), smooth=0).simplify(1)  # numba cache
"""

OURS = WARM + """
v = np.load(r"{vol}")
stages, last = {{}}, [time.perf_counter(), None]
def cb(p):
    now = time.perf_counter()
    if last[1] is not None:
        stages[last[1]] = stages.get(last[1], 0.0) + now - last[0]
    last[0], last[1] = now, p.stage
t0 = time.perf_counter()
tree = join_tree(v, smooth={smooth}, progress=cb)
result["seconds"] = time.perf_counter() - t0
cb(type("P", (), {{"stage": None}})())
result["stages"] = stages
result["n_maxima"] = tree.n_maxima
result["simplify"] = {{}}
for k in (1, 5, 20, 100):
    t = time.perf_counter()
    f = tree.simplify(k)
    result["simplify"][k] = time.perf_counter() - t
    if k == 20 and {check}:
        truth = np.load(r"{truth}")
        found = 0
        for i in range(1, int(truth.max()) + 1):
            m = truth == i
            ids, counts = np.unique(f.labels[m], return_counts=True)
            counts[ids == 0] = 0
            best = f.labels == ids[np.argmax(counts)]
            found += 2 * np.count_nonzero(best & m) / (best.sum() + m.sum()) >= 0.9
        result["fish_found"] = int(found)
        result["fish"] = int(truth.max())
"""

MAXTREE = """
import numpy as np
from skimage.morphology import max_tree
v = np.load(r"{vol}")
t0 = time.perf_counter()
parent, traverser = max_tree(v, connectivity=1)
result["seconds"] = time.perf_counter() - t0
flat, par = v.ravel(), parent.ravel()
result["nodes"] = int(np.count_nonzero(flat[par] != flat) + 1)  # canonical voxels: one per component-tree node
"""


MAKE = """
from pathlib import Path
from benchmarks.bench_segmentation import make_volume
make_volume(Path(r"{folder}"), {n_fish})
"""


def make_volume(folder: Path, n_fish: int) -> tuple[Path, Path]:
    """Write ``volume.npy`` and ``truth.npy`` (fish labels) into ``folder``."""
    from scipy import ndimage

    from napari_unwind.datasets import BACKGROUND, tank_phantom

    tank = tank_phantom(n_fish=n_fish, seed=3, length=235.0, body_radius=14.0, noise=40.0)
    rng = np.random.default_rng(0)
    noise = ndimage.gaussian_filter(rng.normal(0.0, 40.0, (SIDE,) * 3), 0.7)
    vol = np.clip(BACKGROUND + noise, 0, None).astype(np.uint16)
    truth = np.zeros((SIDE,) * 3, np.uint8)
    src = tuple(slice(0, min(n, SIDE)) for n in tank.shape)
    n0, n1, n2 = (min(n, SIDE) for n in tank.shape)
    o1, o2 = (SIDE - n1) // 2, (SIDE - n2) // 2
    dst = (slice(0, n0), slice(o1, o1 + n1), slice(o2, o2 + n2))
    vol[dst] = tank.volume[src]
    truth[dst] = tank.labels[src]
    np.save(folder / "volume.npy", vol)
    np.save(folder / "truth.npy", truth)
    return folder / "volume.npy", folder / "truth.npy"


def crop(vol: Path, side: int) -> Path:
    v = np.load(vol)
    lo = [(n - side) // 2 for n in v.shape]
    out = vol.with_name(f"crop{side}.npy")
    np.save(out, v[lo[0]:lo[0] + side, lo[1]:lo[1] + side, lo[2]:lo[2] + side])
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fish", type=int, default=12, help="fish in the tank (default 12)")
    ap.add_argument("--maxtree-timeout", type=float, default=3600.0,
                    help="seconds given to skimage's max_tree on the whole volume (default 3600)")
    ap.add_argument("--workdir", default=None, help="where to put the volume (default: a temporary folder)")
    args = ap.parse_args(argv)

    work = Path(args.workdir or tempfile.mkdtemp(prefix="unwind-bench-seg-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        t = time.perf_counter()
        # in a child, so that this process stays small: Linux children inherit the parent's peak RSS
        run_isolated(MAKE.format(folder=work, n_fish=args.fish))
        vol, truth = work / "volume.npy", work / "truth.npy"
        print(f"volume: {SIDE}^3 uint16 tank of {args.fish} fish (made in {time.perf_counter() - t:.0f} s)",
              flush=True)
        ours = run_isolated(OURS.format(vol=vol, truth=truth, smooth=1.0, check=True))
        raw = run_isolated(OURS.format(vol=vol, truth=truth, smooth=0.0, check=False))
        print(f"ours: {ours['seconds']:.2f} s (smooth 1), {raw['seconds']:.2f} s (raw)", flush=True)
        small = crop(vol, 128)
        raw_small = run_isolated(OURS.format(vol=small, truth=truth, smooth=0.0, check=False))
        skm_small = run_isolated(MAXTREE.format(vol=small))
        try:
            skm = run_isolated(MAXTREE.format(vol=vol), timeout=args.maxtree_timeout)
        except subprocess.TimeoutExpired:
            skm = None
    finally:
        if args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)

    st = ours["stages"]
    rows = [["job", "seconds", "peak RSS (MB)", "notes"]]
    rows.append([f"join_tree {SIDE}^3, smooth=1 (default)", f"{ours['seconds']:.2f}", f"{ours['peak_rss_mb']:.0f}",
                 f"{ours['n_maxima']} maxima; smooth {st.get('smooth', 0):.2f} s, sort {st.get('sort', 0):.2f} s, "
                 f"sweep {st.get('sweep', 0):.2f} s, prune {st.get('prune', 0):.2f} s"])
    for k, s in ours["simplify"].items():
        note = f"{ours['fish_found']} of {ours['fish']} fish matched (Dice >= 0.9)" if str(k) == "20" else ""
        rows.append([f"simplify(k={k})", f"{s:.3f}", "", note])
    rows.append([f"join_tree {SIDE}^3, smooth=0 (raw voxels)", f"{raw['seconds']:.2f}", f"{raw['peak_rss_mb']:.0f}",
                 f"{raw['n_maxima']} maxima"])
    if skm is None:
        limit = args.maxtree_timeout
        rows.append([f"skimage max_tree {SIDE}^3 (raw voxels)", f"> {limit:.0f}", "",
                     f"stopped after {limit:.0f} s; ratio > {limit / raw['seconds']:.0f}"])
    else:
        rows.append([f"skimage max_tree {SIDE}^3 (raw voxels)", f"{skm['seconds']:.2f}", f"{skm['peak_rss_mb']:.0f}",
                     f"{skm['nodes']} nodes; max_tree / join_tree(smooth=0) = {skm['seconds'] / raw['seconds']:.0f}"])
    rows.append(["join_tree 128^3 crop, smooth=0", f"{raw_small['seconds']:.2f}", f"{raw_small['peak_rss_mb']:.0f}",
                 f"{raw_small['n_maxima']} maxima"])
    ratio = skm_small["seconds"] / raw_small["seconds"]
    rows.append(["skimage max_tree 128^3 crop", f"{skm_small['seconds']:.2f}", f"{skm_small['peak_rss_mb']:.0f}",
                 f"{skm_small['nodes']} nodes; max_tree / join_tree = {ratio:.0f}"])
    print(table(rows))
    ok_build = ours["seconds"] <= 10.0
    ok_simplify = max(ours["simplify"].values()) <= 0.5
    print(f"targets: build <= 10 s {'met' if ok_build else 'MISSED'}; "
          f"re-simplify <= 0.5 s {'met' if ok_simplify else 'MISSED'}")


if __name__ == "__main__":
    main()
