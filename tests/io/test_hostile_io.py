"""The volume I/O layer against hostile input: missing and corrupt chunks, truncated files, relative paths on a
dask.distributed cluster, full disks, pyramid geometry, ImageJ files written by other programs, and a matrix of
truncated / corrupted files of every format we read."""

from __future__ import annotations

import builtins
import errno
import io
import json
import os
import pickle
import re
import warnings

import dask
import numpy as np
import pytest
import tifffile
import zarr

from conftest import no_leftovers
from napari_unwind.errors import InvalidInputError, OutputError, UnknownFormatError
from napari_unwind.io import open_volume, write_volume


def _ramp(shape=(40, 30, 30), dtype="uint8", seed=0):
    """Random values that are never 0 (the fill value), so a chunk read as fill is always wrong."""
    return np.random.default_rng(seed).integers(1, 200, shape).astype(dtype)


# ------------------------------------------------------------------------------------------------------------------
# 1. missing chunks
# ------------------------------------------------------------------------------------------------------------------
def test_a_missing_chunk_of_a_store_we_wrote_is_an_error_naming_it(tmp_path):
    a = _ramp()
    out = write_volume(a, tmp_path / "v.zarr", chunks=16, max_side=16)
    chunk = out / "0" / "c" / "0" / "0" / "0"
    chunk.unlink()
    v = open_volume(out)
    with pytest.raises(InvalidInputError, match=re.escape(str(chunk)) + ".*missing"):
        v.data.compute()
    with pytest.raises(InvalidInputError, match=re.escape(str(chunk))):
        v.data[2:5, 3:4, 1:9].compute()  # a slice inside the missing chunk
    np.testing.assert_array_equal(v.data[16:].compute(), a[16:])  # the other chunks still read


def test_a_missing_chunk_of_a_coarser_level_is_an_error_too(tmp_path):
    out = write_volume(_ramp(), tmp_path / "v.zarr", chunks=8, max_side=8)
    chunk = out / "1" / "c" / "1" / "0" / "1"
    chunk.unlink()
    v = open_volume(out)
    v.data.compute()
    with pytest.raises(InvalidInputError, match=re.escape(str(chunk))):
        v.levels[1].compute()


def test_chunks_that_are_all_fill_are_still_complete(tmp_path):
    """Zeros where the fill value is 0: the writer records that every chunk was written, and they read back."""
    a = _ramp()
    a[:16, :16, :16] = 0
    out = write_volume(a, tmp_path / "v.zarr", chunks=16, max_side=16)
    attrs = json.loads((out / "zarr.json").read_text())["attributes"]["unwind"]
    assert attrs["all_chunks_written"] is True
    assert (out / "0" / "c" / "0" / "0" / "0").is_file()
    np.testing.assert_array_equal(open_volume(out).data.compute(), a)


def test_stores_without_the_record_read_missing_chunks_as_fill(tmp_path):
    """A store written by another program (or an older version) is read as zarr reads it: no check."""
    a = _ramp()
    a[:16, :16, :16] = 0
    root = zarr.open_group(str(tmp_path / "old.zarr"), mode="w", zarr_format=3)
    arr = root.create_array("0", shape=a.shape, chunks=(16, 16, 16), dtype=a.dtype, fill_value=0)
    arr[...] = a  # zarr's default: the all-zero chunk is not stored
    root.attrs["ome"] = {"version": "0.5", "multiscales": [{
        "axes": [{"name": n, "type": "space"} for n in "zyx"],
        "datasets": [{"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 1]}]}]}]}
    assert not (tmp_path / "old.zarr" / "0" / "c" / "0" / "0" / "0").exists()
    np.testing.assert_array_equal(open_volume(tmp_path / "old.zarr").data.compute(), a)


# ------------------------------------------------------------------------------------------------------------------
# 2. corrupt chunks
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("scheduler", ["threads", "synchronous"])
def test_a_corrupt_chunk_is_one_error_naming_the_file(tmp_path, scheduler):
    out = write_volume(_ramp(), tmp_path / "v.zarr", chunks=16, max_side=16)
    chunk = out / "0" / "c" / "1" / "0" / "1"
    chunk.write_bytes(b"this is not a blosc stream" * 20)
    v = open_volume(out)
    with dask.config.set(scheduler=scheduler), pytest.raises(InvalidInputError) as info:
        v.data.compute()
    msg = str(info.value)
    assert str(chunk) in msg and "corrupt" in msg and "re-import" in msg and "\n" not in msg
    copy = pickle.loads(pickle.dumps(info.value))  # a dask.distributed worker sends it back pickled
    assert type(copy) is InvalidInputError and str(copy) == msg


def test_a_corrupt_chunk_of_a_foreign_store_is_named_too(tmp_path):
    a = _ramp()
    arr = zarr.create_array(str(tmp_path / "plain.zarr"), shape=a.shape, chunks=(16, 16, 16), dtype=a.dtype)
    arr[...] = a
    chunk = tmp_path / "plain.zarr" / "c" / "0" / "1" / "0"
    chunk.write_bytes(b"\x00garbage" * 7)
    with pytest.raises(InvalidInputError, match=re.escape(str(chunk)) + ".*corrupt"):
        open_volume(tmp_path / "plain.zarr").data.compute()


def test_broken_zarr_metadata_is_one_error(tmp_path):
    out = write_volume(_ramp(), tmp_path / "v.zarr", chunks=16, max_side=16)
    (out / "1" / "zarr.json").write_text("{ not json")
    with pytest.raises(InvalidInputError, match=re.escape(str(out))):
        open_volume(out)


# ------------------------------------------------------------------------------------------------------------------
# 3. relative paths on a dask.distributed cluster
# ------------------------------------------------------------------------------------------------------------------
RELATIVE_TARGETS = ["v.zarr", "v.tif", "v.nrrd", "v.nhdr", "v.nii", "v.nii.gz", "v.dat", "v.dicom",
                    "slices/v_{:03d}.png"]


@pytest.fixture(scope="module")
def cluster_client():
    """A one-worker process cluster started in the current folder (the test then moves to another one)."""
    distributed = pytest.importorskip("distributed")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=40)
    client = distributed.Client(cluster)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def test_relative_paths_read_the_file_on_a_cluster_started_elsewhere(tmp_path, monkeypatch, cluster_client):
    a = _ramp((12, 10, 9), "uint16")
    written = {t: write_volume(a, tmp_path / t, spacing=(1, 1, 1), unit="mm") for t in RELATIVE_TARGETS}
    monkeypatch.chdir(tmp_path)
    for target, path in written.items():
        relative = os.path.relpath(path, tmp_path)
        v = open_volume(relative)
        got = cluster_client.compute(v.data).result()
        np.testing.assert_array_equal(got, a, err_msg=target)
    # a corrupt chunk read on the worker comes back as the same one-line error
    chunk = tmp_path / "v.zarr" / "0" / "c" / "0" / "0" / "0"
    chunk.write_bytes(b"garbage" * 9)
    with pytest.raises(InvalidInputError, match=re.escape(str(chunk)) + ".*corrupt"):
        cluster_client.compute(open_volume("v.zarr").data).result()


# ------------------------------------------------------------------------------------------------------------------
# 4. a full disk, for every writer
# ------------------------------------------------------------------------------------------------------------------
WRITE_TARGETS = ["v.zarr", "v.tif", "v.nrrd", "v.nhdr", "v.nii", "v.nii.gz", "v.dat", "v.raw", "v.dicom",
                 "slices/v_{:03d}.png", "slices/v_{:03d}.tif"]


class _Disk:
    """Bytes left on a pretend disk; writes past it fail with ENOSPC (or EDQUOT)."""

    left = 0
    code = errno.ENOSPC


class _FullFileIO(io.FileIO):
    def write(self, b):
        n = memoryview(b).nbytes
        if n > _Disk.left:
            raise OSError(_Disk.code, os.strerror(_Disk.code))
        _Disk.left -= n
        return super().write(b)


def _full_disk(monkeypatch, folder, budget, code=errno.ENOSPC):
    """Make every file opened for writing under ``folder`` fail once ``budget`` bytes are written."""
    real_open = builtins.open
    _Disk.left, _Disk.code = budget, code
    folder = str(folder)

    def fake_open(file, mode="r", buffering=-1, encoding=None, errors=None, newline=None, closefd=True, opener=None):
        if (isinstance(file, str | os.PathLike) and any(c in mode for c in "wxa+")
                and os.path.abspath(os.fspath(file)).startswith(folder)):
            raw = _FullFileIO(os.fspath(file), mode.replace("b", "").replace("t", ""))
            buffered = io.BufferedRandom(raw) if "+" in mode else io.BufferedWriter(raw)
            if "b" in mode:
                return buffered
            return io.TextIOWrapper(buffered, encoding=encoding or "utf-8", errors=errors, newline=newline)
        return real_open(file, mode, buffering, encoding, errors, newline, closefd, opener)

    monkeypatch.setattr(builtins, "open", fake_open)
    monkeypatch.setattr(io, "open", fake_open)

    def write_array(self, data, dtype=None):  # tifffile writes arrays with ndarray.tofile, past Python's write
        data = np.ascontiguousarray(data, dtype)
        self._fh.write(data.tobytes())
        return data.nbytes

    monkeypatch.setattr(tifffile.FileHandle, "write_array", write_array)


@pytest.mark.parametrize("budget", [0, 6000])
@pytest.mark.parametrize("target", WRITE_TARGETS)
def test_a_full_disk_is_one_output_error_and_leaves_nothing(tmp_path, monkeypatch, target, budget):
    a = _ramp((20, 24, 24), "uint8")
    out = tmp_path / "out"
    out.mkdir()
    _full_disk(monkeypatch, out, budget)
    with pytest.raises(OutputError) as info:
        write_volume(a, out / target, spacing=(1, 1, 1), unit="mm")
    msg = str(info.value)
    final = out / (target.split("/")[0] if target.startswith("slices") else target)
    assert str(final) in msg and "no space left" in msg and "\n" not in msg, msg
    assert "unwind-tmp" not in msg
    assert f"{a.nbytes}" in msg.replace(",", "") or "KiB" in msg  # the size needed
    monkeypatch.undo()
    assert not final.exists() and no_leftovers(tmp_path) == [] and os.listdir(out) == []


def test_a_full_quota_is_reported_like_a_full_disk(tmp_path, monkeypatch):
    _full_disk(monkeypatch, tmp_path, 100, errno.EDQUOT)
    with pytest.raises(OutputError, match="quota"):
        write_volume(_ramp(), tmp_path / "v.dicom", unit="mm")
    monkeypatch.undo()
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------------------------------------------------------
# 5. misleading messages: truncated TIFF, infinities
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["imagej", "plain", "tifffile", "compressed"])
def test_a_truncated_tiff_says_it_is_truncated(tmp_path, kind):
    a = _ramp((20, 73, 73), "uint8" if kind != "plain" else "int16")
    if kind == "tifffile":
        tifffile.imwrite(tmp_path / "full.tif", a)  # no ImageJ or JSON metadata: one page per plane
    elif kind == "compressed":
        tifffile.imwrite(tmp_path / "full.tif", a, compression="zlib", imagej=True)
    else:
        write_volume(a, tmp_path / "full.tif", spacing=(2, 1, 1), unit="um")
    whole = (tmp_path / "full.tif").read_bytes()
    (tmp_path / "trunc.tif").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(InvalidInputError) as info:
        open_volume(tmp_path / "trunc.tif").data.compute()
    msg = str(info.value)
    assert "truncated" in msg and str(tmp_path / "trunc.tif") in msg and "single 2D image" not in msg, msg


@pytest.mark.parametrize("value, word", [(np.inf, "+inf"), (-np.inf, "-inf"), (np.nan, "NaN")])
def test_non_finite_values_are_named_with_their_sign_and_place(tmp_path, value, word):
    a = np.ones((10, 20, 20), np.float32)
    a[3, 4, 5] = value
    with pytest.raises(InvalidInputError) as info:
        write_volume(a, tmp_path / "v.zarr")
    msg = str(info.value)
    assert word in msg and "(3, 4, 5)" in msg and "nan_value" in msg and "unwind convert" in msg
    if word != "NaN":
        assert "NaN" not in msg
    # nan_value replaces every non-finite value
    v = open_volume(write_volume(a, tmp_path / "w.zarr", nan_value=-1))
    expect = a.copy()
    expect[3, 4, 5] = -1
    np.testing.assert_array_equal(v.data.compute(), expect)


# ------------------------------------------------------------------------------------------------------------------
# 6. the geometry of every pyramid level
# ------------------------------------------------------------------------------------------------------------------
def _ngff_geometry(store):
    """(scale, origin) of every dataset, straight from the NGFF JSON (transforms applied in order)."""
    ms = json.loads((store / "zarr.json").read_text())["attributes"]["ome"]["multiscales"][0]

    def apply(transforms, scale, offset):
        for t in transforms or []:
            if t["type"] == "scale":
                scale = [s * f for s, f in zip(scale, t["scale"])]
                offset = [o * f for o, f in zip(offset, t["scale"])]
            elif t["type"] == "translation":
                offset = [o + d for o, d in zip(offset, t["translation"])]
        return scale, offset

    out = []
    for ds in ms["datasets"]:
        scale, offset = apply(ds["coordinateTransformations"], [1.0] * 3, [0.0] * 3)
        scale, offset = apply(ms.get("coordinateTransformations"), scale, offset)
        out.append((tuple(scale), tuple(offset)))
    return out


def _foreign_pyramid(path, global_transforms=None):
    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    a = _ramp((20, 16, 12))
    root.create_array("0", shape=a.shape, dtype=a.dtype, chunks=(8, 8, 8))[...] = a
    root.create_array("1", shape=(10, 8, 6), dtype=a.dtype, chunks=(8, 8, 8))[...] = a[::2, ::2, ::2]
    ms = {"axes": [{"name": n, "type": "space", "unit": "micrometer"} for n in "zyx"],
          "datasets": [
              {"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [1.0, 0.5, 0.5]},
                                                          {"type": "translation", "translation": [10, 20, 30]}]},
              {"path": "1", "coordinateTransformations": [{"type": "scale", "scale": [2.0, 1.0, 1.0]},
                                                          {"type": "translation",
                                                           "translation": [10.5, 20.5, 30.5]}]}]}
    if global_transforms:
        ms["coordinateTransformations"] = global_transforms
    root.attrs["ome"] = {"version": "0.5", "multiscales": [ms]}
    return path


@pytest.mark.parametrize("global_transforms", [None, [{"type": "scale", "scale": [2.0, 3.0, 4.0]},
                                                      {"type": "translation", "translation": [-1.0, 5.0, 0.25]}]])
def test_every_level_has_the_origin_and_spacing_the_file_declares(tmp_path, global_transforms):
    store = _foreign_pyramid(tmp_path / "f.zarr", global_transforms)
    expect = _ngff_geometry(store)
    whole = open_volume(store)
    for k, (scale, origin) in enumerate(expect):
        v = open_volume(store, level=k)
        assert v.spacing == pytest.approx(scale) and v.origin == pytest.approx(origin), k
        assert whole.level_spacings[k] == pytest.approx(scale) and whole.level_origins[k] == pytest.approx(origin)
        lv = whole.level(k)
        assert lv.spacing == pytest.approx(scale) and lv.origin == pytest.approx(origin)
        assert whole.with_data(whole.levels[k]).origin == pytest.approx(origin)


def test_our_pyramid_translations_match_the_box_averaging(tmp_path):
    """Level k of a linear ramp holds the ramp's value at the centre of each averaged block: that centre is
    where the written NGFF metadata (scale, translation) puts the voxel."""
    shape, spacing, origin = (48, 40, 36), (2.0, 0.5, 0.25), (1.0, -3.0, 7.0)
    grad = np.array([0.7, -1.3, 2.1])  # value per unit length along each axis
    idx = np.indices(shape, dtype=np.float64)
    pos = [origin[a] + idx[a] * spacing[a] for a in range(3)]
    ramp = (grad[0] * pos[0] + grad[1] * pos[1] + grad[2] * pos[2]).astype(np.float32)
    store = write_volume(ramp, tmp_path / "r.zarr", spacing=spacing, origin=origin, chunks=16, max_side=8)
    geometry = _ngff_geometry(store)
    assert len(geometry) >= 3
    assert json.loads((store / "zarr.json").read_text())["attributes"]["ome"]["multiscales"][0]["name"] == "r.zarr"
    for k, (scale, trans) in enumerate(geometry):
        factor = np.array(scale) / np.array(spacing)
        # the pixel-centre convention, computed independently of the writer
        assert trans == pytest.approx(tuple(o + (f - 1) / 2 * s for o, f, s in zip(origin, factor, spacing)))
        level = zarr.open_array(str(store / str(k)), mode="r")[...]
        n = [s - 1 for s in level.shape]  # leave out the last voxel (edge padded for odd sizes)
        i = np.indices(n, dtype=np.float64)
        centre = sum(grad[a] * (trans[a] + i[a] * scale[a]) for a in range(3))
        np.testing.assert_allclose(level[: n[0], : n[1], : n[2]], centre, atol=1e-3 * np.abs(centre).max())
        v = open_volume(store, level=k)
        assert v.origin == pytest.approx(trans) and v.spacing == pytest.approx(scale)


# ------------------------------------------------------------------------------------------------------------------
# 7. ImageJ geometry as Fiji writes it (no JSON of ours)
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("unit, ngff", [("micron", "micrometer"), ("\\u00B5m", "micrometer"), ("mm", "millimeter")])
@pytest.mark.parametrize("xyz_origin", [(5.0, 12.0, 3.0), (-2.5, 0.0, 40.0)])
def test_imagej_origin_as_fiji_stores_it(tmp_path, unit, ngff, xyz_origin):
    """Fiji's Calibration: xorigin is in pixels, and pixel 0 lies at -xorigin * pixelWidth."""
    sx, sy, sz = 0.25, 0.5, 3.0
    xo, yo, zo = xyz_origin
    a = _ramp((5, 6, 7), "uint16")
    tifffile.imwrite(tmp_path / "fiji.tif", a, imagej=True, resolution=(1 / sx, 1 / sy),
                     metadata={"spacing": sz, "unit": unit, "axes": "ZYX", "xorigin": xo, "yorigin": yo,
                               "zorigin": zo, "loop": False, "min": 0.0, "max": 255.0})
    with tifffile.TiffFile(tmp_path / "fiji.tif") as tif:
        assert "unwind" not in tif.imagej_metadata  # nothing of ours in the file
    v = open_volume(tmp_path / "fiji.tif")
    assert v.unit == ngff and v.metadata["geometry_from"] == "imagej"
    assert v.spacing == pytest.approx((sz, sy, sx))
    assert v.origin == pytest.approx((-zo * sz, -yo * sy, -xo * sx))
    np.testing.assert_array_equal(v.data.compute(), a)


def test_imagej_origin_round_trips_through_fiji_tags_alone(tmp_path):
    """Our writer's ImageJ tags (without the JSON) give back the origin: Fiji sees what we meant."""
    a = _ramp((5, 6, 7), "uint16")
    write_volume(a, tmp_path / "ours.tif", spacing=(3.0, 0.5, 0.25), unit="um", origin=(6.0, -1.0, 2.5))
    with tifffile.TiffFile(tmp_path / "ours.tif") as tif:
        meta = dict(tif.imagej_metadata)
        res = (tif.pages.first.tags["XResolution"].value, tif.pages.first.tags["YResolution"].value)
    meta.pop("unwind")
    sx, sy = (d / n for n, d in res)
    tifffile.imwrite(tmp_path / "fiji.tif", a, imagej=True, resolution=(1 / sx, 1 / sy),
                     metadata={"axes": "ZYX", **{k: v for k, v in meta.items()
                                                 if k not in ("ImageJ", "images", "slices", "hyperstack")}})
    v = open_volume(tmp_path / "fiji.tif")
    assert v.metadata["geometry_from"] == "imagej"
    assert v.origin == pytest.approx((6.0, -1.0, 2.5)) and v.spacing == pytest.approx((3.0, 0.5, 0.25))


# ------------------------------------------------------------------------------------------------------------------
# every format we read, truncated and corrupted
# ------------------------------------------------------------------------------------------------------------------
# name -> (target, write options, 8-bit data, files to damage, files whose voxels are stored without a checksum:
# flipped bytes there can only change values)
FORMATS_READ = {
    "zarr": ("v.zarr", {"chunks": 8, "max_side": 8}, False,
             ["v.zarr/zarr.json", "v.zarr/0/zarr.json", "v.zarr/0/c/0/0/0", "v.zarr/1/zarr.json",
              "v.zarr/1/c/0/0/0"], []),
    "tiff-imagej": ("v.tif", {}, False, ["v.tif"], ["v.tif"]),
    "tiff-plain": ("v.tif", {"imagej": False}, False, ["v.tif"], ["v.tif"]),
    "tiff-zlib": ("v.tif", {"compression": "zlib"}, False, ["v.tif"], []),
    "nrrd-gzip": ("v.nrrd", {}, False, ["v.nrrd"], []),
    "nrrd-bzip2": ("v.nrrd", {"encoding": "bzip2"}, False, ["v.nrrd"], []),
    "nrrd-raw": ("v.nrrd", {"encoding": "raw"}, False, ["v.nrrd"], ["v.nrrd"]),
    "nhdr": ("v.nhdr", {}, False, ["v.nhdr", "v.raw.gz"], []),
    "nii": ("v.nii", {}, False, ["v.nii"], ["v.nii"]),
    "nii.gz": ("v.nii.gz", {}, False, ["v.nii.gz"], []),
    "raw": ("v.dat", {}, False, ["v.dat", "v.raw"], ["v.raw"]),
    "dicom": ("v.dicom", {}, False, ["v.dicom/IM00001.dcm", "v.dicom/IM00003.dcm"],
              ["v.dicom/IM00001.dcm", "v.dicom/IM00003.dcm"]),
    "png": ("s/v_{:03d}.png", {}, False, ["s/v_002.png"], []),
    "bmp": ("s/v_{:03d}.bmp", {}, True, ["s/v_002.bmp"], ["s/v_002.bmp"]),
    "jpg": ("s/v_{:03d}.jpg", {}, True, ["s/v_002.jpg"], ["s/v_002.jpg"]),
    "tiff-slices": ("s/v_{:03d}.tif", {}, False, ["s/v_002.tif"], ["s/v_002.tif"]),
}
DAMAGE = ["half", "ten-bytes", "empty", "flipped", "garbage-header"]
HOSTILE_CASES = [(fmt, f, how) for fmt, spec in FORMATS_READ.items() for f in spec[3] for how in DAMAGE]


def _damage(path, how):
    b = path.read_bytes()
    if how == "half":
        b = b[: len(b) // 2]
    elif how == "ten-bytes":
        b = b[:10]
    elif how == "empty":
        b = b""
    elif how == "flipped":
        m = len(b) // 2
        b = b[:m] + bytes(x ^ 0xFF for x in b[m:m + 16]) + b[m + 16:]
    else:  # the first 64 bytes replaced
        b = (b"\x07GARBAGE\xff\x00" * 8)[: min(64, len(b))] + b[64:]
    path.write_bytes(b)


def _digests(folder):
    import hashlib

    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def _read_all(entry):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        v = open_volume(entry)
        return [np.asarray(level.compute()) for level in v.levels]


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    """One intact file (set) per format, and what it reads as."""
    root = tmp_path_factory.mktemp("pristine")
    out = {}
    for fmt, (target, options, eight_bit, *_) in FORMATS_READ.items():
        a = _ramp((6, 20, 24), "uint8" if eight_bit else "uint16", seed=3)
        folder = root / fmt
        folder.mkdir()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # JPEG is lossy
            written = write_volume(a, folder / target, spacing=(2, 1, 1), unit="um", **options)
        entry = written if not target.startswith("s/") else folder / "s"
        out[fmt] = (folder, entry.relative_to(folder), _read_all(entry))
        assert all(level.size for level in out[fmt][2])
    return out


@pytest.mark.parametrize("fmt, victim, how", HOSTILE_CASES, ids=[f"{f}-{v}-{h}" for f, v, h in HOSTILE_CASES])
def test_damaged_files_read_correctly_or_fail_with_one_line_naming_them(tmp_path, pristine, fmt, victim, how):
    import shutil

    folder, entry, intact = pristine[fmt]
    case = tmp_path / fmt
    shutil.copytree(folder, case)
    damaged = case / victim
    _damage(damaged, how)
    before = _digests(case)
    try:
        levels = _read_all(case / entry)
    except (InvalidInputError, UnknownFormatError) as exc:
        msg = str(exc)
        assert "\n" not in msg and "Traceback" not in msg, msg
        assert str(damaged) in msg or str(case / entry) in msg or f"{damaged.name} " in msg, msg
    else:
        same = len(levels) == len(intact) and all(np.array_equal(x, y) for x, y in zip(levels, intact))
        unchecked = how in ("flipped", "garbage-header") and victim in FORMATS_READ[fmt][4]
        assert same or unchecked, f"{fmt}: {victim} {how} read without error but gives other voxels"
        if not same:  # bytes of voxels stored without a checksum: only values can change, never the shape
            assert [x.shape for x in levels] == [y.shape for y in intact]
    assert _digests(case) == before, "reading changed the input"
    assert no_leftovers(tmp_path) == []


def test_the_hostile_matrix_covers_every_readable_format(pristine):
    from napari_unwind.io import FORMATS

    assert {open_volume(folder / entry).format for folder, entry, _ in pristine.values()} == set(FORMATS)


@pytest.mark.parametrize("target", RELATIVE_TARGETS)
def test_readers_called_directly_make_relative_paths_absolute(tmp_path, monkeypatch, target):
    """The graph holds absolute paths whichever reader builds it, so a worker in another folder finds the file."""
    from napari_unwind.io._formats import detect_format, reader_for

    a = _ramp((5, 6, 7), "uint16")
    written = write_volume(a, tmp_path / target, unit="mm")
    written = written if "{" not in target else written.parent if written.suffix else written
    monkeypatch.chdir(tmp_path)
    relative = os.path.relpath(written, tmp_path)
    v = reader_for(detect_format(relative))(__import__("pathlib").Path(relative))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # as a worker started in another folder would be
    np.testing.assert_array_equal(v.data.compute(scheduler="synchronous"), a)


@pytest.fixture(scope="module")
def mixed_inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("mixed")
    a = _ramp((4, 6, 5), "uint16")
    entries = [write_volume(a, root / name) for name in ("v.zarr", "v.tif", "v.nrrd", "v.nii", "v.dat", "v.dicom")]
    (root / "notes.txt").write_text("not a scan\n" * 20)
    (root / "empty").mkdir()
    return a, entries + [root / "notes.txt", root / "empty"]


@pytest.mark.parametrize("fmt", ["ome-zarr", "tiff", "stack", "dicom", "nrrd", "nifti", "raw"])
def test_a_forced_format_on_the_wrong_input_is_one_line(mixed_inputs, fmt):
    """Every reader on every kind of input (``--input-format``): the data, or one line naming the input."""
    a, entries = mixed_inputs
    for entry in entries:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                got = open_volume(entry, format=fmt).data.compute()
        except (InvalidInputError, UnknownFormatError) as exc:
            msg = str(exc)
            assert "\n" not in msg and str(entry) in msg, (fmt, entry, msg)
        else:
            np.testing.assert_array_equal(got, a, err_msg=f"{fmt} {entry}")
