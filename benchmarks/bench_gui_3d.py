"""Switching napari to 3D with Labels shown (issue 21 item 6): napari's volume ray caster (the old behaviour) against
the dock's 3D stand-ins (:func:`napari_unwind._napari._layers.in_3d`: a coarse Surface for the Labels, and with
``--with-scan`` the scan's Image ray cast from a block-reduced copy).

    QT_QPA_PLATFORM=xcb xvfb-run -a -s "-screen 0 1600x1200x24" .venv/bin/python -m benchmarks.bench_gui_3d
    ... -m benchmarks.bench_gui_3d --length 400 --radius 20 --repeat 2

The Labels are a tank phantom's fish labels (``tank_phantom(length, body_radius)``, 440 x 148 x 148 voxels at the
defaults), shown at opacity 0.4 in an 1200 x 900 window on Mesa llvmpipe. Before timing, the fresh window is let
settle (three forced draws, then 0.5 s of ``processEvents()``): after a single draw the first switch also carried
~3 s of the window's pending first paint, unrelated to 3D. One measurement is ``viewer.dims.ndisplay = 3`` plus the
first forced draw (``canvas.native.repaint()`` and ``processEvents()``: what froze the viewer), then the next draw
and the median of four frames while rotating (camera angles changed before each). Each measurement runs in a fresh
process (a GL context of its own, no shader cached from the other mode), old and new alternating; the machine is
shared: compare ratios, not seconds. ``--with-scan`` also shows the scan's Image layer (old: napari's ray caster on
the full volume; new: ``in_3d`` on it too, napari's ray caster on the copy).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time


def one(mode: str, length: float, radius: float, with_scan: bool) -> dict:
    import napari
    from qtpy.QtWidgets import QApplication

    from napari_unwind._napari._layers import in_3d
    from napari_unwind.datasets import tank_phantom

    t = tank_phantom(length=length, body_radius=radius)
    viewer = napari.Viewer(show=True)
    viewer.window._qt_window.resize(1200, 900)
    app = QApplication.instance()
    layers = [viewer.add_image(t.volume, name="tank")] if with_scan else []
    layers.append(viewer.add_labels(t.labels, name="features", opacity=0.4))
    if mode == "new":
        for layer in layers:
            in_3d(viewer, layer)
    canvas = viewer.window._qt_viewer.canvas.native

    def draw() -> None:
        canvas.repaint()
        app.processEvents()

    for _ in range(3):  # let the fresh window settle: its pending first paint is no part of the switch
        draw()
    t_settle = time.perf_counter()
    while time.perf_counter() - t_settle < 0.5:
        app.processEvents()
    t0 = time.perf_counter()
    viewer.dims.ndisplay = 3
    draw()
    t1 = time.perf_counter()
    draw()
    t2 = time.perf_counter()
    frames = []
    for i in range(4):
        viewer.camera.angles = (0.0, 10.0 * (i + 1), 90.0)
        t3 = time.perf_counter()
        draw()
        frames.append(time.perf_counter() - t3)
    out = {"mode": mode, "shape": list(t.labels.shape), "switch": t1 - t0, "next": t2 - t1,
           "rotate": statistics.median(frames)}
    viewer.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--length", type=float, default=400.0)
    ap.add_argument("--radius", type=float, default=20.0)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--with-scan", action="store_true")
    ap.add_argument("--one", choices=("old", "new"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one, args.length, args.radius, args.with_scan)))
        return
    runs: dict[str, list[dict]] = {"old": [], "new": []}
    for _ in range(args.repeat):
        for mode in ("old", "new"):
            cmd = [sys.executable, "-m", "benchmarks.bench_gui_3d", "--one", mode, "--length", str(args.length),
                   "--radius", str(args.radius)] + (["--with-scan"] if args.with_scan else [])
            res = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy(), check=True)
            runs[mode].append(json.loads(res.stdout.strip().splitlines()[-1]))
            r = runs[mode][-1]
            print(f"{mode}: switch + first draw {r['switch']:.2f} s, next draw {r['next']:.2f} s, "
                  f"rotating {r['rotate']:.2f} s a frame", flush=True)
    shape = "x".join(str(v) for v in runs["old"][0]["shape"])
    old = statistics.median(r["switch"] for r in runs["old"])
    new = statistics.median(r["switch"] for r in runs["new"])
    old_n = statistics.median(r["next"] for r in runs["old"])
    new_n = statistics.median(r["next"] for r in runs["new"])
    old_r = statistics.median(r["rotate"] for r in runs["old"])
    new_r = statistics.median(r["rotate"] for r in runs["new"])
    scan = " + scan Image" if args.with_scan else ""
    print(f"\nLabels {shape}{scan}, median of {args.repeat}:")
    print(f"| | old (volume ray cast) | new (Surface, step 2{'; Image copy' if args.with_scan else ''}) | ratio |")
    print("|---|---|---|---|")
    print(f"| ndisplay=3 + first draw | {old:.2f} s | {new:.2f} s | {old / new:.1f}x |")
    print(f"| next draw | {old_n:.2f} s | {new_n:.2f} s | {old_n / max(new_n, 1e-9):.1f}x |")
    print(f"| a frame while rotating | {old_r:.2f} s | {new_r:.2f} s | {old_r / max(new_r, 1e-9):.1f}x |")
    for mode in ("old", "new"):
        print(f"{mode} runs: switch " + " / ".join(f"{r['switch']:.2f}" for r in runs[mode]) + " s; rotating "
              + " / ".join(f"{r['rotate']:.2f}" for r in runs[mode]) + " s")


if __name__ == "__main__":
    main()
