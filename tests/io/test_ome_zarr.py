"""OME-Zarr pyramid: geometry, values, and readability by the reference implementation (ome-zarr-py)."""

import json

import dask
import dask.array as da
import numpy as np
import pytest
import zarr

from napari_unwind.errors import InvalidInputError, UnknownFormatError
from napari_unwind.io import Volume, import_volume, open_volume, write_volume
from napari_unwind.io.ome_zarr import pyramid_shapes


def _box_mean2(a):
    """Independent 2x2x2 block mean with edge padding (odd sides), in float64."""
    pad = [(0, s % 2) for s in a.shape]
    a = np.pad(a.astype(np.float64), pad, mode="edge")
    return a.reshape(a.shape[0] // 2, 2, a.shape[1] // 2, 2, a.shape[2] // 2, 2).mean(axis=(1, 3, 5))


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "int16", "float32"])
def test_round_trip_values_spacing_unit(tmp_path, dtype):
    rng = np.random.default_rng(0)
    a = (rng.random((37, 20, 29)) * 200).astype(dtype)
    out = write_volume(a, tmp_path / "v.zarr", spacing=(2.5, 0.5, 0.5), unit="um", origin=(1, 2, 3), chunks=16,
                       max_side=8)
    v = open_volume(out)
    assert v.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(v.data.compute(), a)
    assert v.spacing == (2.5, 0.5, 0.5) and v.unit == "micrometer" and v.origin == (1.0, 2.0, 3.0)
    assert [lvl.shape for lvl in v.levels] == pyramid_shapes(a.shape, 8)
    # level 1 is the 2x2x2 box mean of level 0
    expect = _box_mean2(a)
    got = v.levels[1].compute().astype(np.float64)
    tol = 0.5 if np.issubdtype(np.dtype(dtype), np.integer) else 1e-4
    np.testing.assert_allclose(got, expect, atol=tol)
    assert v.level_spacings[1] == (5.0, 1.0, 1.0)


@pytest.mark.parametrize("shape, chunks", [((37, 20, 29), 16), ((45, 9, 33), 5), ((64, 64, 64), 32),
                                           ((3, 70, 70), 4), ((17, 17, 17), 17)])
def test_every_level_is_the_box_mean_of_the_one_before(tmp_path, shape, chunks):
    """The one-pass cascade equals an independent level-by-level computation, for odd sizes and chunks too."""
    a = np.random.default_rng(2).integers(0, 5000, shape).astype(np.uint16)
    v = open_volume(write_volume(a, tmp_path / "v.zarr", chunks=chunks, max_side=4))
    expect = a
    for lvl in v.levels[1:]:
        expect_f = _box_mean2_any(expect)
        got = lvl.compute()
        assert got.shape == expect_f.shape
        np.testing.assert_allclose(got, expect_f, atol=0.5 + 1e-9)
        expect = got  # the next level averages the stored (rounded) one


def _box_mean2_any(a):
    """Box mean over 2 along every axis longer than 1, edge-padded, float64 (independent of the writer)."""
    a = a.astype(np.float64)
    for ax in range(3):
        if a.shape[ax] > 1:
            if a.shape[ax] % 2:
                a = np.concatenate([a, np.take(a, [-1], axis=ax)], axis=ax)
            a = (np.take(a, range(0, a.shape[ax], 2), axis=ax) + np.take(a, range(1, a.shape[ax], 2), axis=ax)) / 2
    return a


def test_pyramid_stops_at_max_side():
    shapes = pyramid_shapes((1000, 300, 1))
    assert shapes[0] == (1000, 300, 1)
    assert max(shapes[-1]) <= 256 and max(shapes[-2]) > 256
    assert all(s[2] == 1 for s in shapes)  # a side of 1 is never halved
    for a, b in zip(shapes, shapes[1:]):
        assert all(nb == (na + 1) // 2 or na == 1 for na, nb in zip(a, b))


def test_labels_are_downsampled_by_nearest(tmp_path):
    labels = np.zeros((16, 16, 16), np.uint8)
    labels[:, :, :8] = 3
    labels[::2, ::2, 1::2] = 7  # would be averaged into values that exist nowhere
    v = open_volume(write_volume(labels, tmp_path / "l.zarr", labels=True, max_side=4))
    for lvl in v.levels[1:]:
        assert set(np.unique(lvl.compute())) <= {0, 3, 7}
    np.testing.assert_array_equal(v.levels[1].compute(), labels[::2, ::2, ::2])


def test_metadata_is_ngff_0_5_and_readable_by_ome_zarr_py(tmp_path):
    ome_zarr_reader = pytest.importorskip("ome_zarr.reader")
    from ome_zarr.io import parse_url

    a = np.arange(40 * 30 * 20, dtype=np.uint16).reshape(40, 30, 20)
    out = write_volume(a, tmp_path / "v.ome.zarr", spacing=(3.0, 1.0, 1.0), unit="mm", max_side=16, chunks=8)
    meta = json.loads((out / "zarr.json").read_text())
    assert meta["zarr_format"] == 3
    ome = meta["attributes"]["ome"]
    assert ome["version"] == "0.5"
    axes = ome["multiscales"][0]["axes"]
    assert [ax["name"] for ax in axes] == ["z", "y", "x"]
    assert all(ax["type"] == "space" and ax["unit"] == "millimeter" for ax in axes)

    reader = ome_zarr_reader.Reader(parse_url(str(out)))
    node = next(iter(reader()))
    data = node.data
    assert len(data) == len(pyramid_shapes(a.shape, 16))
    np.testing.assert_array_equal(np.asarray(data[0]), a)
    ms = node.zarr.root_attrs["ome"]["multiscales"][0] if "ome" in node.zarr.root_attrs else \
        node.zarr.root_attrs["multiscales"][0]
    scales = [ds["coordinateTransformations"][0]["scale"] for ds in ms["datasets"]]
    assert scales[0] == [3.0, 1.0, 1.0] and scales[1] == [6.0, 2.0, 2.0]


def test_reads_ngff_0_4_written_by_ome_zarr_py(tmp_path):
    """An independent writer's output (ome-zarr-py, NGFF 0.4 on zarr v2) opens with the right geometry."""
    pytest.importorskip("ome_zarr")
    from ome_zarr.format import FormatV04
    from ome_zarr.writer import write_image

    a = (np.random.default_rng(1).random((32, 24, 16)) * 1000).astype(np.uint16)
    root = zarr.open_group(str(tmp_path / "other.zarr"), mode="w", zarr_format=2)
    write_image(a, root, axes="zyx", fmt=FormatV04(), scale={"z": 4.0, "y": 0.5, "x": 0.5}, scale_factors=[])
    v = open_volume(tmp_path / "other.zarr")
    np.testing.assert_array_equal(v.data.compute(), a)
    assert v.spacing == (4.0, 0.5, 0.5)


def test_group_without_multiscales_is_explained(tmp_path):
    g = zarr.open_group(str(tmp_path / "plain.zarr"), mode="w")
    g.create_array("raw", shape=(4, 4, 4), dtype="uint8")
    with pytest.raises(UnknownFormatError, match="raw"):
        open_volume(tmp_path / "plain.zarr")
    # the array itself opens
    v = open_volume(tmp_path / "plain.zarr" / "raw", format="ome-zarr")
    assert v.shape == (4, 4, 4)


def test_level_option_and_bad_level(tmp_path):
    out = write_volume(np.ones((64, 64, 64), np.uint8), tmp_path / "v.zarr", max_side=16)
    v = open_volume(out, level=1)
    assert v.shape == (32, 32, 32) and v.spacing == (2.0, 2.0, 2.0)
    with pytest.raises(InvalidInputError, match="levels 0..2"):
        open_volume(out, level=5)


def test_streaming_reads_each_source_slab_once(tmp_path):
    """Level 0 is built slab by slab from the lazy source, and each source block is read exactly once."""
    reads = []

    def block(i):
        reads.append(i)
        return np.full((4, 32, 32), i, np.uint16)

    src = da.concatenate([da.from_delayed(dask.delayed(block)(i), (4, 32, 32), np.uint16) for i in range(16)])
    v = import_volume(Volume(src, spacing=1.0), tmp_path / "s.zarr", chunks=(8, 32, 32), max_side=8)
    assert sorted(reads) == list(range(16))
    np.testing.assert_array_equal(v.data[::4, 0, 0].compute(), np.arange(16))


# ------------------------------------------------------------------------------------------------------------------
# the working store's codec (issue 10): lz4 now, zstd stores written before still read the same
# ------------------------------------------------------------------------------------------------------------------
#: Every codec chain write_ome_zarr has written (git history of napari_unwind/io/ome_zarr.py), and the new default.
HISTORIC_CODECS = {
    "blosc-zstd bitshuffle (first releases)": lambda: [zarr.codecs.BloscCodec(cname="zstd", clevel=3,
                                                                              shuffle="bitshuffle")],
    "blosc-zstd byte shuffle": lambda: [zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")],
    "blosc-zstd byte shuffle + crc32c": lambda: [zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle="shuffle"),
                                                 zarr.codecs.Crc32cCodec()],
}


def _ngff_store(path, a, codecs, chunks, *, complete):
    """An OME-Zarr store like the ones write_ome_zarr made with ``codecs``, written by zarr itself."""
    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    arr = root.create_array("0", shape=a.shape, chunks=chunks, dtype=a.dtype, compressors=codecs, fill_value=0,
                            dimension_names=["z", "y", "x"], config={"write_empty_chunks": complete})
    arr[...] = a
    root.attrs["ome"] = {"version": "0.5", "multiscales": [{
        "axes": [{"name": n, "type": "space", "unit": "micrometer"} for n in "zyx"],
        "datasets": [{"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [1.0, 1.0, 1.0]}]}]}]}
    root.attrs["unwind"] = {"spacing": [1.0, 1.0, 1.0], "unit": "micrometer", "all_chunks_written": complete}
    return path


@pytest.mark.parametrize("codecs", list(HISTORIC_CODECS), ids=list(HISTORIC_CODECS))
@pytest.mark.parametrize("dtype", ["uint8", "uint16", "int16", "float32"])
def test_stores_written_with_the_old_codecs_read_back_identically(tmp_path, codecs, dtype):
    rng = np.random.default_rng(3)
    a = (rng.normal(500, 200, (37, 21, 30))).astype(dtype)
    a[:16, :16, :16] = 0  # an all-fill chunk
    for complete in (True, False):
        store = _ngff_store(tmp_path / f"old-{complete}.zarr", a, HISTORIC_CODECS[codecs](), (16, 16, 16),
                            complete=complete)
        v = open_volume(store)
        np.testing.assert_array_equal(v.data.compute(), a)
        np.testing.assert_array_equal(v.data.compute(), zarr.open_array(str(store / "0"), mode="r")[...])
        np.testing.assert_array_equal(v.data[5:30, 3:19, 7:29].compute(), a[5:30, 3:19, 7:29])


def test_the_default_codec_is_blosc_lz4_with_shuffle_and_a_checksum(tmp_path):
    for dtype, shuffle in (("uint16", "shuffle"), ("float32", "shuffle"), ("uint8", "bitshuffle")):
        out = write_volume(np.zeros((8, 8, 8), dtype), tmp_path / f"{dtype}.zarr", max_side=4)
        for level in ("0", "1"):
            codecs = json.loads((out / level / "zarr.json").read_text())["codecs"]
            assert [c["name"] for c in codecs] == ["bytes", "blosc", "crc32c"]
            assert codecs[1]["configuration"]["cname"] == "lz4"
            assert codecs[1]["configuration"]["shuffle"] == shuffle


@pytest.mark.parametrize("options", [{"compression": "zstd"}, {"compression": "zstd", "compression_level": 1},
                                     {"compression": "lz4", "shuffle": "bit"}, {"compression": "none"},
                                     {"compression": "lz4", "compression_level": 9, "shuffle": "none"}])
def test_every_compression_option_round_trips(tmp_path, options):
    a = np.random.default_rng(4).integers(0, 4000, (35, 20, 27)).astype(np.uint16)
    out = write_volume(a, tmp_path / "v.zarr", chunks=16, max_side=8, **options)
    codecs = json.loads((out / "0" / "zarr.json").read_text())["codecs"]
    assert codecs[-1]["name"] == "crc32c"
    if options["compression"] != "none":
        assert codecs[1]["configuration"]["cname"] == options["compression"]
    v = open_volume(out)
    np.testing.assert_array_equal(v.data.compute(), a)
    np.testing.assert_array_equal(v.levels[1].compute(), zarr.open_array(str(out / "1"), mode="r")[...])


@pytest.mark.parametrize("options, match", [({"compression": "gzip"}, "compression must be one of"),
                                            ({"compression_level": 0}, "compression_level must be"),
                                            ({"compression_level": 12}, "compression_level must be"),
                                            ({"compression_level": 2.5}, "compression_level must be"),
                                            ({"shuffle": "bytes"}, "shuffle must be one of")])
def test_bad_codec_options_are_one_line_errors(tmp_path, options, match):
    with pytest.raises(InvalidInputError, match=match) as info:
        write_volume(np.zeros((4, 4, 4), np.uint16), tmp_path / "v.zarr", **options)
    assert "\n" not in str(info.value) and repr(next(iter(options.values()))) in str(info.value)
    assert not (tmp_path / "v.zarr").exists()


def test_whole_chunks_of_our_stores_are_decoded_without_zarrs_pipeline(tmp_path, monkeypatch):
    """dask's reads of the stores we write skip zarr's asynchronous codec pipeline (the faster path)."""
    a = np.random.default_rng(5).integers(0, 60000, (40, 33, 20)).astype(np.uint16)
    v = open_volume(write_volume(a, tmp_path / "v.zarr", chunks=16, max_side=8))

    def refuse(self, key):
        raise AssertionError("read through zarr")

    monkeypatch.setattr(zarr.Array, "__getitem__", refuse)
    np.testing.assert_array_equal(v.data.compute(), a)
    for lvl in v.levels[1:]:
        assert lvl.compute().shape == lvl.shape


@pytest.mark.parametrize("damage", ["valid checksum over garbage", "a chunk of another size", "truncated",
                                    "empty file"])
def test_a_damaged_chunk_read_directly_is_one_error_naming_it(tmp_path, damage):
    import google_crc32c

    a = np.random.default_rng(6).integers(0, 60000, (40, 33, 20)).astype(np.uint16)
    out = write_volume(a, tmp_path / "v.zarr", chunks=16, max_side=8)
    chunk = out / "0" / "c" / "1" / "0" / "1"
    good = chunk.read_bytes()
    if damage == "valid checksum over garbage":
        body = good[:16] + bytes(len(good) - 20)  # the blosc header kept, the stream zeroed
        chunk.write_bytes(body + np.uint32(google_crc32c.value(body)).tobytes())
    elif damage == "a chunk of another size":
        other = write_volume(a, tmp_path / "w.zarr", chunks=8, max_side=8)
        chunk.write_bytes((other / "0" / "c" / "1" / "0" / "1").read_bytes())
    elif damage == "truncated":
        chunk.write_bytes(good[: len(good) // 2])
    else:
        chunk.write_bytes(b"")
    with pytest.raises(InvalidInputError) as info:
        open_volume(out).data.compute()
    msg = str(info.value)
    assert str(chunk) in msg and "corrupt" in msg and "re-import" in msg and "\n" not in msg
    np.testing.assert_array_equal(open_volume(out).data[:16].compute(), a[:16])  # the other chunks still read


def test_import_volume_takes_the_codec_options(tmp_path):
    a = np.random.default_rng(7).integers(0, 4000, (30, 20, 20)).astype(np.uint16)
    src = write_volume(a, tmp_path / "src.tif")
    for compression, level in (("zstd", 2), (None, None)):
        v = import_volume(src, tmp_path / f"{compression}.zarr", compression=compression, compression_level=level,
                          max_side=8)
        blosc = json.loads((tmp_path / f"{compression}.zarr" / "1" / "zarr.json").read_text())["codecs"][1]
        assert blosc["configuration"]["cname"] == (compression or "lz4")
        assert blosc["configuration"]["clevel"] == (level or 5)
        np.testing.assert_array_equal(v.data.compute(), a)


def test_lengths_without_a_unit_are_labelled_voxels():
    from napari_unwind.io._volume import unit_label

    assert unit_label(None) == "voxels" and unit_label("") == "voxels"
    assert unit_label("micrometer") == "um" and unit_label("millimeter") == "mm"
    assert unit_label("inch") == "inch"  # a unit we have no abbreviation for keeps its name


@pytest.mark.parametrize("dtype, options", [("uint16", {}), ("uint8", {}), ("float32", {}), ("int16", {}),
                                            ("uint16", {"compression": "zstd", "shuffle": "bit"}),
                                            ("uint16", {"compression": "none"}), ("uint8", {"labels": True})])
def test_stores_are_written_without_zarrs_pipeline_with_the_bytes_zarr_writes(tmp_path, monkeypatch, dtype,
                                                                               options):
    """Our writer encodes chunks itself (faster); every file is the one zarr's own pipeline writes for the same
    array (zarr writes the reference store here), edge chunks and every pyramid level included."""
    rng = np.random.default_rng(7)
    a = (rng.normal(100, 30, (37, 29, 21)) if dtype == "float32" else rng.integers(0, 200, (37, 29, 21)))
    a = a.astype(dtype)
    calls = []
    real = zarr.Array.__setitem__

    def through_zarr(self, key, value):
        calls.append(key)
        return real(self, key, value)

    monkeypatch.setattr(zarr.Array, "__setitem__", through_zarr)
    ours = write_volume(a, tmp_path / "ours.zarr", chunks=(8, 16, 16), max_side=8, **options)
    assert calls == []
    from napari_unwind.io import ome_zarr

    monkeypatch.setattr(ome_zarr._DirectWriter, "usable", staticmethod(lambda array: False))
    ref = write_volume(a, tmp_path / "ref.zarr", chunks=(8, 16, 16), max_side=8, **options)
    assert calls, "the reference store was not written by zarr"

    def files(root):
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("c/**/*")) if p.is_file()}

    mine, theirs = files(ours), files(ref)
    assert len(theirs) > 20 and mine.keys() == theirs.keys()
    assert [k for k in theirs if mine[k] != theirs[k]] == []
    np.testing.assert_array_equal(zarr.open_array(str(ours / "0"), mode="r")[...], a)


def test_import_volume_takes_an_array_and_open_volume_refuses_one(tmp_path):
    a = np.random.default_rng(8).integers(0, 999, (20, 12, 9)).astype(np.uint16)
    v = import_volume(a, tmp_path / "a.zarr", spacing=(2.0, 1.0, 1.0), unit="um", chunks=8)
    np.testing.assert_array_equal(v.data.compute(), a)
    assert v.spacing == (2.0, 1.0, 1.0) and v.unit == "micrometer"
    with pytest.raises(InvalidInputError, match="open_volume needs a path .* got ndarray; .*as_volume"):
        open_volume(a)
