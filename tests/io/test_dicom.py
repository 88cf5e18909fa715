"""DICOM series reading and writing, checked with pydicom's own reader and checks."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import dask.array as da
import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset, FileMetaDataset, validate_file_meta
from pydicom.uid import (
    CTImageStorage,
    ExplicitVRLittleEndian,
    RLELossless,
    SecondaryCaptureImageStorage,
    generate_uid,
)

from napari_unwind.errors import InvalidInputError, SeriesSelectionError
from napari_unwind.io import Volume, open_volume, write_volume
from napari_unwind.io.dicom import list_series, read_dicom, write_dicom
from napari_unwind.progress import run

SPACING = (2.5, 0.75, 0.5)  # axis0 (between slices), axis1 (rows), axis2 (columns): all different
ORIGIN = (-40.0, 12.5, 7.25)


@pytest.fixture
def vol() -> np.ndarray:
    return np.random.default_rng(6).integers(-1024, 3000, size=(5, 6, 7)).astype(np.int16)


# ------------------------------------------------------------------------------------------------------------------
# an independent writer of classic single-frame slices (pydicom only)
# ------------------------------------------------------------------------------------------------------------------
def make_slice(path: Path, pixels: np.ndarray, *, series_uid: str, position=None, orientation=(1, 0, 0, 0, 1, 0),
               pixel_spacing=(0.75, 0.5), instance: int | None = None, series_number: int | None = 1,
               description: str = "test", slope=None, intercept=None, bits_stored=None, spacing_between=None,
               signed=None) -> None:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = CTImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = CTImageStorage
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = "CT"
    ds.SeriesInstanceUID = series_uid
    ds.StudyInstanceUID = "1.2.3.4"
    if series_number is not None:
        ds.SeriesNumber = series_number
    ds.SeriesDescription = description
    if instance is not None:
        ds.InstanceNumber = instance
    if position is not None:
        ds.ImagePositionPatient = [float(v) for v in position]
        ds.ImageOrientationPatient = [float(v) for v in orientation]
    if pixel_spacing is not None:
        ds.PixelSpacing = [float(v) for v in pixel_spacing]
    if spacing_between is not None:
        ds.SpacingBetweenSlices = spacing_between
    if slope is not None:
        ds.RescaleSlope = slope
        ds.RescaleIntercept = intercept
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = pixels.shape
    ds.BitsAllocated = 8 * pixels.dtype.itemsize
    ds.BitsStored = bits_stored or ds.BitsAllocated
    ds.HighBit = ds.BitsStored - 1
    ds.PixelRepresentation = int(pixels.dtype.kind == "i" if signed is None else signed)
    ds.PixelData = pixels.astype(pixels.dtype.newbyteorder("<")).tobytes()
    ds.save_as(path, enforce_file_format=True)


def make_series(folder: Path, vol: np.ndarray, *, spacing=SPACING, origin=ORIGIN, names=None, **kw) -> str:
    """Write ``vol`` slice by slice along a tilted orientation, files in scrambled order; return the series UID."""
    folder.mkdir(exist_ok=True)
    uid = kw.pop("series_uid", generate_uid())
    n = vol.shape[0]
    perm = np.random.default_rng(7).permutation(n)
    for k in range(n):
        pos = np.array([origin[2], origin[1], origin[0] + k * spacing[0]])
        name = names[k] if names else f"f{perm[k]:03d}.dcm"
        make_slice(folder / name, vol[k], series_uid=uid, position=pos, pixel_spacing=spacing[1:],
                   instance=n - k, **kw)  # instance numbers run backwards: positions must win
    return uid


# ------------------------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------------------------
def test_read_sorts_by_position(tmp_path, vol):
    uid = make_series(tmp_path / "s", vol)
    v = open_volume(tmp_path / "s")
    assert v.format == "dicom" and v.unit == "millimeter"
    np.testing.assert_allclose(v.spacing, SPACING)
    np.testing.assert_allclose(v.origin, ORIGIN)
    np.testing.assert_array_equal(v.data.compute(), vol)
    assert v.dtype == np.int16
    assert v.metadata["series_uid"] == uid


def test_read_oblique_orientation(tmp_path, vol):
    # rows along (0, 1, 0), columns along (0, 0, -1): the normal is (-1, 0, 0)
    row, col = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, -1.0])
    normal = np.cross(row, col)
    uid = generate_uid()
    folder = tmp_path / "obl"
    folder.mkdir()
    corner = np.array([5.0, -3.0, 11.0])
    for k in np.random.default_rng(0).permutation(vol.shape[0]):
        make_slice(folder / f"{k}.dcm", vol[k], series_uid=uid, position=corner + 2.0 * k * normal,
                   orientation=(*row, *col), pixel_spacing=(0.75, 0.5))
    v = read_dicom(folder)
    np.testing.assert_array_equal(v.data.compute(), vol)
    np.testing.assert_allclose(v.spacing, (2.0, 0.75, 0.5))
    np.testing.assert_allclose(v.origin, (corner @ normal, corner @ col, corner @ row))


def test_one_chunk_per_slice_read_on_demand(tmp_path, vol):
    make_series(tmp_path / "s", vol, names=[f"IM{k}.dcm" for k in range(vol.shape[0])])
    v = read_dicom(tmp_path / "s")
    assert v.data.numblocks == (vol.shape[0], 1, 1)
    (tmp_path / "s" / "IM4.dcm").unlink()  # the last slice's pixels are never needed below
    np.testing.assert_array_equal(v.data[1:3, 2:4].compute(), vol[1:3, 2:4])
    np.testing.assert_array_equal(v.data[0].compute(), vol[0])


def test_rescale_keeps_integers_when_they_fit(tmp_path):
    raw = np.random.default_rng(8).integers(0, 4096, size=(3, 4, 5)).astype(np.uint16)
    make_series(tmp_path / "a", raw, slope=1, intercept=-1024, bits_stored=12)
    v = read_dicom(tmp_path / "a")
    assert v.dtype == np.int16  # 12 stored bits: -1024..3071
    np.testing.assert_array_equal(v.data.compute(), raw.astype(np.int32) - 1024)

    full = raw.copy()
    full[0, 0, 0] = 65535
    make_series(tmp_path / "b", full, slope=1, intercept=-1024)
    v = read_dicom(tmp_path / "b")
    assert v.dtype == np.int32  # 16 stored bits: -1024..64511
    np.testing.assert_array_equal(v.data.compute(), full.astype(np.int32) - 1024)
    # the same values as pydicom's own modality LUT, slice by slice
    for f in (tmp_path / "b").iterdir():
        ds = pydicom.dcmread(f)
        k = round((float(ds.ImagePositionPatient[2]) - ORIGIN[0]) / SPACING[0])
        np.testing.assert_array_equal(v.data[k].compute(), pydicom.pixels.apply_rescale(ds.pixel_array, ds))


def test_fractional_rescale_gives_float32(tmp_path):
    raw = np.random.default_rng(9).integers(0, 1000, size=(3, 4, 5)).astype(np.uint16)
    make_series(tmp_path / "f", raw, slope=0.25, intercept=-10.5)
    v = read_dicom(tmp_path / "f")
    assert v.dtype == np.float32
    np.testing.assert_allclose(v.data.compute(), raw * 0.25 - 10.5)


def test_without_positions_sorts_by_instance_number(tmp_path, vol):
    uid = generate_uid()
    folder = tmp_path / "np"
    folder.mkdir()
    for k in range(vol.shape[0]):
        make_slice(folder / f"z{vol.shape[0] - k}.dcm", vol[k], series_uid=uid, instance=k + 1, spacing_between=1.7)
    with pytest.warns(UserWarning, match="InstanceNumber"):
        v = read_dicom(folder)
    np.testing.assert_array_equal(v.data.compute(), vol)
    assert v.spacing[0] == pytest.approx(1.7)


def test_non_uniform_spacing_warns_with_deviation(tmp_path, vol):
    uid = generate_uid()
    folder = tmp_path / "nu"
    folder.mkdir()
    z = [0.0, 1.0, 2.0, 3.0, 4.6]  # mean step 1.15, largest deviation 0.45
    for k in range(vol.shape[0]):
        make_slice(folder / f"{k}.dcm", vol[k], series_uid=uid, position=(0, 0, z[k]))
    with pytest.warns(UserWarning, match=r"max deviation 0\.45 mm"):
        v = read_dicom(folder)
    assert v.spacing[0] == pytest.approx(1.15)
    assert v.metadata["slice_spacing_max_deviation"] == pytest.approx(0.45)


def test_uniform_spacing_does_not_warn(tmp_path, vol):
    make_series(tmp_path / "u", vol)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_dicom(tmp_path / "u")


def test_inconsistent_slice_sizes(tmp_path, vol):
    uid = make_series(tmp_path / "s", vol)
    make_slice(tmp_path / "s" / "odd.dcm", np.zeros((3, 3), np.int16), series_uid=uid, position=(0, 0, 99))
    with pytest.raises(InvalidInputError, match=r"different sizes: 6 x 7 \(5 files.*3 x 3 \(1 files, e.g. odd.dcm\)"):
        read_dicom(tmp_path / "s")


def test_duplicate_positions(tmp_path, vol):
    uid = make_series(tmp_path / "s", vol)
    make_slice(tmp_path / "s" / "dup.dcm", vol[0], series_uid=uid, position=(ORIGIN[2], ORIGIN[1], ORIGIN[0]))
    with pytest.raises(InvalidInputError, match="same position"):
        read_dicom(tmp_path / "s")


def test_no_dicom_in_folder(tmp_path):
    (tmp_path / "e").mkdir()
    (tmp_path / "e" / "notes.txt").write_text("hello")
    with pytest.raises(InvalidInputError, match="no DICOM images"):
        read_dicom(tmp_path / "e")
    (tmp_path / "e" / "notes.dcm").write_text("hello")  # named as DICOM: a damaged slice, not another file
    with pytest.raises(InvalidInputError, match="cannot be read: notes.dcm"):
        read_dicom(tmp_path / "e")


def test_rle_compressed_series(tmp_path, vol):
    make_series(tmp_path / "c", vol)
    for f in (tmp_path / "c").iterdir():
        ds = pydicom.dcmread(f)
        ds.compress(RLELossless)
        ds.save_as(f, enforce_file_format=True)
    assert pydicom.dcmread(next((tmp_path / "c").iterdir())).file_meta.TransferSyntaxUID == RLELossless
    np.testing.assert_array_equal(read_dicom(tmp_path / "c").data.compute(), vol)


def test_multi_frame_file(tmp_path, vol):
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = SecondaryCaptureImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID
    ds.SeriesInstanceUID, ds.Modality = generate_uid(), "OT"
    ds.NumberOfFrames = vol.shape[0]
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.Rows, ds.Columns = vol.shape[1:]
    ds.BitsAllocated = ds.BitsStored = 16
    ds.HighBit, ds.PixelRepresentation = 15, 1
    shared = Dataset()
    measures = Dataset()
    measures.PixelSpacing = [0.75, 0.5]
    shared.PixelMeasuresSequence = [measures]
    orient = Dataset()
    orient.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    shared.PlaneOrientationSequence = [orient]
    ds.SharedFunctionalGroupsSequence = [shared]
    frames = []
    for k in range(vol.shape[0]):
        fg, pos = Dataset(), Dataset()
        pos.ImagePositionPatient = [0, 0, 3.0 * (vol.shape[0] - 1 - k)]  # stored top-down
        fg.PlanePositionSequence = [pos]
        frames.append(fg)
    ds.PerFrameFunctionalGroupsSequence = frames
    ds.PixelData = vol.astype("<i2").tobytes()
    (tmp_path / "mf").mkdir()
    ds.save_as(tmp_path / "mf" / "multi.dcm", enforce_file_format=True)
    v = read_dicom(tmp_path / "mf")
    np.testing.assert_allclose(v.spacing, (3.0, 0.75, 0.5))
    np.testing.assert_array_equal(v.data.compute(), vol[::-1])
    assert v.data.numblocks == (vol.shape[0], 1, 1)


# ------------------------------------------------------------------------------------------------------------------
# several series
# ------------------------------------------------------------------------------------------------------------------
@pytest.fixture
def two_series(tmp_path, vol):
    folder = tmp_path / "two"
    uid_a = make_series(folder, vol, series_number=3, description="first", names=[f"a{k}.dcm" for k in range(5)])
    other = vol[:4, :3, :5] + 1
    uid_b = make_series(folder, other, series_number=7, description="second", names=[f"b{k}.dcm" for k in range(4)])
    return folder, uid_a, uid_b, other


def test_several_series_need_a_choice(two_series):
    folder, uid_a, uid_b, _ = two_series
    with pytest.raises(SeriesSelectionError) as err:
        read_dicom(folder)
    msg = str(err.value)
    assert uid_a in msg and uid_b in msg
    assert "'first'" in msg and "'second'" in msg
    assert "5 slices of 6 x 7" in msg and "4 slices of 3 x 5" in msg
    assert "series=" in msg and "--series" in msg
    assert set(err.value.series) == {uid_a, uid_b}
    assert isinstance(err.value, InvalidInputError)


@pytest.mark.parametrize("choice", ["uid", "number", "number_str", "index"])
def test_choose_series(two_series, vol, choice):
    folder, uid_a, uid_b, other = two_series
    series = {"uid": uid_b, "number": 7, "number_str": "7", "index": 1}[choice]
    v = open_volume(folder, series=series)
    np.testing.assert_array_equal(v.data.compute(), other)
    assert v.metadata["series_uid"] == uid_b
    np.testing.assert_array_equal(read_dicom(folder, series=0).data.compute(), vol)


def test_unknown_series(two_series):
    folder, *_ = two_series
    with pytest.raises(SeriesSelectionError, match="no series with SeriesNumber or index 5"):
        read_dicom(folder, series=5)
    with pytest.raises(SeriesSelectionError, match="no series with UID"):
        read_dicom(folder, series="1.2.3.999")


def test_one_file_opens_its_series(two_series):
    folder, _, uid_b, other = two_series
    v = open_volume(folder / "b2.dcm")
    assert v.metadata["series_uid"] == uid_b
    np.testing.assert_array_equal(v.data.compute(), other)


def test_list_series(two_series):
    folder, uid_a, uid_b, _ = two_series
    rows = list_series(folder)
    assert [(r["index"], r["uid"], r["number"], r["slices"], r["size"]) for r in rows] == [
        (0, uid_a, 3, 5, (6, 7)), (1, uid_b, 7, 4, (3, 5))]


# ------------------------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------------------------
_TYPE1 = ["SOPClassUID", "SOPInstanceUID", "StudyInstanceUID", "SeriesInstanceUID", "Modality", "FrameOfReferenceUID",
          "ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "SamplesPerPixel",
          "PhotometricInterpretation", "Rows", "Columns", "BitsAllocated", "BitsStored", "HighBit",
          "PixelRepresentation", "ImageType", "PixelData"]
_TYPE2 = ["PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate", "StudyTime",
          "ReferringPhysicianName", "StudyID", "AccessionNumber", "SeriesNumber", "InstanceNumber",
          "PositionReferenceIndicator"]


def test_written_series_is_valid_dicom(tmp_path, vol):
    out = write_volume(vol, tmp_path / "w.dicom", spacing=SPACING, unit="mm", origin=ORIGIN,
                       series_description="fish 1", patient_name="Doe^John")
    files = sorted(out.iterdir())
    assert [f.name for f in files] == [f"IM{k:05d}.dcm" for k in range(1, vol.shape[0] + 1)]
    series, sops = set(), set()
    for k, f in enumerate(files):
        ds = pydicom.dcmread(f)  # not forced: needs the preamble and valid file meta
        validate_file_meta(ds.file_meta, enforce_standard=True)
        assert ds.file_meta.TransferSyntaxUID == ExplicitVRLittleEndian
        assert ds.file_meta.MediaStorageSOPClassUID == ds.SOPClassUID == CTImageStorage
        assert ds.file_meta.MediaStorageSOPInstanceUID == ds.SOPInstanceUID
        for kw in _TYPE1:
            assert kw in ds and ds[kw].value not in (None, ""), kw
        for kw in _TYPE2:
            assert kw in ds, kw
        assert ds.Modality == "CT" and ds.SeriesDescription == "fish 1" and str(ds.PatientName) == "Doe^John"
        assert (ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation) == (16, 16, 15, 1)
        np.testing.assert_array_equal(ds.pixel_array, vol[k])
        np.testing.assert_allclose([float(v) for v in ds.ImagePositionPatient],
                                   (ORIGIN[2], ORIGIN[1], ORIGIN[0] + k * SPACING[0]))
        assert [float(v) for v in ds.ImageOrientationPatient] == [1, 0, 0, 0, 1, 0]
        np.testing.assert_allclose([float(v) for v in ds.PixelSpacing], SPACING[1:])
        assert float(ds.SliceThickness) == float(ds.SpacingBetweenSlices) == SPACING[0]
        assert int(ds.InstanceNumber) == k + 1
        series.add(ds.SeriesInstanceUID)
        sops.add(ds.SOPInstanceUID)
    assert len(series) == 1 and len(sops) == vol.shape[0]
    v = read_dicom(out)
    np.testing.assert_array_equal(v.data.compute(), vol)
    np.testing.assert_allclose(v.spacing, SPACING)
    np.testing.assert_allclose(v.origin, ORIGIN)


@pytest.mark.parametrize("dtype, sop, bits, signed", [
    ("uint8", SecondaryCaptureImageStorage, 8, 0), ("int8", SecondaryCaptureImageStorage, 8, 1),
    ("uint16", CTImageStorage, 16, 0), ("int16", CTImageStorage, 16, 1)])
def test_native_types(tmp_path, dtype, sop, bits, signed):
    info = np.iinfo(dtype)
    vol = np.random.default_rng(10).integers(info.min, info.max, size=(3, 5, 7), endpoint=True).astype(dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = write_volume(vol, tmp_path / "n.dicom", spacing=SPACING, unit="mm")
    ds = pydicom.dcmread(sorted(out.iterdir())[1])
    assert ds.SOPClassUID == sop
    assert (ds.BitsAllocated, ds.PixelRepresentation) == (bits, signed)
    np.testing.assert_array_equal(ds.pixel_array, vol[1])
    v = read_dicom(out)
    assert v.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(v.data.compute(), vol)


def test_micrometres_come_back_as_millimetres(tmp_path, vol):
    out = write_volume(vol, tmp_path / "um.dicom", spacing=(35.7, 35.7, 20.0), unit="um", origin=(100, 200, 300))
    ds = pydicom.dcmread(sorted(out.iterdir())[0])
    np.testing.assert_allclose([float(v) for v in ds.PixelSpacing], (0.0357, 0.02))
    v = read_dicom(out)
    assert v.unit == "millimeter"
    np.testing.assert_allclose(v.spacing, (0.0357, 0.0357, 0.02))
    np.testing.assert_allclose(v.origin, (0.1, 0.2, 0.3))
    # same physical extent: 5 x 35.7 um == 5 x 0.0357 mm
    np.testing.assert_allclose(np.array(v.shape) * v.spacing * 1000, np.array(vol.shape) * (35.7, 35.7, 20.0))


def test_float_data_are_quantised_with_a_warning(tmp_path):
    vol = np.random.default_rng(11).normal(0.0, 100.0, size=(4, 6, 8)).astype(np.float32)
    with pytest.warns(UserWarning, match="quantised") as rec:
        out = write_volume(vol, tmp_path / "f.dicom", spacing=SPACING, unit="mm")
    reported = float(str(rec[0].message).rsplit("up to ", 1)[1])
    ds = pydicom.dcmread(sorted(out.iterdir())[0])
    slope = float(ds.RescaleSlope)
    assert (ds.BitsAllocated, ds.PixelRepresentation) == (16, 0)
    assert slope == pytest.approx((vol.max() - vol.min()) / 65535, rel=1e-6)
    # pydicom's own modality LUT gives the values back within the reported error, which is at most half a step
    back0 = pydicom.pixels.apply_rescale(ds.pixel_array, ds)
    assert np.max(np.abs(back0 - vol[0])) <= reported * (1 + 1e-4) + 1e-6
    assert reported <= slope / 2 * (1 + 1e-6)
    v = read_dicom(out)
    assert v.dtype == np.float32
    err = np.max(np.abs(v.data.compute().astype(np.float64) - vol))
    assert err <= reported * (1 + 1e-4) + 1e-5
    assert err > 0  # random floats cannot all survive 16 bits


def test_wide_integers_stored_exactly_with_an_intercept(tmp_path):
    vol = np.random.default_rng(12).integers(-1024, 60000, size=(3, 4, 5)).astype(np.int32)
    vol[0, 0, 0], vol[0, 0, 1] = -1024, 60000
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = write_volume(vol, tmp_path / "i.dicom", spacing=SPACING, unit="mm")
    ds = pydicom.dcmread(sorted(out.iterdir())[0])
    assert (float(ds.RescaleSlope), float(ds.RescaleIntercept)) == (1.0, -1024.0)
    v = read_dicom(out)
    assert v.dtype == np.int32
    np.testing.assert_array_equal(v.data.compute(), vol)


def test_integral_floats_stored_exactly(tmp_path, vol):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = write_volume(vol.astype(np.float64), tmp_path / "x.dicom", spacing=SPACING, unit="mm")
    v = read_dicom(out)
    assert v.dtype == np.int16
    np.testing.assert_array_equal(v.data.compute(), vol)


def test_writer_streams_with_progress(tmp_path, vol):
    v = Volume(da.from_array(vol, chunks=(2, 6, 7)), spacing=SPACING, unit="mm")
    records = []
    run(write_dicom(v, tmp_path / "p", series_number=4), records.append)
    assert records[-1].done == records[-1].total == vol.shape[0]
    assert len(list((tmp_path / "p").iterdir())) == vol.shape[0]
    assert int(pydicom.dcmread(tmp_path / "p" / "IM00003.dcm").SeriesNumber) == 4


def test_unit_unknown_warns(tmp_path, vol):
    with pytest.warns(UserWarning, match="no unit"):
        write_volume(vol, tmp_path / "u.dicom")


def test_two_written_series_in_one_folder(tmp_path, vol):
    a = write_volume(vol, tmp_path / "a.dicom", spacing=SPACING, unit="mm", series_number=1,
                     series_description="first")
    b = write_volume(vol[:, ::-1] * 2, tmp_path / "b.dicom", spacing=SPACING, unit="mm", series_number=2,
                     series_description="second")
    both = tmp_path / "both"
    both.mkdir()
    for src, prefix in ((a, "a"), (b, "b")):
        for f in src.iterdir():
            shutil.move(f, both / f"{prefix}_{f.name}")
    with pytest.raises(SeriesSelectionError, match="holds 2 DICOM series"):
        open_volume(both)
    np.testing.assert_array_equal(open_volume(both, series=2).data.compute(), vol[:, ::-1] * 2)
    np.testing.assert_array_equal(open_volume(both, series=0).data.compute(), vol)


def test_truncated_slice_named_when_read(tmp_path, vol):
    make_series(tmp_path / "t", vol, names=[f"IM{k}.dcm" for k in range(vol.shape[0])])
    victim = tmp_path / "t" / "IM2.dcm"
    victim.write_bytes(victim.read_bytes()[:-20])  # pixel data cut short; the header is intact
    v = read_dicom(tmp_path / "t")  # header-only pass: fine
    np.testing.assert_array_equal(v.data[:2].compute(), vol[:2])
    with pytest.raises(InvalidInputError, match="IM2.dcm: cannot decode its pixel data"):
        v.data[2].compute()


@pytest.mark.parametrize("cut", [200, 10, 0])
def test_unreadable_file_is_an_error(tmp_path, vol, cut):
    """A damaged file may be a slice of the series: reading without it would leave a gap, so it is an error that
    names it (listing the series only warns)."""
    make_series(tmp_path / "u", vol, names=[f"IM{k}.dcm" for k in range(vol.shape[0])])
    broken = tmp_path / "u" / "IM9.dcm"
    broken.write_bytes((tmp_path / "u" / "IM0.dcm").read_bytes()[:cut])  # DICM marker (200), then cut short
    with pytest.raises(InvalidInputError, match="1 DICOM file.*cannot be read: IM9.dcm.*move them out"):
        read_dicom(tmp_path / "u")
    with pytest.warns(UserWarning, match="IM9.dcm"):
        assert len(list_series(tmp_path / "u")) == 1
    broken.unlink()
    np.testing.assert_array_equal(read_dicom(tmp_path / "u").data.compute(), vol)
