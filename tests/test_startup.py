"""Start-up stays light (issue 18): ``import napari_unwind``, ``unwind --version`` and ``unwind info`` import no
dask, scipy, numba, scikit-image, zarr or gRPC. Each runs in a fresh interpreter, which reports its ``sys.modules``.

The times themselves are in benchmarks/bench_startup.py (tests assert no times).
"""

from __future__ import annotations

import ast
import subprocess
import sys

import numpy as np
import pytest

HEAVY = ("dask", "scipy", "numba", "skimage", "zarr", "grpc")

#: runs napari_unwind.cli.main with the arguments given, then prints the heavy modules it imported (last line)
WRAPPER = """
import sys
from napari_unwind.cli import main
status = main(sys.argv[1:])
print(sorted(m for m in {modules!r} if m in sys.modules))
sys.exit(status)
"""


def _run(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=120, check=False)


def _imported(proc: subprocess.CompletedProcess) -> list[str]:
    assert proc.returncode == 0, proc.stderr
    return ast.literal_eval(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("statement", ["import napari_unwind", "import napari_unwind.io",
                                       "from napari_unwind import Volume, open_volume, write_volume, Progress"])
def test_import_is_light(statement):
    code = f"{statement}; import sys; print(sorted(m for m in {HEAVY!r} if m in sys.modules))"
    assert _imported(_run(["-c", code])) == []


def test_version_is_light():
    """``unwind --version`` does not even import numpy."""
    proc = _run(["-c", WRAPPER.format(modules=("numpy", *HEAVY)), "--version"])
    assert proc.stdout.startswith("napari-unwind ")
    assert _imported(proc) == []


VOXELS = np.arange(6 * 7 * 8, dtype=np.uint16).reshape(6, 7, 8)


def _write(folder, name, **options):
    from napari_unwind.io import write_volume

    return write_volume(VOXELS, folder / name, spacing=(2.0, 0.5, 0.5), unit="mm", **options)


@pytest.mark.parametrize("encoding", ["raw", "gzip"])
def test_info_is_light(tmp_path, encoding):
    path = _write(tmp_path, "small.nrrd", encoding=encoding)
    proc = _run(["-c", WRAPPER.format(modules=HEAVY), "info", str(path)])
    assert _imported(proc) == []
    assert "shape:     6 x 7 x 8" in proc.stdout
    assert "  0: 6 x 7 x 8" in proc.stdout and "chunks 6x7x8" in proc.stdout


@pytest.mark.parametrize(("name", "options"), [
    ("raw.nrrd", {"encoding": "raw"}), ("gzip.nrrd", {"encoding": "gzip"}), ("detached.nhdr", {}),
    ("small.tif", {}), ("small.dat", {}), ("small.zarr", {"chunks": (4, 4, 4), "max_side": 4}),
])
def test_header_matches_the_voxels_built_later(tmp_path, name, options):
    """What ``unwind info`` prints comes from the header (no dask array is built); the dask arrays built when the
    voxels are first used have exactly those shapes and chunks, and hold the voxels."""
    from napari_unwind._report import describe
    from napari_unwind.io import open_volume

    path = _write(tmp_path, name, **options)
    vol = open_volume(path)
    before = describe(vol, path)
    assert vol.level_shapes == tuple(lvl.shape for lvl in vol.levels)
    assert vol.level_chunks == tuple(lvl.chunks for lvl in vol.levels)
    assert vol.levels[0] is vol.data
    assert describe(vol, path) == before
    np.testing.assert_array_equal(vol.data.compute(), VOXELS)
    if name.endswith(".zarr"):
        assert len(vol.levels) > 1
