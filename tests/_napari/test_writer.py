"""The npe2 writers: an Image layer saved in every straight export format, read back with open_volume."""

import numpy as np
import pytest

pytest.importorskip("napari")

from napari_unwind.errors import InvalidInputError  # noqa: E402
from napari_unwind.io import open_volume  # noqa: E402

SPACING = (2.0, 1.0, 0.5)
ORIGIN = (1.0, -2.0, 3.0)
SUFFIXES = [".ome.zarr", ".zarr", ".nrrd", ".nii.gz", ".nii", ".tif", ".tiff"]


@pytest.fixture
def straight():
    rng = np.random.default_rng(7)
    return (rng.random((12, 10, 9)) * 60000).astype(np.uint16)


def _meta(**changes):
    meta = {"name": "straight", "scale": list(SPACING), "translate": list(ORIGIN), "units": ("micrometer",) * 3,
            "rgb": False, "multiscale": False, "metadata": {}}
    meta.update(changes)
    return meta


def _write(path, layer_data):
    import npe2

    npe2.PluginManager.instance().discover()  # napari does this on start; here no viewer runs
    return npe2.write(str(path), layer_data, plugin_name="napari-unwind")


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_writer_round_trip_keeps_data_and_spacing(tmp_path, straight, suffix):
    target = tmp_path / f"fish{suffix}"
    written = _write(target, [(straight, _meta(), "image")])
    assert written == [str(target)]
    back = open_volume(target)
    np.testing.assert_array_equal(np.asarray(back.data), straight)
    np.testing.assert_allclose(back.spacing, SPACING)
    assert back.unit == "micrometer"
    np.testing.assert_allclose(back.origin, ORIGIN)
    assert not [p for p in tmp_path.iterdir() if "unwind-tmp" in p.name]


def test_the_straight_preview_beside_the_scan_writes_its_own_origin(tmp_path, straight):
    """The 2D straight preview is drawn beside the scan (its translate moved); saved, the file holds the straight
    grid's origin the preview recorded, not the place it was drawn."""
    target = tmp_path / "preview.nrrd"
    meta = _meta(translate=[1.0, -2.0, 503.0], metadata={"napari_unwind": {"preview": True,
                                                                          "straight_origin": list(ORIGIN)}})
    _write(target, [(straight, meta, "image")])
    np.testing.assert_allclose(open_volume(target).origin, ORIGIN)


def test_multiscale_layer_writes_its_full_resolution(tmp_path, straight):
    target = tmp_path / "fish.nrrd"
    _write(target, [([straight, straight[::2, ::2, ::2]], _meta(multiscale=True), "image")])
    np.testing.assert_array_equal(np.asarray(open_volume(target).data), straight)


def test_pixel_units_write_no_unit_and_replace_an_existing_file(tmp_path, straight):
    target = tmp_path / "fish.nii.gz"
    _write(target, [(np.zeros_like(straight), _meta(units=("pixel",) * 3), "image")])
    _write(target, [(straight, _meta(units=("pixel",) * 3), "image")])  # napari's save dialog asked first
    back = open_volume(target)
    np.testing.assert_array_equal(np.asarray(back.data), straight)
    assert back.unit is None


@pytest.mark.parametrize(("data", "meta", "match"), [
    (np.zeros((5, 6)), _meta(scale=[1, 1], translate=[0, 0]), "3D volumes"),
    (np.zeros((5, 6, 7, 3), np.uint8), _meta(rgb=True), "RGB"),
    (np.zeros((5, 6, 7)), _meta(units=("micrometer", "micrometer", "millimeter")), "different units"),
])
def test_bad_layers_are_clear_errors(tmp_path, data, meta, match):
    from napari_unwind._napari._writer import write_image

    with pytest.raises(InvalidInputError, match=match):
        write_image(str(tmp_path / "x.nrrd"), data, meta)
    assert not list(tmp_path.iterdir())


@pytest.mark.gui
def test_viewer_saves_an_image_layer_with_its_scale(make_napari_viewer, tmp_path, straight):
    viewer = make_napari_viewer()
    viewer.add_image(straight, scale=SPACING, translate=ORIGIN, units="micrometer", name="straight")
    target = tmp_path / "straight.ome.zarr"
    viewer.layers.save(str(target), selected=False, plugin="napari-unwind")
    back = open_volume(target)
    np.testing.assert_array_equal(np.asarray(back.data), straight)
    np.testing.assert_allclose(back.spacing, SPACING)
    np.testing.assert_allclose(back.origin, ORIGIN)
