"""Benchmark helpers: run a job in a fresh process and report its wall time and peak RSS."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from argparse import ArgumentParser, Namespace


def run_isolated(code: str, *, timeout: float = 3600) -> dict:
    """Run ``code`` in a new interpreter; it must leave its results in a dict named ``result``.

    Returns that dict plus ``peak_rss_mb`` (the child's own maximum resident set size).
    """
    wrapper = textwrap.dedent("""
        import json, resource, time
        result = {}
        _t0 = time.perf_counter()
    """) + textwrap.dedent(code) + textwrap.dedent("""
        result.setdefault("seconds", time.perf_counter() - _t0)
        result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print("@@RESULT@@" + json.dumps(result))
    """)
    r = subprocess.run([sys.executable, "-c", wrapper], capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        raise RuntimeError(f"benchmark child failed:\n{r.stderr[-4000:]}")
    line = next(line for line in r.stdout.splitlines() if line.startswith("@@RESULT@@"))
    return json.loads(line[len("@@RESULT@@"):])


def table(rows: list[list[str]]) -> str:
    """A Markdown table from rows of cells, the first row being the header."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    fmt = lambda r: "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    return "\n".join([fmt(rows[0]), "| " + " | ".join("-" * w for w in widths) + " |", *map(fmt, rows[1:])])


def thickness_switch(ap: ArgumentParser) -> None:
    """Add ``--no-thickness`` to ``ap``: a part cut off is read as the body doubled by its two-cored sections only,
    not also by its sections' size (the code before ``_thick_pieces``); :func:`apply_thickness_switch` applies it."""
    ap.add_argument("--no-thickness", action="store_true", help="do not read the cut parts' sections' size")


def apply_thickness_switch(args: Namespace) -> None:
    """Switch the sections' size off in this process when ``args.no_thickness`` (see :func:`thickness_switch`)."""
    if args.no_thickness:
        import napari_unwind.skeleton._api as api

        api._THICK_PIECES = float("inf")


def rise_switch(ap: ArgumentParser) -> None:
    """Add ``--no-rise`` to ``ap``: a dead end off the path is cut as a branch however little it reaches past the
    slack (a kink's outer corner too: the code before ``_rise``); :func:`apply_rise_switch` applies it."""
    ap.add_argument("--no-rise", action="store_true", help="cut a kink's outer corner as a branch (before _rise)")


def apply_rise_switch(args: Namespace) -> None:
    """Switch the rise off in this process when ``args.no_rise`` (see :func:`rise_switch`)."""
    if args.no_rise:
        import napari_unwind.skeleton._api as api

        api._BRANCH_RISE = 0.0


def doubt_switch(ap: ArgumentParser) -> None:
    """Add ``--no-doubt`` to ``ap``: a branch cut where the path turns sharply or next to an end is a branch like
    any other, ok with a note (the code before ``_DOUBT_TURN`` and ``_END_NEAR``); :func:`apply_doubt_switch`."""
    ap.add_argument("--no-doubt", action="store_true", help="no branch in doubt (before _DOUBT_TURN, _END_NEAR)")


def apply_doubt_switch(args: Namespace) -> None:
    """Switch the doubt off in this process when ``args.no_doubt`` (see :func:`doubt_switch`)."""
    if args.no_doubt:
        import napari_unwind.skeleton._api as api

        api._DOUBT_TURN, api._END_NEAR = float("inf"), 0.0
