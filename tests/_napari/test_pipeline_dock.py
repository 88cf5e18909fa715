"""The dock's steps are the one pipeline's (napari, Qt, Xvfb): on a small fish phantom the deformation the dock
makes (its skeleton in a child process) is byte for byte the deformation of ``napari_unwind.pipeline`` on the same
mask and ends with the default options, its status is the pipeline's, and its export applies the one fold rule."""

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("napari")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "services"))

from test_workflow import fish_voxel, wait  # noqa: E402 - the workflow test's helpers

from napari_unwind import pipeline  # noqa: E402
from napari_unwind._napari._messages import for_dock  # noqa: E402
from napari_unwind._napari._widget import UnwindWidget  # noqa: E402
from napari_unwind.datasets import fish_phantom  # noqa: E402
from napari_unwind.deformation import Deformation  # noqa: E402
from napari_unwind.io import write_volume  # noqa: E402
from napari_unwind.progress import run  # noqa: E402
from napari_unwind.workflow import Skeletonized  # noqa: E402

pytestmark = pytest.mark.gui


@pytest.fixture(scope="module")
def fish():
    return fish_phantom(length=80, body_radius=5, tube=False, seed=1)  # the workflow test's phantom


@pytest.fixture
def scan_path(tmp_path, fish):
    path = tmp_path / "fish.nrrd"
    write_volume(fish.volume, path, spacing=fish.spacing, unit=fish.unit)
    return path


def dumps(d):
    return json.dumps(d.to_dict(), sort_keys=True)


def test_dock_skeleton_is_the_pipelines_byte_for_byte(make_napari_viewer, qtbot, fish, scan_path):
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.window.add_dock_widget(w, name="Unwind")  # as test_workflow: the dock in the viewer's window
    assert w.options == pipeline.PipelineOptions()  # the dock restates no default
    wait(qtbot, w, w.open_scan(scan_path))
    wait(qtbot, w, w.segment())
    qtbot.waitUntil(lambda: w.idle and w.features is not None, timeout=60_000)
    assert w.features.k == pipeline.SegmentOptions().k
    vox = fish_voxel(fish)
    w.select_features([int(w.features.ids_at([tuple(vox)])[0])])
    wait(qtbot, w, w.suggest_ends())
    ends = w.endpoints()
    wait(qtbot, w, w.run_skeleton(), timeout=180_000)
    dock = w.model.deformation
    assert dock is not None

    # the pipeline, in this process, on the dock's mask and ends: the skeleton step, then the whole run
    mask = w.mask()
    vol = w.volume
    direct = run(pipeline.skeleton_step(mask, ends, spacing=vol.spacing, origin=vol.origin, unit=vol.unit,
                                        volume=vol.data, options=pipeline.SkeletonOptions()))
    assert dumps(dock) == dumps(direct.deformation)
    whole = pipeline.run(vol, features=w.features, ids=list(w.selected), endpoints=ends)
    assert dumps(dock) == dumps(whole.deformation)

    # the status line is the pipeline's verdict, not a silent "done"
    assert w.specimen.status == whole.status and w.specimen.reason == whole.reason
    text = w.status.text()
    assert text.startswith(f"skeleton: {whole.status}"), text
    if whole.reason:
        assert whole.reason in text


def test_dock_on_a_server_shows_the_status_line_of_the_local_dock(make_napari_viewer, qtbot, fish, scan_path,
                                                                   tmp_path):
    """The same selection and ends, the skeleton on this computer and then on a server (the server's pipeline
    judges it and sends its verdict): the same status line, ok with the default cage and partial (with the same
    reason and coverage) with a cage too small for the body; the verdict is the local pipeline's judge."""
    pytest.importorskip("grpc")
    from _servers import ServerProcess

    from napari_unwind._napari._widget import _status_line

    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.window.add_dock_widget(w, name="Unwind")
    wait(qtbot, w, w.open_scan(scan_path))
    wait(qtbot, w, w.segment())  # on this computer: the server gets the selection's mask uploaded
    qtbot.waitUntil(lambda: w.idle and w.features is not None, timeout=60_000)
    w.select_features([int(w.features.ids_at([tuple(fish_voxel(fish))])[0])])
    wait(qtbot, w, w.suggest_ends())
    ends, mask, vol = w.endpoints(), w.mask(), w.volume
    cages = {"ok": pipeline.SkeletonOptions(), "partial": pipeline.SkeletonOptions(half_extent=(1.5, 1.5))}
    figures = ("status", "reason", "coverage", "folded", "lost", "length", "keyframes", "min_jacobian", "max_tilt")
    local = {}
    for name, options in cages.items():
        w.options = replace(w.options, skeleton=options)
        wait(qtbot, w, w.run_skeleton(), timeout=180_000)
        line = for_dock(_status_line(w.specimen))  # the core's advice said in the dock's words
        report = w.skeleton_step.skeleton_report.toPlainText()
        assert report.splitlines()[0] == line and w.status.text().startswith(line)
        # the pipeline's judge on the same mask and ends
        direct = run(pipeline.skeleton_step(mask, ends, spacing=vol.spacing, origin=vol.origin, unit=vol.unit,
                                            volume=vol.data, options=options))
        assert (w.specimen.status, w.specimen.reason) == pipeline.judge(direct)
        assert w.specimen.status == name, line
        local[name] = (line, {k: getattr(w.specimen, k) for k in figures})
    assert local["partial"][0].startswith("skeleton: partial: coverage")

    srv = ServerProcess(tmp_path / "data", "--workers", "1")
    try:
        w.scan_step.backend_combo.setCurrentIndex(w.scan_step.backend_combo.findData("server"))
        w.scan_step.server_address.setText(srv.address)
        job = w.connect_server()
        qtbot.waitUntil(lambda: job.done, timeout=30_000)
        assert w.server is not None, w.status.text()
        for name, options in cages.items():
            w.options = replace(w.options, skeleton=options)
            w.workflow.skeleton = None
            wait(qtbot, w, w.run_skeleton(), timeout=180_000)
            line, values = local[name]
            assert w.specimen is not None and {k: getattr(w.specimen, k) for k in figures} == values
            assert w.skeleton_step.skeleton_report.toPlainText().splitlines()[0] == line  # the local dock's line
            assert w.status.text().startswith(line + " (server)"), w.status.text()
    finally:
        srv.stop()


def test_partial_status_and_fold_rule_in_the_dock(make_napari_viewer, qtbot, tmp_path):
    """A partial result says so with its reason; a fold over the specimen (unknown coverage: an edited or loaded
    deformation) is refused with the command line's message unless "allow folds" is ticked."""
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    data = np.zeros((40, 40, 40), np.uint16)
    w.use_layer(viewer.add_image(data))

    class Fake:  # a SpecimenResult as the child sends it (only what the dock reads)
        status, reason, folded = "partial", "coverage 95.0 % of the mask inside the cage (goal 99 %)", None
        warnings = ()

        class skeleton:  # noqa: N801
            deformation = Deformation.from_polyline(np.array([[5.0, 20, 20], [20, 20, 20], [35, 20, 20]]),
                                                    spacing=1.0, cage_half_extent=4.0)
            suggested, warnings, endpoints, folded, context = False, (), None, 0.0, None

            @staticmethod
            def report():
                return "min Jacobian 1"

            @staticmethod
            def twist_report():
                return "twist: none (frames by parallel transport)"

    w.skeleton_step.skeleton_ready(Skeletonized(Fake, Fake.skeleton.deformation))
    assert w.status.text().startswith("skeleton: partial: coverage 95.0 %"), w.status.text()

    # a tight bend with a wide cage folds
    t = np.linspace(0, np.pi, 9)
    bent = Deformation.from_polyline(np.stack([20 + 6 * np.sin(t), 20 - 6 * np.cos(t), np.full_like(t, 20)], 1),
                                     spacing=1.0, cage_half_extent=15.0)
    if not bent.folds():
        pytest.skip("the bent phantom deformation does not fold")
    w.model.set_deformation(bent)
    expected = pipeline.fold_rule(bent, folded=None, allow_folds=False).message
    target = tmp_path / "folded.nrrd"
    assert not w.export_step.allow_folds_box.isChecked()
    job = w.export(target)
    qtbot.waitUntil(lambda: job.done, timeout=60_000)
    assert w.status.text() == f"error: {for_dock(expected)}", w.status.text()
    assert "--" not in w.status.text() and "tick \"allow folds\" (Export)" in w.status.text()
    assert not target.exists()
    w.export_step.allow_folds_box.setChecked(True)
    wait(qtbot, w, w.export(target))
    assert target.exists() and "\"allow folds\" is ticked" in w.export_step.export_info.text()


def test_the_docks_context_is_the_pipelines(make_napari_viewer, qtbot, fish, scan_path):
    viewer = make_napari_viewer()
    w = UnwindWidget(viewer)
    viewer.window.add_dock_widget(w, name="Unwind")
    wait(qtbot, w, w.open_scan(scan_path))
    wait(qtbot, w, w.segment())
    qtbot.waitUntil(lambda: w.idle and w.features is not None, timeout=60_000)
    w.select_features([int(w.features.ids_at([tuple(fish_voxel(fish))])[0])])
    wait(qtbot, w, w.suggest_ends())
    ends = w.endpoints()
    w.skeleton_step.context.setValue(3.0)
    wait(qtbot, w, w.run_skeleton(), timeout=180_000)
    vol = w.volume
    direct = run(pipeline.skeleton_step(w.mask(), ends, spacing=vol.spacing, origin=vol.origin, unit=vol.unit,
                                        volume=vol.data, options=pipeline.SkeletonOptions(context=3.0)))
    assert dumps(w.model.deformation) == dumps(direct.deformation)
    assert w.options.skeleton.context == 3.0
    report = w.skeleton_step.skeleton_report.toPlainText()
    assert "context: at least" in report and "twist:" in report
