"""The dock's "server" backend against a real server in a child process on 127.0.0.1 (napari, Qt, Xvfb).

References: the core on this computer. The server's features are the local join tree's simplify(k) labels, its
selection mask is the local refine_mask of the same features, its skeleton on that mask is the local skeleton
(within the mesher's run-to-run noise), and its export of a deformation is the same dock's export on "this
computer" (the core's export_iter, in process). Errors: a wrong token is refused in one line; Cancel of a server
job cancels it on the server and leaves no file.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("napari")
pytest.importorskip("grpc")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "services"))

from _servers import ServerProcess  # noqa: E402
from test_workflow import click, fish_voxel, wait  # noqa: E402

from napari_unwind._napari._widget import UnwindWidget  # noqa: E402
from napari_unwind.cli import main as unwind_main  # noqa: E402
from napari_unwind.datasets import fish_phantom  # noqa: E402
from napari_unwind.deformation import Deformation  # noqa: E402
from napari_unwind.io import open_volume, write_volume  # noqa: E402
from napari_unwind.progress import run  # noqa: E402
from napari_unwind.segmentation import join_tree, refine_mask, select  # noqa: E402
from unwind_services._proto.unwind.v1 import common_pb2 as pb  # noqa: E402

pytestmark = pytest.mark.gui


@pytest.fixture(scope="module")
def fish():
    return fish_phantom(length=80, body_radius=5, tube=False, seed=1)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dock_server")
    tokens = tmp / "tokens"
    token_file = tmp / "alice.token"
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert unwind_main(["serve", "--tokens", str(tokens), "--add-token", "alice"]) == 0
    token_file.write_text(out.getvalue().splitlines()[-1] + "\n")
    srv = ServerProcess(tmp / "data", "--tokens", str(tokens), "--workers", "1")
    yield srv, token_file
    srv.stop()


def _connect(qtbot, w, address, token):
    w.scan_step.backend_combo.setCurrentIndex(w.scan_step.backend_combo.findData("server"))
    w.scan_step.server_address.setText(address)
    w.scan_step.server_token.setText(token)
    job = w.connect_server()
    assert job is not None, w.status.text()
    qtbot.waitUntil(lambda: job.done, timeout=30_000)


def test_wrong_token_and_unreachable_server_say_what_is_wrong_in_one_line(make_napari_viewer, qtbot, server):
    srv, _ = server
    w = UnwindWidget(make_napari_viewer())
    _connect(qtbot, w, srv.address, "not-the-token")
    text = w.status.text()
    assert text.startswith("error: UNAUTHENTICATED") and "\n" not in text and "Traceback" not in text, text
    assert w.server is None
    _connect(qtbot, w, "127.0.0.1:1", "any")  # nothing listens there
    text = w.status.text()
    assert text.startswith("error: UNAVAILABLE: 127.0.0.1:1") and "\n" not in text, text
    assert w.server is None
    w.scan_step.server_address.setText("127.0.0.1")
    assert w.connect_server() is None
    assert w.status.text().startswith("error: the server address must be host:port"), w.status.text()


def test_dock_on_a_server_exports_the_voxels_of_the_local_dock(make_napari_viewer, qtbot, tmp_path, fish, server):
    srv, token_file = server
    scan = tmp_path / "fish.nrrd"
    write_volume(fish.volume, scan, spacing=fish.spacing, unit=fish.unit)
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.window.add_dock_widget(w, name="Unwind")
    wait(qtbot, w, w.open_scan(scan))
    _connect(qtbot, w, srv.address, str(token_file))  # a token file is read
    assert w.server is not None and "SERVING" in w.scan_step.backend_info.text(), w.status.text()

    wait(qtbot, w, w.segment())
    qtbot.waitUntil(lambda: w.idle, timeout=30_000)
    assert type(w.tree).__name__ == "_ServerTree" and "segmentation" in w._remote  # segmented on the server
    vox = fish_voxel(fish)
    click(w._features_layer, vox * np.asarray(w.volume.spacing) + np.asarray(w.volume.origin), viewer=viewer)
    assert w.selected and fish.mask[tuple(vox)]

    wait(qtbot, w, w.suggest_ends())
    assert "volume_id" in w._remote and len(w._ends_layer.data) == 2
    # the selection's mask was made on the server by a Select job (not uploaded), and is the mask this computer
    # makes of the same features (refine_mask's default isovalue)
    mask_id = w._remote["mask"][1]
    features = join_tree(open_volume(scan)).simplify(w.features.k)
    expected_mask = refine_mask(open_volume(scan), select(features, ids=w.selected), features=features).compute()
    with w.server.client() as c:
        assert c.info(mask_id).origin_kind == "output" and c.job(c.info(mask_id).job_id).kind == pb.JOB_KIND_SELECT
        assert not [v for v in c.volumes() if v.origin_kind == "upload" and v.name == "selection"]
        np.testing.assert_array_equal(c.open(mask_id).data.compute().astype(bool), expected_mask)
    ends = (np.asarray(w._ends_layer.data) - np.asarray(w.volume.origin)) / np.asarray(w.volume.spacing)
    true_ends = fish.centerline[[0, -1]]
    assert min(np.linalg.norm(ends - true_ends, axis=1).max(),
               np.linalg.norm(ends[::-1] - true_ends, axis=1).max()) < 6  # the phantom's ends, within voxels

    wait(qtbot, w, w.run_skeleton(), timeout=120_000)
    d = w.model.deformation
    assert d is not None and "server" in w.status.text()
    assert w._remote["mask"][1] == mask_id  # the ends' mask, reused
    # the same skeleton on this computer, same mask and ends: the same deformation, byte for byte (the tet mesh is
    # deterministic)
    import json

    from napari_unwind.pipeline import skeleton_step

    scan_vol = open_volume(scan)
    local_d = run(skeleton_step(expected_mask, w.endpoints(), spacing=scan_vol.spacing, origin=scan_vol.origin,
                                unit=scan_vol.unit, volume=scan_vol.data)).deformation
    assert json.dumps(local_d.to_dict(), sort_keys=True) == json.dumps(d.to_dict(), sort_keys=True)

    # Cancel of a server export: no file
    cancelled = tmp_path / "cancelled.nrrd"
    job = w.export(cancelled)
    w.cancel()
    qtbot.waitUntil(lambda: job.done, timeout=60_000)
    assert "cancelled" in w.status.text() and not cancelled.exists()
    assert not [p for p in tmp_path.iterdir() if "cancelled" in p.name]

    remote = tmp_path / "remote.nrrd"
    wait(qtbot, w, w.export(remote), timeout=120_000)
    assert viewer.layers[-1].name == "straight remote.nrrd" and "(server)" in w.export_step.export_info.text()

    # Cancel of a server job that already started: the job is cancelled on the server (one worker, kept busy by a
    # skeleton job, so the export waits queued: the first record is its queued state, then the dock's Cancel)
    from napari_unwind._remote import _follow

    server_, ids = w.server, dict(w._remote)
    with server_.client() as c:
        blocker = c.skeleton(ids["mask"][1], volume_id=ids["volume_id"], wait=False)
        queued = c.straighten(ids["volume_id"], ids["session"][0], wait=False, output_name="never.nrrd")
        follow = _follow(c, queued)
        first = next(follow)
        assert first.stage == "server job" and first.message == "queued", first
        assert next(follow) == first  # nothing new: the same record again (a point where Cancel is seen)
        follow.close()  # what Cancel does to the job's generator
        assert c.job(queued.id).state == pb.JOB_STATE_CANCELLED
        c.cancel(blocker.id)

    # an edit here is not on the server: its export is refused in one line (the undo brings the server's back)
    w.model.set_deformation(Deformation.from_dict(d.to_dict()).move_keyframe(1, 1.0, 0.0), keep_history=True)
    assert w.export(tmp_path / "edited.nrrd") is None
    assert w.status.text().startswith("error: the server holds no session of this deformation"), w.status.text()
    assert w.model.undo() and w.model.deformation is d

    # the same deformation exported on this computer (switching backend forgets the server)
    w.scan_step.backend_combo.setCurrentIndex(w.scan_step.backend_combo.findData("local"))
    assert w.server is None and w.model.deformation is d
    local = tmp_path / "local.nrrd"
    wait(qtbot, w, w.export(local), timeout=120_000)
    a, b = open_volume(remote), open_volume(local)
    assert a.shape == b.shape and a.dtype == b.dtype
    assert a.spacing == pytest.approx(b.spacing) and a.origin == pytest.approx(b.origin)
    np.testing.assert_array_equal(a.data.compute(), b.data.compute())


def test_dock_segments_on_the_server_and_its_slider_simplifies_there(make_napari_viewer, qtbot, tmp_path, fish,
                                                                      server):
    import psutil
    from qtpy.QtCore import Qt

    from napari_unwind.session import load_session

    srv, token_file = server
    scan = tmp_path / "fish.nrrd"
    write_volume(fish.volume, scan, spacing=fish.spacing, unit=fish.unit)
    tree = join_tree(open_volume(scan))  # the reference: the core on this computer
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.window.add_dock_widget(w, name="Unwind")
    wait(qtbot, w, w.open_scan(scan))
    _connect(qtbot, w, srv.address, str(token_file))

    wait(qtbot, w, w.segment())
    qtbot.waitUntil(lambda: w.idle, timeout=30_000)
    assert type(w.tree).__name__ == "_ServerTree" and "segmentation" in w._remote
    np.testing.assert_array_equal(w.features.labels, tree.simplify(5).labels)
    np.testing.assert_array_equal(np.asarray(w._features_layer.data), tree.simplify(5).labels)
    assert w.segment_step.count_slider.isEnabled() and w.segment_step.count_slider.maximum() == min(100, tree.n_maxima)
    assert w.segment_step.table.rowCount() == 5

    # the slider simplifies on the server; during a drag only the latest value is asked for
    for k in (2, 4, 3):
        w.segment_step.count_slider.setValue(k)
    qtbot.waitUntil(lambda: w.idle and w.features.k == 3, timeout=30_000)
    f3 = tree.simplify(3)
    np.testing.assert_array_equal(w.features.labels, f3.labels)
    np.testing.assert_array_equal(np.asarray(w._features_layer.data), f3.labels)
    assert w.segment_step.table.rowCount() == 3

    # a click picks the feature under it (the local tree's label there); shift-click adds another
    vox = fish_voxel(fish)
    world = vox * np.asarray(w.volume.spacing) + np.asarray(w.volume.origin)
    fid = int(f3.ids_at([vox])[0])
    assert fid
    click(w._features_layer, world, viewer=viewer)
    assert w.selected == [fid]
    other = next(st for st in f3.stats if st.id != fid and st.voxel_count)
    at = np.asarray(other.max_position_full) * np.asarray(w.volume.spacing) + np.asarray(w.volume.origin)
    click(w._features_layer, at, shift=True, viewer=viewer)
    assert w.selected == sorted([fid, other.id])
    table = w.segment_step.table
    selected_rows = {table.item(i.row(), 0).data(Qt.ItemDataRole.UserRole) for i in table.selectedItems()}
    assert selected_rows == {fid, other.id}
    click(w._features_layer, world, viewer=viewer)
    assert w.selected == [fid]

    # the session records the segmentation as on this computer
    wait(qtbot, w, w.save_session(tmp_path / "s.unwind.json"))
    seg = load_session(tmp_path / "s.unwind.json").segmentation
    assert (seg.k, seg.level, seg.selected) == (3, f3.level, (fid,))
    np.testing.assert_allclose(seg.seeds[0], vox)

    # Cancel of a server Segment job cancels it on the server: the server's worker is held (SIGSTOP) so the job
    # cannot end before the Cancel reaches it, then released
    workers = psutil.Process(srv.proc.pid).children(recursive=True)
    for p in workers:
        p.suspend()
    try:
        job = w.segment()
        with w.server.client() as c:
            def segment_job():
                jobs = [j for j in c.jobs() if j.kind == pb.JOB_KIND_SEGMENT]
                return jobs[0] if len(jobs) and jobs[0].state in (pb.JOB_STATE_QUEUED, pb.JOB_STATE_RUNNING) \
                    else None
            qtbot.waitUntil(lambda: segment_job() is not None, timeout=30_000)
            cancelled = segment_job()
            w.cancel()
            qtbot.waitUntil(lambda: job.done, timeout=30_000)
            assert "cancelled" in w.status.text(), w.status.text()
            for p in workers:
                p.resume()
            workers = []
            qtbot.waitUntil(lambda: c.job(cancelled.id).state == pb.JOB_STATE_CANCELLED, timeout=30_000)
    finally:
        for p in workers:
            p.resume()
    assert w.features.k == 3 and w.selected == [fid]  # the dock keeps what it had


def test_dock_registers_a_scan_the_server_holds_instead_of_uploading_it(make_napari_viewer, qtbot, fish, server):
    srv, token_file = server
    scans = srv.data_root / "scans"
    scans.mkdir(exist_ok=True)
    scan = write_volume(fish.volume, scans / "fish_reg.nrrd", spacing=fish.spacing, unit=fish.unit)
    write_volume(fish.volume[:40], scans / "half.nrrd", spacing=fish.spacing, unit=fish.unit)
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    wait(qtbot, w, w.open_scan(scan))  # this computer opens the same file for display
    _connect(qtbot, w, srv.address, str(token_file))

    w.scan_step.server_path.setText("scans/half.nrrd")  # not this scan: refused in one line
    job = w.segment()
    qtbot.waitUntil(lambda: job.done, timeout=30_000)
    text = w.status.text()
    assert text.startswith("error: the server's scans/half.nrrd holds (40,") and "\n" not in text, text

    w.scan_step.server_path.setText("scans/fish_reg.nrrd")
    wait(qtbot, w, w.segment())
    qtbot.waitUntil(lambda: w.idle, timeout=30_000)
    with w.server.client() as c:
        info = c.info(w._remote["volume_id"])
        assert info.origin_kind == "register" and tuple(info.shape) == fish.volume.shape
    np.testing.assert_array_equal(w.features.labels, join_tree(open_volume(scan)).simplify(5).labels)
