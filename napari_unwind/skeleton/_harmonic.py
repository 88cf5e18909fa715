"""The paper's centreline: tet mesh, harmonic function, level-set centroids.

docs/design.md section 4, steps 3-5: a tet mesh of the (box-averaged) mask, the deterministic
:func:`lattice_tet_mesh` by default (the paper's marching cubes + fTetWild, :func:`surface_mesh` and
:func:`tet_mesh`, give a different mesh on every run), the cotangent Laplacian of the tet mesh (libigl) with
Dirichlet values 0 at the head and 1 at the tail, and the area-weighted centroids of the isosurfaces of the
solution, cut tet by tet ("marching tets", numpy).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from ..errors import InvalidInputError
from ..progress import checkpoint

__all__ = ["TetMesh", "surface_mesh", "decimate_surface", "tet_mesh", "lattice_tet_mesh", "harmonic_field",
           "level_set_centroids"]


@dataclass(frozen=True)
class TetMesh:
    """A tetrahedral mesh in physical coordinates.

    Attributes
    ----------
    vertices : ndarray, shape (P, 3)
        Vertex positions (physical units, array axis order).
    tets : ndarray of int32, shape (Q, 4)
        Positively oriented tetrahedra.
    surface : tuple of ndarray
        The triangle surface ``(vertices (N, 3), faces (M, 3))`` it was built from.
    """

    vertices: np.ndarray
    tets: np.ndarray
    surface: tuple[np.ndarray, np.ndarray]

    @property
    def volume(self) -> float:
        """Total volume of the tetrahedra."""
        p = self.vertices[self.tets]
        return float(np.abs(np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]),
                                      p[:, 3] - p[:, 0])).sum() / 6.0)


def surface_mesh(
    occupancy: np.ndarray, *, spacing: tuple[float, float, float], offset: tuple[float, float, float] = (0, 0, 0),
    step_size: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Closed marching-cubes surface of an occupancy volume at the 0.5 isovalue.

    Parameters
    ----------
    occupancy : ndarray of float, shape (N0, N1, N2)
        Values in [0, 1] (a mask or its box average).
    spacing : tuple of 3 float
        Physical size of one voxel of ``occupancy``.
    offset : tuple of 3 float
        Physical position of voxel (0, 0, 0).
    step_size : int
        Marching-cubes step (larger gives fewer triangles).

    Returns
    -------
    vertices : ndarray, shape (N, 3)
        Physical positions.
    faces : ndarray of int, shape (M, 3)
    """
    from skimage.measure import marching_cubes

    padded = np.pad(np.asarray(occupancy, dtype=np.float32), 1)  # a zero border closes the surface
    if not padded.max() > 0.5:
        raise InvalidInputError("the mask has no voxel left at the working resolution; the specimen is too thin "
                                "for it: pass a finer working resolution (max_side)")
    verts, faces, _, _ = marching_cubes(padded, 0.5, spacing=tuple(float(s) for s in spacing),
                                        step_size=int(step_size), allow_degenerate=False)
    verts = verts - np.asarray(spacing, dtype=float) + np.asarray(offset, dtype=float)
    return verts.astype(np.float64), faces.astype(np.int64)


def decimate_surface(vertices: np.ndarray, faces: np.ndarray, *, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Reduce a triangle surface to at most ``max_faces`` triangles by edge collapse (``igl.decimate``).

    Surfaces with no more triangles than that are returned unchanged.
    """
    import igl

    if len(faces) <= max_faces:
        return vertices, faces
    U, G, _, _ = igl.decimate(np.ascontiguousarray(vertices, dtype=np.float64),
                              np.ascontiguousarray(faces, dtype=np.int64), int(max_faces))
    if len(G) < 4:  # nothing usable left: keep the full surface
        return vertices, faces
    return np.asarray(U, dtype=np.float64), np.asarray(G, dtype=np.int64)


def tet_mesh(
    vertices: np.ndarray, faces: np.ndarray, *, edge_length_fac: float = 0.1, epsilon: float = 3e-3,
    max_iterations: int = 5, stop_energy: float = 20.0,
) -> TetMesh:
    """Tetrahedralise a closed surface with fTetWild (pytetwild), sized for speed.

    ``edge_length_fac`` and ``epsilon`` are relative to the bounding-box diagonal (fTetWild's options). The
    defaults trade mesh quality for time (about 1 s for 3000 triangles here, against 5 s at pytetwild's
    defaults, with the same centreline to 0.01 voxel on the phantoms): the harmonic function only needs the
    boundary followed closely (the envelope) and a few tets across the body.
    """
    from .._compat import tetrahedralize

    V, T = tetrahedralize(vertices, faces, edge_length_fac=edge_length_fac, epsilon=epsilon,
                          max_iterations=max_iterations, stop_energy=stop_energy)
    if len(T) == 0:
        raise InvalidInputError(f"the tet mesher produced no tetrahedra from a surface of {len(faces)} triangles; "
                                "the mask is too small or too thin at the working resolution")
    V, T = _largest_component(V, T)
    return TetMesh(V, T, (vertices, faces))



# Kuhn (Freudenthal) subdivision of the unit cube into 6 tets along its main diagonal: every cube of the lattice
# uses the same one, so neighbouring cubes share their faces' triangles (a conforming mesh).
_KUHN = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])
_CORNERS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])
# Dompierre et al. (1999): a prism (bottom 0 1 2, top 3 4 5, lateral edges i - i+3) turned so that its vertex of
# smallest global index is vertex 0, then cut into 3 tets by the diagonal of the far quad through its smallest
# vertex. Neighbours then cut their shared quads alike, whatever the order they are visited in.
_PRISM_TURN = np.array([[0, 1, 2, 3, 4, 5], [1, 2, 0, 4, 5, 3], [2, 0, 1, 5, 3, 4],
                        [3, 5, 4, 0, 2, 1], [4, 3, 5, 1, 0, 2], [5, 4, 3, 2, 1, 0]])
_PRISM_A = np.array([[0, 1, 2, 5], [0, 1, 5, 4], [0, 4, 5, 3]])
_PRISM_B = np.array([[0, 1, 2, 4], [0, 4, 2, 5], [0, 4, 5, 3]])


def _split_prisms(prisms: np.ndarray) -> np.ndarray:
    """Cut prisms ``(n, 6)`` of global vertex ids into 3 tets each, consistently across shared quads."""
    if len(prisms) == 0:
        return np.empty((0, 4), dtype=np.int64)
    turned = np.take_along_axis(prisms, _PRISM_TURN[np.argmin(prisms, axis=1)], axis=1)
    first = np.minimum(turned[:, 1], turned[:, 5]) < np.minimum(turned[:, 2], turned[:, 4])
    tets = np.where(first[:, None, None], turned[:, _PRISM_A], turned[:, _PRISM_B])
    return tets.reshape(-1, 4)


def lattice_tet_mesh(
    occupancy: np.ndarray, *, spacing: tuple[float, float, float], offset: tuple[float, float, float] = (0, 0, 0),
    cell: float = 1.0, snap: float = 0.05,
) -> TetMesh:
    """A deterministic tet mesh of ``occupancy >= 0.5``: a lattice cut at the isosurface (marching tets).

    The lattice of step ``cell`` (working voxels) is split into Kuhn tetrahedra; each tet with all four nodes
    inside is kept, and each tet the 0.5 isosurface crosses is clipped to its inside part (a tet or a prism cut
    into three), the cut points placed on its edges by linear interpolation, as marching cubes places its
    vertices. A lattice coarser than the voxels samples the occupancy smoothed by a Gaussian of 0.4 cells, so
    that the step at the surface spans a cell and the cut follows it within a fraction of one. Node values
    within ``snap`` of the isovalue are moved to ``0.5 +- snap`` first, so that no cut point falls on a node
    and no tet is flat. Pure numpy on the input alone: the same occupancy gives the same mesh,
    byte for byte, in any process and with any number of threads (fTetWild does not, even with one thread).

    Parameters
    ----------
    occupancy : ndarray of float, shape (N0, N1, N2)
        Values in [0, 1] (a mask or its box average); outside the array counts as 0.
    spacing : tuple of 3 float
        Physical size of one voxel of ``occupancy``.
    offset : tuple of 3 float
        Physical position of voxel (0, 0, 0).
    cell : float
        Lattice step, in voxels of ``occupancy`` (>= 1: coarser lattices for large bodies).
    snap : float
        Smallest distance of a node's value from the isovalue, in (0, 0.5).

    Returns
    -------
    TetMesh
        Positively oriented tets of the largest connected piece; ``surface`` is its boundary.
    """
    occ = np.asarray(occupancy, dtype=np.float32)
    if occ.ndim != 3:
        raise InvalidInputError(f"occupancy must be a 3D array, got shape {occ.shape}")
    if not (np.isfinite(cell) and cell >= 1):
        raise InvalidInputError(f"cell must be a number >= 1 (voxels), got {cell!r}")
    if not 0 < snap < 0.5:
        raise InvalidInputError(f"snap must be in (0, 0.5), got {snap!r}")
    inside_vox = np.argwhere(occ >= 0.5)
    if inside_vox.size == 0:
        raise InvalidInputError("the mask has no voxel left at the working resolution; the specimen is too thin "
                                "for it: pass a finer working resolution (max_side)")
    lo = inside_vox.min(axis=0) - 1.0
    hi = inside_vox.max(axis=0) + 1.0
    n = np.floor((hi - lo) / cell).astype(np.int64) + 2  # nodes per axis, one cell beyond the body each side
    grids = np.meshgrid(*(lo[a] + cell * np.arange(n[a]) for a in range(3)), indexing="ij")
    coords = np.stack([g.ravel() for g in grids])  # (3, nodes), voxel coordinates
    if cell > 1:  # a step sharper than the lattice would put the cut anywhere within a cell: widen it to one
        # (on a margin of zeros first: the working mask is cropped to the body, whose blur spills past the crop)
        margin = int(math.ceil(4.0 * 0.4 * cell)) + 1
        occ = ndi.gaussian_filter(np.pad(occ, margin), sigma=0.4 * cell, mode="constant", cval=0.0)
        at = coords + margin
    else:
        at = coords
    # outside the array is 0, interpolated up to its faces ("grid-constant"; "constant" reads 0 from the last
    # voxel's centre outward, moving the surface of a body cropped to its voxels half a voxel in)
    phi = ndi.map_coordinates(occ, at, order=1, mode="grid-constant", cval=0.0).astype(np.float64) - 0.5
    phi = np.where(phi >= 0, np.maximum(phi, snap), np.minimum(phi, -snap))
    inside = phi > 0
    strides = np.array([n[1] * n[2], n[2], 1], dtype=np.int64)
    # cubes (by their lowest corner) with at least one node inside
    cube_any = np.zeros(tuple(n - 1), bool)
    ins3 = inside.reshape(tuple(n))
    for c in _CORNERS:
        cube_any |= ins3[c[0]:c[0] + n[0] - 1, c[1]:c[1] + n[1] - 1, c[2]:c[2] + n[2] - 1]
    base = np.argwhere(cube_any) @ strides
    corner_off = _CORNERS @ strides
    tets = (base[:, None, None] + corner_off[_KUHN][None]).reshape(-1, 4)  # global node ids
    tin = inside[tets]
    count = tin.sum(axis=1)
    # each tet's vertices ordered inside first (stable, so the order is fixed by the lattice alone)
    order = np.argsort(~tin, axis=1, kind="stable")
    tets = np.take_along_axis(tets, order, axis=1)
    nn = int(np.prod(n))

    cut_keys: list[np.ndarray] = []

    def cut(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Provisional ids of the cut points on edges (inside a, outside b): keyed by the edge."""
        key = a * nn + b
        cut_keys.append(key)
        return key

    pieces = [tets[count == 4]]
    t1 = tets[count == 1]
    k1 = [cut(t1[:, 0], t1[:, j]) for j in (1, 2, 3)]
    t3 = tets[count == 3]
    k3 = [cut(t3[:, j], t3[:, 3]) for j in (0, 1, 2)]
    t2 = tets[count == 2]
    k2 = [cut(t2[:, 0], t2[:, 2]), cut(t2[:, 0], t2[:, 3]), cut(t2[:, 1], t2[:, 2]), cut(t2[:, 1], t2[:, 3])]
    keys = np.unique(np.concatenate(cut_keys)) if cut_keys else np.empty(0, np.int64)

    def ids(k: np.ndarray) -> np.ndarray:
        return nn + np.searchsorted(keys, k)

    pieces.append(np.stack([t1[:, 0], *(ids(k) for k in k1)], axis=1))
    pieces.append(_split_prisms(np.stack([t3[:, 0], t3[:, 1], t3[:, 2], *(ids(k) for k in k3)], axis=1)))
    pieces.append(_split_prisms(np.stack([t2[:, 0], ids(k2[0]), ids(k2[1]), t2[:, 1], ids(k2[2]), ids(k2[3])],
                                         axis=1)))
    T = np.concatenate(pieces).astype(np.int64)
    a, b = keys // nn, keys % nn
    t = phi[a] / (phi[a] - phi[b])
    cpts = coords[:, a].T + t[:, None] * (coords[:, b] - coords[:, a]).T
    P = np.concatenate([coords.T, cpts])
    used = np.unique(T)
    remap = np.full(len(P), -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    V = P[used] * np.asarray(spacing, dtype=float) + np.asarray(offset, dtype=float)
    T = remap[T]
    p = V[T]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    flip = vol < 0
    T[flip] = T[flip][:, [0, 1, 3, 2]]
    T = T[np.abs(vol) > 1e-9 * float(np.prod(spacing)) * cell ** 3]
    V, T = _largest_component(V, T.astype(np.int32))
    return TetMesh(V, T, _boundary(V, T))


def _boundary(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The boundary triangles of a tet mesh (faces in one tet only)."""
    f = T[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
    s = np.sort(f, axis=1)
    _, first, cnt = np.unique(s, axis=0, return_index=True, return_counts=True)
    return V, f[first[cnt == 1]].astype(np.int64)


def _largest_component(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the tets of the largest face-or-vertex-connected piece (islands of the surface, such as a speck at a
    thin tip, would otherwise hold an end's Dirichlet value apart from the body)."""
    from scipy.sparse.csgraph import connected_components

    rows = np.repeat(np.arange(len(T)), 4)
    g = sp.csr_matrix((np.ones(rows.size), (rows, T.ravel())), shape=(len(T), len(V)))
    ncomp, lab = connected_components(g @ g.T, directed=False)
    if ncomp > 1:
        T = T[lab == np.argmax(np.bincount(lab))]
    used = np.unique(T)
    remap = np.full(len(V), -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return V[used], remap[T].astype(np.int32)


def _anchor_vertices(vertices: np.ndarray, point: np.ndarray, radius: float) -> np.ndarray:
    """Vertices within ``radius`` of ``point``, at least the nearest one."""
    tree = cKDTree(vertices)
    near = np.asarray(tree.query_ball_point(point, radius), dtype=np.int64)
    if near.size == 0:
        near = np.array([tree.query(point)[1]], dtype=np.int64)
    return near


def harmonic_field(
    mesh: TetMesh, head: np.ndarray, tail: np.ndarray, *, anchor_radius: float,
) -> np.ndarray:
    """The harmonic function on the mesh with ``u = 0`` at the head and ``u = 1`` at the tail.

    Parameters
    ----------
    mesh : TetMesh
    head, tail : ndarray, shape (3,)
        Physical positions of the two ends.
    anchor_radius : float
        Vertices within this distance of an end take its Dirichlet value (the nearest vertex at least).

    Returns
    -------
    u : ndarray, shape (P,)
        The solution at every vertex (vertices in no tet of the head's or tail's component get NaN).
    """
    import igl

    V, T = mesh.vertices, mesh.tets
    h_idx = _anchor_vertices(V, np.asarray(head, float), anchor_radius)
    t_idx = _anchor_vertices(V, np.asarray(tail, float), anchor_radius)
    t_idx = np.setdiff1d(t_idx, h_idx)
    if t_idx.size == 0:
        raise InvalidInputError("the head and the tail fall on the same mesh vertices; click them farther apart")
    L = -igl.cotmatrix(V, T.astype(np.int64))  # positive semidefinite
    L = sp.csr_matrix(L)
    n = len(V)
    used = np.zeros(n, bool)
    used[T.ravel()] = True
    fixed = np.zeros(n, bool)
    fixed[h_idx] = True
    fixed[t_idx] = True
    values = np.zeros(n)
    values[t_idx] = 1.0
    free = np.flatnonzero(used & ~fixed)
    fix = np.flatnonzero(fixed)
    A = L[free][:, free].tocsc()
    b = -(L[free][:, fix] @ values[fix])
    # Vertices not connected to a Dirichlet vertex make A singular: keep only the component of the anchors.
    from scipy.sparse.csgraph import connected_components

    ncomp, lab = connected_components(L, directed=False)
    keep_labels = np.unique(lab[fix])
    u = np.full(n, np.nan)
    if ncomp > 1:
        sel = np.isin(lab[free], keep_labels)
        free = free[sel]
        A = L[free][:, free].tocsc()
        b = -(L[free][:, fix] @ values[fix])
    u[fix] = values[fix]
    if free.size:
        u[free] = spla.splu(A).solve(np.asarray(b, dtype=float))
    return u


def _cut_points(p: np.ndarray, f: np.ndarray, a: int, b: int, level: float) -> np.ndarray:
    """Where the isosurface crosses edge (a, b) of each tet: p (n, 4, 3) sorted vertices, f (n, 4) values."""
    fa, fb = f[:, a], f[:, b]
    t = (level - fa) / np.where(fb > fa, fb - fa, 1.0)
    return p[:, a] + t[:, None] * (p[:, b] - p[:, a])


def _tri_area_centroid(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    return area, (a + b + c) / 3.0


def level_set_centroids(mesh: TetMesh, u: np.ndarray, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted centroids of the isosurfaces ``u = level`` (marching tets).

    Each tet crossed by a level contributes a triangle (one vertex on one side) or a quad (two and two), cut
    on its edges by linear interpolation; the centroid of a level is the area-weighted mean of the centroids of
    its pieces.

    Parameters
    ----------
    mesh : TetMesh
    u : ndarray, shape (P,)
        Values at the vertices (NaN for vertices of no interest: tets touching them are skipped).
    levels : ndarray, shape (k,)
        Isovalues.

    Returns
    -------
    centroids : ndarray, shape (k, 3)
        NaN rows for empty level sets.
    areas : ndarray, shape (k,)
        Area of each isosurface (0 where empty).
    """
    T = mesh.tets
    fv = u[T]
    ok = np.isfinite(fv).all(axis=1)
    T, fv = T[ok], fv[ok]
    order = np.argsort(fv, axis=1)
    f = np.take_along_axis(fv, order, axis=1)
    p = mesh.vertices[np.take_along_axis(T, order, axis=1)]
    levels = np.asarray(levels, dtype=float)
    centroids = np.full((len(levels), 3), np.nan)
    areas = np.zeros(len(levels))
    # tets sorted by their smallest value: each level only looks at the tets whose range holds it
    by_min = np.argsort(f[:, 0])
    fmin_sorted = f[by_min, 0]
    for i, c in enumerate(levels):
        checkpoint()
        cand = by_min[: np.searchsorted(fmin_sorted, c, side="left")]
        cand = cand[f[cand, 3] > c]
        if cand.size == 0:
            continue
        ff, pp = f[cand], p[cand]
        below = (ff < c).sum(axis=1)
        acc_a = 0.0
        acc_c = np.zeros(3)
        # one vertex below (cut edges 01, 02, 03) or one above (03, 13, 23): a triangle
        for count, edges in ((1, ((0, 1), (0, 2), (0, 3))), (3, ((0, 3), (1, 3), (2, 3)))):
            sel = below == count
            if sel.any():
                q, g = pp[sel], ff[sel]
                a, cen = _tri_area_centroid(*(_cut_points(q, g, e0, e1, c) for e0, e1 in edges))
                acc_a += a.sum()
                acc_c += (a[:, None] * cen).sum(axis=0)
        two = below == 2
        if two.any():
            q, g = pp[two], ff[two]
            e02, e03 = _cut_points(q, g, 0, 2, c), _cut_points(q, g, 0, 3, c)
            e13, e12 = _cut_points(q, g, 1, 3, c), _cut_points(q, g, 1, 2, c)
            for x, y, z in ((e02, e03, e13), (e02, e13, e12)):
                a, cen = _tri_area_centroid(x, y, z)
                acc_a += a.sum()
                acc_c += (a[:, None] * cen).sum(axis=0)
        if acc_a > 0:
            areas[i] = acc_a
            centroids[i] = acc_c / acc_a
    return centroids, areas
