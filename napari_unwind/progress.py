"""Progress reporting for long jobs.

A long job is a generator that yields :class:`Progress` records and *returns* its result (``StopIteration.value``).
Every face drives the same generators: the CLI with a progress bar (:func:`run`), the gRPC servicers by streaming
the records, the napari widgets in a ``thread_worker``.

A loop that runs long without yielding (a skeleton's smoothing iterations, its level sets, a Gaussian filter)
calls :func:`checkpoint` instead: it does nothing unless its caller installed a check with :func:`cancellation`
(the server's job workers and unary calls do), and then runs that check at most every ``interval`` seconds; the
check raises to stop the work. A checkpoint never changes what a loop computes.
"""

from __future__ import annotations

import contextlib
import contextvars
import sys
import time
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from typing import Any, TypeVar

__all__ = ["Progress", "ProgressGenerator", "cancellation", "checkpoint", "progress_bar", "run"]

T = TypeVar("T")


@dataclass(frozen=True)
class Progress:
    """One step of a long job.

    Attributes
    ----------
    stage : str
        Short name of the current stage, e.g. ``"level 0"`` or ``"read"``.
    done, total : int
        Work units finished so far, out of ``total`` in this stage (``total`` 0 when unknown).
    message : str
        Optional human readable detail.
    """

    stage: str
    done: int
    total: int
    message: str = ""

    @property
    def fraction(self) -> float:
        """Fraction of the stage finished, in [0, 1] (0 when the total is unknown)."""
        return min(1.0, self.done / self.total) if self.total else 0.0


ProgressGenerator = Generator[Progress, None, T]

#: The check of the current thread's work and when it last ran: ``[check, interval, last]`` or None.
_CHECK: contextvars.ContextVar[list | None] = contextvars.ContextVar("napari_unwind_cancellation", default=None)


@contextlib.contextmanager
def cancellation(check: Callable[[], Any], interval: float = 0.1) -> Iterator[None]:
    """Within the block, :func:`checkpoint` calls ``check()`` (at most once per ``interval`` seconds); ``check``
    raises to stop the work (e.g. a cancelled job, a call whose client went away). The check belongs to the
    calling thread (a context variable): threads of a server do not see each other's."""
    token = _CHECK.set([check, float(interval), time.monotonic()])
    try:
        yield
    finally:
        _CHECK.reset(token)


def checkpoint() -> None:
    """Where a long loop may be stopped: runs the check installed by :func:`cancellation`, if any, once its
    interval has passed. Cheap enough for every iteration of a loop of milliseconds (one clock read)."""
    state = _CHECK.get()
    if state is None:
        return
    now = time.monotonic()
    if now - state[2] >= state[1]:
        state[2] = now
        state[0]()


def run(gen: Generator[Progress, Any, T], callback: Callable[[Progress], Any] | None = None) -> T:
    """Drive a progress generator to its end and return its result.

    Parameters
    ----------
    gen : generator
        A generator yielding :class:`Progress` and returning the job's result.
    callback : callable, optional
        Called with every :class:`Progress` record.
    """
    while True:
        try:
            p = next(gen)
        except StopIteration as stop:
            return stop.value
        if callback is not None:
            callback(p)


def progress_bar(quiet: bool = False, *, stream: Any = None) -> tuple[Callable[[Progress], None], Callable[[], None]]:
    """Progress shown on ``stream`` (default ``sys.stderr``), fed by :class:`Progress` records: ``(callback, close)``.

    On a terminal, a tqdm bar per stage; a new stage closes the previous bar. Anywhere else (a log file, CI, a
    service's journal) one line per stage when it ends, with its time: ``write: 100% (12/12) in 3.4 s`` (a stage
    followed by another is ``done``; the last one, if it did not finish, ends with ``, stopped``; one of unknown
    length gives ``7 steps``). With ``quiet`` the
    callback does nothing.
    """
    if quiet:
        return (lambda p: None), (lambda: None)
    stream = sys.stderr if stream is None else stream
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):
        tty = False
    if not tty:
        return _stage_lines(stream)
    from tqdm.auto import tqdm

    state: dict[str, Any] = {"bar": None, "stage": None}

    def close() -> None:
        if state["bar"] is not None:
            state["bar"].close()
            state["bar"] = None

    def callback(p: Progress) -> None:
        if p.stage != state["stage"]:
            close()
            state["stage"] = p.stage
            state["bar"] = tqdm(total=p.total or None, desc=p.stage, unit="step", leave=True, dynamic_ncols=True,
                                file=stream)
        bar = state["bar"]
        if p.total and bar.total != p.total:
            bar.total = p.total
        bar.n = p.done
        if p.message:
            bar.set_postfix_str(p.message, refresh=False)
        bar.refresh()

    return callback, close


def _stage_lines(stream: Any) -> tuple[Callable[[Progress], None], Callable[[], None]]:
    """One line per stage, written when the stage ends (the next begins, or ``close``)."""
    state: dict[str, Any] = {"last": None, "t0": time.perf_counter()}

    def close(moved_on: bool = False) -> None:
        p = state["last"]
        now = time.perf_counter()
        if p is not None:
            state["last"] = None
            took = f"in {now - state['t0']:.1f} s"
            if not p.total:
                line = f"{p.stage}: {p.done} steps {took}"
            elif p.done >= p.total:
                line = f"{p.stage}: 100% ({p.done}/{p.total}) {took}"
            elif moved_on:
                line = f"{p.stage}: done {took}"  # the next stage began: this one is over, whatever it counted
            else:
                line = f"{p.stage}: {100 * p.fraction:.0f}% ({p.done}/{p.total}) {took}, stopped"
            print(line, file=stream, flush=True)
        state["t0"] = now

    def callback(p: Progress) -> None:
        if state["last"] is not None and p.stage != state["last"].stage:
            close(moved_on=True)  # the stage's time runs from the end of the previous one
        state["last"] = p

    return callback, close
