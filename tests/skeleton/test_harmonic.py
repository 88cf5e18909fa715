"""Surface, tet mesh, harmonic function and level-set centroids against analytic values."""

from __future__ import annotations

import numpy as np
import pytest

from napari_unwind.errors import InvalidInputError
from napari_unwind.skeleton import (
    TetMesh,
    harmonic_field,
    lattice_tet_mesh,
    level_set_centroids,
    surface_mesh,
    tet_mesh,
)
from napari_unwind.skeleton._harmonic import decimate_surface

UNIT_TET = TetMesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]), np.array([[0, 1, 2, 3]], np.int32),
                   (np.zeros((0, 3)), np.zeros((0, 3), int)))


@pytest.mark.parametrize("c", [0.1, 0.35, 0.5, 0.9])
def test_triangle_cut_of_the_unit_tet(c):
    # u = x + y + z: the level set is the triangle with corners c on each axis
    u = UNIT_TET.vertices.sum(axis=1)
    cent, area = level_set_centroids(UNIT_TET, u, np.array([c]))
    np.testing.assert_allclose(cent[0], [c / 3] * 3, atol=1e-12)
    np.testing.assert_allclose(area[0], np.sqrt(3) / 2 * c * c, rtol=1e-12)  # equilateral, side c * sqrt(2)


@pytest.mark.parametrize("c", [0.2, 0.5, 0.7])
def test_quad_cut_of_the_unit_tet(c):
    # u = x + y: two vertices on each side; the section x + y = c is a rectangle c*sqrt(2) by (1 - c)
    u = UNIT_TET.vertices[:, 0] + UNIT_TET.vertices[:, 1]
    cent, area = level_set_centroids(UNIT_TET, u, np.array([c]))
    np.testing.assert_allclose(area[0], np.sqrt(2) * c * (1 - c), rtol=1e-12)
    np.testing.assert_allclose(cent[0], [c / 2, c / 2, (1 - c) / 2], atol=1e-12)


def test_empty_level_is_nan():
    u = UNIT_TET.vertices.sum(axis=1)
    cent, area = level_set_centroids(UNIT_TET, u, np.array([-1.0, 2.0]))
    assert np.isnan(cent).all() and (area == 0).all()


def _cylinder_mask(length=60, radius=8.0, pad=4):
    n = int(2 * radius + 2 * pad)
    z, y, x = np.mgrid[: length + 2 * pad, :n, :n].astype(float)
    c = (n - 1) / 2
    return ((y - c) ** 2 + (x - c) ** 2 <= radius**2) & (z >= pad) & (z < pad + length), c


@pytest.fixture(scope="module")
def cylinder_mesh():
    mask, c = _cylinder_mask()
    V, F = surface_mesh(mask.astype(np.float32), spacing=(1.0, 1.0, 1.0))
    return tet_mesh(V, F), mask, c


def test_tet_mesh_of_a_cylinder_has_its_volume(cylinder_mesh):
    mesh, mask, _ = cylinder_mesh
    assert (mesh.tets >= 0).all() and mesh.tets.max() < len(mesh.vertices)
    p = mesh.vertices[mesh.tets]
    signed = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6
    assert (signed > 0).all()  # positively oriented
    assert mesh.volume == pytest.approx(np.pi * 8.0**2 * 60, rel=0.06)


def test_harmonic_level_sets_of_a_cylinder_are_cross_sections(cylinder_mesh):
    mesh, mask, c = cylinder_mesh
    head, tail = np.array([5.0, c, c]), np.array([62.0, c, c])
    u = harmonic_field(mesh, head, tail, anchor_radius=1.5)
    assert np.nanmin(u) >= -1e-6 and np.nanmax(u) <= 1 + 1e-6
    cents, areas = level_set_centroids(mesh, u, np.linspace(0.05, 0.95, 19))
    # by symmetry the centroids lie on the axis, in order from head to tail; near the point-like ends the mesh
    # vertex that holds the Dirichlet value may be off the axis (the mesh is coarse), which tilts the first and
    # last level sets, so only the middle is held to the axis closely
    levels_inner = slice(2, -2)  # u in [0.15, 0.85]: the first and last caps may wrap round the end vertex
    assert (np.diff(cents[levels_inner, 0]) > 0).all()
    np.testing.assert_allclose(cents[:, 1:], c, atol=4.0)
    mid = (cents[:, 0] > 20) & (cents[:, 0] < 48)
    assert mid.sum() >= 3
    np.testing.assert_allclose(cents[mid, 1:], c, atol=0.3)
    # away from the ends the level sets are (nearly) flat discs of radius 8
    np.testing.assert_allclose(areas[mid], np.pi * 8.0**2, rtol=0.1)


def test_harmonic_field_is_linear_between_end_faces():
    # Dirichlet on the whole end faces of a box (side walls free): the harmonic function is linear along it, and
    # linear functions are exact in the P1 finite elements behind the cotangent Laplacian, on any tet mesh
    corners = np.array([[z, y, x] for z in (0.0, 40.0) for y in (0.0, 8.0) for x in (0.0, 8.0)])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    mesh = tet_mesh(corners, faces, edge_length_fac=0.05)
    z = mesh.vertices[:, 0]
    # fTetWild keeps the surface within its envelope (epsilon x diagonal = 0.12 here), not exactly on it
    assert z.min() == pytest.approx(0.0, abs=0.15) and z.max() == pytest.approx(40.0, abs=0.15)
    # a ball far beyond each face, reaching 0.2 into the box, holds that face's vertices (nothing else)
    d = 1000.0
    u = harmonic_field(mesh, np.array([-d, 4.0, 4.0]), np.array([40.0 + d, 4.0, 4.0]), anchor_radius=d + 0.2)
    assert len(mesh.vertices) > 8
    np.testing.assert_allclose(u, np.clip(z / 40.0, 0, 1), atol=0.01)


def test_head_equal_tail_is_refused(cylinder_mesh):
    mesh, _, c = cylinder_mesh
    p = np.array([30.0, c, c])
    with pytest.raises(InvalidInputError, match="same mesh vertices"):
        harmonic_field(mesh, p, p, anchor_radius=1.0)


def test_decimation_keeps_the_shape(cylinder_mesh):
    mesh, _, _ = cylinder_mesh
    V, F = mesh.surface
    V2, F2 = decimate_surface(V, F, max_faces=1500)
    assert len(F2) <= 1500 < len(F)
    small = tet_mesh(V2, F2)
    assert small.volume == pytest.approx(mesh.volume, rel=0.05)
    same = decimate_surface(V, F, max_faces=len(F))
    assert same[0] is V and same[1] is F


def test_empty_occupancy_is_refused():
    with pytest.raises(InvalidInputError, match="no voxel"):
        surface_mesh(np.zeros((5, 5, 5), np.float32), spacing=(1.0, 1.0, 1.0))


# ---------------------------------------------------------------------------------------------------------------
# the deterministic lattice mesher (the default)
# ---------------------------------------------------------------------------------------------------------------

def _ball_occupancy(radius=9.0, n=25, centre=(12.3, 11.8, 12.1)):
    """The exact fraction of each voxel inside a ball (supersampled 4^3): its 0.5 isosurface is the sphere."""
    s = (np.arange(4) + 0.5) / 4 - 0.5
    g = np.mgrid[:n, :n, :n].astype(float)
    occ = np.zeros((n, n, n))
    for dz in s:
        for dy in s:
            for dx in s:
                r2 = (g[0] + dz - centre[0]) ** 2 + (g[1] + dy - centre[1]) ** 2 + (g[2] + dx - centre[2]) ** 2
                occ += r2 <= radius ** 2
    return (occ / 64).astype(np.float32)


def _signed_volumes(mesh):
    p = mesh.vertices[mesh.tets]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6


@pytest.mark.parametrize("cell", [1.0, 1.7, 3.0])
def test_lattice_mesh_of_a_ball_is_closed_conforming_and_has_its_volume(cell):
    mesh = lattice_tet_mesh(_ball_occupancy(), spacing=(1.0, 1.0, 1.0), cell=cell)
    assert (_signed_volumes(mesh) > 0).all()  # positively oriented, none flat
    # conforming: every interior triangle is shared by exactly two tets, so the boundary is a closed surface
    # (every boundary edge in exactly two boundary triangles) with Euler characteristic 2 (a sphere)
    V, F = mesh.surface
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    edges, counts = np.unique(e, axis=0, return_counts=True)
    assert (counts == 2).all()
    assert len(np.unique(F)) - len(edges) + len(F) == 2
    faces = np.sort(mesh.tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3), axis=1)
    assert np.unique(faces, axis=0, return_counts=True)[1].max() == 2
    # the boundary lies on the sphere within half a cell (marching cubes' accuracy at that step); a coarse
    # lattice's secants and the smoothing that widens the step to a cell lose volume on a convex body
    r = np.linalg.norm(V[np.unique(F)] - (12.3, 11.8, 12.1), axis=1)
    assert np.abs(r - 9.0).max() < 0.5 * cell
    assert abs((r - 9.0).mean()) < 0.1 * cell
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * 9.0 ** 3, rel=0.01 + 0.06 * (cell - 1))


def test_lattice_mesh_spacing_and_offset_are_physical():
    occ = _ball_occupancy()
    a = lattice_tet_mesh(occ, spacing=(1.0, 1.0, 1.0))
    b = lattice_tet_mesh(occ, spacing=(2.0, 0.5, 1.5), offset=(10.0, -3.0, 7.0))
    np.testing.assert_array_equal(a.tets, b.tets)
    np.testing.assert_allclose(b.vertices, a.vertices * (2.0, 0.5, 1.5) + (10.0, -3.0, 7.0), atol=1e-9)


@pytest.mark.parametrize("cell", [1.7, 2.3])
def test_lattice_mesh_of_a_tight_crop_is_the_mesh_of_the_whole(cell):
    # the working mask is cropped to the specimen's voxels, so its first and last voxels touch the array's faces;
    # outside the array counts as 0 and is interpolated up to the face (a node half a voxel out reads half the face
    # voxel), as in the uncropped array: the surface there must not move inward
    occ = _ball_occupancy()
    nz = np.argwhere(occ > 0)
    lo, hi = nz.min(axis=0), nz.max(axis=0) + 1
    tight = np.ascontiguousarray(occ[tuple(slice(a, b) for a, b in zip(lo, hi))])
    whole = lattice_tet_mesh(occ, spacing=(1.0, 1.0, 1.0), cell=cell)
    crop = lattice_tet_mesh(tight, spacing=(1.0, 1.0, 1.0), offset=tuple(float(a) for a in lo), cell=cell)
    assert crop.volume == pytest.approx(whole.volume, rel=1e-3)
    for axis in range(3):
        assert crop.surface[0][:, axis].min() == pytest.approx(whole.surface[0][:, axis].min(), abs=1e-6)


@pytest.mark.parametrize("cell", [1.0, 1.7])
def test_lattice_mesh_passes_the_patch_test(cell):
    # on a conforming P1 mesh the cotangent Laplacian of a linear function vanishes at every interior vertex
    # (its hat function is zero on the boundary), whatever the boundary's shape; a crack (a shared quad cut by
    # different diagonals on its two sides) or a flipped tet breaks it
    import igl

    mesh = lattice_tet_mesh(_ball_occupancy(), spacing=(1.0, 0.8, 1.3), cell=cell)
    L = igl.cotmatrix(mesh.vertices, mesh.tets.astype(np.int64))
    interior = np.ones(len(mesh.vertices), bool)
    interior[np.unique(mesh.surface[1])] = False
    assert interior.sum() > 100
    for axis in range(3):
        r = L @ mesh.vertices[:, axis]
        assert np.abs(r[interior]).max() < 1e-9 * np.abs(L).max()


def test_lattice_mesh_refuses_bad_options():
    occ = _ball_occupancy()
    with pytest.raises(InvalidInputError, match="no voxel"):
        lattice_tet_mesh(np.zeros((5, 5, 5), np.float32), spacing=(1.0, 1.0, 1.0))
    with pytest.raises(InvalidInputError, match=r"cell must be a number >= 1 \(voxels\), got 0.5"):
        lattice_tet_mesh(occ, spacing=(1.0, 1.0, 1.0), cell=0.5)
    with pytest.raises(InvalidInputError, match=r"snap must be in \(0, 0.5\), got 0.7"):
        lattice_tet_mesh(occ, spacing=(1.0, 1.0, 1.0), snap=0.7)


_SOLVE_SCRIPT = """
import hashlib, json, os, sys, warnings
import numpy as np
from napari_unwind.datasets import fish_phantom
from napari_unwind.skeleton import estimate_deformation
ph = fish_phantom(seed=5, curve="s-bend", twist=np.pi / 3, noise=0.05, tube=False)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    d = estimate_deformation(ph.mask, spacing=ph.spacing, volume=ph.volume)
print(hashlib.sha256(json.dumps(d.to_dict(), sort_keys=True).encode()).hexdigest())
"""


def test_skeleton_is_byte_identical_across_processes_and_thread_counts():
    # the same mask gives the same deformation in separate processes, with one BLAS/numba thread or several
    # (fTetWild gave a different mesh each run: 37, 37 and 40 keyframes on the aorta)
    import os
    import subprocess
    import sys

    digests = set()
    for threads in ("1", "2", "1"):
        env = dict(os.environ, OMP_NUM_THREADS=threads, OPENBLAS_NUM_THREADS=threads, NUMBA_NUM_THREADS=threads,
                   MKL_NUM_THREADS=threads)
        out = subprocess.run([sys.executable, "-c", _SOLVE_SCRIPT], env=env, capture_output=True, text=True,
                             timeout=300, check=True)
        digests.add(out.stdout.strip().splitlines()[-1])
    assert len(digests) == 1, digests
