"""The job runner: a pool of worker threads driving task generators, with cancel, timeouts, watch and drain.

A job's generator is advanced one step at a time; between two steps the runner checks for a cancel request, a
timeout or a shutdown. Stopping closes the generator, so the core's ``atomic_output`` removes its temporary
output: a cancelled or interrupted job never leaves a result that looks whole.
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
import traceback
import uuid
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

from napari_unwind.io._atomic import TMP_MARK, remove_path

from ._proto.unwind.v1 import common_pb2 as pb
from ._proto.unwind.v1 import jobs_pb2
from .catalog import Catalog
from .errors import (
    INTERNAL_MESSAGE,
    CancelledError,
    DeadlineError,
    LimitError,
    ShuttingDownError,
    StateError,
    status_for,
)
from .store import ACTIVE, FINAL, INTERRUPTED_MESSAGE
from .tasks import KINDS, TaskContext, kind_of, precheck, run_task

__all__ = ["JobManager"]

log = logging.getLogger("unwind_services.jobs")

_PROGRESS_INTERVAL = 0.1  # seconds between two stored records of the same stage


class _Stop(Exception):
    """Internal: why a running job stops between two steps."""

    def __init__(self, why: str):
        super().__init__(why)
        self.why = why


class JobManager:
    """Submit, run, cancel and watch jobs; durable through the store."""

    def __init__(self, catalog: Catalog, *, workers: int = 2, scheduler: str | None = None):
        self.catalog = catalog
        self.store = catalog.store
        self.scheduler = scheduler
        self._pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="unwind-job")
        self._stop: dict[str, str] = {}  # job id -> "cancel" | "interrupt"
        self._cond = threading.Condition()
        self._running: set[str] = set()
        self._closing = False

    # -- life cycle ------------------------------------------------------------------------------------------------
    def start(self) -> None:
        """Recover after a restart: running jobs become interrupted, leftovers go, queued jobs run again."""
        interrupted = self.store.mark_interrupted()
        for job_id in interrupted:
            log.warning("job %s was running when the server stopped: marked interrupted", job_id)
        self._sweep_leftovers()
        for job_id in self.store.queued_ids():
            self._pool.submit(self._run, job_id)

    def _sweep_leftovers(self) -> None:
        """Temporary outputs of atomic writes that a killed server left behind."""
        users = self.catalog.root.private / "users"
        for p in list(users.rglob(f"*{TMP_MARK}")):
            log.warning("removing the partial output %s", p)
            remove_path(p)
        tmp = self.catalog.root.tmp
        for p in tmp.iterdir():
            remove_path(p)

    def shutdown(self, drain_seconds: float = 0.0) -> None:
        """Accept no new jobs; let running ones finish for ``drain_seconds``, then interrupt them."""
        with self._cond:
            self._closing = True
            deadline = time.monotonic() + max(0.0, drain_seconds)
            while self._running and time.monotonic() < deadline:
                self._cond.wait(timeout=min(0.2, max(0.0, deadline - time.monotonic())))
            for job_id in self._running:
                self._stop[job_id] = "interrupt"
            self._cond.notify_all()
        self._pool.shutdown(wait=True, cancel_futures=True)

    @property
    def closing(self) -> bool:
        return self._closing

    # -- requests --------------------------------------------------------------------------------------------------
    def submit(self, owner: str, spec: jobs_pb2.SubmitRequest) -> pb.Job:
        if self._closing:
            raise ShuttingDownError("the server is shutting down; submit again in a moment")
        kind = kind_of(spec)
        precheck(self.catalog, owner, spec)
        if spec.timeout_seconds < 0:
            from napari_unwind.errors import InvalidInputError

            raise InvalidInputError(f"timeout_seconds must be >= 0 (0: no limit), got {spec.timeout_seconds}")
        limit = self.catalog.limits.max_jobs_per_user
        if limit and self.store.count_active(owner) >= limit:
            raise LimitError(f"you already have {limit} jobs queued or running, this server's limit per user; wait "
                             "for one to finish or cancel one")
        job_id = f"job-{uuid.uuid4().hex[:12]}"
        workdir = self.catalog.root.user_dir(owner) / job_id
        job, new = self.store.add_job(owner, KINDS[kind], spec.name or kind, spec,
                                      self.catalog.root.relative(workdir), job_id)
        if new:
            self._pool.submit(self._run, job.id)
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
        elif job.state == pb.JOB_STATE_RUNNING:
            with self._cond:
                self._stop.setdefault(job_id, "cancel")
            deadline = time.monotonic() + 2  # usually enough for the next step; the caller may wait for the rest
            while self.store.get_job(owner, job_id).state in ACTIVE and time.monotonic() < deadline:
                with self._cond:
                    self._cond.wait(timeout=0.1)
        self._notify()
        return self.store.get_job(owner, job_id)

    def watch(self, owner: str, job_id: str, after_seq: int, is_active=lambda: True) -> Iterator[jobs_pb2.JobEvent]:
        """Progress records after ``after_seq`` as they come, then the final job."""
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
                self._cond.wait(timeout=0.5)

    def _notify(self) -> None:
        with self._cond:
            self._cond.notify_all()

    # -- the worker ------------------------------------------------------------------------------------------------
    def _run(self, job_id: str) -> None:
        if self._closing or not self.store.set_running(job_id):
            return
        row = self.store.job_row(job_id)
        owner, timeout = row["owner"], float(row["timeout"])
        workdir = self.catalog.root.absolute(row["workdir"])
        with self._cond:
            self._running.add(job_id)
        self._notify()
        gen = None
        try:
            workdir.mkdir(parents=True, exist_ok=True)
            spec = self.store.spec(job_id)
            ctx = TaskContext(self.catalog, owner, job_id, workdir, self.scheduler)
            gen = run_task(ctx, spec)
            t0 = time.monotonic()
            last = ("", 0.0)
            while True:
                why = self._stop.get(job_id)
                if why:
                    raise _Stop(why)
                if timeout and time.monotonic() - t0 > timeout:
                    raise DeadlineError(f"the job ran longer than its timeout of {timeout:g} s and was stopped")
                try:
                    p = next(gen)
                except StopIteration as stop:
                    result = stop.value
                    break
                now = time.monotonic()
                if p.stage != last[0] or now - last[1] >= _PROGRESS_INTERVAL or (p.total and p.done >= p.total):
                    self.store.add_progress(job_id, p.stage, p.done, p.total, p.message)
                    last = (p.stage, now)
                    self._notify()
            self.store.finish(job_id, pb.JOB_STATE_SUCCEEDED, result=result)
        except _Stop as stop:
            if gen is not None:
                gen.close()  # GeneratorExit inside the core: atomic_output removes the temporary output
            if stop.why == "interrupt":
                self.store.finish(job_id, pb.JOB_STATE_FAILED, code="UNAVAILABLE", message=INTERRUPTED_MESSAGE,
                                  interrupted=True)
            else:
                self.store.finish(job_id, pb.JOB_STATE_CANCELLED, code="CANCELLED", message="cancelled by its owner")
        except BaseException as exc:  # noqa: BLE001 - every failure is recorded; bugs are logged with a traceback
            if gen is not None:
                gen.close()
            code, message = status_for(exc)
            if message is None:
                ref = uuid.uuid4().hex[:8]
                log.error("job %s failed (reference %s):\n%s", job_id, ref, traceback.format_exc())
                message = INTERNAL_MESSAGE.format(ref=ref)
            state = pb.JOB_STATE_CANCELLED if isinstance(exc, CancelledError) else pb.JOB_STATE_FAILED
            self.store.finish(job_id, state, code=code.name, message=self.catalog.root.scrub(message))
            if not isinstance(exc, Exception):
                raise
        finally:
            with self._cond:
                self._running.discard(job_id)
                self._stop.pop(job_id, None)
                self._cond.notify_all()
            job = self.store.job_row(job_id)
            if job["state"] != pb.JOB_STATE_SUCCEEDED and workdir.exists() and not self.store.has_objects(job_id):
                shutil.rmtree(workdir, ignore_errors=True)  # nothing of a failed job is kept (a saved session is)

    @staticmethod
    def state_name(state: int) -> str:
        return pb.JobState.Name(state)

