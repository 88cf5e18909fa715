"""Straightening throughput against scipy, the memory limit and VTK; peak memory out of core.

    .venv/bin/python -m benchmarks.bench_straighten                  # the throughput table (512^3 -> 768 x 193^2)
    .venv/bin/python -m benchmarks.bench_straighten --peak --workdir /tmp/unwind-bench
                                                                     # 2048 x 1024^2 uint16 (4 GiB) zarr -> zarr

Throughput: one 512^3 uint16 OME-Zarr (made once by ``write_volume``, smooth content) straightened along a smooth
3D curve into a 768 x 193 x 193 output with order 1, every job in a fresh process, same output:

- (a) ``scipy.ndimage.map_coordinates(order=1)``, one thread, over precomputed coordinates (only the call timed);
- (b) ``straighten`` end to end from the zarr (open, graph, read, resample into memory; dask threads);
- (c) ``straighten`` of the volume already in memory (no zarr read; dask threads), and (c1) the same on the
  synchronous scheduler (one thread);
- (d) a numpy copy of the output's bytes: the memory limit;
- (e) VTK ``vtkImageReslice``, one reslice per output slice as 3D Slicer's Curved Planar Reformat and
  napari-curviewer use it (skipped when vtk is not installed; it is not a dependency).

The output cross-section is 193 x 193, not 192 x 192: the straight grid is centred on the curve, so its sides are
always odd (``Deformation.output_shape``). ``--peak`` straightens a 2048 x 1024 x 1024 uint16 zarr into an OME-Zarr
and reports the peak resident memory of that process (the target is < 1 GB).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._util import run_isolated, table

OUT_SHAPE = (768, 193, 193)

# The deformation of the throughput run: keyframes on a smooth 3D curve; its length is made exactly
# (Ns - 1) + 0.5 so that output_shape(1) = (768, 193, 193).
CURVE = """
import numpy as np
from napari_unwind.deformation import Deformation

def bench_deformation(n={n}, ns={ns}, half={half}, keyframes=33):
    t = np.linspace(0.0, 1.0, 4001)
    p0 = np.array([0.12, 0.15, 0.10]) * n
    p1 = np.array([0.88, 0.80, 0.90]) * n
    e = (p1 - p0) / np.linalg.norm(p1 - p0)
    a = np.cross(e, [1.0, 0.0, 0.0]); a /= np.linalg.norm(a)
    b = np.cross(e, a)
    c = (p0 + t[:, None] * (p1 - p0) + (0.22 * n * np.sin(np.pi * t))[:, None] * a
         + (0.12 * n * np.sin(2 * np.pi * t))[:, None] * b)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
    pts = c[[int(np.searchsorted(cum, s)) for s in np.linspace(0.0, cum[-1], keyframes)]]
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    target = ns - 1 + 0.5
    pts[-1] = pts[-2] + (pts[-1] - pts[-2]) / seg[-1] * (target - seg[:-1].sum())
    d = Deformation.from_polyline(pts, spacing=1.0, cage_half_extent=(half, half), unit="micrometer")
    assert not d.folds(), d.folds()
    return d
"""

MAKE_SCAN = """
import dask.array as da
import numpy as np
from napari_unwind.io import write_volume

def smooth_block(block_info=None):
    (z0, z1), (y0, y1), (x0, x1) = block_info[None]["array-location"]
    z = np.arange(z0, z1, dtype=np.float32)[:, None, None]
    y = np.arange(y0, y1, dtype=np.float32)[None, :, None]
    x = np.arange(x0, x1, dtype=np.float32)[None, None, :]
    v = 1000 + 500 * np.sin(z / 20) * np.cos(y / 25) + 300 * np.sin(x / 30) + 200 * np.cos((x + z) / 45)
    return v.astype(np.uint16)

data = da.map_blocks(smooth_block, dtype=np.uint16, chunks=da.core.normalize_chunks((128, 128, 128), {shape}))
write_volume(data, r"{path}", spacing=(1, 1, 1), unit="um", overwrite=True, pyramid=False)
"""

BASELINE = CURVE + """
from napari_unwind.io import open_volume
from scipy import ndimage
vol = open_volume(r"{zarr}").data.compute()
d = bench_deformation()
base, dv, du = d.slice_geometry(1.0)
shape = d.output_shape(1.0)
coords = np.empty((3,) + shape)
i = np.arange(shape[1], dtype=float)[:, None]
j = np.arange(shape[2], dtype=float)[None, :]
for k in range(shape[0]):
    for a in range(3):
        coords[a, k] = base[k, a] + i * dv[k, a] + j * du[k, a]
best = None
for _ in range({repeat}):
    t0 = time.perf_counter()
    out = ndimage.map_coordinates(vol, coords, order=1, mode="constant", cval=0)
    dt = time.perf_counter() - t0
    best = dt if best is None else min(best, dt)
np.save(r"{ref}", out)
result["seconds"] = best
result["voxels"] = out.size
"""

OURS_ZARR = CURVE + """
import dask
from napari_unwind.io import open_volume
from napari_unwind.warp import straighten
d = bench_deformation()
best = None
for _ in range({repeat}):
    t0 = time.perf_counter()
    out = straighten(open_volume(r"{zarr}"), d).data
    with dask.config.set(scheduler="threads"):
        got = out.compute()
    dt = time.perf_counter() - t0
    best = dt if best is None else min(best, dt)
ref = np.load(r"{ref}")
result["seconds"] = best
result["voxels"] = got.size
result["max_diff"] = int(np.abs(got.astype(int) - ref).max())
"""

OURS_MEM = CURVE + """
import dask, dask.array as da
from napari_unwind.io import open_volume
from napari_unwind.warp import straighten
vol = open_volume(r"{zarr}").data.compute()
d = bench_deformation()
data = da.from_array(vol, chunks=vol.shape)
best = None
for _ in range({repeat}):
    t0 = time.perf_counter()
    with dask.config.set(scheduler="{scheduler}"):
        got = straighten(data, d).data.compute()
    dt = time.perf_counter() - t0
    best = dt if best is None else min(best, dt)
ref = np.load(r"{ref}")
result["seconds"] = best
result["voxels"] = got.size
result["max_diff"] = int(np.abs(got.astype(int) - ref).max())
"""

COPY = """
import numpy as np
src = np.ones({shape}, np.uint16)
dst = np.empty_like(src)
best = None
for _ in range(5 * {repeat}):
    t0 = time.perf_counter()
    np.copyto(dst, src)
    dt = time.perf_counter() - t0
    best = dt if best is None else min(best, dt)
result["seconds"] = best
result["voxels"] = src.size
"""

VTK = CURVE + """
import vtk
from vtk.util import numpy_support
from napari_unwind.io import open_volume
vol = open_volume(r"{zarr}").data.compute()
d = bench_deformation()
base, dv, du = d.slice_geometry(1.0)
ns, ny, nx = d.output_shape(1.0)
img = vtk.vtkImageData()
img.SetDimensions(vol.shape[2], vol.shape[1], vol.shape[0])   # VTK (x, y, z) = numpy (axis2, axis1, axis0)
img.SetSpacing(1.0, 1.0, 1.0)
img.GetPointData().SetScalars(numpy_support.numpy_to_vtk(vol.ravel(), deep=False,
                                                         array_type=vtk.VTK_UNSIGNED_SHORT))
reslice = vtk.vtkImageReslice()
reslice.SetInputData(img)
reslice.SetInterpolationModeToLinear()
reslice.SetBackgroundLevel(0)
reslice.SetOutputSpacing(1.0, 1.0, 1.0)
reslice.SetOutputOrigin(0.0, 0.0, 0.0)
reslice.SetOutputExtent(0, nx - 1, 0, ny - 1, 0, 0)
axes = vtk.vtkMatrix4x4()
reslice.SetResliceAxes(axes)
out = np.empty((ns, ny, nx), np.uint16)
best = None
for _ in range({repeat}):
    t0 = time.perf_counter()
    for k in range(ns):
        u = du[k][::-1]; v = dv[k][::-1]; o = base[k][::-1]   # to VTK (x, y, z) order
        n = np.cross(u, v)
        for r in range(3):
            axes.SetElement(r, 0, u[r]); axes.SetElement(r, 1, v[r]); axes.SetElement(r, 2, n[r])
            axes.SetElement(r, 3, o[r])
        axes.Modified()
        reslice.Update()
        out[k] = numpy_support.vtk_to_numpy(reslice.GetOutput().GetPointData().GetScalars()).reshape(ny, nx)
    dt = time.perf_counter() - t0
    best = dt if best is None else min(best, dt)
ref = np.load(r"{ref}")
diff = np.abs(out.astype(int) - ref)
result["seconds"] = best
result["voxels"] = out.size
result["max_diff"] = int(diff.max())
result["differ"] = float((diff > 1).mean())
result["threads"] = int(reslice.GetNumberOfThreads())
"""

PEAK = """
import numpy as np
from napari_unwind.deformation import Deformation
from napari_unwind.io import open_volume
from napari_unwind.warp import export
vol = open_volume(r"{zarr}")
n0, n1, n2 = vol.shape
t = np.linspace(0.0, 1.0, 17)
pts = np.stack([40 + (n0 - 80) * t, n1 / 2 + 0.12 * n1 * np.sin(2 * np.pi * t),
                n2 / 2 + 0.12 * n2 * np.cos(np.pi * t)], axis=1)
d = Deformation.from_polyline(pts, spacing=vol.spacing, cage_half_extent=({half}, {half}), unit=vol.unit)
assert not d.folds(), d.folds()
t0 = time.perf_counter()
path = export(vol, d, r"{out}", order=1, overwrite=True, chunks={chunks}, **{extra})
result["seconds"] = time.perf_counter() - t0
result["out_shape"] = list(open_volume(path).shape)
result["voxels"] = int(np.prod(result["out_shape"]))
"""


def _make_scan(path: Path, shape: tuple[int, int, int]) -> None:
    if (path / "zarr.json").exists():
        return
    t = time.perf_counter()
    run_isolated(MAKE_SCAN.format(shape=shape, path=path), timeout=7200)
    print(f"made {path} {shape} uint16 in {time.perf_counter() - t:.0f} s")


def throughput(work: Path, repeat: int) -> None:
    zarr_path = work / "scan512.zarr"
    _make_scan(zarr_path, (512, 512, 512))
    ref = work / "scipy_reference.npy"
    curve = {"n": 512, "ns": OUT_SHAPE[0], "half": (OUT_SHAPE[1] - 1) // 2}
    fmt = {"zarr": zarr_path, "ref": ref, "repeat": repeat, "shape": OUT_SHAPE}

    def job(code: str, **extra) -> dict:
        src = code.replace("{n}", str(curve["n"])).replace("{ns}", str(curve["ns"])).replace(
            "{half}", str(curve["half"]))
        return run_isolated(src.format(**fmt, **extra))

    rows = {}
    rows["(a) scipy map_coordinates, 1 thread, precomputed coordinates"] = job(BASELINE)
    rows["(b) straighten from the zarr, end to end (threads)"] = job(OURS_ZARR)
    rows["(c) straighten in memory (threads)"] = job(OURS_MEM, scheduler="threads")
    rows["(c1) straighten in memory (1 thread)"] = job(OURS_MEM, scheduler="synchronous")
    rows["(d) numpy copy of the output bytes"] = job(COPY)
    try:
        import vtk  # noqa: F401
    except ImportError:
        print("vtk not installed: skipping (e) (VIRTUAL_ENV=.venv uv pip install vtk to include it)")
    else:
        rows["(e) VTK vtkImageReslice, one reslice per slice"] = job(VTK)
    base = rows["(a) scipy map_coordinates, 1 thread, precomputed coordinates"]
    base_rate = base["voxels"] / base["seconds"]
    out = [["job", "seconds", "Mvox/s", "x (a)", "peak RSS MB", "max |diff| vs (a)"]]
    for name, r in rows.items():
        rate = r["voxels"] / r["seconds"]
        diff = r.get("max_diff", "")
        if "differ" in r:
            diff = f"{diff} ({100 * r['differ']:.2f} % > 1; {r['threads']} threads)"
        out.append([name, f"{r['seconds']:.3f}", f"{rate / 1e6:.1f}", f"{rate / base_rate:.2f}",
                    f"{r['peak_rss_mb']:.0f}", str(diff)])
    print(f"\noutput {OUT_SHAPE[0]} x {OUT_SHAPE[1]} x {OUT_SHAPE[2]} uint16 = {np.prod(OUT_SHAPE) / 1e6:.1f} Mvox, "
          f"order 1, input 512^3 uint16 OME-Zarr (128^3 chunks); best of {repeat}\n")
    print(table(out))


def peak(work: Path, half: int, chunks: int, file_chunks: int) -> None:
    zarr_path = work / "scan2048.zarr"
    _make_scan(zarr_path, (2048, 1024, 1024))
    out = work / "straight2048.zarr"
    r = run_isolated(PEAK.format(zarr=zarr_path, out=out, half=half,
                                 chunks=f"({chunks}, None, None)" if chunks else "None",
                                 extra={"file_chunks": file_chunks} if file_chunks else {}), timeout=7200)
    shutil.rmtree(out, ignore_errors=True)
    rows = [["job", "output shape", "seconds", "Mvox/s", "peak RSS MB"],
            ["export 2048 x 1024 x 1024 uint16 zarr -> OME-Zarr, order 1",
             " x ".join(map(str, r["out_shape"])), f"{r['seconds']:.1f}",
             f"{r['voxels'] / r['seconds'] / 1e6:.1f}", f"{r['peak_rss_mb']:.0f}"]]
    print(table(rows))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workdir", default=None, help="where the scans are made once (default: a temporary folder)")
    ap.add_argument("--repeat", type=int, default=3, help="timed repetitions per job; the best is reported")
    ap.add_argument("--peak", action="store_true", help="peak memory on a 2048 x 1024 x 1024 uint16 zarr instead")
    ap.add_argument("--half", type=int, default=200, help="--peak: cage half-extent in voxels (default 200)")
    ap.add_argument("--chunks", type=int, default=0, help="--peak: output slices per chunk (default: straighten's)")
    ap.add_argument("--file-chunks", type=int, default=0, help="--peak: chunk side of the output zarr (default: 128)")
    args = ap.parse_args(argv)
    temp = args.workdir is None
    work = Path(args.workdir or tempfile.mkdtemp(prefix="unwind-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        if args.peak:
            peak(work, args.half, args.chunks, args.file_chunks)
        else:
            throughput(work, args.repeat)
    finally:
        if temp:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
