"""``bend`` closes the round trip for every straight file we write (issue 20, item 5).

scan -> straighten (pad > 0, spacing != the scan's) -> write in each output format -> read -> bend WITHOUT the pad
or the spacing -> the scan again inside the cage, within the error of two linear interpolations. Through the API
and through ``unwind straighten`` then ``unwind bend``. Also: bend refuses a session whose geometry contradicts its
scan (as straighten does), and writers refuse a spacing or origin their format cannot hold, before writing.

The scan is a smooth field (a sum of three sines), not the fish, so that linear interpolation has a known error
bound (see :func:`tolerance`); the deformation is the fish phantom's true, bent one.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from conftest import no_leftovers
from conftest import run_unwind as _run
from napari_unwind.deformation import Deformation
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import open_volume, write_volume
from napari_unwind.warp import bend, export, straighten

PAD = 3
DS = 1.7  # the straight spacing; the scan's is 1 (micrometre)
#: amplitude, offset and wavelength (voxels) of the smooth scan
A, OFFSET, WAVELENGTH = 9000.0, 30000.0, 16.0
K = 2 * math.pi / WAVELENGTH

#: every writer, by the name its suffix gives (a {} pattern: a folder of numbered slices)
OUTPUTS = {
    "ome-zarr": "straight.zarr",
    "tiff": "straight.tif",
    "nrrd": "straight.nrrd",
    "nhdr": "straight.nhdr",
    "nifti": "straight.nii",
    "nifti-gz": "straight.nii.gz",
    "raw": "straight.dat",
    "stack-tif": "slices_tif/s_{:03d}.tif",
    "stack-png": "slices_png/s_{:03d}.png",
    "dicom": "straight.dicom",
}


def smooth_scan(shape: tuple[int, int, int]) -> np.ndarray:
    """f(p) = OFFSET + A/3 (sin k p0 + sin k p1 + sin k p2), as uint16 (rounded)."""
    p = np.indices(shape, dtype=float)
    f = OFFSET + A / 3 * (np.sin(K * p[0]) + np.sin(K * p[1] + 1.0) + np.sin(K * p[2] + 2.0))
    return np.round(f).astype(np.uint16)


def tolerance(d: Deformation, ds: float) -> float:
    """Largest error of scan -> straight -> bent at a voxel deep inside the cage, from linear interpolation's bound.

    Trilinear interpolation on a grid of steps h_a errs by at most sum_a h_a**2 / 8 * max|d2g/da2| (the 1D bound
    (h**2 / 8) max|g''| applied axis by axis; each 1D pass is a convex combination, so it does not enlarge the error
    already there). Here f = OFFSET + A/3 sum_i sin(k p_i) on the scan's grid (h = 1 voxel = 1 um), so
    |d2f/dp_i2| <= A k**2 / 3, the Hessian H of f is diagonal with norm |H| <= A k**2 / 3, and
    |grad f| <= A k / sqrt(3).

    1. straighten samples f at exact positions: error e1 <= 3 * 1**2 / 8 * A k**2 / 3 = A k**2 / 8.
    2. bend interpolates the straight volume g = f o phi on its grid of step ds, at exactly inverted positions (the
       Newton tolerance is negligible), adding e1 at most (convexity) plus ds**2 / 8 * sum_a max|d2g/da2| over the
       straight axes a = x, y, s. Within a segment of the deformation phi(x, y, s) = c(s) + x u(s) + y v(s), with c
       linear in s (|c'| = 1) and the frame (u, v) turning at the segment's rate w: g_xx = u.H.u and g_yy = v.H.v
       are <= |H|; phi_s = c' + x u' + y v' has |phi_s| <= 1 + |w| r and |phi_ss| <= |w|**2 r (r: the cage's corner
       radius), so |g_ss| <= |H| (1 + |w| r)**2 + |grad f| |w|**2 r. In the padding phi is a translation (smaller).
    3. The two casts to uint16 (the scan, then the bent output; every format keeps uint16 exactly) add <= 0.5 each.

    For the fish's deformation at ds = 1.7 this gives 877 (9.7 % of A); every format measured a largest error of 625,
    and a straight spacing off by 3 % in bend gives 7799.
    """
    w = float(np.max(np.linalg.norm(d._segment_rates(), axis=1)))
    r = float(np.hypot(*d.max_half_extent)) + ds  # the straight grid reaches a little beyond the cage
    hess, grad = A * K**2 / 3, A * K / math.sqrt(3)
    e1 = A * K**2 / 8
    gss = hess * (1 + w * r) ** 2 + grad * w**2 * r
    e2 = ds**2 / 8 * (2 * hess + gss)
    return e1 + e2 + 1.0


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """The smooth scan on the fish phantom's grid as ``scan.zarr``, with a session of the fish's true deformation."""
    from napari_unwind.datasets import fish_phantom
    from napari_unwind.demo import true_deformation
    from napari_unwind.session import Session, SourceInfo, save_session

    tmp = tmp_path_factory.mktemp("bend_roundtrip")
    fish = fish_phantom(seed=2, noise=0.0, tube=False)
    x = smooth_scan(fish.shape)
    scan = write_volume(x, tmp / "scan.zarr", spacing=fish.spacing, unit=fish.unit)
    d = true_deformation(fish)
    session = save_session(Session(source=SourceInfo.from_path(scan), deformation=d), tmp / "scan.unwind.json")
    return tmp, x, scan, session, d


def _deep_voxels(x: np.ndarray, d2: Deformation, ds: float) -> tuple[np.ndarray, ...]:
    """Scan voxels (of a random sample of 40000) whose inverse image lies at least one straight step inside the
    padded cage and whose interpolation never reads outside the scan (independent: Deformation.inverse, not bend)."""
    margin = 1 + math.sqrt(3) * ds  # a straight voxel's neighbours are within sqrt(3) ds; theirs within 1 voxel
    idx = np.indices(x.shape).reshape(3, -1).T
    keep = np.all((idx >= margin) & (idx <= np.array(x.shape) - 1 - margin), axis=1)
    vox = idx[keep][np.random.default_rng(0).choice(int(keep.sum()), 40000, replace=False)].astype(float)
    inv = d2.inverse(d2.to_physical(vox))
    rx, ry = d2.max_half_extent
    s_lo, s_hi = d2.s_range
    deep = inv.inside & (np.abs(inv.xys[:, 0]) <= rx - ds) & (np.abs(inv.xys[:, 1]) <= ry - ds) \
        & (inv.xys[:, 2] >= s_lo + ds) & (inv.xys[:, 2] <= s_hi - ds)
    return tuple(vox[deep].astype(int).T)


@pytest.fixture(scope="module")
def reference(case):
    """The padded deformation straighten used, the deep voxels and the tolerance."""
    _, x, scan, _, d = case
    straight = straighten(open_volume(scan), d, spacing=DS, pad=PAD)
    d2 = Deformation.from_dict(straight.metadata["deformation"])
    deep = _deep_voxels(x, d2, DS)
    assert len(deep[0]) > 3000  # a test of something
    return d2, deep, tolerance(d2, DS)


def _check(bent: np.ndarray, x: np.ndarray, deep: tuple, tol: float) -> float:
    assert bent.shape == x.shape and bent.dtype == x.dtype
    err = np.abs(bent[deep].astype(float) - x[deep].astype(float))
    assert err.max() <= tol, (err.max(), tol)
    return float(err.max())


@pytest.mark.parametrize("name", list(OUTPUTS))
def test_bend_reads_back_what_straighten_wrote_in_every_format(case, reference, name):
    tmp, x, scan, _, d = case
    d2, deep, tol = reference
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # lossless formats only; nothing to warn about that matters here
        folder = tmp / "api" / name
        folder.mkdir(parents=True)
        written = export(open_volume(scan), d, folder / OUTPUTS[name], spacing=DS, pad=PAD)
    back = open_volume(written)
    assert back.metadata["unwind"]["straightening"]["pad"] == PAD
    bent = bend(back, d, shape=x.shape).compute()  # neither pad nor spacing given: both from the file
    _check(bent, x, deep, tol)


@pytest.mark.slow  # two `unwind` processes per format, ~20 s each on a shared machine
@pytest.mark.parametrize("name", ["tiff", "nifti-gz", "raw", "stack-png", "dicom"])  # OME-Zarr: test_cli_warp
def test_unwind_bend_reads_back_what_unwind_straighten_wrote(case, reference, name):
    tmp, x, scan, session, _ = case
    _, deep, tol = reference
    folder = tmp / "cli" / name
    folder.mkdir(parents=True)
    straight = folder / OUTPUTS[name]
    code, _, err = _run("straighten", scan, "--session", session, "-o", straight, "--pad", PAD, "--spacing", DS,
                        "-q")
    assert code == 0, err
    if "{" in straight.name:
        straight = straight.parent
    bent_path = folder / "bent.zarr"
    code, _, err = _run("bend", straight, "--session", session, "-o", bent_path, "-q")
    assert code == 0, err
    bent = open_volume(bent_path)
    assert bent.spacing == (1.0, 1.0, 1.0) and bent.origin == (0.0, 0.0, 0.0) and bent.unit == "micrometer"
    _check(bent.data.compute(), x, deep, tol)


@pytest.mark.parametrize("change", ["spacing", "origin"])
def test_unwind_bend_refuses_a_session_whose_geometry_contradicts_its_scan(case, tmp_path, change):
    from napari_unwind.session import load_session, save_session

    tmp, _, scan, session_path, d = case
    straight = tmp / "for_refusal.nrrd"
    if not straight.exists():
        export(open_volume(scan), d, straight, spacing=DS, pad=PAD)
    session = load_session(session_path)
    spec = d.to_dict()
    spec[change] = [1.5, 1.0, 1.0] if change == "spacing" else [4.0, 0.0, 0.0]
    session.deformation = Deformation.from_dict(spec)
    wrong = save_session(session, tmp_path / "wrong.unwind.json")
    code, _, err = _run("straighten", scan, "--session", wrong, "-o", tmp_path / "s.zarr", "-q")
    assert code == 1 and "differs from the deformation's" in err
    code, _, err = _run("bend", straight, "--session", wrong, "-o", tmp_path / "bent.zarr", "-q")
    assert code == 1, err
    assert "the volume's geometry" in err and "differs from the deformation's" in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "bent.zarr").exists() and no_leftovers(tmp_path) == []


@pytest.mark.parametrize("suffix,spacing,origin,match", [
    (".nii", (1e-320, 1, 1), (0, 0, 0), r"NIfTI stores the spacing as 32-bit floats.*1e-320.*axis0"),
    (".nii", (1, 1e300, 1), (0, 0, 0), r"NIfTI stores the spacing as 32-bit floats.*1e\+300.*axis1"),
    (".nii.gz", (1, 1, 1e-40), (0, 0, 0), r"NIfTI stores the spacing as 32-bit floats.*1e-40.*axis2"),
    (".nii", (1, 1, 1), (0, 0, 1e39), r"NIfTI stores the origin as 32-bit floats.*1e\+39.*axis2"),
    (".nrrd", (1e300, 1, 1), (0, 0, 0), r"NRRD stores the voxel size as the length.*1e\+300 \(axis0\)"),
    (".nhdr", (1, 1e-320, 1), (0, 0, 0), r"NRRD stores the voxel size as the length.*1e-320 \(axis1\)"),
    (".tif", (1, 1, 1e-12), (0, 0, 0), r"TIFF stores the voxel size of axis2 .*1e-12.*32-bit whole numbers"),
    ("s/x_{:02d}.tif", (1, 1e-320, 1), (0, 0, 0), r"TIFF stores the voxel size of axis1 .*1e-320"),
    (".dicom", (1e-4, 1, 1), (0, 0, 0), r"slices 1\.0+1e-07 mm apart .* too close for a DICOM reader"),
    (".dicom", (1, 1, 1), (1e300, 0, 0), r"slices 0\.001 mm apart at up to 1e\+297 mm .* too close"),
])
def test_writers_refuse_what_their_format_cannot_hold(tmp_path, suffix, spacing, origin, match):
    target = tmp_path / ("x" + suffix if not suffix.startswith("s/") else suffix)
    with pytest.raises(InvalidInputError, match=match) as info:
        write_volume(np.zeros((3, 4, 5), np.uint16), target, spacing=spacing, origin=origin, unit="micrometer")
    assert "\n" not in str(info.value)
    assert list(tmp_path.iterdir()) == []  # nothing written, not even a temporary file


@pytest.mark.parametrize("suffix", [".nii", ".nrrd", ".tif", ".tiff"])
def test_writers_keep_what_their_format_can_hold(tmp_path, suffix):
    """The refusals' edges: a float32-normal NIfTI spacing, the NRRD and TIFF range limits' safe sides, an origin
    at float noise (written as 0 by float32, within 1e-6 of a voxel)."""
    # ".tiff": a resolution between 0 and the fraction's smallest step (5e9 was read back as 4294967295)
    spacing = {".nii": (2e-38, 1e38, 1.0), ".nrrd": (1e-150, 1e150, 1.0), ".tif": (1.0, 3e-10, 1e300),
               ".tiff": (1.0, 5e9, 1.7e-9)}[suffix]
    origin = (1e-45, 0.0, -7.7)
    written = write_volume(np.zeros((3, 4, 5), np.float32), tmp_path / ("x" + suffix), spacing=spacing,
                           origin=origin, unit="micrometer")
    back = open_volume(written)
    np.testing.assert_allclose(back.spacing, spacing, rtol=1e-6)
    np.testing.assert_allclose(back.origin, origin, rtol=1e-6, atol=1e-6 * min(spacing))


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_bend_takes_the_recorded_spacing_over_a_float32_header(tmp_path, suffix):
    """NIfTI keeps the spacing as float32: 1.7 comes back as 1.70000005, and a straight box whose length is a whole
    number of steps (170 / 1.7 = 100) then has one slice fewer (100 instead of 101); the recorded 1.7 keeps it."""
    d = Deformation.from_polyline(np.array([[5.0, 10, 10], [175.0, 10, 10]]), spacing=(1.0, 1.0, 1.0),
                                  cage_half_extent=(5.0, 5.0), unit="micrometer")
    assert d.output_shape(1.7)[0] == d.output_shape(float(np.float32(1.7)))[0] + 1  # the trap is there
    x = np.arange(180 * 20 * 20, dtype=np.float32).reshape(180, 20, 20) % 97
    straight = straighten(x, d, spacing=1.7)
    back = open_volume(write_volume(straight, tmp_path / ("s" + suffix)))
    assert back.spacing[0] != 1.7 and back.shape == straight.shape == (101, 7, 7)
    bent = bend(back, d, shape=x.shape).compute()  # refused before: "has shape (101, 7, 7) but ... (100, 7, 7)"
    np.testing.assert_array_equal(bent, bend(straight, d, shape=x.shape).compute())


@pytest.mark.parametrize("name", ["b.zarr", "b.tif", "b.nii.gz", "b.dat", "b.dicom", "b_{:03d}.png"])
def test_a_converted_straight_file_keeps_the_record(tmp_path, name):
    """write_volume of a straight volume read back (unwind convert) carries the record on: bend still needs no pad."""
    d = Deformation.from_polyline(np.array([[5.0, 10, 10], [175.0, 10, 10]]), spacing=(1.0, 1.0, 1.0),
                                  cage_half_extent=(5.0, 5.0), unit="micrometer")
    x = (np.arange(180 * 20 * 20) % 251).astype(np.uint8).reshape(180, 20, 20)
    straight = straighten(x, d, spacing=1.3, pad=4, order=0)
    first = open_volume(write_volume(straight, tmp_path / "a.nrrd"))
    target = tmp_path / name if "{" not in name else tmp_path / "slices" / name
    converted = open_volume(write_volume(first, target))
    assert converted.metadata["unwind"]["straightening"]["pad"] == 4
    np.testing.assert_array_equal(bend(converted, d, shape=x.shape, order=0).compute(),
                                  bend(straight, d, shape=x.shape, order=0).compute())


def test_the_api_bend_with_scan_checks_its_geometry_and_takes_its_shape(case, reference):
    """bend(scan=...) refuses a deformation of another grid, as straighten does, and bends onto the scan's shape."""
    tmp, x, scan, _, d = case
    d2, deep, tol = reference
    straight = straighten(open_volume(scan), d, spacing=DS, pad=PAD)
    bent = bend(straight, d, scan=scan).compute()  # the shape from the scan
    _check(bent, x, deep, tol)
    for change, value in (("spacing", [1.5, 1.0, 1.0]), ("origin", [4.0, 0.0, 0.0])):
        other = Deformation.from_dict({**d.to_dict(), change: value})
        with pytest.raises(InvalidInputError, match=r"the volume's geometry .* differs from the deformation's"):
            bend(straight, other, scan=scan)
    with pytest.raises(InvalidInputError, match=r"shape=\(1, 2, 3\) differs from the scan's shape"):
        bend(straight, d, scan=scan, shape=(1, 2, 3))
