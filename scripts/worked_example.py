"""The user guide's worked example for measurements, channels and the average specimen (issue 24), end to end.

    .venv/bin/python scripts/worked_example.py [--out docs/images] [--work DIR] [--fish 8]

Every step is an `unwind` command as a user types it (run as a subprocess); the pictures are drawn from the files
the commands wrote, with matplotlib. Needs the `plot` extra (matplotlib). Prints the commands and the figures the
guide quotes.

1. A phantom fish (`napari_unwind.datasets.fish_phantom`, seed 1) written as `fish.nrrd`, its true mask as
   `fish.mask.nrrd`, and a second "stain" on the same grid (the body's outer layer, as a skin stain shows it).
2. `unwind run fish.nrrd --mask fish.mask.nrrd` -> the straight fish and its session.
3. `unwind measure --session ... --plot` -> the profile (CSV) and its plot (`measure-01-profile.png`).
4. `unwind straighten fish.nrrd stain.nrrd --session ...` -> one two-channel image; a picture of its mid-planes
   (`channels-01-straight.png`).
5. `--fish` phantoms of one family (seeds 11, 12, ...: lengths, bends, twists and rolls differ), each through
   `unwind run --mask`, then `unwind average` -> mean, median, std and residuals (`average-01-mean-std.png`).
"""

from __future__ import annotations

import argparse
import csv
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
UNWIND = [sys.executable, "-m", "napari_unwind.cli"]


def unwind(*args: object, cwd: Path) -> str:
    cmd = [str(a) for a in args]
    print("$ unwind " + " ".join(shlex.quote(c) for c in cmd), flush=True)
    t0 = time.perf_counter()
    done = subprocess.run(UNWIND + cmd, cwd=cwd, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"unwind {' '.join(cmd)} failed ({done.returncode}):\n{done.stderr}")
    print(f"  ({time.perf_counter() - t0:.1f} s)")
    return done.stdout


def phantom_files(seed: int, folder: Path, stem: str, **kw) -> tuple[Path, Path, object]:
    from napari_unwind.datasets import fish_phantom
    from napari_unwind.io import write_volume

    fish = fish_phantom(seed=seed, tube=False, **kw)
    scan = write_volume(fish.volume, folder / f"{stem}.nrrd", spacing=fish.spacing, unit=fish.unit)
    mask = write_volume(fish.mask.astype(np.uint8), folder / f"{stem}.mask.nrrd", spacing=fish.spacing,
                        unit=fish.unit)
    return scan, mask, fish


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "docs" / "images"))
    ap.add_argument("--work", default=None, help="working folder (default: a new temporary one)")
    ap.add_argument("--fish", type=int, default=8)
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import ndimage as ndi

    from napari_unwind.io import open_channels, open_volume, write_volume

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="unwind_example_"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"working in {work}")

    # 1-2: one fish, its mask, a stain; the pipeline with the mask
    scan, mask, fish = phantom_files(1, work, "fish")
    body = fish.mask.astype(bool)
    skin = body & ~ndi.binary_erosion(body, iterations=2)
    write_volume((skin * 800 + ndi.gaussian_filter(body.astype(np.float32), 2) * 200).astype(np.uint16),
                 work / "stain.nrrd", spacing=fish.spacing, unit=fish.unit)
    unwind("run", "fish.nrrd", "--mask", "fish.mask.nrrd", "-o", "fish.straight.ome.zarr", "-q", "--overwrite",
           cwd=work)

    # 3: the profile and its plot
    unwind("measure", "--session", "fish.straight.ome.unwind.json", "-o", "fish.profile.csv", "--plot",
           out / "measure-01-profile.png", "--overwrite", "-q", cwd=work)
    with open(work / "fish.profile.csv") as f:
        rows = list(csv.reader(f))
    header, table = rows[0], np.array([[float(v) if v else np.nan for v in r] for r in rows[1:]])
    col = {h.split(" [")[0]: i for i, h in enumerate(header)}
    area = table[:, col["area"]]
    print(f"profile: {len(table)} stations, length {table[-1, col['s']]:.1f}, thickest section "
          f"{np.nanmax(area):.1f} at s = {table[np.nanargmax(area), col['s']]:.1f}, mean curvature "
          f"{np.nanmean(table[:, col['curvature']]):.4f}; header: {', '.join(header[:6])} ...")

    # 4: two channels through one deformation
    unwind("straighten", "fish.nrrd", "stain.nrrd", "--session", "fish.straight.ome.unwind.json", "--channel-names",
           "ct,skin", "-o", "fish.channels.ome.zarr", "--overwrite", cwd=work)
    chans = open_channels(work / "fish.channels.ome.zarr")
    fig, axes = plt.subplots(2, 1, figsize=(8, 3.6), dpi=100)
    for ax, ch in zip(axes, chans, strict=True):
        data = np.asarray(ch.data)
        ax.imshow(data[:, data.shape[1] // 2, :].T, cmap="gray", aspect="auto", interpolation="nearest")
        ax.set_title(f"channel '{ch.metadata['channel']}': the straight fish cut through its middle (s across)",
                     fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(out / "channels-01-straight.png", metadata={"Software": None})
    plt.close(fig)

    # 5: a family of fish, each straightened with its own mask, then averaged
    batch = work / "batch"
    for folder in (batch, batch / "straight", batch / "average"):
        folder.mkdir(exist_ok=True)
    rng = np.random.default_rng(5)
    for k in range(args.fish):
        length = float(rng.uniform(130, 170))
        phantom_files(11 + k, batch, f"fish{k:02d}", length=length, twist=float(rng.uniform(0.5, 2.0)),
                      roll=float(rng.uniform(-0.6, 0.6)))
        unwind("run", f"fish{k:02d}.nrrd", "--mask", f"fish{k:02d}.mask.nrrd", "-o",
               f"straight/fish{k:02d}.ome.zarr", "-q", "--overwrite", cwd=batch)
    unwind("average", "straight", "-o", "average/mean.ome.zarr", "--overwrite", cwd=batch)
    mean = np.asarray(open_volume(batch / "average" / "mean.ome.zarr").data)
    std = np.asarray(open_volume(batch / "average" / "mean.std.ome.zarr").data)
    fig, axes = plt.subplots(2, 1, figsize=(8, 3.6), dpi=100)
    for ax, vol, title in ((axes[0], mean, f"mean of {args.fish} straight fish"),
                           (axes[1], std, "standard deviation (where the fish differ)")):
        im = ax.imshow(vol[:, vol.shape[1] // 2, :].T, cmap="magma", aspect="auto", interpolation="nearest")
        ax.set_title(title + ", cut through the middle (s across)", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(im, ax=ax, fraction=0.03)
    fig.tight_layout()
    fig.savefig(out / "average-01-mean-std.png", metadata={"Software": None})
    plt.close(fig)
    print((batch / "average" / "mean.residuals.csv").read_text())


if __name__ == "__main__":
    main()
