"""The zero-click path on hard tanks (issue 18, item 4): every fish one specimen, walls rejected, whole bodies.

Cases are drawn from seeds by :func:`napari_unwind.datasets.hard_tank_phantom` (3-12 fish, a dense wall the field
of view cuts into arcs, touching fish, fish cut by a face, bright spines in softer bodies). References are the
phantom's own ground truth (its fish labels, wall and spines), never the code under test.

Planted one at a time, each of these fails here: no split (``split_saddle=0``: the touching pairs stay one
candidate), touching the border as a container's mark again (the cut fish are rejected), no wall-arc rule
(``max_border_share=1``: the arcs become specimens), the features' own thresholds for the body (``body=False``: the
spine-heavy labels miss the soft body, Dice < 0.9).
"""

from __future__ import annotations

import numpy as np
import pytest

from napari_unwind.datasets import hard_tank_phantom
from napari_unwind.segmentation import candidates, join_tree
from napari_unwind.segmentation._common import MAX_FEATURES

SEEDS = list(range(100, 114))  # 14 random tanks


def dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * np.count_nonzero(a & b) / max(np.count_nonzero(a) + np.count_nonzero(b), 1)


def _features(tank):
    tree = join_tree(tank.volume)
    k = int(min(MAX_FEATURES, max(1, int(tree.significant.sum())), tree.n_maxima))  # run --all's k
    return tree.simplify(k)


def check_tank(tank, found, features) -> list[float]:
    """Every fish exactly one specimen (Dice >= 0.9 at the working level), nothing else a specimen, no wall."""
    spec = [c for c in found if c.status == "specimen"]
    masks = [c.working_mask(features) for c in spec]
    for c, m in zip(spec, masks):
        assert np.count_nonzero(m & tank.wall) < 0.2 * np.count_nonzero(m), (tank, c.name, "a wall as specimen")
    scores, used = [], []
    for i in range(1, tank.n_fish + 1):
        fish = tank.labels == i
        d = [dice(m, fish) for m in masks]
        j = int(np.argmax(d)) if d else -1
        assert d and d[j] >= 0.9, (tank, f"fish {i}", max(d, default=0.0))
        # the soft body, not only the spine: most of the flesh around the spine is in
        flesh = fish & ~tank.spine
        assert np.count_nonzero(masks[j] & flesh) >= 0.85 * np.count_nonzero(flesh), (tank, f"fish {i}")
        used.append(j)
        scores.append(d[j])
    assert sorted(used) == list(range(len(spec))), (tank, "a fish in two specimens or a specimen of no fish",
                                                    [c.name for c in spec])
    return scores


@pytest.mark.parametrize("seed", SEEDS)
def test_every_fish_of_a_hard_tank_is_one_specimen(seed):
    tank = hard_tank_phantom(seed)
    features = _features(tank)
    found = candidates(features)
    scores = check_tank(tank, found, features)
    for c in found:  # every rejection says why
        assert c.status in ("specimen", "rejected") and (c.status == "specimen" or c.reason), c
    print(f"{tank}: Dice " + " ".join(f"{d:.3f}" for d in scores))


def test_the_families_cover_the_hard_cases():
    tanks = [hard_tank_phantom(s) for s in SEEDS]
    assert min(t.n_fish for t in tanks) == 3 and max(t.n_fish for t in tanks) >= 8
    assert sum(t.wall_cut for t in tanks) >= 3 and sum(not t.wall_cut for t in tanks) >= 1
    assert sum(bool(t.touching) for t in tanks) >= 3 and sum(not t.touching for t in tanks) >= 1
    assert sum(bool(t.cut_fish) for t in tanks) >= 3
    assert all(t.spine.any() for t in tanks)
    for t in tanks:
        assert set(np.unique(t.labels).tolist()) == set(range(t.n_fish + 1))


def test_touching_fish_are_split_and_say_so():
    tank = hard_tank_phantom(3)  # fish 5 and 6 touch
    assert tank.touching
    features = _features(tank)
    found = candidates(features)
    split = [c for c in found if c.n_parts > 1]
    assert split and all(c.reason.startswith("touching specimens: split into") for c in split)
    with_split_off = candidates(features, split_saddle=0)
    with pytest.raises(AssertionError):  # the planted bug: no split
        check_tank(tank, with_split_off, features)


def test_a_wall_cut_into_arcs_is_rejected_and_a_cut_fish_is_kept():
    tank = hard_tank_phantom(0)  # wall cut into arcs, every fish cut by the upper face
    assert tank.wall_cut and len(tank.cut_fish) == tank.n_fish
    features = _features(tank)
    found = candidates(features)
    check_tank(tank, found, features)
    arcs = [c for c in found if c.reason.startswith("wall arc cut by the field of view")]
    assert len(arcs) >= 2
    with pytest.raises(AssertionError):  # the planted bug: no arc rule
        check_tank(tank, candidates(features, max_border_share=1.0), features)


def test_the_body_is_cut_between_medium_and_soft_tissue():
    tank = hard_tank_phantom(5)
    features = _features(tank)
    found = candidates(features)
    check_tank(tank, found, features)
    for c in found:
        if c.status == "specimen":  # halfway between medium (100) and flesh (1000), not at the spine's level
            assert 400 < c.isovalue < 700, c
    with pytest.raises(AssertionError):  # the planted bug: the features' own thresholds
        check_tank(tank, candidates(features, body=False), features)


# A fish pressed against a wall arc (gap 0): its flesh meets the wall in the join tree at the flesh's own level, so
# its feature is only its bright spine and the values around the spine are its own flesh. Its body must still be
# cut halfway between the liquid and the flesh (candidates' working body and the full-resolution isovalue that
# run --all refines it at), not between flesh and spine (then it was rejected as "too small"). Seeds 208 and 226
# are the tanks of seeds 200-229 where that happens; with the own-body rule of specimen_isovalue off both fail.
@pytest.mark.parametrize("seed", [208, 226])
def test_a_fish_pressed_against_the_wall_keeps_its_flesh(seed):
    from scipy import ndimage

    from napari_unwind.segmentation import default_isovalue

    tank = hard_tank_phantom(seed, touching=True)
    near_wall = ndimage.binary_dilation(tank.wall, iterations=2)
    pressed = [i for i in range(1, tank.n_fish + 1) if np.any(near_wall & (tank.labels == i))]
    assert pressed, (tank, "no fish against the wall: the case tests nothing")
    features = _features(tank)
    found = candidates(features)
    check_tank(tank, found, features)
    spec = [c for c in found if c.is_specimen]
    for i in pressed:
        fish = tank.labels == i
        c = max(spec, key=lambda c: dice(c.working_mask(features), fish))
        # halfway between the liquid (100) and the flesh (1000), read from the scan as run --all does
        iso = default_isovalue(features, c.working_mask(features), volume=tank.volume)
        assert 400 < iso < 700, (tank, f"fish {i}", iso)


# A fish pressed against a dense, noisy wall whose flesh meets the wall at the flesh's own level: its join-tree
# branch is no higher above that saddle than the wall's noise maxima above theirs, so it is pruned into the wall's
# feature and no feature holds it (seed 106 fish 4; touching seed 11 fish 3). Rule 7 of candidates finds it as
# tissue outside every feature; without it the fish is lost without a word.
@pytest.mark.parametrize("seed, touching", [(106, None), (11, True)])
def test_a_fish_no_feature_holds_is_found_as_unclaimed_tissue(seed, touching, monkeypatch):
    from napari_unwind.segmentation import _candidates

    tank = hard_tank_phantom(seed, touching=True) if touching else hard_tank_phantom(seed)
    features = _features(tank)
    missed = [i for i in range(1, tank.n_fish + 1) if not np.any(features.labels[tank.labels == i])]
    assert missed, (tank, "every fish has a feature: the case tests nothing")
    found = candidates(features)
    check_tank(tank, found, features)
    spec = [c for c in found if c.is_specimen]
    for i in missed:
        c = max(spec, key=lambda c: dice(c.working_mask(features), tank.labels == i))
        assert "outside every feature" in c.reason and c.part >= 1, (tank, c)
    assert len({c.name for c in found}) == len(found), [c.name for c in found]  # names stay unique
    monkeypatch.setattr(_candidates, "_unclaimed_rows", lambda *a, **k: ([], None))  # the rule off
    with pytest.raises(AssertionError, match="fish"):
        check_tank(tank, candidates(features), features)


# Three fish touching in a chain (seed 9 with touching=True: 3-11 and 6-11), 3 and 11 side by side along their
# length: the distance transform's saddle between them is shallow, so the first split left them one part ("not
# elongated: 3 < 3"). Each is a feature of its own, elongated and of the same size: the part is split by them.
def test_two_fish_side_by_side_in_one_part_are_split_by_their_features(monkeypatch):
    from napari_unwind.segmentation import _candidates

    tank = hard_tank_phantom(9, touching=True)
    features = _features(tank)
    check_tank(tank, candidates(features), features)
    monkeypatch.setattr(_candidates, "_split_by_features", lambda parts, n, *a: (parts, n))  # the rule off
    with pytest.raises(AssertionError, match="fish"):
        check_tank(tank, candidates(features), features)


# Two fish pressed side by side whose join tree kept only one fish's bright core as its feature (packed seed 601:
# fish 1's feature is 782 of its 4327 voxels, fish 2's 2965): the distance transform's saddle does not part them,
# and by their labels the core is under half of its neighbour's feature, so the part was not split by features
# and both fish came out of `run --all` as ONE specimen with status ok. Each feature's size is now the part's tissue
# in its basin (the fish, 4135 against 5611 voxels). Seeds 601 and 614 are the packed tanks of 600-639 where it
# happened; with the labels' counts instead of the basins' both fail.
@pytest.mark.parametrize("seed", [601, 614])
def test_a_fish_whose_feature_is_only_its_core_is_split_from_its_neighbour(seed, monkeypatch):
    from napari_unwind.segmentation import _candidates

    tank = hard_tank_phantom(seed, touching=True)
    features = _features(tank)
    core = []  # features all inside one fish and under 30 % of it
    for s in features.stats:
        inside = tank.labels[features.labels == s.id]
        if inside.size and inside.min() > 0 and inside.min() == inside.max():
            if inside.size < 0.3 * np.count_nonzero(tank.labels == inside[0]):
                core.append(s.id)
    assert core, (tank, "no fish whose feature is only its core: the case tests nothing")
    found = candidates(features)
    check_tank(tank, found, features)
    split = _candidates._split_by_features
    monkeypatch.setattr(_candidates, "_split_by_features",
                        lambda parts, n, labels, stats, spacing, e, basins=None: split(parts, n, labels, stats,
                                                                                       spacing, e))
    with pytest.raises(AssertionError, match="fish"):  # the planted bug: sizes from the labels
        check_tank(tank, candidates(features), features)


# Two fish pressed together, each kept by the join tree as its bright core (tank 650: fish 4's feature is 376 of its
# 5527 voxels): the candidate's body is right (its working levels show the liquid around it), but the one isovalue
# rule read the scan within a few core thicknesses of the core, which is mostly flesh, and refined the fish at
# 1340, between flesh and spine: `run --all` then got a 330-voxel line and reported the fish as "failed: the mask
# is a line". The scan is now read around the body the working levels give. Seed 650 is the one of the tanks
# 600-699 (packed and not) where a specimen's isovalue left 400-700; with the body's growth off it fails.
def test_a_fish_whose_feature_is_a_thin_core_is_refined_at_its_flesh(monkeypatch):
    from napari_unwind.segmentation import _candidates, default_isovalue

    tank = hard_tank_phantom(650, touching=True)
    features = _features(tank)
    found = [c for c in candidates(features) if c.is_specimen]

    def isovalues():
        return {c.name: default_isovalue(features, c.working_mask(features), volume=tank.volume) for c in found}

    for name, iso in isovalues().items():  # halfway between the liquid (100) and the flesh (1000)
        assert 400 < iso < 700, (tank, name, iso)
    monkeypatch.setattr(_candidates, "_working_body",  # the rule off: the body is the labels alone
                        lambda features, ids, lab, *a: ((slice(None),) * 3, lab.copy()))
    assert max(isovalues().values()) > 700


def test_unclaimed_pieces_are_split_in_their_own_boxes(monkeypatch):
    # A noisy liquid (100 +- 40) around a bright bar: hundreds of specks of tissue no feature holds. Each was split
    # on the whole volume (a distance transform and h-maxima per speck: over 10 minutes for a 110^3 scan); each is
    # now split in its box, three voxels wider than the two it may grow by.
    from napari_unwind.segmentation import _candidates

    rng = np.random.default_rng(5)
    vol = rng.normal(100.0, 40.0, (72, 72, 72))
    vol[10:62, 30:38, 30:38] += 900.0
    features = _features(type("Tank", (), {"volume": vol.astype(np.float32)})())
    shapes = []
    split = _candidates._split
    monkeypatch.setattr(_candidates, "_split",
                        lambda body, *a, **k: (shapes.append(body.shape), split(body, *a, **k))[1])
    found = candidates(features)
    unclaimed = [c for c in found if "outside every feature" in c.reason]
    assert len(unclaimed) >= 5, len(unclaimed)  # the case has specks
    assert max(np.prod(s) for s in shapes) < 0.5 * vol.size, "a piece was split on the whole volume"
    bar = [c for c in found if c.is_specimen]
    assert len(bar) == 1 and bar[0].stats.voxel_count >= 0.8 * 52 * 8 * 8 / np.prod(features.scale)


def _coil(shape=(40, 80, 80), radius=4.0, centre=(40.0, 40.0)):
    """A tube coiled through three quarters of a circle of radius 25: by its principal axes about as wide as long,
    along itself 2 pi 25 * 3/4 / (sqrt(3) 4) = 17 (written analytically)."""
    zz, yy, xx = np.mgrid[:shape[0], :shape[1], :shape[2]].astype(float)
    rho = np.hypot(yy - centre[0], xx - centre[1])
    ang = np.arctan2(yy - centre[0], xx - centre[1])
    return (np.hypot(rho - 25.0, zz - 20) <= radius) & (ang > -np.pi * 0.75)


def _along(reason: str) -> float:
    return float(reason.split("along itself")[0].rstrip().split(" ")[-1])


def test_a_coiled_body_alone_in_its_scan_is_taken_with_its_length_along_itself():
    # before: rejected as "not elongated" (1.3 by its principal axes), with the hint to select it
    tube = _coil()
    vol = np.where(tube, 1000.0, 100.0).astype(np.float32)
    features = _features(type("Tank", (), {"volume": vol})())
    found = [c for c in candidates(features) if c.stats is not None and c.stats.voxel_count > 0.5 * tube.sum()]
    assert len(found) == 1 and found[0].is_specimen, found
    reason = found[0].reason
    assert reason.startswith("curved or coiled") and 0.8 * 17 <= _along(reason) <= 1.2 * 17, reason


def _coil_and_bar():
    tube = _coil(shape=(60, 80, 80))
    bar = np.zeros_like(tube)
    bar[48:56, 10:70, 36:44] = True  # 8 x 60 x 8: elongated, about 2/3 of the coil's voxels
    return tube, bar


def test_a_coiled_body_beside_an_elongated_one_is_unresolved_with_where_to_click():
    # among other specimens a body curved like this may be two touching at an angle: not taken, but not rejected
    # either (before: "rejected", and a run of every specimen was a success without it); the reason says how long
    # it is along itself, what to do and a point inside it
    tube, bar = _coil_and_bar()
    vol = np.where(tube | bar, 1000.0, 100.0).astype(np.float32)
    features = _features(type("Tank", (), {"volume": vol})())
    found = [c for c in candidates(features) if c.stats is not None and c.stats.voxel_count > 0.5 * bar.sum()]
    coil = [c for c in found if c.stats.elongation < 3]
    assert len(coil) == 1 and coil[0].status == "unresolved" and not coil[0].is_specimen, found
    reason = coil[0].reason
    assert reason.startswith("not elongated") and "--select" in reason, reason
    assert 0.8 * 17 <= _along(reason) <= 1.2 * 17, reason
    point = tuple(int(v) for v in reason.split("a point inside it: ")[1].rstrip(")").split(","))
    assert tube[point], (point, reason)
    assert any(c.is_specimen and c.stats.elongation >= 3 for c in found), found


def test_run_all_with_an_unresolved_candidate_is_not_a_success(tmp_path):
    # the CLI's --all: the bar straightened, the coil a row of its own on stderr and in specimens.csv, exit 3
    import csv

    from napari_unwind.cli import main
    from napari_unwind.io import write_volume

    tube, bar = _coil_and_bar()
    vol = np.where(tube | bar, 1000.0, 100.0) + np.random.default_rng(0).normal(0, 20, tube.shape)
    scan = write_volume(vol.astype(np.float32), tmp_path / "coil_and_bar.nrrd")
    code = main(["run", str(scan), "--all", "-o", str(tmp_path / "out"), "-q"])
    with open(tmp_path / "out" / "specimens.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    statuses = sorted(r["status"] for r in rows if r["status"] != "rejected")
    assert statuses == ["ok", "unresolved"], rows
    assert code == 3
    assert not list((tmp_path / "out").glob("specimen-*[!1].zarr")), sorted((tmp_path / "out").iterdir())


def test_unwind_segment_lists_an_unresolved_candidate_as_such(tmp_path, capsys):
    # the same rules on every face: `unwind segment` showed the coil as "-", as if nothing were there
    from napari_unwind.cli import main
    from napari_unwind.io import write_volume

    tube, bar = _coil_and_bar()
    vol = np.where(tube | bar, 1000.0, 100.0) + np.random.default_rng(0).normal(0, 20, tube.shape)
    scan = write_volume(vol.astype(np.float32), tmp_path / "coil_and_bar.nrrd")
    assert main(["segment", str(scan), "-o", str(tmp_path / "seg.zarr")]) == 0
    out = capsys.readouterr().out
    kinds = [line.split()[-1] for line in out.splitlines() if line.split() and line.split()[0].isdigit()]
    assert kinds.count("unresolved") == 1 and kinds.count("specimen") == 1, out
    assert "a point inside it: " in out, out


def test_a_coiled_body_cut_by_the_scan_is_not_taken():
    # a chest CT's torso, cut by the field of view, is about as long along itself (6.9) as a curled specimen: a
    # body the scan's faces cut is left to a click or a mask
    tube = _coil(centre=(40.0, 22.0))  # the coil runs off the scan at x = 0 over its last 28 degrees
    assert tube[:, :, 0].any()
    vol = np.where(tube, 1000.0, 100.0).astype(np.float32)
    features = _features(type("Tank", (), {"volume": vol})())
    found = [c for c in candidates(features) if c.stats is not None and c.stats.voxel_count > 0.5 * tube.sum()]
    assert len(found) == 1 and found[0].status == "rejected", found
    assert "along itself" in found[0].reason and "cut by the scan's faces" in found[0].reason, found[0].reason


def test_a_curved_plate_alone_is_not_taken():
    # a quarter-turn shell 3 voxels thick and 24 high (a piece of a tank's wall inside the field of view): far more
    # elongated along itself than by its principal axes, but its section is a strip, not a tube's disc
    zz, yy, xx = np.mgrid[:40, :80, :80].astype(float)
    rho = np.hypot(yy - 40, xx - 40)
    ang = np.arctan2(yy - 40, xx - 40)
    plate = (np.abs(rho - 25.0) <= 1.5) & (np.abs(zz - 20) <= 12) & (ang > -np.pi * 0.75)
    vol = np.where(plate, 1000.0, 100.0).astype(np.float32)
    features = _features(type("Tank", (), {"volume": vol})())
    found = [c for c in candidates(features) if c.stats is not None and c.stats.voxel_count > 0.5 * plate.sum()]
    assert found and not any(c.is_specimen for c in found), found
    assert any("a curved plate" in c.reason for c in found), [c.reason for c in found]


# The distance transform has no saddle where a thin tail lies along a thick neighbour: the split gave the tail to the
# neighbour (packed tank 7104: fish 2's tail went with fish 6, which came out partial with "a branch", and fish 2 ok
# holding 97.2 % of itself; tests/test_pipeline_tanks.py runs it end to end). The join tree's features keep the tail
# with its fish, and the parts follow them. The rule on hand-made parts: each case's expected parts are written out.
def test_a_features_stray_piece_follows_it_to_its_part_and_a_shared_feature_moves_nothing():
    from napari_unwind.segmentation._candidates import _parts_follow_features

    def run(parts, labels):
        p = np.asarray(parts, np.int32).reshape(1, 1, -1)
        return _parts_follow_features(p, int(p.max()), np.asarray(labels, np.int32).reshape(1, 1, -1))[0, 0].tolist()

    # feature 3: 5 voxels in part 1, 1 in part 2 beside it -> that one moves (part 2 keeps its own feature 4)
    assert run([1, 1, 1, 1, 1, 2, 2, 2, 2, 2], [3, 3, 3, 3, 3, 3, 4, 4, 4, 4]) == [1] * 6 + [2] * 4
    # a feature split between two parts (two fish in one feature: 5 and 3) moves nothing
    assert run([1, 1, 1, 1, 1, 2, 2, 2, 2, 2], [3, 3, 3, 3, 3, 3, 3, 3, 0, 0]) == [1] * 5 + [2] * 5
    # a stray piece apart from the feature's part stays where it is
    assert run([1, 1, 1, 1, 1, 2, 2, 2, 2, 2], [3, 3, 3, 3, 3, 0, 0, 0, 3, 0]) == [1] * 5 + [2] * 5
    # what a move cuts off its part goes to the part it touches most: feature 3 is row 0 (part 1) and one voxel of
    # part 2's row, whose move leaves part 2's first voxel alone
    parts = np.zeros((1, 3, 7), np.int32)
    parts[0, 0], parts[0, 1] = 1, 2
    labels = np.zeros_like(parts)
    labels[0, 0], labels[0, 1, 1] = 3, 3
    out = _parts_follow_features(parts, 2, labels)
    assert out[0, 1].tolist() == [1, 1, 2, 2, 2, 2, 2] and (out[0, 0] == 1).all() and (out[0, 2] == 0).all()
