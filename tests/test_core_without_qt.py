"""The numerical core imports and runs with Qt, napari, vispy, gRPC, pyvista and VTK all unimportable."""

import subprocess
import sys
import textwrap


def test_core_runs_without_gui_or_server_packages(tmp_path):
    code = textwrap.dedent(f"""
        import sys
        BLOCKED = ("PyQt5", "PyQt6", "PySide2", "PySide6", "qtpy", "napari", "vispy", "magicgui", "grpc",
                   "pyvista", "vtk", "distributed")
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED:
                    raise ImportError("blocked for this test: " + name)
        sys.meta_path.insert(0, Block())

        import numpy as np
        import napari_unwind
        from napari_unwind import open_volume, write_volume, import_volume
        from napari_unwind import cli, demo, datasets, _compat
        from napari_unwind._napari import _layers, _reader, _sample_data, _writer
        a = (np.arange(24 * 20 * 18) % 251).astype(np.uint8).reshape(24, 20, 18)
        write_volume(a, r"{tmp_path}/a.zarr", spacing=(2, 1, 1))
        v = import_volume(r"{tmp_path}/a.zarr", r"{tmp_path}/b.zarr", max_side=8)
        assert (v.data.compute() == a).all() and len(v.levels) > 1
        leaked = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
        assert not leaked, leaked
        print("core ok")
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "core ok" in r.stdout
