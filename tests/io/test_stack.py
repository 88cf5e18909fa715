"""Folders of numbered 2D slices: napari_unwind.io.stack."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import tifffile
from PIL import Image

from napari_unwind.errors import InvalidInputError, OutputError, SeriesSelectionError
from napari_unwind.io import detect_format, open_volume, write_volume
from napari_unwind.io import stack as stackmod
from napari_unwind.io._volume import Volume
from napari_unwind.io.stack import natural_key, numbered_siblings, read_stack, split_stack_target, write_stack
from napari_unwind.progress import run


def _data(dtype="uint8", shape=(5, 6, 7), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if np.issubdtype(np.dtype(dtype), np.integer):
        info = np.iinfo(dtype)
        return rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=dtype)
    return (rng.standard_normal(shape) * 100).astype(dtype)


def _save_pil(folder, names, data) -> None:
    folder.mkdir(exist_ok=True)
    for name, plane in zip(names, data, strict=True):
        Image.fromarray(plane).save(folder / name)


# ---------------------------------------------------------------------------------------------------- ordering
def test_natural_key():
    names = ["fish_10.png", "fish_2.png", "fish_1.png", "Fish_3.png"]
    assert sorted(names, key=natural_key) == ["fish_1.png", "fish_2.png", "Fish_3.png", "fish_10.png"]


@pytest.mark.parametrize("padded", [False, True])
def test_slices_are_sorted_by_number(tmp_path, padded):
    n = 12
    data = np.stack([np.full((4, 5), i, np.uint8) for i in range(n)])  # plane i holds the value i
    names = [f"fish_{i:04d}.png" if padded else f"fish_{i}.png" for i in range(n)]
    rng = np.random.default_rng(1)
    order = rng.permutation(n)  # creation order must not matter
    _save_pil(tmp_path / "s", [names[i] for i in order], data[order])
    vol = open_volume(tmp_path / "s")
    assert vol.format == "stack"
    np.testing.assert_array_equal(vol.data.compute()[:, 0, 0], np.arange(n))
    assert [p.rsplit("/", 1)[-1] for p in vol.metadata["files"]] == names


def test_one_slice_opens_its_siblings(tmp_path):
    data = _data(shape=(11, 4, 5))
    _save_pil(tmp_path / "s", [f"scan2_{i + 1}.bmp" for i in range(11)], data)
    (tmp_path / "s" / "scan2_notes.txt").write_text("not an image")
    for name in ("scan2_1.bmp", "scan2_10.bmp"):
        vol = open_volume(tmp_path / "s" / name)
        np.testing.assert_array_equal(vol.data.compute(), data)
    assert len(numbered_siblings(tmp_path / "s" / "scan2_5.bmp")) == 11


def test_lazy_one_chunk_per_slice(tmp_path, monkeypatch):
    data = _data("uint16", shape=(6, 4, 5))
    _save_pil(tmp_path / "s", [f"z{i:03d}.png" for i in range(6)], data)
    decoded: list = []
    original = stackmod.read_slice

    def counting(path, *args, **kwargs):
        decoded.append(str(path))
        return original(path, *args, **kwargs)

    monkeypatch.setattr(stackmod, "read_slice", counting)
    vol = read_stack(tmp_path / "s")
    assert len(decoded) == 1, "opening should decode the first slice only (the colour check)"
    assert vol.data.chunks == ((1,) * 6, (4,), (5,))
    decoded.clear()
    np.testing.assert_array_equal(vol.data[4].compute(), data[4])
    assert [p.rsplit("/", 1)[-1] for p in decoded] == ["z004.png"]


def test_gap_in_numbers_warns(tmp_path):
    data = _data(shape=(3, 4, 5))
    _save_pil(tmp_path / "s", ["a_1.png", "a_2.png", "a_5.png"], data)
    with pytest.warns(UserWarning, match=r"2 slice number\(s\) missing.*3, 4"):
        vol = open_volume(tmp_path / "s")
    np.testing.assert_array_equal(vol.data.compute(), data)


def test_duplicate_numbers_are_refused(tmp_path):
    _save_pil(tmp_path / "s", ["a_1.png", "a_01.png", "a_2.png"], _data(shape=(3, 4, 5)))
    with pytest.raises(InvalidInputError, match="number 1 appears more than once"):
        open_volume(tmp_path / "s")


# ----------------------------------------------------------------------------------------------- several stacks
def test_largest_stack_is_chosen_with_a_warning(tmp_path):
    big, small = _data(shape=(5, 4, 5), seed=1), _data(shape=(2, 4, 5), seed=2)
    _save_pil(tmp_path / "s", [f"fish_{i}.png" for i in range(5)], big)
    _save_pil(tmp_path / "s", [f"preview_{i}.png" for i in range(2)], small)
    with pytest.warns(UserWarning, match=r"ignoring 2 other image.*preview_\*\.png"):
        vol = open_volume(tmp_path / "s")
    np.testing.assert_array_equal(vol.data.compute(), big)
    vol = read_stack(tmp_path / "s", pattern="preview_*.png")
    np.testing.assert_array_equal(vol.data.compute(), small)


def test_equal_stacks_need_a_pattern(tmp_path):
    a, b = _data(shape=(3, 4, 5), seed=1), _data(shape=(3, 4, 5), seed=2)
    _save_pil(tmp_path / "s", [f"left_{i}.png" for i in range(3)], a)
    _save_pil(tmp_path / "s", [f"right_{i}.png" for i in range(3)], b)
    with pytest.raises(SeriesSelectionError, match="pattern=") as err:
        open_volume(tmp_path / "s")
    assert set(err.value.series) == {"left_*.png", "right_*.png"}
    vol = open_volume(tmp_path / "s", pattern="right_{:d}.png")  # a write pattern works as a glob
    np.testing.assert_array_equal(vol.data.compute(), b)


# ------------------------------------------------------------------------------------------------------ bad input
def test_slice_of_another_size_is_named(tmp_path):
    data = _data(shape=(4, 6, 7))
    _save_pil(tmp_path / "s", [f"f_{i}.png" for i in range(4)], data)
    Image.fromarray(_data(shape=(6, 8))).save(tmp_path / "s" / "f_2.png")  # 8 x 6 instead of 7 x 6
    with pytest.raises(InvalidInputError) as err:
        open_volume(tmp_path / "s")
    msg = str(err.value)
    assert "f_2.png" in msg and "8 x 6" in msg and "7 x 6" in msg
    assert "(6, 7)" in msg and "(6, 8)" in msg


def test_slice_of_another_type_is_refused(tmp_path):
    data = _data(shape=(3, 6, 7))
    _save_pil(tmp_path / "s", [f"f_{i}.png" for i in range(3)], data)
    Image.fromarray(data[1].astype(np.uint16) * 200).save(tmp_path / "s" / "f_1.png")
    with pytest.raises(InvalidInputError, match="f_1.png holds uint16"):
        open_volume(tmp_path / "s")


def test_colour_slices_are_refused(tmp_path):
    rgb = _data(shape=(3, 6, 7, 3))
    _save_pil(tmp_path / "s", [f"c_{i}.png" for i in range(3)], rgb)
    with pytest.raises(InvalidInputError, match="c_0.png is a colour image.*grey"):
        open_volume(tmp_path / "s")


def test_grey_rgb_slices_are_grey(tmp_path):
    grey = _data(shape=(3, 6, 7))
    _save_pil(tmp_path / "s", [f"g_{i}.png" for i in range(3)], np.repeat(grey[..., None], 3, axis=-1))
    vol = open_volume(tmp_path / "s")
    assert vol.dtype == np.uint8 and vol.shape == grey.shape
    np.testing.assert_array_equal(vol.data.compute(), grey)


def test_colour_slice_later_in_the_stack_fails_on_read(tmp_path):
    grey = _data(shape=(3, 6, 7))
    rgb = np.repeat(grey[..., None], 3, axis=-1)
    rgb[2, 0, 0] = (1, 2, 3)
    _save_pil(tmp_path / "s", [f"g_{i}.png" for i in range(3)], rgb)
    vol = open_volume(tmp_path / "s")
    np.testing.assert_array_equal(vol.data[:2].compute(), grey[:2])
    with pytest.raises(InvalidInputError, match="g_2.png is a colour image"):
        vol.data.compute()


def test_grey_palette_and_binary_slices(tmp_path):
    grey = _data(shape=(3, 6, 7))
    _save_pil(tmp_path / "p", [f"p_{i}.png" for i in range(3)], grey)
    for i in range(3):  # re-save as palette images with a grey palette
        im = Image.fromarray(grey[i]).convert("P", palette=Image.Palette.ADAPTIVE, colors=256)
        im.save(tmp_path / "p" / f"p_{i}.png")
    expected = np.stack([np.asarray(Image.open(tmp_path / "p" / f"p_{i}.png").convert("L")) for i in range(3)])
    np.testing.assert_array_equal(open_volume(tmp_path / "p").data.compute(), expected)
    mask = grey > 128
    _save_pil(tmp_path / "m", [f"m_{i}.png" for i in range(3)], mask)
    vol = open_volume(tmp_path / "m")
    assert vol.dtype == np.uint8
    np.testing.assert_array_equal(vol.data.compute(), mask.astype(np.uint8))


def test_single_image_is_refused(tmp_path):
    Image.fromarray(_data(shape=(4, 5))).save(tmp_path / "photo.png")
    with pytest.raises(InvalidInputError, match="single 2D image.*needs 3D"):
        open_volume(tmp_path / "photo.png")
    (tmp_path / "only").mkdir()
    Image.fromarray(_data(shape=(4, 5))).save(tmp_path / "only" / "picture.png")
    with pytest.raises(InvalidInputError, match="no numbered image slices"):
        open_volume(tmp_path / "only")


def test_no_match_for_pattern(tmp_path):
    _save_pil(tmp_path / "s", [f"f_{i}.png" for i in range(2)], _data(shape=(2, 4, 5)))
    with pytest.raises(InvalidInputError, match="matches the pattern"):
        read_stack(tmp_path / "s", pattern="g_*.png")


# ---------------------------------------------------------------------------------------------------- geometry
def test_imagej_tiff_slices_give_pixel_size(tmp_path):
    data = _data("uint16", shape=(3, 4, 5))
    (tmp_path / "s").mkdir()
    for i, plane in enumerate(data):
        tifffile.imwrite(tmp_path / "s" / f"ij_{i}.tif", plane, imagej=True, resolution=(1 / 0.2, 1 / 0.4),
                         metadata={"unit": "micron"})
    with pytest.warns(UserWarning, match="assuming cubic voxels"):
        vol = open_volume(tmp_path / "s")
    assert vol.unit == "micrometer"
    assert vol.spacing == pytest.approx((0.2, 0.4, 0.2))
    np.testing.assert_array_equal(vol.data.compute(), data)


def test_bmp_stack_has_no_geometry(tmp_path):
    _save_pil(tmp_path / "s", [f"b_{i}.bmp" for i in range(3)], _data(shape=(3, 4, 5)))
    vol = open_volume(tmp_path / "s")
    assert vol.spacing == (1.0, 1.0, 1.0) and vol.unit is None


# ------------------------------------------------------------------------------------------------------- writing
@pytest.mark.parametrize(
    ("suffix", "dtype", "keeps_geometry"),
    [("png", "uint8", True), ("png", "uint16", True), ("tif", "uint16", True), ("tif", "int16", True),
     ("tif", "float32", True), ("bmp", "uint8", False)],
)
def test_round_trip_through_write_volume(tmp_path, suffix, dtype, keeps_geometry):
    data = _data(dtype, shape=(4, 6, 7))
    target = tmp_path / "out" / f"fish_{{:04d}}.{suffix}"
    written = write_volume(data, target, spacing=(2.0, 0.5, 0.25), unit="um")  # '{}' + image suffix: a stack
    assert written == tmp_path / "out"
    assert detect_format(written) == "stack"
    names = sorted(p.name for p in written.iterdir())
    assert names == [f"fish_{i:04d}.{suffix}" for i in range(4)]
    # an independent reader of each slice
    for i, name in enumerate(names):
        plane = tifffile.imread(written / name) if suffix == "tif" else np.asarray(Image.open(written / name))
        np.testing.assert_array_equal(plane, data[i])
    vol = open_volume(written)
    assert vol.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(vol.data.compute(), data)
    if keeps_geometry:
        assert vol.spacing == (2.0, 0.5, 0.25) and vol.unit == "micrometer"
    else:
        assert vol.spacing == (1.0, 1.0, 1.0) and vol.unit is None
    assert not [p for p in tmp_path.rglob("*") if p.name.startswith(".")]


def test_png_pattern_detected_from_the_name(tmp_path):
    data = _data("uint8", shape=(3, 4, 5))
    written = write_volume(data, tmp_path / "out" / "z{}.png")  # no format=: chosen from '{}' + .png
    assert sorted(p.name for p in written.iterdir()) == ["z0.png", "z1.png", "z2.png"]


def test_tiff_slices_open_in_fiji_with_calibration(tmp_path):
    data = _data("uint8", shape=(3, 4, 5))
    list(write_stack(Volume(data, spacing=(3.0, 0.5, 0.25), unit="mm"), tmp_path / "s", pattern="s_{:02d}.tif"))
    with tifffile.TiffFile(tmp_path / "s" / "s_01.tif") as tif:
        assert tif.is_imagej and tif.imagej_metadata["unit"] == "mm"
        assert tif.imagej_metadata["spacing"] == pytest.approx(3.0)
        x = tif.pages.first.tags["XResolution"].value
        assert x[1] / x[0] == pytest.approx(0.25)


def test_write_stack_directly(tmp_path):
    data = _data("uint16", shape=(5, 4, 5))
    records = []
    run(write_stack(Volume(data, spacing=(1.0, 2.0, 3.0), unit="nm"), tmp_path / "d", start=1), records.append)
    assert records[-1].done == records[-1].total
    assert sorted(p.name for p in (tmp_path / "d").iterdir()) == [f"slice_{i:05d}.png" for i in range(1, 6)]
    vol = read_stack(tmp_path / "d")
    np.testing.assert_array_equal(vol.data.compute(), data)
    assert vol.spacing == (1.0, 2.0, 3.0) and vol.unit == "nanometer"
    with pytest.raises(OutputError, match="already exists"):
        list(write_stack(Volume(data), tmp_path / "d"))


@pytest.mark.parametrize(
    ("suffix", "dtype", "match"),
    [("bmp", "uint16", r"\.bmp slices hold uint8, not uint16.*\.png"), ("jpg", "int16", r"uint8.*\.png"),
     ("png", "float32", r"uint8 or uint16, not float32.*\.tif")],
)
def test_unsupported_type_names_the_alternative(tmp_path, suffix, dtype, match):
    with pytest.raises(InvalidInputError, match=match):
        list(write_stack(Volume(_data(dtype, shape=(2, 3, 4))), tmp_path / "x", pattern=f"a_{{}}.{suffix}"))
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("pattern", ["fish.png", "fish_{}_{}.png", "fish_{name}.png", "fish_{:04d}.txt",
                                     "sub/fish_{}.png"])
def test_bad_patterns(tmp_path, pattern):
    why = "needs exactly one {} field|must end with an image suffix|one plain file name per slice"
    with pytest.raises(InvalidInputError, match=why):
        list(write_stack(Volume(_data(shape=(2, 3, 4))), tmp_path / "x", pattern=pattern))


def test_jpeg_warns_it_is_lossy(tmp_path):
    with pytest.warns(UserWarning, match="lossy"):
        list(write_stack(Volume(_data(shape=(2, 3, 4))), tmp_path / "j", pattern="j_{}.jpg"))
    assert open_volume(tmp_path / "j").shape == (2, 3, 4)


def test_split_stack_target(tmp_path):
    folder, pattern = split_stack_target(tmp_path / "slices" / "fish_{:04d}.png")
    assert folder == tmp_path / "slices" and pattern == "fish_{:04d}.png"
    (tmp_path / "slices").mkdir()
    (tmp_path / "slices" / "fish_0000.png").write_bytes(b"")
    assert split_stack_target(tmp_path / "slices" / "fish_{:04d}.png")[0] == tmp_path / "slices"
    (tmp_path / "slices" / "notes.txt").write_text("keep me")
    with pytest.raises(OutputError, match="holds other files"):
        split_stack_target(tmp_path / "slices" / "fish_{:04d}.png")
    with pytest.raises(InvalidInputError, match="folder of their own"):
        split_stack_target("fish_{:04d}.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InvalidInputError, match="needs exactly one {} field"):
            split_stack_target(tmp_path / "x" / "fish.png")


def test_folder_holding_one_multipage_tiff(tmp_path):
    data = _data("uint16", shape=(4, 5, 6))
    (tmp_path / "one").mkdir()
    tifffile.imwrite(tmp_path / "one" / "scan.tif", data, photometric="minisblack")
    vol = open_volume(tmp_path / "one")
    assert vol.format == "tiff"
    np.testing.assert_array_equal(vol.data.compute(), data)
    (tmp_path / "num").mkdir()
    tifffile.imwrite(tmp_path / "num" / "scan_001.tif", data, photometric="minisblack")
    tifffile.imwrite(tmp_path / "num" / "scan_002.tif", data, photometric="minisblack")
    with pytest.raises(InvalidInputError, match="multi-page TIFF, not a 2D slice"):
        open_volume(tmp_path / "num")


def test_stack_output_never_replaces_a_folder_holding_other_files(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "notes.txt").write_text("keep me")
    with pytest.raises(OutputError, match="holds other files"):
        write_volume(_data("uint8", shape=(3, 4, 5)), tmp_path / "out" / "z{}.png", overwrite=True)
    assert (tmp_path / "out" / "notes.txt").read_text() == "keep me"
