"""The real scans of ../shared/data through the NRRD, NHDR, NIfTI and DICOM readers and writers.

Every NRRD there is compared with an independent pynrrd read; the aorta CT (int16, HU) and its mask (uint8) go
through every one of these formats and back. Skipped where the data folder is absent (a user's checkout).
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import nibabel as nib
import nrrd
import numpy as np
import pydicom
import pytest

from napari_unwind.errors import SeriesSelectionError
from napari_unwind.io import open_volume, write_volume

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
NRRDS = ["aorta_ct.nrrd", "aorta_ct_aorta_mask.nrrd", "spine_t2.nrrd", "spine_t2_cord_mask.nrrd",
         "spine_t2_centerline_mask.nrrd"]

pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"real data folder {DATA} absent")


def _pynrrd(name: str) -> tuple[np.ndarray, dict]:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"{path} absent")
    return nrrd.read(str(path), index_order="C")


@pytest.fixture(scope="module")
def aorta() -> dict[str, tuple[np.ndarray, dict]]:
    return {"ct": _pynrrd("aorta_ct.nrrd"), "mask": _pynrrd("aorta_ct_aorta_mask.nrrd")}


@pytest.mark.parametrize("name", NRRDS)
def test_open_matches_pynrrd(name):
    data, header = _pynrrd(name)
    v = open_volume(DATA / name)
    assert v.format == "nrrd"
    assert v.shape == data.shape
    assert v.dtype == data.dtype
    spacing = np.linalg.norm(np.asarray(header["space directions"], dtype=float), axis=1)[::-1]
    np.testing.assert_allclose(v.spacing, spacing)
    if "space origin" in header:
        np.testing.assert_allclose(v.origin, np.asarray(header["space origin"])[::-1])
    np.testing.assert_array_equal(v.data.compute(), data)


def test_readme_shapes():
    # the README's table, as an independent statement of what the files hold
    expected = {"aorta_ct.nrrd": ((120, 126, 164), "int16", 1.5), "spine_t2.nrrd": ((60, 55, 52), "int16", 1.0),
                "spine_t2_cord_mask.nrrd": ((60, 55, 52), "uint8", 1.0)}
    for name, (shape, dtype, sp) in expected.items():
        v = open_volume(DATA / name)
        assert (v.shape, str(v.dtype)) == (shape, dtype)
        np.testing.assert_allclose(v.spacing, (sp, sp, sp))


@pytest.mark.parametrize("which", ["ct", "mask"])
@pytest.mark.parametrize("target", ["x.nrrd", "x.nhdr", "x.nii.gz", "x.dicom"])
def test_round_trip(tmp_path, aorta, which, target):
    data, header = aorta[which]
    src = open_volume(DATA / ("aorta_ct.nrrd" if which == "ct" else "aorta_ct_aorta_mask.nrrd"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # 8/16-bit data need no quantisation
        out = write_volume(src, tmp_path / target)
    back = open_volume(out)
    assert back.shape == data.shape
    assert back.dtype == data.dtype
    np.testing.assert_array_equal(back.data.compute(), data)
    np.testing.assert_allclose(back.spacing, src.spacing)
    np.testing.assert_allclose(back.origin, src.origin, atol=1e-4)
    assert back.unit == src.unit == "millimeter"
    # and each library reads what was written
    if target.endswith(".nii.gz"):
        np.testing.assert_array_equal(np.asarray(nib.load(out).dataobj).transpose(2, 1, 0), data)
    elif target.endswith(".dicom"):
        files = sorted(out.iterdir())
        assert len(files) == data.shape[0]
        mid = len(files) // 2
        np.testing.assert_array_equal(pydicom.dcmread(files[mid]).pixel_array, data[mid])
    else:
        np.testing.assert_array_equal(nrrd.read(str(out), index_order="C")[0], data)


def test_two_real_series_in_one_folder(tmp_path, aorta):
    ct, _ = aorta["ct"]
    mask, _ = aorta["mask"]
    src_ct = open_volume(DATA / "aorta_ct.nrrd")
    src_mask = open_volume(DATA / "aorta_ct_aorta_mask.nrrd")
    a = write_volume(src_ct, tmp_path / "ct.dicom", series_number=1, series_description="aorta CT")
    b = write_volume(src_mask, tmp_path / "mask.dicom", series_number=2, series_description="aorta mask")
    uid_ct = str(pydicom.dcmread(next(a.iterdir())).SeriesInstanceUID)
    uid_mask = str(pydicom.dcmread(next(b.iterdir())).SeriesInstanceUID)
    both = tmp_path / "both"
    both.mkdir()
    for folder, prefix in ((a, "ct"), (b, "mask")):
        for f in folder.iterdir():
            shutil.move(f, both / f"{prefix}_{f.name}")

    with pytest.raises(SeriesSelectionError) as err:
        open_volume(both)
    msg = str(err.value)
    for uid, desc in ((uid_ct, "aorta CT"), (uid_mask, "aorta mask")):
        assert uid in msg and desc in msg
    assert msg.count("120 slices of 126 x 164") == 2
    assert set(err.value.series) == {uid_ct, uid_mask}

    for choice, expected in ((uid_mask, mask), (2, mask), ("1", ct), (0, ct)):
        v = open_volume(both, series=choice)
        assert v.dtype == expected.dtype
        np.testing.assert_array_equal(v.data.compute(), expected)
        np.testing.assert_allclose(v.spacing, src_ct.spacing)
    v = open_volume(both / "mask_IM00001.dcm")  # a file picks its own series
    np.testing.assert_array_equal(v.data.compute(), mask)
