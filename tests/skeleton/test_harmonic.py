"""Surface, tet mesh, harmonic function and level-set centroids against analytic values."""

from __future__ import annotations

import numpy as np
import pytest

from napari_unwind.errors import InvalidInputError
from napari_unwind.skeleton import (
    TetMesh,
    harmonic_field,
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
