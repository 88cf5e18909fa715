"""Progress reporting for long jobs.

A long job is a generator that yields :class:`Progress` records and *returns* its result (``StopIteration.value``).
Every face drives the same generators: the CLI with a progress bar (:func:`run`), the gRPC servicers by streaming
the records, the napari widgets in a ``thread_worker``.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any, TypeVar

__all__ = ["Progress", "ProgressGenerator", "run"]

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


def progress_bar(quiet: bool = False) -> tuple[Callable[[Progress], None], Callable[[], None]]:
    """A tqdm progress bar fed by :class:`Progress` records: returns ``(callback, close)``.

    One bar per stage; a new stage closes the previous bar. With ``quiet`` the callback does nothing.
    """
    if quiet:
        return (lambda p: None), (lambda: None)
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
            state["bar"] = tqdm(total=p.total or None, desc=p.stage, unit="step", leave=True, dynamic_ncols=True)
        bar = state["bar"]
        if p.total and bar.total != p.total:
            bar.total = p.total
        bar.n = p.done
        if p.message:
            bar.set_postfix_str(p.message, refresh=False)
        bar.refresh()

    return callback, close
