"""Branched specimens (issue 23 item 2): a Y-shaped mask is straightened along the path between its two ends, the
other branch is cut off at the junction, left out of the cage and reported.

The truth is the phantom's own polylines (the trunk and each leg); what the cage holds is measured by
tests/cage_reference.py's inverse, independent of napari_unwind.warp.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
from cage_reference import held
from scipy.spatial import cKDTree

from napari_unwind.datasets import fish_phantom
from napari_unwind.progress import run
from napari_unwind.skeleton import estimate_deformation_iter


def y_phantom(seed: int, *, stent: bool = False, shape=(130, 90, 60)):
    """A tube of radius 4-7 voxels that forks into two straight legs: ``(mask, head, leg A's end, leg B's end,
    trunk + leg A polyline, trunk + leg B polyline, radius, where the legs part)``: the junction and the distance
    from it beyond which the two legs' tubes no longer touch. ``stent``: the legs leave at 10-14 degrees
    each side of the trunk (a bifurcated graft's legs, running side by side), else at 15-35 degrees."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(4, 5) if stent else rng.uniform(4, 7)
    j = np.array([rng.uniform(50, 70), 45.0, 30.0])
    head = np.array([8.0 + r, 45.0 + rng.uniform(-5, 5), 30.0])
    ang = np.radians(rng.uniform(10, 14) if stent else rng.uniform(15, 35))
    a_end = j + rng.uniform(45, 55) * np.array([np.cos(ang), -np.sin(ang), 0])
    b_end = j + rng.uniform(45 if stent else 30, 55) * np.array([np.cos(ang), np.sin(ang), 0])

    def seg(p0, p1):
        return p0 + np.linspace(0, 1, 200)[:, None] * (p1 - p0)

    trunk, leg_a, leg_b = seg(head, j), seg(j, a_end), seg(j, b_end)
    g = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    dist, _ = cKDTree(np.vstack([trunk, leg_a, leg_b])).query(g)
    mask = (dist <= r).reshape(shape)
    apart = r / np.sin(ang) + r  # the legs' tubes touch until their centrelines are 2r apart
    return mask, head, a_end, b_end, np.vstack([trunk, leg_a]), np.vstack([trunk, leg_b]), r, (j, apart)


def _solve(mask, ends):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run(estimate_deformation_iter(mask, ends, spacing=1.0))


def _check_follows(result, mask, path, other, r, fork):
    j, apart = fork
    d = result.deformation
    c, _ = d.sample(np.linspace(0, d.length, 600))
    # where the legs' tubes touch the mask is one blob, whose sections' centres lie between the legs: the curve
    # is held to the chosen leg from where they part (and on the trunk, three radii before the junction)
    s_j = float(np.linalg.norm(j - path[0]))
    along = np.linalg.norm(c - path[0], axis=1)
    away = (along < s_j - 3 * r) | (np.linalg.norm(c - j, axis=1) > max(3 * r, apart + r))
    away &= np.linalg.norm(c - path[-1], axis=1) > 2 * r  # the tip's end window (a quadratic over two radii)
    dev = cKDTree(path).query(c[away])[0]
    where = np.linalg.norm(c[away][np.argmax(dev)] - j)
    assert dev.max() <= 1.5, f"the curve strays {dev.max():.1f} voxels from the chosen path, {where:.0f} from the fork"
    g = np.argwhere(mask).astype(float)
    on_path = cKDTree(path).query(g)[0] <= r
    beyond = (cKDTree(other).query(g)[0] <= r) & ~on_path & (np.linalg.norm(g - j, axis=1) > max(3 * r, apart))
    assert held(d, g[on_path]).mean() >= 0.99
    # the other leg beyond three radii of the junction: out of the straight volume (all of it was in before)
    assert held(d, g[beyond]).mean() <= 0.3, held(d, g[beyond]).mean()
    notes = [w for w in result.warnings if "branches between the ends" in w]
    assert len(notes) == 1 and "1 other branch" in notes[0] and "% of the mask" in notes[0]
    from napari_unwind.pipeline import judge

    assert judge(result) == ("ok", ""), judge(result)  # a fork's leg: no doubt (the path turns gently there)


@pytest.mark.parametrize("seed", range(4))
def test_a_y_shaped_mask_is_straightened_along_the_chosen_leg(seed):
    mask, head, a_end, b_end, path_a, path_b, r, fork = y_phantom(seed)
    _check_follows(_solve(mask, (head, a_end)), mask, path_a, path_b, r, fork)


@pytest.mark.parametrize("seed", range(2))
def test_the_other_end_picks_the_other_leg(seed):
    mask, head, a_end, b_end, path_a, path_b, r, fork = y_phantom(seed)
    _check_follows(_solve(mask, (head, b_end)), mask, path_b, path_a, r, fork)


@pytest.mark.parametrize("seed", range(3))
def test_a_bifurcated_graft_with_legs_side_by_side(seed):
    mask, head, a_end, b_end, path_a, path_b, r, fork = y_phantom(100 + seed, stent=True)
    _check_follows(_solve(mask, (head, a_end)), mask, path_a, path_b, r, fork)


@pytest.mark.parametrize("seed", range(4))
def test_a_fish_with_its_fins_is_not_taken_for_a_branch(seed):
    ph = fish_phantom(seed=seed, curve=("s-bend", "c-bend", "helix", "s-bend")[seed])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run(estimate_deformation_iter(ph.mask, (ph.head, ph.tail), spacing=ph.spacing))
    assert not any("branches" in w for w in result.warnings)
    assert result.coverage >= 0.99


def hairpin_phantom(seed: int):
    """A tube of radius 3-7 voxels that comes in, turns back in a hairpin 5-11 radii deep whose two sides touch all
    along (their centrelines 1.5-2 radii apart, the pair bent by up to 0.6 rad) and leaves at a random angle; turned
    at random: ``(mask, head, tail, radius, gap in radii, hairpin's centreline (N, 3))``. By its topology the mask is
    a Y whose trunk is the two touching sides."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    r = rng.uniform(3, 7)
    gap = rng.uniform(1.5, 2.0) * r
    depth = rng.uniform(5, 11) * r
    bend = rng.choice([-1, 1]) * rng.uniform(1e-3, 0.6)
    ang = bend * np.linspace(0, 1, 300)
    spine = np.stack([depth / bend * (1 - np.cos(ang)), 0 * ang, depth / bend * np.sin(ang)], 1)
    along = np.stack([np.sin(ang), 0 * ang, np.cos(ang)], 1)
    side = np.stack([along[:, 2], 0 * ang, -along[:, 0]], 1)
    up, down = spine - gap / 2 * side, (spine + gap / 2 * side)[::-1]
    a = np.linspace(0, np.pi, 60)[:, None]
    turn = spine[-1] - gap / 2 * np.cos(a) * side[-1] + gap / 2 * np.sin(a) * along[-1]

    def lead(p, sign):
        th, ph = rng.uniform(0.3, 1.3), rng.uniform(-0.8, 0.8)
        d = np.array([sign * np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)])
        return p + np.linspace(0, rng.uniform(4, 9) * r, 150)[:, None] * d

    lead_a, lead_b = lead(up[0], -1)[::-1], lead(down[-1], 1)
    line = Rotation.random(random_state=int(rng.integers(1 << 31))).apply(np.vstack([lead_a, up, turn, down, lead_b]))
    line = line - line.min(0) + r + 6
    shape = tuple(int(np.ceil(v + r + 6)) for v in line.max(0))
    g = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    mask = (cKDTree(line).query(g, distance_upper_bound=2 * r)[0] <= r).reshape(shape)
    return mask, line[0], line[-1], r, gap / r, line[len(lead_a):len(line) - len(lead_b)]


def kink_phantom(seed: int):
    """A tube of radius 4-9 voxels that kinks: a straight leg 5-8 radii long, an arc of 70-140 degrees whose radius
    is 0-1 times the tube's (tighter than the tube: its inner wall meets itself and its outer corner juts out), and
    a second straight leg; turned at random. ``(mask, head, tail, radius, the arc's radius in tube radii, the turn
    in degrees, centreline (N, 3))``. Unbranched: nothing of it is a branch, and its sides touch only within the
    kink."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    r = rng.uniform(4, 9)
    rc = rng.uniform(0, 1) * r
    turn = np.radians(rng.uniform(70, 140))
    leg = rng.uniform(5, 8) * r
    th = np.linspace(0, turn, 200)
    first = np.stack([0 * th[:150], 0 * th[:150], np.linspace(0, leg, 150)], 1)
    arc = np.stack([0 * th, rc - rc * np.cos(th), leg + rc * np.sin(th)], 1)
    out = np.array([0.0, np.sin(turn), np.cos(turn)])
    second = arc[-1] + np.linspace(0, leg, 150)[1:, None] * out
    line = Rotation.random(random_state=int(rng.integers(1 << 31))).apply(np.vstack([first, arc, second]))
    line = line - line.min(0) + r + 6
    shape = tuple(int(np.ceil(v + r + 6)) for v in line.max(0))
    g = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    d, k = cKDTree(line).query(g, distance_upper_bound=2 * r)
    flat = ((k == 0) | (k == len(line) - 1)) & (d > 0.5)  # flat ends
    mask = ((d <= r) & ~flat).reshape(shape)
    return mask, line[0], line[-1], r, rc / r, float(np.degrees(turn)), line


def _check_fold(result, mask, pin, r, says="fold"):
    """``pin`` (the centreline of what the path skips, radius ``r``) is left out, and the result is partial because
    the mask touches itself (the note saying ``says``), never ok with a branch cut."""
    from napari_unwind.pipeline import judge

    g = np.argwhere(mask).astype(float)
    on_pin = cKDTree(pin).query(g)[0] <= r
    assert held(result.deformation, g[on_pin]).mean() < 0.5  # what the path skips is indeed left out
    assert result.touching and "touches itself" in result.touching[0] and says in result.touching[0]
    assert not any("branches between the ends" in w for w in result.warnings)
    status, reason = judge(result)
    assert status == "partial" and "touches itself" in reason, (status, reason)


@pytest.mark.parametrize("gap", [1.3, 1.5, 1.8])
def test_a_hairpin_whose_sides_touch_is_partial_not_a_branch(gap):
    # a tube that goes up, turns back in a tight hairpin and comes down beside itself, its two sides touching over
    # the hairpin's length: by its topology a Y (the touching sides are the trunk), so the path between the ends
    # cuts across the touching sides and the turn was cut off as a branch, "ok" with 69 % of the mask left out. Its
    # sections hold two cores, a branch's one: the specimen is partial and the reason says where it touches itself.
    # Along the grid's axes the distance transform's own distance (to the first voxel outside) joined the two cores
    # at 1.5 radii.
    r = 5.0
    gap = gap * r
    up = np.stack([np.full(200, 25.0), np.full(200, 30.0), np.linspace(10, 80, 200)], axis=1)
    a = np.linspace(0, np.pi, 100)
    turn = np.stack([25.0 + gap / 2 - gap / 2 * np.cos(a), np.full(100, 30.0), 80 + 10 * np.sin(a)], axis=1)
    down = up[::-1] + np.array([gap, 0.0, 0.0])
    legs = [np.stack([np.linspace(25, 5, 80), np.full(80, 30.0), np.full(80, 10.0)], axis=1),
            np.stack([np.linspace(25 + gap, 45 + gap, 80), np.full(80, 30.0), np.full(80, 10.0)], axis=1)]
    line = np.vstack([legs[0][::-1], up, turn, down, legs[1]])
    shape = (70, 60, 100)
    g = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    mask = (cKDTree(line).query(g)[0] <= r).reshape(shape)
    pin = np.vstack([up[40:], turn, down[:-40]])
    _check_fold(_solve(mask, (legs[0][-1], legs[1][-1])), mask, pin, r)


@pytest.mark.parametrize("seed", [300, 301, 302])
def test_hairpins_drawn_at_random_are_partial_not_branches(seed):
    mask, head, tail, r, gap, pin = hairpin_phantom(seed)
    _check_fold(_solve(mask, (head, tail)), mask, pin, r)


def _share_said(note: str) -> float:
    return float(re.search(r"([0-9.]+) % of the mask", note).group(1))


@pytest.mark.parametrize("seed, stent", [(0, False), (905, False), (1004, True)])
def test_the_share_reported_is_what_the_straight_volume_leaves_out(seed, stent):
    # the note gives the share of the mask that the branch leaves outside the straight volume, as measured by an
    # independent inverse (it gave the part that first marks the branch off the path: 7.3 % for 10 % left out on
    # seed 905, 25 % for 29 % on 1004; on a tube touching itself, 5.5 % for 41 % cut off, bench_tubes seed 90)
    mask, head, a_end, b_end, path_a, path_b, r, fork = y_phantom(seed, stent=stent)
    result = _solve(mask, (head, a_end))
    g = np.argwhere(mask).astype(float)
    truth = 100 * (~held(result.deformation, g)).mean()
    notes = [w for w in result.warnings if "branches between the ends" in w]
    assert len(notes) == 1
    assert abs(_share_said(notes[0]) - truth) <= 1.0, (_share_said(notes[0]), truth)
    # the report's coverage is of the mask between the ends, and says how much of the whole was cut off
    assert abs(100 * result.left_out - truth) <= 0.5
    assert f"{100 * result.left_out:.2g} % of the whole cut off" in result.report()


def _loop_crossed(r=4.0, shape=(70, 75, 40)):
    """A tube that runs east, turns north, west and south round a square and crosses its own first stretch on its
    way to the tail: where it crosses, the mask touches itself, and the path between the ends goes straight
    through the crossing, skipping the square loop."""
    z = 20.0

    def seg(a, b):
        return np.asarray(a, float) + np.linspace(0, 1, 200)[:, None] * (np.asarray(b, float) - np.asarray(a, float))

    corners = [(8, 20, z), (52, 20, z), (52, 55, z), (25, 55, z), (25, 4, z)]
    parts = [seg(a, b) for a, b in zip(corners[:-1], corners[1:])]
    g = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    mask = (cKDTree(np.vstack(parts)).query(g)[0] <= r).reshape(shape)
    loop = np.vstack([seg((25 + 2 * r, 20, z), (52, 20, z)), parts[1], parts[2],
                      seg((25, 55, z), (25, 20 + 2 * r, z))])
    return mask, np.array(corners[0]), np.array(corners[-1]), loop, r


def test_a_loop_that_the_path_skips_is_partial_and_named_not_cut_as_a_branch():
    # the loop is the tube's own: it hangs where the tube crosses itself, and the path between the ends goes
    # straight through the crossing. Left out, it makes the specimen partial (never ok), and the note says where the
    # mask touches itself, not that it branches.
    mask, head, tail, loop, r = _loop_crossed()
    _check_fold(_solve(mask, (head, tail)), mask, loop, r, says="loop")


@pytest.mark.parametrize("seed, stent", [(0, False), (101, True)])
def test_a_branched_mask_between_suggested_ends_is_partial(seed, stent):
    # with no ends given the path follows the mask's longest way and cuts the other branch: which leg is the
    # specimen is a guess, and a guess that leaves a fifth of the mask out is not a success. With the ends given the
    # same cut is the user's choice: ok.
    from napari_unwind.pipeline import judge

    mask, head, a_end, *_ = y_phantom(seed, stent=stent)
    guessed = _solve(mask, None)
    assert guessed.suggested and guessed.branches and not guessed.touching
    status, reason = judge(guessed)
    assert status == "partial" and "the mask branches and the ends were suggested" in reason, (status, reason)
    assert "% of the mask left out" in reason
    given = _solve(mask, (head, a_end))
    assert not given.suggested and given.branches
    assert judge(given) == ("ok", "")


@pytest.mark.parametrize("seed", [411, 472])
def test_a_path_up_one_touching_side_of_a_hairpin_is_partial(seed):
    # with no ends given, the farthest points of these hairpins are a lead's end and the turn: the path runs up one
    # side, the other side (touching it all along) lies within its sections, beside it in the straight volume and
    # never followed, and nothing is cut off. It was "ok" (1 of 30 and 1 of 40 random hairpins). The sections of
    # what is straightened hold two cores over more than 0.4 of it (the cut-off parts' rule).
    from napari_unwind.pipeline import judge

    mask, head, tail, r, gap, pin = hairpin_phantom(seed)
    result = _solve(mask, None)
    assert result.suggested and not result.branches  # nothing cut: the path and the other side are both kept
    said = [t for t in result.touching if "along the path" in t]
    assert said and "two sides of the body run side by side" in said[0], result.touching
    # where it says: on the hairpin's stretch whose sides touch (the truth: the phantom's own centreline there)
    at = np.array(re.search(r"at \[([^\]]+)\]", said[0]).group(1).split(","), float)
    assert cKDTree(pin).query(at)[0] <= 2 * r
    status, reason = judge(result)
    assert status == "partial" and "touches itself along the path" in reason, (status, reason)


@pytest.fixture(scope="module")
def tubes_1234():
    """Tubes 5 and 13 of benchmarks/bench_tubes.py seed 1234 (round tubes along random curves that come back to
    touch themselves), each with where its curve comes nearest itself ``(j, k)``, curve indices more than 4 radii
    apart along it."""
    from benchmarks.bench_tubes import tubes

    out = {}
    for i, t in tubes(1234, (5, 13)).items():
        c, r = t[2], t[3]
        s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))]
        d = np.linalg.norm(c[:, None] - c[None], axis=2)
        d[np.abs(s[:, None] - s[None]) <= 4 * r] = np.inf
        j, k = sorted(np.unravel_index(int(np.argmin(d)), d.shape))
        out[i] = (*t, s, j, k)
    return out


def _tube_solve(t):
    mask, volume, c = t[:3]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run(estimate_deformation_iter(mask, (c[0], c[-1]), spacing=1.0, volume=volume))


def test_a_loop_whose_sides_touch_at_one_place_is_partial_not_a_branch(tubes_1234):
    # the tube comes back to graze itself (2.15 radii between centrelines, touching as voxels) and the path between
    # the ends goes through the contact. The loop it skips parts into two legs within a radius of it, so the part
    # cut off (from where its detour passes a radius) was a tree, "a branch": ok, 58 % of the tube's length gone.
    # Its two legs lie against the kept mask in two places: a cycle through it, the body coming back on itself.
    from napari_unwind.pipeline import judge

    mask, volume, c, r, approach, s, j, k = tubes_1234[5]
    result = _tube_solve(tubes_1234[5])
    trim = (s > s[j] + 2 * r) & (s < s[k] - 2 * r)  # the loop, but for the stretches within 2 radii of the contact
    _check_fold(result, mask, c[trim], r, says="loop")
    at = np.array(re.search(r"at \[([^\]]+)\]", result.touching[0]).group(1).split(","), float)
    assert np.linalg.norm(at - (c[j] + c[k]) / 2) <= 3 * r, (at, c[j], c[k])
    assert judge(result)[0] == "partial"


def test_a_stretch_the_path_skips_between_two_contacts_is_named(tubes_1234):
    # a tube that touches itself in several places: the path between the ends runs 161 voxels of its 364, and the
    # stretch it skips meets the path at both its ends (no dead end, so not a branch and not cut). It stayed inside
    # the straight volume beside the path, the cage holding 97.7 % of the mask; the only reason said was the
    # coverage. The report now says the path skips a stretch of the body, and gives a point on it to chain through.
    from napari_unwind.pipeline import judge

    mask, volume, c, r, approach, s, j, k = tubes_1234[13]
    result = _tube_solve(tubes_1234[13])
    said = [t for t in result.touching if "skips a stretch of the body" in t]
    assert said, result.touching
    p = np.array(re.search(r"through \[([^\]]+)\]", said[0]).group(1).split(","), float)
    assert cKDTree(c).query(p)[0] <= r + 1  # on the tube
    assert cKDTree(result.curve).query(p)[0] >= 2 * r  # and off the path
    assert any(f"P = {np.round(p, 1).tolist()}" in w for w in result.warnings)
    assert judge(result)[0] == "partial"


@pytest.fixture(scope="module")
def tubes_31001():
    """Tubes 26 and 39 of benchmarks/bench_tubes.py seed 31001: tubes whose turns run into one another so that the
    stretch between the contact and the contact hangs off the path as a dead end (no hole left in the loop)."""
    from benchmarks.bench_tubes import tubes

    return tubes(31001, (26, 39))


@pytest.mark.parametrize("i, says", [(26, "where the path turns"), (39, "radii from the path's tail")])
def test_a_loop_that_hangs_off_the_path_like_a_branch_is_in_doubt_not_ok(tubes_31001, i, says):
    # a tube that runs into itself (26: 0.35 radii between its centrelines at the contact; 39: its tail's last
    # stretch against the body) leaves a stretch of itself, 6-21 % of the mask, hanging off the path like a
    # branch: no cycle in its mask and no doubled sections, so it was cut off and the result said ok (8 of 19
    # random tubes fused with themselves on this seed lost 6-28 % of the body so). The path turns 62 degrees where
    # 26's part joins (a fork's leg leaves at most 20.6), and 39's leaves the path 1.5 radii from the tail (a fork's
    # chosen leg runs on 3.7 radii at least): in doubt, partial, the part's share said.
    from napari_unwind.pipeline import judge

    mask, volume, c, r, approach = tubes_31001[i]
    result = _tube_solve(tubes_31001[i])
    truth = held(result.deformation, np.argwhere(mask).astype(float)).mean()
    assert truth <= 0.95  # the body is not all straightened: a whole result would be ok
    said = [t for t in result.touching if says in t and "which the mask cannot tell" in t]
    assert said and not result.branches, (result.touching, result.branches)
    share = float(re.search(r"the mask, ([0-9.]+) % of it", said[0]).group(1)) / 100
    assert abs(share - (1 - truth)) <= 0.02, (share, truth)
    status, reason = judge(result)
    assert status == "partial" and said[0] in reason and reason.endswith("check the straight volume"), reason


def _lens_union(gap: float) -> float:
    """The area of two unit discs whose centres lie ``gap`` apart (0 <= gap <= 2), over one disc's (pi)."""
    lens = 2 * np.arccos(gap / 2) - gap / 2 * np.sqrt(4 - gap * gap)
    return (2 * np.pi - lens) / np.pi


@pytest.mark.parametrize("shape, truth, step", [
    (("round",), 1.0, 1.0),
    (("round",), 1.0, 2.0),
    (("ellipse", 1.6), 1.6, 1.0),
    (("two", 1.0), _lens_union(1.0), 1.0),
    (("two", 1.5), _lens_union(1.5), 1.0),
    (("two", 1.5), _lens_union(1.5), 2.0),
    (("two", 2.0), _lens_union(2.0), 1.0),
])
def test_the_thickness_of_a_part_s_sections_against_the_area_of_discs(shape, truth, step):
    # the measure that tells two sides of the body lying side by side from a branch: a piece's volume over a round
    # tube as deep as it, as long as the shell. The truth is analytic: 1 for a round tube, a / b for an elliptic
    # one, and the area of two discs' union over one disc's for two tubes whose centrelines lie `gap` radii apart;
    # `step`: the voxels' size along the tube (physical units throughout)
    from napari_unwind.skeleton._api import _shell_pieces, _thick_pieces

    r, n = 6.0, 80
    y, z = np.meshgrid(np.arange(-20, 21, dtype=float), np.arange(-20, 21, dtype=float), indexing="ij")
    if shape[0] == "round":
        disc = y * y + z * z <= r * r
    elif shape[0] == "ellipse":
        disc = (y / (shape[1] * r)) ** 2 + (z / r) ** 2 <= 1
    else:
        half = shape[1] * r / 2
        disc = ((y - half) ** 2 + z * z <= r * r) | ((y + half) ** 2 + z * z <= r * r)
    region = np.broadcast_to(disc, (n, *disc.shape)).copy()
    dist = np.broadcast_to(step * np.arange(n, dtype=float)[:, None, None], region.shape) * region  # along it
    box, labels, count, _, edt = _shell_pieces(region, dist, r, (step, 1.0, 1.0))
    got = _thick_pieces(edt, labels, count, r, (step, 1.0, 1.0))
    assert abs(got - truth) <= 0.1 * truth, (got, truth)


@pytest.mark.parametrize("seed", [406, 425])
def test_a_hairpin_so_thin_that_its_sides_share_one_core_is_partial(seed):
    # hairpins of radius 3.3 voxels whose sides lie 1.54 and 1.59 radii apart: the distance transform's steps join
    # the two sides' cores (one core per section), so the turn was cut off as a branch, "ok". Their sections hold
    # 1.8-2 times a round tube as deep as they are (a branch's about 1)
    mask, head, tail, r, gap, pin = hairpin_phantom(seed)
    _check_fold(_solve(mask, (head, tail)), mask, pin, r)


@pytest.mark.parametrize("seed", [2, 7, 9])
def test_a_tube_that_kinks_tighter_than_itself_is_straightened_whole(seed):
    """A kink's outer corner juts out of the path's reach like a short branch: the code before cut it off as one
    and said ok with 12-20 % of the body left out (these three seeds; of 12, five so and three read as touching
    themselves). It reaches past the slack less than its base is wide (``_rise``): kept, and the fold-free cage
    holds the whole tube, by tests/cage_reference.py's inverse."""
    from napari_unwind.pipeline import judge

    mask, head, tail, r, rc, turn, _ = kink_phantom(seed)
    assert rc < 1.0 and turn > 90  # tighter than the tube
    res = _solve(mask, (head, tail))
    assert not res.branches and not res.touching and res.left_out == 0.0, (res.branches, res.touching)
    assert judge(res) == ("ok", "")
    assert held(res.deformation, np.argwhere(mask).astype(float)).mean() >= 0.99


def test_a_short_leg_that_parts_from_the_trunk_is_still_a_branch():
    """The least rise among 240 parts of Y, graft and hairpin phantoms cut as branches but one (``_rise``, Y phantom
    10's leg B, with the tail at leg A's end: 1.33) is over the bound: still cut, the path held and the other leg
    not. (The one, Y 905's leg B, 1.11, is cut because the path does not turn there: the test of the share said
    above.)"""
    mask, head, a_end, _, pa, pb, r, (j, apart) = y_phantom(10)
    res = _solve(mask, (head, a_end))
    assert len(res.branches) == 1 and not res.touching, (res.branches, res.touching)
    g = np.argwhere(mask).astype(float)
    on = cKDTree(pa).query(g)[0] <= r
    beyond = (cKDTree(pb).query(g)[0] <= r) & ~on & (np.linalg.norm(g - j, axis=1) > max(3 * r, apart))
    assert held(res.deformation, g[on]).mean() >= 0.99 and held(res.deformation, g[beyond]).mean() <= 0.05
