"""``unwind demo``: the whole pipeline on the bundled synthetic tank, end to end, checked against the ground truth.

The sample is generated, not downloaded: :func:`napari_unwind.datasets.tank_phantom` builds a tube of fish with
exact ground truth. The demo

1. writes the tank as the multi-page TIFF a scanner would give and imports it into the working OME-Zarr pyramid;
2. segments it once (join tree) and, for every fish, selects the feature under a click inside it (a point of its
   known centreline, where a user would click) and refines that selection at full resolution;
3. lets the skeleton solve SUGGEST the head and the tail (the true ends are not used) and estimates the
   deformation with the automatic twist (the scan's intensities given);
4. straightens every fish out of core into ``fish_N.zarr`` with its session ``fish_N.unwind.json`` and before /
   after maximum-intensity projections (``tank_mip.png``, ``fish_N_mip.png``);
5. prints, per fish, how far the suggested ends are from the true head and tail and the accuracy of the
   deformation against the ground truth (:func:`accuracy`).

:func:`true_deformation` (keyframes on the phantom's true centreline and frames) is kept as a reference: the
accuracy of a deformation made from the truth bounds what the warp alone can do.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from .errors import OutputError

__all__ = ["accuracy", "run_demo", "true_deformation"]

KEYFRAME_STEP = 8.0  # voxels of arclength between keyframes taken from the true centreline
MIN_DICE = 0.85  # the demo fails (exit status 1) when a fish's straightened mask is below this


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


# ------------------------------------------------------------------------------------------------------------------
# accuracy against the ground truth
# ------------------------------------------------------------------------------------------------------------------
def _closest_on_polyline(points: np.ndarray, line: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each point, the arclength ``s`` of its closest point on the polyline ``line`` and the distance to it.

    ``line`` (K, 3) are the vertices, ``s`` (K,) their arclengths. The nearest vertex is found with a k-d tree,
    then the point is projected onto the two segments that meet there and the closer projection wins (exact for
    a polyline whose vertices are closer together than its bends are sharp).
    """
    from scipy.spatial import cKDTree

    _, i = cKDTree(line).query(points)
    best_s = np.full(len(points), np.nan)
    best_d = np.full(len(points), np.inf)
    for a in (i - 1, i):
        a = np.clip(a, 0, len(line) - 2)
        p0, p1 = line[a], line[a + 1]
        seg = p1 - p0
        t = np.clip(np.einsum("ij,ij->i", points - p0, seg) / np.einsum("ij,ij->i", seg, seg), 0.0, 1.0)
        d = np.linalg.norm(points - (p0 + t[:, None] * seg), axis=1)
        better = d < best_d
        best_d[better] = d[better]
        best_s[better] = (s[a] + t * (s[a + 1] - s[a]))[better]
    return best_s, best_d


def _true_frames_at(fish, sigma: np.ndarray) -> np.ndarray:
    """The phantom's frames (rows u, v, n) at arclengths ``sigma``: linear between its dense samples, then made
    orthonormal again (Gram-Schmidt from n, then v)."""
    f = np.stack([np.stack([np.interp(sigma, fish.arclength, fish.frames[:, r, c]) for c in range(3)], axis=-1)
                  for r in range(3)], axis=1)
    n = f[:, 2] / np.linalg.norm(f[:, 2], axis=1, keepdims=True)
    v = f[:, 1] - np.einsum("ij,ij->i", f[:, 1], n)[:, None] * n
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.stack([np.cross(v, n), v, n], axis=1)


def accuracy(fish, deformation, *, step: float = 0.5) -> dict[str, Any]:
    """Compare a deformation with a phantom's ground truth (:class:`napari_unwind.datasets.Phantom`).

    Only the phantom's own arrays are the reference (its dense centreline, arclength, frames, bent mask and
    straight mask); the deformation is evaluated through its public methods (``sample``, ``forward``).

    Matching ``s``: our curve is sampled every ``step`` finest voxels of its arclength; each sample is matched
    to its closest point on the true centreline, whose true arclength is ``sigma(s)``.

    Parameters
    ----------
    fish : Phantom
        The ground truth (a fish of ``tank_phantom`` or a ``fish_phantom``), in the scan's voxel grid.
    deformation : Deformation
        The deformation to judge, in the physical frame of the scan (its ``origin`` is subtracted to compare with
        the phantom, whose voxel (0, 0, 0) is at 0).
    step : float
        Sampling step along our curve, in finest voxels.

    Returns
    -------
    dict
        ``centreline_rms`` : RMS distance from our centre curve (the polyline through the keyframes the warp
        uses) to the true centreline, in finest voxels (physical distance / min spacing).
        ``centreline_max`` : the largest such distance, finest voxels.
        ``arclength_error`` : signed length error of our curve, %, against the true arclength of the stretch it
        covers: ``100 (L - (sigma(L) - sigma(0))) / (sigma(L) - sigma(0))`` (a stretched or shrunk straight
        fish; the ends our curve leaves out are measured by ``start_offset`` / ``end_offset`` instead).
        ``start_offset``, ``end_offset`` : true arclength (finest voxels) between the true head and ``sigma(0)``,
        and between ``sigma(L)`` and the true tail (how much of the fish lies beyond our curve's ends; padding
        covers it in the straight volume).
        ``twist_max``, ``twist_median`` : residual twist in degrees, the absolute angle about the true tangent
        between our ``v`` and the true ``v`` at the matched point (our ``v`` projected on the true cross-section
        plane: ``atan2(-v'.u, v'.v)``, the convention of a rotation about ``n``). A head-down straight fish has
        180 degrees.
        ``dice`` : Dice of the straightened mask against the phantom's ``straight_mask``, on the phantom's
        straight grid (see below).

    Notes
    -----
    The Dice: the phantom's straight grid has ``s_true = 0`` at the true head, ``y`` along the true (dorsal)
    ``v`` and ``x`` along ``u``, centred on the curve, spacing ``fish.straight_spacing``. Our straight volume
    has its ``s = 0`` at our head, which lies ``sigma(0)`` along the true centreline. The two ``s`` axes are
    aligned by that offset: the grid voxel ``(s_true, y, x)`` is our straight point ``(x, y, s_true - sigma(0))``,
    carried into the scan by ``deformation.forward`` and looked up in the fish's TRUE bent mask (nearest
    voxel). Points outside our straight volume (beyond its padded ``s`` range or its cross-section) are empty,
    as they would be in the exported volume. So the fish is straightened with our deformation exactly as
    ``unwind straighten`` would do it (nearest interpolation, the labels' way), only resampled onto the truth's
    grid without a second interpolation; a perfect deformation scores about 1 (sampling on both sides of the
    boundary aside), a shifted, stretched or turned one less.
    """
    from scipy import ndimage

    sp = np.asarray(fish.spacing, dtype=float)
    vox = float(sp.min())
    origin = np.asarray(deformation.origin, dtype=float)
    length = deformation.length
    s = np.linspace(0.0, length, max(2, int(math.ceil(length / (step * vox))) + 1))
    centres, frames = deformation.sample(s)
    centres = centres - origin
    sigma, dist = _closest_on_polyline(centres, fish.centerline_physical, fish.arclength)
    covered = float(sigma[-1] - sigma[0])
    true = _true_frames_at(fish, sigma)
    v = frames[:, 1] - np.einsum("ij,ij->i", frames[:, 1], true[:, 2])[:, None] * true[:, 2]
    theta = np.arctan2(-np.einsum("ij,ij->i", v, true[:, 0]), np.einsum("ij,ij->i", v, true[:, 1]))
    twist = np.degrees(np.abs(theta))

    # the straightened mask on the phantom's straight grid
    ds = float(fish.straight_spacing)
    s_t, y, x = fish.straight_grid()
    S, Y, X = np.meshgrid(s_t - sigma[0], y, x, indexing="ij")
    xys = np.stack([X.ravel(), Y.ravel(), S.ravel()], axis=1)
    bent = (deformation.forward(xys) - origin) / sp
    ours = ndimage.map_coordinates(fish.mask.astype(np.uint8), bent.T, order=0, cval=0, mode="constant") > 0
    ns, ny, nx = deformation.output_shape(ds)
    lo = deformation.s_range[0]
    box = ((S.ravel() >= lo - ds / 2) & (S.ravel() <= lo + (ns - 0.5) * ds)
           & (np.abs(Y.ravel()) <= (ny / 2) * ds) & (np.abs(X.ravel()) <= (nx / 2) * ds))
    ours = (ours & box).reshape(S.shape)
    truth = fish.straight_mask.astype(bool)
    dice = 2.0 * np.logical_and(ours, truth).sum() / max(1, int(ours.sum()) + int(truth.sum()))
    return {
        "centreline_rms": float(np.sqrt(np.mean(dist ** 2)) / vox),
        "centreline_max": float(dist.max() / vox),
        "arclength_error": float(100.0 * (length - covered) / covered) if covered > 0 else float("nan"),
        "start_offset": float(sigma[0] / vox),
        "end_offset": float((fish.length - sigma[-1]) / vox),
        "twist_max": float(twist.max()),
        "twist_median": float(np.median(twist)),
        "dice": float(dice),
    }


# ------------------------------------------------------------------------------------------------------------------
# the demo
# ------------------------------------------------------------------------------------------------------------------
def _distance_vox(a: Any, b: Any, spacing: Any) -> float:
    return float(np.linalg.norm((np.asarray(a, float) - np.asarray(b, float)) * np.asarray(spacing)) / min(spacing))


def run_demo(output: Path, *, quiet: bool = False, overwrite: bool = False, n_fish: int = 3, seed: int = 0) -> int:
    """Run the demo into the folder ``output`` through :func:`napari_unwind.pipeline.run_iter`; returns the CLI's exit
    status: 0 on success, 3 when a fish is straightened only in part (partial), 1 otherwise."""
    from ._report import describe, disk_usage, human_bytes
    from ._report import run_with_bar as _run_with_bar
    from .datasets import tank_phantom
    from .io import import_volume_iter, write_volume
    from .io._volume import unit_label
    from .pipeline import EXIT_PARTIAL, PipelineOptions, SegmentOptions, run_iter, segment_step
    from .session import SourceInfo

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

    t_start = t0 = time.perf_counter()
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
    unit = unit_label(imported.unit)

    t1 = time.perf_counter()
    k = max(5, n_fish + 2)  # the fish, the tube wall and a spare
    options = PipelineOptions(segment=SegmentOptions(features=k))  # every other option: the pipeline's defaults
    features = _run_with_bar(segment_step(imported, options.segment), quiet)
    say(f"segmented the tank into {features.k} features at level {features.level} "
        f"({'x'.join(map(str, features.shape))}) in {time.perf_counter() - t1:.1f} s")
    source = SourceInfo.from_path(store, volume=imported)

    say("")
    rows, worst, swapped, partial = [], 1.0, False, False
    for i, fish in enumerate(tank.fish, start=1):
        t1 = time.perf_counter()
        click = fish.centerline[len(fish.centerline) // 2]  # where a user would click: inside the fish
        target = output / f"fish_{i}.zarr"
        r = _run_with_bar(
            run_iter(imported, features=features, seeds=[click], options=options, output=target,
                     session_path=output / f"fish_{i}.unwind.json", source=source, overwrite=True,
                     notes="unwind demo: segmented, selected by a click, suggested endpoints, automatic twist"),
            quiet)
        t_run = time.perf_counter() - t1
        result, deformation, ends = r.skeleton, r.deformation, r.session.endpoints
        d_head = _distance_vox(ends.head, fish.head, tank.spacing)
        d_tail = _distance_vox(ends.tail, fish.tail, tank.spacing)
        flipped = _distance_vox(ends.head, fish.tail, tank.spacing) < d_head
        swapped |= flipped
        say(f"fish {i}: clicked {_pt(click)} -> feature {', '.join(map(str, r.ids))} ({r.voxels} working voxels); "
            f"suggested head {_pt(ends.head)} ({d_head:.1f} voxels from the true head), tail {_pt(ends.tail)} "
            f"({d_tail:.1f} from the true tail){'  HEAD AND TAIL SWAPPED' if flipped else ''}")
        for m in r.warnings:
            say(f"  warning: {m}")
        say(f"  {result.report()}")
        say(f"  {r.summary()}")
        partial |= r.status != "ok"
        from .io import open_volume

        t2 = time.perf_counter()
        straight = open_volume(target).data.compute()
        _mip_png(straight, output / f"fish_{i}_mip.png", axis=2)
        acc = accuracy(fish, deformation)
        worst = min(worst, acc["dice"])
        rows.append((i, deformation, straight.shape, acc, t_run, time.perf_counter() - t2))

    say("")
    say(f"{'fish':>4} {'length':>9} {'keys':>4} {'straight':>12} {'RMS':>5} {'max':>5} {'length':>6} "
        f"{'twist':>11} {'Dice':>6} {'Dice':>6} {'seconds':>17}")
    say(f"{'':>4} {unit:>9} {'':>4} {'shape':>12} {'vox':>5} {'vox':>5} {'err %':>6} {'max/med deg':>11} "
        f"{'':>6} {'truth':>6} {'pipeline/check':>17}")
    for i, d, shape, acc, t_run, t_check in rows:
        ref = accuracy(tank.fish[i - 1], true_deformation(tank.fish[i - 1]))["dice"]
        say(f"{i:>4} {d.length:>9.1f} {len(d):>4} {'x'.join(map(str, shape)):>12} {acc['centreline_rms']:>5.2f} "
            f"{acc['centreline_max']:>5.2f} {acc['arclength_error']:>+6.2f} "
            f"{acc['twist_max']:>5.1f}/{acc['twist_median']:<5.1f} {acc['dice']:>6.3f} {ref:>6.3f} "
            f"{t_run:>11.1f}/{t_check:>4.1f}")
    say("")
    say(f"round trip scan -> OME-Zarr -> array identical, spacing kept: {'yes' if same else 'NO'}")
    say(f"MIPs: {output / 'tank_mip.png'} (before) and fish_N_mip.png (after); sessions: fish_N.unwind.json")
    say("RMS/max: distance of the deformation's centre curve to the true centreline (voxels); length err: its "
        "length against the true arclength of the stretch it covers; twist: residual angle between its v and the "
        "true dorsal v, at the closest true point; Dice: the fish's true mask straightened with the deformation, "
        "against the true straight mask (s axes aligned at the closest true point of our head); Dice truth: the "
        "same with keyframes on the true centreline and frames (what the warp alone achieves)")
    say(f"total {time.perf_counter() - t_start:.1f} s")
    if not (same and worst >= MIN_DICE and not swapped):
        return 1
    return EXIT_PARTIAL if partial else 0


def _pt(p: Any) -> str:
    return "(" + ", ".join(f"{float(v):.1f}" for v in p) + ")"
