"""Where the join tree's noise rule puts each fish and the wall's noise maxima, on hard_tank_phantom seeds.

    .venv/bin/python benchmarks/bench_noise_rule.py 106 208 [--touching]

For each fish of the ground truth: its most persistent branch (the maximum inside its label), that persistence in
units of the global sigma and of the 9^3 windows' sigmas around the maximum and the saddle (the rule's inputs,
``_jointree.noise_levels``), the saddle value, whether the branch is significant and kept among run --all's k
features. For the wall: the noise maxima (every branch whose maximum lies in the wall, but the most persistent of
each arc) with the highest persistence per own-window sigma. A rule that keeps a fish must keep its ratios above
the wall's.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from napari_unwind.datasets import hard_tank_phantom
from napari_unwind.segmentation import join_tree
from napari_unwind.segmentation._common import MAX_FEATURES
from napari_unwind.segmentation._jointree import _NOISE_WINDOW, _robust_sigma


def window_sigma(residual: np.ndarray, voxel: int) -> float:
    c = np.unravel_index(voxel, residual.shape)
    r = _NOISE_WINDOW
    return float(_robust_sigma(residual[tuple(slice(max(0, i - r), i + r + 1) for i in c)].ravel()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("seeds", nargs="+", type=int)
    ap.add_argument("--touching", action="store_true", help="hard_tank_phantom(seed, touching=True): gap 0")
    args = ap.parse_args()
    for seed in args.seeds:
        tank = hard_tank_phantom(seed, touching=True) if args.touching else hard_tank_phantom(seed)
        tree = join_tree(tank.volume)
        k = int(min(MAX_FEATURES, max(1, int(tree.significant.sum())), tree.n_maxima))
        kept = set(tree.prune_order[len(tree.prune_order) - (k - 1):].tolist()) if k > 1 else set()
        res = tree.values - ndimage.uniform_filter(tree.values, 3, mode="nearest")
        pers = (tree.birth - tree.death).astype(float)
        g = tree.noise
        lab, wall = tank.labels.ravel(), tank.wall.ravel()
        arcs = ndimage.label(tank.wall)[0].ravel()
        print(f"{tank}: global sigma {g:.1f}, k {k}")
        best: dict[int, int] = {}
        arc_top: dict[int, int] = {}
        for b in range(tree.n_maxima):
            f, a = int(lab[tree.max_voxel[b]]), int(arcs[tree.max_voxel[b]])
            if b and f and (f not in best or pers[b] > pers[best[f]]):
                best[f] = b
            if a and (a not in arc_top or pers[b] > pers[arc_top[a]]):
                arc_top[a] = b
        for f, b in sorted(best.items()):
            sm, ss = window_sigma(res, tree.max_voxel[b]), window_sigma(res, tree.saddle_voxel[b])
            print(f"  fish {f:2d}: branch {b} persistence {pers[b]:.0f} (birth {tree.birth[b]:.0f}, saddle "
                  f"{tree.death[b]:.0f}) = {pers[b] / g:.1f} global, {pers[b] / sm:.1f} max-window ({sm:.0f}), "
                  f"{pers[b] / ss:.1f} saddle-window ({ss:.0f}) sigmas; significant {bool(tree.significant[b])}, "
                  f"kept {b in kept}")
        noise = [b for b in range(1, tree.n_maxima) if wall[tree.max_voxel[b]] and b not in arc_top.values()]
        ratios = sorted(((pers[b] / window_sigma(res, tree.max_voxel[b]), b) for b in noise), reverse=True)[:3]
        print("  wall noise maxima, highest persistence / max-window sigma: "
              + ", ".join(f"{r:.1f} (branch {b}, {pers[b] / g:.1f} global)" for r, b in ratios))


if __name__ == "__main__":
    main()
