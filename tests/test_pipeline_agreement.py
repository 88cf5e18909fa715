"""One pipeline, every face: the same scan and options give the same deformation bytes (and the same straight
voxels) through the Python API, ``unwind run`` in a subprocess, ``unwind run --all``, and a job on a real server
(``unwind run --server``); the fold rule is the same on the command line and in the server's straighten job.

References: the faces against each other, byte for byte (the tet mesher is deterministic), and the fold rule's
own verdict. The dock is not driven here (see the report of issue 18).
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import run_unwind
from napari_unwind import cli
from napari_unwind.datasets import tank_phantom
from napari_unwind.io import open_volume, write_volume
from napari_unwind.pipeline import PipelineOptions, SegmentOptions, candidates, run, segment_step, select_step
from napari_unwind.progress import run as drive

sys.path.insert(0, str(Path(__file__).parent / "services"))
from _servers import ServerProcess  # noqa: E402


def _arg(p):
    return ",".join(f"{float(v):.3f}" for v in p)


def _deformation(session_path) -> str:
    return json.dumps(json.loads(Path(session_path).read_text())["deformation"], sort_keys=True)


def _voxels(path) -> bytes:
    return np.asarray(open_volume(path).data.compute()).tobytes()


@pytest.fixture(scope="module")
def tank(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("agreement")
    t = tank_phantom(n_fish=2, seed=1, length=90)
    scan = write_volume(t.volume, tmp / "tank.zarr", spacing=t.spacing, unit=t.unit)
    fish = t.fish[0]
    return tmp, scan, fish.centerline[len(fish.centerline) // 2]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    srv = ServerProcess(tmp_path_factory.mktemp("agreement_server") / "data", "--workers", "1")
    yield srv
    srv.stop()


def test_a_click_gives_the_same_bytes_through_the_api_the_cli_and_a_server_job(tank, server, tmp_path):
    _, scan, click = tank
    api = run(open_volume(scan), seeds=[click], options=PipelineOptions(), output=tmp_path / "api.nrrd",
              session_path=tmp_path / "api.unwind.json", source=scan)
    assert api.status in ("ok", "partial")
    code, _, err = run_unwind("run", scan, "--select", _arg(click), "-o", tmp_path / "cli.nrrd", "-q")
    assert code in (0, 3) and (code == 3) == (api.status == "partial"), err
    code = cli.main(["run", str(scan), "--select", _arg(click), "-o", str(tmp_path / "srv.nrrd"), "--server",
                     server.address, "-q"])
    assert code in (0, 3) and (code == 3) == (api.status == "partial")
    ref = _deformation(tmp_path / "api.unwind.json")
    assert _deformation(tmp_path / "cli.unwind.json") == ref
    assert _deformation(tmp_path / "srv.unwind.json") == ref
    assert _voxels(tmp_path / "cli.nrrd") == _voxels(tmp_path / "api.nrrd") == _voxels(tmp_path / "srv.nrrd")


def test_the_batch_gives_the_bytes_a_run_on_its_specimens_mask_gives(tank, server, tmp_path):
    """``run --all`` straightens each candidate's mask; ``unwind run --mask`` of that mask, here and on the
    server, gives the same deformation bytes."""
    _, scan, _ = tank
    code, _, err = run_unwind("run", scan, "--all", "--features", "5", "-o", tmp_path / "all", "-q")
    assert code in (0, 3), err
    with open(tmp_path / "all" / "specimens.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["status"] in ("ok", "partial")]
    assert rows, err
    row = rows[0]
    # the candidate's mask, as the batch made it (the pipeline's own steps)
    vol = open_volume(scan)
    feats = drive(segment_step(vol, SegmentOptions(features=5)))
    cand = next(c for c in candidates(feats) if c.status == "specimen" and c.name == row["specimen"])
    sel = drive(select_step(vol, feats, candidate=cand))
    mask = write_volume(np.asarray(sel.mask.compute(), dtype=np.uint8), tmp_path / "mask.nrrd", spacing=vol.spacing,
                        origin=vol.origin, unit=vol.unit)
    code, _, err = run_unwind("run", scan, "--mask", mask, "-o", tmp_path / "m.nrrd", "-q")
    assert code in (0, 3), err
    code = cli.main(["run", str(scan), "--mask", str(mask), "-o", str(tmp_path / "ms.nrrd"), "--server",
                     server.address, "-q"])
    assert code in (0, 3)
    ref = _deformation(tmp_path / "all" / row["session"])
    assert _deformation(tmp_path / "m.unwind.json") == ref
    assert _deformation(tmp_path / "ms.unwind.json") == ref


def _folding_session(tmp_path):
    from napari_unwind.deformation import Deformation
    from napari_unwind.session import Session, SourceInfo, save_session

    t = np.linspace(0, np.pi / 2, 40)
    pos = 15 + np.stack([np.zeros_like(t), 10 * np.sin(t), 10 * (1 - np.cos(t))], axis=1)
    n = np.stack([np.zeros_like(t), np.cos(t), np.sin(t)], axis=1)
    v = np.tile([1.0, 0.0, 0.0], (len(t), 1))
    d = Deformation.from_keyframes(pos, np.stack([np.cross(v, n), v, n], axis=1), 12.0)
    assert d.folds()
    scan = write_volume(np.ones((40, 40, 40), np.float32), tmp_path / "scan.nrrd", spacing=1.0)
    session = Session(source=SourceInfo.from_path(scan), deformation=d)
    return scan, session, save_session(session, tmp_path / "fold.unwind.json")


def test_the_fold_rule_is_the_same_on_the_cli_and_in_the_server_job(tmp_path):
    """A fold where the specimen is unknown (a session alone): refused with one message by ``unwind straighten``
    and by the server's straighten job (FAILED_PRECONDITION, not INTERNAL); both export with allow_folds."""
    from napari_unwind.errors import FoldError
    from unwind_services import tasks
    from unwind_services._proto.unwind.v1 import warp_pb2
    from unwind_services.errors import status_for

    scan, session, path = _folding_session(tmp_path)
    code, _, err = run_unwind("straighten", scan, "--session", path, "-o", tmp_path / "cli.nrrd", "-q")
    assert code == 1 and err.startswith("unwind: error: ") and not (tmp_path / "cli.nrrd").exists()
    cli_message = err.strip()[len("unwind: error: "):]

    volume = open_volume(scan)
    catalog = SimpleNamespace(volume=lambda owner, vid: (SimpleNamespace(id=vid, name="scan.nrrd"), volume),
                              session=lambda owner, sid: (None, session),
                              add_volume=lambda *a: (SimpleNamespace(id="vol-out"), None))
    (tmp_path / "job").mkdir()
    ctx = tasks.TaskContext(catalog=catalog, owner="u", job_id="job-1", workdir=tmp_path / "job")

    def job(allow):
        req = warp_pb2.StraightenRequest(volume_id="v", session_id="s", options=warp_pb2.ExportOptions(
            allow_folds=allow, output_name="out.nrrd"))
        return drive(tasks.straighten(ctx, req))

    with pytest.raises(FoldError) as info:
        job(False)
    assert str(info.value) == cli_message
    assert status_for(info.value)[0].name == "FAILED_PRECONDITION"
    assert not (tmp_path / "job" / "out.nrrd").exists()
    code, _, err = run_unwind("straighten", scan, "--session", path, "-o", tmp_path / "cli.nrrd", "-q",
                              "--allow-folds")
    assert code == 0 and "warning" in err
    with pytest.warns(UserWarning, match="exported anyway"):
        assert job(True).volume_id == "vol-out"
    assert _voxels(tmp_path / "cli.nrrd") == _voxels(tmp_path / "job" / "out.nrrd")
