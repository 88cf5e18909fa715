"""Several channels through one deformation (issue 24 item 1): reading channel axes, one-pass straightening,
multi-channel outputs. The references are scipy's map_coordinates per channel and tifffile / zarr / ome-zarr's
own readers."""

from __future__ import annotations

import json

import dask
import dask.array as da
import numpy as np
import pytest
import scipy.ndimage as ndi
import tifffile
import zarr
from test_warp import random_deformation, reference_coords, smooth_volume

from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume, as_volume, open_channels, open_volume, write_channels_iter
from napari_unwind.progress import run
from napari_unwind.warp import export_channels_iter, straighten, straighten_channels


def _channels(shape, n, dtype=np.uint16, seed=0):
    out = []
    for k in range(n):
        v = smooth_volume(shape, seed=seed + k, dtype=np.float32)
        out.append((v * 4000 + 100 * k).astype(dtype) if np.dtype(dtype).kind in "iu" else v.astype(dtype))
    return out


@pytest.mark.parametrize("order", [0, 1, 3])
@pytest.mark.parametrize("dtype", [np.uint16, np.float32, np.int16])
@pytest.mark.parametrize("chunking", ["mixed", "whole"])
def test_every_channel_equals_scipy_on_its_own(order, dtype, chunking):
    shape, spacing, origin = (34, 30, 40), (1.5, 1.0, 0.8), (-3.0, 10.0, 2.5)
    arrays = _channels(shape, 3, dtype=dtype, seed=order)
    d = random_deformation(1, shape, spacing, origin)
    # each channel with its own chunking: the task reads each from its own chunks (the regions assembled into one
    # array); or one chunk each (each channel resampled from a view of its chunk)
    chunks = [(9, 11, 13), (34, 30, 40), (5, 7, 40)] if chunking == "mixed" else [shape] * 3
    vols = [Volume(da.from_array(a, chunks=c), spacing=spacing, origin=origin, unit="um")
            for a, c in zip(arrays, chunks, strict=True)]
    out = straighten_channels(vols, d, order=order, spacing=0.9, pad=2, fill=7, chunks=(6, 7, 8))
    coords = reference_coords(d, 0.9, 2)
    for k, a in enumerate(arrays):
        ref = ndi.map_coordinates(a, coords, order=order, mode="constant", cval=7)
        got = out[k].data.compute()
        assert got.dtype == np.dtype(dtype) and got.shape == ref.shape
        tol = 0 if order == 0 else (1 if np.dtype(dtype).kind in "iu" else 1e-4)
        if order == 3:
            tol = 2e-3 * float(np.ptp(a)) + 1
        np.testing.assert_allclose(got.astype(float), ref.astype(float), atol=tol, rtol=0)
        assert out[k].metadata["channel"] == f"c{k}"
        # and the same bytes as straightening that channel alone
        alone = straighten(vols[k], d, order=order, spacing=0.9, pad=2, fill=7, chunks=(6, 7, 8)).data.compute()
        np.testing.assert_array_equal(got, alone)


def test_one_task_per_output_block_reads_each_input_chunk_once():
    shape = (40, 32, 36)
    arrays = _channels(shape, 2)
    d = random_deformation(0, shape)
    seen: dict[int, list] = {0: [], 1: [], 2: []}

    def counting(block, k, block_info=None):
        seen[k].append(tuple(block_info[0]["chunk-location"]))
        return block

    def counted(a, k):
        x = da.from_array(a, chunks=(10, 16, 18))
        return as_volume(x.map_blocks(counting, k, dtype=a.dtype, meta=np.empty((0, 0, 0), a.dtype)))

    out = straighten_channels([counted(a, k) for k, a in enumerate(arrays)], d, chunks=(8, 100, 100))
    alone = straighten(counted(arrays[0], 2), d, chunks=(8, 100, 100))
    with dask.config.set(scheduler="synchronous"):
        da.stack([v.data for v in out]).compute()
        alone.data.compute()
    # every input chunk of each channel read once, and exactly the chunks one channel alone reads
    assert len(seen[2]) == len(set(seen[2])) > 0
    assert sorted(seen[0]) == sorted(seen[1]) == sorted(seen[2])


def test_channels_of_different_grids_are_refused():
    a, b = _channels((20, 20, 20), 2)
    va = as_volume(a, spacing=(1, 1, 1), unit="um")
    with pytest.raises(InvalidInputError, match="shape"):
        straighten_channels([va, as_volume(b[:19])], random_deformation(0, (20, 20, 20)))
    with pytest.raises(InvalidInputError, match="at least one"):
        straighten_channels([], random_deformation(0, (20, 20, 20)))


def _write_ome_zarr_c(path, arrays, names, spacing, chunk_c=1):
    """A 4D OME-Zarr (c, z, y, x) written with zarr directly (not by the code under test)."""
    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    stack = np.stack(arrays)
    arr = root.create_array("0", shape=stack.shape, chunks=(chunk_c, 8, 16, 16), dtype=stack.dtype)
    arr[...] = stack
    root.attrs["ome"] = {
        "version": "0.5",
        "multiscales": [{
            "axes": [{"name": "c", "type": "channel"}] + [{"name": a, "type": "space", "unit": "micrometer"}
                                                          for a in "zyx"],
            "datasets": [{"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [1, *spacing]}]}],
        }],
        "omero": {"channels": [{"label": n} for n in names]},
    }


def test_open_channels_reads_a_c_axis_an_imagej_hyperstack_and_several_files(tmp_path):
    arrays = _channels((16, 20, 24), 3)
    names = ["dapi", "gfp", "mcherry"]
    _write_ome_zarr_c(tmp_path / "c.zarr", arrays, names, (2.0, 0.5, 0.5), chunk_c=3)
    chans = open_channels(tmp_path / "c.zarr")
    assert [c.metadata["channel"] for c in chans] == names
    for c, a in zip(chans, arrays, strict=True):
        np.testing.assert_array_equal(np.asarray(c.data), a)
        assert c.spacing == (2.0, 0.5, 0.5) and c.unit == "micrometer"
    with pytest.raises(InvalidInputError, match="3 channels.*open_channels"):
        open_volume(tmp_path / "c.zarr")
    # ImageJ hyperstack ZCYX written by tifffile
    tifffile.imwrite(tmp_path / "h.tif", np.stack(arrays, axis=1), imagej=True,
                     metadata={"axes": "ZCYX", "Labels": names * 16})
    chans = open_channels(tmp_path / "h.tif")
    assert [c.metadata["channel"] for c in chans] == names
    for c, a in zip(chans, arrays, strict=True):
        np.testing.assert_array_equal(np.asarray(c.data), a)
    # several single-channel files, named by their file names
    for n, a in zip(names, arrays, strict=True):
        tifffile.imwrite(tmp_path / f"fish_{n}.tif", a, imagej=True, metadata={"axes": "ZYX"})
    chans = open_channels([tmp_path / f"fish_{n}.tif" for n in names])
    assert [c.metadata["channel"] for c in chans] == [f"fish_{n}" for n in names]
    tifffile.imwrite(tmp_path / "small.tif", arrays[0][:, :10], imagej=True, metadata={"axes": "ZYX"})
    with pytest.raises(InvalidInputError, match="shape"):
        open_channels([tmp_path / "fish_dapi.tif", tmp_path / "small.tif"])
    with pytest.raises(InvalidInputError, match="one name per channel"):
        open_channels(tmp_path / "c.zarr", names=["a"])


@pytest.mark.parametrize("suffix", [".zarr", ".tif"])
def test_a_straight_multichannel_export_reads_back_in_other_tools(tmp_path, suffix):
    shape, spacing = (30, 28, 34), (1.0, 1.0, 1.0)
    arrays = _channels(shape, 2)
    d = random_deformation(2, shape, spacing)
    _write_ome_zarr_c(tmp_path / "scan.zarr", arrays, ["dapi", "gfp"], spacing)
    chans = open_channels(tmp_path / "scan.zarr")
    out = tmp_path / f"straight{suffix}"
    written = run(export_channels_iter(chans, d, out, chunks=(8, 100, 100), session={"note": "x"}))
    assert written == out
    coords = reference_coords(d, 1.0)
    refs = [ndi.map_coordinates(a, coords, order=1, mode="constant", cval=0) for a in arrays]
    if suffix == ".tif":
        with tifffile.TiffFile(out) as tif:
            assert tif.is_imagej and tif.series[0].axes == "ZCYX"
            data = tif.series[0].asarray()
            assert tif.imagej_metadata["Labels"][:2] == ["dapi", "gfp"]
        for k in range(2):
            np.testing.assert_allclose(data[:, k].astype(float), refs[k], atol=1)
    else:
        import ome_zarr.io
        import ome_zarr.reader

        node = next(iter(ome_zarr.reader.Reader(ome_zarr.io.parse_url(str(out)))()))
        axes = [a["name"] for a in node.metadata["axes"]]
        assert axes == ["c", "z", "y", "x"]
        data = np.asarray(node.data[0])
        assert node.metadata["channel_names"] == ["dapi", "gfp"]
        for k in range(2):
            np.testing.assert_allclose(data[k].astype(float), refs[k], atol=1)
        attrs = json.loads(json.dumps(dict(zarr.open_group(str(out), mode="r").attrs)))
        rec = attrs["unwind"]["straightening"]
        assert rec["channels"] == ["dapi", "gfp"] and rec["session"] == {"note": "x"}
        # and our own reader gives the channels back, with the straight geometry
        back = open_channels(out)
        assert [b.metadata["channel"] for b in back] == ["dapi", "gfp"]
        np.testing.assert_array_equal(np.asarray(back[1].data), data[1])


def test_a_single_channel_format_is_refused_with_the_formats_that_hold_channels(tmp_path):
    arrays = _channels((20, 20, 20), 2)
    vols = [as_volume(a) for a in arrays]
    with pytest.raises(InvalidInputError, match=r"OME-Zarr \(\.zarr\) or an ImageJ hyperstack"):
        run(write_channels_iter(vols, tmp_path / "x.nrrd"))
    assert not (tmp_path / "x.nrrd").exists()


@pytest.mark.parametrize("ngff", ["0.4", "0.5"])
def test_channels_written_by_ome_zarr_py_open_with_their_names(tmp_path, ngff):
    """ome-zarr-py (the OME's own writer, not ours) writes a czyx pyramid, NGFF 0.4 on zarr v2 or 0.5 on v3."""
    from ome_zarr.format import FormatV04, FormatV05
    from ome_zarr.io import parse_url
    from ome_zarr.writer import add_metadata, write_image

    data = np.stack(_channels((16, 20, 24), 2))
    fmt = FormatV04() if ngff == "0.4" else FormatV05()
    root = zarr.group(store=parse_url(str(tmp_path / "c.zarr"), mode="w", fmt=fmt).store,
                      zarr_format=2 if ngff == "0.4" else 3)
    write_image(image=data, group=root, axes="czyx", fmt=fmt, storage_options={"chunks": (1, 8, 10, 12)})
    add_metadata(root, {"omero": {"channels": [{"label": "dapi"}, {"label": "gfp"}]}}, fmt=fmt)
    chans = open_channels(tmp_path / "c.zarr")
    assert [c.metadata["channel"] for c in chans] == ["dapi", "gfp"]
    for c, a in zip(chans, data, strict=True):
        np.testing.assert_array_equal(np.asarray(c.data), a)
        assert len(c.levels) > 1  # the pyramid is kept


@pytest.mark.parametrize("axes,compression", [("CZYX", None), ("ZCYX", "zlib")])
def test_an_ome_tiff_with_channels_opens_with_names_and_voxel_size(tmp_path, axes, compression):
    """tifffile's OME-TIFF writer (channel names and physical sizes in the OME-XML), either plane order."""
    data = np.stack(_channels((10, 20, 24), 3))
    stored = data if axes == "CZYX" else data.transpose(1, 0, 2, 3)
    tifffile.imwrite(tmp_path / "c.ome.tif", stored, ome=True, compression=compression,
                     metadata={"axes": axes, "Channel": {"Name": ["a", "b", "c"]}, "PhysicalSizeX": 0.5,
                               "PhysicalSizeY": 0.5, "PhysicalSizeZ": 2.0})
    chans = open_channels(tmp_path / "c.ome.tif")
    assert [c.metadata["channel"] for c in chans] == ["a", "b", "c"]
    assert chans[0].spacing == (2.0, 0.5, 0.5) and chans[0].unit == "micrometer"
    for c, a in zip(chans, data, strict=True):
        np.testing.assert_array_equal(np.asarray(c.data), a)
