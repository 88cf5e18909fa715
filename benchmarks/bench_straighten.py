"""Straightening throughput against scipy, the memory limit and VTK; peak memory out of core.

    .venv/bin/python -m benchmarks.bench_straighten                  # the throughput table (512^3 -> 768 x 193^2)
    .venv/bin/python -m benchmarks.bench_straighten --small              # only the small job (128 x 97^2 from 320^3)
    .venv/bin/python -m benchmarks.bench_straighten --codecs --workdir /tmp/unwind-bench
                                                                     # the working store's codec table
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

Small job (issue 10): a 128 x 97 x 97 output from a 320^3 uint16 numpy volume, ``straighten(vol, d).data.compute()``
end to end (checks, graph, resampling on the dask threads) against ``map_coordinates`` over precomputed
coordinates of the same points, both in one process, alternating, best of ``--repeat`` each; ``--small`` runs only
this table. Before issue 10 the fixed cost (hashing and copying the numpy input) made this 0.8x scipy.

Codec table (``--codecs``, issue 10): level 0 of the 512^3 scan rewritten with each codec chain the working store
could use (blosc zstd / lz4 at several levels with byte or bit shuffle, zstd without blosc, none; with and without
crc32c; read directly or through zarr's pipeline at several ``async.concurrency``; one or two dask threads), in one
process so that every row sees the same load: file size, compression ratio on this smooth scan, on the same scan
plus CT-like noise and on the real aorta CT of ``../shared/data``, the single-thread decode rate of its chunks and
job (b) from it, against scipy timed in the same rounds.

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

# The small job: a gentle 3D bend of length exactly (ns - 1) + 0.5 through the middle of an n^3 scan.
SMALL = """
import dask
import numpy as np
from scipy import ndimage
from napari_unwind.deformation import Deformation
from napari_unwind.warp import straighten

n, ns, half = {n}, {ns}, {half}
t = np.linspace(0.0, 1.0, 2001)
e = np.array([1.0, 0.6, 0.3]); e /= np.linalg.norm(e)
a = np.cross(e, [0.0, 0.0, 1.0]); a /= np.linalg.norm(a)
b = np.cross(e, a)
c = (n / 2 + ((t - 0.5) * 1.3 * ns)[:, None] * e + (0.12 * ns * np.sin(np.pi * t))[:, None] * a
     + (0.06 * ns * np.sin(2 * np.pi * t))[:, None] * b)
cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
pts = c[[int(np.searchsorted(cum, s)) for s in np.linspace(0.0, cum[-1], 9)]]
pts = pts[0] + (pts - pts[0]) * (ns - 0.5) / np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()
d = Deformation.from_polyline(pts, spacing=1.0, cage_half_extent=(half, half), unit="micrometer")
assert not d.folds(), d.folds()
z, y, x = np.ogrid[:n, :n, :n]
vol = (1000 + 500 * np.sin(z / 20) * np.cos(y / 25) + 300 * np.sin(x / 30)
       + 200 * np.cos((x + z) / 45)).astype(np.uint16)
base, dv, du = d.slice_geometry(1.0)
shape = d.output_shape(1.0)
coords = np.empty((3,) + shape)
i = np.arange(shape[1], dtype=float)[:, None]
j = np.arange(shape[2], dtype=float)[None, :]
for k in range(shape[0]):
    for q in range(3):
        coords[q, k] = base[k, q] + i * dv[k, q] + j * du[k, q]
with dask.config.set(scheduler="threads"):
    straighten(vol, d).data.compute()  # load the compiled kernels once, as a running program has them
    times = {{"scipy": [], "ours": []}}
    for _ in range({repeat}):
        t0 = time.perf_counter()
        ref = ndimage.map_coordinates(vol, coords, order=1, mode="constant", cval=0)
        times["scipy"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        got = straighten(vol, d).data.compute()
        times["ours"].append(time.perf_counter() - t0)
result["scipy"] = min(times["scipy"])
result["ours"] = min(times["ours"])
result["scipy_median"] = float(np.median(times["scipy"]))
result["ours_median"] = float(np.median(times["ours"]))
result["shape"] = list(got.shape)
result["max_diff"] = int(np.abs(got.astype(int) - ref).max())
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


# The codec table, in one process so that every row sees the same load: level 0 of the 512^3 scan is written once
# per codec chain, then every round times scipy once and each row's reading and straightening (best over rounds).
CODEC_TABLE = CURVE + """
import os, shutil
import dask
import zarr
from scipy import ndimage
from zarr.codecs import BloscCodec, Crc32cCodec, ZstdCodec
from napari_unwind.io import ome_zarr, open_volume, write_volume
from napari_unwind.warp import straighten
rows = {rows}
vol = open_volume(r"{zarr}").data.compute()
direct = ome_zarr._direct_codecs
d = bench_deformation()
base, dv, du = d.slice_geometry(1.0)
shape = d.output_shape(1.0)
coords = np.empty((3,) + shape)
ii = np.arange(shape[1], dtype=float)[:, None]
jj = np.arange(shape[2], dtype=float)[None, :]
for k in range(shape[0]):
    for q in range(3):
        coords[q, k] = base[k, q] + ii * dv[k, q] + jj * du[k, q]
shuffles = {{"byte": "shuffle", "bit": "bitshuffle"}}
stores = {{}}
for label, kind, level, shuffle, crc, reader, scheduler in rows:
    key = (kind, level, shuffle, crc)
    if key in stores:
        continue
    path = os.path.join(r"{work}", "codec-%d.zarr" % len(stores))
    shutil.rmtree(path, ignore_errors=True)
    t0 = time.perf_counter()
    if kind in ("lz4", "zstd", "none") and crc:  # what write_ome_zarr writes
        write_volume(vol, path, spacing=(1, 1, 1), unit="um", pyramid=False, compression=kind,
                     compression_level=level, shuffle=shuffle)
    else:  # other chains, written by zarr into the same layout
        codecs = ([ZstdCodec(level=level)] if kind == "zarr-zstd"
                  else [BloscCodec(cname="lz4", clevel=level, shuffle=shuffles[shuffle])])
        root = zarr.open_group(path, mode="w", zarr_format=3)
        arr = root.create_array("0", shape=vol.shape, chunks=(128, 128, 128), dtype=vol.dtype,
                                compressors=codecs + ([Crc32cCodec()] if crc else []), fill_value=0,
                                dimension_names=["z", "y", "x"], config={{"write_empty_chunks": True}})
        arr[...] = vol
        attrs = zarr.open_group(r"{zarr}", mode="r").attrs.asdict()
        attrs["ome"]["multiscales"][0]["datasets"] = attrs["ome"]["multiscales"][0]["datasets"][:1]
        root.attrs.update(attrs)
    write = time.perf_counter() - t0
    size = sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(os.path.join(path, "0")) for f in fs)
    stores[key] = (path, write, size)


def timed(f):
    t0, c0 = time.perf_counter(), time.process_time()
    out = f()
    return time.perf_counter() - t0, time.process_time() - c0, out


best = {{}}
with dask.config.set(scheduler="threads"):
    straighten(open_volume(stores[next(iter(stores))][0]), d).data.compute()  # load the kernels
for _ in range({repeat}):
    t, c, ref = timed(lambda: ndimage.map_coordinates(vol, coords, order=1, mode="constant", cval=0))
    best["scipy"] = min(best.get("scipy", (t, c)), (t, c))
    for label, kind, level, shuffle, crc, reader, scheduler in rows:
        path = stores[(kind, level, shuffle, crc)][0]
        ome_zarr._direct_codecs = direct if reader == "direct" else (lambda array: None)
        concurrency = int(reader.rsplit("-", 1)[1]) if reader.startswith("zarr-concurrency-") else 10
        with zarr.config.set({{"async.concurrency": concurrency}}), dask.config.set(scheduler=scheduler):
            t, c, got = timed(lambda: straighten(open_volume(path), d).data.compute())
            # every chunk read and decoded in turn, in this thread, as one dask task reads it (no dask, no copy)
            level0 = os.path.join(path, "0")
            chunks = ome_zarr._ZarrChunks(zarr.open_array(level0, mode="r"), level0, complete=True)
            slices = [tuple(slice(i * 128, i * 128 + 128) for i in idx) for idx in np.ndindex(4, 4, 4)]
            rt, rc, _ = timed(lambda: [chunks[key] for key in slices])
        assert np.array_equal(got, ref), label
        prev = best.get(label)
        best[label] = (min(prev[0], (t, c)), min(prev[1], (rt, rc))) if prev else ((t, c), (rt, rc))
result["scipy"] = best["scipy"]
result["rows"] = {{label: {{"straighten": best[label][0], "read": best[label][1],
                          "write": stores[(kind, level, shuffle, crc)][1],
                          "bytes": stores[(kind, level, shuffle, crc)][2]}}
                  for label, kind, level, shuffle, crc, reader, scheduler in rows}}
for path, _, _ in stores.values():
    shutil.rmtree(path, ignore_errors=True)
"""

# Compression ratio of a codec chain on other content: 256^3 of the scan plus Gaussian noise (sigma 40 grey values,
# like a CT's), and the real aorta CT of ../shared/data when it is there.
CODEC_RATIO = """
import os, shutil
import numpy as np
from napari_unwind.io import open_volume, write_volume
scan = open_volume(r"{zarr}").data[:256, :256, :256].compute().astype(np.int32)
noisy = np.clip(scan + np.random.default_rng(0).normal(0, 40, scan.shape), 0, 65535).astype(np.uint16)
samples = {{"noisy": noisy}}
aorta = r"{aorta}"
if aorta and os.path.exists(aorta):
    samples["aorta"] = open_volume(aorta).data.compute()
for name, data in samples.items():
    path = r"{out}" + name + ".zarr"
    write_volume(data, path, pyramid=False, compression={kind!r}, compression_level={level!r}, shuffle={shuffle!r},
                 overwrite=True)
    size = sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(os.path.join(path, "0")) for f in fs)
    result[name] = data.nbytes / size
    shutil.rmtree(path, ignore_errors=True)
"""

#: The codec table's rows: (label, kind, level, shuffle, crc32c, reader, dask scheduler).
CODEC_ROWS = [
    ("blosc zstd 3, byte shuffle, crc32c (before issue 10)", "zstd", 3, "byte", True, "zarr", "threads"),
    ("blosc zstd 3, byte shuffle, crc32c", "zstd", 3, "byte", True, "direct", "threads"),
    ("blosc zstd 1, byte shuffle, crc32c", "zstd", 1, "byte", True, "direct", "threads"),
    ("blosc zstd 5, byte shuffle, crc32c", "zstd", 5, "byte", True, "direct", "threads"),
    ("blosc zstd 3, bit shuffle, crc32c", "zstd", 3, "bit", True, "direct", "threads"),
    ("zstd 1 (no blosc, no shuffle), crc32c", "zarr-zstd", 1, "none", True, "zarr", "threads"),
    ("zstd 3 (no blosc, no shuffle), crc32c", "zarr-zstd", 3, "none", True, "zarr", "threads"),
    ("blosc lz4 1, byte shuffle, crc32c", "lz4", 1, "byte", True, "direct", "threads"),
    ("blosc lz4 5, byte shuffle, crc32c (default)", "lz4", 5, "byte", True, "direct", "threads"),
    ("blosc lz4 9, byte shuffle, crc32c", "lz4", 9, "byte", True, "direct", "threads"),
    ("blosc lz4 5, bit shuffle, crc32c", "lz4", 5, "bit", True, "direct", "threads"),
    ("blosc lz4 5, byte shuffle, no crc32c", "lz4", 5, "byte", False, "direct", "threads"),
    ("blosc lz4 5, byte shuffle, crc32c, read by zarr", "lz4", 5, "byte", True, "zarr", "threads"),
    ("  same, zarr async.concurrency 1", "lz4", 5, "byte", True, "zarr-concurrency-1", "threads"),
    ("  same, zarr async.concurrency 32", "lz4", 5, "byte", True, "zarr-concurrency-32", "threads"),
    ("blosc lz4 5, byte shuffle, crc32c, 1 dask thread", "lz4", 5, "byte", True, "direct", "synchronous"),
    ("none (uncompressed), crc32c", "none", None, "auto", True, "direct", "threads"),
]


def codecs(work: Path, repeat: int) -> None:
    """The codec table: size, reading and straightening end to end for each codec chain of the working store."""
    zarr_path = work / "scan512.zarr"
    _make_scan(zarr_path, (512, 512, 512))
    curve = {"n": 512, "ns": OUT_SHAPE[0], "half": (OUT_SHAPE[1] - 1) // 2}
    code = CODEC_TABLE.replace("{n}", str(curve["n"])).replace("{ns}", str(curve["ns"])).replace(
        "{half}", str(curve["half"]))
    r = run_isolated(code.format(zarr=zarr_path, work=work, repeat=repeat, rows=repr(CODEC_ROWS)), timeout=7200)
    aorta = Path(__file__).resolve().parents[2] / "shared" / "data" / "aorta_ct.nrrd"
    scipy_s = r["scipy"][0]
    rows = [["codec chain (128^3 chunks)", "MB", "ratio smooth", "ratio noisy", "ratio aorta CT", "write s",
             "decode, 1 thread: MB/s (per CPU s)",
             "straighten: s (CPU s)", "x scipy"]]
    for label, kind, level, shuffle, crc, reader, scheduler in CODEC_ROWS:
        row = r["rows"][label]
        ratios = {"noisy": "", "aorta": ""}
        if kind in ("lz4", "zstd", "none") and crc and reader == "direct" and scheduler == "threads":
            q = run_isolated(CODEC_RATIO.format(zarr=zarr_path, out=work / "ratio", aorta=aorta, kind=kind,
                                                level=level, shuffle=shuffle))
            ratios = {k: f"{q[k]:.2f}" if k in q else "" for k in ratios}
        (st, sc), (rt, rc) = row["straighten"], row["read"]
        mb = 2 * 512**3 / 1e6
        rows.append([label, f"{row['bytes'] / 1e6:.0f}", f"{2 * 512**3 / row['bytes']:.2f}", ratios["noisy"],
                     ratios["aorta"], f"{row['write']:.2f}", f"{mb / rt:.0f} ({mb / rc:.0f})", f"{st:.3f} ({sc:.2f})",
                     f"{scipy_s / st:.2f}"])
    print(f"\nscipy map_coordinates (1 thread, precomputed coordinates): {scipy_s:.3f} s (CPU {r['scipy'][1]:.2f} "
          f"s); output {OUT_SHAPE[0]} x {OUT_SHAPE[1]} x {OUT_SHAPE[2]} uint16 from the 512^3 uint16 scan (smooth); "
          f"every row equals scipy exactly; best of {repeat} rounds, each round timing scipy and every row in turn in "
          "one process; decode = the 64 chunks read, checked and decoded one after the other in one thread (no dask); "
          "straighten on the dask threads unless said\n")
    print(table(rows))


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


def small(repeat: int) -> None:
    """The small job: 128 x 97 x 97 from a 320^3 numpy volume, end to end, against scipy in the same process."""
    r = run_isolated(SMALL.format(n=320, ns=128, half=48, repeat=max(repeat, 15)))
    shape = " x ".join(map(str, r["shape"]))
    rows = [["job (output " + shape + " uint16 from a 320^3 numpy volume, order 1)", "seconds (best)",
             "seconds (median)", "x scipy (best)", "max |diff|"],
            ["scipy map_coordinates, 1 thread, precomputed coordinates", f"{r['scipy']:.4f}",
             f"{r['scipy_median']:.4f}", "1.00", ""],
            ["straighten(vol, d).data.compute(), end to end (threads)", f"{r['ours']:.4f}",
             f"{r['ours_median']:.4f}", f"{r['scipy'] / r['ours']:.2f}", str(r["max_diff"])]]
    print(f"\nsmall job, best and median of {max(repeat, 15)} alternating runs\n")
    print(table(rows))


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
    ap.add_argument("--small", action="store_true", help="only the small job (128 x 97 x 97 from a 320^3 array)")
    ap.add_argument("--codecs", action="store_true", help="the working store's codec table instead")
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
        elif args.small:
            small(args.repeat)
        elif args.codecs:
            codecs(work, args.repeat)
        else:
            throughput(work, args.repeat)
            small(args.repeat)
    finally:
        if temp:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
