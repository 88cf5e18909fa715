"""``unwind demo``: the pipeline on the bundled synthetic tank, end to end, with a report.

The sample is generated, not downloaded: :func:`napari_unwind.datasets.tank_phantom` builds a tube of fish with
exact ground truth. The demo writes it as the multi-page TIFF a scanner would give, imports it into the working
OME-Zarr pyramid, straightens every fish out of core, writes each straight fish, a session file per fish and
before/after maximum-intensity projections, and checks everything against the ground truth.

Until the skeleton solve exists, each fish is straightened along its known centreline (keyframes every
``KEYFRAME_STEP`` voxels with the true frames), so the figures measure the deformation and the warp alone.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .errors import OutputError

__all__ = ["run_demo"]

KEYFRAME_STEP = 8.0  # voxels of arclength between keyframes taken from the true centreline


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.astype(bool), b.astype(bool)
    return 2.0 * np.logical_and(a, b).sum() / max(1, a.sum() + b.sum())


def _mip_png(volume: np.ndarray, path: Path, *, axis: int) -> None:
    """Maximum-intensity projection along ``axis`` as an 8-bit PNG, contrast from the 1st to 99.9th percentile."""
    import imageio.v3 as iio

    from .io._atomic import atomic_output

    mip = volume.max(axis=axis).astype(np.float64)
    lo, hi = np.percentile(mip, [1, 99.9])
    img = np.clip((mip - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    with atomic_output(path, overwrite=True) as tmp:
        iio.imwrite(tmp, img, extension=".png")


def _inside_tube(tank) -> np.ndarray:
    """The scan with the tube wall blanked out (voxels beyond its inner radius), so a MIP shows the fish."""
    vol = tank.volume
    if tank.tube_radii is None:
        return vol
    (c1, c2), r_in = tank.tube_center, tank.tube_radii[0]
    yy, xx = np.ogrid[: vol.shape[1], : vol.shape[2]]
    inside = (yy * tank.spacing[1] - c1) ** 2 + (xx * tank.spacing[2] - c2) ** 2 < (0.95 * r_in) ** 2
    return np.where(inside[None], vol, vol.min())


def true_deformation(fish, *, step: float = KEYFRAME_STEP):
    """A Deformation from a phantom's known centreline and frames, keyframes every ``step`` voxels of arclength."""
    from .deformation import Deformation

    s = fish.arclength
    n = max(2, int(round(s[-1] / (step * min(fish.spacing)))) + 1)
    idx = np.unique(np.searchsorted(s, np.linspace(0, s[-1], n)).clip(0, len(s) - 1))
    return Deformation.from_keyframes(fish.centerline_physical[idx], fish.frames[idx], fish.half_extent,
                                      spacing=fish.spacing, unit=fish.unit)


def run_demo(output: Path, *, quiet: bool = False, overwrite: bool = False, n_fish: int = 3, seed: int = 0) -> int:
    """Run the demo into the folder ``output``; returns 0 on success (the CLI's exit status)."""
    from .cli import _run_with_bar, describe, disk_usage, human_bytes
    from .datasets import tank_phantom
    from .io import import_volume_iter, open_volume, write_volume
    from .progress import run
    from .session import Endpoints, Session, SourceInfo, save_session
    from .warp import export_iter, map_labels

    say = (lambda *a: None) if quiet else print
    output = Path(output)
    if output.exists() and not output.is_dir():
        raise OutputError(f"{output} exists and is not a folder; choose another --output")
    output.mkdir(parents=True, exist_ok=True)
    scan, store = output / "tank.tif", output / "tank.zarr"
    outputs = [scan, store] + [output / f"fish_{i}.zarr" for i in range(1, n_fish + 1)]
    for p in outputs:
        if p.exists() and not overwrite:
            raise OutputError(f"{p} exists from an earlier run; pass --overwrite or choose another --output")

    t0 = time.perf_counter()
    tank = tank_phantom(n_fish=n_fish, seed=seed)
    say(f"generated a synthetic tank of {len(tank.fish)} fish, {'x'.join(map(str, tank.volume.shape))} voxels "
        f"({human_bytes(tank.volume.nbytes)}) in {time.perf_counter() - t0:.1f} s")

    write_volume(tank.volume, scan, spacing=tank.spacing, unit=tank.unit, overwrite=overwrite)
    say(f"wrote the scan as a scanner would: {scan} ({human_bytes(disk_usage(scan))})")

    t1 = time.perf_counter()
    imported = _run_with_bar(import_volume_iter(scan, store, overwrite=overwrite), quiet)
    say(f"imported into the working format in {time.perf_counter() - t1:.1f} s")
    say(describe(imported, store))
    same = bool(np.array_equal(imported.data.compute(), tank.volume)) and np.allclose(imported.spacing, tank.spacing)
    _mip_png(_inside_tube(tank), output / "tank_mip.png", axis=1)

    say("")
    say(f"{'fish':>4} {'length':>10} {'keyframes':>9} {'straight shape':>16} {'Dice':>6} {'NRMSE':>7}  output")
    source = SourceInfo.from_path(store, volume=imported)
    worst = 1.0
    for i, fish in enumerate(tank.fish, start=1):
        deformation = true_deformation(fish)
        session = Session(source=source, deformation=deformation,
                          endpoints=Endpoints(head=tuple(map(float, fish.head)), tail=tuple(map(float, fish.tail))),
                          notes="unwind demo: keyframes from the phantom's true centreline")
        save_session(session, output / f"fish_{i}.unwind.json")
        target = output / f"fish_{i}.zarr"
        run(export_iter(imported, deformation, target, overwrite=overwrite, session=session.to_dict()))
        straight = open_volume(target).data.compute()
        # against the ground truth, on the common grid (the true straight grid is the same convention): the
        # fish's own mask carried into straight space, and the intensities inside the true straight mask
        # (the cage also holds bits of neighbours, which the segmentation removes, not the warp)
        mask = np.asarray(map_labels(fish.mask.astype(np.uint8), deformation, to="straight"))
        truth, true_mask = fish.straight_volume, fish.straight_mask
        n = tuple(min(a, b) for a, b in zip(straight.shape, truth.shape, strict=True))
        cut = (slice(0, n[0]), slice(0, n[1]), slice(0, n[2]))
        dice = _dice(mask[cut], true_mask[cut])
        inside = true_mask[cut]
        got, ref = straight[cut][inside].astype(float), truth[cut][inside].astype(float)
        nrmse = float(np.sqrt(np.mean((got - ref) ** 2)) / max(float(truth.max()) - float(truth.min()), 1e-9))
        worst = min(worst, dice)
        _mip_png(straight, output / f"fish_{i}_mip.png", axis=2)
        say(f"{i:>4} {deformation.length:>7.1f} {imported.unit_abbreviation:<2} {len(deformation):>9} "
            f"{'x'.join(map(str, straight.shape)):>16} {dice:>6.3f} {nrmse:>7.3f}  {target.name}")
    say("")
    say(f"round trip scan -> OME-Zarr -> array identical, spacing kept: {'yes' if same else 'NO'}")
    say(f"MIPs: {output / 'tank_mip.png'} (before) and fish_N_mip.png (after); sessions: fish_N.unwind.json")
    say("Dice: the fish's mask straightened, against the true straight mask; NRMSE: straightened intensities "
        "inside the true mask against the noise-free truth (noise sigma 40 of 2400)")
    return 0 if same and worst >= 0.9 else 1
