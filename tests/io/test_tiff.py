"""Multi-page TIFF / BigTIFF / ImageJ / OME-TIFF: napari_unwind.io.tiff."""

from __future__ import annotations

import warnings
from fractions import Fraction

import dask.array as da
import numpy as np
import pytest
import tifffile

from napari_unwind.errors import InvalidInputError
from napari_unwind.io import open_volume, write_volume
from napari_unwind.io import tiff as tiffmod
from napari_unwind.io._volume import Volume
from napari_unwind.io.tiff import read_tiff, write_tiff
from napari_unwind.progress import run

DTYPES = ["uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64"]
SPACING = (2.5, 0.3, 0.125)  # axis0, axis1, axis2: 0.3 has no exact binary fraction


def _data(dtype: str, shape=(6, 5, 7), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if np.issubdtype(np.dtype(dtype), np.integer):
        info = np.iinfo(dtype)
        return rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=dtype)
    return (rng.standard_normal(shape) * 1000).astype(dtype)


def _resolution(page) -> tuple[float, float]:
    """(x, y) resolution from the raw rational tags, independent of our code."""
    return tuple(float(Fraction(*page.tags[n].value)) for n in ("XResolution", "YResolution"))


# ----------------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("compression", [None, "zlib"])
def test_round_trip_keeps_type_and_geometry(tmp_path, dtype, compression):
    data = _data(dtype)
    path = write_volume(data, tmp_path / "v.tif", spacing=SPACING, unit="um", origin=(1.0, -2.0, 0.5),
                        compression=compression)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    vol = open_volume(path)
    assert vol.format == "tiff"
    assert vol.dtype == np.dtype(dtype)
    assert vol.shape == data.shape
    assert vol.spacing == SPACING
    assert vol.unit == "micrometer"
    assert vol.origin == (1.0, -2.0, 0.5)
    np.testing.assert_array_equal(vol.data.compute(), data)
    # an independent reader sees the same voxels
    np.testing.assert_array_equal(tifffile.imread(path), data)
    with tifffile.TiffFile(path) as tif:
        assert tif.is_imagej == (dtype in ("uint8", "uint16", "float32"))
        assert tif.pages.first.compression == (1 if compression is None else 8)


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "float32"])
@pytest.mark.parametrize(("unit", "ij_unit"), [("um", "micron"), ("mm", "mm"), ("nm", "nm")])
def test_fiji_reads_the_calibration(tmp_path, dtype, unit, ij_unit):
    data = _data(dtype, shape=(4, 6, 8))
    path = write_volume(data, tmp_path / "fiji.tif", spacing=SPACING, unit=unit)
    with tifffile.TiffFile(path) as tif:
        assert tif.is_imagej
        ij = tif.imagej_metadata
        assert ij["images"] == 4 and ij["slices"] == 4 and ij.get("channels", 1) == 1
        assert ij["hyperstack"] is True
        assert ij["unit"] == ij_unit
        assert ij["spacing"] == pytest.approx(SPACING[0])
        xres, yres = _resolution(tif.pages.first)
        assert 1 / xres == pytest.approx(SPACING[2], rel=1e-9)
        assert 1 / yres == pytest.approx(SPACING[1], rel=1e-9)
        assert len(tif.pages) == 4
        assert tif.series[0].shape == (4, 6, 8) and tif.series[0].axes == "ZYX"
        assert tif.pages.first.dtype == np.dtype(dtype)


def test_other_types_store_resolution_and_json(tmp_path):
    data = _data("int16", shape=(3, 4, 5))
    path = write_volume(data, tmp_path / "i16.tif", spacing=(0.2, 0.02, 0.01), unit="mm")
    with tifffile.TiffFile(path) as tif:
        assert not tif.is_imagej
        page = tif.pages.first
        assert page.resolutionunit == tifffile.RESUNIT.CENTIMETER
        xres, yres = _resolution(page)  # pixels per cm
        assert 10 / xres == pytest.approx(0.01) and 10 / yres == pytest.approx(0.02)
        meta = tif.shaped_metadata[0]["unwind"]
        assert meta["spacing"] == [0.2, 0.02, 0.01] and meta["unit"] == "millimeter"


def test_direct_functions_stream_with_progress(tmp_path, monkeypatch):
    monkeypatch.setattr(tiffmod, "slab_depth", lambda *a, **k: 3)
    data = _data("uint16", shape=(10, 4, 5))
    records = []
    run(write_tiff(Volume(da.from_array(data, chunks=(2, 4, 5)), spacing=SPACING, unit="mm"),
                   tmp_path / "d.tif"), records.append)
    assert [r.done for r in records] == [1, 2, 3, 4] and records[-1].total == 4
    vol = read_tiff(tmp_path / "d.tif")
    np.testing.assert_array_equal(vol.data.compute(), data)
    assert vol.spacing == SPACING and vol.unit == "millimeter"


# --------------------------------------------------------------------------------------- files from other programs
@pytest.mark.parametrize("unit", ["micron", "\\u00B5m", "um"])
def test_reads_imagej_calibration(tmp_path, unit):
    data = _data("uint16", shape=(5, 6, 7))
    tifffile.imwrite(tmp_path / "ij.tif", data, imagej=True, resolution=(1 / 0.25, 1 / 0.5),
                     metadata={"spacing": 3.0, "unit": unit, "axes": "ZYX"})
    vol = open_volume(tmp_path / "ij.tif")
    assert vol.unit == "micrometer"
    assert vol.spacing == pytest.approx((3.0, 0.5, 0.25))
    assert vol.metadata["geometry_from"] == "imagej"
    np.testing.assert_array_equal(vol.data.compute(), data)


def test_reads_imagej_inches_as_millimetres(tmp_path):
    data = _data("uint8", shape=(3, 4, 5))
    tifffile.imwrite(tmp_path / "in.tif", data, imagej=True, resolution=(100.0, 100.0),
                     metadata={"spacing": 0.01, "unit": "inch", "axes": "ZYX"})
    vol = open_volume(tmp_path / "in.tif")
    assert vol.unit == "millimeter"
    assert vol.spacing == pytest.approx((0.254, 0.254, 0.254))


def test_imagej_geometry_wins_when_tags_were_changed(tmp_path):
    """A stored exact geometry that disagrees with the resolution tags is stale: the tags win."""
    data = _data("uint8", shape=(3, 4, 5))
    tifffile.imwrite(tmp_path / "stale.tif", data, imagej=True, resolution=(1 / 0.5, 1 / 0.5),
                     metadata={"spacing": 2.0, "unit": "mm", "axes": "ZYX",
                               "unwind": '{"spacing": [9.0, 9.0, 9.0], "unit": "millimeter"}'})
    vol = open_volume(tmp_path / "stale.tif")
    assert vol.spacing == pytest.approx((2.0, 0.5, 0.5))


def test_reads_ome_tiff(tmp_path):
    data = _data("uint16", shape=(4, 5, 6))
    tifffile.imwrite(tmp_path / "o.ome.tif", data, ome=True, photometric="minisblack",
                     metadata={"axes": "ZYX", "PhysicalSizeX": 0.5, "PhysicalSizeXUnit": "µm",
                               "PhysicalSizeY": 0.75, "PhysicalSizeYUnit": "µm",
                               "PhysicalSizeZ": 0.002, "PhysicalSizeZUnit": "mm"})
    vol = open_volume(tmp_path / "o.ome.tif")
    assert vol.unit == "micrometer"
    assert vol.spacing == pytest.approx((2.0, 0.75, 0.5))
    np.testing.assert_array_equal(vol.data.compute(), data)


def test_reads_plain_tiff_with_centimetre_resolution(tmp_path):
    data = _data("uint8", shape=(3, 4, 5))
    tifffile.imwrite(tmp_path / "cm.tif", data, photometric="minisblack", resolution=(1000.0, 500.0),
                     resolutionunit="CENTIMETER")
    vol = open_volume(tmp_path / "cm.tif")
    assert vol.unit == "millimeter"
    assert vol.spacing == pytest.approx((1.0, 0.02, 0.01))


def test_plain_tiff_with_dpi_has_no_unit(tmp_path):
    data = _data("uint8", shape=(3, 4, 5))
    tifffile.imwrite(tmp_path / "dpi.tif", data, photometric="minisblack", resolution=(72.0, 72.0),
                     resolutionunit="INCH")
    vol = open_volume(tmp_path / "dpi.tif")
    assert vol.unit is None and vol.spacing == (1.0, 1.0, 1.0)


def test_big_endian_and_tiled_files(tmp_path):
    data = _data("int16", shape=(3, 32, 48))
    tifffile.imwrite(tmp_path / "be.tif", data, byteorder=">", photometric="minisblack")
    tifffile.imwrite(tmp_path / "tiled.tif", data, tile=(16, 16), photometric="minisblack")
    for name in ("be.tif", "tiled.tif"):
        vol = open_volume(tmp_path / name)
        assert vol.dtype == np.dtype("int16") and vol.dtype.isnative
        np.testing.assert_array_equal(vol.data.compute(), data)
        np.testing.assert_array_equal(vol.data[1, 5:20, 7].compute(), data[1, 5:20, 7])


def test_length_one_channel_axis_is_dropped(tmp_path):
    data = _data("uint8", shape=(4, 1, 5, 6))
    tifffile.imwrite(tmp_path / "c1.tif", data, imagej=True, metadata={"axes": "ZCYX"})
    vol = open_volume(tmp_path / "c1.tif")
    assert vol.shape == (4, 5, 6)
    np.testing.assert_array_equal(vol.data.compute(), data[:, 0])


# ------------------------------------------------------------------------------------------------------- laziness
def test_opening_reads_no_voxels(tmp_path, monkeypatch):
    data = _data("uint16", shape=(12, 8, 9))
    write_volume(data, tmp_path / "plain.tif", spacing=SPACING)
    write_volume(data, tmp_path / "zip.tif", spacing=SPACING, compression="zlib")
    calls = {"memmap": 0, "pages": 0}
    raw_get = tiffmod.RawFileArray.__getitem__
    pages_get = tiffmod._TiffPlanes.__getitem__

    def raw_count(self, key):
        calls["memmap"] += 1
        return raw_get(self, key)

    def pages_count(self, key):
        calls["pages"] += 1
        return pages_get(self, key)

    monkeypatch.setattr(tiffmod.RawFileArray, "__getitem__", raw_count)
    monkeypatch.setattr(tiffmod._TiffPlanes, "__getitem__", pages_count)
    a = read_tiff(tmp_path / "plain.tif", chunk_planes=4)
    b = read_tiff(tmp_path / "zip.tif", chunk_planes=4)
    assert calls == {"memmap": 0, "pages": 0}
    assert a.metadata["memmap"] and not b.metadata["memmap"]
    assert a.data.chunks[0] == b.data.chunks[0] == (4, 4, 4)
    assert a.data[5, 2, 3].compute() == b.data[5, 2, 3].compute() == data[5, 2, 3]
    assert calls == {"memmap": 1, "pages": 1}


# ---------------------------------------------------------------------------------------------------- bad inputs
def test_2d_tiff_alone_is_refused(tmp_path):
    tifffile.imwrite(tmp_path / "photo.tif", _data("uint8", shape=(5, 6)))
    with pytest.raises(InvalidInputError, match="single 2D image.*needs 3D"):
        open_volume(tmp_path / "photo.tif")


def test_2d_tiff_slice_opens_its_stack(tmp_path):
    data = _data("uint16", shape=(12, 5, 6))
    for i, plane in enumerate(data, start=1):
        tifffile.imwrite(tmp_path / f"fish_{i}.tif", plane)  # not zero padded: fish_10 after fish_9
    vol = open_volume(tmp_path / "fish_7.tif")
    assert vol.format == "stack" and vol.shape == data.shape
    np.testing.assert_array_equal(vol.data.compute(), data)


def test_rgb_volume_is_refused(tmp_path):
    tifffile.imwrite(tmp_path / "rgb.tif", _data("uint8", shape=(3, 5, 6, 3)), photometric="rgb")
    with pytest.raises(InvalidInputError, match="RGB.*convert it to grey"):
        open_volume(tmp_path / "rgb.tif")


def test_a_multichannel_volume_is_one_volume_only_with_a_channel_picked(tmp_path):
    data = _data("uint8", shape=(4, 2, 5, 6))
    tifffile.imwrite(tmp_path / "c2.tif", data, imagej=True, metadata={"axes": "ZCYX"})
    with pytest.raises(InvalidInputError, match="2 channels.*--input-channel"):
        open_volume(tmp_path / "c2.tif")
    np.testing.assert_array_equal(np.asarray(open_volume(tmp_path / "c2.tif", channel=1).data), data[:, 1])
    with pytest.raises(InvalidInputError, match="channels 0..1, got channel=2"):
        open_volume(tmp_path / "c2.tif", channel=2)


def test_time_series_is_refused(tmp_path):
    tifffile.imwrite(tmp_path / "t.tif", _data("uint8", shape=(2, 3, 5, 6)), imagej=True,
                     metadata={"axes": "TZYX"})
    with pytest.raises(InvalidInputError, match="4D"):
        open_volume(tmp_path / "t.tif")


def test_not_a_tiff(tmp_path):
    (tmp_path / "junk.tif").write_bytes(b"this is not a tiff at all")
    with pytest.raises(InvalidInputError, match="not a readable TIFF"):
        open_volume(tmp_path / "junk.tif")


# ------------------------------------------------------------------------------------------------ writer options
def test_bigtiff_when_large_warns_and_keeps_geometry(tmp_path, monkeypatch):
    monkeypatch.setattr(tiffmod, "BIGTIFF_THRESHOLD", 100)  # stand-in for 4 GB
    data = _data("uint16", shape=(3, 5, 6))
    with pytest.warns(UserWarning, match="BigTIFF"):
        path = write_volume(data, tmp_path / "huge.tif", spacing=SPACING, unit="um")
    with tifffile.TiffFile(path) as tif:
        assert tif.is_bigtiff and not tif.is_imagej
        xres, _ = _resolution(tif.pages.first)
        assert 1e4 / xres == pytest.approx(SPACING[2])  # pixels per cm, spacing in um
    vol = open_volume(path)
    assert vol.spacing == SPACING and vol.unit == "micrometer" and vol.dtype == np.uint16
    np.testing.assert_array_equal(vol.data.compute(), data)
    with pytest.raises(InvalidInputError, match="need BigTIFF"):
        write_volume(data, tmp_path / "no.tif", bigtiff=False)


def test_forced_bigtiff_and_plain(tmp_path):
    data = _data("uint8", shape=(3, 5, 6))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_volume(data, tmp_path / "b.tif", bigtiff=True, spacing=SPACING)
        write_volume(data, tmp_path / "p.tif", imagej=False, spacing=SPACING)
    for name, big in (("b.tif", True), ("p.tif", False)):
        with tifffile.TiffFile(tmp_path / name) as tif:
            assert tif.is_bigtiff == big and not tif.is_imagej
        assert open_volume(tmp_path / name).spacing == SPACING
    with pytest.raises(InvalidInputError, match="ImageJ hyperstacks hold uint8, uint16 or float32"):
        write_volume(data.astype(np.int16), tmp_path / "x.tif", imagej=True)


def test_bad_compression(tmp_path):
    with pytest.raises(InvalidInputError, match="unknown TIFF compression"):
        write_volume(_data("uint8"), tmp_path / "c.tif", compression="lzw2")
    assert not list(tmp_path.iterdir())


def test_zstd(tmp_path):
    data = _data("uint16")
    if not tiffmod._zstd_available():
        with pytest.raises(InvalidInputError, match="imagecodecs"):
            write_volume(data, tmp_path / "z.tif", compression="zstd")
        pytest.skip("zstd needs imagecodecs (or Python >= 3.14)")
    path = write_volume(data, tmp_path / "z.tif", compression="zstd")
    np.testing.assert_array_equal(open_volume(path).data.compute(), data)


def test_writer_error_leaves_nothing(tmp_path):
    def boom(block):
        raise RuntimeError("bad chunk")

    data = da.from_array(_data("uint8", shape=(8, 4, 4)), chunks=(2, 4, 4)).map_blocks(boom, dtype=np.uint8)
    with pytest.raises(RuntimeError, match="bad chunk"):
        write_volume(data, tmp_path / "e.tif")
    assert list(tmp_path.iterdir()) == []


def test_slice_pattern_name_is_not_a_tiff(tmp_path):
    with pytest.raises(InvalidInputError, match="format='stack'"):
        list(write_tiff(Volume(_data("uint8")), tmp_path / "fish_{:04d}.tif"))


def test_closing_the_writer_stops_its_thread(tmp_path, monkeypatch):
    import threading

    monkeypatch.setattr(tiffmod, "slab_depth", lambda *a, **k: 1)
    before = {t.name for t in threading.enumerate()}
    gen = write_tiff(Volume(_data("uint8", shape=(5, 4, 4))), tmp_path / "c.tif")
    assert next(gen).done == 1
    gen.close()  # e.g. the user cancels: the worker must not hang on its queue
    assert {t.name for t in threading.enumerate()} == before


def test_compression_level(tmp_path):
    data = np.zeros((4, 64, 64), np.uint16)
    data[:, ::3] = 1000
    fast = write_volume(data, tmp_path / "l1.tif", compression="zlib", compression_level=1)
    best = write_volume(data, tmp_path / "l9.tif", compression="zlib", compression_level=9)
    np.testing.assert_array_equal(tifffile.imread(fast), data)
    np.testing.assert_array_equal(tifffile.imread(best), data)
    assert best.stat().st_size <= fast.stat().st_size < data.nbytes


def test_2d_colour_tiff_alone_is_refused(tmp_path):
    tifffile.imwrite(tmp_path / "rgb2d.tif", _data("uint8", shape=(5, 6, 3)), photometric="rgb")
    with pytest.raises(InvalidInputError, match="single 2D image of 3 samples per pixel"):
        open_volume(tmp_path / "rgb2d.tif")
