"""The Python API of straightening against hostile input (issue 9): paths, lists, text, wrong shapes, units,
deformations outside the scan, runaway output sizes, full disks.

Every refusal is an :class:`~napari_unwind.errors.UnwindError` whose message holds the received value; sizes and
fractions are checked against numbers computed here, independently of the code under test.
"""

from __future__ import annotations

import math
import re
import shutil
import time
import tracemalloc
import warnings
from collections import namedtuple
from pathlib import Path

import dask.array as da
import numpy as np
import pytest
from scipy import ndimage as ndi
from test_warp import reference_coords

from napari_unwind.deformation import Deformation
from napari_unwind.errors import InvalidInputError, OutputError
from napari_unwind.io import Volume, open_volume, write_volume
from napari_unwind.warp import (
    DEFAULT_MAX_OUTPUT,
    OutsideWarning,
    bend,
    export,
    map_labels,
    map_mesh,
    map_points,
    straighten,
)

SHAPE = (20, 22, 24)


def rod(c0=10.0, c1=11.0, z=(3.0, 20.0), cage=(4.0, 3.0), unit="micrometer", spacing=1.0, origin=0.0, angle=0.0):
    """A straight rod along axis2 at (c0, c1); frames u = axis0, v = axis1 turned by ``angle`` about n = axis2."""
    ca, sa = math.cos(angle), math.sin(angle)
    frame = np.array([[ca, sa, 0.0], [-sa, ca, 0.0], [0.0, 0.0, 1.0]])
    pos = np.array([[c0, c1, z[0]], [c0, c1, z[1]]])
    sp = np.broadcast_to(np.asarray(spacing, float), (3,))
    org = np.broadcast_to(np.asarray(origin, float), (3,))
    return Deformation.from_keyframes(pos * sp + org, np.stack([frame, frame]), cage, spacing=tuple(sp),
                                      origin=tuple(org), unit=unit)


def scan(dtype=np.float32, seed=0):
    return np.random.default_rng(seed).random(SHAPE).astype(dtype)


def independent_shape(d: Deformation, ds: float, pad_slices: int = 0) -> tuple[int, int, int]:
    """The straight grid's shape from its definition (module docstring of napari_unwind.warp)."""
    lo, hi = -d.pad[0] - pad_slices * ds, d.length + d.pad[1] + pad_slices * ds
    rx, ry = d.max_half_extent
    return (int(np.floor((hi - lo) / ds + 1e-9)) + 1, 2 * int(np.ceil(ry / ds - 1e-9)) + 1,
            2 * int(np.ceil(rx / ds - 1e-9)) + 1)


def outside_fraction(d: Deformation, ds: float, shape) -> float:
    """Fraction of output voxels sampling outside the scan (scipy 'constant' rule: 0 <= c <= n - 1)."""
    c = reference_coords(d, ds)
    ok = np.ones(c.shape[1:], bool)
    for ax in range(3):
        ok &= (c[ax] >= 0) & (c[ax] <= shape[ax] - 1)
    return 1.0 - ok.mean()


# ------------------------------------------------------------------------------------------------------------------
# 1. what the API accepts: paths, nested lists, text, 2D arrays, units
# ------------------------------------------------------------------------------------------------------------------
def test_a_path_is_opened_like_open_volume(tmp_path):
    vol = scan()
    d = rod()
    path = write_volume(vol, tmp_path / "scan.zarr", spacing=1.0, unit="micrometer")
    expected = straighten(open_volume(path), d).data.compute()
    for given in (str(path), path):
        got = straighten(given, d)
        np.testing.assert_array_equal(got.data.compute(), expected)
        assert got.unit == "micrometer" and got.source is not None
    out = export(str(path), d, tmp_path / "straight.zarr")
    np.testing.assert_array_equal(open_volume(out).data.compute(), expected)
    # bend reads a straight volume from a path too (its pad and spacing from the file)
    bent = bend(str(out), d, shape=SHAPE).compute()
    ref = bend(open_volume(out), d, shape=SHAPE).compute()
    np.testing.assert_array_equal(bent, ref)
    with pytest.raises(FileNotFoundError, match="missing.zarr"):
        straighten(str(tmp_path / "missing.zarr"), d)


def test_a_nested_list_of_numbers_is_an_array():
    d = rod()
    ints = np.random.default_rng(1).integers(0, 1000, SHAPE)
    got = straighten(ints.tolist(), d)  # Python ints: np.asarray makes int64, which a Volume cannot hold
    assert got.dtype == np.int32
    ref = ndi.map_coordinates(ints.astype(np.float64), reference_coords(d, 1.0), order=1, mode="constant")
    assert np.abs(got.data.compute() - ref).max() <= 0.5 + 1e-9
    floats = scan(np.float64)
    np.testing.assert_allclose(straighten(floats.tolist(), d).data.compute(),
                               ndi.map_coordinates(floats, reference_coords(d, 1.0), order=1, mode="constant"),
                               atol=1e-9)
    big = ints.tolist()
    big[0][0][0] = 2**40  # does not fit int32: say so instead of "unsupported voxel type int64"
    with pytest.raises(InvalidInputError, match=r"int64.*2\*\*31|int64.*int32"):
        straighten(big, d)
    with pytest.raises(InvalidInputError, match=r"int64.*astype"):
        straighten(ints.astype(np.int64), d)  # an int64 array: name the type and what to use
    with pytest.raises(InvalidInputError, match="nested list"):
        straighten([[[1, 2], [3]], [[4, 5], [6, 7]]], d)  # ragged
    with pytest.raises(InvalidInputError, match="3D.*shape \\(2,\\)"):
        straighten([1, 2], d)


def test_map_points_with_text_names_what_it_got():
    d = rod()
    for bad, shown in (("abc", "'abc'"), ([["a", "b", "c"]], "'a'"), ([[1, 2, None]], "None")):
        with pytest.raises(InvalidInputError, match=re.escape(shown)):
            map_points(bad, d)
        with pytest.raises(InvalidInputError, match=re.escape(shown)):
            map_mesh(bad, [[0, 0, 0]], d)
    with pytest.raises(InvalidInputError, match="'x'"):
        map_mesh([[10, 11, 5]] * 3, [["x", 1, 2]], d)


def test_bend_of_a_2d_array_says_3d_with_its_shape():
    d = rod()
    straight = straighten(scan(), d).data.compute()
    with pytest.raises(InvalidInputError, match=r"3D.*got shape \(7, 9\)"):
        bend(straight[0], d)
    with pytest.raises(InvalidInputError, match=r"3D.*got shape \(7, 9\)"):
        bend(straight[0], d, shape=SHAPE)
    with pytest.raises(InvalidInputError, match="shape="):
        bend(straight, d)  # the scan's shape is not in the deformation: say what to pass


def test_a_volume_in_another_length_unit_is_converted():
    """Documented rule: both units known -> the volume's geometry is converted to the deformation's unit; if it
    then agrees the straightening proceeds in the deformation's unit, else it is refused naming both units."""
    vol = scan()
    d = rod(unit="micrometer", spacing=(2.0, 1.0, 1.0), origin=(5.0, -3.0, 0.0))
    in_mm = Volume(da.from_array(vol, chunks=8), spacing=(0.002, 0.001, 0.001), origin=(0.005, -0.003, 0.0),
                   unit="mm")
    got = straighten(in_mm, d)
    same = straighten(Volume(da.from_array(vol), spacing=(2.0, 1.0, 1.0), origin=(5.0, -3.0, 0.0), unit="um"), d)
    assert got.unit == "micrometer" and got.spacing == (1.0, 1.0, 1.0)  # the deformation's unit and ds
    np.testing.assert_array_equal(got.data.compute(), same.data.compute())
    # the same numbers in the wrong unit: refused, both units named
    mislabelled = Volume(da.from_array(vol), spacing=(2.0, 1.0, 1.0), origin=(5.0, -3.0, 0.0), unit="mm")
    with pytest.raises(InvalidInputError, match=r"millimeter.*micrometer"):
        straighten(mislabelled, d)
    # a straight volume written in mm bends back with the deformation in micrometres
    st = straighten(vol, d)
    st_mm = Volume(st.data, spacing=(0.001,) * 3, origin=tuple(o / 1000 for o in st.origin), unit="mm")
    np.testing.assert_array_equal(bend(st_mm, d, shape=SHAPE).compute(), bend(st, d, shape=SHAPE).compute())


# ------------------------------------------------------------------------------------------------------------------
# 2. deformations outside the scan
# ------------------------------------------------------------------------------------------------------------------
def test_a_deformation_entirely_outside_the_scan_is_an_error(tmp_path):
    d = rod(c0=1010.0, c1=1011.0)  # every keyframe moved 1000 voxels
    with pytest.raises(InvalidInputError, match=r"outside the scan.*\b1006\b.*\b1014\b.*0\.\.19, 0\.\.21, 0\.\.23"):
        straighten(scan(), d)
    with pytest.raises(InvalidInputError, match="outside the scan"):
        export(scan(), d, tmp_path / "out.tif")
    with pytest.raises(InvalidInputError, match="outside the scan"):
        map_labels(scan(np.uint8), d)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("c0, warns", [(19.5, True), (16.0, False)])
def test_a_deformation_mostly_outside_warns_with_the_fraction(c0, warns):
    d = rod(c0=c0, angle=0.4, z=(3.0, 26.5))  # the cage pokes out of axis0's far face obliquely, and out of axis2
    expected = outside_fraction(d, 1.0, SHAPE)
    assert (expected > 0.5) == warns and 0.05 < expected < 0.95
    reads = []
    data = da.from_array(scan(), chunks=8).map_blocks(lambda b: reads.append(1) or b, dtype=np.float32,
                                                      meta=np.empty((0, 0, 0), np.float32))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        straighten(data, d)
    assert reads == [], "the fraction comes from the slice geometry, not from computing the output"
    found = [w for w in caught if issubclass(w.category, OutsideWarning)]
    assert len(found) == int(warns)
    if warns:
        assert issubclass(OutsideWarning, UserWarning)
        pct = float(re.search(r"([\d.]+) % of", str(found[0].message)).group(1))
        assert pct == pytest.approx(100 * expected, abs=0.06)


# ------------------------------------------------------------------------------------------------------------------
# 3. runaway sizes, checked before anything proportional to the output is allocated
# ------------------------------------------------------------------------------------------------------------------
Case = namedtuple("Case", "kwargs d ds pad")
BIG = (60.0, 40.0)  # a cage like a large specimen's: these runaway cases then exceed DEFAULT_MAX_OUTPUT


@pytest.mark.parametrize("case", [
    Case({"spacing": 1e-6}, rod(cage=BIG), 1e-6, 0),
    Case({"spacing": 0.01}, rod(cage=BIG), 0.01, 0),
    Case({"pad": 100_000_000}, rod(cage=BIG), 1.0, 100_000_000),
    Case({}, rod(cage=BIG).with_pad(1e7, 0.0), 1.0, 0),
], ids=["spacing-1e-6", "spacing-0.01", "pad-1e8", "deformation-pad-1e7"])
def test_runaway_outputs_are_refused_with_the_numbers_before_any_allocation(case, tmp_path):
    shape = independent_shape(case.d, case.ds, case.pad)
    voxels = math.prod(shape)
    nbytes = voxels * 4
    assert nbytes > DEFAULT_MAX_OUTPUT
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(InvalidInputError) as err:
            straighten(scan(), case.d, **case.kwargs)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 5 and peak < 20 * 2**20, peak
    msg = str(err.value)
    assert "\n" not in msg
    for part in (str(shape), f"{voxels:,} voxels", f"{nbytes:,} bytes", f"{DEFAULT_MAX_OUTPUT:,}", "max_output=",
                 "--max-output"):
        assert part in msg, (part, msg)
    with pytest.raises(InvalidInputError, match="max_output"):
        export(scan(), case.d, tmp_path / "out.zarr", **case.kwargs)
    assert list(tmp_path.iterdir()) == []


def test_max_output_is_a_keyword_of_every_entry_point(tmp_path):
    d = rod()
    vol = scan()
    nbytes = math.prod(independent_shape(d, 1.0)) * 4
    with pytest.raises(InvalidInputError, match=f"{nbytes:,} bytes"):
        straighten(vol, d, max_output=nbytes - 1)
    assert straighten(vol, d, max_output=nbytes).shape == independent_shape(d, 1.0)
    assert straighten(vol, d, max_output=None).shape == independent_shape(d, 1.0)
    with pytest.raises(InvalidInputError, match="max_output"):
        export(vol, d, tmp_path / "a.tif", max_output=100)
    straight = straighten(vol, d)
    with pytest.raises(InvalidInputError, match=f"{math.prod(SHAPE) * 4:,} bytes"):
        bend(straight, d, shape=SHAPE, max_output=1000)
    with pytest.raises(InvalidInputError, match="max_output"):
        bend(straight, d, shape=(10**6,) * 3)  # default limit
    with pytest.raises(InvalidInputError, match="max_output"):
        map_labels(vol.astype(np.uint8), d, max_output=10)
    for bad in (-1, 0, "big", float("nan"), True):
        with pytest.raises(InvalidInputError, match=re.escape(repr(bad))):
            straighten(vol, d, max_output=bad)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), "fine", 1e-320])
def test_bad_spacing_is_refused_with_the_value(bad):
    with pytest.raises(InvalidInputError, match=re.escape(repr(bad)) if not isinstance(bad, float) or
                       math.isfinite(bad) else "spacing"):
        straighten(scan(), rod(), spacing=bad)


@pytest.mark.parametrize("bad", [-1, 1.5, float("nan"), float("inf"), 10**30, "2", True])
def test_bad_pad_is_refused_with_the_value(bad):
    with pytest.raises(InvalidInputError, match="pad.*" + re.escape(repr(bad))):
        straighten(scan(), rod(), pad=bad)


def test_a_whole_number_pad_given_as_a_float_is_accepted():
    assert straighten(scan(), rod(), pad=2.0).shape == independent_shape(rod(), 1.0, 2)


def test_export_checks_the_free_disk(tmp_path, monkeypatch):
    d = rod()
    nbytes = math.prod(independent_shape(d, 1.0)) * 4
    real = shutil.disk_usage
    asked = []

    def small(path):
        asked.append(Path(path))
        return real(path)._replace(free=nbytes // 2)

    monkeypatch.setattr(shutil, "disk_usage", small)
    with pytest.raises(OutputError, match=rf"{nbytes:,} bytes.*{nbytes // 2:,} bytes free"):
        export(scan(), d, tmp_path / "out.tif")
    assert asked and asked[-1] == tmp_path and list(tmp_path.iterdir()) == []
    # a compressed format may fit: a warning, and the export goes ahead
    with pytest.warns(UserWarning, match="free"):
        out = export(scan(), d, tmp_path / "out.zarr")
    assert out.exists()
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=10 * nbytes))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        export(scan(), d, tmp_path / "fits.tif")


@pytest.mark.parametrize("kwargs, d", [({"pad": 1_000_000}, rod()), ({}, rod().with_pad(0.0, 1e7))],
                         ids=["pad-1e6", "deformation-pad-1e7"])
def test_padding_absurdly_far_beyond_the_scan_is_refused(kwargs, d, tmp_path):
    """Small outputs (well under the limit) that are nearly all padding beyond the scan: refused up front."""
    assert math.prod(independent_shape(d, 1.0, kwargs.get("pad", 0))) * 4 < DEFAULT_MAX_OUTPUT
    tracemalloc.start()
    try:
        with pytest.raises(InvalidInputError, match=r"padding at the (head|tail) \((1e\+07|1e\+06) .*absurd"):
            straighten(scan(), d, **kwargs)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 20 * 2**20, peak
    with pytest.raises(InvalidInputError, match="absurd"):
        export(scan(), d, tmp_path / "out.zarr", **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_padding_a_little_beyond_the_scan_is_fine():
    # the rod ends 3 voxels inside axis2's faces; 30 slices of padding reach well past them (fill, no error)
    d = rod(z=(3.0, 20.0))
    with pytest.warns(OutsideWarning):
        out = straighten(scan(), d, pad=30, fill=-1.0).data.compute()
    ref = ndi.map_coordinates(scan(), reference_coords(d, 1.0, 30), order=1, mode="constant", cval=-1.0)
    np.testing.assert_allclose(out, ref, atol=1e-6)
    assert (out[:10] == -1).all() and (out[-10:] == -1).all()
