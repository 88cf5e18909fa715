"""A mask cropped to its segment's box (3D Slicer, ITK-SNAP) is placed back on its scan's grid by its file's origin.

The reference is the full mask, embedded by hand with numpy at the offset the test chose; the crops' headers are
written here with pynrrd and nibabel (signed, rotated directions; a RAS affine), never by the code under test.
"""

import nibabel as nib
import nrrd
import numpy as np
import pytest
import tifffile

from napari_unwind.errors import InvalidInputError
from napari_unwind.io import open_volume
from napari_unwind.io._grid import place_on_grid

SHAPE = (14, 17, 19)  # array order (axis0, axis1, axis2); the files list it reversed (x, y, z)


@pytest.fixture(scope="module")
def full():
    rng = np.random.default_rng(5)
    scan = rng.integers(0, 1000, SHAPE).astype(np.int16)
    mask = np.zeros(SHAPE, np.uint8)
    mask[3:11, 4:13, 6:15] = rng.integers(0, 3, (8, 9, 9))  # labels 0, 1, 2 inside a box
    return scan, mask


def _nrrd(path, data, directions, origin):
    """``data`` in array order written as NRRD: sizes reversed, one direction vector per file axis (x, y, z)."""
    header = {"space": "left-posterior-superior", "space directions": np.asarray(directions, float),
              "space origin": np.asarray(origin, float), "kinds": ["domain"] * 3}
    nrrd.write(str(path), np.ascontiguousarray(data.transpose(2, 1, 0)), header)
    return path


DIRECTIONS = {
    "plain": np.diag([0.5, 0.5, 0.8]),
    "flipped": np.diag([-0.5, -0.5, 0.8]),  # a scan read in another patient orientation
    "rotated": np.array([[0.0, 0.5, 0.0], [-0.5, 0.0, 0.0], [0.0, 0.0, 0.8]]),  # x and y turned by 90 degrees
}


@pytest.mark.parametrize("kind", sorted(DIRECTIONS))
def test_an_nrrd_crop_is_placed_where_its_origin_says(full, tmp_path, kind):
    scan, mask = full
    d = DIRECTIONS[kind]
    origin = np.array([-12.0, 30.5, 7.25])
    lo = np.array([2, 3, 5])  # array order: the crop starts at scan voxel (2, 3, 5)
    crop = mask[lo[0]:12, lo[1]:14, lo[2]:16]
    crop_origin = origin + lo[::-1] @ d  # world of the crop's voxel 0: file axes x, y, z are array axes 2, 1, 0
    s = open_volume(_nrrd(tmp_path / "scan.nrrd", scan, d, origin))
    m = open_volume(_nrrd(tmp_path / "crop.nrrd", crop, d, crop_origin))
    placed, note = place_on_grid(m, s)
    assert placed.shape == SHAPE and placed.data.dtype == np.uint8
    np.testing.assert_array_equal(np.asarray(placed.data), mask)
    assert placed.spacing == s.spacing and placed.origin == s.origin
    assert note == ("the mask crop.nrrd (shape 10 x 11 x 11) is a box of the scan's grid: placed at voxel 2 x 3 x 5 "
                    "by its origin")


def test_a_nifti_crop_with_a_ras_affine_is_placed(full, tmp_path):
    scan, mask = full
    affine = np.array([[-0.5, 0, 0, 40.0], [0, -0.5, 0, 12.0], [0, 0, 0.8, -3.0], [0, 0, 0, 1]])
    lo = np.array([1, 2, 4])  # array order; NIfTI's (i, j, k) are array axes 2, 1, 0
    crop = mask[lo[0]:, lo[1]:, lo[2]:]
    crop_affine = affine.copy()
    crop_affine[:3, 3] = affine[:3, :3] @ lo[::-1] + affine[:3, 3]
    for data, aff, name in ((scan, affine, "scan.nii.gz"), (crop, crop_affine, "crop.nii.gz")):
        nib.save(nib.Nifti1Image(np.ascontiguousarray(data.transpose(2, 1, 0)), aff), tmp_path / name)
    placed, note = place_on_grid(open_volume(tmp_path / "crop.nii.gz"), open_volume(tmp_path / "scan.nii.gz"))
    np.testing.assert_array_equal(np.asarray(placed.data), mask)
    assert "placed at voxel 1 x 2 x 4" in note


def test_a_box_reaching_beyond_the_scan_with_nothing_there_is_cut_to_it(full, tmp_path):
    scan, mask = full
    d = DIRECTIONS["plain"]
    big = np.zeros((SHAPE[0] + 4, SHAPE[1] + 2, SHAPE[2]), np.uint8)
    big[2:2 + SHAPE[0], :SHAPE[1], :] = mask  # the box starts 2 voxels before the scan along axis0
    s = open_volume(_nrrd(tmp_path / "scan.nrrd", scan, d, (0, 0, 0)))
    m = open_volume(_nrrd(tmp_path / "big.nrrd", big, d, np.array([0, 0, -2]) @ d))
    placed, note = place_on_grid(m, s)
    np.testing.assert_array_equal(np.asarray(placed.data), mask)
    assert "placed at voxel -2 x 0 x 0" in note


def test_a_mask_of_the_scans_shape_is_taken_voxel_for_voxel(full, tmp_path):
    scan, mask = full
    s = open_volume(_nrrd(tmp_path / "scan.nrrd", scan, DIRECTIONS["plain"], (0, 0, 0)))
    m = open_volume(_nrrd(tmp_path / "m.nrrd", mask, np.diag([1.0, 1, 1]), (9, 9, 9)))
    placed, note = place_on_grid(m, s)
    np.testing.assert_array_equal(np.asarray(placed.data), mask)
    assert placed.spacing == s.spacing and placed.origin == s.origin
    assert note.startswith("the mask m.nrrd's spacing 1 x 1 x 1 / origin 9 x 9 x 9 differ from the scan's")
    assert place_on_grid(open_volume(tmp_path / "scan.nrrd"), s)[1] is None


def test_masks_off_the_scans_grid_are_refused_saying_why(full, tmp_path):
    scan, mask = full
    d = DIRECTIONS["plain"]
    s = open_volume(_nrrd(tmp_path / "scan.nrrd", scan, d, (0, 0, 0)))
    crop = mask[2:12, 3:14, 5:16]

    def refused(m, words):
        with pytest.raises(InvalidInputError, match=words) as exc:
            place_on_grid(m, s)
        assert "\n" not in str(exc.value) and str(tmp_path) not in str(exc.value)

    # a quarter of a voxel off along x (array axis 2)
    refused(open_volume(_nrrd(tmp_path / "half.nrrd", crop, d, np.array([5.25, 3, 2]) @ d)),
            r"origin lies 0 x 0 x 0\.25 voxels off the scan's grid: resample")
    # another voxel size
    refused(open_volume(_nrrd(tmp_path / "other.nrrd", crop, 1.5 * d, (0, 0, 0))), "voxel size .* resample the mask")
    # a mask at a coarser level of the scan (unwind select without --full-resolution): how to refine it
    refused(open_volume(_nrrd(tmp_path / "coarse.nrrd", crop, 2 * d, (0, 0, 0))),
            r"voxel size .* refine it at the scan's resolution \(unwind select ... --full-resolution SCAN\)")
    # another orientation (the scan plain, the crop flipped), both NRRD
    refused(open_volume(_nrrd(tmp_path / "flip.nrrd", crop, DIRECTIONS["flipped"], (0, 0, 0))),
            "another orientation than the scan")
    # the box moved so that labelled voxels fall beyond the scan
    refused(open_volume(_nrrd(tmp_path / "out.nrrd", crop, d, np.array([12, 3, 2]) @ d)),
            r"voxels of the mask out\.nrrd lie beyond the scan")
    refused(open_volume(_nrrd(tmp_path / "far.nrrd", crop, d, np.array([100, 3, 2]) @ d)), "lies outside the scan")
    # the scan's shape reversed: written in the other axis order (pynrrd's default index_order 'F')
    refused(open_volume(_nrrd(tmp_path / "flipped_axes.nrrd", mask.transpose(2, 1, 0), d[::-1, ::-1], (0, 0, 0))),
            r"has shape 19 x 17 x 14, the scan's 14 x 17 x 19 reversed: its axes were written in the other order")
    # a TIFF states no origin: a crop of it cannot be placed
    tifffile.imwrite(tmp_path / "crop.tif", crop)
    refused(open_volume(tmp_path / "crop.tif"), "does not say where it lies in the scan")
