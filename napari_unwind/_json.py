"""The one gate every JSON input passes: sessions, deformations, batch files (issue 20: inputs that lie).

Two steps, each refusing in one line (:class:`~napari_unwind.errors.InvalidInputError`) instead of a traceback:

1. :func:`load_file` / :func:`loads` read the text safely: a size limit on the file, UTF-8, numbers written with
   at most :data:`MAX_NUMBER_CHARS` characters (Python refuses ints of more than 4300 digits with a ValueError, and
   an int of 400 digits overflows a float), no ``NaN``/``Infinity`` and no number that only becomes infinite when
   read (``1e400``), and nesting at most :data:`MAX_DEPTH` deep, measured before parsing (a nest of 100000 arrays
   made the parser raise RecursionError).
2. :func:`validate` checks the data against a JSON Schema kept as data in ``napari_unwind/schemas/`` (types,
   required fields, bounds on every number, string length and array length); dicts built in Python (the API's
   ``from_dict``) are first brought to plain JSON (numpy scalars and arrays, tuples) and measured for depth the
   same way, without recursion.

The message of a refusal names the JSON path of the bad value (``source.spacing[1]``), what was received
(shortened) and what is expected; the callers put the file name in front.
"""

from __future__ import annotations

import json
import math
import os
import re
import reprlib
from functools import cache
from pathlib import Path
from typing import Any

from .errors import InvalidInputError

__all__ = ["MAX_DEPTH", "MAX_NUMBER_CHARS", "load_file", "loads", "plain", "schema", "validate", "json_path",
           "short"]

#: Deepest nesting of arrays and objects accepted (a session is 5 deep).
MAX_DEPTH = 32
#: Longest number text accepted: a double needs 24 characters at most (``-2.2250738585072014e-308``).
MAX_NUMBER_CHARS = 40
#: Characters of a received value quoted in a message.
_SHORT = 60

#: Integers this large or larger are refused before validation (jsonschema's messages repr them: no repr past 4300
#: digits); a float reaches 1.8e308, so no bound of the schemas is near.
_HUGE = 10**MAX_NUMBER_CHARS
_SCHEMAS = Path(__file__).with_name("schemas")


# ------------------------------------------------------------------------------------------------------------------
# messages
# ------------------------------------------------------------------------------------------------------------------
class _Repr(reprlib.Repr):
    """Bounded reprs: a few items per container, a few levels, strings and integers cut (an int of 5000 digits
    has no repr in Python 3.11+)."""

    def __init__(self) -> None:
        super().__init__()
        self.maxlevel, self.maxlist, self.maxdict, self.maxstring, self.maxother = 3, 6, 6, _SHORT, _SHORT

    def repr_int(self, x: int, level: int) -> str:
        if abs(x) < 10**MAX_NUMBER_CHARS:
            return repr(x)
        if abs(x) < 10**4000:
            return f"an integer of {len(str(abs(x)))} digits"
        return f"an integer of about {x.bit_length() * 0.30103:.0f} digits"

    def repr_str(self, x: str, level: int) -> str:
        if len(x) <= self.maxstring:
            return repr(x)
        return f"{x[:self.maxstring]!r}... ({len(x)} characters)"


_REPR = _Repr()


def short(value: Any, limit: int = _SHORT) -> str:
    """A repr of ``value`` of about ``limit`` characters at most, whatever its size or depth."""
    text = _REPR.repr(value)
    return text if len(text) <= 2 * limit else text[:2 * limit] + "..."


class _Elided(int):
    pass


def json_path(parts: Any, root: str = "") -> str:
    """``source.spacing[1]`` for the parts ``("source", "spacing", 1)`` (``root`` before them)."""
    parts = list(parts)
    if len(parts) > 12:  # a deep nest: its start and its end
        parts = [*parts[:8], _Elided(len(parts) - 10), *parts[-2:]]
    text = root
    for p in parts:
        if isinstance(p, _Elided):
            text += f"...({p} more)..."
        elif isinstance(p, int):
            text += f"[{p}]"
        else:
            text += f".{p}" if text and not text.endswith(" ") else str(p)
    return text.strip() or "(top level)"


def _kind(value: Any) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", int: "a number",
            float: "a number", type(None): "null"}.get(type(value), type(value).__name__)


_TYPE_NAMES = {"object": "an object", "array": "a list", "string": "a string", "number": "a number",
               "integer": "an integer", "boolean": "true or false", "null": "null"}


def _message(error: Any, root: str) -> str:
    """One line for a jsonschema ValidationError: where, what was expected, what was received."""
    where = json_path(error.absolute_path, root)
    v, kw, sch = error.instance, error.validator, error.schema
    got = f"{_kind(v)} ({short(v)})" if kw == "type" else short(v)
    noun = sch.get("x-noun", "values")
    if kw == "type":
        types = error.validator_value if isinstance(error.validator_value, list) else [error.validator_value]
        return f"{where} must be {' or '.join(_TYPE_NAMES.get(t, t) for t in types)}, got {got}"
    if kw == "required":
        missing = re.match(r"'(.*)' is a required property", error.message)
        key = missing.group(1) if missing else error.message
        return f"{where}.{key} is missing" if where != "(top level)" else f"the field {key!r} is missing"
    if kw in ("minItems", "maxItems"):
        lo, hi = sch.get("minItems"), sch.get("maxItems")
        if lo == hi:
            return f"{where} must hold {lo} {noun}, got {len(v)}: {short(v)}"
        if kw == "minItems":
            return f"{where} must hold at least {lo} {noun}, got {len(v)}: {short(v)}"
        return f"{where} holds {len(v)} {noun}, more than the {hi} a file of this kind can hold"
    if kw == "maxLength":
        return f"{where} is a string of {len(v)} characters, longer than the {sch['maxLength']} allowed: {got}"
    if kw == "minLength":
        return f"{where} must not be empty"
    if kw in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
        lo = sch.get("minimum", sch.get("exclusiveMinimum"))
        hi = sch.get("maximum", sch.get("exclusiveMaximum"))
        if hi is None:
            sign = ">" if "exclusiveMinimum" in sch else ">="
            return f"{where} must be {sign} {lo}, got {got}"
        if lo is None:
            sign = "<" if "exclusiveMaximum" in sch else "<="
            return f"{where} must be {sign} {hi:g}, got {got}"
        return f"{where} must be between {lo:g} and {hi:g}, got {got}"
    if kw == "const":
        return f"{where} must be {sch['const']!r}, got {got}"
    if kw == "enum":
        return f"{where} must be one of {', '.join(repr(e) for e in sch['enum'])}, got {got}"
    if kw == "maxProperties":
        return f"{where} holds {len(v)} fields, more than the {sch['maxProperties']} allowed"
    if kw == "pattern":
        return f"{where} must match {sch.get('x-pattern-says', sch['pattern'])}, got {got}"
    return f"{where}: {error.message[:200]}"  # pragma: no cover - a keyword the schemas do not use


# ------------------------------------------------------------------------------------------------------------------
# reading text
# ------------------------------------------------------------------------------------------------------------------
class _Refused:
    """What a parse hook returns for a number it refuses: :func:`plain` reports it with its JSON path."""

    __slots__ = ("problem",)

    def __init__(self, problem: str) -> None:
        self.problem = problem


def _parse_int(text: str) -> Any:
    if len(text) > MAX_NUMBER_CHARS:  # int() itself raises ValueError past 4300 digits
        return _Refused(f"is a number of {len(text)} digits ({text[:20]}...), longer than the {MAX_NUMBER_CHARS} "
                        "characters any value of this file needs")
    return int(text)


def _parse_float(text: str) -> Any:
    if len(text) > MAX_NUMBER_CHARS:
        return _Refused(f"is a number written with {len(text)} characters ({text[:20]}...), longer than the "
                        f"{MAX_NUMBER_CHARS} any value of this file needs")
    value = float(text)
    if not math.isfinite(value):
        return _Refused(f"is the number {text}, too large to be a finite number")
    return value


def _parse_constant(token: str) -> Any:
    return _Refused(f"is the number {token}, which this file never stores; replace it with a finite value")


_STRINGS = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)
_TOKENS = re.compile(r'"(?:[^"\\]|\\.)*"|[\[\]{},]', re.DOTALL)


def _path_at(text: str, at: int) -> tuple:
    """The JSON path of the container open at offset ``at`` of ``text`` (a light scan, no parsing, no recursion)."""
    stack: list[list] = []  # [is_list, index or key, expecting a key]
    for m in _TOKENS.finditer(text, 0, at + 1):
        t = m.group()
        if t == "[" or t == "{":
            stack.append([t == "[", 0 if t == "[" else None, t == "{"])
        elif t == "]" or t == "}":
            if stack:
                stack.pop()
        elif t == ",":
            if stack and stack[-1][0]:
                stack[-1][1] += 1
            elif stack:
                stack[-1][2] = True
        elif stack and not stack[-1][0] and stack[-1][2]:  # a key
            try:
                key = json.loads(t) if len(t) < 200 else t[1:60] + "..."
            except ValueError:
                key = t[1:-1][:60]
            stack[-1][1], stack[-1][2] = key, False
    return tuple(frame[1] for frame in stack[:-1])


def _too_deep(text: str, max_depth: int) -> str | None:
    """Where ``text`` nests arrays and objects deeper than ``max_depth`` (its JSON path, line and column), or None;
    without recursion and without parsing (a text of 100000 ``[`` makes the parser's recursion fail)."""
    import numpy as np

    if text.count("[") + text.count("{") <= max_depth:
        return None
    blank = _STRINGS.sub(lambda m: '"' + " " * (len(m.group()) - 2) + '"', text)  # same offsets, no brackets
    raw = blank.encode("utf-8")  # brackets are ASCII bytes: a multi-byte character never holds one
    b = np.frombuffer(raw, dtype=np.uint8)
    step = (b == ord("[")).astype(np.int64) + (b == ord("{")) - (b == ord("]")) - (b == ord("}"))
    depth = np.cumsum(step)
    if not len(depth) or depth.max() <= max_depth:
        return None
    at = len(raw[:int(np.argmax(depth > max_depth))].decode("utf-8"))
    line = text.count("\n", 0, at) + 1
    column = at - (text.rfind("\n", 0, at) + 1) + 1
    return (f"{json_path(_path_at(text, at))} is nested {int(depth.max())} levels deep (line {line}, column "
            f"{column}), deeper than the {max_depth} any file of this kind needs")


def loads(text: str, *, max_depth: int = MAX_DEPTH) -> Any:
    """Parse JSON text under the rules of the module docstring; the result is plain JSON (:func:`plain`).

    Raises
    ------
    InvalidInputError
        ``"is not valid JSON: <msg> at line L, column C"``, ``"is nested N levels deep at ..."`` or
        ``"<json path> is the number ..."``: the caller puts the file's name in front.
    """
    deep = _too_deep(text, max_depth)
    if deep:
        raise InvalidInputError(deep)
    try:
        data = json.loads(text, parse_int=_parse_int, parse_float=_parse_float, parse_constant=_parse_constant)
    except json.JSONDecodeError as exc:
        raise InvalidInputError(f"is not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}") from None
    except RecursionError:  # pragma: no cover - the depth was measured above
        raise InvalidInputError(f"is nested deeper than the {max_depth} levels allowed") from None
    return plain(data, max_depth=max_depth)


def load_file(path: str | os.PathLike, *, what: str, max_bytes: int, suffix_hint: str = "",
              damaged_hint: str = "", hint: str = "correct that value in the file") -> Any:
    """Read and parse a JSON file: :func:`napari_unwind.io._files.read_small`, not empty, UTF-8, then :func:`loads`.

    ``what`` names the kind of file in messages ("a session"); ``suffix_hint`` is said of a file too large (did you
    give the scan?), ``damaged_hint`` of a file that is not JSON, ``hint`` of a refused value or nesting. Every
    refusal is one line naming ``path``.
    """
    from .io._files import read_small

    path = Path(path).expanduser()
    raw = read_small(path, what=what, max_bytes=max_bytes, hint=suffix_hint and f" (*{suffix_hint})")
    if not raw.strip():
        raise InvalidInputError(f"{path} is empty, not {what} (was the save or the copy interrupted?)")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InvalidInputError(f"{path} is not {what} file: it is not UTF-8 text "
                                f"(invalid byte at offset {exc.start})") from None
    try:
        return loads(text)
    except InvalidInputError as exc:
        message = str(exc)
        if message.startswith("is not valid JSON"):
            message += f"; {damaged_hint or 'the file is truncated or damaged'}"
        elif hint:
            message += f"; {hint}"
        raise InvalidInputError(f"{path} {message}" if message.startswith("is ") else f"{path}: {message}") from None


# ------------------------------------------------------------------------------------------------------------------
# validation
# ------------------------------------------------------------------------------------------------------------------
@cache
def schema(name: str) -> dict:
    """The schema document ``napari_unwind/schemas/<name>.schema.json``."""
    return json.loads((_SCHEMAS / f"{name}.schema.json").read_text(encoding="utf-8"))


@cache
def _validator(name: str, part: str = "") -> Any:
    import jsonschema

    doc = schema(name)
    cls = jsonschema.validators.validator_for(doc)
    cls.check_schema(doc)
    if part:  # one of the document's $defs (a CSV row of a batch file is one item)
        doc = {"$schema": doc["$schema"], "$defs": doc["$defs"], "$ref": f"#/$defs/{part}"}
    return cls(doc)


def plain(data: Any, *, max_depth: int = MAX_DEPTH, root: str = "") -> Any:
    """``data`` as plain JSON values (numpy scalars and arrays to numbers and lists, tuples to lists), built without
    recursion; deeper than ``max_depth`` or holding something JSON has no value for is an InvalidInputError."""
    import numpy as np

    def convert(v: Any) -> Any:
        if isinstance(v, np.ndarray):
            v = v.tolist()
        elif isinstance(v, np.generic):
            v = v.item()
        if isinstance(v, tuple):
            v = list(v)
        return v

    def check(v: Any, where: tuple) -> None:
        if isinstance(v, _Refused):
            raise InvalidInputError(f"{json_path(where, root)} {v.problem}")
        if isinstance(v, float) and not math.isfinite(v):
            raise InvalidInputError(f"{json_path(where, root)} must be a finite number, got {v}")
        if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= _HUGE:
            raise InvalidInputError(f"{json_path(where, root)} must be a number a file of this kind can hold, got "
                                    f"{short(v)}")
        if not (v is None or isinstance(v, (str, bool, int, float, list, dict))):
            raise InvalidInputError(f"{json_path(where, root)} must be a JSON value, got {type(v).__name__}")

    top = convert(data)
    check(top, ())
    if not isinstance(top, (list, dict)):
        return top
    out = [] if isinstance(top, list) else {}
    stack = [(top, out, 1, ())]
    while stack:
        src, dst, depth, where = stack.pop()
        if depth > max_depth:
            raise InvalidInputError(f"{json_path(where, root)} is nested deeper than the {max_depth} levels any "
                                    "value of this kind needs")
        items = enumerate(src) if isinstance(src, list) else src.items()
        for k, v in items:
            if isinstance(src, dict) and not isinstance(k, str):
                raise InvalidInputError(f"{json_path(where, root)} has the key {short(k)}, not a string")
            v = convert(v)
            check(v, (*where, k))
            if isinstance(v, (list, dict)):
                child: Any = [] if isinstance(v, list) else {}
                stack.append((v, child, depth + 1, (*where, k)))
                v = child
            if isinstance(dst, list):
                dst.append(v)
            else:
                dst[k] = v
    return out


def validate(data: Any, name: str, *, part: str = "", root: str = "", prefix: str = "", hint: str = "") -> Any:
    """Check ``data`` against the schema ``name`` (see :func:`schema`); return it as plain JSON (:func:`plain`).

    Parameters
    ----------
    part : str
        Check against the schema's ``$defs/<part>`` instead of the whole document.
    root : str
        The JSON path of ``data`` in its document (``"deformation"``), put in front of every path named.
    prefix : str
        Put in front of the message (``"malformed deformation: "``).
    hint : str
        What to do, put after the message (``"correct it or save the session again"``).

    Raises
    ------
    InvalidInputError
        The first error found, in one line: path, what is expected, what was received.
    """
    try:
        data = plain(data, root=root)
    except InvalidInputError as exc:
        raise InvalidInputError(f"{prefix}{exc}{f'; {hint}' if hint else ''}") from None
    import hashlib

    # a document seen valid is not checked again (the warp rebuilds its deformation from the same dict in every
    # block: jsonschema takes ~20 ms for 60 keyframes, 8 times the rest of Deformation.from_dict)
    key = (name, part, hashlib.sha256(json.dumps(data, sort_keys=True).encode()).digest())
    if key in _VALID:
        return data
    error = next(iter(_validator(name, part).iter_errors(data)), None)  # the first in document order
    if error is not None:
        raise InvalidInputError(f"{prefix}{_message(error, root)}{f'; {hint}' if hint else ''}")
    if len(_VALID) >= 256:
        _VALID.clear()
    _VALID.add(key)
    return data


#: (schema, part, sha256 of the canonical JSON) of documents found valid (at most 256; cleared when full)
_VALID: set[tuple[str, str, bytes]] = set()
