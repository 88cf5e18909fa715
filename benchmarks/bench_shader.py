"""Live straight view (issue 12): the GPU shader against CPU re-straightening, on this machine's GL (llvmpipe).

Run under Xvfb:
    QT_QPA_PLATFORM=xcb xvfb-run -a -s "-screen 0 1600x1200x24" .venv/bin/python -m benchmarks.bench_shader [--big]

Measures, on a smooth random scan of N^3 float32 with a bent deformation (quarter circle, cage N/8):
- edit -> new frame: the shader (frame table upload + draw + readback) against the original's approach, CPU
  re-straightening (``straighten`` order 1 at the same straight grid, upload of the straight volume to the layer,
  the same draw + readback), same volume, same viewer, same canvas size;
- frame time of the straight view in MIP and translucent modes (256^3, and 512^3 with --big);
- frames per second while dragging a keyframe (a sequence of small moves, each drawn).
"""
from __future__ import annotations

import argparse
import itertools
import time

import numpy as np
from scipy import ndimage

from napari_unwind.deformation import Deformation
from napari_unwind.warp import straighten


def scan(n: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    vol = ndimage.uniform_filter(rng.random((n, n, n), dtype=np.float32), 5)
    vol -= vol.min()
    vol /= vol.max()
    return vol


def bent(n: int, dx: float = 0.0) -> Deformation:
    r = 0.6 * n
    t = np.linspace(0, np.pi / 2, 5)
    pos = np.stack([r * np.sin(t), r * (1 - np.cos(t)), np.zeros_like(t)], axis=1) + [0.15 * n, 0.15 * n, 0.5 * n]
    pos[2, 2] += dx
    nn = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    u = np.tile([0.0, 0.0, 1.0], (5, 1))
    v = np.cross(nn, u)
    return Deformation.from_keyframes(pos, np.stack([u, v, nn], axis=1), (n / 8, n / 8), spacing=(1.0, 1.0, 1.0),
                                      origin=(0.0, 0.0, 0.0))


def _best(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def measure(viewer, canvas, n: int, rows: list) -> None:
    from napari_unwind._napari._straight_view import StraightView

    vol = scan(n)
    sv = StraightView(viewer, vol)
    d = bent(n)
    sv.update(d)
    sv.layer.contrast_limits = (0, 1)
    viewer.reset_view()
    shape = sv._shape
    canvas.render()
    for mode in ("mip", "translucent"):
        sv.layer.rendering = mode
        canvas.render()
        rows.append((f"{n}^3 straight view {shape}, frame time {mode}", _best(canvas.render, 3)))
    sv.layer.rendering = "mip"
    canvas.render()

    # edit -> new frame, shader
    k = [0]
    ticks = itertools.count()

    def shader_edit():
        k[0] += 1
        sv.update(bent(n, dx=0.5 * (k[0] % 7)))
        canvas.render()

    shader = _best(shader_edit, 5)
    rows.append((f"{n}^3 edit -> frame, shader", shader))
    shader_only = _best(lambda: sv.update(bent(n, dx=0.5 * (next(ticks) % 7))), 5)
    rows.append((f"{n}^3 edit without the draw, shader (frame table upload)", shader_only))

    # fps while dragging: 10 successive moves, each drawn
    t0 = time.perf_counter()
    for i in range(10):
        sv.update(bent(n, dx=0.3 * i))
        canvas.render()
    fps = 10 / (time.perf_counter() - t0)

    # edit -> frame, CPU re-straightening at the same straight grid (the original's approach)
    sv.layer.visible = False
    cpu_layer = viewer.add_image(np.asarray(straighten(vol, d, spacing=1.0, order=1).data), contrast_limits=(0, 1))
    canvas.render()

    def cpu_edit():
        k[0] += 1
        cpu_layer.data = np.asarray(straighten(vol, bent(n, dx=0.5 * (k[0] % 7)), spacing=1.0, order=1).data)
        canvas.render()

    rows.append((f"{n}^3 frame time mip, napari's shader on the CPU-straightened volume", _best(canvas.render, 3)))
    cpu = _best(cpu_edit, 3)
    cpu_only = _best(lambda: setattr(cpu_layer, "data", np.asarray(
        straighten(vol, bent(n, dx=0.5 * (next(ticks) % 7)), spacing=1.0, order=1).data)), 3)
    rows.append((f"{n}^3 edit -> frame, CPU re-straighten + upload", cpu))
    rows.append((f"{n}^3 edit without the draw, CPU straighten + layer upload", cpu_only))
    rows.append((f"{n}^3 shader / CPU, edit -> frame", shader / cpu))
    rows.append((f"{n}^3 shader / CPU, edit without the draw", shader_only / cpu_only))
    rows.append((f"{n}^3 fps while dragging (shader, mip)", fps))
    viewer.layers.remove(cpu_layer)
    sv.close()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--big", action="store_true", help="also 512^3")
    args = ap.parse_args()

    import napari

    from napari_unwind._napari import _private

    viewer = napari.Viewer(show=True)
    viewer.window._qt_window.resize(1000, 800)
    viewer.dims.ndisplay = 3
    canvas = _private.scene_canvas(viewer)
    print(f"canvas {canvas.size}, GL 3D texture limit {_private.max_3d_texture_size()}")
    rows = []
    for n in [256] + ([512] if args.big else []):
        measure(viewer, canvas, n, rows)
    for name, value in rows:
        unit = "" if ("/" in name or "fps" in name) else " s"
        print(f"| {name} | {value:.3f}{unit} |")
    viewer.close()


if __name__ == "__main__":
    main()
