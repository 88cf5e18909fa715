"""The workflow model's ServerBackend against a real server in a child process on 127.0.0.1, without Qt: the same
steps as LocalBackend, and the same results.

References: the core on this computer (join_tree, refine_mask, the skeleton step, straighten), called directly.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("grpc")

sys.path.insert(0, str(Path(__file__).resolve().parent / "services"))

from _servers import ServerProcess  # noqa: E402

from napari_unwind._remote import parse_server  # noqa: E402
from napari_unwind.cli import main as unwind_main  # noqa: E402
from napari_unwind.datasets import fish_phantom  # noqa: E402
from napari_unwind.errors import InvalidInputError  # noqa: E402
from napari_unwind.io import open_volume, write_volume  # noqa: E402
from napari_unwind.pipeline import skeleton_step  # noqa: E402
from napari_unwind.progress import run  # noqa: E402
from napari_unwind.segmentation import join_tree, refine_mask, select  # noqa: E402
from napari_unwind.warp import straighten  # noqa: E402
from napari_unwind.workflow import LocalBackend, ServerBackend, Workflow  # noqa: E402


def _do(task):
    return task.apply(run(task.make()))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wf_server")
    tokens = tmp / "tokens"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert unwind_main(["serve", "--tokens", str(tokens), "--add-token", "alice"]) == 0
    srv = ServerProcess(tmp / "data", "--tokens", str(tokens), "--workers", "1")
    yield parse_server(srv.address, out.getvalue().splitlines()[-1])
    srv.stop()


def test_the_server_backend_gives_the_local_results(tmp_path, server):
    fish = fish_phantom(length=80, body_radius=5, tube=False, seed=1)
    scan = tmp_path / "fish.nrrd"
    write_volume(fish.volume, scan, spacing=fish.spacing, unit=fish.unit)
    volume = open_volume(scan)
    wf = Workflow(ServerBackend(server))
    wf.set_scan(volume, name="fish")
    _do(wf.segment_task())
    local = join_tree(volume).simplify(wf.features.k)
    np.testing.assert_array_equal(np.asarray(wf.features.labels), np.asarray(local.labels))
    fid = wf.pick(fish.centerline[len(fish.centerline) // 2])
    assert fid != 0
    _do(wf.suggest_ends_task())
    _do(wf.skeleton_task())
    mask = refine_mask(volume, select(local, ids=[fid]), features=local).compute()
    expected = run(skeleton_step(mask, wf.ends, spacing=volume.spacing, origin=volume.origin, unit=volume.unit,
                                 volume=volume.data)).deformation
    d = wf.edit.deformation
    assert json.dumps(d.to_dict(), sort_keys=True) == json.dumps(expected.to_dict(), sort_keys=True)
    assert "server" in wf.skeleton.where

    out = tmp_path / "remote.nrrd"
    _do(wf.export_task(out))
    np.testing.assert_array_equal(np.asarray(open_volume(out).data), np.asarray(straighten(volume, d).data))
    # with another channel of the scan's grid (uploaded): one two-channel image, each channel as straightened here
    from dataclasses import replace

    from napari_unwind.io import as_volume, open_channels

    body = replace(as_volume(fish.mask.astype(np.uint16) * 100, spacing=volume.spacing, unit=volume.unit,
                             origin=volume.origin), metadata={"channel": "body"})
    both = tmp_path / "both.ome.zarr"
    _do(wf.export_task(both, channels=[body]))
    chans = open_channels(both)
    assert [c.metadata["channel"] for c in chans] == ["fish", "body"]
    np.testing.assert_array_equal(np.asarray(chans[0].data), np.asarray(straighten(volume, d).data))
    np.testing.assert_array_equal(np.asarray(chans[1].data), np.asarray(straighten(body, d).data))

    # an edited deformation is not the server's session: refused with what to do, nothing written
    wf.edit.select_keyframe(1)
    wf.edit.move(1.0, 0.0)
    with pytest.raises(InvalidInputError, match="the server holds no session of this deformation"):
        wf.export_task(tmp_path / "edited.nrrd")
    assert not (tmp_path / "edited.nrrd").exists()

    # back to this computer: the edited deformation exports there
    wf.set_backend(LocalBackend())
    _do(wf.export_task(tmp_path / "edited.nrrd"))
    assert (tmp_path / "edited.nrrd").exists()
