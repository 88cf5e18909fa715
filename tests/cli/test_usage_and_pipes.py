"""Usage errors, closed pipes, progress in a log, and ``--max-output`` (issue 9)."""

import argparse
import os
import subprocess

import numpy as np
import pytest
from cli_support import PROGRESS_LINE, UNWIND, demo_outputs, leftovers, one_error_line, run, run_main

from napari_unwind import cli
from napari_unwind.errors import UnwindError
from napari_unwind.io import write_volume


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return demo_outputs(tmp_path_factory)


# ------------------------------------------------------------------------------------------------------------------
# usage errors: exit status 1, one line, as the README says of every error
# ------------------------------------------------------------------------------------------------------------------
USAGE = [
    ([], "unwind --help"),
    (["frobnicate"], "unwind --help"),
    (["info"], "unwind info --help"),
    (["straighten", "x.zarr"], "unwind straighten --help"),  # --session and -o missing
    (["straighten", "x.zarr", "--session", "s.json", "-o", "y.zarr", "--order", "2"], "unwind straighten --help"),
    (["straighten", "x.zarr", "--session", "s.json", "-o", "y.zarr", "--spacing", "nan"], "finite"),
    (["straighten", "x.zarr", "--session", "s.json", "-o", "y.zarr", "--pad", "-3"], ">= 0"),
    (["straighten", "x.zarr", "--session", "s.json", "-o", "y.zarr", "--max-output", "lots"], "500G"),
    (["map-points", "--session", "s.json", "--at", "1,inf,2"], "finite"),
    (["import", "a.tif", "b.zarr", "--spacing", "0"], "> 0"),
    (["segment", "a.zarr", "-o", "l.zarr", "--features", "0"], "from 1 to 100"),
    (["demo", "--fish", "many"], "whole number"),
    (["convert", "a.zarr", "b.zarr", "--bogus"], "unrecognized arguments: --bogus"),
]


@pytest.mark.parametrize("argv, says", USAGE)
def test_usage_errors_exit_1_with_one_line(argv, says, capsys):
    code, out, err = run_main(argv, capsys)
    assert code == 1 and out == ""
    assert one_error_line(err) and says in err, err
    assert err.rstrip().endswith("--help") and "usage:" not in err


def test_usage_error_as_a_user_sees_it():
    code, out, err = run("straighten", "x.zarr", "--order", "2")
    assert code == 1 and out == "" and one_error_line(err), err
    assert err.startswith("unwind: error: ") and err.rstrip().endswith("see unwind straighten --help")


def test_help_documents_the_exit_status():
    parser = cli.build_parser()
    for text in (parser.format_help(), parser._subparsers._group_actions[0].choices["straighten"].format_help()):
        text = " ".join(text.split())
        assert "exit status: 0 success; 1 an error, a wrong option included" in text
        assert "130 interrupted" in text and "143 terminated (SIGTERM)" in text


# ------------------------------------------------------------------------------------------------------------------
# a closed pipe ends quietly
# ------------------------------------------------------------------------------------------------------------------
def test_a_closed_pipe_ends_quietly(demo):
    # the reader is gone before unwind writes a byte (as with `unwind info X | head -0`)
    r, w = os.pipe()
    os.close(r)
    p = subprocess.run([str(UNWIND), "info", str(demo.tank)], stdout=w, stderr=subprocess.PIPE, text=True)
    os.close(w)
    assert p.returncode == 0 and p.stderr == "", p.stderr


# ------------------------------------------------------------------------------------------------------------------
# progress written to a log: one line per stage, with its time
# ------------------------------------------------------------------------------------------------------------------
def test_progress_into_a_log_is_one_line_per_stage(tmp_path):
    src = write_volume(np.arange(48 * 20 * 20, dtype=np.uint16).reshape(48, 20, 20), tmp_path / "s.zarr", chunks=8)
    log = tmp_path / "log.txt"
    with open(log, "w") as fh:
        p = subprocess.run([str(UNWIND), "import", str(src), str(tmp_path / "a.zarr"), "--chunks", "8",
                            "--max-side", "8"], stdout=subprocess.PIPE, stderr=fh, text=True)
    assert p.returncode == 0
    text = log.read_text()
    lines = text.splitlines()
    assert "\r" not in text and lines, text
    assert all(PROGRESS_LINE.match(ln) for ln in lines), lines
    stages = [ln.split(":")[0] for ln in lines]
    assert len(stages) == len(set(stages)) and any(s.startswith("write") for s in stages), lines
    assert all("100% (" in ln for ln in lines)  # every stage finished


def test_progress_printer_one_line_per_stage(capsys):
    from napari_unwind.progress import Progress, progress_bar

    callback, close = progress_bar()  # captured stderr: not a terminal
    for stage, n in (("read", 3), ("write", 40)):
        for i in range(1, n + 1):
            callback(Progress(stage, i, n, f"step {i}"))
    close()
    close()  # twice is harmless
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("read: 100% (3/3) in ") and lines[1].startswith("write: 100% (40/40) in ")
    assert all(PROGRESS_LINE.match(ln) for ln in lines)
    # a stage followed by another is over, whatever it counted (the skeleton's stages report 0/1 then move on);
    # an unknown total counts steps; the last stage, unfinished, says it stopped
    callback, close = progress_bar()
    callback(Progress("verify", 2, 5))
    callback(Progress("scan", 7, 0))
    callback(Progress("write", 1, 4))
    close()
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith("verify: done in ") and "stopped" not in lines[0]
    assert lines[1].startswith("scan: 7 steps in ")
    assert lines[2].startswith("write: 25% (1/4) in ") and lines[2].endswith(", stopped")
    assert all(PROGRESS_LINE.match(ln) for ln in lines)
    quiet_cb, quiet_close = progress_bar(quiet=True)
    quiet_cb(Progress("x", 1, 1))
    quiet_close()
    assert capsys.readouterr().err == ""


# ------------------------------------------------------------------------------------------------------------------
# --max-output SIZE
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("text, expected", [
    ("500G", 500 * 1024 ** 3), ("2T", 2 * 1024 ** 4), ("1.5GiB", int(1.5 * 1024 ** 3)), ("800MB", 800 * 10 ** 6),
    ("1000000", 10 ** 6), ("12k", 12 * 1024), ("3 tb", 3 * 10 ** 12), ("7B", 7), ("1e3", 1000), ("none", None),
    ("NONE", None), (".5K", 512),
])
def test_parse_size(text, expected):
    assert cli.parse_size(text) == expected


@pytest.mark.parametrize("text", ["", "G", "-1G", "0", "0.1", "1.5.2G", "5X", "nan", "inf", "1e400", "lots", "5 G B"])
def test_parse_size_refuses(text):
    with pytest.raises(argparse.ArgumentTypeError, match="expected a size"):
        cli.parse_size(text)


def test_max_output_is_passed_to_the_warp(monkeypatch, demo, tmp_path, capsys):
    """--max-output reaches export_iter as max_output (bytes; None for none); without it the library's default."""
    import napari_unwind.warp as warp

    seen = []

    def fake_export_iter(*a, **kw):
        seen.append(kw.get("max_output", "default"))
        raise UnwindError("stop here")
        yield  # pragma: no cover

    monkeypatch.setattr(warp, "export_iter", fake_export_iter)
    base = ["straighten", demo.tank, "--session", demo.session, "--no-verify", "-q"]
    for extra, want in ((["--max-output", "2T"], 2 * 1024 ** 4), (["--max-output", "none"], None), ([], "default")):
        code, _, err = run_main(base + ["-o", tmp_path / "o.zarr"] + extra, capsys)
        assert code == 1 and "stop here" in err
        assert seen[-1] == want


def test_max_output_refuses_a_huge_output_at_once(demo, tmp_path, capsys):
    import time

    import napari_unwind.warp as warp

    if not hasattr(warp, "DEFAULT_MAX_OUTPUT"):
        pytest.skip("napari_unwind.warp has no DEFAULT_MAX_OUTPUT yet (the warp's output size check)")
    args = ["straighten", demo.tank, "--session", demo.session, "-o", tmp_path / "huge.zarr", "--spacing", "1e-6",
            "-q"]
    # the work before the refusal, timed in-process (a loaded machine's interpreter start aside)
    t0 = time.perf_counter()
    code, _, err = run_main(args, capsys)
    assert time.perf_counter() - t0 < 10
    assert code == 1 and one_error_line(err) and any(ch.isdigit() for ch in err), err
    # as a user runs it (it once ran until the kernel killed it, 24 GB after 263 s)
    code, _, err = run(*args, timeout=120)
    assert code == 1 and one_error_line(err) and any(ch.isdigit() for ch in err), err
    assert not (tmp_path / "huge.zarr").exists() and leftovers(tmp_path) == []
    # the fish is about 200 KiB: a limit of 1 KiB refuses it, naming numbers
    code, _, err = run_main(args[:-3] + ["-o", tmp_path / "small.zarr", "-q", "--max-output", "1K"], capsys)
    assert code == 1 and one_error_line(err) and any(ch.isdigit() for ch in err), err
    assert not (tmp_path / "small.zarr").exists()


def test_other_os_errors_stay_errors(capsys, tmp_path):
    """Only a closed pipe is quiet: every other OSError is still one error line."""
    code, _, err = run_main(["info", tmp_path / "missing.zarr"], capsys)
    assert code == 1 and "does not exist" in err and one_error_line(err)


# ------------------------------------------------------------------------------------------------------------------
# a library's warning is one line too
# ------------------------------------------------------------------------------------------------------------------
def test_a_library_warning_is_one_warning_line(tmp_path, capsys):
    # a numbered stack with a slice missing: the reader warns that distances along axis 0 are wrong there
    write_volume(np.arange(6 * 8 * 8, dtype=np.uint8).reshape(6, 8, 8), tmp_path / "s" / "z_{:03d}.png")
    (tmp_path / "s" / "z_003.png").unlink()
    code, out, err = run_main(["info", tmp_path / "s"], capsys)
    assert code == 0 and "shape:" in out
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("unwind: warning: ") and "missing" in lines[0], err
