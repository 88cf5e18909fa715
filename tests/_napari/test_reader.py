"""The readers: scans (napari with Qt under Xvfb, Mesa llvmpipe for GL) and sessions (*.unwind.json).

The session round trip writes a session with the core API from the fish phantom, reads it back through the npe2
reader and checks every layer against the phantom (independent ground truth) and the session file.
"""

import json

import numpy as np
import pytest

pytest.importorskip("napari")

from napari_unwind.datasets import fish_phantom  # noqa: E402
from napari_unwind.deformation import Deformation  # noqa: E402
from napari_unwind.errors import InvalidInputError  # noqa: E402
from napari_unwind.io import open_volume, write_volume  # noqa: E402
from napari_unwind.progress import run  # noqa: E402
from napari_unwind.segmentation import segment, selected_ids  # noqa: E402
from napari_unwind.session import (  # noqa: E402
    Endpoints,
    Segmentation,
    Session,
    SourceChangedError,
    SourceInfo,
    SourceMissingError,
    load_session,
    save_session,
)
from napari_unwind.skeleton import estimate_deformation_iter  # noqa: E402

SPACING = (1.2, 1.0, 1.0)
ORIGIN = (10.0, -5.0, 3.0)


@pytest.fixture
def scan(tmp_path):
    rng = np.random.default_rng(3)
    a = (rng.random((64, 48, 40)) * 3000).astype(np.uint16)
    a[20:40, 10:30, 10:30] = 60000  # a bright block to see in the screenshot
    return a, write_volume(a, tmp_path / "scan.zarr", spacing=(2.0, 1.0, 1.0), unit="um", max_side=16)


@pytest.fixture(scope="module")
def fish_session(tmp_path_factory):
    """A session made with the core API: the phantom's scan, a click on the fish, the skeleton of its true mask."""
    folder = tmp_path_factory.mktemp("session")
    p = fish_phantom()
    scan = write_volume(p.volume, folder / "fish.zarr", spacing=SPACING, origin=ORIGIN, unit="um")
    volume = open_volume(scan)
    features = segment(volume, features=5)
    click = tuple(float(c) for c in p.centerline[len(p.centerline) // 2])
    ids = selected_ids(features, seeds=[click])
    result = run(estimate_deformation_iter(p.mask, None, spacing=SPACING, origin=ORIGIN, unit="um"))
    session = Session(source=SourceInfo.from_path(scan), deformation=result.deformation, endpoints=result.endpoints,
                      segmentation=Segmentation(k=5, level=features.level, selected=tuple(ids), seeds=(click,)))
    return p, save_session(session, folder / "fish.unwind.json")


def _read_session(path):
    import npe2

    npe2.PluginManager.instance().discover()  # napari does this on start; here no viewer runs
    return npe2.read([str(path)], plugin_name="napari-unwind", stack=False)


def _by_type(layers):
    return {layer_type: (data, meta) for data, meta, layer_type in layers}


def test_session_restores_scan_selection_ends_and_deformation(fish_session):
    p, path = fish_session
    session = load_session(path)
    layers = _read_session(path)
    assert [t for *_, t in layers] == ["image", "labels", "points", "shapes"]
    got = _by_type(layers)
    for _, meta in got.values():
        assert meta["metadata"]["napari_unwind"]["session_path"] == str(path)

    # the scan, lazily, in world coordinates
    data, meta = got["image"]
    np.testing.assert_array_equal(np.asarray(data), p.volume)
    np.testing.assert_allclose(meta["scale"], SPACING)
    np.testing.assert_allclose(meta["translate"], ORIGIN)
    assert meta["units"] == ("micrometer",) * 3

    # the selection: the feature under the click is the fish (the phantom's true mask), and only it
    labels, meta = got["labels"]
    assert set(np.unique(labels)) - {0} == set(session.segmentation.selected)
    assert labels.shape == p.mask.shape  # the phantom is small: segmented at full resolution
    np.testing.assert_allclose(meta["scale"], SPACING)
    np.testing.assert_allclose(meta["translate"], ORIGIN)
    sel, truth = labels > 0, p.mask.astype(bool)
    dice = 2 * (sel & truth).sum() / (sel.sum() + truth.sum())
    assert dice > 0.8, dice
    assert meta["metadata"]["napari_unwind"]["segmentation"] == session.segmentation.to_dict()

    # the ends: the session's voxels x spacing + origin, near the phantom's true head and tail
    ends, meta = got["points"]
    assert meta["name"] == "ends" and list(meta["features"]["end"]) == ["head", "tail"]
    expected = np.array([session.endpoints.head, session.endpoints.tail]) * SPACING + ORIGIN
    np.testing.assert_allclose(ends, expected)
    true_ends = np.array([p.head, p.tail]) * SPACING + ORIGIN
    assert np.linalg.norm(ends - true_ends, axis=1).max() < 10, (ends, true_ends)
    assert meta["metadata"]["napari_unwind"]["endpoints"] == session.endpoints.to_dict()

    # the deformation: its dict, exactly; the drawn curve runs along the phantom's centreline (world coordinates)
    (curve,), meta = got["shapes"]
    assert meta["name"] == "curve" and meta["shape_type"] == "path"
    stored = meta["metadata"]["napari_unwind"]["deformation"]
    assert stored == session.deformation.to_dict()
    assert Deformation.from_dict(stored).to_dict() == json.loads(path.read_text())["deformation"]
    np.testing.assert_allclose(curve[[0, -1]], session.deformation.positions[[0, -1]], atol=1e-9)
    centreline = p.centerline * SPACING + ORIGIN
    gap = np.linalg.norm(curve[:, None, :] - centreline[None, :, :], axis=2).min(axis=1)
    assert gap.max() < 3.0, gap.max()


def test_session_with_only_a_scan_and_a_chain_of_ends(fish_session, tmp_path):
    p, path = fish_session
    source = load_session(path).source
    chain = (((5.0, 30.0, 40.0), (60.0, 33.0, 38.0)), ((80.0, 34.0, 37.0), (150.0, 32.0, 40.0)))
    alone = save_session(Session(source=source), tmp_path / "alone.unwind.json")
    assert [t for *_, t in _read_session(alone)] == ["image"]
    pieces = save_session(Session(source=source, endpoints=Endpoints(head=chain[0][0], tail=chain[-1][1],
                                                                     chain=chain)),
                          tmp_path / "pieces.unwind.json")
    ends, meta = _by_type(_read_session(pieces))["points"]
    np.testing.assert_allclose(ends, np.array([q for pair in chain for q in pair]) * SPACING + ORIGIN)
    assert list(meta["features"]["end"]) == ["head", "part 1 end", "part 2 start", "tail"]
    np.testing.assert_allclose(_by_type(_read_session(pieces))["image"][1]["translate"], ORIGIN)


def test_session_layers_without_the_selection_keep_its_record(fish_session):
    from napari_unwind._napari._reader import session_layers

    p, path = fish_session
    session = load_session(path)
    layers = session_layers(session, session_path=path, selection=False)
    assert [t for *_, t in layers] == ["image", "points", "shapes"]
    assert layers[0][1]["metadata"]["napari_unwind"]["segmentation"] == session.segmentation.to_dict()
    # the scan's contrast: its voxels' 0.5th and 99.5th percentiles (napari's own would be one slice's range)
    expected = np.percentile(np.asarray(p.volume, dtype=np.float64), [0.5, 99.5])
    np.testing.assert_allclose(layers[0][1]["contrast_limits"], expected, rtol=1e-6, atol=1e-6)
    assert expected[1] > expected[0]


def test_session_whose_selection_was_a_mask_file_reopens_it(fish_session, tmp_path):
    """A mask file as the selection (issue 21 items 3/5): the session brings it back as a Labels layer on the scan
    naming the chosen label; a missing or other-grid mask is refused in one line. Reference: the phantom's mask."""
    p, path = fish_session
    session = load_session(path)
    labels = p.mask.astype(np.uint8) * 4
    mask_file = write_volume(labels, tmp_path / "expert.nrrd", spacing=SPACING)
    session.segmentation = Segmentation(mask=str(mask_file), mask_label=4)
    with_mask = save_session(session, tmp_path / "masked.unwind.json")
    layers = _read_session(with_mask)
    assert [t for *_, t in layers] == ["image", "labels", "points", "shapes"]
    data, meta = _by_type(layers)["labels"]
    np.testing.assert_array_equal(np.asarray(data) == 4, p.mask)
    assert meta["metadata"]["napari_unwind"]["mask_label"] == 4 and meta["metadata"]["napari_unwind"]["selection_mask"]
    np.testing.assert_allclose(meta["scale"], SPACING)
    np.testing.assert_allclose(meta["translate"], ORIGIN)

    write_volume(labels[:, 1:], tmp_path / "expert.nrrd", spacing=SPACING, overwrite=True)
    with pytest.raises(SourceChangedError, match="not the mask the session was made with"):
        _read_session(with_mask)
    (tmp_path / "expert.nrrd").unlink()
    with pytest.raises(SourceMissingError, match="the mask of .* is missing"):
        _read_session(with_mask)


def _moved_source(path, tmp_path, new_source):
    d = json.loads(path.read_text())
    d["source"]["path"] = str(new_source)
    out = tmp_path / "moved.unwind.json"
    out.write_text(json.dumps(d))
    return out


def test_session_whose_scan_is_missing_says_where_and_what_to_do(fish_session, tmp_path):
    from napari_unwind._napari._reader import get_session_reader

    _, path = fish_session
    gone = tmp_path / "elsewhere" / "fish.zarr"
    moved = _moved_source(path, tmp_path, gone)
    with pytest.raises(SourceMissingError) as err:
        get_session_reader(str(moved))(str(moved))
    msg = str(err.value)
    assert str(gone) in msg and str(moved) in msg and "Put the scan back" in msg


def test_session_whose_scan_changed_is_refused(fish_session, tmp_path):
    from napari_unwind._napari._reader import read_session

    _, path = fish_session
    other = write_volume(np.zeros((10, 11, 12), np.uint16), tmp_path / "other.zarr")
    with pytest.raises(SourceChangedError, match="is not the one"):
        read_session(str(_moved_source(path, tmp_path, other)))


def test_damaged_session_is_a_clear_error_and_other_files_are_not_sessions(tmp_path, scan):
    from napari_unwind._napari._reader import get_reader, get_session_reader, read_session

    bad = tmp_path / "bad.unwind.json"
    bad.write_text('{"schema": "napari-unwind/session", ')
    with pytest.raises(InvalidInputError, match="not valid JSON"):
        read_session(str(bad))
    _, zarr = scan
    assert get_session_reader(str(zarr)) is None
    assert get_session_reader(str(tmp_path / "notes.json")) is None
    assert get_reader(str(bad)) is None  # the scan reader leaves sessions alone
    assert get_session_reader([str(bad), str(bad)]) is None


@pytest.mark.gui
def test_viewer_opens_a_session_as_its_layers(make_napari_viewer, fish_session):
    p, path = fish_session
    session = load_session(path)
    viewer = make_napari_viewer()
    layers = viewer.open(str(path), plugin="napari-unwind")
    assert [layer.name for layer in viewer.layers] == ["fish.zarr", "selection", "ends", "curve"]
    assert [type(layer).__name__ for layer in layers] == ["Image", "Labels", "Points", "Shapes"]
    ends = viewer.layers["ends"]
    world = np.array([ends.data_to_world(q) for q in ends.data])
    np.testing.assert_allclose(world, np.array([session.endpoints.head, session.endpoints.tail]) * SPACING + ORIGIN)
    scan = viewer.layers["fish.zarr"]
    np.testing.assert_allclose(scan.data_to_world((0, 0, 0)), ORIGIN)
    assert viewer.layers["curve"].metadata["napari_unwind"]["deformation"] == session.deformation.to_dict()


@pytest.mark.gui
def test_reader_opens_pyramid_with_geometry(make_napari_viewer, scan):
    a, path = scan
    viewer = make_napari_viewer()
    layers = viewer.open(str(path), plugin="napari-unwind")
    layer = layers[0]
    assert layer.multiscale and len(layer.data) == 3
    np.testing.assert_array_equal(np.asarray(layer.data[0]), a)
    np.testing.assert_allclose(layer.scale, (2.0, 1.0, 1.0))
    assert [str(u) for u in layer.units] == ["micrometer"] * 3


@pytest.mark.gui
def test_rendered_slice_matches_the_data(make_napari_viewer, scan):
    """Render plane 30 and check the bright block sits where the data has it (pixels read back from GL)."""
    a, path = scan
    viewer = make_napari_viewer(show=True)
    layer = viewer.open(str(path), plugin="napari-unwind")[0]
    layer.contrast_limits = (0, 65535)
    layer.colormap = "gray"
    viewer.dims.set_point(0, 30 * 2.0)
    viewer.reset_view()
    shot = viewer.screenshot(canvas_only=True, flash=False)
    grey = shot[..., :3].mean(axis=-1)
    bright = grey > 200
    assert bright.any(), "nothing bright was rendered"
    rows, cols = np.nonzero(bright)
    # the block covers rows 10..29 of 48 and columns 10..29 of 40: compare the proportions on screen
    data_rows, data_cols = np.nonzero(a[30] > 50000)
    h_ratio = (rows.max() - rows.min() + 1) / (cols.max() - cols.min() + 1)
    data_ratio = (data_rows.max() - data_rows.min() + 1) / (data_cols.max() - data_cols.min() + 1)
    assert abs(h_ratio - data_ratio) < 0.1


def _ct_scan(dtype):
    """A CT-like scan in Hounsfield units: air (-1000) around a water body (0 +- 30) holding bone (1000..3000)."""
    rng = np.random.default_rng(5)
    shape = (40, 36, 32)
    z, y, x = np.ogrid[tuple(slice(0, n) for n in shape)]
    body = ((z - 20) / 18) ** 2 + ((y - 18) / 14) ** 2 + ((x - 16) / 12) ** 2 < 1
    a = rng.normal(-1000, 20, shape)
    a[body] = rng.normal(0, 30, int(body.sum()))
    bone = body & (np.abs(y - 18) < 3) & (np.abs(x - 16) < 3)
    a[bone] = rng.uniform(1000, 3000, int(bone.sum()))
    return np.clip(a, -1000, 3000).astype(dtype)


@pytest.fixture
def reader_preference():
    """napari's reader preferences (Preferences > Plugins), restored after the test; not saved to the user's
    settings file meanwhile."""
    from napari.settings import get_settings

    settings = get_settings()
    before = dict(settings.plugins.extension2reader)
    saving = settings._save_on_change
    settings._save_on_change = False
    try:
        yield settings.plugins
    finally:
        settings.plugins.extension2reader = before
        settings._save_on_change = saving


@pytest.mark.gui
@pytest.mark.parametrize("dtype", ["int16", "float32"])
def test_nrrd_opens_with_the_contrast_of_its_voxels(make_napari_viewer, reader_preference, tmp_path, dtype):
    """File > Open of a .nrrd by this plugin (chosen, or napari's preference for *.nrrd): the CT is not black and
    white, its contrast limits are its voxels' 0.5th and 99.5th percentiles (issue 21)."""
    a = _ct_scan(dtype)
    path = write_volume(a, tmp_path / "ct.nrrd", spacing=(0.5, 0.4, 0.4), unit="mm")
    expected = np.percentile(a.astype(np.float64), [0.5, 99.5])
    viewer = make_napari_viewer()

    chosen = viewer.open(str(path), plugin="napari-unwind")[0]

    reader_preference.extension2reader = {**reader_preference.extension2reader, "*.nrrd": "napari-unwind"}
    # File > Open names no plugin: napari takes its preference (viewer.open's own default, plugin="napari", is
    # napari's builtins, which need itk for NRRD)
    preferred = viewer.open(str(path), plugin=None)[0]

    for layer in (chosen, preferred):
        assert layer.metadata["napari_unwind"]["format"] == "nrrd"
        np.testing.assert_allclose(layer.contrast_limits, expected, atol=0.01 * 4000)
        assert list(layer.contrast_limits) != [0, 1]
        np.testing.assert_array_equal(np.asarray(layer.data), a)
