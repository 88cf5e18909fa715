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


# the skeleton's rules a benchmark can switch off to measure what each changes: ``--no-NAME`` sets these constants of
# ``napari_unwind.skeleton._api`` in the benchmark's own process (the code before the rule)
SWITCHES: dict[str, tuple[str, dict[str, float]]] = {
    "thickness": ("a part cut off is read as the body doubled by its two-cored sections only, not also by its "
                  "sections' size (before _thick_pieces)", {"_THICK_PIECES": float("inf")}),
    "rise": ("a dead end off the path is cut as a branch however little it reaches past the slack, a kink's outer "
             "corner too (before _rise)", {"_BRANCH_RISE": 0.0}),
    "doubt": ("a branch cut where the path turns sharply or next to an end is a branch like any other, ok with a "
              "note (before _DOUBT_TURN and _END_NEAR)", {"_DOUBT_TURN": float("inf"), "_END_NEAR": 0.0}),
}


def add_switches(ap: ArgumentParser) -> None:
    """Add ``--no-NAME`` to ``ap`` for each rule of :data:`SWITCHES`; :func:`apply_switches` applies them."""
    for name, (what, _) in SWITCHES.items():
        ap.add_argument(f"--no-{name}", action="store_true", help=what.replace("%", "%%"))


def apply_switches(args: Namespace) -> None:
    """Switch off in this process each rule of :data:`SWITCHES` whose ``--no-NAME`` is in ``args``."""
    import napari_unwind.skeleton._api as api

    for name, (_, constants) in SWITCHES.items():
        if getattr(args, f"no_{name}", False):
            for constant, value in constants.items():
                assert hasattr(api, constant), constant  # a renamed rule must not leave its switch a no-op
                setattr(api, constant, value)
