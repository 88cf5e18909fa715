"""The roll of the frames along the real vessel and spinal cord (issue 23 item 1), against the rotation-minimising
frames of the same centres and normals (double reflection, written in tests/test_real_scans_run.py).

    .venv/bin/python -m benchmarks.bench_roll [--step 10]

For each real scan of ../shared/data with its mask (the aorta CT, the spine MRI's cord), the skeleton is solved in
this process with the defaults and with ``estimate_twist=False``; prints the twist's source and confident share,
the total roll, the largest change within 10 mm, and the roll profile every ``--step`` mm.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

from napari_unwind.io import open_volume
from napari_unwind.pipeline import SkeletonOptions, skeleton_step
from napari_unwind.progress import run
from tests.test_real_scans_run import _roll_against_rotation_minimising

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
CASES = (("aorta", "aorta_ct.nrrd", "aorta_ct_aorta_mask.nrrd"), ("spinal cord", "spine_t2.nrrd",
                                                                   "spine_t2_cord_mask.nrrd"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--step", type=float, default=10.0, help="profile step, mm (default 10)")
    args = ap.parse_args()
    for name, scan_file, mask_file in CASES:
        scan, mask = open_volume(DATA / scan_file), open_volume(DATA / mask_file)
        for label, options in (("default", SkeletonOptions()), ("no twist", SkeletonOptions(estimate_twist=False))):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                result = run(skeleton_step(np.asarray(mask.data) > 0, spacing=mask.spacing, origin=mask.origin,
                                           unit=mask.unit, volume=np.asarray(scan.data), options=options))
            roll, s = _roll_against_rotation_minimising(result.deformation)
            k = int(round(10.0 / 0.5))
            local = np.abs(roll[k:] - roll[:-k])
            print(f"{name}, {label}: {result.twist_report()}")
            print(f"  roll against the rotation-minimising frames: {roll.max() - roll.min():.1f} deg in all, "
                  f"at most {local.max():.1f} deg within 10 mm (s = {s[np.argmax(local)]:.0f} mm)")
            at = np.arange(0.0, s[-1], args.step)
            print("  s (mm):   " + " ".join(f"{v:6.0f}" for v in at))
            print("  roll (deg)" + " ".join(f"{v:6.1f}" for v in np.interp(at, s, roll)))


if __name__ == "__main__":
    main()
