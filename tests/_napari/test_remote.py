"""The dock's "server" backend against a real server in a child process on 127.0.0.1 (napari, Qt, Xvfb).

Reference: the same dock's export on "this computer" of the same deformation (the core's export_iter, in process);
the server must write the same voxels and geometry. Errors: a wrong token is refused in one line; Cancel of a
server export leaves no file.
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
    w.backend_combo.setCurrentIndex(w.backend_combo.findData("server"))
    w.server_address.setText(address)
    w.server_token.setText(token)
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
    w.server_address.setText("127.0.0.1")
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
    assert w.server is not None and "SERVING" in w.backend_info.text(), w.status.text()

    wait(qtbot, w, w.segment())
    qtbot.waitUntil(lambda: w.idle, timeout=30_000)
    vox = fish_voxel(fish)
    click(w._features_layer, vox * np.asarray(w.volume.spacing) + np.asarray(w.volume.origin), viewer=viewer)
    assert w.selected and fish.mask[tuple(vox)]

    wait(qtbot, w, w.suggest_ends())
    assert "volume_id" in w._remote and len(w._ends_layer.data) == 2
    ends = (np.asarray(w._ends_layer.data) - np.asarray(w.volume.origin)) / np.asarray(w.volume.spacing)
    true_ends = fish.centerline[[0, -1]]
    assert min(np.linalg.norm(ends - true_ends, axis=1).max(),
               np.linalg.norm(ends[::-1] - true_ends, axis=1).max()) < 6  # the phantom's ends, within voxels

    wait(qtbot, w, w.run_skeleton(), timeout=120_000)
    d = w.model.deformation
    assert d is not None and "server" in w.status.text()

    # Cancel of a server export: no file
    cancelled = tmp_path / "cancelled.nrrd"
    job = w.export(cancelled)
    w.cancel()
    qtbot.waitUntil(lambda: job.done, timeout=60_000)
    assert "cancelled" in w.status.text() and not cancelled.exists()
    assert not [p for p in tmp_path.iterdir() if "cancelled" in p.name]

    remote = tmp_path / "remote.nrrd"
    wait(qtbot, w, w.export(remote), timeout=120_000)
    assert viewer.layers[-1].name == "straight remote.nrrd" and "(server)" in w.export_info.text()

    # Cancel of a server job that already started: the job is cancelled on the server (one worker, kept busy by a
    # skeleton job, so the export waits queued: the first record is its queued state, then the dock's Cancel)
    from napari_unwind._napari._remote import _follow

    server_, ids = w.server, dict(w._remote)
    with server_.client() as c:
        blocker = c.skeleton(ids["mask"][1], volume_id=ids["volume_id"], wait=False)
        queued = c.straighten(ids["volume_id"], ids["session"][0], wait=False, output_name="never.nrrd")
        follow = _follow(c, queued)
        first = next(follow)
        assert first.stage == "server job" and first.message == "queued", first
        follow.close()  # what Cancel does to the job's generator
        assert c.job(queued.id).state == pb.JOB_STATE_CANCELLED
        c.cancel(blocker.id)

    # an edit here is not on the server: its export is refused in one line (the undo brings the server's back)
    w.model.set_deformation(Deformation.from_dict(d.to_dict()), keep_history=True)
    assert w.export(tmp_path / "edited.nrrd") is None
    assert w.status.text().startswith("error: the server holds no session of this deformation"), w.status.text()
    assert w.model.undo() and w.model.deformation is d

    # the same deformation exported on this computer (switching backend forgets the server)
    w.backend_combo.setCurrentIndex(w.backend_combo.findData("local"))
    assert w.server is None and w.model.deformation is d
    local = tmp_path / "local.nrrd"
    wait(qtbot, w, w.export(local), timeout=120_000)
    a, b = open_volume(remote), open_volume(local)
    assert a.shape == b.shape and a.dtype == b.dtype
    assert a.spacing == pytest.approx(b.spacing) and a.origin == pytest.approx(b.origin)
    np.testing.assert_array_equal(a.data.compute(), b.data.compute())
