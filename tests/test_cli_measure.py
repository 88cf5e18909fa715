"""``unwind measure`` as a user runs it, on the phantom fish with its true deformation and mask: the profile's
cross-sections against the phantom's own straight mask (made by the phantom generator, not by the code under test)."""

import csv

import numpy as np
import pytest

from conftest import fish_case, no_leftovers
from conftest import run_unwind as _run
from napari_unwind.io import write_volume


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("measure_cli")
    fish, scan, session, d = fish_case(tmp)
    mask = write_volume(fish.mask.astype(np.uint8), tmp / "mask.nrrd", spacing=fish.spacing, unit=fish.unit)
    return tmp, fish, scan, session, d, mask


def read(path):
    rows = list(csv.reader(open(path)))
    header = rows[0]
    return header, {h.split(" [")[0]: np.array([float(r[i]) if r[i] else np.nan for r in rows[1:]])
                    for i, h in enumerate(header)}


def test_the_profile_holds_the_fishs_volume_and_its_thickest_section(case):
    tmp, fish, scan, session, d, mask = case
    out = tmp / "profile.csv"
    ds = fish.straight_spacing
    code, stdout, err = _run("measure", "--session", session, "--mask", mask, "--channel", f"scan={scan}",
                             "--spacing", ds, "-o", out, "-q")
    assert code == 0, err
    header, cols = read(out)
    unit = header[0][len("s ["):-1]                                 # the scan's unit, e.g. "um"
    assert header[0] == f"s [{unit}]" and unit in ("um", "µm", "micrometer") and f"area [{unit}^2]" in header
    assert "scan_mean" in cols
    truth = fish.straight_mask.sum(axis=(1, 2)) * ds * ds        # the phantom's own straight sections
    volume = np.nansum(cols["area"]) * ds
    assert volume == pytest.approx(truth.sum() * ds, rel=0.03)
    # two digitisations of one body (the bent mask resampled, the straight truth voxelised at pixel centres):
    # the thickest section within 4 % (3.4 % seen), its equivalent radius within 2 %
    assert np.nanmax(cols["area"]) == pytest.approx(truth.max(), rel=0.04)
    assert np.nanmax(cols["radius"]) == pytest.approx(np.sqrt(truth.max() / np.pi), rel=0.02)
    assert cols["s"][0] == 0.0 and cols["s"][-1] == pytest.approx(d.length, abs=ds)
    # inside the fish the scan is bright; the mean per station never below the scan's median
    body = cols["area"] > 0.5 * np.nanmax(cols["area"])
    assert np.all(cols["scan_mean"][body] > np.median(fish.volume))


def test_an_existing_profile_is_kept_without_overwrite_and_bad_input_is_one_line(case):
    tmp, fish, scan, session, d, mask = case
    out = tmp / "kept.csv"
    out.write_text("mine\n")
    code, _, err = _run("measure", "--session", session, "--mask", mask, "-o", out, "-q")
    assert code != 0 and out.read_text() == "mine\n" and "Traceback" not in err
    code, _, err = _run("measure", "--session", session, "--mask", mask, "-o", tmp / "p.xlsx", "-q")
    assert code != 0 and ".csv" in err and len(err.strip().splitlines()) == 1
    other = write_volume(fish.mask[::2].astype(np.uint8), tmp / "coarse.nrrd", spacing=(2.0, 1.0, 1.0),
                         unit=fish.unit)
    code, _, err = _run("measure", "--session", session, "--mask", other, "-o", tmp / "p.csv", "-q")
    assert code != 0 and "Traceback" not in err and not (tmp / "p.csv").exists()
    assert no_leftovers(tmp) == []


def test_a_mask_of_the_scans_shape_whose_header_differs_is_read_voxel_for_voxel_as_unwind_run_reads_it(case):
    tmp, fish, scan, session, d, mask = case
    code, _, err = _run("measure", "--session", session, "--mask", mask, "-o", tmp / "right.csv", "-q")
    assert code == 0, err
    # the same voxels, a header without the scan's geometry (a tool that writes no spacing or origin)
    bare = write_volume(fish.mask.astype(np.uint8), tmp / "bare.nrrd", spacing=(2.0, 2.0, 2.0), origin=(5, 6, 7),
                        unit=fish.unit)
    code, _, err = _run("measure", "--session", session, "--mask", bare, "-o", tmp / "bare.csv", "-q")
    assert code == 0, err
    assert "the mask's spacing 2 x 2 x 2 / origin 5 x 6 x 7 differ from the session's scan's" in err, err
    assert (tmp / "bare.csv").read_bytes() == (tmp / "right.csv").read_bytes()
    # a label map of the scan's shape: its labels named, one of them measured as its own mask
    lab = fish.mask.astype(np.uint8)
    lab[:4, :4, :4] = 2
    labels = write_volume(lab, tmp / "labels.nrrd", spacing=fish.spacing, unit=fish.unit)
    code, _, err = _run("measure", "--session", session, "--mask", labels, "--mask-label", "1", "-o",
                        tmp / "one.csv", "-q")
    assert code == 0 and (tmp / "one.csv").read_bytes() == (tmp / "right.csv").read_bytes(), err
    code, _, err = _run("measure", "--session", session, "--mask", labels, "-o", tmp / "all.csv", "-q")
    assert code == 0 and "the mask holds 2 labels" in err, err


def test_a_mask_cropped_to_its_box_measures_as_the_whole_mask(case):
    """A mask saved cropped to the fish's box with its origin (as 3D Slicer saves a segment): placed on the session's
    scan grid, the same profile bytes as the whole mask's, and said; a box off the grid is refused in one line."""
    tmp, fish, scan, session, d, mask = case
    code, _, err = _run("measure", "--session", session, "--mask", mask, "-o", tmp / "whole.csv", "-q")
    assert code == 0, err
    idx = np.argwhere(fish.mask)
    lo, hi = idx.min(axis=0), idx.max(axis=0) + 1
    sp = np.asarray(fish.spacing, dtype=float)
    crop = fish.mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.uint8)
    box = write_volume(crop, tmp / "box.nrrd", spacing=fish.spacing, origin=tuple(np.add(d.origin, lo * sp)),
                       unit=fish.unit)
    code, _, err = _run("measure", "--session", session, "--mask", box, "-o", tmp / "box.csv", "-q")
    assert code == 0, err
    assert f"is a box of the scan's grid: placed at voxel {' x '.join(map(str, lo))} by its origin" in err, err
    assert (tmp / "box.csv").read_bytes() == (tmp / "whole.csv").read_bytes()
    off = write_volume(crop, tmp / "off.nrrd", spacing=fish.spacing, origin=tuple(np.add(d.origin, (lo + 0.5) * sp)),
                       unit=fish.unit)
    code, _, err = _run("measure", "--session", session, "--mask", off, "-o", tmp / "off.csv", "-q")
    assert code == 1 and "voxels off the scan's grid" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp / "off.csv").exists()
