"""A file that declares a voxel size that is not a positive number (0, NaN) is read as 1 with a warning that names
the file, the axis and the value, never silently (issue 20: NRRD and NIfTI with zero or NaN spacing were read as 1
without a word). A file that states no voxel size at all is read as 1 quietly, as every reader of the format does."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from napari_unwind.io import open_volume


def _read(path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        v = open_volume(path)
    return v, [str(w.message) for w in caught if issubclass(w.category, UserWarning)]


@pytest.mark.parametrize("bad, shown", [(0.0, "0"), (float("nan"), "nan")])
def test_nrrd_spacing_that_is_not_positive_is_said(tmp_path, bad, shown):
    import nrrd

    a = np.zeros((4, 5, 6), np.uint8)
    path = tmp_path / "lies.nrrd"
    # file axes are the array's reversed: the first "spacings" entry is array axis2
    nrrd.write(str(path), a, {"spacings": [bad, 2.0, 3.0]}, index_order="C")
    v, said = _read(path)
    assert v.spacing == (3.0, 2.0, 1.0)
    assert said == [f"lies.nrrd declares a voxel size of {shown} along axis2, which is not a positive number: it is "
                    "read as 1; give the real spacing (--spacing A0,A1,A2, or spacing= in Python) or fix the file's "
                    "header"]
    path2 = tmp_path / "dirs.nrrd"
    nrrd.write(str(path2), a, {"space": "left-posterior-superior",
                               "space directions": np.diag([1.5, 0.0, 1.0])}, index_order="C")
    v, said = _read(path2)
    assert v.spacing == (1.0, 1.0, 1.5) and len(said) == 1 and "of 0 along axis1" in said[0]


def test_nrrd_without_a_voxel_size_is_read_as_1_quietly(tmp_path):
    import nrrd

    path = tmp_path / "plain.nrrd"
    nrrd.write(str(path), np.zeros((4, 5, 6), np.uint8), index_order="C")
    v, said = _read(path)
    assert v.spacing == (1.0, 1.0, 1.0) and said == []


def test_nifti_zero_zoom_is_said(tmp_path):
    import nibabel as nib

    path = tmp_path / "lies.nii"
    img = nib.Nifti1Image(np.zeros((6, 5, 4), np.uint8), np.diag([1.0, 2.0, 3.0, 1.0]))
    img.header["pixdim"][2] = 0.0  # the j axis (array axis1 after the transpose to K, J, I)
    raw = img.header.binaryblock + b"\x00" * 4 + np.zeros((6, 5, 4), np.uint8).tobytes(order="F")
    path.write_bytes(raw)
    v, said = _read(path)
    assert v.spacing[1] == 1.0 and any("lies.nii declares a voxel size of 0 along axis1" in m for m in said), said


@pytest.mark.parametrize("ext", ["tif", "nrrd", "zarr", "nii"])
def test_an_infinite_origin_is_refused_before_writing(tmp_path, ext):
    """TIFF wrote an infinite origin and read it back; NRRD and NIfTI dropped it for 0 without a word."""
    from napari_unwind.errors import InvalidInputError
    from napari_unwind.io import write_volume

    with pytest.raises(InvalidInputError, match=r"origin must be finite numbers, got \(inf, 0.0, 0.0\)"):
        write_volume(np.zeros((4, 5, 6), np.uint8), tmp_path / f"o.{ext}", origin=(float("inf"), 0, 0))
    assert list(tmp_path.iterdir()) == []


def test_a_zarr_chunk_side_of_0_is_one_line_not_a_traceback(tmp_path):
    """A store whose metadata declares a chunk side of 0: `info` reported chunks 1x5x6 and convert raised
    ZeroDivisionError (issue 20)."""
    import json

    from conftest import run_unwind
    from napari_unwind.io import write_volume

    store = write_volume(np.zeros((4, 5, 6), np.uint8), tmp_path / "s.zarr")
    meta = store / "0" / "zarr.json"
    j = json.loads(meta.read_text())
    j["chunk_grid"]["configuration"]["chunk_shape"] = [0, 5, 6]
    meta.write_text(json.dumps(j))
    for args in (("info", store), ("convert", store, tmp_path / "o.tif")):
        code, out, err = run_unwind(*args)
        assert code == 1 and "Traceback" not in err and err.count("\n") == 1, err
        assert "declares chunks (0, 5, 6); every chunk side must be at least 1" in err, err
    assert not (tmp_path / "o.tif").exists()


def test_a_negative_size_in_a_header_is_one_line(tmp_path):
    """NRRD 'sizes: 6 5 -4' opened as an array of shape (-4, 5, 6) and `info` raised IndexError; a NIfTI dim of -4
    raised dask's ValueError (issue 20: reported as "4 x 5 x -6, -120 B")."""
    import nibabel as nib

    from conftest import run_unwind

    nrrd_path = tmp_path / "neg.nrrd"
    nrrd_path.write_bytes(b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 6 5 -4\nencoding: raw\n\n" + bytes(120))
    h = nib.Nifti1Image(np.zeros((6, 5, 4), np.uint8), np.eye(4)).header.copy()
    h["dim"][3] = -4
    nii_path = tmp_path / "neg.nii"
    nii_path.write_bytes(h.binaryblock + bytes(4) + bytes(120))
    for path in (nrrd_path, nii_path):
        code, out, err = run_unwind("info", path)
        assert code == 1 and "Traceback" not in err and err.count("\n") == 1, err
        assert "hold a size below 1" in err and "-4" in err, err


def test_ome_zarr_axes_in_different_units_are_brought_to_the_finest(tmp_path):
    """Axis 0 in millimetres, axes 1-2 in micrometres was reported as "2 x 1 x 1 mm" (issue 20): now 2000 x 1 x 1
    micrometres, in `info` (the header reader) and in the volume alike; a unit on some axes only is one line."""
    import json

    from conftest import run_unwind
    from napari_unwind.errors import InvalidInputError
    from napari_unwind.io import write_volume

    store = write_volume(np.zeros((4, 5, 6), np.uint8), tmp_path / "s.zarr", spacing=(2.0, 1.0, 1.0),
                         origin=(3.0, 0.0, 0.0), unit="micrometer")
    meta = store / "zarr.json"
    j = json.loads(meta.read_text())
    axes = j["attributes"]["ome"]["multiscales"][0]["axes"]
    axes[0]["unit"] = "millimeter"
    meta.write_text(json.dumps(j))
    v = open_volume(store)
    assert v.unit == "micrometer" and v.spacing == (2000.0, 1.0, 1.0) and v.origin == (3000.0, 0.0, 0.0)
    code, out, err = run_unwind("info", store)
    assert code == 0 and "2000 x 1 x 1 um" in out, out + err
    del axes[1]["unit"]
    meta.write_text(json.dumps(j))
    with pytest.raises(InvalidInputError, match="mix lengths with none"):
        open_volume(store)


def test_an_nrrd_space_direction_far_from_1_is_read_as_its_length(tmp_path):
    """The voxel size is the length of a space direction vector: 1e200 and 1e-170 (whose squares overflow and
    underflow a 64-bit float) are read as themselves, not as inf (then 1, with a warning) and 0."""
    path = tmp_path / "far.nrrd"
    path.write_bytes(b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nspace dimension: 3\n"
                     b"space directions: (1e200,0,0) (0,3e-170,4e-170) (0,0,1)\nencoding: raw\n\n" + bytes(8))
    v, said = _read(path)
    assert v.spacing == (1.0, 5e-170, 1e200) and said == []
