"""``unwind map-points`` with point files, ``--at`` or both, and coordinates whose first value is negative
(``--head=-3,10,10`` and ``--head -3,10,10``) for every command that takes a point."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import run_unwind
from napari_unwind.cli import build_parser, main

# points inside the phantom fish's cage (its centreline, seed 2), and one far outside (a NaN row)
PTS = [[44.25, 21.5, 45.0], [81.0, 23.5, 32.0], [118.5, 21.75, 18.5]]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from conftest import fish_case

    return fish_case(tmp_path_factory.mktemp("points_cli"))[2]


def _map(capsys, *args) -> tuple[int, np.ndarray | None, str]:
    """``unwind map-points ARGS`` in this process: status, the mapped points, stderr."""
    code = main(["map-points", *map(str, args)])
    out, err = capsys.readouterr()
    rows = [r for r in out.splitlines() if r and not r.startswith("#")][1:]
    return code, (np.array([[float(c) for c in r.split(",")] for r in rows]) if code == 0 else None), err


def _at(points) -> list[str]:
    return [a for p in points for a in ("--at", ",".join(repr(float(v)) for v in p))]


@pytest.fixture(scope="module")
def reference(session):
    """The mapping of PTS through --at: what every file holding PTS must give."""
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["map-points", "--session", str(session), *_at(PTS)]) == 0
    rows = [r for r in buf.getvalue().splitlines() if r and not r.startswith("#")][1:]
    got = np.array([[float(c) for c in r.split(",")] for r in rows])
    assert got.shape == (3, 3) and np.isfinite(got).all()  # the points are inside the cage
    return got


FILES = {
    "napari": b"index,axis-0,axis-1,axis-2\r\n0.0,44.25,21.5,45.0\r\n1.0,81.0,23.5,32.0\r\n2.0,118.5,21.75,18.5\r\n",
    "napari with BOM": "\ufeffindex,axis-0,axis-1,axis-2\n0,44.25,21.5,45\n1,81,23.5,32\n2,118.5,21.75,18.5\n".encode(),
    "Excel CSV UTF-8": "\ufeff44.25,21.5,45\n81,23.5,32\n118.5,21.75,18.5\n".encode(),
    "Latin-1 semicolons": "Tête;Höhe;Länge\n44.25;21.5;45\n81;23.5;32\n118.5;21.75;18.5\n".encode("latin-1"),
    "tabs": b"44.25\t21.5\t45\n81\t23.5\t32\n118.5\t21.75\t18.5\n",
}


@pytest.mark.parametrize("name", list(FILES))
def test_map_points_reads_the_file(session, reference, capsys, tmp_path, name):
    path = tmp_path / "points.csv"
    path.write_bytes(FILES[name])
    code, got, err = _map(capsys, path, "--session", session)
    assert code == 0, err
    np.testing.assert_allclose(got, reference, rtol=0, atol=1e-5)  # the output's 6 significant digits


REFUSED = {
    "typo in the first row": (b"52,19.5,38.25x\n80,21,40\n", r"points\.csv line 1: axis 2 is '38\.25x', not a number"),
    "European decimals": (b"52;19,5;38,25\n", r"points\.csv line 1: axis 1 is '19,5', a comma as the decimal mark; "
                                              r"use '\.' as the decimal mark"),
    "binary": (b"\x00\x01\x02PK", r"points\.csv is not a text file"),
    "index without header": (b"0,52,19.5,38.25\n", r"points\.csv line 1: 4 comma-separated columns, expected 3"),
    "no points": (b"index,axis-0,axis-1,axis-2\n", r"points\.csv holds a header but no point"),
    "non-finite": (b"52,inf,3\n", r"points\.csv line 1: axis 1 is 'inf'; every coordinate must be a finite number"),
}


@pytest.mark.parametrize("name", list(REFUSED))
def test_map_points_refuses_a_bad_file_in_one_line(session, capsys, tmp_path, name):
    import re

    data, match = REFUSED[name]
    path = tmp_path / "points.csv"
    path.write_bytes(data)
    out_csv = tmp_path / "out.csv"
    code, _, err = _map(capsys, path, "--session", session, "-o", out_csv)
    assert code == 1 and re.search(match, err), err
    assert err.count("\n") == 1 and err.startswith("unwind: error: ") and "Traceback" not in err
    assert not out_csv.exists()


def test_at_and_a_file_together_are_refused(session, capsys, tmp_path):
    path = tmp_path / "points.csv"
    path.write_bytes(FILES["napari"])
    out_csv = tmp_path / "out.csv"
    code, _, err = _map(capsys, path, "--session", session, *_at(PTS[:1]), "-o", out_csv)
    assert code == 1 and "give points with --at or a file, not both" in err, err
    assert err.count("\n") == 1 and not out_csv.exists()
    code, _, err = _map(capsys, "--session", session, "-o", out_csv)
    assert code == 1 and "give points with --at" in err


@pytest.mark.parametrize("spelling", ["joined", "apart"])
def test_map_points_at_with_a_negative_first_value(session, reference, capsys, spelling):
    """--at=-3,10,10 and --at -3,10,10 are the same point (outside the cage: a NaN row), not an unknown option."""
    far, inside = "-3,10,10", ",".join(repr(v) for v in PTS[0])
    at = [f"--at={far}"] if spelling == "joined" else ["--at", far]
    code, got, err = _map(capsys, "--session", session, *at, "--at", inside)
    assert code == 0, err
    assert np.isnan(got[0]).all()
    np.testing.assert_allclose(got[1], reference[0], rtol=0, atol=1e-5)


def test_a_negative_point_through_the_real_command_line(session, reference):
    """The installed ``unwind`` (a separate process, argv as a shell passes it)."""
    code, out, err = run_unwind("map-points", "--session", session, "--at", "-3,10,10", "--at=-1.5,-2,4e1",
                                "--at", ",".join(repr(v) for v in PTS[0]))
    assert code == 0, err
    rows = [r for r in out.splitlines() if r and not r.startswith("#")][1:]
    assert rows[:2] == ["nan,nan,nan", "nan,nan,nan"]
    np.testing.assert_allclose([float(c) for c in rows[2].split(",")], reference[0], rtol=0, atol=1e-5)


# every command taking a point, and the option: both spellings must parse to the same negative point
POINT_OPTIONS = [
    (["skeleton", "m.zarr", "-o", "s.unwind.json"], "--head", "head"),
    (["skeleton", "m.zarr", "-o", "s.unwind.json"], "--tail", "tail"),
    (["run", "in.zarr", "-o", "out.zarr"], "--head", "head"),
    (["run", "in.zarr", "-o", "out.zarr"], "--tail", "tail"),
    (["run", "in.zarr", "-o", "out.zarr"], "--select", "select"),
    (["submit", "in.zarr", "--server", "localhost:1"], "--head", "head"),
    (["submit", "in.zarr", "--server", "localhost:1"], "--tail", "tail"),
    (["submit", "in.zarr", "--server", "localhost:1"], "--select", "select"),
    (["select", "labels.zarr", "-o", "mask.zarr"], "--at", "at"),
    (["map-points", "--session", "s.unwind.json"], "--at", "at"),
]


@pytest.mark.parametrize("command,option,dest", POINT_OPTIONS, ids=[f"{c[0]} {o}" for c, o, _ in POINT_OPTIONS])
@pytest.mark.parametrize("value,expected", [("-3,10,10", (-3.0, 10.0, 10.0)), ("-1.5,-2,4e1", (-1.5, -2.0, 40.0)),
                                            ("-.5,0,-0", (-0.5, 0.0, 0.0)), ("-7", (-7.0, -7.0, -7.0))])
def test_negative_first_value_both_spellings(command, option, dest, value, expected):
    parser = build_parser()
    for argv in ([*command, f"{option}={value}"], [*command, option, value]):
        got = getattr(parser.parse_args(argv), dest)
        assert (got[0] if isinstance(got, list) else got) == expected, argv


def test_chain_takes_negative_points():
    args = build_parser().parse_args(["skeleton", "m.zarr", "-o", "s.unwind.json", "--chain", "-1,2,3", "-4,5,6"])
    assert args.chain == [[(-1.0, 2.0, 3.0), (-4.0, 5.0, 6.0)]]


@pytest.mark.parametrize("argv,match", [
    (["map-points", "--session", "s.json", "--at", "-3,x,10"], "expected one argument"),  # not a point: an option
    (["map-points", "--session", "s.json", "--at", "-3,10"], "expected 1 or 3 comma-separated numbers"),
    (["skeleton", "m.zarr", "-o", "s.unwind.json", "--head", "-q"], "expected one argument"),  # an option stays one
])
def test_what_is_still_an_option_or_a_mistake(capsys, argv, match):
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert match in err and err.count("\n") == 1
