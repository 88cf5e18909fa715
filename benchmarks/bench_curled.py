"""Curled specimens with no click and no mask (issue 23): hard phantoms written as scans, through ``unwind run --all``.

    .venv/bin/python -m benchmarks.bench_curled [--seed 1000] [--n 6]

Phantoms ``hard_fish_phantom(seed + i, kind=k)`` for i < n and every kind (tight S-bends, coils, helices; noise,
a tube wall cut by the scan's faces), each written as an NRRD scan (the volume only, no mask) and run through
``pipeline.run_all_iter`` with the defaults. For each scan: the rows' statuses, and for each specimen straightened
``ok`` the figures of tests/test_hard_phantoms.py against the phantom's truth: the fraction of the phantom's voxels
held at their own place (``coverage``), the centreline's RMS distance from the true one (voxels) and the length
error. A specimen is *right* when it holds >= 0.95 of the phantom at its own place with an RMS under 2 voxels.
Prints one row per scan and the totals.

``--among``: each phantom beside a fish of the usual family (``fish_phantom``, an S-bend 110 voxels long), side by
side in one noisy scan: the curled one is then among elongated bodies. Reported per scan: what became of the curled
phantom (a row ``ok`` or ``partial`` whose centreline lies on its side of the scan, a row ``unresolved`` whose point
to click lies there, or *missing*: no such row), the other fish's status and the run's exit status
(``pipeline.exit_status``). A missing phantom in a run that exits 0 is a specimen passed over in silence.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from napari_unwind import pipeline
from napari_unwind.datasets import HARD_KINDS, hard_fish_phantom
from napari_unwind.io import write_volume
from napari_unwind.progress import run
from napari_unwind.session import load_session
from tests.skeleton.test_skeleton import centreline_errors
from tests.test_hard_phantoms import coverage


def one(ph, tmp: Path) -> tuple[dict, list[dict]]:
    scan = tmp / "scan.nrrd"
    write_volume(np.asarray(ph.volume), scan, spacing=ph.spacing)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run(pipeline.run_all_iter(scan, tmp / "out"))
    rows = res.rows() if callable(getattr(res, "rows", None)) else res.rows
    counts: dict = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    figs = []
    for r in rows:
        if r["status"] != "ok":
            continue
        dfm = load_session(tmp / "out" / r["session"]).deformation
        rms, length_err = centreline_errors(ph, dfm)
        figs.append({"coverage": coverage(ph, dfm), "rms_vox": rms, "length_err_pct": 100 * abs(length_err),
                     "reason": r.get("reason") or ""})
    return counts, figs


def among(ph, seed: int, tmp: Path) -> tuple[str, str, int]:
    """The phantom beside an S-bend fish in one scan: (the phantom's status or "missing", the fish's, exit)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_pipeline import beside_a_fish

    vol, split = beside_a_fish(ph, seed)  # the phantom's side: axis2 < split
    scan = write_volume(vol, tmp / "scan.nrrd", spacing=ph.spacing)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run(pipeline.run_all_iter(scan, tmp / "out"))
    sides: dict[bool, list[str]] = {True: [], False: []}
    for r in res.specimens:
        if r.status == "unresolved":
            at = [float(v) for v in r.reason.split("a point inside it: ")[1].rstrip(")").split(",")]
            sides[at[2] < split].append(r.status)
        elif r.status in ("ok", "partial"):
            sides[float(np.mean(r.deformation.positions[:, 2])) / ph.spacing[2] < split].append(r.status)
    order = ("ok", "partial", "unresolved")
    mine = min(sides[True], key=order.index) if sides[True] else "missing"
    other = min(sides[False], key=order.index) if sides[False] else "missing"
    return mine, other, pipeline.exit_status(res.specimens)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--n", type=int, default=6)
    ap.add_argument("--among", action="store_true", help="each phantom beside an S-bend fish in one scan")
    args = ap.parse_args()
    if args.among:
        tally: dict = {}
        for i in range(args.n):
            for kind in HARD_KINDS:
                ph = hard_fish_phantom(args.seed + i, kind=kind)
                with tempfile.TemporaryDirectory() as d:
                    mine, other, code = among(ph, args.seed + i, Path(d))
                silent = mine == "missing" and code == 0
                tally.setdefault(kind, {}).setdefault(mine + (" (exit 0)" if silent else ""), 0)
                tally[kind][mine + (" (exit 0)" if silent else "")] += 1
                print(f"{kind}-{args.seed + i} beside a fish: {mine}; the fish {other}; exit {code}"
                      + ("  <-- passed over in silence" if silent else ""), flush=True)
        print()
        for kind, t in tally.items():
            print(f"{kind}: " + ", ".join(f"{k} {v}" for k, v in sorted(t.items())))
        return
    total = {k: [0, 0, 0] for k in HARD_KINDS}  # scans, one right ok specimen, a wrong ok specimen
    for i in range(args.n):
        for kind in HARD_KINDS:
            ph = hard_fish_phantom(args.seed + i, kind=kind)
            t = time.perf_counter()
            with tempfile.TemporaryDirectory() as d:
                counts, figs = one(ph, Path(d))
            right = [f for f in figs if f["coverage"] >= 0.95 and f["rms_vox"] <= 2.0]
            total[kind][0] += 1
            total[kind][1] += bool(right)
            total[kind][2] += len(figs) - len(right)
            shown = "; ".join(f"coverage {f['coverage']:.3f}, RMS {f['rms_vox']:.2f}, "
                              f"length {f['length_err_pct']:.2f} % ({f['reason'][:60]})" for f in figs)
            print(f"{kind}-{args.seed + i}: rows {counts}; ok: {shown or 'none'}; {time.perf_counter() - t:.0f} s",
                  flush=True)
    print()
    for kind, (n, ok, wrong) in total.items():
        print(f"{kind}: {ok} of {n} straightened right with no click; {wrong} ok specimen(s) not the phantom")


if __name__ == "__main__":
    main()
