"""SegmentationService on a real server: the features' label volume comes back, equal to the core's.

References: the core run in this process on the same voxels (join_tree + simplify, save_features/load_features,
select + refine_mask). The volume is a closed bright shell around a dimmer ball on a background: the shell is the
root feature, the ball a second one whose threshold is lower than the shell's, so a shell selection with its
cavity filled covers the ball and the default isovalue (the lowest threshold the mask covers) is the ball's.
"""

from __future__ import annotations

import numpy as np
import pytest
from _servers import ServerProcess

from napari_unwind.client import Client, RemoteError
from napari_unwind.io import as_volume
from napari_unwind.segmentation import join_tree, load_features, refine_mask, save_features, select
from unwind_services.auth import add_token


def _shell_and_ball(n: int = 40) -> np.ndarray:
    z, y, x = np.mgrid[:n, :n, :n] - n / 2 + 0.5
    r = np.sqrt(z**2 + y**2 + x**2)
    v = np.full((n, n, n), 100.0)
    v[(r > 12) & (r < 16)] = 1000.0
    v[r < 6] = 400.0
    v += np.random.default_rng(0).normal(0, 5, v.shape)
    return v.astype(np.uint16)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("segmentation_service")
    tokens = tmp / "tokens"
    alice, bob = add_token(tokens, "alice"), add_token(tokens, "bob")
    srv = ServerProcess(tmp / "data", "--tokens", tokens, "--workers", "1")
    volume = as_volume(_shell_and_ball(), spacing=(2.0, 1.0, 1.0), unit="um")
    with Client(srv.address, token=alice, progress=False) as c:
        vid = c.upload(volume, name="shell").volume_id
        seg = c.segment(vid, features=2).result.segmentation_id
    yield srv, alice, bob, volume, vid, seg, join_tree(volume)
    srv.stop()


def test_simplify_returns_a_downloadable_label_volume_equal_to_the_cores(setup, tmp_path):
    srv, alice, _, _, _, seg, tree = setup
    with Client(srv.address, token=alice, progress=False) as c:
        first = c.segmentation(seg)  # the Segment job's own features
        assert first.features == 2 and first.maxima == tree.n_maxima and first.labels_volume_id
        ids = {}
        for k in (2, 5, 3):
            info = c.simplify(seg, k)
            ids[k] = info.labels_volume_id
            local = tree.simplify(k)
            saved = load_features(save_features(local, tmp_path / f"k{k}.zarr"))
            labels = c.open(info.labels_volume_id)
            assert labels.data.dtype == np.uint16 and labels.shape == local.labels.shape
            np.testing.assert_array_equal(labels.data.compute(), local.labels)
            assert info.features == k and [f.threshold for f in info.feature] == [s.threshold for s in local.stats]
            remote = c.features(seg, k)  # Simplify + download + Features.from_labels
            np.testing.assert_array_equal(remote.labels, saved.labels)
            assert remote.stats == saved.stats and remote.k == k and remote.tree is None
            for attr in ("scale", "full_shape", "level", "spacing", "full_spacing", "origin", "unit"):
                assert getattr(remote, attr) == getattr(saved, attr), attr
        assert ids[2] == first.labels_volume_id and len(set(ids.values())) == 3
        # written once per k: asking again gives the same volume and adds none
        n = len(c.volumes())
        assert c.simplify(seg, 5).labels_volume_id == ids[5] and c.simplify(seg, 2).labels_volume_id == ids[2]
        assert len(c.volumes()) == n
        # Info describes the current (last) simplification
        assert c.segmentation(seg).features == 2 and c.features(seg).k == 2
        with pytest.raises(RemoteError) as info:
            c.simplify(seg, tree.n_maxima + 1) if tree.n_maxima < 100 else c.simplify(seg, 101)
        assert info.value.code == "INVALID_ARGUMENT"


def test_another_users_segmentation_and_labels_are_not_found(setup):
    srv, alice, bob, _, _, seg, _ = setup
    with Client(srv.address, token=alice, progress=False) as c:
        labels_id = c.simplify(seg, 3).labels_volume_id
    with Client(srv.address, token=bob, progress=False) as c:
        for call in (lambda: c.simplify(seg, 3), lambda: c.segmentation(seg), lambda: c.features(seg),
                     lambda: c.open(labels_id), lambda: c.select(seg, ids=[1])):
            with pytest.raises(RemoteError) as info:
                call()
            assert info.value.code == "NOT_FOUND", info.value
            assert seg in str(info.value) or labels_id in str(info.value)


def test_select_takes_the_features_it_names_and_cuts_where_refine_mask_cuts(setup):
    srv, alice, _, volume, _, seg, tree = setup
    f2 = tree.simplify(2)
    shell = next(s.id for s in f2.stats if s.container)
    ball = 3 - shell
    assert f2.stat(ball).threshold < f2.stat(shell).threshold  # the case where the two rules differ
    working = select(f2, ids=[shell], fill_holes=True)
    expected = refine_mask(volume, working, features=f2).compute()  # the default of this computer
    with Client(srv.address, token=alice, progress=False) as c:
        c.simplify(seg, 5)  # current: 5 features; the select names its own 2
        job = c.select(seg, ids=[shell], fill_holes=True, features=2)
        mask = c.open(job.result.volume_id).data.compute().astype(bool)
        np.testing.assert_array_equal(mask, expected)
        # the one rule, from the phantom's values: the enclosed ball (400 in a medium of 100) is the dimmer body,
        # cut at its contrast midpoint (within 10 % of its contrast), so the mask keeps it
        iso = float(job.result.figures["isovalue"])
        assert abs(iso - 250.0) <= 0.1 * 300.0, iso
        z, y, x = np.mgrid[:40, :40, :40] - 19.5
        inner = np.sqrt(z**2 + y**2 + x**2) < 5
        assert mask[inner].mean() >= 0.99
        with pytest.raises(RemoteError) as info:
            c.select(seg, ids=[1], features=7)  # never simplified to 7
        assert info.value.code == "FAILED_PRECONDITION" and "Simplify with features=7" in str(info.value)


def test_an_empty_features_statistics_cross_the_wire_as_nan(tmp_path):
    """A feature with no voxel above its threshold has no value range: its saved statistics hold null (JSON has no
    NaN), which the message gives as NaN instead of failing the call."""
    from dataclasses import replace

    from unwind_services import convert

    local = join_tree(_shell_and_ball()).simplify(2)
    empty = replace(local.stats[1], voxel_count=0, value_min=float("nan"), value_max=float("nan"))
    features = replace(local, stats=(local.stats[0], empty))
    loaded = load_features(save_features(features, tmp_path / "f.zarr"))  # what Info and Simplify read
    assert loaded.stats[1].value_min is None
    msg = convert.feature_msg(loaded.stats[1])
    assert np.isnan(msg.value_min) and np.isnan(msg.value_max) and msg.voxel_count == 0
