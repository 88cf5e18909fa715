"""Long jobs of the dock off the UI thread: a core progress generator in a napari ``thread_worker``.

The core's long jobs are generators that yield :class:`~napari_unwind.progress.Progress` and return their result
(:mod:`napari_unwind.progress`). :func:`start_job` runs one in a worker thread, shows its records in a napari
``progress`` bar (the activity dock), and calls back on the UI thread with the result or the error.
:meth:`Job.cancel` stops the generator at its next yield: it is closed in the worker thread (so its ``finally``
blocks and the atomic writers' clean-up run) and the job ends with :class:`JobCancelled`. The shape follows
stardist-napari's ``plugin_function_generator``: the worker yields progress, the widget connects ``yielded`` /
``returned`` / ``errored``.

Some core steps call compiled extensions that hold the GIL for seconds (fTetWild's tet mesh in the skeleton solve
stalls a thread-based worker's UI by about 2 s on the fish phantom). :func:`start_process_job` runs such a job in a
child process (spawned: no Qt in it) and relays its progress through a queue from a thread worker, so the UI thread
only ever waits on the queue; Cancel terminates the child. A fresh interpreter spends seconds importing the
core, so one spare child per job kind waits ready, its imports done (:func:`prewarm`; one job per child).
"""

from __future__ import annotations

import contextlib
import importlib
import multiprocessing
import pickle
import queue as queue_module
import sys
import threading
import time
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from typing import Any

from ..progress import Progress

# napari and Qt are imported where a worker starts, not here: the spawned child of start_process_job imports this
# module to find its entry point and must stay free of Qt (importing napari there costs seconds, or worse).

__all__ = ["Job", "JobCancelled", "in_child", "prewarm", "start_job", "start_process_job"]

#: Seconds the relay waits on the child's queue before checking Cancel and the child's health again.
_POLL = 0.05


class JobCancelled(Exception):
    """The job was cancelled (Cancel button): not an error to report."""


@dataclass
class Job:
    """A running job: its worker and its cancel flag."""

    worker: Any  # napari's GeneratorWorker
    label: str
    _cancel: threading.Event
    #: Set on the UI thread once the job is over (returned, failed or cancelled) and its callbacks have run.
    done: bool = False
    #: ``time.perf_counter()`` when the result reached the UI thread (None before; for the stall measurements).
    returned_at: float | None = None

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
    _cancel: threading.Event | None = None,
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
    from napari.qt.threading import thread_worker
    from napari.utils import progress as napari_progress

    cancel = threading.Event() if _cancel is None else _cancel
    worker = thread_worker(_relay, start_thread=False, ignore_errors=True)(make, cancel)  # errors: on_error
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
    def returned(value: Any) -> None:
        job.returned_at = time.perf_counter()
        on_returned(value)

    worker.returned.connect(returned)
    worker.errored.connect(on_error)
    worker.finished.connect(finished)
    worker.start()
    return job


def _resolve(fn: Callable[..., Any] | str) -> Callable[..., Any]:
    if callable(fn):
        return fn
    module, _, name = fn.partition(":")
    return getattr(importlib.import_module(module), name)


def _module(fn: Callable[..., Any] | str) -> str:
    return fn.partition(":")[0] if isinstance(fn, str) else fn.__module__


def _child(fn: Callable[..., Generator[Progress, None, Any]] | str, args: tuple, kwargs: dict, out: Any) -> None:
    """In the child process: drive the generator, send ("progress", p), then ("result", value) or ("error", exc)."""
    try:
        gen = _resolve(fn)(*args, **kwargs)
        while True:
            try:
                p = next(gen)
            except StopIteration as stop:
                out.put(("result", stop.value))
                return
            out.put(("progress", p))
    except BaseException as exc:  # noqa: BLE001 - every failure goes back to the dock
        try:
            pickle.dumps(exc)
            out.put(("error", exc))
        except Exception:  # noqa: BLE001 - an exception that does not pickle goes back as its text
            out.put(("error", RuntimeError(f"{type(exc).__name__}: {exc}")))


def _child_loop(module: str, jobs: Any, out: Any) -> None:
    """A spare child: import the job's module while idle (seconds: scipy, numba, the mesher), then run one job."""
    importlib.import_module(module)
    task = jobs.get()
    if task is not None:
        _child(*task, out)


#: One idle child per module, ready for the next job (see :func:`prewarm`).
_SPARES: dict[str, tuple[Any, Any, Any]] = {}
_SPARES_LOCK = threading.Lock()


@contextlib.contextmanager
def _main_hidden() -> Iterator[None]:
    """Hide the parent's ``__main__`` from a child being spawned: multiprocessing's spawn runs the parent's main
    script again in the child, and a napari script rarely has an ``if __name__ == "__main__"`` guard (the child would
    open a second viewer, or fail in its bootstrapping). The children here need nothing from ``__main__``."""
    main = sys.modules.get("__main__")
    if main is None:
        yield
        return
    missing = object()
    saved = {k: main.__dict__.get(k, missing) for k in ("__file__", "__spec__")}
    main.__dict__.pop("__file__", None)
    main.__spec__ = None
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is missing:
                main.__dict__.pop(k, None)
            else:
                main.__dict__[k] = v


def prewarm(fn: Callable[..., Any] | str) -> None:
    """Start an idle child process that imports ``fn``'s module (a function or ``"module:name"``), so the next
    :func:`start_process_job` of it skips the seconds of a fresh interpreter's imports. Does nothing when one is
    ready already."""
    module = _module(fn)
    with _SPARES_LOCK:
        spare = _SPARES.get(module)
        if spare is not None and spare[0].is_alive():
            return
        ctx = multiprocessing.get_context("spawn")
        jobs, out = ctx.Queue(), ctx.Queue()
        proc = ctx.Process(target=_child_loop, args=(module, jobs, out), daemon=True, name="napari-unwind job")
        with _main_hidden():
            proc.start()
        _SPARES[module] = (proc, jobs, out)


def _take_spare(fn: Callable[..., Any] | str) -> tuple[Any, Any, Any]:
    while True:
        prewarm(fn)
        with _SPARES_LOCK:
            proc, jobs, out = _SPARES.pop(_module(fn))
        if proc.is_alive():
            return proc, jobs, out


def _in_process(fn: Callable[..., Generator[Progress, None, Any]] | str, args: tuple, kwargs: dict,
                cancel: threading.Event) -> Generator[Progress, None, Any]:
    proc, jobs, out = _take_spare(fn)
    jobs.put((fn, args, kwargs))
    try:
        while True:
            if cancel.is_set():
                raise JobCancelled("cancelled")
            try:
                kind, value = out.get(timeout=_POLL)
            except queue_module.Empty:
                if proc.is_alive():
                    continue
                try:  # the child may have ended right after its last message
                    kind, value = out.get(timeout=1.0)
                except queue_module.Empty:
                    raise RuntimeError(f"the worker process ended without a result (exit code {proc.exitcode}); "
                                       "it may have run out of memory") from None
            if kind == "progress":
                yield value
            elif kind == "result":
                return value
            else:
                raise value
    finally:
        if proc.is_alive():
            proc.terminate()
        proc.join(timeout=5)
        for q in (jobs, out):  # a child stopped before reading its task must not block our exit on the pipe
            q.cancel_join_thread()
            q.close()
        prewarm(fn)  # the next run starts warm


def in_child(fn: Callable[..., Generator[Progress, None, Any]] | str, args: tuple = (), kwargs: dict | None = None
             ) -> Generator[Progress, None, Any]:
    """``fn(*args, **kwargs)`` in a spare child process, as a progress generator (the workflow's runner for the
    skeleton step: :class:`napari_unwind.workflow.LocalBackend`); closing it (Cancel) terminates the child."""
    return (yield from _in_process(fn, args, dict(kwargs or {}), threading.Event()))


def start_process_job(
    fn: Callable[..., Generator[Progress, None, Any]] | str,
    args: tuple = (),
    kwargs: dict | None = None,
    **callbacks: Any,
) -> Job:
    """:func:`start_job` for ``fn(*args, **kwargs)`` run in a spawned child process.

    ``fn`` is a module-level function of the core, or its ``"module:name"`` (then the UI process never imports
    it), run in a spare child (:func:`prewarm`); its arguments and result must be
    picklable (numpy arrays, lazy dask arrays of a file, the core's dataclasses). Cancel terminates the child.
    The keyword arguments are those of :func:`start_job`.
    """
    cancel = threading.Event()

    def make() -> Generator[Progress, None, Any]:
        return _in_process(fn, args, dict(kwargs or {}), cancel)

    return start_job(make, _cancel=cancel, **callbacks)
