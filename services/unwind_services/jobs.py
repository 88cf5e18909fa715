"""The job runner: worker processes driving task generators, with cancel, timeouts, watch and drain.

Jobs run in a pool of ``workers`` processes (spawned once, their imports warmed), so the core's long computations
never hold the server's GIL: health checks and other calls stay fast under load. The SQLite store (WAL) is the
only channel between the server and its workers: a worker marks its job running, appends progress records,
polls the job's stop flag between two steps, and records the result or the error.

A job's generator is advanced one step at a time; between two steps the worker checks for a cancel request, a
timeout or a shutdown, and within a step the core's long loops do the same check (``progress.checkpoint``, at
most every 0.2 s), so a job stops within about a second whatever its parameters. Stopping closes the generator,
so the core's ``atomic_output`` removes its temporary output: a cancelled or interrupted job never leaves a
result that looks whole. Workers die with the server (``PR_SET_PDEATHSIG``); after a ``kill -9`` the next start
marks their jobs interrupted.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing
import os
import shutil
import signal
import threading
import time
import traceback
import uuid
import warnings
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from napari_unwind.errors import InvalidInputError
from napari_unwind.io._atomic import TMP_MARK, remove_path
from napari_unwind.progress import cancellation
from napari_unwind.scheduler import use_scheduler

from ._proto.unwind.v1 import common_pb2 as pb
from ._proto.unwind.v1 import jobs_pb2
from .catalog import Catalog, Limits
from .errors import (
    INTERNAL_MESSAGE,
    CancelledError,
    DeadlineError,
    LimitError,
    ShuttingDownError,
    StateError,
    status_for,
)
from .paths import DataRoot
from .store import ACTIVE, FINAL, INTERRUPTED_MESSAGE, Store
from .tasks import KINDS, TaskContext, kind_of, precheck, run_task

__all__ = ["JobManager"]

log = logging.getLogger("unwind_services.jobs")

_PROGRESS_INTERVAL = 0.1  # seconds between two stored records of the same stage
_WATCH_POLL = 0.2  # seconds between two looks at the store while watching
_CHECK_INTERVAL = 0.2  # seconds between two looks at the stop flag from inside a step (progress.checkpoint)
#: Seconds a job asked to stop (after the drain) has to reach its next step before its worker process is killed.
STOP_GRACE = 3.0


class JobManager:
    """Submit, run, cancel and watch jobs; durable through the store."""

    def __init__(self, catalog: Catalog, *, workers: int = 2, scheduler: str | None = None,
                 imports: int | None = None):
        self.catalog = catalog
        self.store = catalog.store
        self.scheduler = scheduler
        self.workers = max(1, int(workers))
        self._pool: ProcessPoolExecutor | None = None
        self.imports = max(1, int(imports or self.workers))
        self._import_pool: ProcessPoolExecutor | None = None
        self._futures: dict[str, Future] = {}  # jobs handed to a worker (at most ``workers``): running or starting
        self._owners: dict[str, str] = {}  # their owners
        self._cond = threading.Condition()  # its lock is reentrant: a job that ends at once calls back in _dispatch
        self._closing = False

    # -- life cycle ------------------------------------------------------------------------------------------------
    def start(self) -> None:
        """Recover after a restart (running jobs become interrupted, leftovers go), start the workers, requeue."""
        interrupted = self.store.mark_interrupted()
        for job_id in interrupted:
            log.warning("job %s was running when the server stopped: marked interrupted", job_id)
        self._sweep_leftovers()
        self._pool = self._new_pool()
        self._pump()

    def _new_pool(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init,
            initargs=(str(self.catalog.root.root), self.catalog.limits, self.scheduler))

    def _sweep_leftovers(self) -> None:
        """Temporary outputs of atomic writes that a killed server left behind."""
        users = self.catalog.root.private / "users"
        for p in list(users.rglob(f"*{TMP_MARK}")):
            log.warning("removing the partial output %s", p)
            remove_path(p)
        for p in self.catalog.root.tmp.iterdir():
            remove_path(p)

    def _pump(self) -> None:
        """Hand queued jobs to free workers, fairly: a job is handed to a worker only when one is free, and the
        next is the oldest job of the users with the fewest jobs running, among those below their limit of running
        jobs (:meth:`Limits.running_per_user`). One user's long queue never keeps another user's job waiting
        behind it."""
        with self._cond:
            while not self._closing and self._pool is not None and len(self._futures) < self.workers:
                picked = self._pick()
                if picked is None:
                    return
                self._dispatch(*picked)

    def _pick(self) -> tuple[str, str] | None:
        per_user = self.catalog.limits.running_per_user(self.workers)
        running: dict[str, int] = {}
        for owner in self._owners.values():
            running[owner] = running.get(owner, 0) + 1
        best: tuple[str, str, int] | None = None
        for job_id, owner in self.store.queued_jobs():  # oldest first
            n = running.get(owner, 0)
            if job_id in self._futures or n >= per_user:
                continue
            if best is None or n < best[2]:
                best = (job_id, owner, n)
                if n == 0:
                    break
        return None if best is None else best[:2]

    def _dispatch(self, job_id: str, owner: str) -> None:
        try:
            fut = self._pool.submit(_worker_run, job_id)
        except BrokenProcessPool:  # a worker was killed: its jobs are marked interrupted; start fresh workers
            log.error("a job worker died; starting new workers")
            self._pool = self._new_pool()
            fut = self._pool.submit(_worker_run, job_id)
        with self._cond:
            self._futures[job_id] = fut
            self._owners[job_id] = owner
        fut.add_done_callback(lambda f, j=job_id: self._done(j, f))

    def _done(self, job_id: str, fut: Future) -> None:
        if not fut.cancelled() and fut.exception() is not None:  # the worker process died (not a job error)
            if not self._closing:
                log.error("the worker running job %s died: %s", job_id, fut.exception())
            self._abandon(job_id)
        with self._cond:
            self._futures.pop(job_id, None)
            owner = self._owners.pop(job_id, None)
            self._cond.notify_all()
        if owner is not None:
            self.catalog.forget_stored_bytes(owner)
        self._pump()

    def _abandon(self, job_id: str) -> None:
        """A job whose worker died or was killed: interrupted, and its folder removed (as a failed job's)."""
        self.store.finish(job_id, pb.JOB_STATE_FAILED, code="UNAVAILABLE", message=INTERRUPTED_MESSAGE,
                          interrupted=True)
        workdir = self.catalog.root.absolute(self.store.job_row(job_id)["workdir"])
        if workdir.exists() and not self.store.has_objects(job_id):
            shutil.rmtree(workdir, ignore_errors=True)

    def shutdown(self, drain_seconds: float = 0.0, stop_seconds: float = STOP_GRACE) -> None:
        """Accept no new jobs; let running ones finish for ``drain_seconds``, then interrupt them (they stop at
        their next step); a job still running ``stop_seconds`` later has its worker process killed. Queued jobs
        stay queued: they run after the restart. Returns within about ``drain_seconds + stop_seconds``."""
        with self._cond:
            self._closing = True  # nothing more is handed to a worker
        deadline = time.monotonic() + max(0.0, drain_seconds)
        self._wait_idle(deadline)
        for job_id in list(self._futures):
            self.store.request_stop(job_id, "interrupt")
        if not self._wait_idle(time.monotonic() + stop_seconds):
            log.warning("jobs %s did not stop within %g s of the request: killing their workers",
                        ", ".join(self._futures), stop_seconds)
            _kill_workers(self._pool)
            self._wait_idle(time.monotonic() + 5)  # the pool reports the dead workers: _done marks the jobs
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        if self._import_pool is not None:  # the gRPC server has stopped: open uploads were cancelled, their imports end
            procs = _workers(self._import_pool)  # before shutdown(), which forgets them
            self._import_pool.shutdown(wait=False, cancel_futures=True)
            _kill(procs, after=stop_seconds)

    def _wait_idle(self, deadline: float) -> bool:
        """Wait until no job is handed to a worker, or the deadline; whether none is."""
        with self._cond:
            while self._futures and time.monotonic() < deadline:
                self._cond.wait(timeout=min(0.2, max(0.0, deadline - time.monotonic())))
            return not self._futures

    @property
    def closing(self) -> bool:
        return self._closing

    def start_import(self, fn, *args) -> Future:
        """Start ``fn(*args)`` (an upload's import) in a process of the import pool; its Future.

        Imports have their own processes (``imports`` of them, spawned on first use): an import lasts as long as its
        client sends, and a slow or stalled client must not hold a job worker.
        """
        with self._cond:
            if self._import_pool is None:
                self._import_pool = self._new_import_pool()
            try:
                return self._import_pool.submit(fn, *args)
            except BrokenProcessPool:
                self._import_pool = self._new_import_pool()
                return self._import_pool.submit(fn, *args)

    def _new_import_pool(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=self.imports, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_die_with_server)

    # -- requests --------------------------------------------------------------------------------------------------
    def submit(self, owner: str, spec: jobs_pb2.SubmitRequest) -> pb.Job:
        if self._closing:
            raise ShuttingDownError("the server is shutting down; submit again in a moment")
        kind = kind_of(spec)
        precheck(self.catalog, owner, spec)
        if spec.timeout_seconds < 0:
            raise InvalidInputError(f"timeout_seconds must be >= 0 (0: no limit), got {spec.timeout_seconds}")
        limit = self.catalog.limits.max_jobs_per_user
        if limit and self.store.count_active(owner) >= limit:
            raise LimitError(f"you already have {limit} jobs queued or running, this server's limit per user; wait "
                             "for one to finish or cancel one")
        self.catalog.check_quota(owner, 0, "the jobs you ran")
        job_id = f"job-{uuid.uuid4().hex[:12]}"
        workdir = self.catalog.root.user_dir(owner) / job_id
        job, new = self.store.add_job(owner, KINDS[kind], spec.name or kind, spec,
                                      self.catalog.root.relative(workdir), job_id)
        if new:
            self._pump()
        return job

    def resubmit(self, owner: str, job_id: str) -> pb.Job:
        job = self.store.get_job(owner, job_id)
        if job.state in ACTIVE:
            raise StateError(f"job {job_id} is still {pb.JobState.Name(job.state)}; cancel it first")
        spec = self.store.spec(job_id)
        spec.request_id = ""
        return self.submit(owner, spec)

    def cancel(self, owner: str, job_id: str) -> pb.Job:
        job = self.store.get_job(owner, job_id)
        if job.state == pb.JOB_STATE_QUEUED:
            self.store.finish(job_id, pb.JOB_STATE_CANCELLED, code="CANCELLED", message="cancelled before it started")
        if self.store.get_job(owner, job_id).state == pb.JOB_STATE_RUNNING:
            self.store.request_stop(job_id, "cancel")
            deadline = time.monotonic() + 2  # usually enough for the next step; the caller may wait for the rest
            while self.store.get_job(owner, job_id).state in ACTIVE and time.monotonic() < deadline:
                time.sleep(0.05)
        return self.store.get_job(owner, job_id)

    def watch(self, owner: str, job_id: str, after_seq: int, is_active=lambda: True) -> Iterator[jobs_pb2.JobEvent]:
        """The job now, its progress records after ``after_seq`` as they come, then the final job."""
        job = self.store.get_job(owner, job_id)
        yield jobs_pb2.JobEvent(job=job)
        seq = after_seq
        while is_active():
            for p in self.store.progress_after(job_id, seq):
                seq = p.seq
                yield jobs_pb2.JobEvent(progress=p)
            job = self.store.get_job(owner, job_id)
            if job.state in FINAL:
                for p in self.store.progress_after(job_id, seq):
                    seq = p.seq
                    yield jobs_pb2.JobEvent(progress=p)
                yield jobs_pb2.JobEvent(job=job)
                return
            if self._closing:
                # the stream ends with the server; the client reconnects and resumes after `seq`
                raise ShuttingDownError("the server is shutting down; watch again after it restarts")
            with self._cond:
                self._cond.wait(timeout=_WATCH_POLL)


# ------------------------------------------------------------------------------------------------------------------
# the worker processes
# ------------------------------------------------------------------------------------------------------------------
class _Stop(Exception):
    """Internal: why a running job stops between two steps."""

    def __init__(self, why: str):
        super().__init__(why)
        self.why = why


_WORKER: dict = {}


def _die_with_server() -> None:
    """In a worker process (jobs or imports): end when the server ends, even by kill -9; leave SIGTERM/SIGINT to
    the server (it decides: drain, then interrupt)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass
    # PR_SET_PDEATHSIG follows the thread that spawned this process, which may end before the server does:
    # also leave as soon as the server is gone
    parent = os.getppid()

    def orphan_watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=orphan_watch, name="unwind-orphan-watch", daemon=True).start()
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the server decides: drain, then interrupt
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _workers(pool: ProcessPoolExecutor | None) -> list:
    """The processes of ``pool`` (none after its ``shutdown()``, which forgets them)."""
    return list((getattr(pool, "_processes", None) or {}).values()) if pool is not None else []


def _kill_workers(pool: ProcessPoolExecutor | None, after: float = 0.0) -> None:
    """Kill the processes of ``pool`` still alive ``after`` seconds from now (a job step or an import that does not
    end). ``ProcessPoolExecutor`` has no public way before Python 3.14 (``terminate_workers``)."""
    _kill(_workers(pool), after)


def _kill(procs: list, after: float = 0.0) -> None:
    """Kill the processes ``procs`` still alive ``after`` seconds from now."""
    end = time.monotonic() + after
    for p in procs:
        p.join(timeout=max(0.0, end - time.monotonic()))
        if p.is_alive():
            p.kill()


def _worker_init(root: str, limits: Limits, scheduler: str | None) -> None:
    """Once per job worker process: die with the server, open the store, warm imports."""
    _die_with_server()
    warnings.filterwarnings("ignore", category=UserWarning, module="napari_unwind.warp")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    data_root = DataRoot(root)
    _WORKER["catalog"] = Catalog(Store(data_root.database), data_root, limits)
    _WORKER["scheduler"] = scheduler
    import napari_unwind.segmentation  # noqa: F401 - numba kernels and the mesher load now, not in the first job
    import napari_unwind.skeleton  # noqa: F401
    import napari_unwind.warp  # noqa: F401


def _worker_run(job_id: str) -> None:
    run_job(_WORKER["catalog"], job_id, _WORKER["scheduler"])


def run_job(catalog: Catalog, job_id: str, scheduler: str | None = None) -> None:
    """Run one queued job to its end, recording everything in the store (used by the worker processes)."""
    store = catalog.store
    if not store.set_running(job_id):
        return  # cancelled while queued
    row = store.job_row(job_id)
    owner, timeout = row["owner"], float(row["timeout"])
    workdir = catalog.root.absolute(row["workdir"])
    gen = None
    try:
        workdir.mkdir(parents=True, exist_ok=True)
        ctx = TaskContext(catalog, owner, job_id, workdir, scheduler)
        # all the job's chunked dask work (refine, segment, skeleton, straighten, bend, writes) runs on the
        # server's scheduler; a cluster that loses the work ends the job with SchedulerError (UNAVAILABLE)
        with use_scheduler(scheduler):
            gen = run_task(ctx, store.spec(job_id))
            try:
                result = _advance(store, job_id, gen, timeout)
            except BaseException:
                gen.close()  # still on the scheduler: a chunk read in flight ends before its client is closed
                raise
        store.finish(job_id, pb.JOB_STATE_SUCCEEDED, result=result)
    except _Stop as stop:
        if gen is not None:
            gen.close()  # GeneratorExit inside the core: atomic_output removes the temporary output
        if stop.why == "interrupt":
            store.finish(job_id, pb.JOB_STATE_FAILED, code="UNAVAILABLE", message=INTERRUPTED_MESSAGE,
                         interrupted=True)
        else:
            store.finish(job_id, pb.JOB_STATE_CANCELLED, code="CANCELLED", message="cancelled by its owner")
    except BaseException as exc:  # noqa: BLE001 - every failure is recorded; bugs are logged with a traceback
        if gen is not None:
            gen.close()
        code, message = status_for(exc)
        if message is None:
            ref = uuid.uuid4().hex[:8]
            log.error("job %s failed (reference %s):\n%s", job_id, ref, traceback.format_exc())
            message = INTERNAL_MESSAGE.format(ref=ref)
        state = pb.JOB_STATE_CANCELLED if isinstance(exc, CancelledError) else pb.JOB_STATE_FAILED
        store.finish(job_id, state, code=code.name, message=catalog.root.scrub(message))
        if not isinstance(exc, Exception):
            raise
    finally:
        if store.job_row(job_id)["state"] != pb.JOB_STATE_SUCCEEDED and workdir.exists() \
                and not store.has_objects(job_id):
            shutil.rmtree(workdir, ignore_errors=True)  # nothing of a failed job is kept (a saved session is)


def _advance(store: Store, job_id: str, gen, timeout: float):
    """Step the job's generator to its end, storing progress; stop between two steps when asked or past its
    timeout. Returns the generator's result."""
    t0 = time.monotonic()
    last = ("", 0.0)

    def check() -> None:
        why = store.stop_requested(job_id)
        if why:
            raise _Stop(why)
        if timeout and time.monotonic() - t0 > timeout:
            raise DeadlineError(f"the job ran longer than its timeout of {timeout:g} s and was stopped")

    while True:
        check()
        try:
            with cancellation(check, _CHECK_INTERVAL):  # the core's long loops check too (progress.checkpoint)
                p = next(gen)
        except StopIteration as stop:
            return stop.value
        now = time.monotonic()
        if p.stage != last[0] or now - last[1] >= _PROGRESS_INTERVAL or (p.total and p.done >= p.total):
            store.add_progress(job_id, p.stage, p.done, p.total, p.message)
            last = (p.stage, now)


def job_workdir(root: Path, owner: str, job_id: str) -> Path:
    """Where a job writes (for admins and tests)."""
    return Path(root) / DataRoot.PRIVATE / "users" / owner / job_id
