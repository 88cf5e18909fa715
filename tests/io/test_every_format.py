"""Every format in both directions, on a phantom and on the real scans, through the public API only."""

import numpy as np
import pytest

from conftest import no_leftovers
from napari_unwind.datasets import fish_phantom
from napari_unwind.errors import InvalidInputError, UnknownFormatError
from napari_unwind.io import FORMATS, Volume, open_volume, write_volume

# target name -> whether the format keeps the unit exactly (DICOM is always millimetres)
TARGETS = {
    "scan.zarr": True,
    "scan.ome.zarr": True,
    "scan.tif": True,
    "slices/scan_{:04d}.tif": True,
    "scan.nrrd": True,
    "scan.nhdr": True,
    "scan.nii.gz": True,
    "scan.nii": True,
    "scan.dat": True,
    "scan.dicom": False,
}


def test_targets_cover_every_format():
    from napari_unwind.io._formats import output_format

    assert {output_format(t) for t in TARGETS} == set(FORMATS)


@pytest.fixture(scope="module")
def phantom():
    p = fish_phantom(seed=1)
    return p.volume, p.spacing


def _check(tmp_path, target, data, spacing, unit, keeps_unit):
    written = write_volume(data, tmp_path / target, spacing=spacing, unit=unit)
    v = open_volume(written)
    got = v.data.compute()
    np.testing.assert_array_equal(got, data)
    assert got.dtype == data.dtype or (target.endswith(".dicom") and np.can_cast(data.dtype, got.dtype))
    if keeps_unit:
        np.testing.assert_allclose(v.spacing, spacing, rtol=1e-6)
        assert v.unit == unit
    else:  # DICOM: millimetres, same physical size
        factor = {"millimeter": 1.0, "micrometer": 1e-3, None: 1.0}[unit]  # no unit: taken as mm, with a warning
        np.testing.assert_allclose(v.spacing, np.asarray(spacing) * factor, rtol=1e-5)
        assert v.unit == "millimeter"
    assert no_leftovers(tmp_path) == []


@pytest.mark.parametrize("target", TARGETS)
def test_phantom_round_trip(tmp_path, phantom, target):
    data, spacing = phantom
    _check(tmp_path, target, data, spacing, "micrometer", TARGETS[target])


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("name", ["aorta_ct.nrrd", "spine_t2_cord_mask.nrrd"])
def test_real_scan_round_trip(tmp_path, shared_data, target, name):
    import nrrd

    src = open_volume(shared_data / name)
    ref, header = nrrd.read(str(shared_data / name), index_order="C")  # independent reader
    np.testing.assert_array_equal(src.data.compute(), ref)
    spacing = tuple(np.linalg.norm(np.asarray(header["space directions"], float), axis=1)[::-1])
    np.testing.assert_allclose(src.spacing, spacing)
    _check(tmp_path, target, ref, src.spacing, src.unit, TARGETS[target])


def test_a_dimension_of_size_zero_is_refused(tmp_path):
    with pytest.raises(InvalidInputError, match="size 0"):
        write_volume(np.zeros((0, 4, 4), np.uint8), tmp_path / "a.nrrd")
    (tmp_path / "z.dat").write_text("RawFile: z.raw\nResolution: 4 0 3\nFormat: UCHAR\n")
    (tmp_path / "z.raw").write_bytes(b"")
    with pytest.raises(InvalidInputError, match="Resolution sizes must be positive"):
        open_volume(tmp_path / "z.dat")
    assert not (tmp_path / "a.nrrd").exists()


def test_2d_and_4d_arrays_are_refused(tmp_path):
    with pytest.raises(InvalidInputError, match="3D"):
        Volume(np.zeros((4, 4), np.uint8))
    with pytest.raises(InvalidInputError, match="3D"):
        write_volume(np.zeros((2, 3, 4, 5), np.uint8), tmp_path / "a.tif")


def test_unsupported_voxel_type_is_explained(tmp_path):
    with pytest.raises(InvalidInputError, match="unsupported voxel type complex64"):
        write_volume(np.zeros((2, 3, 4), np.complex64), tmp_path / "a.nrrd")


def test_unknown_format_is_explained(tmp_path):
    (tmp_path / "scan.xyz").write_bytes(b"\0" * 64)
    with pytest.raises(UnknownFormatError, match="supported: OME-Zarr"):
        open_volume(tmp_path / "scan.xyz")
    with pytest.raises(UnknownFormatError, match="cannot choose an output format"):
        write_volume(np.zeros((2, 3, 4), np.uint8), tmp_path / "out.xyz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(UnknownFormatError, match="empty folder"):
        open_volume(tmp_path / "empty")


def test_inputs_are_never_modified(tmp_path, shared_data):
    """Reading and converting leaves the source bytes and times untouched."""
    import hashlib
    import shutil

    src = tmp_path / "aorta.nrrd"
    shutil.copy(shared_data / "aorta_ct.nrrd", src)
    before = (hashlib.sha256(src.read_bytes()).hexdigest(), src.stat().st_mtime_ns)
    v = open_volume(src)
    write_volume(v, tmp_path / "a.zarr")
    write_volume(v, tmp_path / "a.tif")
    assert (hashlib.sha256(src.read_bytes()).hexdigest(), src.stat().st_mtime_ns) == before
