"""``unwind straighten | bend | map-points`` as a user runs them, on a phantom with known truth."""


import numpy as np
import pytest

from conftest import fish_case, no_leftovers
from conftest import run_unwind as _run
from napari_unwind.io import open_volume, write_volume
from napari_unwind.session import save_session


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("warp_cli")
    return (tmp, *fish_case(tmp))


def test_straighten_matches_the_ground_truth(case):
    tmp, fish, scan, session, d = case
    out = tmp / "straight.nrrd"
    code, stdout, err = _run("straighten", scan, "--session", session, "-o", out, "-q")
    assert code == 0, err
    got = open_volume(out)
    assert got.shape == d.output_shape()
    np.testing.assert_allclose(got.spacing, [min(fish.spacing)] * 3)
    # straighten the true mask through the same path and compare with the true straight mask
    n = tuple(min(a, b) for a, b in zip(got.shape, fish.straight_mask.shape))
    mask = got.data.compute()[: n[0], : n[1], : n[2]] > 550
    truth = fish.straight_mask[: n[0], : n[1], : n[2]]
    dice = 2 * (mask & truth).sum() / (mask.sum() + truth.sum())
    assert dice > 0.9


def test_straighten_refuses_a_changed_scan(case, tmp_path):
    _, fish, _, session, _ = case
    changed = fish.volume.copy()
    changed[0, 0, 0] += 1
    other = write_volume(changed, tmp_path / "other.zarr", spacing=fish.spacing, unit=fish.unit)
    code, _, err = _run("straighten", other, "--session", session, "-o", tmp_path / "x.zarr", "-q")
    assert code == 1 and "has changed since this session was made" in err and "Traceback" not in err
    assert not (tmp_path / "x.zarr").exists() and no_leftovers(tmp_path) == []
    code, _, err = _run("straighten", tmp_path / "missing.zarr", "--session", session, "-o", tmp_path / "x.zarr")
    assert code == 1 and "missing" in err


def test_straighten_refuses_a_folding_deformation(case, tmp_path):
    tmp, _, scan, session_path, d = case
    from napari_unwind.session import load_session

    session = load_session(session_path)
    session.deformation = d.resize_keyframe(None, (80.0, 80.0))  # far larger than the bend radius
    folding = save_session(session, tmp_path / "fold.unwind.json")
    code, _, err = _run("straighten", scan, "--session", folding, "-o", tmp_path / "x.zarr", "-q")
    assert code == 1 and "folds" in err and "--allow-folds" in err
    assert not (tmp_path / "x.zarr").exists()


def test_bend_puts_the_straight_fish_back(case):
    tmp, fish, scan, session, d = case
    straight = tmp / "straight_for_bend.zarr"
    assert _run("straighten", scan, "--session", session, "-o", straight, "-q")[0] == 0
    bent = tmp / "bent.zarr"
    code, _, err = _run("bend", straight, "--session", session, "-o", bent, "-q")
    assert code == 0, err
    back = open_volume(bent).data.compute()
    assert back.shape == fish.volume.shape
    inside = fish.mask  # deep inside the specimen the round trip is close to the original
    from scipy.ndimage import binary_erosion

    core = binary_erosion(inside, iterations=2)
    err_rel = np.abs(back[core].astype(float) - fish.volume[core]) / fish.volume[core].max()
    assert np.median(err_rel) < 0.05


def test_map_points_round_trip(case, tmp_path):
    tmp, fish, scan, session, d = case
    pts = fish.centerline[::25]
    csv = tmp_path / "pts.csv"
    csv.write_text("axis0,axis1,axis2\n" + "\n".join(",".join(f"{v:.6f}" for v in p) for p in pts) + "\n")
    code, out, err = _run("map-points", csv, "--session", session, "--to", "straight")
    assert code == 0, err
    rows = [r for r in out.splitlines() if r and not r.startswith("#")][1:]
    straight = np.array([[float(c) for c in r.split(",")] for r in rows])
    # the centreline maps to the middle of the cross-section: i = (Ny-1)/2, j = (Nx-1)/2
    _, ny, nx = d.output_shape()
    np.testing.assert_allclose(straight[:, 1], (ny - 1) / 2, atol=0.6)
    np.testing.assert_allclose(straight[:, 2], (nx - 1) / 2, atol=0.6)
    back_csv = tmp_path / "back.csv"
    args = ["map-points", "--session", session, "--to", "scan", "-o", back_csv, "-q"]
    for p in straight:
        args += ["--at", ",".join(f"{v:.9f}" for v in p)]
    code, _, err = _run(*args)
    assert code == 0, err
    rows = [r for r in back_csv.read_text().splitlines() if r and not r.startswith("#")][1:]
    back = np.array([[float(c) for c in r.split(",")] for r in rows])
    np.testing.assert_allclose(back, pts, atol=1e-3)


def test_map_points_bad_csv(case, tmp_path):
    _, _, _, session, _ = case
    bad = tmp_path / "bad.csv"
    bad.write_text("1,2,3\n4,five,6\n")
    code, _, err = _run("map-points", bad, "--session", session)
    assert code == 1 and "line 2" in err


def test_another_channel_of_the_same_grid_is_straightened_with_the_session(case, tmp_path):
    """Issue 24 item 1: ``--same-grid`` takes another image of the scan's grid (here 2 x the scan, float32): checked
    by shape, spacing and origin instead of the checksum, straightened with the session's deformation (linear
    interpolation is linear: twice the scan's straight volume), and the output's own session records the image."""
    import json

    import zarr

    tmp, fish, scan, session, d = case
    other = write_volume(fish.volume.astype(np.float32) * 2, tmp_path / "channel2.nrrd", spacing=fish.spacing,
                         unit=fish.unit)
    code, _, err = _run("straighten", other, "--session", session, "-o", tmp_path / "refused.zarr", "-q")
    assert code == 1 and "has changed since this session was made" in err      # without the flag: the checksum
    out1, out2 = tmp_path / "scan.ome.zarr", tmp_path / "channel2.ome.zarr"
    assert _run("straighten", scan, "--session", session, "-o", out1, "-q")[0] == 0
    code, _, err = _run("straighten", other, "--session", session, "--same-grid", "-o", out2, "-q")
    assert code == 0, err
    a, b = open_volume(out1).data.compute(), open_volume(out2).data.compute()
    np.testing.assert_allclose(b, 2.0 * a, rtol=0, atol=1.0 + 1e-3)   # the scan's straight volume is uint16 (rounded)
    attrs = json.loads(json.dumps(dict(zarr.open_group(str(out2), mode="r").attrs)))
    text = json.dumps(attrs)
    assert "channel2.nrrd" in text and '"channels"' in text
    # another grid is refused in one line, before any work
    small = write_volume(fish.volume[:-4], tmp_path / "small.nrrd", spacing=fish.spacing, unit=fish.unit)
    code, _, err = _run("straighten", small, "--session", session, "--same-grid", "-o", tmp_path / "x.zarr", "-q")
    assert code == 1 and "--same-grid" in err and "shape" in err and len(err.strip().splitlines()) == 1
    coarse = write_volume(fish.volume, tmp_path / "coarse.nrrd", spacing=(2.0, 2.0, 2.0), unit=fish.unit)
    code, _, err = _run("straighten", coarse, "--session", session, "--same-grid", "-o", tmp_path / "y.zarr", "-q")
    assert code == 1 and "Traceback" not in err and "spacing" in err
    assert not (tmp_path / "x.zarr").exists() and not (tmp_path / "y.zarr").exists()


def test_several_channels_are_straightened_in_one_pass_into_one_image(case, tmp_path):
    """Issue 24 item 1: the scan plus two images of its grid (2 x the scan as float32, the true mask as uint8) give
    one OME-Zarr with a c axis (channels named, types promoted to the common float32) and one ImageJ hyperstack;
    each channel equals that image straightened alone; the output's session records the two other channels."""
    import json

    import tifffile
    import zarr

    from napari_unwind.io import open_channels

    tmp, fish, scan, session, d = case
    double = write_volume(fish.volume.astype(np.float32) * 2, tmp_path / "double.nrrd", spacing=fish.spacing,
                          unit=fish.unit)
    mask = write_volume(fish.mask.astype(np.uint8), tmp_path / "mask.nrrd", spacing=fish.spacing, unit=fish.unit)
    alone = tmp_path / "alone.ome.zarr"
    assert _run("straighten", scan, "--session", session, "-o", alone, "-q")[0] == 0
    ref = open_volume(alone).data.compute().astype(np.float32)
    out = tmp_path / "all.ome.zarr"
    code, stdout, err = _run("straighten", scan, double, mask, "--session", session, "--channel-names",
                             "ct,double,mask", "-o", out)
    assert code == 0, err
    assert "3 channels (ct, double, mask)" in stdout
    chans = open_channels(out)
    assert [c.metadata["channel"] for c in chans] == ["ct", "double", "mask"]
    got = [np.asarray(c.data) for c in chans]
    assert got[0].dtype == np.float32 and got[0].shape == ref.shape
    np.testing.assert_allclose(got[0], ref, atol=0.5 + 1e-3)          # the scan alone is uint16 (rounded)
    np.testing.assert_allclose(got[1], 2 * got[0], rtol=1e-6, atol=1e-3)
    assert 0 <= got[2].min() and got[2].max() <= 1 and got[2].max() > 0.99
    attrs = json.loads(json.dumps(dict(zarr.open_group(str(out), mode="r").attrs)))
    rec = attrs["unwind"]["straightening"]
    recorded = rec["session"]["channels"]
    assert [c["channel"] for c in recorded] == ["double", "mask"]
    assert "unwind-tmp" not in json.dumps(attrs)   # no temporary name leaks into the metadata
    # the same command again: the same bytes in every file of the store
    again = tmp_path / "again.ome.zarr"
    assert _run("straighten", scan, double, mask, "--session", session, "--channel-names", "ct,double,mask",
                "-o", again, "-q")[0] == 0
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    assert all((out / f).read_bytes() == (again / f).read_bytes() for f in files)
    assert recorded[0]["path"].endswith("double.nrrd") and recorded[0]["checksum"].startswith("sha256:")
    # the hyperstack: Fiji's ZCYX with the names as labels
    tif = tmp_path / "all.tif"
    code, _, err = _run("straighten", scan, mask, "--session", session, "-o", tif, "-q")
    assert code == 0, err
    with tifffile.TiffFile(tif) as t:
        assert t.is_imagej and t.series[0].axes == "ZCYX" and t.series[0].shape[1] == 2
        data = t.series[0].asarray()
    np.testing.assert_array_equal(data[:, 0], open_volume(alone).data.compute())
    # a format with one channel is refused in one line, nothing written
    code, _, err = _run("straighten", scan, mask, "--session", session, "-o", tmp_path / "x.nrrd", "-q")
    assert code == 1 and "OME-Zarr" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.nrrd").exists()
    # another grid among the channels: refused before any work
    small = write_volume(fish.volume[:-4], tmp_path / "small.nrrd", spacing=fish.spacing, unit=fish.unit)
    code, _, err = _run("straighten", scan, small, "--session", session, "-o", tmp_path / "y.zarr", "-q")
    assert code == 1 and "shape" in err and not (tmp_path / "y.zarr").exists()


def test_a_scan_with_a_channel_axis_gives_every_channel(case, tmp_path):
    """One OME-Zarr with a c axis (written here with zarr itself): all its channels, named by its omero labels."""
    import zarr

    from napari_unwind.io import open_channels

    tmp, fish, scan, session, d = case
    root = zarr.open_group(str(tmp_path / "two.zarr"), mode="w", zarr_format=3)
    stack = np.stack([fish.volume.astype(np.uint16), (fish.mask * 1000).astype(np.uint16)])
    arr = root.create_array("0", shape=stack.shape, chunks=(1, 32, 32, 32), dtype=stack.dtype)
    arr[...] = stack
    unit = open_volume(scan).unit
    root.attrs["ome"] = {"version": "0.5", "multiscales": [{
        "axes": [{"name": "c", "type": "channel"}] + [{"name": a, "type": "space", "unit": unit} for a in "zyx"],
        "datasets": [{"path": "0", "coordinateTransformations": [
            {"type": "scale", "scale": [1.0, *map(float, fish.spacing)]}]}]}],
        "omero": {"channels": [{"label": "ct"}, {"label": "body"}]}}
    out = tmp_path / "two.tif"
    code, _, err = _run("straighten", tmp_path / "two.zarr", "--session", session, "--same-grid", "-o", out, "-q")
    assert code == 0, err
    chans = open_channels(out)
    assert [c.metadata["channel"] for c in chans] == ["ct", "body"]
    alone = tmp_path / "alone.nrrd"
    assert _run("straighten", scan, "--session", session, "-o", alone, "-q")[0] == 0
    np.testing.assert_array_equal(np.asarray(chans[0].data), open_volume(alone).data.compute())
    # without --same-grid the first input must be the session's scan: its checksum is checked
    code, _, err = _run("straighten", tmp_path / "two.zarr", "--session", session, "-o", tmp_path / "y.tif", "-q")
    assert code == 1 and "changed" in err and not (tmp_path / "y.tif").exists()


def test_one_channel_of_a_multichannel_scan_runs_the_whole_pipeline(tmp_path):
    """``unwind run two.zarr --input-channel ct``: segmented and straightened on that channel; the session records
    it; ``unwind straighten two.zarr --session`` then gives both channels (the file's checksum is the session's)."""
    import zarr

    from napari_unwind.datasets import fish_phantom
    from napari_unwind.io import open_channels
    from napari_unwind.session import load_session
    from napari_unwind.warp import straighten

    fish = fish_phantom(length=60, body_radius=4, tube=False, seed=2)
    root = zarr.open_group(str(tmp_path / "two.zarr"), mode="w", zarr_format=3)
    stack = np.stack([(fish.mask * 900).astype(np.uint16), fish.volume.astype(np.uint16)])
    arr = root.create_array("0", shape=stack.shape, chunks=(1, 32, 32, 32), dtype=stack.dtype)
    arr[...] = stack
    root.attrs["ome"] = {"version": "0.5", "multiscales": [{
        "axes": [{"name": "c", "type": "channel"}] + [{"name": a, "type": "space", "unit": "micrometer"}
                                                      for a in "zyx"],
        "datasets": [{"path": "0", "coordinateTransformations": [
            {"type": "scale", "scale": [1.0, *map(float, fish.spacing)]}]}]}],
        "omero": {"channels": [{"label": "stain"}, {"label": "ct"}]}}
    code, _, err = _run("run", tmp_path / "two.zarr", "--input-channel", "ct", "--select",
                        ",".join(str(int(v)) for v in fish.centerline[len(fish.centerline) // 2]),
                        "-o", tmp_path / "fish.ome.zarr", "-q")
    assert code in (0, 2), err           # 2: a partial result, still written with its session
    session = load_session(tmp_path / "fish.ome.unwind.json")
    assert session.source.channel == "ct"
    code, _, err = _run("straighten", tmp_path / "two.zarr", "--session", tmp_path / "fish.ome.unwind.json",
                        "-o", tmp_path / "both.ome.zarr", "-q")
    assert code == 0, err
    chans = open_channels(tmp_path / "both.ome.zarr")
    assert [c.metadata["channel"] for c in chans] == ["stain", "ct"]
    expected = straighten(open_channels(tmp_path / "two.zarr")[1], session.deformation).data.compute()
    np.testing.assert_array_equal(np.asarray(chans[1].data), expected)
    code, _, err = _run("run", tmp_path / "two.zarr", "--input-channel", "nope", "--select", "1,1,1",
                        "-o", tmp_path / "x.ome.zarr")
    assert code == 1 and "stain, ct" in err and len(err.strip().splitlines()) == 1


def test_info_describes_every_channel(tmp_path):
    import tifffile

    data = np.arange(2 * 3 * 4 * 5, dtype=np.uint16).reshape(3, 2, 4, 5)
    tifffile.imwrite(tmp_path / "h.tif", data, imagej=True, metadata={"axes": "ZCYX", "Labels": ["dapi", "gfp"] * 3})
    code, out, err = _run("info", tmp_path / "h.tif")
    assert code == 0, err
    assert "shape:     3 x 4 x 5" in out and "channels:  2 (dapi, gfp)" in out
    code, out, err = _run("info", tmp_path / "h.tif", "--input-channel", "gfp")
    assert code == 0 and "channels:" not in out and "shape:     3 x 4 x 5" in out


def test_convert_and_import_keep_every_channel(tmp_path):
    """An ImageJ hyperstack (written by tifffile) converted and imported to OME-Zarr: the channels, their names,
    voxels and (import) the pyramid."""
    import tifffile

    from napari_unwind.io import open_channels

    data = np.random.default_rng(4).integers(0, 4000, (5, 3, 6, 7)).astype(np.uint16)
    tifffile.imwrite(tmp_path / "h.tif", data, imagej=True, metadata={"axes": "ZCYX", "Labels": ["a", "b", "c"] * 5})
    code, _, err = _run("convert", tmp_path / "h.tif", tmp_path / "h.ome.zarr", "-q")
    assert code == 0, err
    chans = open_channels(tmp_path / "h.ome.zarr")
    assert [c.metadata["channel"] for c in chans] == ["a", "b", "c"]
    for k, c in enumerate(chans):
        np.testing.assert_array_equal(np.asarray(c.data), data[:, k])
    code, _, err = _run("import", tmp_path / "h.tif", tmp_path / "i.zarr", "--max-side", "4", "-q")
    assert code == 0, err
    imported = open_channels(tmp_path / "i.zarr")
    assert [c.metadata["channel"] for c in imported] == ["a", "b", "c"] and len(imported[2].levels) > 1
    np.testing.assert_array_equal(np.asarray(imported[2].data), data[:, 2])
    code, _, err = _run("convert", tmp_path / "h.tif", tmp_path / "h.nrrd", "-q")
    assert code == 1 and "holds one channel" in err and not (tmp_path / "h.nrrd").exists()
    code, _, err = _run("convert", tmp_path / "h.tif", tmp_path / "b.nrrd", "--input-channel", "b", "-q")
    assert code == 0, err
    np.testing.assert_array_equal(np.asarray(open_channels(tmp_path / "b.nrrd")[0].data), data[:, 1])


@pytest.mark.parametrize("channels", [1, 2])
def test_straighten_writes_what_the_pipeline_export_step_writes(case, tmp_path, channels):
    """One pipeline: ``unwind straighten --chunks`` writes what the core's ``export_step`` (the step ``unwind run``,
    the batch, the server and the dock call) writes with the same options, file for file: the OME-Zarr stored in
    the chunks asked for (it kept zarr's default chunking on disk before), one channel and several."""
    import json

    from napari_unwind.io import open_volume as ov
    from napari_unwind.pipeline import ExportOptions, export_step
    from napari_unwind.progress import run as drive
    from napari_unwind.session import load_session

    tmp, fish, scan, session_path, d = case
    inputs = [scan]
    if channels == 2:
        inputs.append(write_volume(fish.volume.astype(np.float32) * 2, tmp_path / "c2.nrrd", spacing=fish.spacing,
                                   unit=fish.unit))
    cli_out = tmp_path / "cli.ome.zarr"
    code, _, err = _run("straighten", *inputs, "--session", session_path, "--chunks", "8,12,10", "--pad", "2",
                        "-o", cli_out, "-q")
    assert code == 0, err
    # the chunking on disk, read from the store's own metadata (the reference: what was asked)
    meta = json.loads((cli_out / "0" / "zarr.json").read_text())
    chunk = meta["chunk_grid"]["configuration"]["chunk_shape"]
    assert chunk[-3:] == [8, 12, 10]
    # and every array file byte for byte what export_step writes
    api_out = tmp_path / "api.ome.zarr"
    others = [ov(p) for p in inputs[1:]]
    for k, v in enumerate(others, start=1):
        v.metadata["channel"] = f"c{k}"
    drive(export_step(ov(scan), load_session(session_path).deformation, api_out,
                      options=ExportOptions(chunks=(8, 12, 10), pad=2), channels=others or None))
    cli_files = sorted(p.relative_to(cli_out) for p in cli_out.rglob("*") if p.is_file() and p.parent != cli_out)
    api_files = sorted(p.relative_to(api_out) for p in api_out.rglob("*") if p.is_file() and p.parent != api_out)
    assert cli_files == api_files
    for rel in cli_files:
        if rel.name != "zarr.json":
            assert (cli_out / rel).read_bytes() == (api_out / rel).read_bytes(), rel


def test_channel_names_for_one_image_of_one_channel_is_refused(case, tmp_path):
    tmp, fish, scan, session_path, d = case
    code, _, err = _run("straighten", scan, "--session", session_path, "--channel-names", "ct", "-o",
                        tmp_path / "x.ome.zarr", "-q")
    assert code == 1 and "--channel-names" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.ome.zarr").exists()
