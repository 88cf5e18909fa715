"""Landmarks along s in the average (issue 24 item 3): a seeded family of tubes whose bright ring sits at a
different fraction of the length in each member. With the ring's position as a landmark, each member's ring goes to
the batch's mean position and the average's axial profile is the analytic one (sharp, full height); without, the
rings are spread over several stations and the average's ring is blurred. The reference profile is built here from
the members' own axial profiles and the definition of the piecewise-linear map (np.interp), never through the code
under test."""
from __future__ import annotations

import numpy as np
import pytest

from napari_unwind.average import average, read_landmarks
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume

SPACING = 0.5
N_ACROSS, RADIUS = 21, 7.0
HALF_RING = 1.0          # ring: stations with |k - c| <= 1 (3 stations), value 3 on a body of 1, background 0


def axial(ns: int, c: float) -> np.ndarray:
    k = np.arange(ns, dtype=float)
    return 1.0 + 2.0 * (np.abs(k - c) <= HALF_RING)


def tube(ns: int, c: float) -> Volume:
    """A straight tube of ``ns`` stations, value 1 inside (radius 7 pixels), 3 over the ring at station c."""
    yy, xx = np.indices((N_ACROSS, N_ACROSS), dtype=float) - (N_ACROSS - 1) / 2
    disk = (yy ** 2 + xx ** 2 <= RADIUS ** 2).astype(np.float32)
    v = axial(ns, c)[:, None, None].astype(np.float32) * disk[None]
    return Volume(v, spacing=(SPACING,) * 3, unit="mm")


@pytest.fixture(scope="module")
def family():
    rng = np.random.default_rng(3)
    lengths = np.array([81, 91, 101, 111, 95])
    fracs = rng.uniform(0.3, 0.65, len(lengths))
    centres = np.round(fracs * (lengths - 1))          # the ring on a whole station: the profile is exact
    return [tube(int(n), float(c)) for n, c in zip(lengths, centres, strict=True)], lengths, centres


def reference(lengths, centres, n, with_landmarks):
    """The mean of the members' axial profiles on the average's n stations, by the definition of the map."""
    frac = centres / (lengths - 1)
    out = np.arange(n, dtype=float)
    prof = []
    for ns, c in zip(lengths, centres, strict=True):
        if with_landmarks:
            s_in = np.interp(out, [0, frac.mean() * (n - 1), n - 1], [0, c, ns - 1])
        else:
            s_in = out * (ns - 1) / (n - 1)
        prof.append(np.interp(s_in, np.arange(ns), axial(ns, c)))
    return np.mean(prof, axis=0)


def centre_profile(vol):
    n, ny, nx = vol.shape
    cy, cx = (ny - 1) // 2, (nx - 1) // 2
    return vol[:, cy - 1:cy + 2, cx - 1:cx + 2].mean(axis=(1, 2))


def test_with_landmarks_the_ring_is_sharp_at_the_mean_position_without_it_is_blurred(family):
    members, lengths, centres = family
    lm = [[c * SPACING] for c in centres]                       # arc length from the head, mm
    n = int(np.median(lengths))
    res = average(members, landmarks=lm, normalise="none", max_roll=0.0)
    flat = average(members, normalise="none", max_roll=0.0)
    got, blurred = centre_profile(res.mean), centre_profile(flat.mean)
    want = reference(lengths, centres, n, True)
    assert np.abs(got - want).max() < 0.02, np.abs(got - want).max()
    assert np.abs(blurred - reference(lengths, centres, n, False)).max() < 0.02
    mean_pos = float(np.mean(centres / (lengths - 1))) * (n - 1)
    assert abs(res.landmarks[0] - mean_pos * SPACING) < 1e-9 and flat.landmarks is None
    # sharp and full height at the mean position with landmarks; spread and low without
    assert abs(int(np.argmax(got)) - mean_pos) <= 1 and got.max() > 2.8, (np.argmax(got), mean_pos, got.max())
    assert blurred.max() < 2.0, blurred.max()
    assert (got > 2).sum() <= 4 < (blurred > 1.2).sum()
    # the median sees the ring too (every member has it there), the std is small on it
    k = int(round(mean_pos))
    assert centre_profile(res.median)[k] > 2.8 and centre_profile(res.std)[k] < 0.3


def test_bad_landmarks_are_one_line_errors(family):
    members, lengths, centres = family
    good = [[c * SPACING] for c in centres]
    cases = [
        (good[:-1], "rows for 5 specimens"),
        ([*good[:-1], [1.0, 2.0]], "the same landmarks"),
        ([*good[:-1], [float(lengths[-1])]], "inside its length"),             # beyond L = (Ns - 1) * 0.5
        ([*good[:-1], [-0.5]], "inside its length"),
        ([[1.0, 3.0]] * 4 + [[3.0, 1.0]], "increase along s"),
        ([*good[:-1], ["gill"]], "must be numbers"),
        ("gill.csv", "one sequence"),
    ]
    for lm, match in cases:
        with pytest.raises(InvalidInputError, match=match) as err:
            average(members, landmarks=lm)
        assert "\n" not in str(err.value)


def test_landmarks_from_a_csv_by_name_or_path(tmp_path):
    paths = [tmp_path / "a" / "fish1.nrrd", tmp_path / "b" / "fish2.nrrd", tmp_path / "b" / "fish3.nrrd"]
    csv = tmp_path / "lm.csv"
    csv.write_text("specimen,gill,anus\nfish2.nrrd,1.5,4\n" + f"{paths[0]},1,3.5\n" + "b/fish3.nrrd,2,5\n")
    assert read_landmarks(csv, paths) == [[1.0, 3.5], [1.5, 4.0], [2.0, 5.0]]
    bad = {
        "fish1.nrrd,1,2\nfish2.nrrd,1,2\nfish9.nrrd,1,2\n": "fish9.nrrd is not one of",
        "fish1.nrrd,1,2\nfish2.nrrd,1,2\nfish1.nrrd,1,2\n": "named twice",
        "fish1.nrrd,1,2\nfish2.nrrd,1,2\n": "no landmarks for fish3.nrrd",
        "fish1.nrrd,1,2\nfish2.nrrd,1\nfish3.nrrd,1,2\n": "fish2.nrrd has 1 landmarks, fish1.nrrd has 2",
        "name,gill\n": "holds no landmarks",
        "fish1.nrrd,1\nfish2.nrrd,x\nfish3.nrrd,1\n": "must be numbers",
    }
    for text, match in bad.items():
        csv.write_text(text)
        with pytest.raises(InvalidInputError, match=match) as err:
            read_landmarks(csv, paths)
        assert "\n" not in str(err.value)
    same = [tmp_path / "a" / "fish.nrrd", tmp_path / "b" / "fish.nrrd"]
    csv.write_text("fish.nrrd,1\nfish.nrrd,2\n")
    with pytest.raises(InvalidInputError, match="give their paths"):
        read_landmarks(csv, same)
