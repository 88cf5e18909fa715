"""The workflow model without Qt or napari (issue 21, item 1): the steps the dock runs, driven as a script would.

References are independent of the model: the phantom's ground truth (mask, centreline), the core's own functions
called directly (join_tree, refine_mask, straighten) and the spine's manual cord mask read with pynrrd.
"""

from __future__ import annotations

import numpy as np
import pytest

from napari_unwind.datasets import fish_phantom
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import as_volume, open_volume
from napari_unwind.progress import run
from napari_unwind.warp import straighten
from napari_unwind.workflow import LocalBackend, Workflow


def _do(wf, task):
    """Run a task as the dock does: its generator off the UI thread, then apply."""
    return task.apply(run(task.make()))


@pytest.fixture(scope="module")
def fish():
    return fish_phantom(length=80, body_radius=5, tube=False, seed=1)


@pytest.fixture(scope="module")
def done(fish, tmp_path_factory):
    """The whole workflow on the fish phantom, with the events it emitted."""
    wf = Workflow()
    events: list[str] = []
    for name in ("scan_changed", "features_changed", "selection_changed", "ends_changed", "skeleton_changed",
                 "exported"):
        getattr(wf, name).connect(lambda *a, name=name: events.append(name))
    volume = as_volume(fish.volume, spacing=fish.spacing, unit=fish.unit)
    wf.set_scan(volume, name="fish")
    _do(wf, wf.segment_task())
    centre = fish.centerline[len(fish.centerline) // 2]
    fid = wf.pick(centre)
    _do(wf, wf.suggest_ends_task())
    _do(wf, wf.skeleton_task())
    out = tmp_path_factory.mktemp("wf") / "straight.nrrd"
    _do(wf, wf.export_task(out))
    return wf, events, fid, out, volume


def test_the_steps_in_order_emit_their_events(done):
    wf, events, fid, out, _ = done
    assert events == ["scan_changed", "selection_changed", "features_changed", "selection_changed", "ends_changed",
                      "skeleton_changed", "exported"]


def test_the_click_selects_the_fish(done, fish):
    wf, _, fid, _, _ = done
    assert fid != 0 and wf.selection.ids == (fid,)
    mask = np.asarray(wf.mask())
    assert (mask & fish.mask).sum() > 0.9 * fish.mask.sum()
    assert (mask & ~fish.mask).sum() < 0.3 * fish.mask.sum()


def test_ends_and_skeleton_follow_the_phantom(done, fish):
    wf, *_ = done
    assert np.linalg.norm(np.asarray(wf.ends.head) - fish.centerline[0]) < 12
    assert np.linalg.norm(np.asarray(wf.ends.tail) - fish.centerline[-1]) < 12
    d = wf.edit.deformation
    assert d is wf.skeleton.deformation and abs(d.length - fish.length) < 0.2 * fish.length
    assert wf.skeleton.specimen.status == "ok", wf.skeleton.specimen.reason


def test_the_export_is_the_cores_straighten(done):
    wf, _, _, out, volume = done
    written = np.asarray(open_volume(out).data)
    np.testing.assert_array_equal(written, np.asarray(straighten(volume, wf.edit.deformation).data))


def test_the_export_takes_other_channels_of_the_scans_grid(done, fish, tmp_path):
    """Issue 24 item 1 through the model: the scan plus its mask as a second channel, one OME-Zarr with a c axis;
    each channel is that image straightened alone; a one-channel format and another grid are refused."""
    from dataclasses import replace

    from napari_unwind.io import open_channels

    wf, _, _, _, volume = done
    mask = as_volume(fish.mask.astype(np.uint16), spacing=fish.spacing, unit=fish.unit)
    mask = replace(mask, metadata={"channel": "mask"})
    out = tmp_path / "both.ome.zarr"
    _do(wf, wf.export_task(out, channels=[mask]))
    chans = open_channels(out)
    assert [c.metadata["channel"] for c in chans] == ["fish", "mask"]
    d = wf.edit.deformation
    np.testing.assert_array_equal(np.asarray(chans[0].data), np.asarray(straighten(volume, d).data))
    np.testing.assert_array_equal(np.asarray(chans[1].data), np.asarray(straighten(mask, d).data))
    with pytest.raises(InvalidInputError, match="holds one channel"):
        wf.export_task(tmp_path / "x.nrrd", channels=[mask])
    small = replace(as_volume(fish.mask[:-2].astype(np.uint16), spacing=fish.spacing, unit=fish.unit),
                    metadata={"channel": "small"})
    with pytest.raises(InvalidInputError, match="shape"):
        wf.export_task(tmp_path / "y.ome.zarr", channels=[small])


def test_a_new_scan_drops_the_old_work(done, fish):
    wf = Workflow()
    wf.set_scan(as_volume(fish.volume, spacing=fish.spacing), name="a")
    _do(wf, wf.segment_task())
    wf.pick(fish.centerline[len(fish.centerline) // 2])
    assert wf.has_selection
    wf.set_scan(as_volume(fish.volume[:, :, :-2], spacing=fish.spacing), name="b")
    assert wf.features is None and not wf.has_selection and wf.ends is None


def test_a_mask_is_the_selection(fish):
    wf = Workflow()
    wf.set_scan(as_volume(fish.volume, spacing=fish.spacing, unit=fish.unit), name="fish")
    labels = fish.mask.astype(np.uint8) * 2
    assert wf.use_mask(labels, label=2) == int(fish.mask.sum())
    np.testing.assert_array_equal(np.asarray(wf.mask()), fish.mask)
    with pytest.raises(InvalidInputError, match="holds no voxel of label 3"):
        wf.use_mask(labels, label=3)
    with pytest.raises(InvalidInputError, match="must lie on the scan's voxel grid"):
        wf.use_mask(labels[:, 1:])


@pytest.mark.parametrize("step", ["segment_task", "suggest_ends_task", "skeleton_task", "export_task"])
def test_steps_without_what_they_need_say_what_to_do(step):
    wf = Workflow()
    args = ("x.nrrd",) if step == "export_task" else ()
    with pytest.raises(InvalidInputError, match="there is no scan yet"):
        getattr(wf, step)(*args)


def test_no_step_knows_its_backend(fish):
    """A backend that records its calls runs every step: the model passes the scan, the selection and the
    options; nothing else decides where the work happens."""
    calls = []

    class Recording(LocalBackend):
        label = "recording"

        def segment(self, volume, **kw):
            calls.append(("segment", sorted(kw)))
            return (yield from super().segment(volume, **kw))

        def suggest_ends(self, volume, selection, **kw):
            calls.append(("suggest_ends", sorted(kw)))
            return (yield from super().suggest_ends(volume, selection, **kw))

    wf = Workflow(Recording())
    wf.set_scan(as_volume(fish.volume, spacing=fish.spacing), name="fish")
    _do(wf, wf.segment_task(k=3))
    assert wf.features.k == 3
    wf.pick(fish.centerline[len(fish.centerline) // 2])
    _do(wf, wf.suggest_ends_task())
    assert calls == [("segment", ["k", "level", "name", "smooth"]), ("suggest_ends", ["name"])]


def test_the_isovalue_grows_and_shrinks_the_mask(fish):
    """A lower threshold gives a larger mask, a higher one a smaller; each equals the core's refine_mask of the
    same features at that threshold; None is the default rule again."""
    from napari_unwind.segmentation import refine_mask, select

    wf = Workflow()
    volume = as_volume(fish.volume, spacing=fish.spacing, unit=fish.unit)
    wf.set_scan(volume, name="fish")
    _do(wf, wf.segment_task())
    fid = wf.pick(fish.centerline[len(fish.centerline) // 2])
    n0, share0, iso0 = run(wf.measure_task().make())
    assert wf.isovalue is None and share0 == pytest.approx(n0 / fish.volume.size)
    lo, hi = wf.intensity_range()
    assert lo < iso0 < hi
    counts = {}
    for iso in (iso0 - 0.3 * (iso0 - lo), iso0 + 0.3 * (hi - iso0)):
        wf.set_isovalue(iso)
        n, _, used = run(wf.measure_task().make())
        assert used == pytest.approx(iso)
        reference = refine_mask(volume, select(wf.features, ids=[fid]), features=wf.features, isovalue=iso)
        assert n == int(np.asarray(reference).sum())
        np.testing.assert_array_equal(np.asarray(wf.mask()), np.asarray(reference))
        counts[iso] = n
    low, high = sorted(counts)
    assert counts[low] > n0 > counts[high]
    wf.set_isovalue(None)
    assert run(wf.measure_task().make())[0] == n0


def test_a_mask_file_is_recorded_in_the_session_and_reopens_it(fish, tmp_path):
    """Issue 21 item 3/5: a session whose selection was a mask (a file, one of its labels) reopens that selection;
    a mask without a file is recorded once it is written. Reference: the phantom's own mask on disk (pynrrd)."""
    import nrrd

    from napari_unwind.session import Segmentation, Session, SourceInfo

    labels = fish.mask.astype(np.uint8) * 3
    labels[0, 0, 0] = 7  # another label: the session must keep the chosen one
    path = tmp_path / "expert mask.nrrd"
    nrrd.write(str(path), labels, index_order="C")
    wf = Workflow()
    volume = as_volume(fish.volume, spacing=fish.spacing, unit=fish.unit)
    wf.set_scan(volume, name="fish")
    task = wf.mask_file_task(path, label=3)
    data = run(task.make())
    task.apply(data)
    assert np.array_equal(np.asarray(wf.mask()), fish.mask)
    source = SourceInfo(path="scan", shape=volume.shape, dtype=volume.dtype.name, spacing=volume.spacing)
    seg = Session.from_dict(wf.session(source).to_dict()).segmentation
    assert seg == Segmentation(mask=str(path.absolute()), mask_label=3)

    again = Workflow()
    again.set_scan(volume, name="fish")
    task = again.mask_file_task(seg.mask, label=seg.mask_label)
    task.apply(run(task.make()))
    assert np.array_equal(np.asarray(again.mask()), fish.mask)

    # a mask that has no file: no record (nothing could reopen it) until it is written
    again.use_mask(labels, label=3)
    assert again.session(source).segmentation is None
    again.mask_written(tmp_path / "written.ome.zarr")
    assert again.session(source).segmentation.mask == str((tmp_path / "written.ome.zarr").absolute())

    path.unlink()
    with pytest.raises(InvalidInputError, match="mask file is missing"):
        run(again.mask_file_task(seg.mask).make())
    with pytest.raises(InvalidInputError, match="mask_label is given without"):
        Segmentation(mask_label=2)


def test_a_mask_file_cropped_to_its_box_is_placed_on_the_scan(fish, tmp_path):
    """A mask saved cropped to its segment's box (3D Slicer's .seg.nrrd) with its origin: the dock's selection is
    the full mask (reference: the phantom's mask; the crop's header written with pynrrd)."""
    from conftest import write_segment_crop

    path, _, _ = write_segment_crop(fish.mask, fish.spacing, tmp_path / "segment.seg.nrrd")
    wf = Workflow()
    wf.set_scan(as_volume(fish.volume, spacing=fish.spacing, unit=fish.unit), name="fish")
    task = wf.mask_file_task(path)
    value = run(task.make())
    task.apply(value)
    assert np.array_equal(np.asarray(wf.mask()), fish.mask)
    (note,) = value[1]  # said, as the command line says it (the dock shows it)
    assert "is a box of the scan's grid: placed at voxel" in note


def test_a_probability_map_as_the_mask_file_is_thresholded_and_says_so(fish, tmp_path):
    """A probability map saved as the mask (float, fractional values): the selection is its voxels >= 0.5
    (reference: numpy on the map), and the task's notes say so; a 0.0/1.0 float mask is taken as it is, unsaid."""
    import nrrd

    rng = np.random.default_rng(23)
    prob = np.where(fish.mask, rng.uniform(0.5, 1.0, fish.mask.shape), rng.uniform(0.0, 0.5, fish.mask.shape))
    prob = prob.astype(np.float32)
    nrrd.write(str(tmp_path / "prob.nrrd"), prob, index_order="C")
    nrrd.write(str(tmp_path / "binary.nrrd"), fish.mask.astype(np.float32), index_order="C")
    wf = Workflow()
    wf.set_scan(as_volume(fish.volume, spacing=fish.spacing, unit=fish.unit), name="fish")
    task = wf.mask_file_task(tmp_path / "prob.nrrd")
    value = run(task.make())
    task.apply(value)
    assert np.array_equal(np.asarray(wf.mask()), prob >= 0.5)
    (note,) = value[1]
    assert "fractional values" in note and ">= 0.5 are the specimen" in note
    task = wf.mask_file_task(tmp_path / "binary.nrrd")
    value = run(task.make())
    task.apply(value)
    assert np.array_equal(np.asarray(wf.mask()), fish.mask) and value[1] == ()
