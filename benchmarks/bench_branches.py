"""Branched specimens (issue 23 item 2): what the cage holds of the chosen path and of the other leg.

    .venv/bin/python -m benchmarks.bench_branches [--before]

The Y phantoms (seeds 0-7) and graft-like ones (seeds 100-103) of tests/skeleton/test_branches.py, ends at the trunk
and at leg A; held fractions by tests/cage_reference.py's inverse (the path; leg B from where the legs part).
``--before``: the same solve with the branch cut switched off (the code before it).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "tests" / "skeleton")]

from cage_reference import held  # noqa: E402
from test_branches import _solve, y_phantom  # noqa: E402

import napari_unwind.skeleton._api as api  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", action="store_true", help="switch the branch cut off")
    args = ap.parse_args()
    if args.before:
        api._cut_branches = lambda wm, head, tail: (wm, [])
    for stent, seeds in ((False, range(8)), (True, range(100, 104))):
        for seed in seeds:
            mask, head, a_end, _, pa, pb, r, (j, apart) = y_phantom(seed, stent=stent)
            res = _solve(mask, (head, a_end))
            d = res.deformation
            g = np.argwhere(mask).astype(float)
            on = cKDTree(pa).query(g)[0] <= r
            beyond = (cKDTree(pb).query(g)[0] <= r) & ~on & (np.linalg.norm(g - j, axis=1) > max(3 * r, apart))
            note = [w for w in res.warnings if "branches" in w]
            share = note[0].split("long, ")[1].split(" %")[0] if note else "-"
            print(f"{'graft-like' if stent else 'Y'} {seed}: r {r:.1f}, path held {held(d, g[on]).mean():.3f}, "
                  f"other leg held {held(d, g[beyond]).mean():.3f}, branch cut {share} % of the mask", flush=True)


if __name__ == "__main__":
    main()
