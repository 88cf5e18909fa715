"""NIfTI reading and writing, checked against nibabel's own reader and writer."""

from __future__ import annotations

import dask.array as da
import nibabel as nib
import numpy as np
import pytest

from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume, open_volume, write_volume
from napari_unwind.io import nifti as nifti_mod
from napari_unwind.io.nifti import read_nifti, write_nifti
from napari_unwind.progress import Progress, run

SPACING = (3.0, 2.0, 0.5)  # axis0, axis1, axis2
ORIGIN = (10.0, -20.0, 30.5)


@pytest.fixture
def vol() -> np.ndarray:
    return np.random.default_rng(4).integers(-3000, 3000, size=(4, 5, 6)).astype(np.int16)


@pytest.mark.parametrize("name", ["a.nii", "a.nii.gz"])
def test_written_file_read_by_nibabel(tmp_path, vol, name):
    out = write_volume(vol, tmp_path / name, spacing=SPACING, unit="um", origin=ORIGIN)
    img = nib.load(str(out))
    assert isinstance(img, nib.Nifti1Image)
    data = np.asarray(img.dataobj)
    assert data.shape == (6, 5, 4) and data.dtype == vol.dtype
    np.testing.assert_array_equal(data, vol.transpose(2, 1, 0))  # nibabel (i, j, k) = ours (k, j, i) reversed
    np.testing.assert_allclose(img.header.get_zooms(), SPACING[::-1])
    assert img.header.get_xyzt_units()[0] == "micron"
    expected = np.diag([*SPACING[::-1], 1.0])
    expected[:3, 3] = ORIGIN[::-1]
    np.testing.assert_allclose(img.affine, expected)
    np.testing.assert_allclose(img.get_qform(), expected)
    assert int(img.header["sform_code"]) > 0 and int(img.header["qform_code"]) > 0
    with open(out, "rb") as fh:
        magic = fh.read(2)
    assert (magic == b"\x1f\x8b") == name.endswith(".gz")
    assert [p.name for p in tmp_path.iterdir()] == [name]


def test_read_nibabel_file(tmp_path):
    rng = np.random.default_rng(5)
    ijk = rng.random((7, 5, 3)).astype(np.float32)
    affine = np.diag([0.5, 2.0, 3.0, 1.0])
    affine[:3, 3] = (1.0, 2.0, 3.0)
    img = nib.Nifti1Image(ijk, affine)
    img.header.set_xyzt_units(xyz="mm")
    nib.save(img, tmp_path / "x.nii.gz")
    v = open_volume(tmp_path / "x.nii.gz")
    assert v.shape == (3, 5, 7) and v.dtype == np.float32
    np.testing.assert_array_equal(v.data.compute(), ijk.transpose(2, 1, 0))
    np.testing.assert_allclose(v.spacing, (3.0, 2.0, 0.5))
    np.testing.assert_allclose(v.origin, (3.0, 2.0, 1.0))
    assert v.unit == "millimeter" and v.format == "nifti"
    np.testing.assert_allclose(v.metadata["affine"], affine)


def test_unknown_unit(tmp_path, vol):
    nib.save(nib.Nifti1Image(vol, np.eye(4)), tmp_path / "u.nii")
    assert read_nifti(tmp_path / "u.nii").unit is None


def test_nifti2(tmp_path, vol):
    nib.save(nib.Nifti2Image(vol, np.diag([1.0, 2.0, 4.0, 1.0])), tmp_path / "two.nii")
    v = read_nifti(tmp_path / "two.nii")
    np.testing.assert_array_equal(v.data.compute(), vol.transpose(2, 1, 0))
    np.testing.assert_allclose(v.spacing, (4.0, 2.0, 1.0))
    assert v.metadata["nifti_version"] == 2


def _scaled(tmp_path, raw: np.ndarray, slope: float, inter: float):
    img = nib.Nifti1Image(raw, np.eye(4))
    img.header.set_data_dtype(raw.dtype)
    img.header.set_slope_inter(slope, inter)
    nib.save(img, tmp_path / "s.nii")
    return read_nifti(tmp_path / "s.nii"), np.asarray(nib.load(tmp_path / "s.nii").dataobj)


def test_unscaled_keeps_integer_type(tmp_path, vol):
    v, ref = _scaled(tmp_path, vol, 1.0, 0.0)
    assert v.dtype == np.int16
    np.testing.assert_array_equal(v.data.compute(), ref.transpose(2, 1, 0))


def test_integer_scaling_gives_integers(tmp_path):
    raw = np.array([0, 1, 4095, 65535] * 6, dtype=np.uint16).reshape(2, 3, 4)
    v, ref = _scaled(tmp_path, raw, 2.0, -1024.0)
    assert v.dtype == np.int32  # 65535 * 2 - 1024 does not fit 16 bits
    np.testing.assert_array_equal(v.data.compute(), ref.transpose(2, 1, 0))
    np.testing.assert_array_equal(v.data.compute(), (raw.astype(np.int64) * 2 - 1024).transpose(2, 1, 0))


def test_fractional_scaling_gives_floats(tmp_path, vol):
    v, ref = _scaled(tmp_path, vol, 0.5, 0.25)
    assert v.dtype == np.float32
    np.testing.assert_allclose(v.data.compute(), ref.transpose(2, 1, 0))
    np.testing.assert_allclose(v.data.compute(), vol.transpose(2, 1, 0) * 0.5 + 0.25)


def test_four_dimensional(tmp_path, vol):
    nib.save(nib.Nifti1Image(vol[..., np.newaxis], np.eye(4)), tmp_path / "t1.nii")
    v = read_nifti(tmp_path / "t1.nii")
    np.testing.assert_array_equal(v.data.compute(), vol.transpose(2, 1, 0))
    nib.save(nib.Nifti1Image(np.stack([vol] * 3, axis=-1), np.eye(4)), tmp_path / "t3.nii")
    with pytest.raises(InvalidInputError, match="3D volume"):
        read_nifti(tmp_path / "t3.nii")
    nib.save(nib.Nifti1Image(vol[:, :, 0], np.eye(4)), tmp_path / "flat.nii")
    with pytest.raises(InvalidInputError, match="3D volume"):
        read_nifti(tmp_path / "flat.nii")


def test_big_endian_file(tmp_path, vol):
    hdr = nib.Nifti1Header(endianness=">")
    hdr.set_data_dtype(np.int16)
    nib.save(nib.Nifti1Image(vol.astype(">i2"), np.eye(4), header=hdr), tmp_path / "be.nii")
    assert nib.load(tmp_path / "be.nii").header.endianness == ">"
    v = read_nifti(tmp_path / "be.nii")
    assert v.dtype == np.dtype("int16") and v.dtype.isnative
    np.testing.assert_array_equal(v.data.compute(), vol.transpose(2, 1, 0))


def test_read_is_lazy(tmp_path, vol):
    out = write_volume(vol, tmp_path / "l.nii")
    v = read_nifti(out, chunks=(1, 5, 6))
    assert v.data.numblocks == (4, 1, 1)
    changed = (vol + 7).astype(np.int16)
    with open(out, "r+b") as fh:  # overwrite the voxels in place after opening
        fh.seek(352)
        fh.write(changed.astype("<i2").tobytes())
    np.testing.assert_array_equal(v.data.compute(), changed)
    np.testing.assert_array_equal(v.data[1:3, 2].compute(), changed[1:3, 2])


@pytest.mark.parametrize("unit, nifti_unit, factor", [("nm", "micron", 1e-3), ("cm", "mm", 10.0),
                                                      ("m", "meter", 1.0), (None, "unknown", 1.0)])
def test_units_nifti_lacks_are_converted(tmp_path, vol, unit, nifti_unit, factor):
    out = write_volume(vol, tmp_path / "u.nii", spacing=SPACING, unit=unit, origin=ORIGIN)
    img = nib.load(out)
    assert img.header.get_xyzt_units()[0] == nifti_unit
    np.testing.assert_allclose(img.header.get_zooms(), np.array(SPACING[::-1]) * factor)
    np.testing.assert_allclose(img.affine[:3, 3], np.array(ORIGIN[::-1]) * factor)


@pytest.mark.parametrize("dtype", ["uint8", "int8", "uint16", "int32", "uint32", "float32", "float64"])
def test_every_dtype_round_trips(tmp_path, dtype):
    vol = (np.arange(60).reshape(3, 4, 5) * 1.5).astype(dtype)
    out = write_volume(vol, tmp_path / "x.nii.gz")
    ref = np.asarray(nib.load(out).dataobj)
    assert ref.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(ref.transpose(2, 1, 0), vol)
    back = open_volume(out)
    assert back.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(back.data.compute(), vol)


def test_streams_in_slabs_with_progress(tmp_path, vol, monkeypatch):
    monkeypatch.setattr(nifti_mod, "write_slab_depth", lambda volume: 3)  # 4 planes -> slabs of 3 and 1
    v = Volume(da.from_array(vol, chunks=(1, 5, 6)), spacing=SPACING)
    records: list[Progress] = []
    run(write_nifti(v, tmp_path / "p.nii.gz"), records.append)
    assert [(r.done, r.total) for r in records] == [(1, 2), (2, 2)]
    np.testing.assert_array_equal(np.asarray(nib.load(tmp_path / "p.nii.gz").dataobj).transpose(2, 1, 0), vol)


def test_not_a_nifti(tmp_path):
    p = tmp_path / "x.nii"
    p.write_bytes(b"\x00" * 100)
    with pytest.raises(InvalidInputError, match="not a readable NIfTI"):
        open_volume(p)


def test_compression_level_validated(tmp_path, vol):
    with pytest.raises(InvalidInputError, match="compression_level"):
        write_volume(vol, tmp_path / "x.nii.gz", compression_level=10)


@pytest.mark.parametrize("kind", ["plain", "scaled", "big-endian", "4d", "float"])
def test_gzipped_files_read_like_nibabel(tmp_path, kind):
    """The .nii.gz plane reader against nibabel's own reading, for scaling, byte order and a length-1 4th axis."""
    rng = np.random.default_rng(5)
    arr = rng.integers(-300, 3000, (7, 6, 5)).astype(">i2" if kind == "big-endian" else "<i2")
    if kind == "float":
        arr = rng.standard_normal((7, 6, 5)).astype(np.float32)
    if kind == "4d":
        arr = arr[..., None]
    img = nib.Nifti1Image(arr, np.diag([0.5, 0.25, 2.0, 1.0]))
    if kind == "scaled":
        img.header.set_slope_inter(0.5, -10.0)
    nib.save(img, tmp_path / "g.nii.gz")
    expect = np.asarray(nib.load(tmp_path / "g.nii.gz").dataobj)
    if expect.ndim == 4:
        expect = expect[..., 0]
    v = open_volume(tmp_path / "g.nii.gz", chunks=(3, 6, 7))
    np.testing.assert_allclose(v.data.compute(), expect.transpose(2, 1, 0), rtol=1e-6)
    np.testing.assert_allclose(v.data[1:4, 2:5, 3].compute(), expect.transpose(2, 1, 0)[1:4, 2:5, 3], rtol=1e-6)


def test_gzipped_file_with_flipped_bytes_is_an_error(tmp_path):
    """nibabel stops before the gzip trailer, so its CRC would never be checked: ours reads on to it."""
    big = np.random.default_rng(6).integers(0, 3000, (20, 30, 40)).astype(np.int16)
    out = write_volume(big, tmp_path / "f.nii.gz", compression_level=1)
    raw = bytearray(out.read_bytes())
    for i in range(len(raw) // 2, len(raw) // 2 + 8):
        raw[i] ^= 0xFF
    damaged = tmp_path / "d.nii.gz"
    damaged.write_bytes(bytes(raw))
    with pytest.raises(InvalidInputError, match=str(damaged).replace(".", r"\.") + ": cannot read its voxels"):
        open_volume(damaged).data.compute()
