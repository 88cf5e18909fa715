"""Zero clicks on hard tanks, end to end (issue 18, item 4): ``unwind run SCAN --all`` (``pipeline.run_all_iter``)
on tanks of ``datasets.hard_tank_phantom(seed)`` (3-12 fish, a wall cut into arcs, touching fish, fish cut by a
face), and for each fish of the ground truth whether a specimen straightened to the goals (status ``ok``)
follows it.

    .venv/bin/python -m benchmarks.bench_tanks 200 201 ... 211

A straightened specimen is matched to the fish whose true label holds most of 50 points along its centreline
(the session's deformation); a fish is straightened when such a specimen is ``ok``. Prints one line per tank and
the totals, every "ok" specimen with more than 1.4x its fish's voxels (two fish reported as one) and every "ok"
specimen whose deformation holds under 99 % of its fish's true voxels (a part of it reported whole).
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

MERGED = 1.4  # an "ok" specimen with more voxels than this times its fish's: two fish reported as one
SHORT = 0.99  # an "ok" specimen whose deformation holds less of its fish's true voxels: a part of it reported whole


def fish_of(deformation: dict, labels: np.ndarray) -> tuple[int, float]:
    """The true fish label most of the specimen's centreline lies in, and that share."""
    from napari_unwind.deformation import Deformation

    d = Deformation.from_dict(deformation)
    c, _ = d.sample(np.linspace(0, d.length, 50))
    vox = np.round((c - np.asarray(d.origin)) / np.asarray(d.spacing)).astype(int)
    lab = labels[tuple(np.clip(vox, 0, np.array(labels.shape) - 1).T)]
    vals, cnt = np.unique(lab[lab > 0], return_counts=True)
    return (int(vals[np.argmax(cnt)]), float(cnt.max() / len(lab))) if len(vals) else (0, 0.0)


def fish_held(deformation: dict, fish: np.ndarray) -> float:
    """The share of the fish's true voxels (bool array) that the deformation holds (inside its cage, unfolded)."""
    from napari_unwind.deformation import Deformation
    from napari_unwind.skeleton._foldfree import held_points

    d = Deformation.from_dict(deformation)
    pts = np.argwhere(fish) * np.asarray(d.spacing) + np.asarray(d.origin)
    held, _ = held_points(d, pts)
    return float(held.mean()) if len(pts) else 0.0


def one(seed: int, touching: bool = False) -> dict:
    from napari_unwind.datasets import hard_tank_phantom
    from napari_unwind.io import write_volume
    from napari_unwind.pipeline import run_all_iter
    from napari_unwind.progress import run

    tank = hard_tank_phantom(seed, touching=True) if touching else hard_tank_phantom(seed)
    with tempfile.TemporaryDirectory() as tmp:
        scan = write_volume(tank.volume, Path(tmp) / "tank.nrrd", spacing=tank.spacing, unit=tank.unit)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run(run_all_iter(scan, Path(tmp) / "out"))
        seconds = time.perf_counter() - t0
        rows = list(csv.DictReader(open(Path(tmp) / "out" / "specimens.csv", encoding="utf-8")))
        straightened: dict[int, list[str]] = {}
        merged = []
        short = []
        held: list[float] = []
        deformations: dict[int, list[dict]] = {}
        true_size = np.bincount(tank.labels.ravel(), minlength=tank.n_fish + 1)
        for r in rows:
            if r["session"]:
                deformation = json.loads((Path(tmp) / "out" / r["session"]).read_text())["deformation"]
                fish, _ = fish_of(deformation, tank.labels)
                straightened.setdefault(fish, []).append(r["status"])
                deformations.setdefault(fish, []).append(deformation)
                if r["status"] == "ok" and fish:
                    share = fish_held(deformation, tank.labels == fish)
                    held.append(share)
                    if share < SHORT:
                        short.append((r["specimen"], fish, share))
                if r["status"] == "ok" and int(r["voxels"]) > MERGED * true_size[fish]:
                    merged.append((r["specimen"], fish, int(r["voxels"]), int(true_size[fish])))
    ok = [f for f in range(1, tank.n_fish + 1) if "ok" in straightened.get(f, [])]
    return dict(seed=seed, tank=tank, ok=ok, statuses=[r["status"] for r in rows], seconds=seconds, merged=merged,
                short=short, held=held, deformations=deformations,
                missed=[f for f in range(1, tank.n_fish + 1) if f not in ok], by_fish=straightened)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("seeds", nargs="+", type=int)
    ap.add_argument("--touching", action="store_true", help="every tank packed to gap 0 (hard_tank_phantom(seed, "
                    "touching=True): fish against each other and against the wall's arcs)")
    args = ap.parse_args()
    total = found = merges = shorts = 0
    helds: list[float] = []
    for seed in args.seeds:
        r = one(seed, touching=args.touching)
        t = r["tank"]
        counts = {s: r["statuses"].count(s) for s in ("ok", "partial", "failed", "rejected")}
        print(f"seed {seed}: {t.n_fish} fish (touching {list(t.touching)}, cut by a face {len(t.cut_fish)}, wall cut "
              f"{t.wall_cut}): {len(r['ok'])}/{t.n_fish} straightened ok; rows {counts}; {r['seconds']:.0f} s"
              + (f"; missed fish {r['missed']} ({[r['by_fish'].get(f) for f in r['missed']]})" if r["missed"] else "")
              + "".join(f"; MERGED: specimen {n} ok with {v} voxels, its fish {f} has {tv}"
                        for n, f, v, tv in r["merged"])
              + "".join(f"; SHORT: specimen {n} ok holds {100 * h:.1f} % of its fish {f}" for n, f, h in r["short"]))
        total += t.n_fish
        found += len(r["ok"])
        merges += len(r["merged"])
        shorts += len(r["short"])
        helds += r["held"]
    print(f"\n{found}/{total} fish straightened ok over {len(args.seeds)} tanks; {merges} ok specimens that hold "
          f"more than {MERGED}x their fish's voxels (two fish as one); {shorts} ok specimens that hold less than "
          f"{100 * SHORT:.0f} % of their fish's true voxels (a part reported whole)")
    if helds:
        print("share of its fish's true voxels an ok specimen holds, min / p10 / median: "
              + " / ".join(f"{v:.4f}" for v in np.percentile(helds, [0, 10, 50])))


if __name__ == "__main__":
    main()
