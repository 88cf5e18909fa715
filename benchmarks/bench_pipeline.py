"""The one pipeline's overhead over its stages (issue 18): ``pipeline.run_iter`` against its stages called one by
one on the same input, in the same process, alternating.

    .venv/bin/python -m benchmarks.bench_pipeline              # the recorded run
    .venv/bin/python -m benchmarks.bench_pipeline --repeat 1   # a quicker look

Input: a tank phantom of 3 fish (``tank_phantom(n_fish=3, seed=2)``) written as NRRD; the specimen is picked by
a point inside the first fish. One round = the pipeline (segment, select + refine, skeleton, checksum, session,
OME-Zarr export) and the same stages called directly (``segment_iter``, ``select`` + ``default_isovalue`` +
``refine_mask_iter``, ``estimate_deformation_iter``, ``SourceInfo.from_path``, ``save_session``, ``export_iter``),
each round into a fresh folder. Reported: the median of each, and their ratio (target: overhead < 5 %).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
import warnings
from pathlib import Path

from benchmarks._util import table


def _stages(volume, scan_path: Path, seed, out: Path) -> None:
    from napari_unwind.progress import run
    from napari_unwind.segmentation import default_isovalue, refine_mask_iter, segment_iter, select, selected_ids
    from napari_unwind.session import Session, SourceInfo, save_session
    from napari_unwind.skeleton import estimate_deformation_iter
    from napari_unwind.warp import export_iter

    features = run(segment_iter(volume, features=5))
    ids = selected_ids(features, seeds=[seed])
    working = select(features, ids=ids)
    mask = run(refine_mask_iter(volume, working, features=features, isovalue=default_isovalue(features, working)))
    res = run(estimate_deformation_iter(mask, spacing=volume.spacing, origin=volume.origin, unit=volume.unit,
                                        volume=volume.data))
    source = SourceInfo.from_path(scan_path, volume=volume)
    session = Session(source=source, deformation=res.deformation)
    save_session(session, out / "s.unwind.json")
    run(export_iter(volume, res.deformation, out / "s.zarr", session=session.to_dict()))


def _pipeline(volume, scan_path: Path, seed, out: Path) -> None:
    from napari_unwind.pipeline import run

    run(volume, seeds=[seed], output=out / "p.zarr", session_path=out / "p.unwind.json", source=scan_path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5, help="rounds (each: the pipeline and the stages)")
    args = ap.parse_args()

    from napari_unwind.datasets import tank_phantom
    from napari_unwind.io import open_volume, write_volume

    warnings.simplefilter("ignore")
    tank = tank_phantom(n_fish=3, seed=2)
    fish = tank.fish[0]
    seed = fish.centerline[len(fish.centerline) // 2]
    times: dict[str, list[float]] = {"pipeline.run_iter": [], "stages called directly": []}
    with tempfile.TemporaryDirectory() as tmp:
        scan_path = write_volume(tank.volume, Path(tmp) / "tank.nrrd", spacing=tank.spacing, unit=tank.unit)
        volume = open_volume(scan_path)
        _stages(volume, scan_path, seed, Path(tempfile.mkdtemp(dir=tmp)))  # warm-up: imports, numba
        for _ in range(args.repeat):
            for name, job in (("pipeline.run_iter", _pipeline), ("stages called directly", _stages)):
                out = Path(tempfile.mkdtemp(dir=tmp))
                t0 = time.perf_counter()
                job(volume, scan_path, seed, out)
                times[name].append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"scan {tank.volume.shape} {tank.volume.dtype}, {args.repeat} rounds, medians")
    print(table([["job", "median s", "min s", "max s"],
                 *[[k, f"{med[k]:.3f}", f"{min(v):.3f}", f"{max(v):.3f}"] for k, v in times.items()]]))
    ratio = med["pipeline.run_iter"] / med["stages called directly"]
    print(f"\npipeline / stages: {ratio:.3f} (overhead {100 * (ratio - 1):+.1f} %; target < 5 %: "
          f"{'met' if ratio < 1.05 else 'NOT met'})")


if __name__ == "__main__":
    main()
