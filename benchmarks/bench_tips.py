"""How far the suggested ends stop short of a specimen's tips, along its true centreline (issue 18).

    .venv/bin/python benchmarks/bench_tips.py [--hard N] [--tanks N]

For each hard phantom (``hard_fish_phantom(seed)``, seeds 0..N-1) and each fish of the dense tanks
(``tank_phantom(n_fish=3, seed, wall_value=3000, wall_thickness=6, wall_noise=600)``, seeds 0..N-1), the suggested
head and tail (``suggest_endpoints`` on the true mask) are placed on the phantom's centreline by their nearest
sample; the shortfall is the arclength between that and the mask's own first / last sample, in voxels of the
coarsest axis. Prints p50 / p90 / max per family and end.
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
from scipy.spatial import cKDTree

from napari_unwind.datasets import hard_fish_phantom, tank_phantom
from napari_unwind.skeleton import suggest_endpoints


def shortfall(ph, mask, spacing, volume) -> tuple[float, float]:
    sp = np.asarray(spacing, dtype=float) * np.ones(3)
    tree = cKDTree(ph.centerline_physical)
    s_mask = ph.arclength[tree.query(np.argwhere(mask) * sp)[1]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        head, tail = suggest_endpoints(mask, spacing=sp, volume=volume)
    s_head, s_tail = (ph.arclength[tree.query(p * sp)[1]] for p in (head, tail))
    return float(s_head - s_mask.min()) / sp.max(), float(s_mask.max() - s_tail) / sp.max()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hard", type=int, default=30, help="hard phantoms, seeds 0..N-1 (default 30)")
    ap.add_argument("--tanks", type=int, default=8, help="dense tanks of 3 fish, seeds 0..N-1 (default 8)")
    args = ap.parse_args()
    rows = {"hard": [], "tank": []}
    for seed in range(args.hard):
        ph = hard_fish_phantom(seed)
        rows["hard"].append(shortfall(ph, ph.mask, ph.spacing, ph.volume))
    for seed in range(args.tanks):
        tank = tank_phantom(n_fish=3, seed=seed, wall_value=3000, wall_thickness=6, wall_noise=600)
        for i, ph in enumerate(tank.fish):
            rows["tank"].append(shortfall(ph, tank.labels == i + 1, tank.spacing, tank.volume))
    for family, r in rows.items():
        a = np.asarray(r)
        for j, end in enumerate(("head", "tail")):
            p = np.percentile(a[:, j], [50, 90, 100])
            print(f"{family:5s} {end}: n {len(a)}, shortfall p50 {p[0]:.1f}, p90 {p[1]:.1f}, max {p[2]:.1f} voxels")


if __name__ == "__main__":
    main()
