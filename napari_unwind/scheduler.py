"""Where dask computations run: threads, the synchronous scheduler, or a ``dask.distributed`` cluster.

:func:`use_scheduler` is the one place that chooses. :func:`napari_unwind.warp.export` takes its ``scheduler=``; the
server's job workers run every job (refine, segment, skeleton, straighten, bend, writes) inside one ``use_scheduler``
of the server's ``--scheduler`` (an upload's streamed import runs in its own process, no dask). Entered again with
the address of a cluster that is already in use (an export inside such a job), it reuses that connection instead of
opening a second one.

A cluster that loses the work (a worker killed while it held the task, the scheduler gone, no worker left) ends
the computation with :class:`SchedulerError`, one line saying what happened and what to do, never a partial
result: the writers are atomic, so whatever was being written is removed.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

import dask

from .errors import InvalidInputError, UnwindError

__all__ = ["SchedulerError", "use_scheduler", "THREADS", "SYNCHRONOUS"]

#: The names ``scheduler=`` accepts besides a cluster address.
THREADS = ("threads", "threading")
SYNCHRONOUS = ("synchronous", "sync", "single-threaded")

_open = threading.local()  # .counts: cluster address -> how many use_scheduler() of it this thread has open


class SchedulerError(UnwindError):
    """The dask cluster lost the work: a worker died holding it, the scheduler went away, or no worker is left."""


def _lost_work_errors() -> tuple[type[BaseException], ...]:
    from distributed import KilledWorker
    from distributed.client import FutureCancelledError
    from distributed.comm.core import CommClosedError
    from distributed.scheduler import NoValidWorkerError

    return KilledWorker, FutureCancelledError, CommClosedError, NoValidWorkerError


@contextlib.contextmanager
def use_scheduler(scheduler: str | None) -> Iterator[None]:
    """Run the dask computations of the ``with`` body on ``scheduler``.

    Parameters
    ----------
    scheduler : str or None
        None or ``"threads"``: dask's thread pool in this process; ``"synchronous"``: one thread (debugging);
        ``"tcp://host:port"`` (any ``protocol://`` address): a ``dask.distributed`` cluster, connected for the
        body and closed after it (unless an enclosing ``use_scheduler`` of the same address holds it). Its
        workers must see the paths of the data (a shared file system or the same machine).

    Raises
    ------
    InvalidInputError
        An unknown name.
    SchedulerError
        The cluster cannot be reached, or (in the body) it lost the work.
    """
    if scheduler is None or scheduler in THREADS:
        with dask.config.set(scheduler="threads"):
            yield
        return
    if scheduler in SYNCHRONOUS:
        with dask.config.set(scheduler="synchronous"):
            yield
        return
    if not isinstance(scheduler, str) or "://" not in scheduler:
        raise InvalidInputError(
            f"scheduler must be None (threads), 'synchronous' or a scheduler address such as "
            f"'tcp://host:8786', got {scheduler!r}"
        )
    counts: dict[str, int] = _open.__dict__.setdefault("counts", {})
    if counts.get(scheduler, 0) > 0:
        # an enclosing use_scheduler() of this thread set dask's scheduler to this cluster and handles its errors
        yield
        return
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - distributed is in the [server] extra
        raise InvalidInputError(
            "a scheduler address needs the 'distributed' package (pip install napari-unwind[server])"
        ) from None
    try:
        client = Client(scheduler, timeout="20s", set_as_default=False)
    except OSError as exc:
        raise SchedulerError(f"cannot reach the dask scheduler at {scheduler}: {exc}; start it, or choose "
                             "another scheduler") from None
    counts[scheduler] = counts.get(scheduler, 0) + 1
    try:
        with dask.config.set(scheduler=client.get):
            yield
    except _lost_work_errors() as exc:
        what = type(exc).__name__
        detail = str(exc).split(". ")[0].splitlines()[0] if str(exc) else ""  # the first sentence
        raise SchedulerError(
            f"the dask cluster at {scheduler} lost this work ({what}{': ' + detail if detail else ''}): a worker "
            "died while it held a task, or the scheduler went away; nothing partial was kept. Run it again; if it "
            "happens again, check the workers' logs and memory limit"
        ) from None
    finally:
        counts[scheduler] -= 1
        client.close()
