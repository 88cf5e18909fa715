"""candidates(): one definition of a specimen, every feature reported with its status and reason (issue 18).

References are hand-built volumes whose specimens, containers and blobs follow from their construction.
"""

from __future__ import annotations

import numpy as np
import pytest
from _scenes import rods_in_tube

from napari_unwind.errors import InvalidInputError
from napari_unwind.segmentation import Candidate, candidates, segment, specimens


def _scene() -> tuple[np.ndarray, dict[str, np.ndarray]]:
    return rods_in_tube(ball_on_border=False)


def _which(features, parts):
    out = {}
    for name, m in parts.items():
        ids, counts = np.unique(features.labels[m], return_counts=True)
        out[name] = int(ids[np.argmax(counts)])
    return out


def test_every_feature_is_a_candidate_with_a_status_and_a_reason():
    vol, parts = _scene()
    features = segment(vol, features=5, smooth=0)
    which = _which(features, parts)
    found = candidates(features)
    assert all(isinstance(c, Candidate) for c in found)
    by_id = {i: c for c in found for i in c.ids}
    assert set(by_id) == set(which.values())
    for name in ("rod_a", "rod_b", "rod_out"):
        c = by_id[which[name]]
        assert c.status == "specimen" and c.reason == "", (name, c.reason)
        np.testing.assert_array_equal(c.working_mask(features), features.labels == which[name])
    assert by_id[which["tube"]].status == "rejected" and by_id[which["tube"]].reason.startswith("container")
    assert by_id[which["ball"]].status == "rejected"
    assert by_id[which["ball"]].reason.startswith("not elongated: ")
    assert [c.stats for c in found if c.status == "specimen"] == list(specimens(features))
    small = {i: c for c in candidates(features, min_voxels=500) for i in c.ids}
    n = features.stat(which["rod_out"]).voxel_count
    assert small[which["rod_out"]].reason == f"too small: {n} voxels < 500"


def test_candidates_refuses_bad_input_naming_the_value():
    vol, _ = _scene()
    features = segment(vol, features=3, smooth=0)
    with pytest.raises(InvalidInputError, match="needs Features"):
        candidates(vol)
    with pytest.raises(InvalidInputError, match=r"min_elongation.*0\.5"):
        candidates(features, min_elongation=0.5)
    with pytest.raises(InvalidInputError, match="min_elongation.*'x'"):
        candidates(features, min_elongation="x")
    with pytest.raises(InvalidInputError, match="min_voxels.*0"):
        candidates(features, min_voxels=0)
    with pytest.raises(InvalidInputError, match="min_voxels.*2.5"):
        candidates(features, min_voxels=2.5)
