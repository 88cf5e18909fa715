"""The dock's new layers in steps (``_reveal``): added hidden, shown on a later turn, one step per timer shot; a
visibility set in between wins; ``flush`` and ``cancel``."""

import time

import numpy as np
import pytest

pytest.importorskip("napari")

from napari.layers import Points  # noqa: E402

from napari_unwind._napari import _reveal  # noqa: E402

pytestmark = pytest.mark.gui


def points(name):
    return Points(np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]), name=name)


def test_a_layer_is_added_hidden_then_shown_and_made_active(make_napari_viewer, qtbot):
    viewer = make_napari_viewer()
    first = viewer.add_points(np.zeros((1, 3)), name="first")
    layer = _reveal.add_layer(viewer, points("new"))
    assert layer in viewer.layers and not layer.visible and viewer.layers.selection.active is first
    qtbot.waitUntil(lambda: not _reveal.pending(), timeout=5000)
    assert layer.visible and viewer.layers.selection.active is layer  # as napari's own add_layer leaves it
    other = _reveal.add_layer(viewer, points("kept"), keep_active=True)
    qtbot.waitUntil(lambda: not _reveal.pending(), timeout=5000)
    assert other.visible and viewer.layers.selection.active is layer
    hidden = points("hidden")
    hidden.visible = False
    _reveal.add_layer(viewer, hidden)
    qtbot.waitUntil(lambda: not _reveal.pending(), timeout=5000)
    assert not hidden.visible  # added hidden, stays hidden


def test_a_visibility_set_in_between_wins(make_napari_viewer, qtbot):
    viewer = make_napari_viewer()
    layer = _reveal.add_layer(viewer, points("new"))
    layer.visible = True   # the user's eye button, twice
    layer.visible = False
    qtbot.waitUntil(lambda: not _reveal.pending(), timeout=5000)
    assert not layer.visible


def test_steps_run_one_per_timer_shot_in_order(make_napari_viewer, qtbot):
    viewer = make_napari_viewer()
    ran = []
    for i in range(4):
        _reveal.later(lambda i=i: ran.append((i, time.perf_counter())))
    assert ran == [] and _reveal.pending()
    qtbot.waitUntil(lambda: not _reveal.pending(), timeout=5000)
    assert [i for i, _ in ran] == [0, 1, 2, 3]
    gaps = np.diff([t for _, t in ran])
    assert np.all(gaps > 0.6 * _reveal.STEP_MS / 1000), gaps  # a timer shot each (Qt's coarse timers: +-5 %)
    layer = _reveal.add_layer(viewer, points("later"), now=False)
    assert layer not in viewer.layers and _reveal.waiting(layer)
    _reveal.flush()
    assert layer in viewer.layers and layer.visible and not _reveal.pending()
    dropped = _reveal.add_layer(viewer, points("dropped"), now=False)
    _reveal.cancel(dropped)
    qtbot.wait(50)
    assert dropped not in viewer.layers and not _reveal.pending()
