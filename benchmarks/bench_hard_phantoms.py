"""Hard phantoms: the distribution of issue 10's figures over N random ones, with and without the fold-free
construction, in the same run.

    .venv/bin/python -m benchmarks.bench_hard_phantoms                  # the recorded run: 30 phantoms, seeds 1000-1029
    .venv/bin/python -m benchmarks.bench_hard_phantoms --n 6 --seed 2000

Phantom i is ``hard_fish_phantom(seed + i, kind=HARD_KINDS[i % 3])`` (the slow test's 30 cases at the defaults):
tight S-bends, coils and helices, twisted up to 200 degrees, isotropic or anisotropic spacing. Each is solved with
``estimate_deformation`` from its true ends, once with ``fold_free=False`` (today's construction) and once with
``fold_free=True``, then straightened with ``straighten``; the figures are those of tests/test_hard_phantoms.py
(:func:`measure`). Prints one row per phantom and construction, the distribution (min, p10, median, p90, max) of
each figure, and how many phantoms miss each goal. Where ``estimate_deformation`` has no ``fold_free`` option yet,
the first run uses its default and the second is reported as n/a; figures a result does not report are n/a.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks._util import table

FIGURES = ("folds", "fold_length", "min_jacobian", "min_jacobian_reported", "max_tilt", "coverage",
           "coverage_reported", "rms_vox", "length_err_pct", "twist_max_deg", "twist_median_deg", "dice", "dice_all",
           "foreign", "keyframes", "seconds")
#: The columns of the table of phantoms (the distribution has every figure).
ROW = ("folds", "min_jacobian", "max_tilt", "coverage", "rms_vox", "length_err_pct", "twist_max_deg", "dice",
       "foreign", "seconds")


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=30, help="number of phantoms (default 30)")
    ap.add_argument("--seed", type=int, default=1000, help="seed of the first phantom (default 1000)")
    args = ap.parse_args()
    if args.n < 1 or args.seed < 0:
        ap.error("--n must be >= 1 and --seed >= 0")

    from napari_unwind.datasets import HARD_KINDS, hard_fish_phantom
    from tests.test_hard_phantoms import GOALS, failed_goals, measure, supports_fold_free

    ff = supports_fold_free()
    runs = {"fold_free=False": False if ff else None, "fold_free=True": True if ff else "n/a"}
    rows = [["phantom", "spacing", "twist deg", "r/b", "gap/width", "construction", *ROW, "missed"]]
    results: dict[str, list[dict]] = {name: [] for name in runs}
    t_all = time.perf_counter()
    for i in range(args.n):
        kind, seed = HARD_KINDS[i % len(HARD_KINDS)], args.seed + i
        ph = hard_fish_phantom(seed, kind=kind)
        info = ph.info
        desc = [ph.name, "x".join(f"{s:g}" for s in ph.spacing), f"{info['twist_deg']:.0f}",
                f"{info['radius_to_half_height']:.2f}",
                f"{info['min_gap'] / info['body_width']:.2f}" if np.isfinite(info["min_gap"]) else "-"]
        for name, option in runs.items():
            if option == "n/a":
                rows.append([*desc, name, *(["n/a"] * len(ROW)), "n/a"])
                continue
            try:
                fig = measure(ph, fold_free=option)
            except Exception as exc:  # noqa: BLE001 - a refusal is a result: count it as missing every goal
                rows.append([*desc, name, *(["error"] * len(ROW)), f"{type(exc).__name__}: {exc}"[:80]])
                results[name].append({"error": str(exc)})
                continue
            results[name].append(fig)
            missed = failed_goals(fig)
            rows.append([*desc, name, *(_fmt(fig[k]) for k in ROW),
                         "; ".join(m.split(" ")[0] for m in missed) or "-"])
        print(f"{ph.name}: done ({time.perf_counter() - t_all:.0f} s)", flush=True)
    print()
    print(table(rows))

    print(f"\n{args.n} phantoms, seeds {args.seed}-{args.seed + args.n - 1}; estimate_deformation "
          f"{'has' if ff else 'has NO'} fold_free option\n")
    dist = [["figure", "construction", "min", "p10", "median", "p90", "max"]]
    for k in FIGURES:
        for name in runs:
            vals = [f[k] for f in results[name] if "error" not in f and f[k] is not None]
            if not vals:
                dist.append([k, name, *(["n/a"] * 5)])
                continue
            q = np.percentile(np.asarray(vals, dtype=float), [0, 10, 50, 90, 100])
            dist.append([k, name, *(_fmt(float(x)) for x in q)])
    print(table(dist))

    print()
    counts = [["goal", *runs]]
    for fig_name, op, limit in GOALS:
        cells = []
        for name in runs:
            done = results[name]
            if not done:
                cells.append("n/a")
                continue
            bad = sum(1 for f in done if "error" in f or any(m.startswith(fig_name + " ") for m in failed_goals(f)))
            cells.append(f"{bad} / {len(done)}")
        counts.append([f"{fig_name} {op} {limit}", *cells])
    counts.append(["refused (error)", *(f"{sum('error' in f for f in results[n])} / {len(results[n])}"
                                        if results[n] else "n/a" for n in runs)])
    counts.append(["all goals met", *(f"{sum('error' not in f and not failed_goals(f) for f in results[n])} / "
                                      f"{len(results[n])}" if results[n] else "n/a" for n in runs)])
    print(table(counts))
    print(f"\ntotal {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
