"""The header-only fast path of ``unwind info`` (napari_unwind.io._headers, issue 18).

- agreement: for many scans (the project's own writers; NRRD headers written by hand and NIfTI headers by nibabel;
  OME-Zarr v3 and v2 metadata), all drawn from seeds, the fast path's report equals the full reader's byte for byte;
- anomalies: the fast path returns None (the full reader opens the scan, and reports, warns or refuses);
- ``unwind info`` on NRRD, NIfTI and OME-Zarr imports neither numpy nor zarr, dask or the format libraries.
"""

from __future__ import annotations

import ast
import gzip
import json
import math
import random
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from napari_unwind._report import describe
from napari_unwind.cli import main
from napari_unwind.io import open_volume, write_volume
from napari_unwind.io._headers import read_header

DTYPES = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")
UNITS = (None, "mm", "um", "m", "cm", "nm")


def _full(path: Path) -> str:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return describe(open_volume(path), path)


def _agree(path: Path) -> bool:
    """The fast path's report equals the full reader's; True when the fast path answered (not deferred)."""
    header = read_header(path)
    if header is None:
        return False
    assert describe(header, path) == _full(path)
    return True


def _spacing(rng: random.Random) -> tuple[float, float, float]:
    pick = (lambda: rng.choice([1.0, 0.5, 0.1, 0.3, 1.5, 2.0, 0.001, 1e-6, 123.456, 7.0])) if rng.random() < 0.5 \
        else (lambda: rng.uniform(1e-3, 10.0))
    return pick(), pick(), pick()


def _shape(rng: random.Random) -> tuple[int, int, int]:
    return tuple(rng.randint(1, 13) for _ in range(3))


def _voxels(rng: random.Random, shape, dtype: str) -> np.ndarray:
    return np.random.default_rng(rng.randrange(2**31)).integers(0, 100, size=shape).astype(dtype)


# ------------------------------------------------------------------------------------------------------------------
# agreement
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(24))
def test_agrees_with_the_full_reader_on_the_projects_writers(tmp_path, seed):
    rng = random.Random(seed)
    shape = _shape(rng)
    dtype = DTYPES[seed % len(DTYPES)]
    voxels = _voxels(rng, shape, dtype)
    spacing, unit = _spacing(rng), UNITS[seed % len(UNITS)]
    origin = tuple(rng.choice([0.0, rng.uniform(-500, 500)]) for _ in range(3))
    answered = []
    for name, options in (("a.nrrd", {"encoding": "gzip"}), ("b.nrrd", {"encoding": "raw"}), ("c.nii", {}),
                          ("d.nii.gz", {}), ("e.zarr", {"chunks": tuple(rng.randint(1, 8) for _ in range(3)),
                                                        "max_side": rng.choice([1, 2, 4, 16])})):
        path = write_volume(voxels, tmp_path / name, spacing=spacing, unit=unit, origin=origin, **options)
        answered.append(_agree(path))
    assert all(answered), answered  # every scan these writers make takes the fast path


def _nrrd_header(rng: random.Random, shape, dtype: str, encoding: str) -> tuple[list[str], str]:
    """NRRD header lines as pynrrd, 3D Slicer or ITK write them, drawn from ``rng``; and the file's byte order."""
    spellings = {"uint8": ["uchar", "unsigned char", "uint8", "uint8_t"], "int8": ["signed char", "int8", "int8_t"],
                 "uint16": ["ushort", "unsigned short", "uint16"], "int16": ["short", "int16", "signed short int"],
                 "uint32": ["uint", "unsigned int", "uint32"], "int32": ["int", "int32", "signed int"],
                 "float32": ["float"], "float64": ["double"]}
    endian = rng.choice(["little", "big"])
    lines = [f"NRRD000{rng.randint(4, 5)}", "# written by a test"]
    lines += [f"type: {rng.choice(spellings[dtype])}", "dimension: 3"]
    space = rng.choice([None, "left-posterior-superior", "RAS", "3D-right-handed", "scanner-xyz"])
    if space:
        lines.append(f"space: {space}")
    lines.append(f"sizes: {shape[2]} {shape[1]} {shape[0]}")
    geometry = rng.choice(["diagonal", "oblique", "spacings", "none"])
    if geometry == "diagonal":
        s = _spacing(rng)
        lines.append(f"space directions: ({s[0]!r},0,0) (0,{s[1]!r},0) (0,0,{s[2]!r})")
    elif geometry == "oblique":
        a, b = rng.uniform(0, math.pi), rng.uniform(0, math.pi)
        rot = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]) @ \
            np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
        s = _spacing(rng)
        lines.append("space directions: " + " ".join(
            "(" + ",".join(repr(float(v)) for v in rot[:, i] * s[i]) + ")" for i in range(3)))
    elif geometry == "spacings":
        s = _spacing(rng)
        lines.append(f"spacings: {s[0]!r} {s[1]!r} {s[2]!r}")
    if rng.random() < 0.7:
        lines.append("kinds: " + " ".join(rng.choice(["domain", "space"]) for _ in range(3)))
    if np.dtype(dtype).itemsize > 1 or rng.random() < 0.5:
        lines.append(f"endian: {endian}")
    lines.append(f"encoding: {encoding}")
    if geometry != "none" and rng.random() < 0.6:
        u = rng.choice(["mm", "um", "micron", "m", "cm", "nm", "millimeter", "micrometer", "MM"])
        lines.append(f'space units: "{u}" "{u}" "{u}"')
    if rng.random() < 0.6 and geometry in ("diagonal", "oblique"):
        lines.append("space origin: (" + ",".join(repr(rng.uniform(-300, 300)) for _ in range(3)) + ")")
    if rng.random() < 0.3:
        lines.append("content: a test scan")
    if rng.random() < 0.3:
        lines.append("centerings: cell cell cell")
    if rng.random() < 0.3:
        lines.append("my key:=my value")
    if rng.random() < 0.2:
        lines.append("measurement frame: (1,0,0) (0,1,0) (0,0,1)")
    return lines, endian


def _write_nrrd(path: Path, lines: list[str], voxels: np.ndarray, endian: str, encoding: str,
                newline: str = "\n") -> Path:
    data = np.ascontiguousarray(voxels, dtype=voxels.dtype.newbyteorder("<" if endian == "little" else ">"))
    payload = data.tobytes()
    if encoding in ("gzip", "gz"):
        payload = gzip.compress(payload, mtime=0)
    path.write_bytes((newline.join(lines) + newline + newline).encode("ascii") + payload)
    return path


@pytest.mark.parametrize("seed", range(48))
def test_agrees_with_the_full_reader_on_nrrd_headers(tmp_path, seed):
    rng = random.Random(1000 + seed)
    shape, dtype = _shape(rng), rng.choice(DTYPES)
    encoding = rng.choice(["raw", "gzip", "gz"])
    lines, endian = _nrrd_header(rng, shape, dtype, encoding)
    path = _write_nrrd(tmp_path / "x.nrrd", lines, _voxels(rng, shape, dtype), endian, encoding,
                       newline=rng.choice(["\n", "\n", "\r\n"]))
    assert _agree(path), lines


def _nifti(rng: random.Random, shape, dtype: str, version: int):
    import nibabel as nib

    affine = np.eye(4)
    affine[:3, :3] = np.diag(_spacing(rng))
    affine[:3, 3] = [rng.uniform(-200, 200) for _ in range(3)]
    data = _voxels(rng, shape[::-1], dtype)
    if rng.random() < 0.3:
        data = data[..., None]  # a fourth axis of length 1
    cls = nib.Nifti1Image if version == 1 else nib.Nifti2Image
    img = cls(data, affine)
    img.header.set_xyzt_units(xyz=rng.choice(["unknown", "meter", "mm", "micron"]), t="sec")
    img.header.set_qform(affine, code=rng.choice([0, 1, 2]))
    img.header.set_sform(affine, code=rng.choice([1, 2, 3, 4]))
    if rng.random() < 0.5:
        img.header.set_slope_inter(rng.choice([1.0, 2.0, 0.5, -1.0]), rng.choice([0.0, -1024.0, 3.5]))
    return img


@pytest.mark.parametrize("seed", range(24))
def test_agrees_with_the_full_reader_on_nifti_headers(tmp_path, seed):
    import nibabel as nib

    rng = random.Random(2000 + seed)
    img = _nifti(rng, _shape(rng), rng.choice(DTYPES), version=1 + seed % 2)
    path = tmp_path / rng.choice(["x.nii", "x.nii.gz"])
    nib.save(img, str(path))
    assert _agree(path)


def _zarr_meta(rng: random.Random, folder: Path, v3: bool) -> Path:
    """An OME-Zarr's metadata alone (no chunks: ``unwind info`` reads none), drawn from ``rng``."""
    folder.mkdir()
    dtype = rng.choice(DTYPES)
    shape = list(_shape(rng))
    extra = rng.random() < 0.4  # a leading channel axis of length 1
    axes = ([{"name": "c", "type": "channel"}] if extra else []) + [
        {"name": n, "type": "space", **({"unit": u} if u else {})}
        for n, u in zip("zyx", [rng.choice([None, "micrometer", "millimeter", "nanometer"])] * 3, strict=True)]
    datasets = []
    scale = list(_spacing(rng))
    for i in range(rng.randint(1, 4)):
        transforms = [{"type": "scale", "scale": ([1.0] if extra else []) + scale}]
        if rng.random() < 0.6:
            transforms.append({"type": "translation",
                               "translation": ([0.0] if extra else []) + [rng.uniform(-5, 5) for _ in range(3)]})
        datasets.append({"path": f"s{i}", "coordinateTransformations": transforms})
        full = ([1] if extra else []) + shape
        chunks = ([1] if extra else []) + [rng.randint(1, 16) for _ in range(3)]
        level = folder / f"s{i}"
        level.mkdir()
        if v3:
            meta = {"zarr_format": 3, "node_type": "array", "shape": full, "data_type": dtype,
                    "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": chunks}},
                    "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
                    "fill_value": 0, "codecs": [{"name": "bytes", "configuration": {"endian": "little"}},
                                                {"name": "zstd", "configuration": {"level": 3, "checksum": False}}],
                    "attributes": {}}
            (level / "zarr.json").write_text(json.dumps(meta))
        else:
            meta = {"zarr_format": 2, "shape": full, "chunks": chunks, "dtype": np.dtype(dtype).str,
                    "compressor": {"id": "zlib", "level": 1}, "fill_value": 0, "order": "C", "filters": None}
            (level / ".zarray").write_text(json.dumps(meta))
        shape = [(n + 1) // 2 for n in shape]
        scale = [s * 2 for s in scale]
    ms = {"version": "0.5" if v3 else "0.4", "axes": axes, "datasets": datasets}
    if rng.random() < 0.4:
        ms["coordinateTransformations"] = [{"type": "scale", "scale": ([1.0] if extra else []) + list(_spacing(rng))}]
    if v3:
        (folder / "zarr.json").write_text(json.dumps({"zarr_format": 3, "node_type": "group",
                                                      "attributes": {"ome": {"version": "0.5",
                                                                             "multiscales": [ms]}}}))
    else:
        (folder / ".zgroup").write_text(json.dumps({"zarr_format": 2}))
        (folder / ".zattrs").write_text(json.dumps({"multiscales": [ms]}))
    return folder


@pytest.mark.parametrize("seed", range(16))
def test_agrees_with_the_full_reader_on_ome_zarr_metadata(tmp_path, seed):
    rng = random.Random(3000 + seed)
    path = _zarr_meta(rng, tmp_path / "x.zarr", v3=seed % 2 == 0)
    assert _agree(path)


@pytest.mark.parametrize("dtype", ["uint8", "int16", "float64"])
def test_agrees_on_the_chunks_of_large_scans(tmp_path, dtype):
    """Planes of tens of MiB: the slab depth of the dask chunks (64 MiB for NRRD and .nii, 512 MiB for .nii.gz)
    shows. The voxels are sparse files (NRRD raw, .nii) or absent (.nii.gz: read lazily)."""
    import nibabel as nib

    itemsize = np.dtype(dtype).itemsize
    shape = (40, 2048, 1536 * 2 // itemsize)  # planes of 3-6 MiB per byte of voxel type
    nbytes = math.prod(shape) * itemsize
    nrrd = tmp_path / "big.nrrd"
    lines = ["NRRD0005", f"type: {dtype.replace('float64', 'double')}", "dimension: 3",
             f"sizes: {shape[2]} {shape[1]} {shape[0]}", "endian: little", "encoding: raw"]
    nrrd.write_bytes(("\n".join(lines) + "\n\n").encode())
    with open(nrrd, "r+b") as fh:
        fh.truncate(nrrd.stat().st_size + nbytes)
    header = nib.Nifti1Header()
    header.set_data_shape(shape[::-1])
    header.set_data_dtype(dtype)
    header.set_sform(np.diag([0.5, 0.25, 2.0, 1.0]), code=1)
    header["vox_offset"] = 352
    block = header.binaryblock + b"\0" * 4
    nii = tmp_path / "big.nii"
    nii.write_bytes(block)
    with open(nii, "r+b") as fh:
        fh.truncate(352 + nbytes)
    niigz = tmp_path / "big.nii.gz"
    niigz.write_bytes(gzip.compress(block))
    for path in (nrrd, nii, niigz):
        assert _agree(path), path


def test_cli_prints_the_fast_paths_report(tmp_path, capsys):
    path = write_volume(np.zeros((3, 4, 5), np.int16), tmp_path / "a.nrrd", spacing=(0.5, 1, 2), unit="mm")
    assert main(["info", str(path)]) == 0
    assert capsys.readouterr().out == _full(path) + "\n"
    assert main(["info", str(path), "--input-format", "nrrd"]) == 0
    assert capsys.readouterr().out == _full(path) + "\n"


# ------------------------------------------------------------------------------------------------------------------
# anomalies: the full reader decides
# ------------------------------------------------------------------------------------------------------------------
GOOD = ["NRRD0005", "type: int16", "dimension: 3", "sizes: 5 4 3", "space directions: (2,0,0) (0,1,0) (0,0,0.5)",
        "kinds: domain domain domain", "endian: little", "encoding: raw", 'space units: "mm" "mm" "mm"',
        "space origin: (1,2,3)"]


def _edit(lines: list[str], field: str, value: str | None) -> list[str]:
    out = [ln for ln in lines if not ln.startswith(field + ":")]
    return out + ([f"{field}: {value}"] if value is not None else [])


NRRD_ANOMALIES = {
    "unknown field": _edit(GOOD, "my field", "1"),
    "duplicate field": GOOD + ["type: int16"],
    "bzip2": _edit(GOOD, "encoding", "bzip2"),
    "ascii": _edit(GOOD, "encoding", "ascii"),
    "detached data file": _edit(GOOD, "data file", "other.raw"),
    "byte skip": _edit(GOOD, "byte skip", "4"),
    "line skip": _edit(GOOD, "line skip", "1"),
    "zero spacing": _edit(GOOD, "space directions", "(0,0,0) (0,1,0) (0,0,0.5)"),
    "nan spacing": _edit(_edit(GOOD, "space directions", None), "spacings", "nan 1 1"),
    "negative spacing": _edit(_edit(GOOD, "space directions", None), "spacings", "-2 1 1"),
    "none direction": _edit(GOOD, "space directions", "none (0,1,0) (0,0,0.5)"),
    "nan origin": _edit(GOOD, "space origin", "(nan,2,3)"),
    "zero size": _edit(GOOD, "sizes", "5 0 3"),
    "fractional size": _edit(GOOD, "sizes", "5 4.5 3"),
    "four dimensions": _edit(_edit(GOOD, "dimension", "4"), "sizes", "1 5 4 3"),
    "list kind": _edit(GOOD, "kinds", "list domain domain"),
    "mixed units": _edit(GOOD, "space units", '"mm" "um" "mm"'),
    "unknown unit": _edit(GOOD, "space units", '"furlong" "furlong" "furlong"'),
    "per-axis units": GOOD + ['units: "mm" "mm" "mm"'],
    "no endian": _edit(GOOD, "endian", None),
    "64-bit type": _edit(GOOD, "type", "int64"),
    "block type": _edit(GOOD, "type", "block"),
    "key/value pair over a field": GOOD + ["sizes:=1 2 3"],
    "no colon": GOOD + ["what is this"],
    "newer magic": ["NRRD0006"] + GOOD[1:],
}


@pytest.mark.parametrize("case", sorted(NRRD_ANOMALIES))
def test_defers_on_nrrd_anomalies(tmp_path, case):
    path = tmp_path / "x.nrrd"
    path.write_bytes(("\n".join(NRRD_ANOMALIES[case]) + "\n\n").encode() + bytes(5 * 4 * 3 * 2))
    assert read_header(path) is None


def test_defers_on_non_ascii_headers_and_truncated_data(tmp_path):
    good = ("\n".join(GOOD) + "\n\n").encode()
    voxels = bytes(5 * 4 * 3 * 2)
    cases = {
        "fine.nrrd": good + voxels,
        "non-ascii.nrrd": good.replace(b"# ", b"# \xb5") .replace(b"type:", b"# caf\xc3\xa9\ntype:") + voxels,
        "truncated raw.nrrd": good + voxels[:-1],
        "no blank line.nrrd": good[:-1],
        "truncated gzip.nrrd": good.replace(b"raw", b"gzip") + gzip.compress(voxels)[:-3],
        "gzip of other length.nrrd": good.replace(b"raw", b"gzip") + gzip.compress(voxels + b"\0\0"),
        "not gzip.nrrd": good.replace(b"raw", b"gzip") + voxels,
    }
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
    assert read_header(tmp_path / "fine.nrrd") is not None
    for name in cases:
        if name != "fine.nrrd":
            assert read_header(tmp_path / name) is None, name


def test_defers_on_other_formats_options_and_detached_headers(tmp_path):
    voxels = np.zeros((3, 4, 5), np.uint8)
    for name in ("a.tif", "a.dat", "a.nhdr"):
        assert read_header(write_volume(voxels, tmp_path / name)) is None
    nrrd = write_volume(voxels, tmp_path / "a.nrrd")
    assert read_header(nrrd, format="tiff") is None
    assert read_header(nrrd, series=0) is None
    assert read_header(tmp_path / "missing.nrrd") is None


def _nifti_bytes(mutate) -> bytes:
    import nibabel as nib

    img = nib.Nifti1Image(np.zeros((5, 4, 3), np.int16), np.diag([0.5, 1.0, 2.0, 1.0]))
    img.header.set_sform(img.affine, code=1)
    img.header.set_xyzt_units(xyz="mm")
    img.header["vox_offset"] = 352
    raw = bytearray(img.header.binaryblock + b"\0" * 4 + bytes(5 * 4 * 3 * 2))
    mutate(raw)
    return bytes(raw)


def _put(fmt: str, offset: int, *values):
    import struct

    return lambda raw: struct.pack_into("<" + fmt, raw, offset, *values)


NIFTI_ANOMALIES = {
    "negative pixdim": _put("f", 80, -0.5),
    "zero pixdim": _put("f", 84, 0.0),
    "nan pixdim": _put("f", 88, math.nan),
    "no sform": _put("h", 254, 0),
    "unknown sform code": _put("h", 254, 9),
    "nan origin": _put("f", 292, math.nan),
    "wrong bitpix": _put("h", 72, 8),
    "64-bit voxels": lambda raw: (_put("h", 70, 1024)(raw), _put("h", 72, 64)(raw)),
    "five real dimensions": lambda raw: (_put("h", 40, 4)(raw), _put("h", 48, 2)(raw)),
    "zero dimension": _put("h", 42, 0),
    "low vox_offset": _put("f", 108, 0.0),
    "unknown unit code": _put("B", 123, 5),
    "bad magic": lambda raw: raw.__setitem__(slice(344, 348), b"ni1\0"),
    "truncated": lambda raw: raw.__delitem__(slice(len(raw) - 1, None)),
}


@pytest.mark.parametrize("case", sorted(NIFTI_ANOMALIES))
def test_defers_on_nifti_anomalies(tmp_path, case):
    fine = tmp_path / "fine.nii"
    fine.write_bytes(_nifti_bytes(lambda raw: None))
    assert read_header(fine) is not None
    path = tmp_path / "x.nii"
    path.write_bytes(_nifti_bytes(NIFTI_ANOMALIES[case]))
    assert read_header(path) is None


def _zarr_edit(folder: Path, name: str, edit) -> None:
    meta = json.loads((folder / name).read_text())
    edit(meta)
    (folder / name).write_text(json.dumps(meta))


def _ms(meta):
    return meta["attributes"]["ome"]["multiscales"][0]


ZARR_ANOMALIES = {
    "sharded": ("s0/zarr.json", lambda m: m.__setitem__("codecs", [{"name": "sharding_indexed"}])),
    "unknown codec": ("s0/zarr.json", lambda m: m["codecs"].append({"name": "mystery"})),
    "unknown array key": ("s0/zarr.json", lambda m: m.__setitem__("extra", 1)),
    "64-bit voxels": ("s0/zarr.json", lambda m: m.__setitem__("data_type", "int64")),
    "zero size": ("s0/zarr.json", lambda m: m.__setitem__("shape", [0, 2, 2])),
    "irregular chunks": ("s0/zarr.json", lambda m: m["chunk_grid"].__setitem__("name", "rectilinear")),
    "missing level": ("zarr.json", lambda m: _ms(m)["datasets"].append({"path": "nowhere"})),
    "zero scale": ("zarr.json", lambda m: _ms(m)["datasets"][0].__setitem__(
        "coordinateTransformations", [{"type": "scale", "scale": [0.0, 1.0, 1.0]}])),
    "string scale": ("zarr.json", lambda m: _ms(m)["datasets"][0].__setitem__(
        "coordinateTransformations", [{"type": "scale", "scale": ["1", 1.0, 1.0]}])),
    "affine transform": ("zarr.json", lambda m: _ms(m)["datasets"][0].__setitem__(
        "coordinateTransformations", [{"type": "affine", "affine": [[1, 0, 0, 0]] * 3}])),
    "unknown unit": ("zarr.json", lambda m: [a.__setitem__("unit", "parsec") for a in _ms(m)["axes"]]),
    "two spatial axes": ("zarr.json", lambda m: _ms(m)["axes"][0].__setitem__("type", "time")),
    "no multiscales": ("zarr.json", lambda m: m["attributes"].pop("ome")),
    "parent path": ("zarr.json", lambda m: _ms(m)["datasets"][0].__setitem__("path", "../s0")),
}


@pytest.mark.parametrize("case", sorted(ZARR_ANOMALIES))
def test_defers_on_ome_zarr_anomalies(tmp_path, case):
    rng = random.Random(7)
    path = _zarr_meta(rng, tmp_path / "x.zarr", v3=True)
    _zarr_edit(path, "zarr.json", lambda m: _ms(m).__setitem__("axes", [a for a in _ms(m)["axes"]
                                                                        if a["type"] == "space"]))
    for ds in _ms(json.loads((path / "zarr.json").read_text()))["datasets"]:
        _zarr_edit(path, f"{ds['path']}/zarr.json", lambda m: (m.__setitem__("shape", m["shape"][-3:]),
                                                                 m["chunk_grid"]["configuration"].__setitem__(
                                                                     "chunk_shape", [2, 2, 2])))
        _zarr_edit(path, "zarr.json", lambda m: [d.__setitem__("coordinateTransformations", [
            {"type": "scale", "scale": [1.0, 1.0, 1.0]}]) for d in _ms(m)["datasets"]])
    assert read_header(path) is not None
    name, edit = ZARR_ANOMALIES[case]
    _zarr_edit(path, name, edit)
    assert read_header(path) is None


def test_the_full_reader_still_explains_bad_input(tmp_path, capsys):
    """Deferred, ``unwind info`` prints the full reader's one-line error."""
    path = tmp_path / "x.nrrd"
    path.write_bytes(("\n".join(GOOD) + "\n\n").encode() + bytes(7))
    assert main(["info", str(path)]) == 1
    assert "the raw data are truncated: expected 120 bytes of voxels" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------------------------
# start-up: no numpy
# ------------------------------------------------------------------------------------------------------------------
HEAVY = ("numpy", "zarr", "dask", "nrrd", "nibabel", "scipy")

WRAPPER = """
import sys
from napari_unwind.cli import main
status = main(sys.argv[1:])
print(sorted(m for m in {modules!r} if m in sys.modules))
sys.exit(status)
"""


@pytest.mark.parametrize("name", ["aorta.nrrd", "aorta.nii.gz", "aorta.nii", "aorta.zarr"])
def test_info_imports_no_numpy(tmp_path, name):
    path = write_volume(np.arange(60, dtype=np.int16).reshape(3, 4, 5), tmp_path / name, spacing=(1.5, 1, 1),
                        unit="mm")
    proc = subprocess.run([sys.executable, "-c", WRAPPER.format(modules=HEAVY), "info", str(path)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    *report, imported = proc.stdout.strip().splitlines()
    assert ast.literal_eval(imported) == []
    assert "\n".join(report) == _full(path)
