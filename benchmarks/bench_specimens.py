"""Per-case recall and Dice of segmentation.candidates on hard_tank_phantom seeds (run --all's k features).

Usage: .venv/bin/python benchmarks/bench_specimens.py [--touching] SEED [SEED ...]   (default seeds 0..7)

--touching: hard_tank_phantom(seed, touching=True), every tank packed to gap 0 (fish against each other and
against the wall's arcs).
"""
import time

import numpy as np

from napari_unwind.datasets import hard_tank_phantom
from napari_unwind.segmentation import candidates, join_tree
from napari_unwind.segmentation._common import MAX_FEATURES


def dice(a, b):
    return 2.0 * np.count_nonzero(a & b) / max(np.count_nonzero(a) + np.count_nonzero(b), 1)

def run(seed, verbose=False, touching=False):
    t0 = time.time()
    h = hard_tank_phantom(seed, touching=True) if touching else hard_tank_phantom(seed)
    tree = join_tree(h.volume)
    k = int(min(MAX_FEATURES, max(1, int(tree.significant.sum())), tree.n_maxima))
    f = tree.simplify(k)
    t1 = time.time()
    cands = candidates(f)
    t2 = time.time()
    spec = [c for c in cands if c.status == "specimen"]
    masks = [c.working_mask(f) for c in spec]
    found, dices, cover = 0, [], []
    used = {}
    for i in range(1, h.n_fish + 1):
        fish = h.labels == i
        d = [dice(m, fish) for m in masks]
        j = int(np.argmax(d)) if d else -1
        best = d[j] if d else 0.0
        dices.append(best)
        if best >= 0.9:
            found += 1
            used.setdefault(j, []).append(i)
        cover.append(np.count_nonzero(masks[j] & fish) / np.count_nonzero(fish) if d else 0)
    wall_specs = sum(1 for m in masks if np.count_nonzero(m & h.wall) > 0.5 * np.count_nonzero(m))
    extra = len(spec) - len(used)
    print(f"seed {seed:3d} n={h.n_fish:2d} touch={len(h.touching)} wallcut={int(h.wall_cut)} cut={len(h.cut_fish):2d} "
          f"k={k:3d} recall {found}/{h.n_fish} specimens={len(spec):2d} wall-specimens={wall_specs} extra={extra} "
          f"minDice {min(dices):.3f} medDice {np.median(dices):.3f} minCover {min(cover):.2f} "
          f"[{t1-t0:.1f}+{t2-t1:.1f} s]", flush=True)
    if verbose:
        for c in cands:
            print("   ", c.name, c.status, c.reason, c.stats.voxel_count, round(c.stats.elongation, 2))
    return found, h.n_fish, dices

if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seeds", nargs="*", type=int, default=list(range(8)), help="hard_tank_phantom seeds (0..7)")
    parser.add_argument("--touching", action="store_true", help="every tank packed to gap 0")
    args = parser.parse_args()
    touching, seeds = args.touching, args.seeds
    tot = n = 0
    alld = []
    for s in seeds:
        a, b, d = run(s, verbose=len(seeds) == 1, touching=touching)
        tot += a
        n += b
        alld += d
    print(f"recall {tot}/{n}; Dice min {min(alld):.3f} p10 {np.percentile(alld,10):.3f} median {np.median(alld):.3f}")
