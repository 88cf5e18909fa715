"""Long jobs of the dock off the UI thread: a core progress generator in a napari ``thread_worker``.

The core's long jobs are generators that yield :class:`~napari_unwind.progress.Progress` and return their result
(:mod:`napari_unwind.progress`). :func:`start_job` runs one in a worker thread, shows its records in a napari
``progress`` bar (the activity dock), and calls back on the UI thread with the result or the error.
:meth:`Job.cancel` stops the generator at its next yield: it is closed in the worker thread (so its ``finally``
blocks and the atomic writers' clean-up run) and the job ends with :class:`JobCancelled`. The shape follows
stardist-napari's ``plugin_function_generator``: the worker yields progress, the widget connects ``yielded`` /
``returned`` / ``errored``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any

from napari.qt.threading import GeneratorWorker, thread_worker
from napari.utils import progress as napari_progress

from ..progress import Progress

__all__ = ["Job", "JobCancelled", "start_job"]


class JobCancelled(Exception):
    """The job was cancelled (Cancel button): not an error to report."""


@dataclass
class Job:
    """A running job: its worker and its cancel flag."""

    worker: GeneratorWorker
    label: str
    _cancel: threading.Event
    #: Set on the UI thread once the job is over (returned, failed or cancelled) and its callbacks have run.
    done: bool = False

    def cancel(self) -> None:
        """Stop the job at the generator's next yield."""
        self._cancel.set()

    @property
    def running(self) -> bool:
        return not self.done


def _relay(make: Callable[[], Generator[Progress, None, Any]], cancel: threading.Event
           ) -> Generator[Progress, None, Any]:
    if cancel.is_set():
        raise JobCancelled("cancelled")
    gen = make()  # built in the worker: argument checks that read data happen off the UI thread too
    try:
        while True:
            try:
                p = next(gen)
            except StopIteration as stop:
                return stop.value
            if cancel.is_set():
                raise JobCancelled("cancelled")
            yield p
            if cancel.is_set():
                raise JobCancelled("cancelled")
    finally:
        gen.close()


def start_job(
    make: Callable[[], Generator[Progress, None, Any]],
    *,
    label: str,
    on_returned: Callable[[Any], Any],
    on_error: Callable[[BaseException], Any],
    on_finished: Callable[[], Any] | None = None,
    on_progress: Callable[[Progress], Any] | None = None,
) -> Job:
    """Run the progress generator ``make()`` in a worker thread; return the started :class:`Job`.

    Parameters
    ----------
    make : callable
        Builds the generator (called in the worker thread).
    label : str
        The progress bar's title.
    on_returned, on_error : callable
        Called on the UI thread with the generator's return value, or with the exception it raised
        (:class:`JobCancelled` after :meth:`Job.cancel`).
    on_finished : callable, optional
        Called on the UI thread once the job is over in any way (returned, failed or cancelled).
    on_progress : callable, optional
        Called on the UI thread with every :class:`Progress` record.
    """
    cancel = threading.Event()
    worker = thread_worker(_relay, start_thread=False)(make, cancel)
    bar = napari_progress(total=0, desc=label)
    state = {"stage": None}

    def show(p: Progress) -> None:
        if not isinstance(p, Progress):
            return
        if p.stage != state["stage"]:
            state["stage"] = p.stage
            bar.set_description(f"{label}: {p.stage}")
            bar.total = max(int(p.total), 0)
            bar.n = 0
        if p.total and int(p.total) != bar.total:
            bar.total = int(p.total)
        step = int(p.done) - int(bar.n)
        bar.update(step)
        if on_progress is not None:
            on_progress(p)

    def finished() -> None:
        bar.close()
        job.done = True
        if on_finished is not None:
            on_finished()

    job = Job(worker, label, cancel)
    worker.yielded.connect(show)
    worker.returned.connect(on_returned)
    worker.errored.connect(on_error)
    worker.finished.connect(finished)
    worker.start()
    return job
