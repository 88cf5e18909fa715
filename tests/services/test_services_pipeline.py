"""The pipeline on a real server: the same voxels as in process, each step against the core, and a batch.

References: the core run in this process (the servicers must add nothing), and the phantom's ground truth.
Every stage is deterministic (the skeleton's tet mesh too), so bytes are compared: segmentation, selection, the
skeleton's deformation, straight export, bend, map points.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from _servers import ServerProcess
from scipy.spatial import cKDTree

from napari_unwind import cli
from napari_unwind.cli import main as remote_main
from napari_unwind.client import BatchItem, Client
from napari_unwind.datasets import tank_phantom
from napari_unwind.deformation import Deformation
from napari_unwind.io import open_volume, write_volume
from napari_unwind.session import load_session
from unwind_services._proto.unwind.v1 import common_pb2 as pb


def _arg(p):
    return ",".join(f"{float(v):.3f}" for v in p)


def _centreline_rms(deformation, fish, step=0.5):
    """RMS distance (voxels) of the deformation's centre curve to the phantom's dense true centreline."""
    s = np.linspace(0, deformation.length, int(deformation.length / step) + 2)
    centres, _ = deformation.sample(s)
    vox = (centres - np.asarray(deformation.origin)) / np.asarray(fish.spacing)
    d, _ = cKDTree(fish.centerline).query(vox)
    return float(np.sqrt(np.mean(d**2)))


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("remote_pipeline")
    t = tank_phantom(n_fish=2, seed=1, length=90)
    scan = write_volume(t.volume, tmp / "tank.zarr", spacing=t.spacing, unit=t.unit)
    srv = ServerProcess(tmp / "data", "--workers", "2")
    yield tmp, t, scan, srv
    srv.stop()


def test_remote_run_writes_the_voxels_a_local_straighten_of_its_session_writes(setup):
    tmp, t, scan, srv = setup
    fish = t.fish[0]
    click = fish.centerline[len(fish.centerline) // 2]
    out = tmp / "remote" / "fish0.nrrd"
    out.parent.mkdir()
    code = remote_main(["run", str(scan), "--select", _arg(click), "-o", str(out), "--server", srv.address, "-q"])
    assert code == 0
    session = load_session(tmp / "remote" / "fish0.unwind.json")
    # the session describes the local scan: the local commands accept it
    assert session.source.path == str(scan.absolute()) and session.segmentation.k == 5
    assert _centreline_rms(session.deformation, fish) < 1.0  # against the ground truth
    local = tmp / "local_fish0.nrrd"
    assert cli.main(["straighten", str(scan), "--session", str(tmp / "remote" / "fish0.unwind.json"),
                     "-o", str(local), "-q"]) == 0
    a, b = open_volume(out), open_volume(local)
    assert a.dtype == b.dtype and a.shape == b.shape and a.spacing == b.spacing and a.origin == b.origin
    assert a.data.compute().tobytes() == b.data.compute().tobytes()
    # the segmentation part of the session is the one the local pipeline makes
    from napari_unwind.segmentation import segment, selected_ids

    features = segment(open_volume(scan), features=5)
    ids = selected_ids(features, seeds=[click])
    assert session.segmentation.selected == tuple(ids)
    # the one isovalue rule, from the phantom's values: the contrast midpoint of medium and flesh, within 10 %
    from napari_unwind.datasets import BACKGROUND, FLESH

    mid = 0.5 * (BACKGROUND + FLESH)
    assert abs(session.segmentation.isovalue - mid) <= 0.1 * (FLESH - BACKGROUND), session.segmentation.isovalue


def test_each_step_on_the_server_matches_the_core(setup, tmp_path):
    from napari_unwind.segmentation import join_tree, refine_mask, select
    from napari_unwind.warp import bend, map_points, straighten

    tmp, t, scan, srv = setup
    fish = t.fish[1]
    volume = open_volume(scan)
    with Client(srv.address, progress=False) as c:
        vid = c.upload(scan).volume_id
        np.testing.assert_array_equal(c.open(vid).data.compute(), t.volume)
        seg = c.segment(vid, features=5).result.segmentation_id
        tree = join_tree(volume)
        for k in (5, 3):
            info = c.simplify(seg, k) if k != 5 else c.segmentation(seg)
            local = tree.simplify(k)
            assert [f.voxel_count for f in info.feature] == [s.voxel_count for s in local.stats]
            assert [f.threshold for f in info.feature] == [s.threshold for s in local.stats]
        c.simplify(seg, 5)
        click = fish.centerline[len(fish.centerline) // 2]
        mask_job = c.select(seg, seeds=[click], output_name="fish1_mask.zarr")
        features = tree.simplify(5)
        working = select(features, seeds=[click])
        expected_mask = refine_mask(volume, working, features=features).compute()
        mask = c.open(mask_job.result.volume_id).data.compute()
        np.testing.assert_array_equal(mask.astype(bool), expected_mask)
        # the phantom's own mask: the selection is this fish
        assert (mask.astype(bool) & fish.mask).sum() > 0.9 * fish.mask.sum()

        head, tail = c.suggest_ends(mask_job.result.volume_id, vid)
        assert min(np.linalg.norm(head - fish.head), np.linalg.norm(head - fish.tail)) < 6
        sk = c.skeleton(mask_job.result.volume_id, volume_id=vid, head=fish.head, tail=fish.tail)
        session = Client.session(sk)
        assert _centreline_rms(session.deformation, fish) < 1.0
        d = session.deformation
        # the skeleton of the same mask and ends in this process: the same deformation, byte for byte
        from napari_unwind.pipeline import skeleton_step
        from napari_unwind.progress import run as drive
        from napari_unwind.session import Endpoints

        local = drive(skeleton_step(mask, Endpoints(head=tuple(fish.head), tail=tuple(fish.tail)),
                                    spacing=volume.spacing, origin=volume.origin, unit=volume.unit,
                                    volume=volume.data)).deformation
        assert json.dumps(local.to_dict(), sort_keys=True) == json.dumps(d.to_dict(), sort_keys=True)

        st = c.straighten(vid, sk.result.session_id, output_name="fish1.tif", order=1)
        straight = c.open(st.result.volume_id)
        expected = straighten(volume, d).data.compute()
        assert straight.data.dtype == expected.dtype
        np.testing.assert_array_equal(straight.data.compute(), expected)

        bj = c.bend(st.result.volume_id, sk.result.session_id, output_name="fish1_bent.nrrd")
        expected_bent = bend(open_volume(c.download(st.result.volume_id, tmp_path / "s.tif")), d,
                             shape=volume.shape).compute()
        np.testing.assert_array_equal(c.open(bj.result.volume_id).data.compute(), expected_bent)

        pts = np.array([fish.head, click, fish.tail])
        remote = c.map_points(sk.result.session_id, pts)
        np.testing.assert_array_equal(remote, map_points(pts, d))
        back = c.map_points(sk.result.session_id, remote, to="scan")
        np.testing.assert_allclose(back, pts, atol=1e-3)
        # measurements along the centreline (issue 24): the bytes unwind measure writes for the same inputs
        from napari_unwind.measure import measure

        mj = c.measure(sk.result.session_id, mask_volume_id=mask_job.result.volume_id, channels={"scan": vid})
        expected_csv = measure(d, mask=mask.astype(np.uint8), channels={"scan": volume}).csv_text()
        assert mj.result.table_csv == expected_csv
        assert "area [" in mj.result.table_csv.splitlines()[0] and int(mj.result.figures["stations"]) > 50
        assert list(mj.result.warnings) == []
        # the same voxels under a header without the scan's geometry: on its grid voxel for voxel, as a run takes a
        # mask, and said
        from napari_unwind.io import Volume

        bare = c.upload(Volume(mask, spacing=(2.0, 2.0, 2.0), origin=(5.0, 6.0, 7.0), unit=volume.unit),
                        name="bare").volume_id
        bj_ = c.measure(sk.result.session_id, mask_volume_id=bare, channels={"scan": vid})
        assert bj_.result.table_csv == expected_csv
        assert [w.split(":")[0] for w in bj_.result.warnings] == [
            "the mask's spacing 2 x 2 x 2 / origin 5 x 6 x 7 differ from the session's scan's 1 x 1 x 1 / 0 x 0 x 0"]
        # a mask cropped to its box with its origin (as 3D Slicer saves a segment): placed on the scan, the same
        # skeleton as the full mask's, and said (by the name the user gave it)
        idx = np.argwhere(mask)
        lo, hi = idx.min(axis=0), idx.max(axis=0) + 1
        box = Volume(mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]],
                     spacing=volume.spacing, origin=tuple(np.add(volume.origin, lo * np.asarray(volume.spacing))),
                     unit=volume.unit)
        crop_id = c.upload(box, name="fish1_segment").volume_id
        ck = c.skeleton(crop_id, volume_id=vid, head=fish.head, tail=fish.tail)
        assert json.dumps(Client.session(ck).deformation.to_dict(), sort_keys=True) == json.dumps(
            d.to_dict(), sort_keys=True)
        assert list(ck.result.warnings)[0].startswith("the mask fish1_segment (shape ")
        from napari_unwind.client import RemoteError

        for bad, code in (({"": vid}, "INVALID_ARGUMENT"), ({"a,b": vid}, "INVALID_ARGUMENT"),
                          ({"scan": "v_nothere"}, "NOT_FOUND")):
            with pytest.raises(RemoteError) as err:
                c.measure(sk.result.session_id, channels=bad)
            assert err.value.code == code, (bad, err.value.code, str(err.value))
        # the straighten job with other images of the scan's grid: one multi-channel output (issue 24 item 1),
        # each channel the image straightened alone
        mc = c.straighten(vid, sk.result.session_id, channels={"mask": mask_job.result.volume_id}, scan_name="ct",
                          output_name="fish1_channels.zarr")
        got = c.download(mc.result.volume_id, tmp_path / "channels.zarr")
        from napari_unwind.io import open_channels

        chans = open_channels(got)
        assert [ch.metadata["channel"] for ch in chans] == ["ct", "mask"]
        # what the output says of its sources: the volumes by name and checksum, never the server's paths; its
        # session records the other channel as the command line's does
        text = (got / "zarr.json").read_text()
        assert str((tmp / "data").resolve()) not in text and str(tmp / "data") not in text
        info = json.loads(text)["attributes"]["unwind"]["straightening"]
        records = info["session"]["channels"]
        assert [r["channel"] for r in records] == ["mask"]
        assert records[0]["path"] == c.info(mask_job.result.volume_id).name
        assert records[0]["checksum"].startswith("sha256:")
        np.testing.assert_array_equal(np.asarray(chans[0].data), expected)
        np.testing.assert_array_equal(np.asarray(chans[1].data),
                                      straighten(c.open(mask_job.result.volume_id), d).data.compute()
                                      .astype(expected.dtype))
        for bad, code in (({"ct": vid}, "INVALID_ARGUMENT"), ({"x": "v_nothere"}, "NOT_FOUND"),
                          ({f"c{k}": vid for k in range(17)}, "INVALID_ARGUMENT")):
            with pytest.raises(RemoteError) as err:
                c.straighten(vid, sk.result.session_id, channels=bad, scan_name="ct", output_name="x.zarr")
            assert err.value.code == code, (bad, err.value.code, str(err.value))
        with pytest.raises(RemoteError) as err:
            c.straighten(vid, sk.result.session_id, channels={"mask": mask_job.result.volume_id},
                         output_name="x.nrrd")
        assert err.value.code == "INVALID_ARGUMENT" and "OME-Zarr" in str(err.value)
        kinds = {pb.JobKind.Name(j.kind) for j in c.jobs()}
        assert {"JOB_KIND_SEGMENT", "JOB_KIND_SELECT", "JOB_KIND_ESTIMATE_DEFORMATION", "JOB_KIND_STRAIGHTEN",
                "JOB_KIND_BEND", "JOB_KIND_MEASURE"} <= kinds
    # nothing a job wrote for the user names the server's own files (a straight volume's source, a mask's, the
    # features'; they named the stored volume's path on the server)
    assert _server_paths_in_outputs(tmp / "data") == []


def _server_paths_in_outputs(data_root):
    """Files a job wrote for a user (what a download hands over: metadata, sessions, tables) that name the server's
    own data root."""
    root = str(data_root.resolve()).encode()
    return [str(f.relative_to(data_root)) for f in (data_root / ".unwind" / "users").rglob("*")
            if f.is_file() and f.suffix in (".json", ".csv", ".txt", ".nhdr", ".zattrs", ".zgroup", ".zarray")
            and root in f.read_bytes()[:200_000]]


def test_a_batch_straightens_every_fish_of_a_tank_and_writes_a_summary(setup, tmp_path):
    tmp, t, scan, srv = setup
    with Client(srv.address, progress=False) as c:
        rows = c.run_batch([BatchItem(scan=str(scan), select="all", name="tank", features=3),
                            BatchItem(scan=str(tmp / "missing.zarr"), select="all", name="missing")],
                           max_parallel=2, out_dir=tmp_path / "out", suffix=".nrrd")
    assert _server_paths_in_outputs(tmp / "data") == []
    by_name = {r["name"]: r for r in rows}
    assert set(by_name) == {"tank_f1", "tank_f2", "tank_f3", "missing"}
    assert by_name["missing"]["state"] == "failed" and "does not exist" in by_name["missing"]["error"]
    with open(tmp_path / "out" / "summary.csv") as f:
        table = list(csv.DictReader(f))
    assert {r["name"] for r in table} == set(by_name)
    # feature 2 of this tank is its tube wall, not a fish: reported, whatever became of it
    assert by_name["tank_f2"]["state"] == "succeeded" or by_name["tank_f2"]["error"]
    matched = []
    for name in ("tank_f1", "tank_f3"):
        r = by_name[name]
        assert r["state"] == "succeeded", r
        d = Deformation.from_dict(json.loads((tmp_path / "out" / f"{name}.unwind.json").read_text())["deformation"])
        # each specimen is one of the tank's fish, followed within a voxel
        rms = [_centreline_rms(d, f) for f in t.fish]
        assert min(rms) < 1.0
        matched.append(int(np.argmin(rms)))
        assert float(r["length"]) == pytest.approx(d.length, rel=1e-5)
        assert open_volume(tmp_path / "out" / f"{name}.nrrd").shape == d.output_shape()
    assert sorted(matched) == [0, 1]  # both fish, once each
