"""read_points: napari's Points CSV, spreadsheets' exports (BOM, Latin-1, ';' or tab) and hand-written lists.

Every expected array is written by hand (or built with the file, for the generated ones), never computed by the
reader; every refusal is checked with ``match=``: the file's name, the line and what to do.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from napari_unwind.errors import InvalidInputError
from napari_unwind.io.points import read_points


def _write(tmp_path, data, name="points.csv"):
    path = tmp_path / name
    path.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))
    return path


def _read(tmp_path, data, name="points.csv"):
    return read_points(_write(tmp_path, data, name))


# ------------------------------------------------------------------------------------------------------------------
# what is read
# ------------------------------------------------------------------------------------------------------------------
READ = {
    "plain": ("1,2,3\n4.5,-6,7e1\n", [[1, 2, 3], [4.5, -6, 70]]),
    "napari": ("index,axis-0,axis-1,axis-2\n0,10,20,30\n1,11,21,31\n2,12,22,32\n",
               [[10, 20, 30], [11, 21, 31], [12, 22, 32]]),
    # napari writes its index as a float when the table is float (0.0, 1.0): still the index, not axis 0
    "napari float index": ("index,axis-0,axis-1,axis-2\r\n0.0,-3.5,10.0,10.0\r\n1.0,1.0,2.0,3.25\r\n",
                           [[-3.5, 10, 10], [1, 2, 3.25]]),
    "napari with properties": ('index,axis-0,axis-1,axis-2,label,size\n0,1,2,3,"eye, left",4\n1,5,6,7,tail,8\n',
                               [[1, 2, 3], [5, 6, 7]]),
    "columns by name in any order": ("axis-2,index,axis-0,axis-1\n3,0,1,2\n", [[1, 2, 3]]),
    "header case and blanks": (" Index , AXIS-0 , Axis-1 , axis-2 \n0, 1 , 2 ,3\n", [[1, 2, 3]]),
    "map-points scan output": ("# straight -> scan voxels; NaN: outside the cage\naxis0,axis1,axis2\n1,2,3\n",
                               [[1, 2, 3]]),
    "map-points straight output": ("# scan -> straight voxels\ns_index,y_index,x_index\n4,5,6\n", [[4, 5, 6]]),
    "three named columns": ("z,y,x\n1,2,3\n", [[1, 2, 3]]),
    "pandas unnamed index": (",a,b,c\n0,1,2,3\n1,4,5,6\n", [[1, 2, 3], [4, 5, 6]]),
    "semicolon": ("1;2;3\n4;5;6\n", [[1, 2, 3], [4, 5, 6]]),
    "semicolon header": ("x;y;z\n1.5;2.5;3.5\n", [[1.5, 2.5, 3.5]]),
    "tab": ("1\t2\t3\n-4\t5\t6\n", [[1, 2, 3], [-4, 5, 6]]),
    "tab napari": ("index\taxis-0\taxis-1\taxis-2\n0\t1\t2\t3\n", [[1, 2, 3]]),
    "blank lines and comments": ("\n# points\n  \n1,2,3\n\n  # more\n4,5,6\n\n", [[1, 2, 3], [4, 5, 6]]),
    "CRLF": ("x,y,z\r\n1,2,3\r\n", [[1, 2, 3]]),
    "trailing separators": ("1,2,3,,\n4,5,6,\n", [[1, 2, 3], [4, 5, 6]]),
    "quoted numbers": ('"1.5", "2" ,"3"\n', [[1.5, 2, 3]]),
    "blanks around cells": ("  1 ,  2 , 3  \n", [[1, 2, 3]]),
    "negative first value": ("-3,10,10\n", [[-3, 10, 10]]),
    "leading dot and plus": ("-.5,+.25,1.\n", [[-0.5, 0.25, 1]]),
    "no final newline": ("1,2,3", [[1, 2, 3]]),
    "BOM": ("\ufeffaxis-0,axis-1,axis-2\n1,2,3\n4,5,6\n", [[1, 2, 3], [4, 5, 6]]),
    "BOM no header": ("\ufeff1,2,3\n4,5,6\n", [[1, 2, 3], [4, 5, 6]]),
    "BOM napari": ("\ufeffindex,axis-0,axis-1,axis-2\n0,1,2,3\n1,4,5,6\n", [[1, 2, 3], [4, 5, 6]]),
    "UTF-8 header": ("Température,Höhe,Länge\n1,2,3\n", [[1, 2, 3]]),
    "Latin-1 header": ("Température;Höhe;Länge\n1;2;3\n".encode("latin-1"), [[1, 2, 3]]),
    "Latin-1 comment": ("# mesuré à 20 °C\n1,2,3\n".encode("latin-1"), [[1, 2, 3]]),
}


@pytest.mark.parametrize("name", list(READ))
def test_reads(tmp_path, name):
    data, expected = READ[name]
    got = _read(tmp_path, data)
    assert got.dtype == np.float64 and got.shape == (len(expected), 3)
    np.testing.assert_array_equal(got, np.array(expected, dtype=float))


def test_accepts_str_and_pathlike(tmp_path):
    path = _write(tmp_path, "1,2,3\n")
    np.testing.assert_array_equal(read_points(str(path)), [[1.0, 2.0, 3.0]])


def test_a_file_napari_itself_wrote(tmp_path):
    """The CSV napari's own Points writer saves (index column, axis-N names, its properties, CRLF lines)."""
    pytest.importorskip("napari")
    from napari_builtins.io import napari_write_points

    data = np.array([[-3.5, 10.0, 10.0], [1.0, 2.0, 3.25], [0.0, 0.0, 0.0], [7.0, 8.0, 9.0], [100.5, 2e-3, 6.0],
                     [1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [3.0, 3.0, 3.0]])
    expected = data.copy()  # the file holds these coordinates: napari writes what its layer holds
    plain = napari_write_points(str(tmp_path / "plain.csv"), data, {})
    text = (tmp_path / "plain.csv").read_text()
    assert text.splitlines()[0] == "index,axis-0,axis-1,axis-2", text  # napari's format, as the reader expects
    np.testing.assert_array_equal(read_points(plain), expected)
    with_props = napari_write_points(str(tmp_path / "props.csv"), data,
                                     {"properties": {"kind": np.array(["eye, left", "fin"] * 4),
                                                     "size": np.arange(8.0)}})
    np.testing.assert_array_equal(read_points(with_props), expected)


def test_a_file_napari_layer_saved(tmp_path):
    """The Points layer's own File > Save Selected Layers path: napari's builtin writer, found through npe2."""
    napari = pytest.importorskip("napari")
    npe2 = pytest.importorskip("npe2")
    npe2.PluginManager.instance().discover()  # what napari's viewer does at start; a bare import does not
    data = np.array([[-3.0, 10.0, 10.0], [4.0, 5.0, 6.5], [0.0, -0.25, 1e3]])
    path = tmp_path / "layer.csv"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        written = napari.layers.Points(data).save(str(path), plugin="napari")
    assert written == [str(path)] and path.read_text().splitlines()[0] == "index,axis-0,axis-1,axis-2"
    np.testing.assert_array_equal(read_points(path), [[-3.0, 10.0, 10.0], [4.0, 5.0, 6.5], [0.0, -0.25, 1000.0]])


# ------------------------------------------------------------------------------------------------------------------
# what is refused, in one line
# ------------------------------------------------------------------------------------------------------------------
REFUSED = {
    "typo in the first row is no header": ("1,2,3x\n4,5,6\n", r"points\.csv line 1: axis 2 is '3x', not a number"),
    "one word among numbers": ("x,2,3\n4,5,6\n", r"points\.csv line 1: axis 0 is 'x', not a number"),
    "typo in a later row": ("1,2,3\n4,five,6\n", r"points\.csv line 2: axis 1 is 'five', not a number"),
    "typo after a header": ("axis-0,axis-1,axis-2\n1,2,3\n\n4,5,6o\n",
                            r"points\.csv line 4: column 'axis-2' is '6o', not a number"),
    "European decimals": ("1,5;2,5;3,5\n", r"points\.csv line 1: axis 0 is '1,5', a comma as the decimal mark; use "
                                           r"'\.' as the decimal mark"),
    "European decimals later": ("x;y;z\n1.5;2.5;3.5\n1;2,75;3\n",
                                r"line 3: column 'y' is '2,75', a comma as the decimal mark; use '\.'"),
    "European decimals in a tab file": ("1\t2\t-0,5\n", r"line 1: axis 2 is '-0,5', a comma as the decimal mark"),
    "European decimals with commas": ("1,5,2,5,3,5\n", r"line 1: 6 comma-separated columns, expected 3 .*if ',' is "
                                                       r"the decimal mark, use '\.' instead"),
    "index column without header": ("0,1,2,3\n1,4,5,6\n", r"line 1: 4 comma-separated columns, expected 3 .*needs "
                                                          r"its header line \(index,axis-0,axis-1,axis-2\)"),
    "two columns": ("1,2\n", r"line 1: 2 comma-separated columns, expected 3"),
    "a short row": ("1,2,3\n4,5\n", r"line 2: 2 comma-separated columns, expected 3"),
    "a long row": ("1,2,3\n4,5,6,7\n", r"line 2: 4 comma-separated columns, expected 3"),
    "short row after header": ("index,axis-0,axis-1,axis-2\n0,1,2\n",
                               r"line 2: 3 comma-separated columns, expected 4 as the header \(line 1\)"),
    "long row after header": ("x,y,z\n1,2,3,4\n", r"line 2: 4 comma-separated columns, expected 3 as the header"),
    "mixed separators": ("1;2;3\n4,5,6\n", r"line 2: 1 semicolon-separated column, expected 3 .*separator"),
    "space separated": ("1 2 3\n", r"line 1: 1 comma-separated column, expected 3"),
    "non-ASCII digits": ("\u0661,2,3\n", r"line 1: axis 0 is '\u0661', not a number"),
    "underscores": ("1_000,2,3\n", r"line 1: axis 0 is '1_000', not a number"),
    "empty cell": ("1,,3\n", r"line 1: axis 1 is empty"),
    "nan": ("1,2,3\n4,nan,6\n", r"line 2: axis 1 is 'nan'; every coordinate must be a finite number"),
    "inf": ("x,y,z\n-inf,1,2\n", r"line 2: column 'x' is '-inf'; every coordinate must be a finite number"),
    "overflow": ("1e999,1,2\n", r"line 1: axis 0 is '1e999'; every coordinate must be a finite number"),
    "a nan header is data": ("nan,nan,nan\n", r"line 1: axis 0 is 'nan'; every coordinate must be a finite"),
    "no letters is no header": ("-,-,-\n1,2,3\n", r"line 1: axis 0 is '-', not a number"),
    "empty file": ("", r"points\.csv is empty"),
    "blank file": ("\n  \n\n", r"points\.csv is empty"),
    "comments only": ("# nothing\n", r"points\.csv is empty"),
    "BOM only": ("\ufeff", r"points\.csv is empty"),
    "header only": ("index,axis-0,axis-1,axis-2\n", r"points\.csv holds a header but no point"),
    "2D napari points": ("index,axis-0,axis-1\n0,1,2\n", r"line 1: the header names napari axes axis-0, axis-1; "
                                                         r"points of 3 dimensions are needed"),
    "4D napari points": ("index,axis-0,axis-1,axis-2,axis-3\n0,1,2,3,4\n",
                         r"napari axes axis-0, axis-1, axis-2, axis-3; points of 3 dimensions"),
    "unknown 4 columns": ("a,b,c,d\n1,2,3,4\n", r"line 1: cannot tell the 3 coordinate columns among the header's "
                                                r"'a', 'b', 'c', 'd'; name them axis-0,axis-1,axis-2"),
    "named twice": ("axis-0,axis-1,axis-2,axis-1\n1,2,3,4\n", r"names column 'axis-1' twice"),
    "binary": (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", r"points\.csv is not a text file \(it holds NUL bytes"),
    "UTF-16": ("x,y,z\n1,2,3\n".encode("utf-16"), r"points\.csv is not a text file"),
}


@pytest.mark.parametrize("name", list(REFUSED))
def test_refuses_in_one_line(tmp_path, name):
    data, match = REFUSED[name]
    with pytest.raises(InvalidInputError, match=match) as info:
        _read(tmp_path, data)
    message = str(info.value)
    assert "\n" not in message and message.startswith("points.csv")


def test_a_missing_file_is_an_os_error(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_points(tmp_path / "missing.csv")
    with pytest.raises(OSError):
        read_points(tmp_path)


# ------------------------------------------------------------------------------------------------------------------
# 200 generated files, their points known by construction
# ------------------------------------------------------------------------------------------------------------------
def _generated(seed: int):
    """A points file's bytes and the points it holds, drawn at random: separator, BOM, Latin-1, header, index
    column, napari property columns, comments, blank lines, CRLF, negative values, quoting, exponents."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 30))
    # values written exactly: whole numbers over 10**d (a correctly rounded division) are the floats nearest to
    # their decimal text, whichever way it is written
    points = rng.integers(-500_0000, 500_0000, (n, 3)) / 10.0 ** int(rng.integers(0, 5))
    points[rng.random((n, 3)) < 0.1] = 0.0
    if rng.random() < 0.3:
        points[:, 0] = -np.abs(points[:, 0]) - 1  # a negative first value on every row
    sep = str(rng.choice([",", ";", "\t"]))
    encoding = str(rng.choice(["utf-8", "utf-8-sig", "latin-1"]))
    header = str(rng.choice(["none", "napari", "napari-props", "axis", "named", "named-index", "straight"]))
    index = header in ("napari", "napari-props", "named-index")
    fmt = str(rng.choice(["repr", "g", "e", "quoted"]))

    def number(v: float) -> str:
        text = {"repr": repr, "g": lambda x: f"{x:.10g}", "e": lambda x: f"{x:.12e}", "quoted": repr}[fmt](float(v))
        return f'"{text}"' if fmt == "quoted" else text

    order = [0, 1, 2]
    if header in ("napari", "napari-props", "axis", "straight") and rng.random() < 0.3:
        order = list(rng.permutation(3))  # named columns in another order
    names = {"napari": "axis-{}", "napari-props": "axis-{}", "axis": "axis{}",
             "straight": ("s_index", "y_index", "x_index")}
    lines = []
    if rng.random() < 0.3:
        lines.append("# points saved at 20 °C, mesuré")
    if header != "none":
        if header in ("named", "named-index"):
            cols = [str(rng.choice(["Température", "Höhe", "Länge", "z", "y", "x", "Zeile"])) + str(i)
                    for i in range(3)]
        elif header == "straight":
            cols = [names["straight"][i] for i in order]
        else:
            cols = [names[header].format(i) for i in order]
        if index:
            cols = ["index"] + cols
        if header == "napari-props":
            cols += ["label", "size"]
        lines.append(sep.join(cols))
    for k, p in enumerate(points):
        cells = [number(p[i]) for i in order] if header != "named" and header != "named-index" else \
            [number(v) for v in p]
        if index:
            cells = [str(k) if rng.random() < 0.5 else f"{k}.0"] + cells
        if header == "napari-props":
            cells += [str(rng.choice(["eye", "fin", '"a, b"', "Température"])), number(rng.integers(0, 9))]
        if rng.random() < 0.1:
            cells = [f" {c} " for c in cells]
        lines.append(sep.join(cells))
        if rng.random() < 0.05:
            lines.append("")
    eol = "\r\n" if rng.random() < 0.3 else "\n"
    text = eol.join(lines) + (eol if rng.random() < 0.8 else "")
    return text.encode(encoding), points


@pytest.mark.parametrize("seed", range(200))
def test_generated_files(tmp_path, seed):
    data, expected = _generated(seed)
    got = _read(tmp_path, data)
    np.testing.assert_array_equal(got, expected)
