"""The UI keeps running while the dock's long jobs work: the longest event-loop stall during a skeleton solve and
during an export.

A QTimer fires every 10 ms on the UI thread and records the gaps between its calls while the job runs in its
worker. A gap is measured in the process's CPU time (at most its wall time): a worker that holds the GIL in a long
compiled call keeps the process busy for the whole gap, while a process that the machine's other work keeps off the
cores accrues no CPU time, so the figure does not grow with the machine's load (a wall-time bound failed on a
loaded CI machine). The goal is 100 ms (benchmarks); the test allows 250 ms.
Showing the result on the UI thread (napari adding layers: the ends, the straight preview, the wireframes, the
exported volume) is measured apart. napari's cost of a new layer is 40-80 ms to add it and 10-80 ms for its first
paint under Xvfb's software GL; the dock adds each new layer hidden and shows it on a later turn, one step a turn
(``_reveal``), so no turn holds two of them: checked by counting, per turn, the layers added and the layers shown
(a layer added visible counts twice: it is drawn in the same turn). The times are bounds against work on the UI
thread, not the goal: the 100 ms goal and its figures are in benchmarks/RESULTS.md ("edit latency and UI stalls",
measured with ``pytest -s`` on this file). Showing a result is napari's own cost and grows with the machine's load
(81-97 ms on a loaded machine, 167 ms on the official CI at dc1147e, 232-270 ms with two suites on two cores), so its
bound is SHOWN_LIMIT (400 ms); what the steps' split and the dock's collection policy keep out of a turn is checked
by counting (the turns above; tests/_napari/test_gc.py), not by time. The figures are printed (``pytest -s``).
"""

import time
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("napari")

from qtpy.QtCore import QTimer  # noqa: E402

from napari_unwind._napari import _gc  # noqa: E402
from napari_unwind._napari._widget import UnwindWidget, warming_kernels  # noqa: E402
from napari_unwind.datasets import fish_phantom  # noqa: E402
from napari_unwind.io import write_volume  # noqa: E402

pytestmark = pytest.mark.gui

#: seconds, the longest gap until the result: 9-21 ms measured with the dock's numba warm-up and collection policy;
#: without them 221-241 ms (a first call compiling) and 224-227 ms (a full collection of napari's heap)
LIMIT = 0.25
#: seconds, the longest gap while the dock shows a result (the skeleton's layers, an export, steps 1-3 from the click
#: until settled): 19-120 ms measured on a quiet machine, 167 ms on the official CI, 232-270 ms under two suites (a
#: bound of 150-250 ms failed there); 0.45 s of work on the UI thread when the export is shown reads 561 ms (planted,
#: caught). Turns with two layers, which a bound cannot tell from load, fail apart
SHOWN_LIMIT = 0.4


def layer_steps(viewer, ticks):
    """Record, for each layer added to ``viewer`` and each layer shown, the number of timer ticks so far: a list of
    (tick count, what). A layer added visible is recorded twice (added, and drawn in the same turn)."""
    steps = []

    def on_visible(event):
        if event.source.visible:
            steps.append((len(ticks), f"shown {event.source.name}"))

    def on_inserted(event):
        layer = event.value
        steps.append((len(ticks), f"added {layer.name}"))
        if layer.visible:
            steps.append((len(ticks), f"shown {layer.name}"))
        layer.events.visible.connect(on_visible)

    viewer.layers.events.inserted.connect(on_inserted)
    return steps


def crowded_turns(steps):
    """The turns (tick counts) in which more than one layer was added or shown, with what."""
    by_turn = {}
    for turn, what in steps:
        by_turn.setdefault(turn, []).append(what)
    return {turn: whats for turn, whats in by_turn.items() if len(whats) > 1}


def longest_stall(qtbot, start, timeout=120_000, settled=lambda: True, viewer=None):
    """Start a job with ``start()`` from the event loop (as a button click does) and run the loop until it is done
    and ``settled()``; return the longest gap between 10 ms timer ticks until the result reached the UI thread (the
    click included), the longest gap after it (the dock showing the result: its layers, the Refine panel's
    wireframes and preview), the number of ticks, and the turns that added or showed more than one layer of
    ``viewer``. Python's automatic full collections are measured with the step (the dock keeps them short:
    ``_napari/_gc.py``)."""
    ticks = [time.perf_counter()]
    cpu = [time.process_time()]
    steps = layer_steps(viewer, ticks) if viewer is not None else []

    def tick():
        ticks.append(time.perf_counter())
        cpu.append(time.process_time())

    timer = QTimer()
    timer.setInterval(10)
    timer.timeout.connect(tick)
    timer.start()
    jobs = []
    QTimer.singleShot(50, lambda: jobs.append(start()))
    try:
        qtbot.waitUntil(lambda: bool(jobs) and (jobs[0] is None or jobs[0].done), timeout=timeout)
        job = jobs[0]
        assert job is not None, "the job did not start"
        qtbot.waitUntil(settled, timeout=timeout)
        qtbot.wait(300)  # and the paints that follow
    finally:
        timer.stop()
    tick()
    assert job.returned_at is not None, "the job returned no result"
    t = np.asarray(ticks)
    gaps = np.minimum(np.diff(t), np.diff(np.asarray(cpu)))
    during = gaps[t[1:] <= job.returned_at]  # gaps over before the result reached the UI thread
    shown = gaps[t[1:] > job.returned_at]  # the dock showing the result
    return float(during.max(initial=0.0)), float(shown.max(initial=0.0)), len(ticks), crowded_turns(steps)


@pytest.fixture
def no_idle_collection(monkeypatch):
    """Called once the dock has settled: the dock's collection of the whole heap once it has been idle 3 s after a
    step (``_napari/_gc.py``) is kept out of the measured steps from then on (a test's steps follow closer than a
    user's): it runs between steps by design, its cost (one full pass, 200-300 ms) is in benchmarks/RESULTS.md."""
    return lambda: monkeypatch.setattr(_gc, "RELEASE_AFTER_MS", 3_600_000)


def settled_dock(make_napari_viewer, qtbot, tmp_path, hold_collection):
    """A phantom fish written as a scan file, and a viewer with the dock added as the Plugins menu does, once the dock
    has settled as a user looking at it lets it: its imports ahead (``_warm_imports``), numba's cache filled by its
    child (``_warm_kernels``), the heap collected and frozen (``_gc``); then ``hold_collection()``. Returns
    ``(fish, scan path, viewer, dock)``."""
    fish = fish_phantom(length=80, body_radius=5, tube=False, seed=1)
    scan = tmp_path / "fish.nrrd"
    write_volume(fish.volume, scan, spacing=fish.spacing, unit=fish.unit)
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.window.add_dock_widget(w, name="Unwind")
    qtbot.waitUntil(lambda: w.idle and not warming_kernels() and not _gc.pending(), timeout=300_000)
    hold_collection()
    return fish, scan, viewer, w


def test_no_long_stall_during_skeleton_and_export(make_napari_viewer, qtbot, tmp_path, no_idle_collection):
    fish, scan, viewer, w = settled_dock(make_napari_viewer, qtbot, tmp_path, no_idle_collection)
    job = w.open_scan(scan)
    qtbot.waitUntil(lambda: job.done, timeout=60_000)
    job = w.segment()
    qtbot.waitUntil(lambda: job.done and w.idle, timeout=60_000)
    p = np.round(fish.centerline[len(fish.centerline) // 2]).astype(int)
    w.select_features([int(w.features.labels[tuple(p)])])

    def settled():
        return w.idle and not w.refine_panel.pending

    skeleton, shown1, n1, crowded1 = longest_stall(qtbot, w.run_skeleton, settled=settled, viewer=viewer)
    assert w.model.deformation is not None, w.status.text()
    names = {layer.name for layer in viewer.layers}
    assert {"ends", "straight preview", "unwind curve", "unwind frames", "unwind cage"} <= names, names
    assert all(layer.visible for layer in viewer.layers), [layer.name for layer in viewer.layers if not layer.visible]
    assert viewer.layers.selection.active is viewer.layers["ends"]  # as when napari adds it
    w.export_step.spacing_box.setValue(0.5)  # 8 times the voxels of the default spacing: a longer export
    export, shown2, n2, crowded2 = longest_stall(qtbot, lambda: w.export(tmp_path / "straight.ome.zarr"),
                                                 settled=settled, viewer=viewer)
    assert w.exported is not None, w.status.text()
    straight = viewer.layers[f"straight {w.exported.name}"]
    assert straight.visible and viewer.layers.selection.active is straight
    print(f"\nlongest UI stall: skeleton solve {1000 * skeleton:.0f} ms ({n1} ticks; showing the result "
          f"{1000 * shown1:.0f} ms), export {1000 * export:.0f} ms ({n2} ticks; opening the result as a layer "
          f"{1000 * shown2:.0f} ms)")
    assert skeleton < LIMIT, f"the UI stalled {skeleton:.3f} s during the skeleton solve"
    assert export < LIMIT, f"the UI stalled {export:.3f} s during the export"
    assert not crowded1 and not crowded2, f"turns that added or showed more than one layer: {crowded1} {crowded2}"
    assert shown1 < SHOWN_LIMIT, f"the UI stalled {shown1:.3f} s showing the skeleton"
    assert shown2 < SHOWN_LIMIT, f"the UI stalled {shown2:.3f} s opening the export as a layer"
    qtbot.waitUntil(lambda: w.idle, timeout=60_000)  # the Refine panel's preview


def at_once(step):
    """A start function for ``longest_stall`` of a step that runs on the UI thread (no worker): its result
    "reaches the UI thread" at the click, so its whole cost counts as showing it."""
    def start():
        job = SimpleNamespace(done=True, returned_at=time.perf_counter())
        step()
        return job
    return start


def test_no_long_stall_opening_segmenting_selecting_and_suggesting(make_napari_viewer, qtbot, tmp_path,
                                                                   no_idle_collection):
    """Steps 1-3 each from the click until the dock has settled: opening a scan (its Image layer), segmenting (the
    "features" and "selection" Labels layers), a click selecting a feature (the selection layer's data), suggesting
    head and tail (the "ends" layer), choosing a mask (the selection layer hidden), a click after it (the selection
    layer shown again) and opening a mask file (its Labels layer)."""
    fish, scan, viewer, w = settled_dock(make_napari_viewer, qtbot, tmp_path, no_idle_collection)
    p = np.round(fish.centerline[len(fish.centerline) // 2]).astype(int)
    figures = {}

    def measure(name, start):
        figures[name] = longest_stall(qtbot, start, settled=lambda: w.idle, viewer=viewer)

    measure("open scan", lambda: w.open_scan(scan))
    assert [ly.name for ly in viewer.layers] == ["fish.nrrd"] and w.scan_layer.visible
    assert viewer.layers.selection.active is w.scan_layer
    measure("segment", w.segment)
    assert [ly.name for ly in viewer.layers] == ["fish.nrrd", "selection", "features"]
    assert all(ly.visible for ly in viewer.layers)
    assert viewer.layers.selection.active is viewer.layers["features"]
    fid = int(w.features.labels[tuple(p)])
    measure("select a feature", at_once(lambda: w.select_features([fid])))
    assert np.array_equal(np.unique(viewer.layers["selection"].data), [0, fid])
    measure("suggest head and tail", w.suggest_ends)
    ends = viewer.layers["ends"]
    assert ends.visible and len(ends.data) == 2 and viewer.layers.selection.active is ends
    mask = viewer.add_labels(fish.mask.astype(np.uint8), name="mask", scale=fish.spacing)
    qtbot.wait(300)
    measure("choose a mask", at_once(lambda: w.use_labels(mask)))
    assert w.mask_choice == (mask, None)
    selection = viewer.layers["selection"]  # kept hidden and empty: the click after a mask shows it again
    assert not selection.visible and not np.any(selection.data)
    measure("select a feature after a mask", at_once(lambda: w.select_features([fid])))
    assert w.mask_choice is None and viewer.layers["selection"] is selection and selection.visible
    assert np.array_equal(np.unique(selection.data), [0, fid])
    assert viewer.layers.selection.active is viewer.layers["features"]
    write_volume(fish.mask.astype(np.uint8), tmp_path / "mask.nrrd", spacing=fish.spacing, unit=fish.unit)
    measure("open a mask file", lambda: w.open_mask(tmp_path / "mask.nrrd"))
    opened = viewer.layers[-1]
    assert w.mask_choice == (opened, None) and opened.visible and not selection.visible
    print("\nlongest UI stall from the click until settled (until the result / showing it): " + ", ".join(
        f"{name} {1000 * during:.0f} / {1000 * shown:.0f} ms" for name, (during, shown, _, _) in figures.items()))
    crowded = {name: c for name, (_, _, _, c) in figures.items() if c}
    assert not crowded, f"turns that added or showed more than one layer: {crowded}"
    running = {name: round(during, 3) for name, (during, _, _, _) in figures.items() if during >= LIMIT}
    assert not running, f"the UI stalled (s) from the click until the result: {running}"
    slow = {name: round(shown, 3) for name, (_, shown, _, _) in figures.items() if shown >= SHOWN_LIMIT}
    assert not slow, f"the UI stalled (s) showing the result: {slow}"


def test_the_imports_ahead_run_in_a_thread_and_keep_the_dock_busy(make_napari_viewer, qtbot, monkeypatch):
    """``_warm_imports``: once per process, in a background thread (the dock is not idle meanwhile); a module that
    is missing is skipped."""
    import threading

    from napari_unwind._napari import _widget

    ran, release = [], threading.Event()

    def dashes():
        ran.append(threading.current_thread().name)
        release.wait(10)

    monkeypatch.setattr(_widget, "_WARM_STARTED", [])
    monkeypatch.setattr(_widget, "WARM_IMPORTS", ("napari_unwind_no_such_module",))
    monkeypatch.setattr(_widget, "_warm_dashes", dashes)
    kernels = []
    monkeypatch.setattr(_widget, "_warm_kernels", lambda: kernels.append(threading.current_thread().name))
    w = UnwindWidget(make_napari_viewer())
    qtbot.waitUntil(lambda: bool(ran) and bool(kernels), timeout=10_000)
    assert ran == ["unwind-warm-imports"] and not w.idle
    assert kernels == ["unwind-warm-kernels"]  # numba's cache filled in a thread of its own (its child process)
    UnwindWidget(make_napari_viewer())  # a second dock starts none
    release.set()
    qtbot.waitUntil(lambda: w.idle, timeout=10_000)
    assert ran == ["unwind-warm-imports"] and kernels == ["unwind-warm-kernels"]
