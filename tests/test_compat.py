"""pytetwild without pyvista: the mesher runs and its tets fill the surface with positive orientation."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest


def test_tetrahedralize_sphere_without_pyvista(tmp_path):
    code = textwrap.dedent("""
        import sys
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("pyvista", "vtk"):
                    raise ImportError("blocked: " + name)
        sys.meta_path.insert(0, Block())
        import numpy as np
        from skimage.measure import marching_cubes
        from napari_unwind._compat import tetrahedralize
        r = 8.0
        z, y, x = np.mgrid[:24, :24, :24] - 11.5
        v, f, _, _ = marching_cubes(np.sqrt(z * z + y * y + x * x), r)
        V, T = tetrahedralize(v, f, edge_length_fac=0.1)
        a, b, c = (V[T[:, k]] - V[T[:, 0]] for k in (1, 2, 3))
        vol = np.einsum("ij,ij->i", np.cross(a, b), c) / 6
        # every tet positively oriented; total volume close to the analytic ball's
        print(vol.min() > 0, abs(vol.sum() / (4 / 3 * np.pi * r ** 3) - 1))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert list(tmp_path.iterdir()) == []  # fTetWild's debug file is cleaned up
    positive, rel_err = r.stdout.split()[-2:]
    assert positive == "True"
    assert float(rel_err) < 0.05


def test_bad_surface_is_rejected():
    from napari_unwind._compat import tetrahedralize

    with pytest.raises(ValueError, match="vertices"):
        tetrahedralize(np.zeros((3, 2)), np.zeros((4, 3), int))


OCTAHEDRON = (np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float),
              np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]))


@pytest.mark.parametrize("damage, match", [("nan", "vertices must be finite, got 1 with NaN"),
                                           ("index", "faces must index the 6 vertices, got index 6")])
def test_bad_surface_values_are_rejected_before_the_mesher(damage, match):
    from napari_unwind._compat import tetrahedralize

    v, f = OCTAHEDRON[0].copy(), OCTAHEDRON[1].copy()
    if damage == "nan":
        v[2, 1] = np.nan
    else:
        f[3, 2] = 6
    with pytest.raises(ValueError, match=match):
        tetrahedralize(v, f)


def test_a_mesher_crash_is_an_error_not_the_end_of_the_caller():
    """All vertices at one point: fTetWild segfaults. The caller gets one RuntimeError and goes on (the mesher runs
    in a child; in the caller's own process the crash would end it, a napari session or a server with it)."""
    code = textwrap.dedent("""
        import numpy as np
        from napari_unwind._compat import tetrahedralize
        f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
        try:
            tetrahedralize(np.zeros((6, 3)), f)
        except RuntimeError as e:
            print("RuntimeError:", e)
        print("still here")
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, (r.returncode, r.stderr[-1000:])
    assert r.stdout.splitlines() == ["RuntimeError: fTetWild ended with signal SIGSEGV on a surface of 8 triangles; "
                                     "tet_mesher='lattice' meshes without it", "still here"], r.stdout
