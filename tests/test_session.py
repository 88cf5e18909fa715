"""The session file: round trip, atomic save, corrupt files, schema versions, checksums, the scan behind it."""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

import napari_unwind
from conftest import no_leftovers
from napari_unwind import session as S
from napari_unwind.datasets import cylinder_phantom
from napari_unwind.deformation import Deformation
from napari_unwind.errors import InvalidInputError, OutputError
from napari_unwind.io import open_volume, write_volume
from napari_unwind.session import (
    SCHEMA_ID,
    SCHEMA_VERSION,
    Endpoints,
    Segmentation,
    Session,
    SourceChangedError,
    SourceInfo,
    SourceMissingError,
    checksum,
    checksum_iter,
    load_session,
    save_session,
    verify_source,
)


# ------------------------------------------------------------------------------------------------------------------
# helpers (independent references: hashlib over the documented layout, json from the standard library)
# ------------------------------------------------------------------------------------------------------------------
def sha256_file(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def manifest_digest(entries: dict[str, Path]) -> str:
    """``find . -type f | sort | xargs sha256sum | sha256sum``: the documented folder / file-set checksum."""
    text = "".join(f"{sha256_file(p)}  {rel}\n" for rel, p in sorted(entries.items()))
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def flip_byte(path: Path, offset: int = -1) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def phantom():
    return cylinder_phantom(shape=(24, 32, 72), radius=4.0, amplitude=6.0)


@pytest.fixture
def scan(tmp_path, phantom) -> Path:
    """The phantom as NRRD with a detached raw data file (fish.nhdr + fish.raw): voxels easy to flip."""
    folder = tmp_path / "scans"
    folder.mkdir()
    return write_volume(phantom.volume, folder / "fish.nhdr", spacing=phantom.spacing, unit="um", encoding="raw")


def make_session(scan: Path, phantom, **changes) -> Session:
    deformation = Deformation.from_polyline(phantom.centerline[::12], spacing=phantom.spacing,
                                            cage_half_extent=phantom.half_extent, unit=phantom.unit)
    fields = dict(
        source=SourceInfo.from_path(scan),
        deformation=deformation,
        segmentation=Segmentation(k=5, level=1, selected=[2, 4], seeds=[[12.0, 16.0, 20.5]], isovalue=812.5,
                                  fill_holes=True),
        endpoints=Endpoints(head=phantom.centerline[0], tail=phantom.centerline[-1],
                            chain=[(phantom.centerline[0], phantom.centerline[60]),
                                   (phantom.centerline[62], phantom.centerline[-1])]),
        notes="left pectoral fin torn; 3 µm scan",
    )
    fields.update(changes)
    return Session(**fields)


# ------------------------------------------------------------------------------------------------------------------
# round trip, timestamps, version
# ------------------------------------------------------------------------------------------------------------------
def test_round_trip_with_real_deformation(tmp_path, scan, phantom):
    session = make_session(scan, phantom)
    path = save_session(session, tmp_path / "fish.unwind.json")
    assert path == (tmp_path / "fish.unwind.json").absolute()
    loaded = load_session(path)
    assert loaded == session
    # the map itself survives exactly (JSON keeps every float's repr)
    rng = np.random.default_rng(0)
    xys = np.column_stack([rng.uniform(-5, 5, 50), rng.uniform(-5, 5, 50),
                           rng.uniform(0, session.deformation.length, 50)])
    np.testing.assert_array_equal(loaded.deformation.forward(xys), session.deformation.forward(xys))
    assert loaded.endpoints.chain[1][0] == tuple(phantom.centerline[62])
    # provenance of the scan, against independent references
    src = loaded.source
    assert src.path == str(scan) and Path(src.path).is_absolute()
    assert src.shape == phantom.volume.shape and src.dtype == phantom.volume.dtype.name == "uint16"
    assert src.spacing == phantom.spacing and src.unit == "micrometer" and src.format == "nrrd"
    raw = scan.with_suffix(".raw")
    assert src.size == scan.stat().st_size + raw.stat().st_size
    assert src.checksum == manifest_digest({"fish.nhdr": scan, "fish.raw": raw})
    # pretty, sorted JSON for readable diffs
    text = path.read_text(encoding="utf-8")
    data = json.loads(text)
    assert text == json.dumps(data, sort_keys=True, indent=2, ensure_ascii=False) + "\n"
    assert data["schema"] == SCHEMA_ID and data["schema_version"] == SCHEMA_VERSION
    assert "µm" in text  # UTF-8, not escaped


def test_optional_parts_round_trip(tmp_path, scan):
    session = Session(SourceInfo.from_path(scan))
    loaded = load_session(save_session(session, tmp_path / "bare.unwind.json"))
    assert loaded == session
    assert loaded.deformation is None and loaded.segmentation is None and loaded.endpoints is None


def test_timestamps_and_version(tmp_path, scan, phantom, monkeypatch):
    before = datetime.now(UTC).replace(microsecond=0)
    session = make_session(scan, phantom, software_version="0.0.1")
    created = datetime.fromisoformat(session.created)
    assert created.utcoffset().total_seconds() == 0 and session.created.endswith("Z")
    assert before <= created <= datetime.now(UTC)
    assert session.modified == session.created

    monkeypatch.setattr(S, "_utcnow", lambda: "2031-05-06T07:08:09.010Z")
    path = save_session(session, tmp_path / "t.unwind.json")
    data = json.loads(path.read_text())
    assert data["created"] == session.created  # kept
    assert data["modified"] == session.modified == "2031-05-06T07:08:09.010Z"  # set by the save
    assert data["software"] == {"name": "napari-unwind", "version": napari_unwind.__version__}
    assert session.software_version == napari_unwind.__version__
    # any time zone is stored as UTC
    other = Session(session.source, created="2025-03-01T12:00:00+02:00")
    assert other.created == "2025-03-01T10:00:00.000Z"


# ------------------------------------------------------------------------------------------------------------------
# saving
# ------------------------------------------------------------------------------------------------------------------
def test_failing_save_keeps_the_old_file(tmp_path, scan, phantom, monkeypatch):
    session = make_session(scan, phantom)
    path = save_session(session, tmp_path / "fish.unwind.json")
    old = path.read_bytes()
    modified = session.modified

    def disk_full(target: Path, text: str) -> None:
        target.write_text(text[: len(text) // 3])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(S, "_write_text", disk_full)
    session.notes = "edited"
    with pytest.raises(OutputError, match="No space left"):
        save_session(session, path)
    assert path.read_bytes() == old
    assert no_leftovers(tmp_path) == []
    assert session.modified == modified  # not saved, so not stamped


@pytest.mark.parametrize("name", ["fish.json", "fish.unwind", "fish", ".unwind.json", "fish.unwind.json.bak"])
def test_session_names_must_end_in_unwind_json(tmp_path, scan, name):
    with pytest.raises(InvalidInputError, match=r"\.unwind\.json"):
        save_session(Session(SourceInfo.from_path(scan)), tmp_path / name)
    assert list(tmp_path.glob("*.json")) == []


def test_overwrite_and_missing_folder(tmp_path, scan):
    session = Session(SourceInfo.from_path(scan))
    path = save_session(session, tmp_path / "a.unwind.json")
    with pytest.raises(OutputError, match="already exists"):
        save_session(session, path, overwrite=False)
    with pytest.raises(OutputError, match="does not exist"):
        save_session(session, tmp_path / "nope" / "a.unwind.json")


def test_nan_is_never_written(tmp_path, scan, phantom, monkeypatch):
    with pytest.raises(InvalidInputError, match="segmentation.isovalue"):
        Segmentation(isovalue=float("nan"))
    with pytest.raises(InvalidInputError, match=r"endpoints.head\[0\]"):
        Endpoints(head=[math.inf, 0, 0], tail=[1, 2, 3])
    with pytest.raises(InvalidInputError, match=r"segmentation.seeds\[0\]\[2\]"):
        Segmentation(seeds=[[1, 2, float("nan")]])

    session = make_session(scan, phantom)
    original = Session.to_dict

    def with_nan(self):
        d = original(self)
        d["deformation"]["keyframes"][1]["position"][2] = float("nan")
        return d

    monkeypatch.setattr(Session, "to_dict", with_nan)
    target = tmp_path / "nan.unwind.json"
    with pytest.raises(InvalidInputError, match=r"deformation\.keyframes\[1\]\.position\[2\] is nan"):
        save_session(session, target)
    assert not target.exists() and no_leftovers(tmp_path) == []


def test_reassigned_fields_are_checked_on_save(tmp_path, scan):
    session = Session(SourceInfo.from_path(scan))
    session.segmentation = {"k": 3}  # not a Segmentation
    with pytest.raises(InvalidInputError, match="session.segmentation must be a Segmentation"):
        save_session(session, tmp_path / "x.unwind.json")


# ------------------------------------------------------------------------------------------------------------------
# loading damaged files
# ------------------------------------------------------------------------------------------------------------------
def _edit(key_path: str, value):
    def edit(d):
        *parents, last = key_path.split(".")
        for k in parents:
            d = d[k]
        if value is KeyError:
            del d[last]
        else:
            d[last] = value
    return edit


CORRUPT = {
    "truncated": (lambda text: text[: len(text) // 2], ["not valid JSON", "line ", "column "]),
    "not json": (lambda text: "hello, world\n", ["not valid JSON", "line 1, column 1"]),
    "empty": (lambda text: "", ["empty"]),
    "whitespace": (lambda text: "  \n\n", ["empty"]),
    "a list": (lambda text: "[1, 2, 3]", ["a list, not a JSON object"]),
    "nan": (lambda text: text.replace('"isovalue": 812.5', '"isovalue": NaN'), ["NaN"]),
    "infinity": (lambda text: text.replace('"isovalue": 812.5', '"isovalue": -Infinity'), ["-Infinity"]),
    "no source": (_edit("source", KeyError), ["'source' is missing"]),
    "no source shape": (_edit("source.shape", KeyError), ["source.shape is missing"]),
    "shape a string": (_edit("source.shape", "big"), ["source.shape must be a list", "'big'"]),
    "shape of 2": (_edit("source.shape", [3, 4]), ["source.shape must hold 3"]),
    "negative spacing": (_edit("source.spacing", [1.0, -1.0, 1.0]), ["source.spacing must be positive"]),
    "spacing strings": (_edit("source.spacing", ["1", "1", "1"]), ["source.spacing[0] must be a number"]),
    "bad dtype": (_edit("source.dtype", "complex128"), ["source.dtype must be one of"]),
    "bad unit": (_edit("source.unit", "furlong"), ["source.unit", "furlong"]),
    "bad checksum": (_edit("source.checksum", "md5:0123"), ["source.checksum", "md5:0123"]),
    "k a boolean": (_edit("segmentation.k", True), ["segmentation.k must be an integer"]),
    "selected not ints": (_edit("segmentation.selected", [1.5]), [r"segmentation.selected[0]"]),
    "segmentation a list": (_edit("segmentation", [5]), ["segmentation must be an object"]),
    "head of 2": (_edit("endpoints.head", [1, 2]), ["endpoints.head must hold 3"]),
    "chain not pairs": (_edit("endpoints.chain", [[[1, 2, 3]]]), ["endpoints.chain[0] must hold 2"]),
    "deformation garbage": (_edit("deformation.keyframes", [1, 2]), ["deformation:"]),
    "deformation schema": (_edit("deformation.schema", "other"), ["deformation:", "other"]),
    "bad time": (_edit("created", "yesterday"), ["created must be an ISO 8601 time", "yesterday"]),
    "naive time": (_edit("modified", "2025-01-01T00:00:00"), ["modified must say its time zone"]),
    "no modified": (_edit("modified", KeyError), ["'modified' is missing"]),
    "notes a number": (_edit("notes", 3), ["notes must be a string"]),
    "software missing": (_edit("software", KeyError), ["'software' is missing"]),
    "other schema": (_edit("schema", "napari-unwind/deformation/1"), ["not a napari-unwind session",
                                                                        "napari-unwind/deformation/1"]),
    "no schema": (_edit("schema", KeyError), ["not a napari-unwind session"]),
    "schema version text": (_edit("schema_version", "one"), ["schema_version must be an integer", "'one'"]),
    "schema version negative": (_edit("schema_version", -1), ["schema_version must be an integer"]),
    "foreign json": (lambda text: '{"name": "my fish", "length": 3}', ["not a napari-unwind session"]),
}


@pytest.mark.parametrize("case", sorted(CORRUPT))
def test_corrupt_files_are_refused_clearly(tmp_path, scan, phantom, case):
    good = save_session(make_session(scan, phantom), tmp_path / "good.unwind.json")
    change, expected = CORRUPT[case]
    text = good.read_text(encoding="utf-8")
    if change.__name__ == "edit":
        d = json.loads(text)
        change(d)
        text = json.dumps(d, indent=2)
    else:
        text = change(text)
    bad = tmp_path / "bad.unwind.json"
    bad.write_text(text, encoding="utf-8")
    with pytest.raises(InvalidInputError) as info:
        load_session(bad)
    message = str(info.value)
    assert str(bad) in message
    for part in expected:
        assert part in message, (part, message)


def test_truncated_file_names_the_line(tmp_path, scan, phantom):
    good = save_session(make_session(scan, phantom), tmp_path / "good.unwind.json")
    lines = good.read_text().splitlines(keepends=True)
    bad = tmp_path / "bad.unwind.json"
    bad.write_text("".join(lines[:40]))  # cut after line 40: the parser fails on line 41 (end of input)
    with pytest.raises(InvalidInputError, match=r"line 4[01], column \d+"):
        load_session(bad)


def test_binary_and_missing_files(tmp_path):
    binary = tmp_path / "scan.unwind.json"
    binary.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(InvalidInputError, match="not UTF-8"):
        load_session(binary)
    with pytest.raises(FileNotFoundError, match="nothere.unwind.json"):
        load_session(tmp_path / "nothere.unwind.json")
    with pytest.raises(InvalidInputError, match="is a folder"):
        load_session(tmp_path)


# ------------------------------------------------------------------------------------------------------------------
# schema versions
# ------------------------------------------------------------------------------------------------------------------
def test_newer_schema_is_refused(tmp_path, scan, phantom):
    path = save_session(make_session(scan, phantom), tmp_path / "s.unwind.json")
    d = json.loads(path.read_text())
    d["schema_version"] = SCHEMA_VERSION + 1
    d["software"]["version"] = "9.9.0"
    d["source"] = {"whatever": "a future layout"}
    path.write_text(json.dumps(d))
    with pytest.raises(InvalidInputError) as info:
        load_session(path)
    message = str(info.value)
    assert f"written by a newer napari-unwind 9.9.0 (schema {SCHEMA_VERSION + 1})" in message
    assert "upgrade" in message and str(path) in message


def schema0(phantom, scan: Path, every: int = 12) -> tuple[dict, np.ndarray, np.ndarray]:
    """A pre-release (schema 0) session, written by hand from the phantom's true keyframes."""
    positions = phantom.centerline_physical[::every]
    frames = phantom.frames[::every]
    old = {
        "source_path": str(scan),
        "shape": list(phantom.volume.shape),
        "dtype": "uint16",
        "spacing": list(phantom.spacing),
        "unit": "um",
        "keyframes": [{"position": p.tolist(), "frame": f.tolist(), "half_extent": [5.0, 6.0]}
                      for p, f in zip(positions, frames, strict=True)],
        "pad": [2.0, 3.0],
        "head": phantom.centerline[0].tolist(),
        "tail": phantom.centerline[-1].tolist(),
        "k": 7,
        "selected": [1, 3],
        "isovalue": 700.0,
        "napari_unwind_version": "0.0.1.dev3",
        "saved": "2024-11-02T10:00:00",
        "notes": "from the prototype",
    }
    return old, positions, frames


def test_schema0_is_migrated(tmp_path, scan, phantom):
    old, positions, frames = schema0(phantom, scan)
    path = tmp_path / "old.unwind.json"
    path.write_text(json.dumps(old))
    session = load_session(path)

    truth = Deformation.from_keyframes(positions, frames, (5.0, 6.0), pad=(2.0, 3.0), spacing=phantom.spacing,
                                       unit="micrometer")
    assert session.deformation == truth
    s = np.linspace(*truth.s_range, 17)
    np.testing.assert_allclose(session.deformation.sample(s)[0], truth.sample(s)[0], atol=1e-12)
    assert session.source == SourceInfo(path=str(scan), shape=phantom.volume.shape, dtype="uint16",
                                        spacing=phantom.spacing, unit="micrometer")
    assert session.source.checksum is None and session.source.size is None
    assert session.endpoints == Endpoints(head=phantom.centerline[0], tail=phantom.centerline[-1])
    assert session.segmentation == Segmentation(k=7, selected=(1, 3), isovalue=700.0)
    assert session.created == session.modified == "2024-11-02T10:00:00.000Z"
    assert session.software_version == "0.0.1.dev3" and session.notes == "from the prototype"

    # saving writes the current schema; verify_source cannot check content without a checksum: it warns and
    # returns the checksum to record
    resaved = save_session(session, tmp_path / "new.unwind.json")
    assert json.loads(resaved.read_text())["schema_version"] == SCHEMA_VERSION
    again = load_session(resaved)
    assert again.deformation == truth and again.created == session.created
    with pytest.warns(UserWarning, match="no checksum"):
        info = verify_source(again)
    assert info.checksum == checksum(scan)
    again.source = info
    assert load_session(save_session(again, resaved)).source.checksum == checksum(scan)


def test_schema0_without_required_field(tmp_path, scan, phantom):
    old, _, _ = schema0(phantom, scan)
    del old["shape"]
    path = tmp_path / "old.unwind.json"
    path.write_text(json.dumps(old))
    with pytest.raises(InvalidInputError, match="'shape' of a schema-0 session is missing"):
        load_session(path)


def test_schema_without_migration_path_is_refused(tmp_path, scan, phantom, monkeypatch):
    old, _, _ = schema0(phantom, scan)
    path = tmp_path / "old.unwind.json"
    path.write_text(json.dumps(old))
    monkeypatch.setattr(S, "_MIGRATIONS", {})
    with pytest.raises(InvalidInputError, match="schema 0 is too old") as info:
        load_session(path)
    assert str(path) in str(info.value)


# ------------------------------------------------------------------------------------------------------------------
# checksums
# ------------------------------------------------------------------------------------------------------------------
def test_checksum_of_a_file(tmp_path):
    data = np.random.default_rng(1).integers(0, 256, 3 * 2**20 + 17, dtype=np.uint8).tobytes()
    f = tmp_path / "scan.tif"
    f.write_bytes(data)
    records = []
    digest = checksum(f, progress=records.append)
    assert digest == "sha256:" + hashlib.sha256(data).hexdigest()  # the same as `sha256sum scan.tif`
    assert records[-1].done == records[-1].total == len(data)
    assert [r.done for r in records] == sorted(r.done for r in records)

    copy = tmp_path / "copy" / "renamed.tif"
    copy.parent.mkdir()
    shutil.copyfile(f, copy)
    assert checksum(copy) == digest
    flip_byte(copy, 1_000_000)
    assert checksum(copy) != digest


def test_checksum_streams_in_blocks(tmp_path, monkeypatch):
    monkeypatch.setattr(S, "_BLOCK", 1000)
    data = os.urandom(10_500)
    f = tmp_path / "f.bin"
    f.write_bytes(data)
    gen = checksum_iter(f)
    records = []
    while True:
        try:
            records.append(next(gen))
        except StopIteration as stop:
            digest = stop.value
            break
    assert digest == "sha256:" + hashlib.sha256(data).hexdigest()
    assert [r.done for r in records] == [0] + list(range(1000, 10_001, 1000)) + [10_500]


def _make_tree(root: Path, order: list[str], contents: dict[str, bytes]) -> None:
    for rel in order:
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(contents[rel])


def test_checksum_of_a_folder(tmp_path):
    contents = {"zarr.json": b"{}", "0/c/0/0/0": os.urandom(5000), "0/c/0/0/1": os.urandom(3000),
                "1/c/0/0/0": b"\x00" * 100, "slice_10.png": b"png10", "slice_9.png": b"png9"}
    a, b = tmp_path / "a.zarr", tmp_path / "b.zarr"
    _make_tree(a, sorted(contents), contents)
    _make_tree(b, sorted(contents, reverse=True), contents)  # created in the other order
    os.utime(b / "zarr.json", (0, 0))  # times do not matter
    digest = checksum(a)
    assert digest == checksum(b) == manifest_digest({rel: a / rel for rel in contents})
    copy = tmp_path / "copy.zarr"
    shutil.copytree(a, copy)
    assert checksum(copy) == digest

    # litter and our temporaries are ignored
    (a / ".DS_Store").write_bytes(b"finder")
    (a / "0" / "._c").write_bytes(b"appledouble")
    (a / "0" / "Thumbs.db").write_bytes(b"thumbs")
    (a / ".zarr.json.0123abcd.unwind-tmp").write_bytes(b"half written")
    (a / ".1.0123abcd.unwind-tmp").mkdir()
    (a / ".1.0123abcd.unwind-tmp" / "x").write_bytes(b"half written")
    assert checksum(a) == digest

    # but content, names and other hidden files (zarr v2 metadata) count
    (copy / ".zattrs").write_bytes(b"{}")
    assert checksum(copy) != digest
    for change in ("flip", "rename", "delete"):
        shutil.rmtree(b)
        shutil.copytree(a, b)
        if change == "flip":
            flip_byte(b / "0/c/0/0/1", 1234)
        elif change == "rename":
            (b / "slice_9.png").rename(b / "slice_09.png")
        else:
            (b / "1/c/0/0/0").unlink()
        assert checksum(b) != digest, change


def test_checksum_of_a_written_ome_zarr(tmp_path, phantom):
    store = write_volume(phantom.volume, tmp_path / "fish.zarr", spacing=phantom.spacing, unit="um")
    info = SourceInfo.from_path(store)
    assert info.format == "ome-zarr" and info.shape == phantom.volume.shape
    files = {p.relative_to(store).as_posix(): p for p in store.rglob("*") if p.is_file()}
    assert info.checksum == manifest_digest(files)
    assert info.size == sum(p.stat().st_size for p in files.values())
    copy = tmp_path / "elsewhere" / "fish.zarr"
    shutil.copytree(store, copy)
    assert checksum(copy) == info.checksum


def test_empty_folder_and_missing_path(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(InvalidInputError, match="empty folder"):
        checksum(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="nothing.tif does not exist"):
        checksum(tmp_path / "nothing.tif")


def test_checksum_includes_nhdr_data_file(tmp_path, scan):
    raw = scan.with_suffix(".raw")
    digest = checksum(scan)
    assert digest == manifest_digest({"fish.nhdr": scan, "fish.raw": raw})
    assert digest != "sha256:" + sha256_file(scan)  # not the header alone
    flip_byte(raw, 100)
    assert checksum(scan) != digest
    raw.unlink()
    with pytest.raises(SourceMissingError, match="fish.raw"):
        checksum(scan)


@pytest.mark.parametrize("spec", ["LIST", "part%d.raw 1 3 1", "part%d.raw 3 1 -1"])
def test_checksum_includes_every_file_an_nhdr_names(tmp_path, spec):
    parts = {f"part{i}.raw": os.urandom(64) for i in (1, 2, 3)}
    for name, data in parts.items():
        (tmp_path / name).write_bytes(data)
    header = tmp_path / "multi.nhdr"
    text = "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4 12\nencoding: raw\n"
    text += f"data file: {spec}\n" + ("".join(f"{n}\n" for n in parts) if spec == "LIST" else "")
    header.write_text(text)
    digest = checksum(header)
    assert digest == manifest_digest({"multi.nhdr": header, **{n: tmp_path / n for n in parts}})
    flip_byte(tmp_path / "part3.raw", 5)
    assert checksum(header) != digest


def test_dat_and_raw_hash_the_pair(tmp_path, phantom):
    dat = write_volume(phantom.volume, tmp_path / "fish.dat", spacing=phantom.spacing)
    raw = tmp_path / "fish.raw"
    digest = checksum(dat)
    assert digest == checksum(raw) == manifest_digest({"fish.dat": dat, "fish.raw": raw})
    flip_byte(raw, 10)
    assert checksum(dat) != digest


def test_one_slice_of_a_stack_hashes_the_stack(tmp_path, phantom):
    folder = tmp_path / "slices"
    write_volume(phantom.volume[:5], folder / "fish_{:03d}.png")
    slices = sorted(folder.glob("fish_*.png"))
    assert len(slices) == 5
    digest = checksum(slices[2])
    assert digest == manifest_digest({p.name: p for p in slices})
    flip_byte(slices[4], -20)
    assert checksum(slices[0]) != digest


# ------------------------------------------------------------------------------------------------------------------
# the scan behind a session
# ------------------------------------------------------------------------------------------------------------------
def test_verify_source_accepts_the_same_scan(scan, phantom):
    session = make_session(scan, phantom)
    records = []
    info = verify_source(session, progress=records.append)
    assert info == session.source
    assert records[-1].done == records[-1].total == session.source.size


def test_verify_source_on_a_moved_scan(tmp_path, scan, phantom):
    session = make_session(scan, phantom)
    moved = tmp_path / "archive"
    moved.mkdir()
    for p in scan.parent.iterdir():
        p.rename(moved / p.name)
    with pytest.raises(SourceMissingError) as info:
        verify_source(session)
    message = str(info.value)
    assert isinstance(info.value, InvalidInputError)
    assert str(scan) in message and "NEW_PATH --session" in message and "path=" in message

    new = verify_source(session, path=moved / "fish.nhdr")
    assert new.path == str(moved / "fish.nhdr")
    assert new.checksum == session.source.checksum and new.shape == session.source.shape
    with pytest.raises(SourceMissingError, match=f"the session recorded {scan}"):
        verify_source(session, path=tmp_path / "wrong.nhdr")


def test_verify_source_on_changed_content(scan, phantom):
    session = make_session(scan, phantom)
    flip_byte(scan.with_suffix(".raw"), 5000)  # same shape, same size, other voxels
    with pytest.raises(SourceChangedError, match="content differs") as info:
        verify_source(session)
    message = str(info.value)
    assert isinstance(info.value, InvalidInputError)
    assert "changed since this session was made" in message and "would not match" in message


def test_verify_source_compares_shape_and_size_before_hashing(scan, phantom, monkeypatch):
    session = make_session(scan, phantom)
    write_volume(phantom.volume[:, :, :-1], scan, spacing=phantom.spacing, unit="um", encoding="raw",
                 overwrite=True)

    def no_hashing(*args, **kwargs):
        raise AssertionError("hashed although a cheap check already failed")

    monkeypatch.setattr(S, "_digest_iter", no_hashing)
    with pytest.raises(SourceChangedError, match=r"its shape is \(24, 32, 71\), the session's \(24, 32, 72\)"):
        verify_source(session)
    other = open_volume(scan).with_data(open_volume(scan).data, spacing=(2.0, 1.0, 1.0))
    with pytest.raises(SourceChangedError, match="spacing"):
        verify_source(session, volume=other)


def test_spacing_given_by_hand_is_not_a_change(tmp_path, phantom):
    # a BMP/PNG stack stores no spacing: the user gives it, the session records it
    folder = tmp_path / "slices"
    write_volume(phantom.volume[:6], folder / "fish_{:03d}.png")
    by_hand = open_volume(folder).with_data(open_volume(folder).data, spacing=(3.0, 0.5, 0.5))
    session = Session(SourceInfo.from_path(folder, volume=by_hand))
    assert session.source.spacing == (3.0, 0.5, 0.5)
    assert verify_source(session).spacing == (3.0, 0.5, 0.5)  # the file says 1, 1, 1; content identical
    flip_byte(folder / "fish_002.png", -20)
    with pytest.raises(SourceChangedError, match="content differs.*spacing"):
        verify_source(session)


def test_verify_source_compares_size_before_hashing(tmp_path, phantom, monkeypatch):
    store = write_volume(phantom.volume, tmp_path / "fish.zarr", spacing=phantom.spacing, unit="um")
    session = Session(SourceInfo.from_path(store))
    (store / "added by someone.txt").write_bytes(b"12345")  # same voxels, 5 more bytes
    monkeypatch.setattr(S, "_digest_iter", lambda *a, **k: pytest.fail("hashed although the size differs"))
    expected = rf"it holds {session.source.size + 5} bytes, the session's scan {session.source.size}"
    with pytest.raises(SourceChangedError, match=expected):
        verify_source(session)


def test_one_dicom_file_hashes_its_series_folder(tmp_path, phantom):
    folder = write_volume(phantom.volume[:4], tmp_path / "fish.dicom", spacing=phantom.spacing, unit="mm")
    files = sorted(p for p in folder.iterdir() if p.is_file())
    assert len(files) >= 4
    (folder / ".DS_Store").write_bytes(b"finder")
    digest = checksum(files[0])
    assert digest == manifest_digest({p.name: p for p in files})
    flip_byte(files[-1], -1)
    assert checksum(files[0]) != digest


def test_schema1_is_migrated_with_centred_cages_and_a_schema2_file_is_newer_for_a_schema1_reader(
        tmp_path, scan, phantom, monkeypatch):
    session = make_session(scan, phantom)
    session.deformation = session.deformation.set_cage(1, (-1.0, 5.0, -4.0, 2.0))
    path = save_session(session, tmp_path / "s.unwind.json")
    new = json.loads(path.read_text())
    assert new["schema_version"] == 2 and new["deformation"]["schema"] == "napari-unwind/deformation/2"
    assert load_session(path).deformation.keyframes[1].bounds == (-1.0, 5.0, -4.0, 2.0)

    # a schema-1 file (centred cages, no offsets) loads with zero offsets and the same half extents
    old = json.loads(path.read_text())
    old["schema_version"] = 1
    old["deformation"]["schema"] = "napari-unwind/deformation/1"
    for k in old["deformation"]["keyframes"]:
        del k["offset"]
    path.write_text(json.dumps(old))
    loaded = load_session(path).deformation
    assert np.all(loaded.offsets == 0)
    np.testing.assert_allclose(loaded.half_extents[1], (3.0, 3.0))

    # a reader of schema 1 refuses the new file instead of dropping the offsets
    path.write_text(json.dumps(new))
    monkeypatch.setattr(S, "SCHEMA_VERSION", 1)
    with pytest.raises(InvalidInputError, match="newer napari-unwind"):
        load_session(path)


def test_the_twist_profile_round_trips_and_bad_ones_are_refused(tmp_path, scan):
    from napari_unwind.session import TwistProfile

    tw = TwistProfile(s=(0.0, 1.5, 3.0), angle=(0.0, 10.0, 20.5), confidence=(0.0, 0.5, 1.0), source="estimated")
    session = Session(SourceInfo.from_path(scan), twist=tw)
    path = save_session(session, tmp_path / "twist.unwind.json")
    assert json.loads(path.read_text())["twist"]["angle"] == [0.0, 10.0, 20.5]
    assert load_session(path).twist == tw
    assert "twist" not in Session(SourceInfo.from_path(scan)).to_dict()  # files without it stay as they were
    for kwargs, match in [(dict(s=(0.0, 1.0), angle=(0.0,), confidence=(0.0, 1.0)), "as long as"),
                          (dict(s=(1.0, 1.0), angle=(0.0, 0.0), confidence=(0.0, 1.0)), "increase"),
                          (dict(s=(0.0, 1.0), angle=(0.0, 0.0), confidence=(0.0, 1.5)), r"\[0, 1\]"),
                          (dict(s=(0.0, 1.0), angle=(0.0, math.nan), confidence=(0.0, 1.0)), "angle"),
                          (dict(s=(0.0,), angle=(0.0,), confidence=(1.0,), source="guess"), "source")]:
        with pytest.raises(InvalidInputError, match=match):
            TwistProfile(**kwargs)
    d = json.loads(path.read_text())
    d["twist"]["confidence"] = [0, 2, 1]  # a hand-edited file: the schema names the field
    bad = tmp_path / "bad.unwind.json"
    bad.write_text(json.dumps(d))
    with pytest.raises(InvalidInputError, match="twist"):
        load_session(bad)


def test_the_channels_a_session_was_applied_to_round_trip(tmp_path, scan):
    """Issue 24 item 1: a session records the other images of its grid it straightened; files without them stay as
    they were, and a hand-edited record is refused by the schema naming the field."""
    info = SourceInfo.from_path(scan)
    session = Session(info, channels=(info,))
    path = save_session(session, tmp_path / "channels.unwind.json")
    assert json.loads(path.read_text())["channels"][0]["checksum"] == info.checksum
    assert load_session(path).channels == (info,)
    assert "channels" not in Session(info).to_dict()
    d = json.loads(path.read_text())
    d["channels"][0]["shape"] = [1, 2]
    bad = tmp_path / "bad.unwind.json"
    bad.write_text(json.dumps(d))
    with pytest.raises(InvalidInputError, match="channels"):
        load_session(bad)
    with pytest.raises(InvalidInputError, match="channels"):
        Session(info, channels=("scan.nrrd",))
