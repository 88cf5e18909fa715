"""The dock's child processes (napari_unwind._napari._workers), without a viewer."""

import subprocess
import sys
import textwrap

import pytest


def test_a_script_without_a_main_guard_is_not_run_again_in_the_child(tmp_path):
    """napari scripts rarely guard their top level with ``if __name__ == "__main__"``; the spawned child of a job
    must not run the user's script again (it would open a second viewer, or fail at its bootstrapping)."""
    marker = tmp_path / "runs.txt"
    script = tmp_path / "user_script.py"
    script.write_text(textwrap.dedent(f"""
        import threading
        with open({str(marker)!r}, "a") as f:
            f.write("run\\n")
        import numpy as np
        from napari_unwind._napari._workers import _in_process
        a = np.zeros((12, 12, 12), np.float32)
        a[3, 3, 3] = a[8, 8, 8] = 1.0
        gen = _in_process("napari_unwind.segmentation:join_tree_iter", (a,), {{"smooth": 0.0}}, threading.Event())
        records = []
        try:
            while True:
                records.append(next(gen))
        except StopIteration as stop:
            from napari_unwind.segmentation import join_tree
            here = join_tree(a, smooth=0.0)
            same = bool((stop.value.branch == here.branch).all()) and stop.value.n_maxima == here.n_maxima
            print("RESULT", same, len(records) > 0)
    """))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "RESULT True True" in done.stdout, done.stdout + done.stderr[-2000:]
    assert marker.read_text().count("run") == 1, "the child ran the user's script again"


def test_the_dock_names_the_skeleton_step_that_exists():
    """The dock names its skeleton step by string (its UI thread must not import the solver); the name must be the
    steps module's own and resolve to the function the child process calls."""
    import importlib

    pytest.importorskip("qtpy")
    from napari_unwind import _steps
    from napari_unwind._napari import _widget

    assert _widget._SKELETON == _steps.SKELETON
    module, _, name = _widget._SKELETON.partition(":")
    assert getattr(importlib.import_module(module), name) is _steps.skeleton
