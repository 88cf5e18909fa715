"""Raw voxels + the original Unwind .dat header: napari_unwind.io.raw."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from napari_unwind.errors import InvalidInputError, OutputError
from napari_unwind.io import open_volume, write_volume
from napari_unwind.io import raw as rawmod
from napari_unwind.io._atomic import final_name
from napari_unwind.io._lazy import RawFileArray
from napari_unwind.io._volume import Volume
from napari_unwind.io.raw import read_dat_header, read_raw, write_raw
from napari_unwind.progress import run

DTYPES = ["uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64"]


def _data(dtype: str, shape=(6, 5, 7), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    info = np.iinfo(dtype) if np.issubdtype(np.dtype(dtype), np.integer) else None
    if info is not None:
        return rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=dtype)
    return (rng.standard_normal(shape) * 1000).astype(dtype)


def _write_pair(folder, name, data: np.ndarray, header: str) -> None:
    (folder / f"{name}.raw").write_bytes(np.ascontiguousarray(data).tobytes())
    (folder / f"{name}.dat").write_text(header)


# --------------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("target", ["fish.dat", "fish.raw"])
def test_round_trip_every_dtype(tmp_path, dtype, target):
    data = _data(dtype)
    written = write_volume(data, tmp_path / target, spacing=(0.03, 0.02, 0.01), unit="mm", origin=(1.5, -2.0, 0.25))
    assert written == tmp_path / target
    assert (tmp_path / "fish.dat").is_file() and (tmp_path / "fish.raw").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temporary files left behind"
    # independent check of the bytes: C order (Z, Y, X), little endian, nothing else in the file
    on_disk = np.fromfile(tmp_path / "fish.raw", dtype=np.dtype(dtype).newbyteorder("<"))
    np.testing.assert_array_equal(on_disk.reshape(data.shape), data)
    for path in (tmp_path / "fish.dat", tmp_path / "fish.raw"):
        vol = open_volume(path)
        assert vol.format == "raw"
        assert vol.dtype == np.dtype(dtype)
        assert vol.shape == data.shape
        assert vol.spacing == (0.03, 0.02, 0.01)
        assert vol.unit == "millimeter"
        assert vol.origin == (1.5, -2.0, 0.25)
        np.testing.assert_array_equal(vol.data.compute(), data)


def test_header_text_is_the_original_layout(tmp_path):
    data = _data("uint16", shape=(4, 3, 2))
    list(write_raw(Volume(data, spacing=(3.0, 2.0, 1.0), unit="um"), tmp_path / "a.dat"))
    fields = dict(line.split(":", 1) for line in (tmp_path / "a.dat").read_text().splitlines())
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    assert fields["RawFile"] == "a.raw"
    assert fields["Resolution"].split() == ["2", "3", "4"]  # X Y Z: fastest axis first
    assert [float(v) for v in fields["SliceThickness"].split()] == [1.0, 2.0, 3.0]
    assert fields["Format"] == "USHORT"
    assert fields["Unit"] == "um"


def test_direct_functions_and_progress(tmp_path):
    data = _data("float32", shape=(9, 4, 4))
    vol = Volume(data, spacing=(2.0, 1.0, 1.0), unit="nm")
    records = []
    run(write_raw(vol, tmp_path / "v.dat"), records.append)
    assert records and records[-1].done == records[-1].total
    back = read_raw(tmp_path / "v.dat")
    np.testing.assert_array_equal(back.data.compute(), data)
    assert back.unit == "nanometer"


def test_big_endian_and_aliases(tmp_path):
    data = _data("int16", shape=(3, 4, 5))
    (tmp_path / "scan.bin").write_bytes(data.astype(">i2").tobytes())
    (tmp_path / "scan.dat").write_text(
        "# written by hand\n"
        "objectfilename: scan.bin\n"
        "RESOLUTION: 5 4 3\n"
        "format: int16\n"
        "Spacing: 0.5, 0.25, 2\n"
        "ByteOrder: BigEndian\n"
        "TaggedFileName: ---\nGridType: EQUIDISTANT\nObjectModel: I\n"
    )
    vol = open_volume(tmp_path / "scan.dat")
    assert vol.dtype == np.dtype("int16") and vol.dtype.isnative
    assert vol.spacing == (2.0, 0.25, 0.5)
    assert vol.unit is None
    np.testing.assert_array_equal(vol.data.compute(), data)


def test_write_big_endian(tmp_path):
    data = _data("uint16", shape=(2, 3, 4))
    write_volume(data, tmp_path / "b.dat", byteorder="big")
    np.testing.assert_array_equal(np.fromfile(tmp_path / "b.raw", dtype=">u2").reshape(data.shape), data)
    assert read_dat_header(tmp_path / "b.dat")["dtype"] == np.dtype(">u2")
    np.testing.assert_array_equal(open_volume(tmp_path / "b.raw").data.compute(), data)


def test_raw_found_through_a_header_with_another_stem(tmp_path):
    data = _data("uint8", shape=(2, 3, 4))
    (tmp_path / "voxels.raw").write_bytes(data.tobytes())
    (tmp_path / "header.dat").write_text("RawFile: voxels.raw\nResolution: 4 3 2\nFormat: UCHAR\n")
    np.testing.assert_array_equal(open_volume(tmp_path / "voxels.raw").data.compute(), data)


# ---------------------------------------------------------------------------------------------------- bad inputs
def test_truncated_raw(tmp_path):
    data = _data("uint16", shape=(4, 3, 5))
    (tmp_path / "t.raw").write_bytes(data.tobytes()[:-7])
    (tmp_path / "t.dat").write_text("RawFile: t.raw\nResolution: 5 3 4\nFormat: USHORT\n")
    with pytest.raises(InvalidInputError) as err:
        open_volume(tmp_path / "t.dat")
    msg = str(err.value)
    assert "truncated raw file" in msg
    assert f"expected {data.nbytes} bytes (5 x 3 x 4 x 2)" in msg
    assert f"found {data.nbytes - 7}" in msg
    assert "incomplete" in msg


def test_larger_raw_warns_and_reads(tmp_path):
    data = _data("uint8", shape=(2, 3, 4))
    (tmp_path / "l.raw").write_bytes(data.tobytes() + b"\xff" * 10)
    (tmp_path / "l.dat").write_text("RawFile: l.raw\nResolution: 4 3 2\nFormat: UCHAR\n")
    with pytest.warns(UserWarning, match="ignoring the rest"):
        vol = open_volume(tmp_path / "l.dat")
    np.testing.assert_array_equal(vol.data.compute(), data)


@pytest.mark.parametrize(
    ("header", "match"),
    [
        ("RawFile: x.raw\nResolution: 4 3 2\nFormat: QUADRUPLE\n", r"unknown Format 'QUADRUPLE'.*UCHAR"),
        ("RawFile: x.raw\nResolution 4 3 2\nFormat: UCHAR\n", r"line 2: expected 'Key: value'"),
        ("RawFile: x.raw\nFormat: UCHAR\n", r"lacks Resolution"),
        ("Resolution: 4 3 2\nFormat: UCHAR\n", r"lacks RawFile"),
        ("RawFile: x.raw\nResolution: 4 3\nFormat: UCHAR\n", r"3 whole numbers.*3D"),
        ("RawFile: x.raw\nResolution: 4 3 two\nFormat: UCHAR\n", r"line 2: Resolution needs 3 whole numbers"),
        ("RawFile: x.raw\nResolution: 4 0 2\nFormat: UCHAR\n", r"must be positive"),
        ("RawFile: x.raw\nResolution: 4 3 2\nFormat: UCHAR\nSliceThickness: 1 -1 1\n", r"positive"),
        ("RawFile: x.raw\nResolution: 4 3 2\nFormat: UCHAR\nByteOrder: Middle\n", r"LittleEndian or BigEndian"),
        ("RawFile: x.raw\nObjectFileName: y.raw\nResolution: 4 3 2\nFormat: UCHAR\n", r"repeats line 1"),
        ("RawFile: x.raw\nResolution: 4 3 2\nFormat: UCHAR\nObjectModel: RGBA\n", r"colour"),
        ("RawFile: x.raw\nResolution: 4 3 2\nFormat: UCHAR\nUnit: furlong\n", r"line 4: unknown length unit"),
    ],
)
def test_malformed_headers(tmp_path, header, match):
    (tmp_path / "x.raw").write_bytes(bytes(24))
    (tmp_path / "x.dat").write_text(header)
    with pytest.raises(InvalidInputError, match=match):
        open_volume(tmp_path / "x.dat")


def test_missing_header_explains_what_to_write(tmp_path):
    (tmp_path / "lonely.raw").write_bytes(bytes(24))
    with pytest.raises(InvalidInputError) as err:
        open_volume(tmp_path / "lonely.raw")
    assert "no .dat header" in str(err.value)
    assert "Resolution:" in str(err.value) and "lonely.dat" in str(err.value)


def test_missing_raw_named_by_header(tmp_path):
    (tmp_path / "h.dat").write_text("RawFile: gone.raw\nResolution: 4 3 2\nFormat: UCHAR\n")
    with pytest.raises(InvalidInputError, match="gone.raw, which does not exist"):
        open_volume(tmp_path / "h.dat")


# -------------------------------------------------------------------------------------------------------- laziness
def test_large_raw_is_lazy_and_chunked_by_slabs(tmp_path, monkeypatch):
    shape = (400, 512, 512)  # 200 MiB of uint16, a sparse file: nothing is really on disk
    with open(tmp_path / "big.raw", "wb") as fh:
        fh.truncate(int(np.prod(shape)) * 2)
    (tmp_path / "big.dat").write_text("RawFile: big.raw\nResolution: 512 512 400\nFormat: USHORT\n")
    reads: list = []
    original = RawFileArray.__getitem__

    def counting(self, key):
        reads.append(key)
        return original(self, key)

    monkeypatch.setattr(RawFileArray, "__getitem__", counting)
    vol = open_volume(tmp_path / "big.dat")
    assert reads == [], "opening read voxels"
    depth = rawmod.slab_depth(shape[1:], np.uint16)
    assert 1 < depth < shape[0]
    assert vol.data.chunks[1:] == ((512,), (512,))
    assert set(vol.data.chunks[0][:-1]) == {depth}
    assert vol.data.numblocks == (-(-shape[0] // depth), 1, 1)
    assert vol.data[123, 45, 67].compute() == 0
    assert len(reads) == 1, f"one voxel needed {len(reads)} chunk reads"


def test_raw_array_pickles_without_data(tmp_path):
    import pickle

    data = _data("uint16", shape=(3, 4, 5))
    (tmp_path / "p.raw").write_bytes(data.tobytes())
    arr = RawFileArray(tmp_path / "p.raw", "<u2", data.shape)
    blob = pickle.dumps(arr)
    assert len(blob) < 1000
    np.testing.assert_array_equal(pickle.loads(blob)[1:, ::2, 3], data[1:, ::2, 3])


# ----------------------------------------------------------------------------------------- companion file safety
def test_final_name():
    assert final_name(".fish.dat.1a2b3c4d.unwind-tmp") == "fish.dat"
    assert final_name("/x/.a.b.raw.0000ffff.unwind-tmp") == "a.b.raw"
    assert final_name("fish.dat") == "fish.dat"
    assert final_name(".fish.dat.XYZ.unwind-tmp") == ".fish.dat.XYZ.unwind-tmp"


def test_existing_companion_is_not_clobbered(tmp_path):
    (tmp_path / "fish.raw").write_bytes(b"precious")
    with pytest.raises(OutputError, match="fish.raw already exists"):
        write_volume(_data("uint8"), tmp_path / "fish.dat")
    assert (tmp_path / "fish.raw").read_bytes() == b"precious"
    assert not (tmp_path / "fish.dat").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_overwrite_replaces_the_pair(tmp_path):
    first, second = _data("uint8", seed=1), _data("int16", seed=2)
    write_volume(first, tmp_path / "fish.dat")
    with pytest.raises(OutputError, match="already exists"):
        write_volume(second, tmp_path / "fish.dat")
    write_volume(second, tmp_path / "fish.dat", overwrite=True)
    vol = open_volume(tmp_path / "fish.dat")
    assert vol.dtype == np.int16
    np.testing.assert_array_equal(vol.data.compute(), second)


def test_failed_write_leaves_nothing(tmp_path):
    def boom(block):
        raise RuntimeError("disk on fire")

    import dask.array as da

    data = da.from_array(_data("uint8", shape=(4, 3, 2)), chunks=(2, 3, 2)).map_blocks(boom, dtype=np.uint8)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_volume(data, tmp_path / "f.dat")
    assert list(tmp_path.iterdir()) == []


def test_no_warning_for_exact_size(tmp_path):
    data = _data("float64", shape=(2, 2, 2))
    _write_pair(tmp_path, "e", data, "RawFile: e.raw\nResolution: 2 2 2\nFormat: DOUBLE\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(open_volume(tmp_path / "e.dat").data.compute(), data)
