"""Topology-based segmentation (TopoAngler's join tree): one feature per specimen, fast enough for a whole scan.

1. :func:`join_tree` builds the superlevel-set merge tree of a volume at a working resolution (default: the
   pyramid level with every side <= 256, lightly smoothed) and precomputes its hypervolume pruning.
2. :meth:`JoinTree.simplify` keeps the ``k`` most important features (1..100, default 5) as a label volume with
   statistics, without recomputing the tree; :func:`segment` does both.
3. :func:`select` turns features chosen by seed points (full-resolution voxel coordinates) or ids into a mask;
   :func:`refine_mask` / :func:`refine_mask_iter` upsample it to full resolution chunk by chunk and refine it
   with an isovalue.
4. :func:`candidates` gives every feature (or part of one) as a candidate specimen, kept or rejected with its
   reason (the one definition of a specimen); :func:`specimens` returns the statistics of the kept ones.
5. :func:`save_features` / :func:`load_features` keep a segmentation as OME-Zarr labels with its statistics;
   :meth:`JoinTree.to_npz` / :meth:`JoinTree.from_npz` cache a tree.
"""

from ._candidates import Candidate, candidates, specimen_isovalue, specimens
from ._common import MAX_FEATURES
from ._features import Features, FeatureStats, simplify
from ._jointree import JoinTree, join_tree, join_tree_iter, sweep_order
from ._segment import segment, segment_iter
from ._select import (
    check_segmentation_output,
    default_isovalue,
    load_features,
    refine_mask,
    refine_mask_iter,
    refine_mask_to,
    save_features,
    save_features_iter,
    select,
    selected_ids,
)

__all__ = [
    "MAX_FEATURES",
    "Candidate",
    "candidates",
    "check_segmentation_output",
    "default_isovalue",
    "FeatureStats",
    "Features",
    "JoinTree",
    "join_tree",
    "join_tree_iter",
    "load_features",
    "refine_mask",
    "refine_mask_iter",
    "refine_mask_to",
    "save_features",
    "save_features_iter",
    "segment",
    "segment_iter",
    "select",
    "selected_ids",
    "simplify",
    "specimen_isovalue",
    "specimens",
    "sweep_order",
]
