"""Volume and its checks (io/_volume.py), each value written out by hand."""

from __future__ import annotations

import pickle
import re

import dask.array as da
import numpy as np
import pytest

from napari_unwind.errors import InvalidInputError
from napari_unwind.io._volume import SUPPORTED_DTYPES, LazyArray, Volume, check_origin, check_spacing, warn_bad_spacing


def test_check_spacing_broadcasts_and_returns_plain_floats():
    assert check_spacing(2) == (2.0, 2.0, 2.0)
    assert check_spacing([1, 2.5, 3]) == (1.0, 2.5, 3.0)
    assert check_spacing((0.5, 4), ndim=2) == (0.5, 4.0)
    assert check_spacing(7, ndim=1) == (7.0,)
    assert all(type(v) is float for v in check_spacing(np.array([1, 2, 3], dtype=np.int16)))
    assert check_spacing(1e-300) == (1e-300,) * 3  # tiny but positive


@pytest.mark.parametrize("bad", [(1, 2), "abc", (1, 2, 3, 4), [[1, 2, 3], [4, 5, 6]]])
def test_check_spacing_refuses_the_wrong_count_or_text_and_names_it(bad):
    with pytest.raises(InvalidInputError) as info:
        check_spacing(bad)
    assert str(info.value) == (
        f"spacing must be 3 positive numbers in array axis order (axis0, axis1, axis2), got {bad!r}")


def test_check_spacing_wrong_count_names_ndim():
    with pytest.raises(InvalidInputError, match=re.escape("spacing must be 2 positive numbers")):
        check_spacing((1, 2, 3), ndim=2)


@pytest.mark.parametrize("bad", [(1, 0, 1), (1, -2, 1), (np.inf, 1, 1), (1, 1, np.nan), (-np.inf, 1, 1), 0])
def test_check_spacing_refuses_zero_negative_and_non_finite(bad):
    values = tuple(float(v) for v in np.broadcast_to(np.asarray(bad, dtype=float), (3,)))
    with pytest.raises(InvalidInputError) as info:
        check_spacing(bad)
    assert str(info.value) == f"spacing must be finite and positive, got {values}"


def test_check_origin_allows_zero_and_negative_and_broadcasts():
    assert check_origin(0) == (0.0, 0.0, 0.0)
    assert check_origin((-1.5, 0, 2)) == (-1.5, 0.0, 2.0)
    assert check_origin((3, -4), ndim=2) == (3.0, -4.0)
    assert all(type(v) is float for v in check_origin(np.array([1, 2, 3], dtype=np.int8)))


@pytest.mark.parametrize("bad", [(1, 2), "abc", (1, 2, 3, 4), 10**400])
def test_check_origin_refuses_the_wrong_count_text_and_overflow_and_names_it(bad):
    with pytest.raises(InvalidInputError) as info:
        check_origin(bad)
    assert str(info.value) == f"origin must be 3 numbers in array axis order (axis0, axis1, axis2), got {bad!r}"


def test_check_origin_wrong_count_names_ndim():
    with pytest.raises(InvalidInputError, match=re.escape("origin must be 4 numbers")):
        check_origin((1, 2, 3), ndim=4)


@pytest.mark.parametrize("bad", [(0, np.inf, 0), (np.nan, 0, 0), (0, 0, -np.inf)])
def test_check_origin_refuses_non_finite(bad):
    values = tuple(float(v) for v in bad)
    with pytest.raises(InvalidInputError) as info:
        check_origin(bad)
    assert str(info.value) == f"origin must be finite numbers, got {values}"


def test_a_numpy_volume_becomes_dask_with_the_defaults():
    arr = np.arange(24, dtype=np.uint16).reshape(2, 3, 4)
    vol = Volume(arr)
    assert isinstance(vol.data, da.Array)
    np.testing.assert_array_equal(vol.data.compute(), arr)
    assert vol.shape == (2, 3, 4) and vol.dtype == np.uint16
    assert vol.spacing == (1.0, 1.0, 1.0) and vol.origin == (0.0, 0.0, 0.0) and vol.unit is None
    assert vol.levels[0] is vol.data and len(vol.levels) == 1
    assert vol.level_spacings == ((1.0, 1.0, 1.0),) and vol.level_origins == ((0.0, 0.0, 0.0),)
    assert vol.level_shapes == ((2, 3, 4),)
    assert vol.nbytes == 24 * 2
    assert vol.unit_abbreviation == "voxels"
    assert vol.source is None and vol.format is None and vol.metadata == {}
    # a list of lists is data too
    assert Volume([[[1.0, 2.0]]]).shape == (1, 1, 2)


def test_a_dask_volume_is_kept_as_it_is_and_the_geometry_normalised():
    arr = da.zeros((4, 5, 6), dtype=np.float32, chunks=(2, 5, 3))
    vol = Volume(arr, spacing=2, origin=[1, 2, 3], unit=" MM ")
    assert vol.data is arr
    assert vol.spacing == (2.0, 2.0, 2.0) and vol.origin == (1.0, 2.0, 3.0) and vol.unit == "millimeter"
    assert vol.level_spacings == ((2.0, 2.0, 2.0),) and vol.level_origins == ((1.0, 2.0, 3.0),)
    assert vol.level_chunks == (((2, 2), (5,), (3, 3)),)
    assert vol.unit_abbreviation == "mm"
    assert vol.nbytes == 4 * 5 * 6 * 4
    assert repr(vol) == ("Volume(shape=(4, 5, 6), dtype=float32, spacing=(2.0, 2.0, 2.0), unit='millimeter', "
                         "levels=1, format=None, source=None)")


@pytest.mark.parametrize("shape", [(3, 4), (2, 3, 4, 5), (5,)])
def test_a_volume_must_be_3d(shape):
    with pytest.raises(InvalidInputError) as info:
        Volume(np.zeros(shape, dtype=np.uint8))
    assert str(info.value) == f"a volume must be 3D (axis0, axis1, axis2), got shape {shape}"


@pytest.mark.parametrize("shape", [(0, 3, 4), (2, 0, 4), (2, 3, 0)])
def test_a_volume_must_not_be_empty(shape):
    with pytest.raises(InvalidInputError) as info:
        Volume(np.zeros(shape, dtype=np.uint8))
    assert str(info.value) == f"a volume must not have a dimension of size 0, got shape {shape}"


@pytest.mark.parametrize("dtype", ["bool", "int64", "uint64", "complex64", "float16"])
def test_unsupported_voxel_types_are_refused_with_the_list(dtype):
    supported = "uint8, int8, uint16, int16, uint32, int32, float32, float64"
    with pytest.raises(InvalidInputError) as info:
        Volume(np.zeros((2, 2, 2), dtype=dtype))
    assert str(info.value) == (f"unsupported voxel type {np.dtype(dtype)}; supported are {supported}"
                               " (convert colour images to grey first)")


@pytest.mark.parametrize("dtype", SUPPORTED_DTYPES)
def test_every_supported_voxel_type_is_accepted(dtype):
    assert Volume(np.zeros((1, 1, 1), dtype=dtype)).dtype == dtype


def test_bad_spacing_origin_and_unit_are_refused():
    data = np.zeros((2, 2, 2), np.uint8)
    with pytest.raises(InvalidInputError, match="spacing must be finite and positive"):
        Volume(data, spacing=(1, 0, 1))
    with pytest.raises(InvalidInputError, match="origin must be finite"):
        Volume(data, origin=(0, np.inf, 0))
    with pytest.raises(InvalidInputError, match="unknown length unit"):
        Volume(data, unit="parsec")


def _pyramid():
    l0 = da.arange(8 * 8 * 8, dtype=np.uint16, chunks=4).reshape(8, 8, 8)
    l1 = l0[::2, ::2, ::2]
    l2 = l0[::4, ::4, ::4]
    return l0, l1, l2


def test_levels_need_one_spacing_and_one_origin_each():
    l0, l1, l2 = _pyramid()
    sp = ((1.0, 1, 1), (2.0, 2, 2), (4.0, 4, 4))
    with pytest.raises(InvalidInputError) as info:
        Volume(l0, levels=(l0, l1, l2), level_spacings=sp[:2])
    assert str(info.value) == "a Volume needs one spacing per pyramid level"
    with pytest.raises(InvalidInputError) as info:
        Volume(l0, levels=(l0, l1, l2), level_spacings=sp, level_origins=((0, 0, 0),) * 2)
    assert str(info.value) == "a Volume needs one origin per pyramid level"
    # without origins, every level gets the volume's own; given ones are broadcast to 3 floats
    vol = Volume(l0, origin=(1, 2, 3), levels=(l0, l1, l2), level_spacings=sp)
    assert vol.level_origins == ((1.0, 2.0, 3.0),) * 3
    vol = Volume(l0, levels=(l0, l1, l2), level_spacings=sp, level_origins=(0, 0.5, [1.5, 2, 2.5]))
    assert vol.level_origins == ((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), (1.5, 2.0, 2.5))
    assert all(type(v) is float for lo in vol.level_origins for v in lo)
    assert vol.level_spacings == sp and vol.spacing == (1.0, 1.0, 1.0)
    assert vol.level_shapes == ((8, 8, 8), (4, 4, 4), (2, 2, 2))
    assert vol.levels == (l0, l1, l2)


def _pyramid_volume():
    l0, l1, l2 = _pyramid()
    return Volume(l0, spacing=(1, 1, 1), origin=(10, 20, 30), unit="um", levels=(l0, l1, l2),
                  level_spacings=((1.0, 1.0, 1.0), (2.0, 2.0, 2.0), (4.0, 4.0, 4.0)),
                  level_origins=((10, 20, 30), (10.5, 20.5, 30.5), (11.5, 21.5, 31.5)),
                  source="scan.zarr", format="ome-zarr", metadata={"k": 1})


def test_level_for_picks_the_finest_level_that_fits():
    vol = _pyramid_volume()
    assert vol.level_for(8) == 0
    assert vol.level_for(100) == 0
    assert vol.level_for(7) == 1
    assert vol.level_for(4) == 1
    assert vol.level_for(3) == 2
    assert vol.level_for(2) == 2
    assert vol.level_for(1) == 2  # none fits: the coarsest
    assert vol.level_for() == 0  # 8 <= 256
    assert Volume(da.zeros((257, 1, 1), dtype=np.uint8)).level_for() == 0  # one level: that one


def test_level_is_a_single_level_volume_with_its_own_geometry():
    vol = _pyramid_volume()
    one = vol.level(1)
    assert one.data is vol.levels[1]
    assert one.spacing == (2.0, 2.0, 2.0) and one.origin == (10.5, 20.5, 30.5)
    assert one.levels == (one.data,) and one.level_spacings == ((2.0,) * 3,)
    assert one.level_origins == ((10.5, 20.5, 30.5),)
    assert one.unit == "micrometer" and one.source == "scan.zarr" and one.format == "ome-zarr"
    assert vol.level(np.int64(2)).origin == (11.5, 21.5, 31.5)
    assert vol.level(0).spacing == (1.0, 1.0, 1.0) and vol.level(0).data is vol.data
    for bad in (3, -1, 10):
        with pytest.raises(InvalidInputError) as info:
            vol.level(bad)
        assert str(info.value) == f"scan.zarr has pyramid levels 0..2, got level {bad}"
    with pytest.raises(InvalidInputError) as info:
        Volume(np.zeros((1, 1, 1), np.uint8)).level(1)
    assert str(info.value) == "the volume has pyramid levels 0..0, got level 1"


def test_with_data_of_a_level_keeps_that_levels_geometry_unless_given():
    vol = _pyramid_volume()
    for i in (1, 2):
        out = vol.with_data(vol.levels[i])
        assert out.data is vol.levels[i]
        assert out.spacing == vol.level_spacings[i] and out.origin == vol.level_origins[i]
        assert out.levels == (out.data,) and out.level_spacings == (out.spacing,)
        assert out.level_origins == (out.origin,)
        assert out.unit == "micrometer" and out.source == "scan.zarr" and out.metadata == {"k": 1}
    out = vol.with_data(vol.levels[2], spacing=(3, 3, 3), origin=(0, 0, 0))
    assert out.spacing == (3.0, 3.0, 3.0) and out.origin == (0.0, 0.0, 0.0)
    out = vol.with_data(vol.levels[1], origin=(-1, -1, -1))
    assert out.spacing == (2.0, 2.0, 2.0) and out.origin == (-1.0, -1.0, -1.0)


def test_with_data_of_other_voxels_keeps_the_volumes_geometry_and_drops_the_pyramid():
    vol = _pyramid_volume()
    other = da.ones((8, 8, 8), dtype=np.float32, chunks=8)
    out = vol.with_data(other)
    assert out.data is other and out.spacing == (1.0, 1.0, 1.0) and out.origin == (10.0, 20.0, 30.0)
    assert out.levels == (other,) and len(out.level_shapes) == 1
    # level 0 is the volume's own data: its geometry is the volume's
    same = vol.with_data(vol.levels[0])
    assert same.origin == (10.0, 20.0, 30.0) and same.levels == (vol.data,)
    # a level equal in value but not the same array is other voxels
    copy = vol.levels[1] + 0
    assert vol.with_data(copy).origin == (10.0, 20.0, 30.0)
    # levels given with the data are kept
    l0, l1, _ = _pyramid()
    kept = vol.with_data(l0, levels=(l0, l1), level_spacings=((1,) * 3, (2,) * 3))
    assert kept.levels == (l0, l1) and kept.level_origins == ((10.0, 20.0, 30.0),) * 2


def test_a_lazy_array_is_built_once_and_only_when_the_voxels_are_read():
    calls = []
    arr = da.arange(2 * 3 * 5, dtype=np.int16, chunks=2).reshape(2, 3, 5).rechunk((2, 2, 2))

    def build():
        calls.append(1)
        return arr

    lazy = LazyArray(build, (2, 3, 5), "int16", (2, 2, 2))
    assert lazy.shape == (2, 3, 5) and lazy.dtype == np.int16 and lazy.ndim == 3
    assert lazy.chunks == ((2,), (2, 1), (2, 2, 1))
    assert repr(lazy) == "LazyArray(shape=(2, 3, 5), dtype=int16, chunks=((2,), (2, 1), (2, 2, 1)))"
    vol = Volume(lazy, spacing=(1, 2, 3))
    # the header's facts, without building
    assert vol.shape == (2, 3, 5) and vol.dtype == np.int16 and vol.nbytes == 60
    assert vol.level_shapes == ((2, 3, 5),) and vol.level_chunks == (((2,), (2, 1), (2, 2, 1)),)
    assert not calls
    assert vol.data is arr and calls
    assert len(calls) == 1  # data and levels[0] are the same LazyArray: built once (it was built twice)
    assert vol.levels == (arr,) and vol.levels[0] is vol.data and vol.data is arr and len(calls) == 1
    # a pickled volume carries the dask arrays, not the builder (a lambda, which pickle refuses)
    vol2 = Volume(LazyArray(lambda: arr, (2, 3, 5), np.int16, (2, 2, 2)), spacing=(1, 2, 3))
    back = pickle.loads(pickle.dumps(vol2))
    np.testing.assert_array_equal(back.data.compute(), arr.compute())
    assert back.spacing == (1.0, 2.0, 3.0) and back.levels[0] is back.data


def test_a_lazy_level_among_built_ones_is_built_on_reading_levels():
    l0, l1, _ = _pyramid()
    calls = []

    def build():
        calls.append(1)
        return l1

    lazy1 = LazyArray(build, (4, 4, 4), np.uint16, (4, 4, 4))
    vol = Volume(l0, levels=(l0, lazy1), level_spacings=((1,) * 3, (2,) * 3))
    assert vol.level_shapes == ((8, 8, 8), (4, 4, 4)) and not calls
    assert vol.levels == (l0, l1) and calls == [1]
    assert vol.data is l0


def test_warn_bad_spacing_names_the_file_axis_and_value():
    with pytest.warns(UserWarning) as rec:
        warn_bad_spacing("/some/dir/scan.nrrd", 2, -0.5)
    assert str(rec[0].message) == (
        "scan.nrrd declares a voxel size of -0.5 along axis2, which is not a positive number: it is read as 1; give "
        "the real spacing (--spacing A0,A1,A2, or spacing= in Python) or fix the file's header")
