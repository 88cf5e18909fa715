"""`io._formats.compresses` (what the disk-space checks of `write_volume` and the export assume) against what each
writer really does: a volume of zeros written with the same options is far smaller than its voxels exactly when
it says the writer compresses. Reference: the bytes on disk, not the function's own table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from napari_unwind.io import as_volume, write_volume
from napari_unwind.io._formats import compresses, output_format

CASES = [
    ("a.ome.zarr", {}), ("b.ome.zarr", {"compression": "none"}), ("c.tif", {}), ("d.tif", {"compression": "zlib"}),
    ("e.nrrd", {}), ("f.nrrd", {"encoding": "raw"}), ("g.nii", {}), ("h.nii.gz", {}), ("i.dat", {}),
    ("j_stack", {"pattern": "slice_{:04d}.png"}), ("k_stack", {"pattern": "slice_{:04d}.tif"}),
]


def _size(path: Path) -> int:
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return sum(p.stat().st_size for p in path.parent.iterdir() if p.name.split(".")[0] == path.name.split(".")[0])


@pytest.mark.parametrize(("name", "options"), CASES, ids=[c[0] for c in CASES])
def test_compresses_says_what_the_writer_does(tmp_path, name, options):
    volume = as_volume(np.zeros((24, 64, 64), np.uint16), spacing=(1.0, 1.0, 1.0))
    target = tmp_path / name
    fmt = "stack" if name.endswith("_stack") else output_format(target)
    written = write_volume(volume, target, format=fmt, **options)
    shrunk = _size(Path(written)) < volume.nbytes // 4
    assert compresses(fmt, target, options) == shrunk, (fmt, options, _size(Path(written)), volume.nbytes)
