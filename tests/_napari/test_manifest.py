"""The npe2 manifest: valid, discovered, and every contribution points at code that exists."""

import importlib
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("napari")

import napari_unwind  # noqa: E402

MANIFEST = Path(napari_unwind.__file__).with_name("napari.yaml")
WIDGET = "napari_unwind._napari._widget"


@pytest.fixture(scope="module")
def manifest():
    import npe2

    pm = npe2.PluginManager.instance()
    pm.discover()
    return pm.get_manifest("napari-unwind")


def test_manifest_is_valid_and_discovered(manifest):
    keys = {s.key for s in manifest.contributions.sample_data}
    assert {"fish", "tank", "cylinder"} <= keys
    assert manifest.contributions.readers
    from npe2 import PluginManifest

    # the installed entry point is the package's napari.yaml (an editable install or a wheel alike)
    assert [c.id for c in manifest.contributions.commands] == \
        [c.id for c in PluginManifest.from_file(MANIFEST).contributions.commands]


def test_npe2_validate_is_clean():
    npe2_cli = Path(sys.executable).with_name("npe2")
    r = subprocess.run([str(npe2_cli), "validate", "napari-unwind"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "valid" in r.stdout


def test_every_command_imports():
    """Like ``npe2 validate --imports``; the dock is checked once its module exists (it is written in parallel)."""
    from npe2 import PluginManifest

    pm = PluginManifest.from_file(MANIFEST)
    for command in pm.contributions.commands:
        module, _, name = command.python_name.partition(":")
        if module == WIDGET and importlib.util.find_spec(module) is None:
            continue
        assert callable(getattr(importlib.import_module(module), name)), command.python_name


def test_contributions(manifest):
    c = manifest.contributions
    (widget,) = c.widgets
    assert widget.display_name == "Unwind"
    assert manifest.contributions.commands[[x.id for x in c.commands].index(widget.command)].python_name == \
        f"{WIDGET}:UnwindWidget"
    session_readers = [r for r in c.readers if "*.unwind.json" in r.filename_patterns]
    assert len(session_readers) == 1 and not session_readers[0].accepts_directories
    extensions = {e for w in c.writers for e in w.filename_extensions}
    assert extensions == {".ome.zarr", ".zarr", ".nrrd", ".nii.gz", ".nii", ".tif", ".tiff"}
    assert all(w.layer_types == ["image"] for w in c.writers)


def test_writer_suffixes_are_ones_write_volume_knows():
    from npe2 import PluginManifest

    from napari_unwind._napari._writer import WRITER_SUFFIXES
    from napari_unwind.io._formats import output_format

    declared = {e for w in PluginManifest.from_file(MANIFEST).contributions.writers for e in w.filename_extensions}
    assert declared == set(WRITER_SUFFIXES)
    for suffix in WRITER_SUFFIXES:
        assert output_format(f"fish{suffix}", None) in ("ome-zarr", "nrrd", "nifti", "tiff")


def test_the_session_reader_is_chosen_for_sessions(manifest, tmp_path):
    import npe2

    session = tmp_path / "fish.unwind.json"
    session.write_text("{}")
    readers = [r.command for r in npe2.PluginManager.instance().iter_compatible_readers([str(session)])
               if r.command.startswith("napari-unwind.")]
    assert readers == ["napari-unwind.get_session_reader"]


@pytest.mark.gui
def test_sample_data_opens_the_phantom_and_its_truth(make_napari_viewer):
    import numpy as np

    from napari_unwind.datasets import fish_phantom

    viewer = make_napari_viewer()
    viewer.open_sample("napari-unwind", "fish")
    assert [type(layer).__name__ for layer in viewer.layers] == ["Image", "Labels"]
    p = fish_phantom()
    np.testing.assert_array_equal(np.asarray(viewer.layers[0].data), p.volume)
    np.testing.assert_array_equal(np.asarray(viewer.layers[1].data) > 0, p.mask)
