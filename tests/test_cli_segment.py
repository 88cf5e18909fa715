"""``unwind segment`` and ``unwind select`` on the phantom tank, as a user runs them."""


import numpy as np
import pytest

from conftest import no_leftovers
from conftest import run_unwind as _run
from napari_unwind.datasets import tank_phantom
from napari_unwind.io import open_volume, write_volume


@pytest.fixture(scope="module")
def tank(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("seg_cli")
    t = tank_phantom(n_fish=3, seed=0)
    scan = write_volume(t.volume, tmp / "tank.zarr", spacing=t.spacing, unit=t.unit)
    labels = tmp / "labels.zarr"
    code, out, err = _run("segment", scan, "-o", labels, "--features", "5", "-q")
    assert code == 0, err
    return tmp, t, scan, labels


def _dice(a, b):
    return 2 * np.logical_and(a, b).sum() / (a.sum() + b.sum())


def test_each_fish_is_selected_by_a_click(tank):
    tmp, t, scan, labels = tank
    for i, fish in enumerate(t.fish):
        seed = fish.centerline[len(fish.centerline) // 2]
        out = tmp / f"fish{i}.nrrd"
        code, _, err = _run("select", labels, "--at", ",".join(f"{v:.1f}" for v in seed), "-o", out,
                            "--full-resolution", scan, "-q")
        assert code == 0, err
        mask = open_volume(out).data.compute().astype(bool)
        assert mask.shape == t.volume.shape
        assert _dice(mask, fish.mask) >= 0.9


def test_a_click_in_the_background_names_the_nearest_feature(tank, tmp_path):
    _, t, _, labels = tank
    code, _, err = _run("select", labels, "--at", "0,0,0", "-o", tmp_path / "m.zarr")
    assert code == 1 and "background" in err and "nearest feature" in err and "Traceback" not in err
    code, _, err = _run("select", labels, "--at", "9999,0,0", "-o", tmp_path / "m.zarr")
    assert code == 1 and "outside the volume" in err
    code, _, err = _run("select", labels, "-o", tmp_path / "m.zarr")
    assert code == 1 and "--at" in err
    assert no_leftovers(tmp_path) == [] and not (tmp_path / "m.zarr").exists()


def test_segment_refuses_bad_input(tmp_path):
    flat = write_volume(np.full((20, 20, 20), 7, np.uint16), tmp_path / "flat.zarr")
    code, _, err = _run("segment", flat, "-o", tmp_path / "l.zarr")
    assert code == 1 and "nothing to segment" in err
    code, _, err = _run("segment", flat, "-o", tmp_path / "l.zarr", "--features", "101")
    assert code == 1 and "100" in err
    assert not (tmp_path / "l.zarr").exists()


def test_segment_checks_its_output_before_working(tmp_path):
    # a flat volume fails in the tree build ("nothing to segment"); a bad output name must be reported first
    flat = write_volume(np.full((20, 20, 20), 7, np.uint16), tmp_path / "flat.zarr")
    code, _, err = _run("segment", flat, "-o", tmp_path / "labels.tif")
    assert code == 1 and "*.zarr" in err and "nothing to segment" not in err
    (tmp_path / "labels.zarr").mkdir()
    code, _, err = _run("segment", flat, "-o", tmp_path / "labels.zarr")
    assert code == 1 and "--overwrite" in err and "nothing to segment" not in err


def test_segment_lists_the_specimens(tank, tmp_path):
    _, t, scan, _ = tank
    labels = tmp_path / "labels.zarr"
    code, out, err = _run("segment", scan, "-o", labels, "--features", "7", "--specimens", "-q")
    assert code == 0, err
    ids = [int(v) for v in out.strip().split(",")]
    lab = np.asarray(open_volume(labels).data)
    assert len(ids) == len(t.fish)  # the fish, not the tube nor its pieces
    for fish in t.fish:
        assert max(_dice(lab == i, fish.mask) for i in ids) >= 0.9
    code, out, err = _run("segment", scan, "-o", labels, "--features", "7", "--overwrite")
    assert code == 0, err
    assert "container" in out  # the full table marks the tube
    assert f"{len(t.fish)} specimen(s) (elongated, inside the scan, not containers): {', '.join(map(str, ids))}" in out
