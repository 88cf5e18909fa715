"""JSON inputs that lie (issue 20, item 3): sessions, deformations and collection files through one gate.

A hostile family, seeded: a valid file with one field (chosen at random among every field and item of the file) made
a lie: an integer too large for a float, a 5000-digit number, 1e400, NaN, a nest of 100000 arrays, a 10 MB string,
a value of the wrong type, a required key removed, a number out of the schema's bounds. Every case must be refused
by ONE line of InvalidInputError naming the field, never by another exception; through ``unwind`` it is exit 1 and
a single stderr line ``unwind: error: ...``.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import random
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from napari_unwind import _json
from napari_unwind.batch import read_batch
from napari_unwind.deformation import Deformation
from napari_unwind.errors import InvalidInputError
from napari_unwind.session import Endpoints, Segmentation, Session, SourceInfo, load_session, save_session

SEED = 20_03
N_SESSION, N_DEFORMATION, N_BATCH, N_CLI = 120, 60, 40, 24

#: the hostile family: name -> JSON text put in place of the chosen value
LIES = {
    "int_over_float": "1" + "0" * 400,          # an int that no float holds (OverflowError on float())
    "digits_5000": "7" * 5000,                  # past Python's int max str digits (ValueError on int())
    "float_1e400": "1e400",                     # read as inf
    "nan": "NaN",
    "minus_infinity": "-Infinity",
    "deep_nest": "[" * 100_000 + "]" * 100_000,  # RecursionError in the parser
    "string_10mb": json.dumps("x" * 10_000_000),
    "out_of_bounds": "1" + "0" * 30,            # a finite number beyond every bound of the schemas
    "wrong_type": None,                         # chosen by the value's own type
    "missing_key": None,                        # a required key removed
}
FAMILIES = sorted(LIES)
_MARK = "@@hostile@@"


# ------------------------------------------------------------------------------------------------------------------
# valid documents
# ------------------------------------------------------------------------------------------------------------------
def _deformation() -> Deformation:
    t = np.linspace(0, 3, 7)
    points = np.stack([t * 15, np.sin(t) * 5 + 20, np.cos(t) * 3 + 20], axis=1)
    d = Deformation.from_polyline(points, spacing=(1.0, 0.5, 0.5), cage_half_extent=(4.0, 3.0), unit="um")
    return d.set_cage(1, (-1.0, 5.0, -4.0, 2.0))


def _session() -> Session:
    src = SourceInfo(path="/data/fish.nrrd", shape=(40, 48, 64), dtype="uint16", spacing=(1.0, 0.5, 0.5),
                     unit="um", checksum="sha256:" + "0" * 64, size=245760, format="nrrd")
    return Session(source=src, deformation=_deformation(),
                   segmentation=Segmentation(k=5, level=1, selected=[2, 4], seeds=[[12.0, 16.0, 20.5]],
                                             isovalue=812.5, fill_holes=True),
                   endpoints=Endpoints(head=(1.0, 20.0, 20.0), tail=(40.0, 22.0, 18.0),
                                       chain=[((1.0, 20.0, 20.0), (20.0, 21.0, 19.0)),
                                              ((22.0, 21.0, 19.0), (40.0, 22.0, 18.0))]),
                   notes="left pectoral fin torn")


@pytest.fixture(scope="module")
def session_doc(tmp_path_factory) -> dict:
    path = save_session(_session(), tmp_path_factory.mktemp("s") / "good.unwind.json")
    return json.loads(path.read_text())


BATCH = [{"scan": "fish_1.zarr", "select": [[10.0, 20.0, 30.0], [1.0, 2.0, 3.0]], "name": "fish 1"},
         {"scan": "vol-0123", "select": "all"}]


# ------------------------------------------------------------------------------------------------------------------
# the hostile family
# ------------------------------------------------------------------------------------------------------------------
def _paths(doc) -> list[tuple]:
    """Every (path, value) of a document, the root left out, without recursion."""
    out, stack = [], [((), doc)]
    while stack:
        where, v = stack.pop()
        if where:
            out.append(where)
        items = enumerate(v) if isinstance(v, list) else v.items() if isinstance(v, dict) else ()
        stack.extend(((*where, k), c) for k, c in items)
    return sorted(out, key=str)


def _get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


def _required(kind: str, path: tuple) -> bool:
    """Is the last key of ``path`` one the schema requires (removing it must be refused)?"""
    generic = tuple("*" if isinstance(p, int) else p for p in path)
    required = {
        "session": {("schema",), ("schema_version",), ("software",), ("software", "name"), ("software", "version"),
                    ("created",), ("modified",), ("source",), ("source", "path"), ("source", "shape"),
                    ("source", "dtype"), ("source", "spacing"), ("endpoints", "head"), ("endpoints", "tail"),
                    ("deformation", "schema"), ("deformation", "spacing"), ("deformation", "keyframes"),
                    ("deformation", "keyframes", "*", "position"), ("deformation", "keyframes", "*", "frame"),
                    ("deformation", "keyframes", "*", "half_extent")},
        "deformation": {("schema",), ("spacing",), ("keyframes",), ("keyframes", "*", "position"),
                        ("keyframes", "*", "frame"), ("keyframes", "*", "half_extent")},
        "batch": {("*", "scan")},
    }[kind]
    return generic in required


def _wrong(value):
    """A value of another JSON type than ``value``."""
    if isinstance(value, bool):
        return "yes"
    if isinstance(value, (int, float)):
        return {"value": value}
    if isinstance(value, str):
        return [value]
    if isinstance(value, list):
        return {"items": value} if value else 7
    if isinstance(value, dict):
        return [1, 2, 3]
    return [[]]  # null


def _candidates(kind: str, doc, family: str) -> list[tuple]:
    paths = _paths(doc)
    if family == "missing_key":
        return [p for p in paths if isinstance(p[-1], str) and _required(kind, p)]
    if family == "out_of_bounds":  # an intensity may be any finite number: 1e30 is a lie only elsewhere
        return [p for p in paths if p[-1] != "isovalue"]
    return paths


def _lie(kind: str, doc, family: str, rng: random.Random) -> tuple[str, tuple]:
    """The text of ``doc`` with one field made a lie of ``family``, and the path of that field."""
    doc = json.loads(json.dumps(doc))
    path = rng.choice(_candidates(kind, doc, family))
    parent, last = _get(doc, path[:-1]), path[-1]
    if family == "missing_key":
        del parent[last]
        return json.dumps(doc, indent=1), path
    parent[last] = _wrong(parent[last]) if family == "wrong_type" else _MARK
    text = json.dumps(doc, indent=1)
    if family != "wrong_type":
        text = text.replace(json.dumps(_MARK), LIES[family])
    return text, path


def _field_named(message: str, path: tuple) -> bool:
    """The message names the field: its last key, or for an item of a list, the key of the list."""
    keys = [p for p in path if isinstance(p, str)]
    if not keys:  # an item of the batch list itself: the line or the index
        return bool(re.search(rf"\[{path[0]}\]|line {path[0] + 2}", message))
    return keys[-1] in message


#: what a message quotes of the value received, per family (the others name the field only)
RECEIVED = {"int_over_float": "401 digits", "digits_5000": "5000 digits", "float_1e400": "1e400", "nan": "NaN",
            "minus_infinity": "-Infinity", "deep_nest": "nested", "string_10mb": "10000000 characters",
            "out_of_bounds": LIES["out_of_bounds"]}


#: the same for the values handed to from_dict in Python (their reprs)
PYTHON_RECEIVED = {"int_over_float": "401 digits", "digits_5000": "digits", "float_1e400": "inf", "nan": "nan",
                   "minus_infinity": "-inf", "deep_nest": "nested", "string_10mb": "10000000 characters",
                   "out_of_bounds": "1e+30"}


def _quotes_value(message: str, family: str) -> bool:
    return RECEIVED.get(family, "") in message


def _one_line(exc: BaseException) -> str:
    message = str(exc)
    assert "\n" not in message and len(message) < 1000, message[:2000]
    return message


def _cases(kind: str, n: int, offset: int) -> list[tuple[int, str]]:
    rng = random.Random(SEED + offset)
    # every family at least a few times, then at random
    return [(rng.randrange(1 << 30), FAMILIES[i % len(FAMILIES)] if i < 3 * len(FAMILIES) else rng.choice(FAMILIES))
            for i in range(n)]


@pytest.mark.parametrize("seed,family", _cases("session", N_SESSION, 1))
def test_hostile_session_file_is_one_line(tmp_path, session_doc, seed, family):
    text, path = _lie("session", session_doc, family, random.Random(seed))
    bad = tmp_path / "bad.unwind.json"
    bad.write_text(text)
    with pytest.raises(InvalidInputError) as info:
        load_session(bad)
    message = _one_line(info.value)
    assert str(bad) in message
    assert _field_named(message, path), (family, path, message[:300])
    assert _quotes_value(message, family), (family, path, message[:300])


@pytest.mark.parametrize("seed,family", _cases("deformation", N_DEFORMATION, 2))
def test_hostile_deformation_is_one_line(seed, family):
    """The API face: the text parsed by the gate, then Deformation.from_dict; and the parsed value handed straight
    to from_dict as a Python dict (int 10**5000, inf, a nest of 100000 lists built in Python)."""
    text, path = _lie("deformation", _deformation().to_dict(), family, random.Random(seed))
    with pytest.raises(InvalidInputError) as info:
        Deformation.from_dict(_json.loads(text))
    assert _field_named(_one_line(info.value), path), (family, path, str(info.value)[:300])
    assert _quotes_value(str(info.value), family), (family, path, str(info.value)[:300])

    python = {"int_over_float": 10**400, "digits_5000": 10**5000, "float_1e400": float("inf"), "nan": float("nan"),
              "minus_infinity": float("-inf"), "out_of_bounds": 1e30, "string_10mb": "x" * 10_000_000}
    if family in python or family == "deep_nest":
        d = _deformation().to_dict()
        value = python.get(family)
        if family == "deep_nest":
            value = []
            for _ in range(100_000):
                value = [value]
        parent = _get(d, path[:-1])
        parent[path[-1]] = value
        with pytest.raises(InvalidInputError) as info:
            Deformation.from_dict(d)
        assert _field_named(_one_line(info.value), path), (family, path, str(info.value)[:300])
        assert PYTHON_RECEIVED[family] in str(info.value), (family, path, str(info.value)[:300])


@pytest.mark.parametrize("seed,family", _cases("batch", N_BATCH, 3))
def test_hostile_batch_file_is_one_line(tmp_path, seed, family):
    text, path = _lie("batch", BATCH, family, random.Random(seed))
    bad = tmp_path / "collection.json"
    bad.write_text(text)
    with pytest.raises(InvalidInputError) as info:
        read_batch(bad)
    message = _one_line(info.value)
    assert str(bad) in message
    assert _field_named(message, path), (family, path, message[:300])
    assert _quotes_value(message, family), (family, path, message[:300])


def _string_fields(doc) -> list[tuple]:
    return [p for p in _paths(doc) if isinstance(_get(doc, p), str)]


@pytest.mark.parametrize("path", _string_fields(_session().to_dict()), ids=str)
def test_every_string_field_of_a_session_is_bounded(tmp_path, session_doc, path):
    """The random draw above rarely lands on a free-text field (notes, path): a sweep of every string field of a
    session with the 10 MB string, so that each maxLength of the schema is seen refusing."""
    doc = json.loads(json.dumps(session_doc))
    _get(doc, path[:-1])[path[-1]] = "x" * 10_000_000
    bad = tmp_path / "bad.unwind.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(InvalidInputError) as info:
        load_session(bad)
    assert _field_named(_one_line(info.value), path), (path, str(info.value)[:300])


def _csv_lie(rng: random.Random) -> tuple[bytes, str]:
    """A collection CSV with one cell or the whole file made a lie."""
    rows = [["scan", "select", "name"], ["fish_1.zarr", "10 20 30; 1 2 3", "fish 1"], ["vol-0123", "all", ""]]
    lie = rng.choice(["binary", "nul", "huge_field", "digits_5000", "1e400", "nan", "two_numbers", "letters",
                      "empty_scan", "long_scan", "extra_column", "no_header"])
    cell = {"digits_5000": "7" * 5000 + " 1 1", "1e400": "1e400 2 3", "nan": "nan 2 3", "two_numbers": "1 2",
            "letters": "a b c"}.get(lie)
    if cell is not None:
        rows[1][1] = cell
    if lie == "empty_scan":
        rows[2][0] = " "
    if lie == "long_scan":
        rows[2][0] = "s" * 5000
    if lie == "extra_column":
        rows[1].append("surplus")
    if lie == "no_header":
        rows = [["fish.zarr", "all"]]
    text = "\n".join(",".join(r) for r in rows) + "\n"
    data = text.encode()
    if lie == "binary":
        data = bytes(rng.randrange(256) for _ in range(3000))
        data = b"\x92" + data
    if lie == "nul":
        data = data.replace(b"fish_1", b"fi\0sh")
    if lie == "huge_field":
        data = data.replace(b"fish 1", b"f" * 200_000)
    return data, lie


@pytest.mark.parametrize("seed", range(24))
def test_hostile_batch_csv_is_one_line(tmp_path, seed):
    data, lie = _csv_lie(random.Random(SEED + 100 + seed))
    bad = tmp_path / "collection.csv"
    bad.write_bytes(data)
    with pytest.raises(InvalidInputError) as info:
        read_batch(bad)
    message = _one_line(info.value)
    assert str(bad) in message, (lie, message)


def test_valid_files_pass_the_gate(tmp_path, session_doc):
    """What the code writes is accepted: a session, a deformation, a schema-0 and -1 session, a collection."""
    path = tmp_path / "s.unwind.json"
    path.write_text(json.dumps(session_doc))
    assert load_session(path).deformation == _deformation()
    assert Deformation.from_dict(_deformation().to_dict()) == _deformation()
    (tmp_path / "c.json").write_text(json.dumps(BATCH))
    assert read_batch(tmp_path / "c.json")[0]["select"] == [[10.0, 20.0, 30.0], [1.0, 2.0, 3.0]]
    (tmp_path / "c.csv").write_text("scan,select,name\nfish_1.zarr,\"10,20,30; 1 2 3\",fish 1\nvol-0123,,\n")
    assert read_batch(tmp_path / "c.csv") == [
        {"scan": "fish_1.zarr", "select": [[10.0, 20.0, 30.0], [1.0, 2.0, 3.0]], "name": "fish 1"},
        {"scan": "vol-0123", "select": "all", "name": None}]


def test_a_numpy_dict_is_plain_json():
    d = _deformation().to_dict()
    d["keyframes"][0]["position"] = np.asarray(d["keyframes"][0]["position"])
    d["spacing"] = tuple(np.float32(s) for s in d["spacing"])
    assert Deformation.from_dict(d) == _deformation()


# ------------------------------------------------------------------------------------------------------------------
# schema 1 -> 2: cage offsets a schema-1 file carries are kept
# ------------------------------------------------------------------------------------------------------------------
def test_schema1_offsets_survive_migration(tmp_path, session_doc):
    old = json.loads(json.dumps(session_doc))
    old["schema_version"] = 1
    old["deformation"]["schema"] = "napari-unwind/deformation/1"
    kfs = old["deformation"]["keyframes"]
    assert kfs[1]["offset"] == [2.0, -1.0]  # the off-centre cage of _deformation()
    for k in kfs[2:]:
        del k["offset"]  # the others: centred, as schema 1 wrote them
    path = tmp_path / "old.unwind.json"
    path.write_text(json.dumps(old))
    loaded = load_session(path).deformation
    assert loaded.keyframes[1].offset == (2.0, -1.0)
    assert loaded.keyframes[1].bounds == (-1.0, 5.0, -4.0, 2.0)
    assert all(k.offset == (0.0, 0.0) for k in loaded.keyframes[2:])


# ------------------------------------------------------------------------------------------------------------------
# through the napari reader (its module needs neither Qt nor napari: napari calls the function it returns)
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed,family", _cases("session", 10, 5))
def test_hostile_session_through_the_napari_reader(tmp_path, session_doc, seed, family):
    from napari_unwind._napari._reader import get_session_reader

    text, path = _lie("session", session_doc, family, random.Random(seed))
    bad = tmp_path / "bad.unwind.json"
    bad.write_text(text)
    reader = get_session_reader(str(bad))
    assert reader is not None
    with pytest.raises(InvalidInputError) as info:
        reader(str(bad))
    message = _one_line(info.value)
    assert str(bad) in message and _field_named(message, path), (family, path, message[:300])


# ------------------------------------------------------------------------------------------------------------------
# through the command line
# ------------------------------------------------------------------------------------------------------------------
def _run_cli(argv: list[str]) -> tuple[int, str]:
    from napari_unwind.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    return code, err.getvalue()


@pytest.mark.parametrize("seed,family", _cases("session", N_CLI, 4))
def test_hostile_session_through_the_cli(tmp_path, session_doc, seed, family):
    text, path = _lie("session", session_doc, family, random.Random(seed))
    bad = tmp_path / "bad.unwind.json"
    bad.write_text(text)
    code, err = _run_cli(["map-points", "--at", "1,2,3", "--session", str(bad), "-q"])
    lines = err.splitlines()
    assert code == 1 and len(lines) == 1 and lines[0].startswith("unwind: error:"), (family, path, err[:500])
    assert _field_named(lines[0], path), (family, path, err[:300])


@pytest.mark.parametrize("family", ["digits_5000", "deep_nest"])
def test_hostile_session_through_the_unwind_command(tmp_path, session_doc, family):
    """The installed console script itself (a subprocess: the recursion limit and int digits of a fresh
    interpreter)."""
    text, _ = _lie("session", session_doc, family, random.Random(SEED))
    bad = tmp_path / "bad.unwind.json"
    bad.write_text(text)
    unwind = Path(sys.executable).with_name("unwind")
    r = subprocess.run([str(unwind), "map-points", "--at", "1,2,3", "--session", str(bad), "-q"],
                       capture_output=True, text=True, timeout=120)
    lines = r.stderr.splitlines()
    assert r.returncode == 1 and len(lines) == 1 and lines[0].startswith("unwind: error:"), r.stderr[-2000:]


@pytest.mark.parametrize("seed", range(12))
def test_hostile_batch_through_unwind_submit(tmp_path, seed):
    """``unwind submit --batch FILE``: the file is read before any call to the server (none listens here)."""
    rng = random.Random(SEED + 200 + seed)
    if seed % 2:
        data, lie = _csv_lie(rng)
        bad = tmp_path / "collection.csv"
        bad.write_bytes(data)
    else:
        lie = FAMILIES[seed // 2 % len(FAMILIES)]
        text, _ = _lie("batch", BATCH, lie, rng)
        bad = tmp_path / "collection.json"
        bad.write_text(text)
    code, err = _run_cli(["submit", "--batch", str(bad), "--server", "127.0.0.1:1", "-q"])
    lines = err.splitlines()
    assert code == 1 and len(lines) == 1 and lines[0].startswith("unwind: error:"), (lie, err[:500])
    assert str(bad) in lines[0], (lie, err[:500])


# ------------------------------------------------------------------------------------------------------------------
# JSON the server sends and JSON embedded in files we read (a hostile server, a crafted TIFF description)
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("text", ["[" * 100000, "1" * 5000, '{"a": 1e400}', "[NaN]", "{"])
def test_json_from_a_server_is_read_under_the_same_rules(text):
    from napari_unwind.client import _server_json

    with pytest.raises(InvalidInputError, match=r"^the session the server sent .*is the server a napari-unwind") as e:
        _server_json(text, "the session")
    assert "\n" not in str(e.value)


def test_a_straightening_record_nested_too_deep_is_ignored_not_a_recursion_error():
    from napari_unwind.io._straight_record import parse_record

    assert parse_record("[" * 100000) is None
    assert parse_record('{"pad": ' + "9" * 5000 + "}") is None


@pytest.mark.parametrize("item, match", [({"scan": "a", "bogus": 1}, r"batch item 0: .*'bogus'"),
                                         (["a"], r"batch item 0 must be a BatchItem or a dict")])
def test_a_batch_item_of_the_api_is_checked_in_one_line(item, match):
    from napari_unwind.client import _batch_item

    with pytest.raises(InvalidInputError, match=match):
        _batch_item(item, 0)


SPECIAL_FILES = textwrap.dedent("""
    import os, sys
    from napari_unwind.batch import read_batch
    from napari_unwind.errors import InvalidInputError
    from napari_unwind.session import load_session

    for name in sys.argv[1:]:
        for read in (load_session, read_batch):
            try:
                read(name)
                print("read", name)
            except InvalidInputError as e:
                print(str(e).replace(os.path.dirname(name) + os.sep, ""))
""")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes: POSIX")
def test_a_pipe_or_a_folder_given_as_session_or_collection_is_named_and_never_waited_on(tmp_path):
    """Before, both readers called a named pipe "a folder" (exists, is not a file) and one that passed the check
    would have waited for a writer for ever; now one bounded reader names what it found without opening it for a
    blocking read."""
    os.mkfifo(tmp_path / "s.unwind.json")
    os.mkfifo(tmp_path / "items.csv")
    (tmp_path / "folder.json").mkdir()
    r = subprocess.run([sys.executable, "-c", SPECIAL_FILES, *(str(tmp_path / n) for n in
                        ("s.unwind.json", "items.csv", "folder.json", "/dev/zero"))],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.splitlines() == [
        "s.unwind.json is a named pipe, not a session file (*.unwind.json)",
        "s.unwind.json is a named pipe, not a collection file",
        "items.csv is a named pipe, not a session file (*.unwind.json)",
        "items.csv is a named pipe, not a collection file (CSV with columns scan, select, name)",
        "folder.json is a folder, not a session file (*.unwind.json)",
        "folder.json is a folder, not a collection file",
        "zero is a character device, not a session file (*.unwind.json)",
        "zero is a character device, not a collection file (CSV with columns scan, select, name)",
    ], r.stdout
