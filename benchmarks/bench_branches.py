"""Branched specimens (issue 23 item 2): what the cage holds of the chosen path and of the other leg.

    .venv/bin/python -m benchmarks.bench_branches [--before] [--seeds FIRST N] [--hairpins FIRST N] [--kinks FIRST N]
        [--suggested] [--no-thickness] [--no-rise] [--no-doubt]

The Y phantoms (seeds 0-7) and graft-like ones (seeds 100-103) of tests/skeleton/test_branches.py, ends at the trunk
and at leg A; held fractions by tests/cage_reference.py's inverse (the path; leg B from where the legs part); a Y
taken for the body touching itself (partial) is counted. ``--hairpins``: instead, N of the tests' hairpins whose
sides touch (``hairpin_phantom``), by its topology a Y: each is to be partial ("touches itself"), not a branch.
``--suggested``: no ends given (the suggested ones, as a run with no click), and only each result's status.
``--kinks``: instead, N kinked tubes (``kink_phantom``: no branch, an arc tighter than the tube), each to be
straightened whole; ``--no-rise`` cuts a kink's outer corner as a branch (the code before ``_rise``).
``--before``: the same solve with the branch cut switched off (the code before it). ``--no-thickness``: a part cut
off is read as the body doubled by its two-cored sections only, not also by its sections' size (the code before
``_thick_pieces``). ``--no-doubt``: no branch is in doubt (the code before ``_DOUBT_TURN`` and ``_END_NEAR``).
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
from test_branches import _solve, hairpin_phantom, kink_phantom, y_phantom  # noqa: E402

import napari_unwind.skeleton._api as api  # noqa: E402
from benchmarks._util import add_switches, apply_switches  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", action="store_true", help="switch the branch cut off")
    ap.add_argument("--seeds", type=int, nargs=2, metavar=("FIRST", "N"), default=None,
                    help="N Y phantoms and N graft-like ones from seed FIRST on (default: the tests' seeds)")
    ap.add_argument("--hairpins", type=int, nargs=2, metavar=("FIRST", "N"), default=None,
                    help="N hairpins whose sides touch, from seed FIRST on, instead of the Y phantoms")
    ap.add_argument("--kinks", type=int, nargs=2, metavar=("FIRST", "N"), default=None,
                    help="N kinked tubes (no branch) from seed FIRST on, instead of the Y phantoms")
    ap.add_argument("--suggested", action="store_true", help="no ends given: each result's status only")
    add_switches(ap)
    args = ap.parse_args()
    apply_switches(args)
    if args.kinks is not None:
        return kinks(*args.kinks)
    if args.hairpins is not None:
        return hairpins(*args.hairpins, suggested=args.suggested)
    if args.before:
        def uncut(wm, head, tail):
            return api._Cut(wm, [], [], *api._along(wm.binary, head, wm.working_spacing))

        api._cut_branches = uncut
    sets = ((False, range(8)), (True, range(100, 104))) if args.seeds is None else (
        (False, range(args.seeds[0], args.seeds[0] + args.seeds[1])),
        (True, range(args.seeds[0], args.seeds[0] + args.seeds[1])))
    paths, others, touching = [], [], 0
    statuses: dict[str, int] = {}
    for stent, seeds in sets:
        for seed in seeds:
            mask, head, a_end, _, pa, pb, r, (j, apart) = y_phantom(seed, stent=stent)
            if args.suggested:
                st = _status(_solve(mask, None), f"{'graft-like' if stent else 'Y'} {seed}")
                statuses[st] = statuses.get(st, 0) + 1
                continue
            res = _solve(mask, (head, a_end))
            d = res.deformation
            g = np.argwhere(mask).astype(float)
            on = cKDTree(pa).query(g)[0] <= r
            beyond = (cKDTree(pb).query(g)[0] <= r) & ~on & (np.linalg.norm(g - j, axis=1) > max(3 * r, apart))
            note = [w for w in res.warnings if "branches" in w]
            share = note[0].split("long, ")[1].split(" %")[0] if note else "-"
            paths.append(held(d, g[on]).mean())
            touching += bool(res.touching)
            others.append(held(d, g[beyond]).mean())
            print(f"{'graft-like' if stent else 'Y'} {seed}: r {r:.1f}, path held {paths[-1]:.3f}, "
                  f"other leg held {others[-1]:.3f}, branch cut {share} % of the mask"
                  f"{'; taken for the body touching itself' if res.touching else ''}", flush=True)
    if args.suggested:
        print(f"\nwith suggested ends: {statuses}")
        return
    q = [0, 10, 50, 90, 100]
    print(f"\npath held, min / p10 / median / p90 / max: {' / '.join(f'{v:.3f}' for v in np.percentile(paths, q))}")
    print(f"other leg held: {' / '.join(f'{v:.3f}' for v in np.percentile(others, q))}")
    print(f"taken for the body touching itself (partial): {touching} of {len(paths)}")


def _status(res, name: str) -> str:
    """Print and return the status of a solve with suggested ends (``judge``'s, with the start of its reason)."""
    from napari_unwind.pipeline import judge

    status, reason = judge(res)
    print(f"{name}: suggested ends, {status}{': ' + reason[:90] if reason else ''}", flush=True)
    return status


def hairpins(first: int, n: int, *, suggested: bool = False) -> None:
    from napari_unwind.pipeline import judge

    partial, left = 0, []
    statuses: dict[str, int] = {}
    for seed in range(first, first + n):
        mask, head, tail, r, gap, pin = hairpin_phantom(seed)
        if suggested:
            st = _status(_solve(mask, None), f"hairpin {seed}")
            statuses[st] = statuses.get(st, 0) + 1
            continue
        res = _solve(mask, (head, tail))
        g = np.argwhere(mask).astype(float)
        on_pin = cKDTree(pin).query(g)[0] <= r
        status, _ = judge(res)
        partial += status == "partial" and bool(res.touching)
        left.append(res.left_out)
        branch = any("branches between the ends" in w for w in res.warnings)
        print(f"hairpin {seed}: r {r:.1f}, sides {gap:.2f} radii apart, hairpin {on_pin.mean():.2f} of the mask, "
              f"held {held(res.deformation, g[on_pin]).mean():.3f}; {status}"
              f"{', touches itself' if res.touching else ''}{', cut as a branch' if branch else ''}, "
              f"{100 * res.left_out:.0f} % of the mask left out", flush=True)
    if suggested:
        print(f"\nwith suggested ends: {statuses}")
        return
    q = [0, 10, 50, 90, 100]
    print(f"\npartial, touching itself: {partial} of {n}; left out, min / p10 / median / p90 / max: "
          f"{' / '.join(f'{v:.2f}' for v in np.percentile(left, q))}")


def kinks(first: int, n: int) -> None:
    """Kinked tubes (``kink_phantom``), true ends: each is one unbranched body, to be straightened whole."""
    from napari_unwind.pipeline import judge

    statuses: dict[str, int] = {}
    whole, left = [], []
    for seed in range(first, first + n):
        mask, head, tail, r, rc, turn, _ = kink_phantom(seed)
        res = _solve(mask, (head, tail))
        status, _ = judge(res)
        cut = "cut as a branch" if res.branches else "touches itself" if res.touching else "nothing cut"
        statuses[f"{status}, {cut}"] = statuses.get(f"{status}, {cut}", 0) + 1
        whole.append(held(res.deformation, np.argwhere(mask).astype(float)).mean())
        left.append(res.left_out)
        print(f"kink {seed}: r {r:.1f}, arc {rc:.2f} radii, turn {turn:.0f} deg: {status}, {cut}, "
              f"{100 * res.left_out:.0f} % of the mask left out, held {whole[-1]:.3f}", flush=True)
    q = [0, 10, 50, 90, 100]
    print(f"\n{statuses}; the whole mask held (tests/cage_reference.py), min / p10 / median / p90 / max: "
          f"{' / '.join(f'{v:.3f}' for v in np.percentile(whole, q))}; left out, max {max(left):.2f}")


if __name__ == "__main__":
    main()
