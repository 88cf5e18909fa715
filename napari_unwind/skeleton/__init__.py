"""Skeleton solve: from a mask and two clicks to the keyframes of a deformation (docs/design.md section 4).

- :func:`estimate_deformation` / :func:`estimate_deformation_iter`: the paper's pipeline (working mask,
  connectivity by dilation, a deterministic lattice tet mesh cut at the mask's isosurface (or the paper's
  marching cubes + fTetWild, which varies run to run), cotangent-Laplacian harmonic function, level-set
  centroids by marching tets, smoothing, resampling, parallel-transport frames, prism-subdivision keyframes),
  plus the automatic twist, suggested endpoints and the cage and padding proposal.
- :func:`suggest_endpoints`, :func:`snap_to_mask`: head and tail proposals, clicks moved into the mask.
- :func:`estimate_twist`, :func:`apply_twist`: cross-section orientation along the curve.
- :func:`propose_cage`: cage half-extents and end padding from the cross-sections; :func:`fit_cages`: each
  keyframe's cage, per side, from the sections there.
"""

from ._api import SkeletonResult, WorkingMask, estimate_deformation, estimate_deformation_iter, working_mask
from ._cage import fit_cages, propose_cage
from ._curve import regularise_ends, resample_curve, select_keyframes, smooth_curve
from ._endpoints import snap_to_mask, suggest_endpoints
from ._harmonic import TetMesh, harmonic_field, lattice_tet_mesh, level_set_centroids, surface_mesh, tet_mesh
from ._twist import apply_twist, estimate_twist

__all__ = [
    "SkeletonResult",
    "TetMesh",
    "WorkingMask",
    "apply_twist",
    "estimate_deformation",
    "estimate_deformation_iter",
    "estimate_twist",
    "fit_cages",
    "harmonic_field",
    "lattice_tet_mesh",
    "level_set_centroids",
    "propose_cage",
    "regularise_ends",
    "resample_curve",
    "select_keyframes",
    "smooth_curve",
    "snap_to_mask",
    "suggest_endpoints",
    "surface_mesh",
    "tet_mesh",
    "working_mask",
]
