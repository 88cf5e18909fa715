"""Separating touching structures on a phantom whose label map is derived by hand.

The phantom is piecewise constant: rods A (value 10), B (8) and C (6 or 7.5) of 5 x 5 voxels touch through
one-voxel necks (saddles), and a 2-voxel noise peak N touches two of them through necks of different heights. Everything
else is background at minus its Euclidean distance to the parts, so every background voxel has a higher
neighbour and the only maxima are the four plateaus.

What follows from the construction (the definitions in napari_unwind/segmentation/_jointree.py and _features.py):

- merge tree: a plateau's first voxel (C order) is its maximum; two components meet at a neck, the one with the
  higher maximum (elder) lives on;
- basins: a voxel joins the basin of its highest neighbour swept before it, so a neck joins the brighter part it
  touches; a pruned branch hands its basin to the basin it touches at its saddle (on the elder's side, the
  highest there), followed until a survivor; this is NOT its parent when the elder is further away;
- hypervolume = persistence x voxels: N (2 voxels) is pruned first, then C (125-150 voxels, persistence 4-5.5),
  then B (200 voxels, persistence 4);
- labels: a feature is cut at a threshold between its base (saddle) and its plateau (the half-maximum), so with
  every object value above its feature's base and the necks at or below it, the label map at ``k`` is exactly
  the union of the feature's parts, whatever the threshold inside that interval.

Planted one at a time in a copy of the code, each of these wrong rules fails here (tests/test_segmentation.py
without the real CT passes the first three): attach a dying branch to its parent (the elder) instead of the
basin it touches (5 of 5 cases fail); follow the parents instead of the attachments when simplifying (5 of 5);
attach to the lowest instead of the highest neighbour on the elder's side (the A-B junction case); a voxel joins
its lowest swept neighbour (5 of 5); follow an attachment one step instead of until a survivor (2 of 5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy import ndimage

from napari_unwind.segmentation import join_tree, segment, select

SHAPE = (7, 7, 30)
ROD = (slice(1, 6), slice(1, 6))  # the 5 x 5 cross-section of every rod


@dataclass(frozen=True)
class Case:
    name: str
    parts: dict[str, tuple[tuple, float]]  # name -> (index expression, value)
    k3: dict[str, int]  # expected label of every object part with k = 3 (necks are all 0)
    neck_basin_k3: dict[str, int]  # expected feature of each neck's basin with k = 3
    k2: dict[str, int]  # expected feature of every object's basin with k = 2 (C pruned too)
    parent: dict[str, str]  # the parent of each branch in the merge tree (the elder where it dies)
    attach: dict[str, str]  # the part whose basin each branch's basin is handed to (touched at its saddle)
    connectivities: tuple[int, ...] = (6, 26)


CASES = [
    # N sits between B and C, its neck to B (3) higher than its neck to C (2). At 3, A and B have already met
    # (neck 4), so N's parent is A, but it touches B: N belongs to B's feature. C (7.5, 125 voxels, born before
    # N) dies at its neck into the component holding N: its basin is handed to N's, a younger branch, i.e. on
    # to B when C is pruned too (k = 2: the attachments are followed until a survivor).
    Case(
        "noise nearer B",
        {
            "A": ((*ROD, slice(1, 9)), 10.0),
            "neck AB": ((3, 3, 9), 4.0),
            "B": ((*ROD, slice(10, 18)), 8.0),
            "neck BN": ((3, 3, 18), 3.0),
            "N": ((3, 3, slice(19, 21)), 7.0),
            "neck NC": ((3, 3, 21), 2.0),
            "C": ((*ROD, slice(22, 27)), 7.5),
        },
        k3={"A": 1, "B": 2, "N": 2, "C": 3},
        neck_basin_k3={"neck AB": 1, "neck BN": 2, "neck NC": 3},
        k2={"A": 1, "B": 2, "N": 2, "C": 2},
        parent={"B": "A", "N": "A", "C": "A"},
        attach={"B": "A", "N": "B", "C": "N"},
    ),
    # The mirror: N (5) now touches C through the higher neck (3) and B through the lower (2). N merges into C
    # first (C is the elder there): N belongs to C's feature. Its parent is C as well, so only the "other
    # neighbour" rule (B) is wrong here.
    Case(
        "noise nearer C",
        {
            "A": ((*ROD, slice(1, 9)), 10.0),
            "neck AB": ((3, 3, 9), 4.0),
            "B": ((*ROD, slice(10, 18)), 8.0),
            "neck BN": ((3, 3, 18), 2.0),
            "N": ((3, 3, slice(19, 21)), 5.0),
            "neck NC": ((3, 3, 21), 3.0),
            "C": ((*ROD, slice(22, 28)), 6.0),
        },
        k3={"A": 1, "B": 2, "N": 3, "C": 3},
        neck_basin_k3={"neck AB": 1, "neck BN": 2, "neck NC": 3},
        k2={"A": 1, "B": 2, "N": 2, "C": 2},
        parent={"B": "A", "N": "C", "C": "A"},
        attach={"B": "A", "N": "C", "C": "B"},
    ),
    # N (8.5, outside the rods) hangs off a neck (3) in the gap between A and B that touches A (10) and B (8):
    # at 3, A and B are one component, both on the elder's side; the neck's highest neighbour is A's, so N
    # belongs to A's feature. (Faces only: with 26-connectivity N would touch A and B diagonally.)
    Case(
        "noise at the A-B junction",
        {
            "A": ((*ROD, slice(1, 9)), 10.0),
            "neck AB": ((3, 3, 9), 4.0),
            "B": ((*ROD, slice(10, 18)), 8.0),
            "neck N": ((1, 1, 9), 3.0),
            "N": ((0, slice(1, 3), 9), 8.5),
            "neck BC": ((3, 3, 18), 2.0),
            "C": ((*ROD, slice(19, 25)), 6.0),
        },
        k3={"A": 1, "B": 2, "N": 1, "C": 3},
        neck_basin_k3={"neck AB": 1, "neck N": 1, "neck BC": 2},
        k2={"A": 1, "B": 2, "N": 1, "C": 2},
        parent={"B": "A", "N": "A", "C": "A"},
        attach={"B": "A", "N": "A", "C": "B"},
        connectivities=(6,),
    ),
]

PARAMS = [pytest.param(c, conn, id=f"{c.name}-{conn}") for c in CASES for conn in c.connectivities]


def _build(case: Case) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    v = np.zeros(SHAPE, np.float32)
    masks = {}
    for name, (where, value) in case.parts.items():
        m = np.zeros(SHAPE, bool)
        m[where] = True
        assert not (m & np.any(list(masks.values()) or [np.zeros(SHAPE, bool)], axis=0)).any(), name
        masks[name] = m
        v[m] = value
    parts = np.any(list(masks.values()), axis=0)
    dist = ndimage.distance_transform_edt(~parts)
    v[~parts] = -dist[~parts]
    return v, masks


def _expected_labels(case: Case, masks: dict[str, np.ndarray], labels: dict[str, int]) -> np.ndarray:
    out = np.zeros(SHAPE, np.uint16)
    for name, f in labels.items():
        out[masks[name]] = f
    return out


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))


def _first_voxel(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask.ravel())[0])


@pytest.mark.parametrize("case, connectivity", PARAMS)
def test_touching_objects_by_hand(case, connectivity):
    v, masks = _build(case)
    objects = [n for n in case.k3]
    assert objects == ["A", "B", "N", "C"]
    tree = join_tree(v, smooth=0, connectivity=connectivity)

    # the merge tree: one maximum per plateau, at its first voxel in C order
    assert tree.n_maxima == 4
    branch_of = {n: int(tree.branch.ravel()[_first_voxel(masks[n])]) for n in objects}
    assert sorted(int(tree.max_voxel[b]) for b in branch_of.values()) == sorted(
        _first_voxel(masks[n]) for n in objects
    )
    assert branch_of["A"] == 0  # the global maximum is the root
    value = {n: case.parts[n][1] for n in case.parts}
    # parents by the elder rule; attachments: the basin each branch touches at its saddle
    assert {n: int(tree.parent[branch_of[n]]) for n in case.parent} == {n: branch_of[p] for n, p in case.parent.items()}
    assert {n: int(tree.attach[branch_of[n]]) for n in case.attach} == {n: branch_of[p] for n, p in case.attach.items()}
    n_branch = branch_of["N"]
    # N is pruned first, then C, then B
    assert [int(b) for b in tree.prune_order] == [branch_of["N"], branch_of["C"], branch_of["B"]]

    # k = 3: A, B and C, N handed to the neighbour it touches at its saddle
    features = segment(v, features=3, smooth=0, connectivity=connectivity)
    expected = _expected_labels(case, masks, case.k3)
    for name, f in case.k3.items():
        if name != "N":
            assert _dice(features.labels == f, expected == f) == 1.0, (name, f)
    np.testing.assert_array_equal(features.labels, expected)
    assert features.feature_of_branch[n_branch] == case.k3["N"]
    for neck, f in case.neck_basin_k3.items():  # each neck joins the basin of its brightest neighbour
        assert features.basins([f])[masks[neck]].all(), neck
    # the thresholds lie where the construction says the label map cannot depend on them: at or above each
    # feature's base (its saddle), below its lowest object value
    for s in features.stats:
        lowest = min(value[n] for n, f in case.k3.items() if f == s.id)
        assert s.base <= s.threshold < lowest, s
    # clicking on N chooses the feature it was handed to, with every part of it
    mask = select(features, seeds=np.argwhere(masks["N"])[:1])
    np.testing.assert_array_equal(mask, expected == case.k3["N"])

    # k = 4: N is its own feature 4 and nothing else moves
    f4 = tree.simplify(4)
    np.testing.assert_array_equal(f4.labels, _expected_labels(case, masks, {**case.k3, "N": 4}))

    # k = 2: C is pruned too; its basin, and N's, go where they touch, followed until a survivor
    f2 = tree.simplify(2)
    for name, f in case.k2.items():
        assert f2.basins([f])[masks[name]].all(), (name, f)
