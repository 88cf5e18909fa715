"""The command line's argument types and checks, shared by ``unwind`` (:mod:`napari_unwind.cli`) and its remote
commands (:mod:`napari_unwind._cli_remote`). Both import from here; neither imports the other's module for them.

The types raise ``argparse.ArgumentTypeError`` with the received text, so a wrong option is one line
(``unwind: error: argument --spacing: ...``); the checks raise :class:`napari_unwind.errors.UnwindError`.
"""

from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from .errors import InvalidInputError, UnwindError

#: The options whose value may begin with "-" (tokens an older server issued do, one in 64): the parser of
#: ``unwind`` (napari_unwind.cli._Parser) reads ``--token VALUE`` as ``--token=VALUE`` (see :func:`join_dash_values`).
DASH_VALUE_OPTIONS = ("--token",)


def join_dash_values(args: list[str], options: set[str]) -> list[str]:
    """``args`` with ``--token VALUE`` joined into ``--token=VALUE`` (argparse reads a VALUE that starts with "-"
    as an option: "expected one argument"). VALUE stays apart when it is one of ``options`` (``--token --server``:
    the token was forgotten, and argparse says so); nothing after ``--`` is touched."""
    out: list[str] = []
    i = 0
    while i < len(args):
        a = args[i]
        if a == "--":
            out.extend(args[i:])
            break
        if a in DASH_VALUE_OPTIONS and i + 1 < len(args):
            value = args[i + 1]
            if value != "--" and value not in options and value.split("=", 1)[0] not in options:
                out.append(f"{a}={value}")
                i += 2
                continue
        out.append(a)
        i += 1
    return out


def option_strings(parser: argparse.ArgumentParser) -> set[str]:
    """Every option string of ``parser`` and of its subcommands' parsers, at any depth."""
    found: set[str] = set()
    for action in parser._actions:
        found.update(action.option_strings)
        if isinstance(action, argparse._SubParsersAction):
            for sub in set(action.choices.values()):
                found |= option_strings(sub)
    return found


def _number(text: str, what: str = "a number") -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _finite(text: str) -> float:
    """A finite number (no nan, no inf)."""
    return _number(text)


def _positive(text: str) -> float:
    """A finite number > 0."""
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def _non_negative(text: str) -> float:
    """A finite number >= 0."""
    value = _number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def _whole(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """A type: a whole number in [lo, hi]."""

    def parse(text: str) -> int:
        try:
            value = int(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < lo or (hi is not None and value > hi):
            within = f">= {lo}" if hi is None else f"from {lo} to {hi}"
            raise argparse.ArgumentTypeError(f"expected a whole number {within}, got {text!r}")
        return value

    parse.__name__ = "whole number"
    return parse


def _triple(text: str) -> tuple[float, float, float]:
    """Parse ``"a,b,c"`` (or one number for all three axes) into three finite floats."""
    parts = text.replace(" ", "").split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers like 1.5 or 2,1,1, got {text!r}") from None
    if len(values) == 1:
        values *= 3
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected 1 or 3 comma-separated numbers (axis0,axis1,axis2), got {text!r}")
    if not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected finite numbers (axis0,axis1,axis2), got {text!r}")
    return tuple(values)  # type: ignore[return-value]


_ADDRESS = re.compile(r"^([a-z][a-z0-9+.-]*://)?(\[[0-9a-f:.]+\]|[a-z0-9._-]+)(:[0-9]{1,5})?$", re.IGNORECASE)


def _address(text: str) -> str:
    """A dask.distributed scheduler address: ``[protocol://]host[:port]``."""
    if not _ADDRESS.match(text.strip()):
        raise argparse.ArgumentTypeError(f"expected a scheduler address like tcp://host:8786, got {text!r}")
    return text.strip()


def _spacing3(text: str) -> tuple[float, float, float]:
    values = _triple(text)
    if any(v <= 0 for v in values):
        raise argparse.ArgumentTypeError(f"voxel spacings must be > 0, got {text!r}")
    return values


_SIZE_UNITS = {"": 1, "b": 1}


for _i, _p in enumerate("kmgtpe", start=1):
    _SIZE_UNITS[_p] = _SIZE_UNITS[_p + "ib"] = 1024 ** _i
    _SIZE_UNITS[_p + "b"] = 1000 ** _i


_SIZE_RE = re.compile(r"^([0-9]*\.?[0-9]+(?:e[+-]?[0-9]+)?)\s*([a-z]*)$")


def parse_size(text: str) -> int | None:
    """A size in bytes from ``500G``, ``2T``, ``1.5GiB``, ``800MB``, ``1000000``; None for ``none`` (no limit).

    K, M, G, T, P (and KiB, MiB, GiB, TiB, PiB) are powers of 1024; KB, MB, GB, TB, PB powers of 1000 (as GNU
    ``du`` and ``sort -S`` read them). Case does not matter.

    Raises
    ------
    argparse.ArgumentTypeError
        Anything else, or a size below one byte.
    """
    t = str(text).strip().lower()
    if t == "none":
        return None
    m = _SIZE_RE.match(t)
    if not m or m.group(2) not in _SIZE_UNITS:
        raise argparse.ArgumentTypeError(f"expected a size like 500G, 2T, 1.5GiB or a number of bytes (or none for "
                                         f"no limit), got {text!r}")
    value = float(m.group(1)) * _SIZE_UNITS[m.group(2)]
    if not math.isfinite(value) or value < 1:
        raise argparse.ArgumentTypeError(f"expected a size of at least 1 byte (or none for no limit), got {text!r}")
    return int(round(value))


def _chunks(text: str) -> tuple[int, int, int]:
    values = _triple(text)
    if any(v < 1 or v != int(v) for v in values):
        raise argparse.ArgumentTypeError(f"chunk sizes must be positive whole numbers, got {text!r}")
    return tuple(int(v) for v in values)  # type: ignore[return-value]


def _series(text: str) -> str | int:
    return int(text) if text.isdigit() else text


def _check_io(outputs: Sequence[Any], inputs: Sequence[Any]) -> None:
    """Refuse, before any work, an output that is, contains or lies inside an input (inputs are never modified)."""
    from .io._atomic import check_not_input

    check_not_input(outputs, inputs)


def _reader_options(args: argparse.Namespace, path: Any) -> dict[str, Any]:
    """``--series`` and ``--input-format`` as options of ``open_volume(path, ...)``."""
    opts: dict[str, Any] = {}
    if getattr(args, "input_format", None):
        opts["format"] = args.input_format
    if getattr(args, "series", None) is not None:
        from .io import detect_format

        fmt = opts.get("format") or detect_format(path)
        if fmt != "dicom":
            raise UnwindError(f"--series chooses a series of a DICOM folder; {path} is {fmt}: leave out --series")
        opts["series"] = args.series
    if getattr(args, "input_channel", None) is not None:
        from .io.channels import channel_index

        opts["channel"] = channel_index(path, args.input_channel, **opts)
    return opts


def _arg_point(p: Sequence[float]) -> str:
    """A point as the command line takes it (``A0,A1,A2``)."""
    return ",".join(f"{float(v):.4g}" for v in p)


def _endpoints_from_args(args: argparse.Namespace):
    """``--head``/``--tail``/``--chain`` as an Endpoints, or None (suggest them)."""
    import numpy as np

    from .session import Endpoints

    head, tail = args.head, args.tail
    chain = [tuple(pair) for pair in (args.chain or [])]
    if chain:
        # the chain runs head to tail: its first part starts at the head, its last ends at the tail
        for name, given, end, which in (("--head", head, chain[0][0], "first --chain pair starts"),
                                        ("--tail", tail, chain[-1][1], "last --chain pair ends")):
            if given is not None and not np.allclose(given, end, atol=1e-6):
                raise UnwindError(f"the {which} at {_arg_point(end)} but {name} is {_arg_point(given)}; the chain runs "
                                  "from the head to the tail: make them the same point, or leave out " + name)
        head, tail = chain[0][0], chain[-1][1]
        if len(chain) == 1:
            chain = []
    elif (head is None) != (tail is None):
        raise UnwindError("give both --head and --tail, or neither to use the suggested ones")
    if head is None:
        return None
    if np.allclose(head, tail, atol=1e-6):
        raise UnwindError(f"--head and --tail are the same point {_arg_point(head)}; give the two ends of the "
                          "specimen (or neither, to use the suggested ones)")
    return Endpoints(head=head, tail=tail, chain=tuple(chain))


def _check_session_path(path: str | os.PathLike, overwrite: bool) -> Path:
    """Check up front that a session file can be written at ``path`` (its name, its folder, an existing file)."""
    from .io._atomic import check_writable
    from .session import SESSION_SUFFIX

    name = Path(path).name.lower()
    if not name.endswith(SESSION_SUFFIX) or name == SESSION_SUFFIX:
        raise UnwindError(f"a session file name must end with {SESSION_SUFFIX}, got {Path(path).name!r}; name it "
                          f"e.g. {Path(path).name.split('.')[0] or 'fish'}{SESSION_SUFFIX}")
    return check_writable(path, overwrite=overwrite)


def _default_session_path(output: str | os.PathLike) -> Path:
    """``OUTPUT``'s name without its suffixes (and slice-number pattern) + ``.unwind.json``, beside it."""
    import re

    from .session import SESSION_SUFFIX

    out = Path(str(output).rstrip("/\\"))
    name = re.sub(r"\{[^}]*\}", "", out.name)
    for ext in (".gz", ".bz2"):
        if name.lower().endswith(ext):
            name = name[: -len(ext)]
    stem = Path(name).stem if Path(name).suffix else name
    stem = stem.rstrip("_-. ") or "straight"
    return out.with_name(stem + SESSION_SUFFIX)


def _skeleton_options(args: argparse.Namespace):
    """The :class:`~napari_unwind.pipeline.SkeletonOptions` of the skeleton options given (the rest default)."""
    from .pipeline import SkeletonOptions

    if args.no_twist and (getattr(args, "dorsal", None) or getattr(args, "dorsal_direction", None)):
        raise InvalidInputError("--dorsal and --dorsal-direction set the twist, and --no-twist asks for none: give "
                                "one of them")
    given = dict(estimate_twist=False if args.no_twist else None, n_levels=args.levels,
                 smoothing_iterations=args.smoothing_iterations, cage_radius=args.cage_radius,
                 tolerance=args.tolerance, snap_tolerance=args.snap_tolerance, half_extent=getattr(args, "cage", None),
                 cage_margin=getattr(args, "cage_margin", None),
                 dorsal_points=tuple(args.dorsal) if getattr(args, "dorsal", None) else None,
                 dorsal_direction=getattr(args, "dorsal_direction", None), context=getattr(args, "context", None))
    return SkeletonOptions(**{k: v for k, v in given.items() if v is not None})


def _pipeline_options(args: argparse.Namespace):
    """The :class:`~napari_unwind.pipeline.PipelineOptions` of ``unwind run`` (the options not given default)."""
    from .pipeline import PipelineOptions, SegmentOptions

    seg = {k: v for k, v in dict(features=args.features, level=args.level, isovalue=args.isovalue,
                                  fill_holes=args.fill_holes or None).items() if v is not None}
    return PipelineOptions(SegmentOptions(**seg), _skeleton_options(args), _export_options(args))


def _export_options(args: argparse.Namespace):
    """The :class:`~napari_unwind.pipeline.ExportOptions` of the export options given (``unwind run``,
    ``unwind straighten``; the rest default)."""
    from .pipeline import ExportOptions

    exp = {k: v for k, v in dict(order=args.order, spacing=args.spacing, pad=args.pad, chunks=args.chunks,
                                  allow_folds=args.allow_folds or None).items() if v is not None}
    if hasattr(args, "max_output"):
        exp["max_output"] = args.max_output
    return ExportOptions(**exp)
