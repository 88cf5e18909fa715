"""Plugin latency (issue 11): an edit to the updated 2D plane, and an edit to the updated CPU straight preview.

    QT_QPA_PLATFORM=xcb xvfb-run -a -s "-screen 0 1600x1200x24" .venv/bin/python -m benchmarks.bench_plugin
    ... -m benchmarks.bench_plugin --repeat 15

The scan is a 256^3 uint16 fish phantom (s-bend, twisted, in its tube) held as a two-level pyramid (level 1 the
2x2x2 block mean), the deformation its true centreline with 9 keyframes and the true cage. Everything runs in
this one process, alternating ours and the baseline each round (the machine is shared: compare ratios, not
seconds). One edit is a twist of the middle keyframe by +-0.01 rad.

Plane (goal <= 30 ms):
  (a) ``EditModel.twist`` with the 2D editor listening: the model edit, the cross-section resampled and put in the
      canvas's image (what the UI thread pays before the next frame);
  (b) the same through the whole Refine panel: editor, s strip, the preview's request (its worker runs off the UI
      thread); the wireframe layers and fold marks wait for the event loop to be free;
  (b2) (b) until the wireframe layers and the fold marks are updated too (the event loop running);
  (c) (a) plus drawing the canvas and reading it back from GL (``canvas.render()``, an upper bound of a frame);
  baseline: ``scipy.ndimage.map_coordinates(order=1)`` of the same plane's points on the numpy scan (points
  precomputed, only the call timed).
Preview (goal <= 150 ms):
  (d) ``EditModel.twist`` until the "straight preview" layer shows the result (the Qt event loop running);
  (e) ``preview_volume`` alone (choose the level, straighten it, compute);
  baseline: ``map_coordinates(order=1)`` on precomputed coordinates of the same straight grid on the same level's
  numpy array.
"""

from __future__ import annotations

import argparse
import statistics
import time

import dask.array as da
import numpy as np
from scipy import ndimage

from benchmarks._util import table


def make_scan():
    from napari_unwind.datasets import fish_phantom
    from napari_unwind.deformation import Deformation
    from napari_unwind.io import Volume

    ph = fish_phantom(shape=(256, 256, 256), length=220.0, body_radius=28.0, seed=0)
    base = ph.volume
    lvl1 = base[:256, :256, :256].reshape(128, 2, 128, 2, 128, 2).mean(axis=(1, 3, 5)).astype(np.uint16)
    sp = np.asarray(ph.spacing)
    vol = Volume(da.from_array(base, chunks=128), spacing=ph.spacing, unit=ph.unit,
                 levels=(da.from_array(base, chunks=128), da.from_array(lvl1, chunks=64)),
                 level_spacings=(ph.spacing, tuple(sp * 2)), level_origins=((0.0, 0.0, 0.0), tuple(sp / 2)))
    idx = np.linspace(0, len(ph.arclength) - 1, 9).round().astype(int)
    d = Deformation.from_keyframes(ph.centerline_physical[idx], ph.frames[idx], ph.half_extent,
                                   spacing=ph.spacing, unit=ph.unit)
    return vol, base, d


def plane_points(cross, d):
    """Voxel coordinates of the cross-section's pixels, computed from its geometry (as the baseline sees them)."""
    h, w = cross.image.shape
    xs = cross.x0 + cross.pixel * np.arange(w)
    ys = cross.y0 + cross.pixel * np.arange(h)
    sp = np.asarray(d.spacing)
    base = (cross.centre - np.asarray(d.origin)) / sp
    du, dv = cross.frame[0] / sp, cross.frame[1] / sp
    pts = base[:, None, None] + dv[:, None, None] * ys[None, :, None] + du[:, None, None] * xs[None, None, :]
    return pts.reshape(3, -1)


def grid_points(d, level_array_spacing, level_origin, ds):
    base, dv, du = d.slice_geometry(ds, voxels=False)
    ns, ny, nx = d.output_shape(ds)
    pts = (base[:, None, None, :] + np.arange(ny)[None, :, None, None] * dv[:, None, None, :]
           + np.arange(nx)[None, None, :, None] * du[:, None, None, :])
    return ((pts - level_origin) / level_array_spacing).reshape(-1, 3).T.copy()


def summary(name, times, base_times, goal=None):
    med, best = statistics.median(times), min(times)
    bmed = statistics.median(base_times)
    ratio = bmed / med
    return [name, f"{1e3 * med:.1f}", f"{1e3 * best:.1f}", f"{1e3 * bmed:.1f}", f"{ratio:.2f}x",
            "" if goal is None else ("yes" if med <= goal else "NO") + f" (<= {1e3 * goal:.0f} ms)"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=11)
    args = ap.parse_args()

    import napari
    from napari.qt import get_qapp

    from napari_unwind._napari._editor_canvas import EditorCanvas
    from napari_unwind._napari._refine import RefinePanel
    from napari_unwind.editing import EditModel
    from napari_unwind.preview import level_deformation, preview_level, preview_volume

    t0 = time.perf_counter()
    vol, base, d = make_scan()
    print(f"scan {vol.shape} {vol.dtype}, levels {[lv.shape for lv in vol.levels]}, made in "
          f"{time.perf_counter() - t0:.1f} s; deformation {len(d)} keyframes, length {d.length:.0f}, "
          f"cage {d.bounds[0].round(1).tolist()}")
    base_f = base.astype(np.float32)
    app = get_qapp()
    rows = [["measure", "median ms", "best ms", "baseline median ms", "baseline / ours", "goal met"]]

    # ---------------------------------------------------------------- the plane, the editor alone
    model = EditModel(d)
    model.select_keyframe(4)
    editor = EditorCanvas(model, lambda: vol)
    editor.native.resize(420, 420)
    editor.native.show()
    for _ in range(20):
        app.processEvents()
    sign = 1.0
    ta, tc, tb = [], [], []
    for _ in range(args.repeat):
        sign = -sign
        t = time.perf_counter()
        model.twist(0.01 * sign)
        ta.append(time.perf_counter() - t)
        pts = plane_points(editor.cross, model.deformation)
        t = time.perf_counter()
        ndimage.map_coordinates(base_f, pts, order=1, mode="constant", cval=0.0, prefilter=False)
        tb.append(time.perf_counter() - t)
        t = time.perf_counter()
        model.twist(-0.01 * sign)
        editor.canvas.render()
        tc.append(time.perf_counter() - t)
    shape = editor.cross.image.shape
    rows.append(summary(f"(a) edit -> 2D plane ({shape[1]} x {shape[0]} px), editor", ta, tb, 0.030))
    rows.append(summary("(c) (a) + GL draw and read-back", tc, tb, 0.030))
    editor.native.close()

    # ---------------------------------------------------------------- the whole panel and the preview
    viewer = napari.Viewer(show=False)
    viewer.add_image(vol.data, name="scan", scale=vol.spacing)
    model = EditModel(d)
    panel = RefinePanel(viewer, model, lambda: vol)
    viewer.window.add_dock_widget(panel, name="refine")
    model.select_keyframe(4)
    preview = panel.preview

    def wait_preview():
        while not (preview.idle and preview.shown_generation == preview.generation):
            app.processEvents()
            time.sleep(0.0005)

    wait_preview()
    level = preview_level(vol, d)
    dl = level_deformation(vol, d, level)
    ds = float(min(dl.spacing))
    lvl_np = np.asarray(vol.levels[level]).astype(np.float32)
    coords = grid_points(d, np.asarray(vol.level_spacings[level]), np.asarray(vol.level_origins[level]), ds)
    tbp, tbw, tdp, tep, tbase = [], [], [], [], []
    for _ in range(args.repeat):
        sign = -sign
        t = time.perf_counter()
        model.twist(0.01 * sign)
        tbp.append(time.perf_counter() - t)
        while panel.pending:
            app.processEvents()
        tbw.append(time.perf_counter() - t)
        wait_preview()
        tdp.append(time.perf_counter() - t)
        t = time.perf_counter()
        preview_volume(vol, model.deformation)
        tep.append(time.perf_counter() - t)
        t = time.perf_counter()
        ndimage.map_coordinates(lvl_np, coords, order=1, mode="constant", cval=0.0, prefilter=False)
        tbase.append(time.perf_counter() - t)
    out = preview.layer.data.shape
    rows.append(summary("(b) edit -> 2D plane, whole Refine panel (UI thread)", tbp, tb, 0.030))
    rows.append(summary("(b2) (b) + wireframe layers and fold marks", tbw, tb))
    rows.append(summary(f"(d) edit -> preview layer shown (level {level}, {out[0]} x {out[1]} x {out[2]})", tdp,
                        tbase, 0.150))
    rows.append(summary("(e) preview_volume alone", tep, tbase, 0.150))
    print(table(rows))
    print(f"baseline points: plane {shape[0] * shape[1]}, preview {coords.shape[1]}; repeats {args.repeat}")
    viewer.close()


if __name__ == "__main__":
    main()
