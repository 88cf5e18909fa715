"""Round tubes along random 3D curves (issue 23 item 1, a vessel family drawn from a seed): is each taken as round,
and how far do its frames roll against the rotation-minimising frames?

    .venv/bin/python -m benchmarks.bench_tubes [--seed 22] [--n 40] [--no-thickness] [--no-rise] [--no-doubt]

Tube i: a radius of 3-8 voxels around a cubic spline through 6 random-walk points scaled into a 110^3 scan (liquid
100, tube 1000, Gaussian noise 40); ends at the curve's ends. Curves shorter than 8 radii are skipped; a curve that
comes within 2 radii of itself (at least 4 radii away along it) makes a tube fused with itself, which is reported
in a total of its own (its fused sections are not round), with how many were found to touch themselves (a loop left
out: partial), had a part cut off in doubt (partial: joining where the path turns sharply or next to an end, a
branch or the body running into itself, which the mask cannot tell) or as a branch (ok, with a note: sides that run
into one another, joining gently away from the ends, cannot be told from a branch by its mask). ``body held``: the
share of the tube's voxels the straight volume holds (tests/cage_reference.py's inverse, independent of ours); the
totals count the ok tubes holding under 0.99 of their body (an ok result that is not whole). A spline may leave
the scan and come back: the tube is then in two parts, which the
solve refuses (a row "refused" with the reason's start) or, where the parts lie within the dilation's reach, joins
(the curve then takes the shortcut: partial, by its coverage). The skeleton is solved with the defaults and the
volume; the roll is that of tests/test_real_scans_run.py (double reflection, independent of our frames); each tube's
status is ``pipeline.judge``'s (a partial result's roll is printed too; the totals give the largest change within 10
voxels over the ok ones apart). ``--no-thickness``: a part cut off is read as the body doubled by its two-cored
sections only, not also by its sections' size (the code before ``_thick_pieces``). ``--no-rise``: a kink's outer
corner is cut as a branch (the code before ``_rise``). ``--no-doubt``: no branch is in doubt (the code
before).
"""

from __future__ import annotations

import argparse
import warnings
from collections.abc import Sequence

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

from benchmarks._util import add_switches, apply_switches
from napari_unwind.errors import InvalidInputError
from napari_unwind.pipeline import judge
from napari_unwind.progress import run
from napari_unwind.skeleton import estimate_deformation_iter
from tests.cage_reference import held
from tests.test_real_scans_run import _roll_against_rotation_minimising

SHAPE = (110, 110, 110)


def tube(rng: np.random.Generator, grid: np.ndarray, *, build: bool = True) -> tuple | None:
    """(mask, volume, curve, radius, closest self-approach in radii), or None for a curve under 8 radii long.
    ``build=False``: draws what a tube draws from ``rng`` (the next tube is the same) and returns None."""
    r = rng.uniform(3, 8)
    ctrl = np.cumsum(rng.normal(0, 1, (6, 3)), axis=0)
    ctrl = (ctrl - ctrl.min(0)) / np.ptp(ctrl, axis=0).max() * (SHAPE[0] - 2 * r - 16) + r + 8
    c = CubicSpline(np.linspace(0, 1, 6), ctrl)(np.linspace(0, 1, 2000))
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))]
    noise = rng.normal(0, 40, SHAPE)
    if s[-1] < 8 * r or not build:
        return None
    approach = min((np.linalg.norm(c[np.abs(s - s[j]) > 4 * r] - c[j], axis=1).min()
                    if (np.abs(s - s[j]) > 4 * r).any() else np.inf) for j in range(0, len(c), 20))
    d, k = cKDTree(c).query(grid, distance_upper_bound=3 * r)
    cap = ((k == 0) | (k >= len(c) - 1)) & (d > 0.5)  # flat ends
    mask = ((d <= r) & ~cap).reshape(SHAPE)
    return mask, (np.where(mask, 1000.0, 100.0) + noise).astype(np.float32), c, r, approach / r


def grid_points() -> np.ndarray:
    """The voxel centres of SHAPE, (N, 3) in index order."""
    return np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in SHAPE], indexing="ij"), -1).reshape(-1, 3)


def tubes(seed: int, indices: Sequence[int]) -> dict[int, tuple | None]:
    """The tubes ``indices`` as this benchmark draws them with ``--seed seed`` (``tube``'s tuple, or None)."""
    rng = np.random.default_rng(seed)
    grid = grid_points()
    return {i: t for i, t in ((i, tube(rng, grid, build=i in indices)) for i in range(max(indices) + 1))
            if i in indices}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=22)
    ap.add_argument("--n", type=int, default=40, help="curves drawn (short ones are skipped)")
    add_switches(ap)
    args = ap.parse_args()
    apply_switches(args)
    rng = np.random.default_rng(args.seed)
    grid = grid_points()
    rows = {False: [], True: []}
    for i in range(args.n):
        t = tube(rng, grid)
        if t is None:
            continue
        mask, volume, c, r, approach = t
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                res = run(estimate_deformation_iter(mask, (c[0], c[-1]), spacing=1.0, volume=volume))
            except InvalidInputError as e:
                print(f"tube {i}: radius {r:.1f}: refused: {str(e)[:100]}", flush=True)
                continue
        is_round = any("taken as round" in str(w.message) for w in caught)
        roll, s = _roll_against_rotation_minimising(res.deformation)
        n10 = max(1, int(round(10 / (s[1] - s[0]))))
        jump = float(np.abs(roll[n10:] - roll[:-n10]).max()) if len(roll) > n10 else 0.0
        fused = approach < 2
        branch = any("branches between the ends" in w for w in res.warnings)
        doubt = any("which the mask cannot tell" in w for w in res.touching)
        loop = any(w.startswith("the mask touches") for w in res.touching)
        status = judge(res)[0]
        body = float(held(res.deformation, np.argwhere(mask).astype(float)).mean())
        rows[fused].append((float(np.ptp(roll)), jump, is_round, loop, branch, status == "ok", doubt,
                            status == "ok" and body < 0.99))
        cut = (("; loop left out (partial)" if loop else "") + ("; a part cut off in doubt (partial)" if doubt else "")
               + ("; cut as a branch" if branch else ""))
        print(f"tube {i}: radius {r:.1f}, length {res.deformation.length:.0f}, closest self-approach {approach:.2f} "
              f"radii{' (fused)' if fused else ''}: taken as round {is_round}, roll range {np.ptp(roll):.1f} deg, "
              f"largest change within 10 voxels {jump:.1f} deg, coverage {res.coverage:.3f}, "
              f"body held {body:.3f}{cut}; {status}", flush=True)
    for fused, rs in rows.items():
        if rs:
            q = " / ".join(f"{v:.1f}" for v in np.percentile([x[0] for x in rs], [0, 10, 50, 90, 100]))
            print(f"\n{'fused' if fused else 'apart'}: {len(rs)} tubes, taken as round {sum(x[2] for x in rs)}; roll "
                  f"range min / p10 / median / p90 / max {q} deg; largest change within 10 voxels, max "
                  f"{max(x[1] for x in rs):.1f} deg; a loop left out (partial) {sum(x[3] for x in rs)}, a part cut off "
                  f"in doubt (partial) {sum(x[6] for x in rs)}, a part cut off as a branch {sum(x[4] for x in rs)}; ok "
                  f"{sum(x[5] for x in rs)} ({sum(x[7] for x in rs)} holding under 0.99 of the body), the largest "
                  f"change within 10 voxels of those {max((x[1] for x in rs if x[5]), default=0.0):.1f} deg")


if __name__ == "__main__":
    main()
