"""Several channels through one deformation (issue 24 item 1): N channels against one, in the same run.

    .venv/bin/python -m benchmarks.bench_channels [--channels 3] [--size 256] [--repeat 3]

A smooth random scan of ``--size``^3 uint16 voxels per channel, N channels stored as one OME-Zarr with a ``c`` axis
(chunks of one channel, 64^3, lz4 as ``unwind import`` writes them), and a bent deformation through it (an arc
of half a turn across the scan, a 64 x 48 voxel cage, a twist): the straight volume (289 x 97 x 129) is a
fifth of one channel of the scan.

Rows (best of ``--repeat``, after a warm-up that compiles the kernels):

* compute, one channel: ``straighten(channel 0).data.compute()`` (the baseline);
* compute, N channels one by one: N such calls;
* compute, N channels together: ``straighten_channels`` and one ``compute`` of all;
* export, one channel: ``export`` to OME-Zarr (the baseline with its writing);
* export, N channels: ``export_channels_iter`` into one OME-Zarr with a ``c`` axis.

``--command``: instead, the user's command as a user times it. A phantom fish in a ``--size``^3 scan (written as
NRRD, gzip, and its mask); ``unwind run SCAN --mask MASK`` makes the session once; then ``unwind straighten SCAN
--session S -o one.zarr`` (one channel) against ``unwind straighten SCAN C2 C3 --session S -o all.zarr`` (the other
channels: the scan times 2 and 3 plus noise, the same grid), each a fresh process, best of ``--repeat``, alternating.

The goal (issue 24): N channels cost <= 1.3x one channel plus the extra output writing. "Extra writing" is
estimated in the same run as N-1 times (export of one channel - compute of one channel).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--channels", type=int, default=3)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--command", action="store_true", help="time the CLI's straighten of N files against one")
    args = ap.parse_args()
    if args.command:
        return _command(args)
    import dask.array as da
    import zarr
    from scipy import ndimage as ndi

    from napari_unwind.deformation import Deformation
    from napari_unwind.io import open_channels
    from napari_unwind.progress import run
    from napari_unwind.warp import export, export_channels_iter, straighten, straighten_channels

    n0 = args.size
    rng = np.random.default_rng(0)
    arrays = []
    for k in range(args.channels):
        noise = ndi.gaussian_filter(rng.random((n0, n0, n0), dtype=np.float32), 2.0 + k)
        noise = (noise - noise.min()) / np.ptp(noise)
        arrays.append((noise * 60000).astype(np.uint16))
    t = np.linspace(0, np.pi, 9)
    pts = np.stack([n0 * (0.1 + 0.8 * t / np.pi), n0 / 2 + 0.3 * n0 * np.sin(t), n0 / 2 + 0.2 * n0 * np.cos(t)], 1)
    d = Deformation.from_polyline(pts, spacing=(1.0, 1.0, 1.0), cage_half_extent=(64.0, 48.0), unit="micrometer")
    d = d.twist_keyframe(4, 0.5)
    tmp = Path(tempfile.mkdtemp(prefix="bench_channels_"))
    try:
        root = zarr.open_group(str(tmp / "scan.zarr"), mode="w", zarr_format=3)
        stack = np.stack(arrays)
        arr = root.create_array("0", shape=stack.shape, chunks=(1, 64, 64, 64), dtype=stack.dtype)
        arr[...] = stack
        root.attrs["ome"] = {"version": "0.5", "multiscales": [{
            "axes": [{"name": "c", "type": "channel"}] + [{"name": a, "type": "space", "unit": "micrometer"}
                                                          for a in "zyx"],
            "datasets": [{"path": "0", "coordinateTransformations": [
                {"type": "scale", "scale": [1.0, 1.0, 1.0, 1.0]}]}]}]}
        chans = open_channels(tmp / "scan.zarr")
        straighten_channels(chans[:2], d).pop().data[:8].compute()  # warm-up
        straighten(chans[0], d).data[:8].compute()

        def best(fn):
            times = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                fn()
                times.append(time.perf_counter() - t)
            return min(times)

        def export_one():
            export(chans[0], d, tmp / "one.zarr", overwrite=True)

        def export_all():
            run(export_channels_iter(chans, d, tmp / "all.zarr", overwrite=True))

        from napari_unwind.io import as_volume

        mem = [as_volume(a) for a in arrays]  # in memory: no decoding, the resampling alone
        m_one = best(lambda: straighten(mem[0], d).data.compute())
        m_each = best(lambda: [straighten(c, d).data.compute() for c in mem])
        m_together = best(lambda: da.stack([v.data for v in straighten_channels(mem, d)]).compute())
        one = best(lambda: straighten(chans[0], d).data.compute())
        each = best(lambda: [straighten(c, d).data.compute() for c in chans])
        together = best(lambda: da.stack([v.data for v in straighten_channels(chans, d)]).compute())
        e_one = best(export_one)
        e_all = best(export_all)
        n = args.channels
        extra = (n - 1) * max(e_one - one, 0.0)
        shape = straighten(chans[0], d).shape
        print(f"scan {(n0,) * 3} uint16 x {n} channels (OME-Zarr c axis, 64^3 lz4), straight {shape}")
        print("| | time | ratio to one channel |")
        print("|---|---|---|")
        print(f"| in memory, one channel (baseline) | {m_one:.3f} s | 1.00x |")
        print(f"| in memory, {n} channels one by one | {m_each:.3f} s | {m_each / m_one:.2f}x |")
        print(f"| in memory, {n} channels together | {m_together:.3f} s | {m_together / m_one:.2f}x |")
        print(f"| compute, one channel (baseline) | {one:.2f} s | 1.00x |")
        print(f"| compute, {n} channels one by one | {each:.2f} s | {each / one:.2f}x |")
        print(f"| compute, {n} channels together | {together:.2f} s | {together / one:.2f}x |")
        print(f"| export OME-Zarr, one channel | {e_one:.2f} s | 1.00x |")
        print(f"| export OME-Zarr, {n} channels in one image | {e_all:.2f} s | {e_all / e_one:.2f}x |")
        print(f"| the same less the extra writing ({extra:.2f} s) | {e_all - extra:.2f} s | "
              f"{(e_all - extra) / e_one:.2f}x |")
        print("goal: N channels <= 1.3x one channel plus the extra output writing")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _command(args: argparse.Namespace) -> None:
    import subprocess
    import sys

    from napari_unwind.datasets import fish_phantom
    from napari_unwind.io import Volume, write_volume

    unwind = [sys.executable, "-m", "napari_unwind.cli"]
    n0 = args.size
    ph = fish_phantom(length=0.9 * n0, curve="c-bend", body_radius=n0 / 20, shape=(n0, n0, n0), seed=1)
    tmp = Path(tempfile.mkdtemp(prefix="bench_channels_cli_"))
    try:
        scan = write_volume(ph.volume, tmp / "scan.nrrd", spacing=ph.spacing)
        mask = write_volume(ph.mask.astype(np.uint8), tmp / "mask.nrrd", spacing=ph.spacing)
        rng = np.random.default_rng(0)
        others = []
        for k in range(2, args.channels + 1):
            v = ph.volume.astype(np.float32) * k + rng.normal(0, 20, ph.volume.shape).astype(np.float32)
            others.append(write_volume(Volume(v, spacing=ph.spacing), tmp / f"c{k}.nrrd"))
        subprocess.run(unwind + ["run", str(scan), "--mask", str(mask), "-o", str(tmp / "fish.zarr"), "-q"],
                       check=True)
        session = tmp / "fish.unwind.json"

        def timed(cmd: list[str]) -> float:
            t = time.perf_counter()
            subprocess.run(unwind + cmd, check=True, stderr=subprocess.DEVNULL)
            return time.perf_counter() - t

        one = [str(scan), "--session", str(session), "--overwrite", "-q", "-o", str(tmp / "one.zarr")]
        alln = [str(scan), *map(str, others), "--session", str(session), "--overwrite", "-q",
                "-o", str(tmp / "all.zarr")]
        t1, tn = [], []
        for _ in range(args.repeat):
            t1.append(timed(["straighten", *one]))
            tn.append(timed(["straighten", *alln]))
        t1, tn = min(t1), min(tn)
        n = args.channels
        size_one = sum(f.stat().st_size for f in (tmp / "one.zarr").rglob("*") if f.is_file())
        size_all = sum(f.stat().st_size for f in (tmp / "all.zarr").rglob("*") if f.is_file())
        print(f"scan {ph.volume.shape} {ph.volume.dtype} (NRRD gzip) + {n - 1} more of its grid (float32)")
        print(f"outputs: one channel {size_one / 2**20:.1f} MiB, {n} channels {size_all / 2**20:.1f} MiB")
        print("| `unwind straighten` | time | ratio to one channel |")
        print("|---|---|---|")
        print(f"| the scan alone (baseline) | {t1:.2f} s | 1.00x |")
        print(f"| the scan and {n - 1} more files of its grid, one output | {tn:.2f} s | {tn / t1:.2f}x |")
        print("goal: N channels <= 1.3x one channel plus the extra output writing")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
