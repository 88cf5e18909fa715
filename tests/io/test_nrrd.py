"""NRRD / NHDR reading and writing, checked against pynrrd's own reader and writer."""

from __future__ import annotations

import gzip
import os
import zlib

import dask.array as da
import nrrd
import numpy as np
import pytest

from napari_unwind.errors import InvalidInputError, OutputError
from napari_unwind.io import Volume, nrrd_io, open_volume, write_volume
from napari_unwind.io.nrrd_io import read_nrrd, write_nrrd
from napari_unwind.progress import Progress, run

SPACING = (3.0, 2.0, 0.5)  # axis0, axis1, axis2: deliberately all different
ORIGIN = (10.0, -20.0, 30.5)


@pytest.fixture
def vol() -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.integers(-3000, 3000, size=(4, 5, 6)).astype(np.int16)


@pytest.mark.parametrize("encoding", ["gzip", "raw", "bzip2"])
def test_written_file_read_by_pynrrd(tmp_path, vol, encoding):
    out = write_volume(vol, tmp_path / "a.nrrd", spacing=SPACING, unit="um", origin=ORIGIN, encoding=encoding)
    data, header = nrrd.read(str(out), index_order="C")
    np.testing.assert_array_equal(data, vol)
    assert data.dtype == vol.dtype
    # the header lists axes fastest first: everything reversed
    assert list(header["sizes"]) == [6, 5, 4]
    np.testing.assert_allclose(header["space directions"], np.diag(SPACING[::-1]))
    np.testing.assert_allclose(header["space origin"], ORIGIN[::-1])
    assert header["space units"] == ["um", "um", "um"]
    assert header["encoding"] == encoding
    assert [p.name for p in tmp_path.iterdir()] == ["a.nrrd"]


def test_read_pynrrd_file_with_oblique_directions(tmp_path):
    # file axes (x, y, z) with spacings 0.5, 2, 3 along rotated and flipped directions
    rng = np.random.default_rng(2)
    c_array = rng.random((7, 5, 3)).astype(np.float32)  # (z, y, x)
    theta = 0.3
    rot = np.array([[np.cos(theta), -np.sin(theta), 0], [np.sin(theta), np.cos(theta), 0], [0, 0, 1]])
    directions = rot @ np.diag([0.5, -2.0, 3.0])  # columns are the axis vectors
    header = {"space": "left-posterior-superior", "space directions": directions.T,
              "space origin": np.array([1.0, 2.0, 3.0]), "kinds": ["domain"] * 3, "encoding": "raw"}
    nrrd.write(str(tmp_path / "o.nrrd"), c_array, header, index_order="C")
    v = read_nrrd(tmp_path / "o.nrrd")
    assert v.shape == (7, 5, 3)
    np.testing.assert_allclose(v.spacing, (3.0, 2.0, 0.5))
    np.testing.assert_allclose(v.origin, (3.0, 2.0, 1.0))
    assert v.unit == "millimeter"  # anatomical space without 'space units'
    np.testing.assert_array_equal(v.data.compute(), c_array)
    np.testing.assert_allclose(v.metadata["space directions"], directions.T)
    assert v.format == "nrrd" and v.source == str(tmp_path / "o.nrrd")


def test_spacings_field_and_units(tmp_path, vol):
    header = {"spacings": np.array([0.25, 0.5, 4.0]), "units": ["um", "um", "um"], "encoding": "gzip"}
    nrrd.write(str(tmp_path / "s.nrrd"), vol, header, index_order="C")
    v = read_nrrd(tmp_path / "s.nrrd")
    np.testing.assert_allclose(v.spacing, (4.0, 0.5, 0.25))
    assert v.unit == "micrometer"
    assert v.origin == (0.0, 0.0, 0.0)
    np.testing.assert_array_equal(v.data.compute(), vol)


def test_no_geometry_means_unit_spacing_and_unknown_unit(tmp_path, vol):
    nrrd.write(str(tmp_path / "n.nrrd"), vol, {"encoding": "raw"}, index_order="C")
    v = read_nrrd(tmp_path / "n.nrrd")
    assert v.spacing == (1.0, 1.0, 1.0) and v.unit is None


def test_big_endian_raw(tmp_path, vol):
    nrrd.write(str(tmp_path / "b.nrrd"), vol.astype(">i2"), {"encoding": "raw"}, index_order="C")
    assert nrrd.read_header(str(tmp_path / "b.nrrd"))["endian"] == "big"
    v = read_nrrd(tmp_path / "b.nrrd")
    assert v.dtype == np.dtype("int16") and v.dtype.isnative
    np.testing.assert_array_equal(v.data.compute(), vol)


def test_raw_is_memory_mapped_lazily_and_gzip_read_eagerly(tmp_path, vol):
    raw = write_volume(vol, tmp_path / "r.nrrd", spacing=SPACING, encoding="raw")
    gz = write_volume(vol, tmp_path / "g.nrrd", spacing=SPACING, encoding="gzip")
    v_raw, v_gz = open_volume(raw), open_volume(gz)
    assert isinstance(v_raw.data, da.Array)
    # change the voxels on disk after opening: the memory-mapped volume sees it, the eager one does not
    changed = (vol + 1).astype(np.int16)
    with open(raw, "r+b") as fh:
        fh.seek(os.path.getsize(raw) - changed.nbytes)
        fh.write(changed.astype("<i2").tobytes())
    write_volume(changed, gz, spacing=SPACING, encoding="gzip", overwrite=True)
    np.testing.assert_array_equal(v_raw.data.compute(), changed)
    np.testing.assert_array_equal(v_gz.data.compute(), vol)


def test_chunks_are_slabs_of_planes(tmp_path, vol):
    out = write_volume(vol, tmp_path / "c.nrrd", encoding="raw")
    v = read_nrrd(out, chunks=(1, 5, 6))
    assert v.data.numblocks == (4, 1, 1)
    np.testing.assert_array_equal(v.data[2].compute(), vol[2])
    assert read_nrrd(out).data.chunks[1:] == ((5,), (6,))


@pytest.mark.parametrize("encoding, companion", [("gzip", "d.raw.gz"), ("raw", "d.raw"), ("bzip2", "d.raw.bz2")])
def test_nhdr_detached(tmp_path, vol, encoding, companion):
    out = write_volume(vol, tmp_path / "d.nhdr", spacing=SPACING, unit="mm", origin=ORIGIN, encoding=encoding)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["d.nhdr", companion])  # no temporary leftovers
    header = nrrd.read_header(str(out))
    assert header["data file"] == companion  # the final name, not the temporary one
    data, _ = nrrd.read(str(out), index_order="C")
    np.testing.assert_array_equal(data, vol)
    v = open_volume(out)
    np.testing.assert_array_equal(v.data.compute(), vol)
    np.testing.assert_allclose(v.spacing, SPACING)
    np.testing.assert_allclose(v.origin, ORIGIN)
    assert v.unit == "millimeter"


def test_nhdr_overwrite_replaces_companion(tmp_path, vol):
    out = write_volume(vol, tmp_path / "d.nhdr", encoding="raw")
    write_volume(vol * 2, out, encoding="raw", overwrite=True)
    np.testing.assert_array_equal(open_volume(out).data.compute(), vol * 2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.nhdr", "d.raw"]


def test_nhdr_refuses_to_replace_a_foreign_companion(tmp_path, vol):
    foreign = tmp_path / "d.raw.gz"
    foreign.write_bytes(b"not ours")
    with pytest.raises(OutputError, match="d.raw.gz"):
        write_volume(vol, tmp_path / "d.nhdr")
    assert foreign.read_bytes() == b"not ours"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.raw.gz"]


def test_nhdr_failure_leaves_nothing(tmp_path, vol):
    def boom(block):
        raise RuntimeError("disk on fire")

    bad = da.from_array(vol, chunks=(2, 5, 6)).map_blocks(boom, dtype=vol.dtype)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_volume(bad, tmp_path / "d.nhdr")
    assert list(tmp_path.iterdir()) == []


def test_detached_header_with_missing_data_file(tmp_path, vol):
    out = write_volume(vol, tmp_path / "d.nhdr", encoding="raw")
    (tmp_path / "d.raw").unlink()
    with pytest.raises(InvalidInputError, match="d.raw does not exist"):
        open_volume(out)


def test_truncated_raw(tmp_path, vol):
    out = write_volume(vol, tmp_path / "t.nrrd", encoding="raw")
    size = os.path.getsize(out)
    with open(out, "r+b") as fh:
        fh.truncate(size - 10)
    with pytest.raises(InvalidInputError) as err:
        open_volume(out)
    assert f"expected {vol.nbytes} bytes" in str(err.value)
    assert f"found {vol.nbytes - 10}" in str(err.value)


def test_truncated_gzip(tmp_path):
    rng = np.random.default_rng(3)
    vol = rng.integers(0, 60000, size=(20, 30, 40)).astype(np.uint16)  # random: compresses badly
    out = write_volume(vol, tmp_path / "t.nrrd", encoding="gzip")
    with open(out, "r+b") as fh:
        fh.truncate(os.path.getsize(out) // 2)
    payload = out.read_bytes().split(b"\n\n", 1)[1]
    recoverable = len(zlib.decompressobj(zlib.MAX_WBITS | 16).decompress(payload))
    assert 0 < recoverable < vol.nbytes
    with pytest.raises(InvalidInputError, match=f"expected {vol.nbytes} bytes of voxels, found {recoverable}"):
        open_volume(out)


@pytest.mark.parametrize("skip", [7, -1])
def test_multi_member_gzip_with_byte_skip(tmp_path, skip):
    vol = np.random.default_rng(4).integers(0, 60000, size=(6, 7, 8)).astype(np.uint16)
    raw = vol.astype("<u2").tobytes()
    header = ("NRRD0004\ntype: uint16\ndimension: 3\nsizes: 8 7 6\nendian: little\nencoding: gzip\n"
              f"byte skip: {skip}\n\n")
    payload = gzip.compress(b"1234567" + raw[:100]) + gzip.compress(raw[100:])  # two gzip members
    (tmp_path / "m.nrrd").write_bytes(header.encode() + payload)
    np.testing.assert_array_equal(read_nrrd(tmp_path / "m.nrrd").data.compute(), vol)


def test_not_an_nrrd(tmp_path):
    p = tmp_path / "x.nrrd"
    p.write_bytes(b"hello world\n\n")
    with pytest.raises(InvalidInputError, match="not a readable NRRD"):
        open_volume(p)


def test_four_dimensional(tmp_path, vol):
    # a length-1 list axis (fastest in the file) is dropped; a real channel axis is refused
    one = vol[..., np.newaxis]
    # kinds are listed in file order (fastest first): the C-order last axis is the file's first
    nrrd.write(str(tmp_path / "one.nrrd"), one, {"kinds": ["list", "domain", "domain", "domain"], "encoding": "raw"},
               index_order="C")
    v = read_nrrd(tmp_path / "one.nrrd")
    assert v.shape == vol.shape
    np.testing.assert_array_equal(v.data.compute(), vol)
    three = np.stack([vol] * 3, axis=-1)
    nrrd.write(str(tmp_path / "three.nrrd"), three, {"kinds": ["list", "domain", "domain", "domain"]},
               index_order="C")
    with pytest.raises(InvalidInputError, match="3D scalar volume"):
        read_nrrd(tmp_path / "three.nrrd")


def test_writer_options_validated(tmp_path, vol):
    with pytest.raises(InvalidInputError, match="encoding"):
        write_volume(vol, tmp_path / "x.nrrd", encoding="zip")
    with pytest.raises(InvalidInputError, match="compression_level"):
        write_volume(vol, tmp_path / "x.nrrd", compression_level=0)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("dtype", ["uint8", "int8", "uint16", "int32", "uint32", "float32", "float64"])
def test_every_dtype_round_trips(tmp_path, dtype):
    vol = (np.arange(60).reshape(3, 4, 5) * 1.5).astype(dtype)
    out = write_volume(vol, tmp_path / "x.nrrd")
    data, _ = nrrd.read(str(out), index_order="C")
    assert data.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(data, vol)
    np.testing.assert_array_equal(open_volume(out).data.compute(), vol)


def test_streams_in_slabs_with_progress(tmp_path, vol, monkeypatch):
    monkeypatch.setattr(nrrd_io, "write_slab_depth", lambda volume: 3)  # 4 planes -> slabs of 3 and 1
    v = Volume(da.from_array(vol, chunks=(1, 5, 6)), spacing=SPACING)
    records: list[Progress] = []
    run(write_nrrd(v, tmp_path / "p.nrrd"), records.append)
    assert [(r.done, r.total) for r in records] == [(1, 2), (2, 2)]
    data, _ = nrrd.read(str(tmp_path / "p.nrrd"), index_order="C")
    np.testing.assert_array_equal(data, vol)


def test_ascii_encoding(tmp_path, vol):
    nrrd.write(str(tmp_path / "a.nrrd"), vol, {"encoding": "ascii", "spacings": [1.0, 2.0, 3.0]}, index_order="C")
    v = read_nrrd(tmp_path / "a.nrrd")
    assert v.dtype == vol.dtype
    np.testing.assert_array_equal(v.data.compute(), vol)
    np.testing.assert_allclose(v.spacing, (3.0, 2.0, 1.0))


def test_detached_nrrd_companion_temp_records_its_owner(tmp_path, monkeypatch):
    """A killed write of a detached header leaves a companion temp that the next write can clean up."""
    import napari_unwind.io.nrrd_io as nrrd_io
    from napari_unwind.io import write_volume
    from napari_unwind.io._atomic import remove_stale_temps

    seen = []
    real = nrrd_io.temp_path

    def spy(path, **kw):
        p = real(path, **kw)
        seen.append(p)
        return p

    monkeypatch.setattr(nrrd_io, "temp_path", spy)
    write_volume(np.arange(24, dtype=np.uint16).reshape(2, 3, 4), tmp_path / "a.nhdr")
    assert seen, "the companion must be written under an owned temporary name"
    # the owner is alive: never removed; the name parses as a temp of the companion
    assert remove_stale_temps(tmp_path / "a.raw") == []
    assert ".p" in seen[0].name and seen[0].name.startswith(".a.raw.")
