"""Take the user guide's screenshots of the real plugin, step by step, on the bundled tank phantom.

    xvfb-run -a -s "-screen 0 1600x1200x24" .venv/bin/python scripts/screenshots.py [--out docs/images]

Drives the Unwind dock the way a user does (open the scan, segment, click a fish, accept the ends, compute the
skeleton, refine, export) through its public methods and napari's own mouse callbacks, and saves a picture of the
whole window after each step. Needs napari with Qt and an X display with GL (Xvfb + Mesa); nothing here is a mock.
Look at every picture before committing it.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np


def _wait(app, cond, timeout: float = 300.0) -> None:
    t0 = time.monotonic()
    while not cond():
        app.processEvents()
        time.sleep(0.02)
        if time.monotonic() - t0 > timeout:
            raise TimeoutError("the dock did not finish in time")
    for _ in range(20):
        app.processEvents()
        time.sleep(0.01)


def _click(layer, world, *, dims_displayed=(1, 2)) -> None:
    """A click as napari's canvas delivers it to the active layer (press, release at the same place)."""
    from napari.utils._proxies import ReadOnlyWrapper
    from napari.utils.interactions import mouse_press_callbacks, mouse_release_callbacks

    common = dict(position=tuple(float(c) for c in world), modifiers=[], view_direction=None,
                  dims_displayed=list(dims_displayed), handled=False)
    for kind, fn in (("mouse_press", mouse_press_callbacks), ("mouse_release", mouse_release_callbacks)):
        fn(layer, ReadOnlyWrapper(SimpleNamespace(type=kind, **common), exceptions=("handled",)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "images"),
                    help="folder for the PNG files (default docs/images)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    import napari
    from qtpy.QtCore import Qt
    from qtpy.QtWidgets import QApplication

    from napari_unwind._napari._widget import UnwindWidget
    from napari_unwind.datasets import tank_phantom
    from napari_unwind.io import write_volume

    tmp = Path(tempfile.mkdtemp(prefix="unwind-shots-"))
    tank = tank_phantom(n_fish=3, seed=0, length=110.0, body_radius=7.0)
    scan = tmp / "tank.nrrd"
    write_volume(tank.volume, scan, spacing=tank.spacing, unit=tank.unit)

    viewer = napari.Viewer(show=True, title="napari-unwind")
    viewer.window._qt_window.resize(1600, 1150)
    app = QApplication.instance()
    dock = UnwindWidget(viewer)
    dock_widget = viewer.window.add_dock_widget(dock, name="Unwind", area="right")
    viewer.window._qt_window.resizeDocks([dock_widget], [560], Qt.Orientation.Horizontal)

    def shot(name: str, page: int | None = None) -> None:
        if page is not None:
            dock.toolbox.setCurrentIndex(page)
        for _ in range(30):
            app.processEvents()
            time.sleep(0.01)
        path = out / f"{name}.png"
        img = viewer.screenshot(canvas_only=False, flash=False)
        import imageio.v3 as iio

        iio.imwrite(path, img)
        print(f"{path} ({img.shape[1]} x {img.shape[0]})")

    def run(job, timeout: float = 300.0) -> None:
        if job is None:
            raise RuntimeError(f"the dock refused: {dock.status.text()}")
        _wait(app, lambda: job.done and dock.idle, timeout)
        if dock.status.text().startswith("error"):
            raise RuntimeError(dock.status.text())

    run(dock.open_scan(scan))
    viewer.reset_view()
    shot("01-scan", 0)

    run(dock.segment())
    dock.count_slider.setValue(6)
    _wait(app, lambda: dock.idle and dock.features is not None and dock.features.k == 6)
    fish = tank.fish[0]
    p = np.round(fish.centerline[len(fish.centerline) // 2]).astype(int)
    world = p * np.asarray(dock.volume.spacing) + np.asarray(dock.volume.origin)
    viewer.dims.set_point(0, float(world[0]))
    _click(dock._features_layer, world)
    _wait(app, lambda: dock.idle)
    shot("02-segment", 1)

    run(dock.suggest_ends())
    # in 3D, so both ends show (in 2D each lies on its own slice)
    viewer.dims.ndisplay = 3
    viewer.layers["features"].visible = False
    viewer.layers[scan.name].visible = False
    viewer.reset_view()
    viewer.scene.camera.angles = (-10.0, 25.0, 70.0)
    viewer.scene.camera.zoom *= 0.85
    shot("03-ends", 2)
    viewer.layers["features"].visible = True
    viewer.layers[scan.name].visible = True
    viewer.dims.ndisplay = 2

    run(dock.run_skeleton(), timeout=600)
    # the 3D view from the side, the fish's own features only: the curve, its keyframe frames and the cage
    viewer.dims.ndisplay = 3
    # (the tube wall would hide the fish in a projection of the scan: show the picked fish's mask instead)
    hidden = [name for name in ("features", "straight preview", scan.name) if name in viewer.layers]
    for name in hidden:
        viewer.layers[name].visible = False
    viewer.layers["selection"].opacity = 0.35
    viewer.reset_view()
    viewer.scene.camera.angles = (-10.0, 25.0, 70.0)
    viewer.scene.camera.zoom *= 0.85
    shot("04-skeleton", 3)
    for name in hidden:
        viewer.layers[name].visible = True
    viewer.layers["selection"].opacity = 0.6

    dock.toolbox.setCurrentIndex(4)
    dock.model.set_s(0.45 * dock.model.deformation.length)
    _wait(app, lambda: dock.idle)
    # the straight preview next to the bent scan, in 2D, at the same position along the fish
    viewer.dims.ndisplay = 2
    viewer.layers["straight preview"].visible = True
    viewer.reset_view()
    shot("05-refine", 4)

    # the live straight view (GLSL shader), to set beside the bent view with its cage (04)
    panel = dock.refine_panel
    for layer in viewer.layers:
        layer.visible = layer.name in ("unwind cage", "unwind curve")
    panel.live_check.setChecked(True)
    straight_layer = viewer.layers["straight view"] if "straight view" in viewer.layers else None
    if straight_layer is not None:
        straight_layer.contrast_limits = tuple(float(v) for v in np.percentile(tank.volume, [60, 99.5]))
        viewer.layers["unwind cage"].visible = viewer.layers["unwind curve"].visible = False
        lo, hi = np.asarray(straight_layer.extent.world)
        viewer.scene.camera.center = tuple((lo + hi) / 2)
        viewer.scene.camera.angles = (0.0, 0.0, 90.0)
        viewer.scene.camera.zoom = 0.8 * min(viewer.window._qt_viewer.canvas.size) / float(max(hi - lo))
        shot("08-live-straight", 4)
    panel.live_check.setChecked(False)
    for layer in viewer.layers:
        layer.visible = True

    run(dock.export(tmp / "fish-straight.nrrd"))
    viewer.dims.ndisplay = 3
    straight = None
    for layer in viewer.layers:
        layer.visible = "fish-straight" in layer.name
        straight = layer if layer.visible else straight
    # the straight fish from the side, centred (reset_view would frame the whole scan as well)
    lo, hi = np.asarray(straight.extent.world)
    viewer.scene.camera.center = tuple((lo + hi) / 2)
    viewer.scene.camera.angles = (0.0, 0.0, 90.0)
    viewer.scene.camera.zoom = 0.8 * min(viewer.window._qt_viewer.canvas.size) / float(max(hi - lo))
    shot("06-export", 5)

    run(dock.save_session(tmp / "fish.unwind.json"))
    shot("07-session", 6)
    viewer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
