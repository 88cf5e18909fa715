"""Read a file of 3D points: napari's Points CSV, a spreadsheet's export or a hand-written list.

The rules, in the order they are applied (every refusal is one
:class:`~napari_unwind.errors.InvalidInputError` line naming the file, the line and what to do):

1. **Encoding.** A file holding a NUL byte is binary and refused. Otherwise it is read as UTF-8 (a byte-order
   mark, as Excel's "CSV UTF-8" writes, is dropped); bytes that are not UTF-8 are read as Latin-1.
2. **Lines.** Blank lines and lines whose first non-blank character is ``#`` are skipped. Line numbers in
   messages count every physical line from 1, as an editor or a spreadsheet's row numbers do.
3. **Separator.** One per file, taken from the first remaining line: tab if it holds one, else semicolon if it
   holds one, else comma. Blanks around a cell are ignored; a cell may be quoted (``"1.5"``).
4. **Header.** The first remaining line is a header if and only if none of its cells is a number (``nan`` and
   ``inf`` count as numbers) and it holds at least one letter. A first line with numbers and one bad cell is data
   with a mistake (refused, naming the line), never a header.
5. **Columns.** With a header, the coordinates are the columns named (case and surrounding blanks ignored)
   ``axis-0, axis-1, axis-2`` (napari's Points CSV: ``index,axis-0,axis-1,axis-2`` followed by any property
   columns), else ``axis0, axis1, axis2`` or ``s_index, y_index, x_index`` (what ``unwind map-points`` writes),
   in any order; other columns (``index``, properties) are ignored. Without one of these name sets, columns named
   ``index`` or with no name are ignored and exactly 3 columns must remain, read in their order. napari points of
   2 or 4 dimensions (``axis-3``...) are refused. Without a header, every line holds exactly 3 numbers: a 4th
   column (napari's ``index``) is refused, since a number column cannot be told from a coordinate without its
   name. Empty cells at the end of a line (left by a spreadsheet) are ignored.
6. **Numbers.** Decimal numbers with ``.`` as the decimal mark, optionally with an exponent (``1e3``). A comma
   used as the decimal mark (``1,5`` in a semicolon- or tab-separated file) is refused with a hint. Coordinates
   must be finite (no ``nan`` or ``inf``).
7. A file with no point is refused.

Coordinates are full-resolution voxel indices in array order (axis 0, 1, 2), as napari shows them.
"""

from __future__ import annotations

import csv
import os
import re

import numpy as np

from ..errors import InvalidInputError

__all__ = ["read_points", "POINT_COLUMN_NAMES"]

#: The header names that pick the coordinate columns, by name, in the order tried.
POINT_COLUMN_NAMES: tuple[tuple[str, str, str], ...] = (
    ("axis-0", "axis-1", "axis-2"),  # napari's Points layer CSV
    ("axis0", "axis1", "axis2"),  # unwind map-points --to scan
    ("s_index", "y_index", "x_index"),  # unwind map-points --to straight
)

_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?", re.ASCII)
_NON_FINITE = re.compile(r"[-+]?(?:nan|inf|infinity)", re.IGNORECASE)
_COMMA_DECIMAL = re.compile(r"[-+]?\d*,\d+(?:[eE][-+]?\d+)?", re.ASCII)
_NAPARI_AXIS = re.compile(r"axis-(\d+)")
_IGNORED = ("index", "")


def _is_number(cell: str) -> bool:
    return bool(_NUMBER.fullmatch(cell) or _NON_FINITE.fullmatch(cell))


def _decode(data: bytes, name: str) -> str:
    if b"\x00" in data:
        raise InvalidInputError(f"{name} is not a text file (it holds NUL bytes: binary, or UTF-16); give a CSV "
                                "of points saved as text (UTF-8)")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def _cells(line: str, sep: str) -> list[str]:
    row = next(csv.reader([line], delimiter=sep, quotechar="\"", skipinitialspace=True), [])
    cells = [c.strip() for c in row]
    while cells and cells[-1] == "":
        cells.pop()
    return cells


def _columns(header: list[str], name: str, lineno: int) -> list[int]:
    """The indices of the 3 coordinate columns named by ``header``."""
    names = [h.strip().lower() for h in header]
    axes = sorted({int(m.group(1)) for n in names if (m := _NAPARI_AXIS.fullmatch(n))})
    if axes and axes != [0, 1, 2]:
        raise InvalidInputError(
            f"{name} line {lineno}: the header names napari axes {', '.join(f'axis-{a}' for a in axes)}; points "
            "of 3 dimensions are needed (axis-0, axis-1, axis-2): save 3D points")
    for triple in POINT_COLUMN_NAMES:
        if all(t in names for t in triple):
            for t in triple:
                if names.count(t) > 1:
                    raise InvalidInputError(f"{name} line {lineno}: the header names column {t!r} twice; name each "
                                            "column once")
            return [names.index(t) for t in triple]
    kept = [i for i, n in enumerate(names) if n not in _IGNORED]
    if len(kept) != 3:
        seen = ", ".join(repr(h) for h in header)
        raise InvalidInputError(
            f"{name} line {lineno}: cannot tell the 3 coordinate columns among the header's {seen}; name them "
            "axis-0,axis-1,axis-2 (napari's Points CSV) or keep only 3 columns (axis 0, 1, 2)")
    return kept


def _value(cell: str, name: str, lineno: int, what: str, sep: str) -> float:
    if _NUMBER.fullmatch(cell):
        value = float(cell)
        if np.isfinite(value):
            return value
    elif not _NON_FINITE.fullmatch(cell):
        if sep != "," and _COMMA_DECIMAL.fullmatch(cell):
            raise InvalidInputError(
                f"{name} line {lineno}: {what} is {cell!r}, a comma as the decimal mark; use '.' as the decimal mark "
                f"(e.g. {cell.replace(',', '.')}): save the CSV with '.' decimals")
        if cell == "":
            raise InvalidInputError(f"{name} line {lineno}: {what} is empty; give 3 numbers on every line")
        raise InvalidInputError(f"{name} line {lineno}: {what} is {cell!r}, not a number; give numbers such as "
                                "12.5 on every line")
    raise InvalidInputError(f"{name} line {lineno}: {what} is {cell!r}; every coordinate must be a finite number")


def read_points(path: str | os.PathLike) -> np.ndarray:
    """Read 3D points from a CSV file: napari's Points CSV, a spreadsheet's export or a plain list.

    Parameters
    ----------
    path : str or os.PathLike
        The file. Comma-, semicolon- or tab-separated; UTF-8 (with or without a byte-order mark) or Latin-1;
        with a header line or none. See the module's documentation for the exact rules.

    Returns
    -------
    points : ndarray of float64, shape (N, 3)
        One row per point, its coordinates in array order (axis 0, 1, 2), N >= 1.

    Raises
    ------
    napari_unwind.errors.InvalidInputError
        The file is binary, empty, holds no point, or a line is malformed: the message is one line naming the
        file, the line and what to do.
    OSError
        The file cannot be read (missing, a folder, no permission).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "points.csv"
    >>> _ = p.write_text("index,axis-0,axis-1,axis-2\\n0,-3,10,10\\n1,4.5,6,7\\n")
    >>> read_points(p)
    array([[-3. , 10. , 10. ],
           [ 4.5,  6. ,  7. ]])
    """
    path = os.fspath(path)
    name = os.path.basename(path) or path
    with open(path, "rb") as f:
        text = _decode(f.read(), name)
    lines = [(n, line) for n, line in enumerate(text.splitlines(), start=1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise InvalidInputError(f"{name} is empty: give one point per line, 3 numbers (axis 0, 1, 2) such as "
                                "12,40.5,33")
    first = lines[0][1]
    sep = "\t" if "\t" in first else ";" if ";" in first else ","
    sep_name = {"\t": "tab", ";": "semicolon", ",": "comma"}[sep]
    header = _cells(first, sep)
    has_header = not any(_is_number(c) for c in header) and any(ch.isalpha() for ch in first)
    if has_header:
        columns = _columns(header, name, lines[0][0])
        width = len(header)
        rows = lines[1:]
        names = [header[i] for i in columns]
    else:
        columns, width, rows = [0, 1, 2], 3, lines
        names = ["axis 0", "axis 1", "axis 2"]
    points = []
    for lineno, line in rows:
        cells = _cells(line, sep)
        if (not has_header and len(cells) != 3) or len(cells) > width or len(cells) <= max(columns):
            if has_header:
                expected = f"{width} as the header (line {lines[0][0]})"
            else:
                expected = "3 (axis 0, 1, 2)"
            hint = ""
            if not has_header and len(cells) == 4:
                hint = "; a napari Points CSV needs its header line (index,axis-0,axis-1,axis-2)"
            elif len(cells) == 1:
                hint = f"; the file's separator is its first line's, {sep_name}: use it on every line"
            elif sep == "," and len(cells) == 2 * len(columns):
                hint = "; if ',' is the decimal mark, use '.' instead"
            got = f"{len(cells)} {sep_name}-separated column{'s' if len(cells) != 1 else ''}"
            raise InvalidInputError(f"{name} line {lineno}: {got}, expected "
                                    f"{expected}{hint}")
        points.append([_value(cells[i], name, lineno, f"column {n!r}" if has_header else n, sep)
                       for i, n in zip(columns, names)])
    if not points:
        raise InvalidInputError(f"{name} holds a header but no point: add one point per line, 3 numbers (axis "
                                "0, 1, 2)")
    return np.array(points, dtype=float).reshape(-1, 3)
