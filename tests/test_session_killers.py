"""Tests for mutants of session.py that survived the sampled mutation pass (docs/testing-mutation.md, issue 19).

Each test names the mutants it kills (numbers as in ``mutmut show napari_unwind.session.<function>__mutmut_N``).
Every expected value is written out by hand from the documented layout and messages, never taken from a run of the
code under test. No scan is written: the records are built directly, so each test takes milliseconds.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from napari_unwind import session as S
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import open_volume, write_volume
from napari_unwind.session import (
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


def _source(path) -> SourceInfo:
    return SourceInfo(path=str(path), shape=(2, 3, 4), dtype="uint8", spacing=(1.0, 1.0, 1.0))


def test_a_null_field_is_called_null():
    # Kills _json_kind 20 ("NULL").
    with pytest.raises(InvalidInputError, match=r"source\.shape must be a list of sizes, got null \(None\)"):
        SourceInfo(path="/scan.tif", shape=None, dtype="uint8", spacing=(1.0, 1.0, 1.0))


def test_a_missing_scan_names_the_recorded_path_only_when_given_another(tmp_path):
    # verify_source(session, path=...) of a scan that is not there: the message adds "(the session recorded ...)"
    # only when the path given is not the recorded one.
    # Kills verify_source 20 (str(None) compared with the recorded path: the note was always added).
    recorded = tmp_path / "gone.nrrd"
    session = Session(source=_source(recorded))
    with pytest.raises(SourceMissingError) as same:
        verify_source(session, path=recorded)
    assert f"expected at {recorded}. If it was moved" in str(same.value)
    assert "the session recorded" not in str(same.value)
    elsewhere = tmp_path / "moved.nrrd"
    with pytest.raises(SourceMissingError, match=f"expected at {elsewhere} \\(the session recorded {recorded}\\)"):
        verify_source(session, path=elsewhere)


def test_a_wrong_value_in_a_session_file_says_what_to_do(tmp_path):
    # A session dict whose source.shape is text: the error ends with the hint, as written.
    # Kills Session.from_dict 20 (the hint upper-cased).
    d = Session(source=_source(tmp_path / "scan.nrrd")).to_dict()
    d["source"]["shape"] = "2 x 3 x 4"
    with pytest.raises(InvalidInputError, match=r"; correct that value in the file, or make the session again$"):
        Session.from_dict(d)


def test_segmentation_lists_of_the_wrong_kind_say_what_they_hold():
    # Kills Segmentation.__post_init__ 40 (what=None) and 80 (what="XXpointsXX") in the messages.
    with pytest.raises(InvalidInputError, match=r"^segmentation\.selected must be a list of feature ids, got a string"):
        Segmentation(selected="2, 4")
    with pytest.raises(InvalidInputError, match=r"^segmentation\.seeds must be a list of points, got a number \(3\)"):
        Segmentation(seeds=3)


def test_a_truncated_session_file_says_how_to_get_it_back(tmp_path):
    # Kills load_session 20 (the damaged-file hint).
    path = save_session(Session(source=_source(tmp_path / "scan.nrrd")), tmp_path / "fish.unwind.json")
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    with pytest.raises(InvalidInputError, match=r"restore it from a backup or from version control\)"):
        load_session(path)


def test_a_migration_that_loses_the_version_is_a_bug_not_a_loop(tmp_path, monkeypatch):
    # A migration step whose result has no integer schema_version must stop the upgrade with a RuntimeError.
    # Kills _upgrade 40 ('and' for 'or': None <= 0 raised a TypeError; an integer that does not advance looped).
    d = Session(source=_source(tmp_path / "scan.nrrd")).to_dict()
    d["schema_version"] = 1
    monkeypatch.setattr(S, "_MIGRATIONS", {1: lambda old: {k: v for k, v in old.items() if k != "schema_version"}})
    with pytest.raises(RuntimeError, match=r"migration from schema 1 did not advance the version \(None\)"):
        Session.from_dict(d)


def test_an_nrrd_header_is_read_no_further_than_16_mib(tmp_path):
    # A header whose 'data file' line comes after 16 MiB of comments: the reader stops at 16 MiB, so the file is
    # hashed alone (the plain sha256 of its bytes), and the data file it names past the limit is not asked for.
    # Kills _nrrd_data_files 20 (limit 16 * 3**20: the missing data file was required).
    comment = b"#" + b"x" * 1022 + b"\n"  # 1 KiB a line
    data = b"NRRD0004\n" + comment * (16 * 1024 + 1) + b"data file: missing.raw\n\n"
    path = tmp_path / "long.nhdr"
    path.write_bytes(data)
    assert checksum(path) == "sha256:" + hashlib.sha256(data).hexdigest()


def test_an_nrrd_pattern_of_step_0_is_refused_with_the_fix(tmp_path):
    # Kills _nrrd_data_files 80 (the "step 0" reason) and 100 (the hint).
    path = tmp_path / "slices.nhdr"
    path.write_bytes(b"NRRD0004\ntype: uint8\ndata file: s%03d.raw 1 3 0\n\n")
    with pytest.raises(InvalidInputError, match=r"cannot expand the data file pattern 's%03d\.raw 1 3 0' \(step 0\); "
                                                r"fix the header's 'data file' field$"):
        checksum(path)


def test_a_session_needs_a_source_and_a_text_software_name(tmp_path):
    # Kills Session.__post_init__ 20 (source=None accepted) and 40 (the field's name in the message).
    with pytest.raises(InvalidInputError, match=r"^session\.source must be a SourceInfo, got NoneType$"):
        Session(source=None)
    with pytest.raises(InvalidInputError, match=r"^software\.name must be a string, got a number \(3\)$"):
        Session(source=_source(tmp_path / "scan.nrrd"), software=3)


def test_source_spacing_and_unit_of_the_wrong_kind_name_their_field():
    # Kills SourceInfo.__post_init__ 80 (the spacing's field name) and 120 (the unit's, inside "source.unit: ...").
    with pytest.raises(InvalidInputError, match=r"^source\.spacing must be a list of numbers, got a number \(1\.0\)$"):
        SourceInfo(path="/scan.tif", shape=(2, 3, 4), dtype="uint8", spacing=1.0)
    with pytest.raises(InvalidInputError, match=r"^source\.unit: source\.unit must be a string, got a number \(5\)$"):
        SourceInfo(path="/scan.tif", shape=(2, 3, 4), dtype="uint8", spacing=(1.0, 1.0, 1.0), unit=5)


def test_a_file_that_grows_while_it_is_hashed_is_refused_with_the_advice(tmp_path):
    # 10 bytes when listed, 15 when read: the checksum is refused. Kills _digest_iter 60 (the advice upper-cased).
    f = tmp_path / "growing.bin"
    f.write_bytes(b"0123456789")
    gen = checksum_iter(f)
    next(gen)  # listed (10 bytes), nothing read yet
    with open(f, "ab") as fh:
        fh.write(b"abcde")
    with pytest.raises(InvalidInputError, match=r"changed while it was being checksummed \(10 bytes, then 15\); is it "
                                                r"still being copied or written\? Try again once it is complete$"):
        for _ in gen:
            pass


def test_a_negative_source_size_names_its_field():
    # Kills SourceInfo.__post_init__ 140 (the field name).
    with pytest.raises(InvalidInputError, match=r"^source\.size must be an integer >= 0, got -1$"):
        SourceInfo(path="/scan.tif", shape=(2, 3, 4), dtype="uint8", spacing=(1.0, 1.0, 1.0), size=-1)


def test_a_spacing_given_by_hand_two_millionths_off_is_a_change(tmp_path):
    # A scan opened with a spacing 2e-6 (relative) off the session's, passed as volume=: the spacing must match to
    # a relative 1e-6, so this is a change. Kills verify_source 60 (rtol dropped: numpy's 1e-5 accepted it).
    path = write_volume(np.arange(24, dtype=np.uint8).reshape(2, 3, 4), tmp_path / "s.nrrd", spacing=(1.0, 1.0, 1.0))
    session = Session(SourceInfo.from_path(path))
    volume = open_volume(path)
    off = volume.with_data(volume.data, spacing=(1.000002, 1.0, 1.0))
    with pytest.raises(SourceChangedError, match=r"its spacing is \(1\.000002, 1\.0, 1\.0\), the session's"):
        verify_source(session, volume=off)
    assert verify_source(session, volume=volume).spacing == (1.0, 1.0, 1.0)
