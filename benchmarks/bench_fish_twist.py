"""Random fish phantoms, the residual twist of the whole skeleton solve (issue 23 item 1: <= 6 degrees on the fish).

    .venv/bin/python -m benchmarks.bench_fish_twist [--seed 7] [--n 30] [--intensities alternate|always|never]

Fish i: ``fish_phantom`` with a curve drawn from s-bend / c-bend / helix, a twist uniform in [-pi, pi], a head roll
in [0, 2 pi), a body radius of 5-10 and a length of 120-220 (noise seed ``100 seed + i``); solved by
``estimate_deformation_iter`` from the true ends with the defaults, with the intensities on even fish and the mask
alone on odd ones (``--intensities always``: as every face runs it, ``never``: the mask alone, the Python API called
without ``volume=``). The error is tests/skeleton/test_skeleton.py's ``residual_twist_deg`` (the deformation's v
against the phantom's true v, at 400 stations), over s/L 0.03-0.97 as that test reads it. Prints one row per fish,
the distribution of each fish's worst and median angle, and how many fish exceed 6 degrees.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from napari_unwind.datasets import fish_phantom
from tests.skeleton.test_skeleton import _solve_quiet, residual_twist_deg

GOAL_DEG = 6.0


def draw(rng: np.random.Generator) -> dict:
    return dict(curve=str(rng.choice(["s-bend", "c-bend", "helix"])), twist=float(rng.uniform(-np.pi, np.pi)),
                roll=float(rng.uniform(0, 2 * np.pi)), body_radius=float(rng.uniform(5, 10)),
                length=float(rng.uniform(120, 220)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--n", type=int, default=30)
    ap.add_argument("--intensities", choices=("alternate", "always", "never"), default="alternate",
                    help="pass the scan's intensities on even fish (alternate), on every fish, or on none")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    worst, median = [], []
    for i in range(args.n):
        kw = draw(rng)
        t = time.perf_counter()
        ph = fish_phantom(seed=100 * args.seed + i, **kw)
        given = args.intensities == "always" or (args.intensities == "alternate" and i % 2 == 0)
        res = _solve_quiet(ph.mask, (ph.head, ph.tail), spacing=ph.spacing, volume=ph.volume if given else None)
        err = residual_twist_deg(ph, res.deformation)
        lo = int(0.03 * len(err))
        body = err[lo:int(0.97 * len(err))]
        worst.append(float(body.max()))
        median.append(float(np.median(body)))
        shown = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in kw.items())
        how = "intensities" if given else "mask alone"
        at = (lo + int(np.argmax(body))) / len(err)
        print(f"fish {i} ({how}): {shown}: worst {body.max():.2f} deg at s/L {at:.2f}, "
              f"median {np.median(body):.2f}; {time.perf_counter() - t:.1f} s", flush=True)
    w, m = np.array(worst), np.array(median)
    def spread(x: np.ndarray) -> str:
        return " / ".join(f"{v:.2f}" for v in np.percentile(x, [0, 10, 50, 90, 100]))

    print(f"\nworst per fish, min / p10 / median / p90 / max: {spread(w)} deg")
    print(f"median per fish, min / p10 / median / p90 / max: {spread(m)} deg")
    print(f"fish over {GOAL_DEG:g} degrees: {(w > GOAL_DEG).sum()} of {len(w)}")


if __name__ == "__main__":
    main()
