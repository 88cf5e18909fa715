"""``napari_unwind._warm``: the child the dock starts fills numba's cache with every kernel the dock's steps call, so
that napari's own process compiles none (a first call compiles there and stalls the UI thread: issue 21).

The reference is numba's own record of its compilations (the ``numba:compile`` event, sent only when a kernel is
compiled, not when it is loaded from the cache), in a fresh cache directory, on scans the warm-up does not use: a
phantom fish and CT-like, microscopy-like and 8-bit scans, through the steps the dock runs (the workflow's segment,
click, suggested ends and selection mask, the straight preview, an export to OME-Zarr and points mapped both ways).
"""

import os
import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("numba")

STEPS = textwrap.dedent("""
    import json, warnings
    import numpy as np
    from numba.core import event
    from napari_unwind.datasets import fish_phantom
    from napari_unwind.deformation import Deformation
    from napari_unwind.io import Volume
    from napari_unwind.pipeline import ExportOptions, export_step
    from napari_unwind.preview import preview_volume
    from napari_unwind.progress import run
    from napari_unwind.warp import map_points
    from napari_unwind.workflow import Workflow

    warnings.simplefilter("ignore")
    fish = fish_phantom(length=60, body_radius=4, tube=False, seed=3)
    d = Deformation.from_polyline(fish.centerline[::8], spacing=fish.spacing, cage_half_extent=8.0)
    scans = {"uint16": fish.volume, "int16": (fish.volume.astype(np.int32) - 1024).astype(np.int16),
             "float32": fish.volume.astype(np.float32) / 7.0, "uint8": (fish.volume // 256).astype(np.uint8)}
    compiled = []
    with event.install_recorder("numba:compile") as rec:
        for i, (name, data) in enumerate(scans.items()):
            volume = Volume(data, spacing=fish.spacing, unit=fish.unit)
            wf = Workflow()
            wf.set_scan(volume, name=name)
            task = wf.segment_task()
            task.apply(run(task.make()))
            assert wf.pick(np.round(fish.centerline[len(fish.centerline) // 2]).astype(int))
            task = wf.suggest_ends_task()
            task.apply(run(task.make()))
            np.asarray(wf.mask())
            preview_volume(volume, d)
            run(export_step(volume, d, OUT + f"/{i}.ome.zarr", options=ExportOptions()))
            run(export_step(Volume(fish.mask.astype(np.uint8), spacing=fish.spacing, unit=fish.unit), d,
                            OUT + f"/mask{i}.ome.zarr", options=ExportOptions(order=0)))
            p = map_points(fish.centerline[::10], d, to="straight", strict=False)
            map_points(p[np.isfinite(p).all(axis=1)], d, to="scan", strict=False)
    for _, ev in rec.buffer:
        if ev.is_start:
            compiled.append(str(ev.data["dispatcher"].py_func.__qualname__))
    print(json.dumps(sorted(set(compiled))))
""")


def _python(code: str, cache: str, out: str) -> str:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    env.pop("NUMBA_DISABLE_JIT", None)
    done = subprocess.run([sys.executable, "-c", f"OUT = {out!r}\n" + code], env=env, capture_output=True,
                          text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout.strip().splitlines()[-1]


def test_the_warm_child_leaves_nothing_for_the_docks_steps_to_compile(tmp_path):
    import json

    from napari_unwind._warm import warm_in_child

    cache = tmp_path / "numba-cache"
    cache.mkdir()
    env = os.environ.get("NUMBA_CACHE_DIR")
    os.environ["NUMBA_CACHE_DIR"] = str(cache)  # the child inherits the environment, as the dock's does
    try:
        assert warm_in_child()
    finally:
        if env is None:
            os.environ.pop("NUMBA_CACHE_DIR")
        else:
            os.environ["NUMBA_CACHE_DIR"] = env
    assert any(cache.rglob("*.nbc")), "the child wrote nothing into numba's cache"
    compiled = json.loads(_python(STEPS, str(cache), str(tmp_path)))
    assert compiled == [], f"the dock's steps compiled kernels the warm-up left out: {compiled}"


def test_the_steps_compile_kernels_in_a_fresh_cache(tmp_path):
    """The test above can fail: without the warm-up the same steps compile (the recorder sees them)."""
    import json

    cache = tmp_path / "numba-cache"
    cache.mkdir()
    compiled = json.loads(_python(STEPS, str(cache), str(tmp_path)))
    assert "_sweep" in compiled and "_linear_block" in compiled, compiled
