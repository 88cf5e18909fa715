"""The pipeline's verdict on a server: a skeleton job and a pipeline job report the status, reason and figures the
local pipeline gives (``napari_unwind.pipeline.judge``), and a partial specimen is never reported as a success
(the client's verdict, ``unwind run --server`` and ``unwind jobs watch`` exit 3 with the reason).

References: the local pipeline on the same mask, ends and options in this process (its ``judge`` and
``SpecimenResult``), and the coverage counted here independently with numpy/scipy: every mask voxel is projected
onto the deformation's centre curve (nearest dense sample, scipy cKDTree) and counted when it lies within the
cage's sides there. The phantom is a straight rod, so that projection is exact; a cage of 2.5 x 2.5 voxels round a
rod of radius 4.5 leaves about two thirds of the mask out (partial), the fitted cage holds all of it (ok).
"""

from __future__ import annotations

import numpy as np
import pytest
from _servers import ServerProcess
from scipy.spatial import cKDTree

from napari_unwind import cli, pipeline
from napari_unwind.client import Client
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import write_volume
from napari_unwind.progress import run as drive
from napari_unwind.session import Endpoints
from unwind_services._proto.unwind.v1 import common_pb2 as pb

SPACING = (1.0, 1.0, 1.0)
HEAD, TAIL = (8.0, 14.0, 13.0), (56.0, 14.0, 13.0)
SMALL_CAGE = (2.5, 2.5)
FIGURES = ("status", "reason", "length", "unit", "keyframes", "min_jacobian", "max_tilt", "coverage", "folded",
           "lost", "warnings")


def _rod(shape=(64, 28, 28), radius=4.5, z0=8, z1=56, centre=(14.0, 13.0)):
    z, y, x = np.mgrid[: shape[0], : shape[1], : shape[2]]
    inside = ((y - centre[0]) ** 2 + (x - centre[1]) ** 2 <= radius**2) & (z >= z0) & (z <= z1)
    return inside.astype(np.uint8)


def independent_coverage(mask, d, spacing=SPACING):
    """The fraction of mask voxels inside the cage of ``d``, by nearest-point projection on its centre curve."""
    pts = np.argwhere(mask > 0) * np.asarray(spacing, float)
    lo, hi = d.s_range
    s = np.linspace(lo, hi, int((hi - lo) / 0.05) + 1)
    centres, frames = d.sample(s)
    _, k = cKDTree(centres).query(pts)
    rel = pts - centres[k]
    u, v, n = (np.einsum("ij,ij->i", rel, frames[k, i]) for i in range(3))
    b = d.bounds_at(s[k])
    inside = (u >= b[:, 0]) & (u <= b[:, 1]) & (v >= b[:, 2]) & (v <= b[:, 3])
    inside &= ~((k == 0) & (n < 0)) & ~((k == len(s) - 1) & (n > 0))  # not beyond the ends of the cage
    return float(inside.mean())


@pytest.fixture(scope="module")
def rod():
    mask = _rod()
    return mask, mask.astype(np.float32) * 1000


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    srv = ServerProcess(tmp_path_factory.mktemp("verdict") / "data", "--workers", "1")
    yield srv
    srv.stop()


def _local(mask, scan, options):
    result = drive(pipeline.skeleton_step(mask, Endpoints(head=HEAD, tail=TAIL), spacing=SPACING, volume=scan,
                                          options=options))
    return result, pipeline.SpecimenResult.of(result)


@pytest.mark.parametrize("cage", [SMALL_CAGE, None], ids=["partial", "ok"])
def test_a_skeleton_job_reports_the_local_pipelines_verdict(rod, server, cage, tmp_path, capsys):
    mask, scan = rod
    options = pipeline.SkeletonOptions(half_extent=cage)
    result, local = _local(mask, scan, options)
    status, reason = pipeline.judge(result)
    assert (status, reason) == (local.status, local.reason)
    with Client(server.address, progress=False) as c:
        vid = c.upload(scan, spacing=SPACING, name="rod").volume_id
        mid = c.upload(mask, spacing=SPACING, name="rod_mask").volume_id
        job = c.skeleton(mid, volume_id=vid, head=HEAD, tail=TAIL, options=options)
        remote = Client.specimen(job)
    # the job succeeded (its session is written) and carries the verdict: the same status, reason and figures
    assert job.state == pb.JOB_STATE_SUCCEEDED and job.result.HasField("verdict")
    assert {k: getattr(remote, k) for k in FIGURES} == {k: getattr(local, k) for k in FIGURES}
    assert remote.status == status and remote.reason == reason
    # the coverage is the share of the mask inside the cage, counted here without the solver's inverse map
    count = independent_coverage(mask, Client.session(job).deformation)
    assert remote.coverage == pytest.approx(count, abs=2e-3)
    if cage is None:
        assert remote.status == "ok" and remote.ok and remote.reason == "" and remote.coverage >= pipeline.MIN_COVERAGE
    else:
        assert remote.status == "partial" and not remote.ok
        assert 0.2 < remote.coverage < 0.6 and remote.lost, remote
        assert f"coverage {100 * count:.1f} % of the mask inside the cage" in remote.reason
    # unwind jobs watch: the exit status of the local command (0 ok, 3 partial with its reason)
    code = cli.main(["jobs", "watch", job.id, "--server", server.address, "-q"])
    err = capsys.readouterr().err
    if cage is None:
        assert code == 0, err
    else:
        assert code == pipeline.EXIT_PARTIAL and f"unwind: partial: job {job.id}: {reason}" in err, err


def test_a_result_without_a_verdict_is_never_ok():
    job = pb.Job(id="job-x", state=pb.JOB_STATE_SUCCEEDED, result=pb.JobResult(session_id="s"))
    with pytest.raises(InvalidInputError, match="carries no verdict"):
        Client.specimen(job)


def test_run_on_a_server_reports_partial_as_the_local_run_does(rod, server, tmp_path, capsys):
    """``unwind run --mask ... --cage`` here and with ``--server``: exit 3 both, the same ``unwind: partial:`` line
    (the specimen's summary: figures and the pipeline's reason), and the pipeline job's verdict is the local
    pipeline's."""
    mask, scan = rod
    scan_path = write_volume(scan, tmp_path / "rod.nrrd", spacing=SPACING)
    mask_path = write_volume(mask, tmp_path / "rod_mask.nrrd", spacing=SPACING)
    args = [str(scan_path), "--mask", str(mask_path), "--head", ",".join(map(str, HEAD)), "--tail",
            ",".join(map(str, TAIL)), "--cage", ",".join(map(str, SMALL_CAGE)), "-q"]
    lines = {}
    for where, extra in (("local", []), ("server", ["--server", server.address])):
        (tmp_path / where).mkdir()
        code = cli.main(["run", *args, "-o", str(tmp_path / where / "rod_straight.nrrd"), *extra])
        err = capsys.readouterr().err
        assert code == pipeline.EXIT_PARTIAL, (where, err)
        lines[where] = [line for line in err.splitlines() if line.startswith("unwind: partial: ")]
        assert len(lines[where]) == 1, (where, err)
    assert lines["server"] == lines["local"]
    assert "coverage" in lines["local"][0]
    # the pipeline job through the client: the local pipeline's verdict
    from napari_unwind.io import open_volume

    local = pipeline.run(open_volume(scan_path), mask=mask, endpoints=Endpoints(head=HEAD, tail=TAIL),
                         options=pipeline.PipelineOptions(skeleton=pipeline.SkeletonOptions(half_extent=SMALL_CAGE)))
    with Client(server.address, progress=False) as c:
        vid = c.upload(scan_path).volume_id
        mid = c.upload(mask_path).volume_id
        job = c.pipeline(vid, mask_volume_id=mid, head=HEAD, tail=TAIL, skeleton=dict(half_extent=SMALL_CAGE),
                         output_name="rod.nrrd")
    remote = Client.specimen(job)
    assert remote.status == local.status == "partial"
    assert {k: getattr(remote, k) for k in FIGURES if k != "warnings"} == {
        k: getattr(local, k) for k in FIGURES if k != "warnings"}
