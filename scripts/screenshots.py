"""Take the user guide's screenshots of the real plugin, step by step: on the bundled tank sample, and on the shared
aorta CT with its expert mask.

    cd /work/main && QT_QPA_PLATFORM=xcb xvfb-run -a -s "-screen 0 1600x1200x24" \\
        .venv/bin/python scripts/screenshots.py [--out docs/images] [--only tank|aorta]

The window is napari's own layout with its own dock widths, filling the 1600 x 1200 screen; the dock is added the
way the Plugins menu adds it (``add_plugin_dock_widget("napari-unwind", "Unwind")``, never widened) and the sample
is opened the way File > Open Sample does. napari's settings are read from a fresh temporary file, so a saved window
geometry or layout on this machine does not change the pictures. The dock is driven through its public methods (open
the scan, segment, click a fish, suggest the ends, compute the skeleton, refine, export, save the session; for the
aorta: open the scan, open the mask as the selection, ...) and a picture of the whole window is saved after each step.

The aorta set needs ``../shared/data`` (relative to the repository); without that folder it is skipped with a note.
A step that fails there is photographed anyway (the dock's status line says why) and reported on stdout.
Needs napari with Qt and an X display with GL (Xvfb + Mesa); nothing here is a mock. Look at every picture before
committing it.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
SCREEN = (1600, 1200)
#: the 3D camera on the aorta: the arch at the top, the descending aorta down the canvas
AORTA_VIEW = (90.0, 0.0, 0.0)


def _scan_contrast(layer, volume) -> None:
    """The contrast napari-unwind's reader gives a scan (File > Open): the dock's own "Open file..." leaves napari's
    limits of lazy data, [0, 1] for this CT (black and white); set the reader's when they differ, and say so."""
    from napari_unwind._napari._reader import contrast_limits

    limits = tuple(float(v) for v in contrast_limits(volume.levels))
    if not np.allclose(layer.contrast_limits, limits):
        print(f"NOTE the dock opened {layer.name!r} with contrast limits {tuple(layer.contrast_limits)}, File > Open "
              f"gives {limits}: set to those")
        layer.contrast_limits = limits


def _click(layer, world, *, dims_displayed=(1, 2)) -> None:
    """A click as napari's canvas delivers it to the active layer (press, release at the same place)."""
    from napari.utils._proxies import ReadOnlyWrapper
    from napari.utils.interactions import mouse_press_callbacks, mouse_release_callbacks

    common = dict(position=tuple(float(c) for c in world), modifiers=[], view_direction=None,
                  dims_displayed=list(dims_displayed), handled=False)
    for kind, fn in (("mouse_press", mouse_press_callbacks), ("mouse_release", mouse_release_callbacks)):
        fn(layer, ReadOnlyWrapper(SimpleNamespace(type=kind, **common), exceptions=("handled",)))


class Session:
    """A napari window at the screen's size with the Unwind dock, as a user has it, and its picture taker."""

    def __init__(self, out: Path) -> None:
        import napari
        from qtpy.QtWidgets import QApplication

        self.out = out
        self.viewer = napari.Viewer(show=True)
        self.app = QApplication.instance()
        # napari's first start sizes the window to its layout's hint (about 1090 x 630, too small to show a step
        # whole); a user maximises it: the screen's size. The docks keep the widths napari gives them.
        self.viewer.window._qt_window.resize(*SCREEN)
        self.dock, self.w = self.viewer.window.add_plugin_dock_widget("napari-unwind", "Unwind")
        self.settle(50)
        self.failures: list[str] = []

    def settle(self, n: int = 30) -> None:
        for _ in range(n):
            self.app.processEvents()
            time.sleep(0.01)

    def wait(self, cond, timeout: float = 600.0) -> None:
        t0 = time.monotonic()
        while not cond():
            self.app.processEvents()
            time.sleep(0.02)
            if time.monotonic() - t0 > timeout:
                raise TimeoutError("the dock did not finish in time")
        self.settle(20)

    def run(self, job, what: str, timeout: float = 600.0, *, strict: bool = True) -> bool:
        """Wait for a dock job; False (and a note) when the dock refused it or it ended in an error."""
        w = self.w
        if job is not None:
            self.wait(lambda: job.done and w.idle, timeout)
        status = w.status.text()
        if job is None or status.startswith("error"):
            message = f"{what}: {status or 'the dock refused'}"
            if strict:
                raise RuntimeError(message)
            print(f"NOTE {message}")
            self.failures.append(message)
            return False
        return True

    def shot(self, name: str, page: int | None = None) -> None:
        import imageio.v3 as iio

        if page is not None:
            self.w.toolbox.setCurrentIndex(page)
        self.settle()
        path = self.out / f"{name}.png"
        img = self.viewer.screenshot(canvas_only=False, flash=False)
        iio.imwrite(path, img)
        print(f"{path} ({img.shape[1]} x {img.shape[0]}); status: {self.w.status.text()!r}")

    def to_3d(self, angles=None, zoom: float = 1.0) -> None:
        """The 3D view (the dock draws its Labels layers as surfaces then), framed on the visible layers."""
        self.viewer.dims.ndisplay = 3
        self.settle()
        self.viewer.reset_view()
        if angles is not None:
            self.viewer.scene.camera.angles = angles
        self.viewer.scene.camera.zoom *= zoom

    def show_only(self, *names: str) -> None:
        for layer in self.viewer.layers:
            layer.visible = layer.name in names

    def side_view(self, layer, *, angles=(0.0, 0.0, 90.0), fill: float = 0.8, box=None) -> None:
        """The 3D view centred on ``layer`` (or the world ``box``: low and high corners) at ``angles``, its longest
        side ``fill`` of the canvas."""
        self.viewer.dims.ndisplay = 3
        self.settle()
        lo, hi = np.asarray(layer.extent.world if box is None else box, dtype=float)
        self.viewer.scene.camera.center = tuple((lo + hi) / 2)
        self.viewer.scene.camera.angles = angles
        self.viewer.scene.camera.zoom = fill * min(self.viewer.window._qt_viewer.canvas.size) / float(max(hi - lo))

    def close(self) -> None:
        if self.w.refine_panel is not None:
            self.wait(lambda: self.w.refine_panel.preview.idle, 60)
        self.viewer.close()
        self.settle()


def tank_set(out: Path, tmp: Path) -> list[str]:
    """01-scan ... 08-live-straight: File > Open Sample > napari-unwind > Tank of fish, one fish straightened."""
    s = Session(out)
    viewer, w = s.viewer, s.w
    layers = viewer.open_sample("napari-unwind", "tank")  # File > Open Sample > napari-unwind > Tank of fish (...)
    image = next(lyr for lyr in layers if lyr.name == "tank")
    truth = next(lyr for lyr in layers if lyr.name == "tank true fish")
    w.use_layer(image)
    s.settle()
    viewer.reset_view()
    s.shot("01-scan", 0)

    s.run(w.segment(), "segment")
    # the first fish of the true labels: a voxel on its centre slice, clicked in 2D as a user does
    fish = np.argwhere(np.asarray(truth.data) == 1)
    p = fish[np.argsort(fish[:, 0])[len(fish) // 2]]
    world = p * np.asarray(w.volume.spacing) + np.asarray(w.volume.origin)
    viewer.dims.set_point(0, float(world[0]))
    viewer.layers.selection.active = w._features_layer
    _click(w._features_layer, world)
    s.wait(lambda: w.idle)
    if not w.selected:
        raise RuntimeError(f"the click selected nothing: {w.status.text()}")
    s.shot("02-segment", 1)

    s.run(w.suggest_ends(), "suggest ends")
    # in 3D, so both ends show (in 2D each lies on its own slice): the selected fish and its ends
    s.show_only("selection", "selection (3D)", "ends")
    ends = np.asarray(viewer.layers["ends"].data)[:, -3:]
    s.side_view(None, angles=(-10.0, 25.0, 70.0), fill=0.75, box=(ends.min(axis=0), ends.max(axis=0)))
    s.shot("03-ends", 2)

    viewer.dims.ndisplay = 2
    for layer in viewer.layers:
        layer.visible = layer is not truth
    s.run(w.run_skeleton(), "skeleton", timeout=1200)
    # the 3D view from the side: the picked fish's mask with the curve, the keyframe frames and the cage (the
    # tube wall would hide the fish in a projection of the scan)
    s.show_only("selection", "selection (3D)", "ends", "unwind curve", "unwind frames", "unwind cage")
    viewer.layers["selection"].opacity = 0.35
    s.to_3d((-10.0, 25.0, 70.0), 0.85)
    s.shot("04-skeleton", 3)
    viewer.layers["selection"].opacity = 0.6

    # Refine: the straight preview beside the bent scan, in 2D, at the same position along the fish
    w.toolbox.setCurrentIndex(4)
    for layer in viewer.layers:
        layer.visible = layer is not truth
    viewer.dims.ndisplay = 2
    w.model.set_s(0.45 * w.model.deformation.length)
    s.wait(lambda: w.idle and (w.refine_panel is None or w.refine_panel.preview.idle))
    viewer.reset_view()
    s.shot("05-refine", 4)

    # the live straight view (GLSL shader), to set beside the bent view with its cage (04)
    panel = w.refine_panel
    # the fish's inside (a maximum projection of the fish at the scan's contrast is white all over)
    fish_contrast = tuple(float(v) for v in np.percentile(np.asarray(image.data), [60, 99.5]))
    if panel is not None:
        s.show_only()
        panel.live_check.setChecked(True)
        s.settle()
        if "straight view" in viewer.layers:
            live = viewer.layers["straight view"]
            live.visible = True
            live.contrast_limits = fish_contrast  # the dock frames the view itself (from the side)
            s.shot("08-live-straight", 4)
        else:
            s.failures.append(f"live straight view: {panel.live_label.text()}")
            print(f"NOTE no live straight view: {panel.live_label.text()}")
        panel.live_check.setChecked(False)
        s.settle()

    s.run(w.export(tmp / "fish-straight.nrrd"), "export")
    straight = next(lyr for lyr in viewer.layers if "fish-straight" in lyr.name)
    s.show_only(straight.name)
    straight.contrast_limits = fish_contrast
    s.side_view(straight)  # the straight fish from the side, centred (reset_view would frame the scan as well)
    s.shot("06-export", 5)

    s.run(w.save_session(tmp / "fish.unwind.json"), "save session")
    s.shot("07-session", 6)
    s.close()
    return s.failures


def aorta_set(out: Path, tmp: Path) -> list[str]:
    """aorta-01 ... aorta-05: the shared aorta CT, its expert mask as the selection, ends, skeleton, refine, export."""
    scan, mask = SHARED / "aorta_ct.nrrd", SHARED / "aorta_ct_aorta_mask.nrrd"
    if not (scan.is_file() and mask.is_file()):
        print(f"NOTE the aorta set is skipped: {SHARED} (aorta_ct.nrrd, aorta_ct_aorta_mask.nrrd) is absent")
        return []
    s = Session(out)
    viewer, w = s.viewer, s.w
    s.run(w.open_scan(scan), "open the scan")
    _scan_contrast(w.scan_layer, w.volume)
    if not s.run(w.open_mask(mask), "open the mask", strict=False):
        s.shot("aorta-01-scan-and-mask", 1)
        s.close()
        return s.failures
    mask_layer = viewer.layers[mask.name]
    # the slice through the middle of the mask, the mask over the scan
    voxels = np.argwhere(np.asarray(mask_layer.data) != 0)
    middle = float(np.median(voxels[:, 0]) * w.volume.spacing[0] + w.volume.origin[0])
    mask_layer.opacity = 0.5
    viewer.dims.ndisplay = 2
    viewer.reset_view()
    viewer.dims.set_point(0, middle)
    s.shot("aorta-01-scan-and-mask", 1)

    ok = s.run(w.suggest_ends(), "suggest ends", strict=False)
    s.show_only(mask.name, f"{mask.name} (3D)", "ends")
    s.to_3d(AORTA_VIEW, 0.9)
    s.shot("aorta-02-ends", 2)
    if not ok:
        s.close()
        return s.failures

    ok = s.run(w.run_skeleton(), "skeleton", timeout=1200, strict=False)
    s.show_only(mask.name, f"{mask.name} (3D)", "ends", "unwind curve", "unwind frames", "unwind cage")
    mask_layer.opacity = 0.35
    s.to_3d(AORTA_VIEW, 0.9)
    s.shot("aorta-03-skeleton", 3)
    if not ok or w.model.deformation is None:
        s.close()
        return s.failures

    w.toolbox.setCurrentIndex(4)
    for layer in viewer.layers:
        layer.visible = True
    mask_layer.opacity = 0.35
    viewer.dims.ndisplay = 2
    w.model.set_s(0.5 * w.model.deformation.length)
    s.wait(lambda: w.idle and (w.refine_panel is None or w.refine_panel.preview.idle))
    viewer.reset_view()
    viewer.dims.set_point(0, middle)  # the straight preview is longer than the scan: a slice through both
    s.shot("aorta-04-refine", 4)

    if s.run(w.export(tmp / "aorta-straight.nrrd"), "export", strict=False):
        straight = next(lyr for lyr in viewer.layers if "aorta-straight" in lyr.name)
        s.show_only(straight.name)
        s.side_view(straight)
    s.shot("aorta-05-export", 5)
    s.close()
    return s.failures


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "docs" / "images"), help="folder for the PNG files (default "
                    "docs/images)")
    ap.add_argument("--only", choices=("tank", "aorta"), help="take one set only")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="unwind-shots-"))
    # napari's defaults, not this machine's saved window geometry and dock layout
    os.environ["NAPARI_CONFIG"] = str(tmp / "napari-settings.yaml")

    failures = []
    if args.only in (None, "tank"):
        failures += tank_set(out, tmp)
    if args.only in (None, "aorta"):
        failures += aorta_set(out, tmp)
    for line in failures:
        print(f"failed: {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
