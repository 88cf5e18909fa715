"""The durable table of jobs and objects (volumes, segmentations, sessions): SQLite in WAL mode under the data root.

Every row has an owner; every lookup takes the caller's user, so another user's row is simply not found. Progress
records of each job are kept (throttled) so that ``Watch`` can replay them after a reconnect or a restart.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ._proto.unwind.v1 import common_pb2 as pb
from ._proto.unwind.v1 import jobs_pb2
from .errors import NotFoundError

__all__ = ["Store", "ObjectRow", "ACTIVE", "FINAL", "INTERRUPTED_MESSAGE"]

ACTIVE = (pb.JOB_STATE_QUEUED, pb.JOB_STATE_RUNNING)
FINAL = (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED, pb.JOB_STATE_CANCELLED)
INTERRUPTED_MESSAGE = ("interrupted: the server stopped while this job ran; its partial output was removed. "
                       "Resubmit it (unwind jobs resubmit ID, or JobService.Resubmit)")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS objects (
    id TEXT PRIMARY KEY, owner TEXT NOT NULL, kind TEXT NOT NULL, name TEXT NOT NULL, path TEXT NOT NULL,
    meta TEXT NOT NULL DEFAULT '{}', job_id TEXT NOT NULL DEFAULT '', created REAL NOT NULL);
CREATE INDEX IF NOT EXISTS objects_owner ON objects(owner, kind, created);
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY, owner TEXT NOT NULL, kind INTEGER NOT NULL, state INTEGER NOT NULL, name TEXT NOT NULL,
    spec BLOB NOT NULL, request_id TEXT NOT NULL DEFAULT '', timeout REAL NOT NULL DEFAULT 0,
    created REAL NOT NULL, started REAL NOT NULL DEFAULT 0, finished REAL NOT NULL DEFAULT 0,
    error_code TEXT NOT NULL DEFAULT '', error_message TEXT NOT NULL DEFAULT '', interrupted INTEGER NOT NULL DEFAULT 0,
    result BLOB, last_seq INTEGER NOT NULL DEFAULT 0, workdir TEXT NOT NULL DEFAULT '',
    stop TEXT NOT NULL DEFAULT '');
CREATE INDEX IF NOT EXISTS jobs_owner ON jobs(owner, created);
CREATE UNIQUE INDEX IF NOT EXISTS jobs_request ON jobs(owner, request_id) WHERE request_id != '';
CREATE TABLE IF NOT EXISTS progress (
    job_id TEXT NOT NULL, seq INTEGER NOT NULL, stage TEXT NOT NULL, done INTEGER NOT NULL, total INTEGER NOT NULL,
    message TEXT NOT NULL, t REAL NOT NULL, PRIMARY KEY (job_id, seq));
"""


@dataclass
class ObjectRow:
    id: str
    owner: str
    kind: str
    name: str
    path: str
    meta: dict[str, Any] = field(default_factory=dict)
    job_id: str = ""
    created: float = 0.0


def new_id(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


class Store:
    """Thread-safe access to the SQLite file (one connection, one lock; WAL keeps readers of backups unblocked)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._lock = threading.RLock()
        self._db = sqlite3.connect(str(self.path), check_same_thread=False, isolation_level=None, timeout=30)
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(_SCHEMA)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def _query(self, sql: str, args: tuple = ()) -> list[sqlite3.Row]:
        with self._lock:
            return self._db.execute(sql, args).fetchall()

    # -- objects ---------------------------------------------------------------------------------------------------
    def add_object(self, owner: str, kind: str, name: str, path: str, meta: dict | None = None, job_id: str = "",
                   object_id: str | None = None) -> ObjectRow:
        row = ObjectRow(object_id or new_id(kind[:3]), owner, kind, name, path, dict(meta or {}), job_id, time.time())
        with self._tx() as db:
            db.execute("INSERT INTO objects VALUES (?,?,?,?,?,?,?,?)",
                       (row.id, owner, kind, name, path, json.dumps(row.meta), job_id, row.created))
        return row

    def update_meta(self, owner: str, object_id: str, meta: dict) -> None:
        with self._tx() as db:
            db.execute("UPDATE objects SET meta=? WHERE id=? AND owner=?", (json.dumps(meta), object_id, owner))

    def get_object(self, owner: str, object_id: str, kind: str) -> ObjectRow:
        rows = self._query("SELECT * FROM objects WHERE id=? AND owner=? AND kind=?", (object_id, owner, kind))
        if not rows:
            raise NotFoundError(f"no {kind} with id {object_id!r}" + ("" if object_id else " (give an id)"))
        return self._object(rows[0])

    def list_objects(self, owner: str, kind: str, limit: int = 100) -> list[ObjectRow]:
        rows = self._query("SELECT * FROM objects WHERE owner=? AND kind=? ORDER BY created DESC LIMIT ?",
                           (owner, kind, int(limit)))
        return [self._object(r) for r in rows]

    def has_objects(self, job_id: str) -> bool:
        return bool(self._query("SELECT 1 FROM objects WHERE job_id=? LIMIT 1", (job_id,)))

    @staticmethod
    def _object(r: sqlite3.Row) -> ObjectRow:
        return ObjectRow(r["id"], r["owner"], r["kind"], r["name"], r["path"], json.loads(r["meta"]), r["job_id"],
                         r["created"])

    # -- jobs ------------------------------------------------------------------------------------------------------
    def add_job(self, owner: str, kind: int, name: str, spec: jobs_pb2.SubmitRequest, workdir: str,
                job_id: str) -> tuple[pb.Job, bool]:
        """Insert a queued job; with a request id already used by this owner, return that job instead.

        Returns the job and whether it is new.
        """
        with self._tx() as db:
            if spec.request_id:
                old = db.execute("SELECT * FROM jobs WHERE owner=? AND request_id=?",
                                 (owner, spec.request_id)).fetchone()
                if old is not None:
                    return self._job(old), False
            db.execute("INSERT INTO jobs (id, owner, kind, state, name, spec, request_id, timeout, created, workdir) "
                       "VALUES (?,?,?,?,?,?,?,?,?,?)",
                       (job_id, owner, kind, pb.JOB_STATE_QUEUED, name, spec.SerializeToString(), spec.request_id,
                        float(spec.timeout_seconds), time.time(), workdir))
        return self.get_job(owner, job_id), True

    def count_active(self, owner: str) -> int:
        return self._query("SELECT COUNT(*) FROM jobs WHERE owner=? AND state IN (?,?)", (owner, *ACTIVE))[0][0]

    def job_row(self, job_id: str) -> sqlite3.Row:
        rows = self._query("SELECT * FROM jobs WHERE id=?", (job_id,))
        if not rows:
            raise NotFoundError(f"no job with id {job_id!r}")
        return rows[0]

    def get_job(self, owner: str, job_id: str) -> pb.Job:
        rows = self._query("SELECT * FROM jobs WHERE id=? AND owner=?", (job_id, owner))
        if not rows:
            raise NotFoundError(f"no job with id {job_id!r}" + ("" if job_id else " (give an id)"))
        return self._job(rows[0])

    def list_jobs(self, owner: str, state: int = 0, limit: int = 100) -> list[pb.Job]:
        sql, args = "SELECT * FROM jobs WHERE owner=?", [owner]
        if state:
            sql += " AND state=?"
            args.append(state)
        rows = self._query(sql + " ORDER BY created DESC LIMIT ?", (*args, int(limit)))
        return [self._job(r) for r in rows]

    def queued_jobs(self) -> list[tuple[str, str]]:
        """(id, owner) of every queued job, oldest first."""
        return [(r[0], r[1]) for r in self._query("SELECT id, owner FROM jobs WHERE state=? ORDER BY created",
                                                  (pb.JOB_STATE_QUEUED,))]

    def queued_ids(self) -> list[str]:
        return [r[0] for r in self._query("SELECT id FROM jobs WHERE state=? ORDER BY created", (pb.JOB_STATE_QUEUED,))]

    def set_running(self, job_id: str) -> bool:
        """QUEUED -> RUNNING; False when the job is no longer queued (cancelled meanwhile)."""
        with self._tx() as db:
            cur = db.execute("UPDATE jobs SET state=?, started=? WHERE id=? AND state=?",
                             (pb.JOB_STATE_RUNNING, time.time(), job_id, pb.JOB_STATE_QUEUED))
            return cur.rowcount == 1

    def finish(self, job_id: str, state: int, *, result: pb.JobResult | None = None, code: str = "",
               message: str = "", interrupted: bool = False, only_if_active: bool = True) -> bool:
        with self._tx() as db:
            sql = ("UPDATE jobs SET state=?, finished=?, result=?, error_code=?, error_message=?, interrupted=? "
                   "WHERE id=?")
            args: tuple = (state, time.time(), None if result is None else result.SerializeToString(), code, message,
                           int(interrupted), job_id)
            if only_if_active:
                sql += " AND state IN (?,?)"
                args += ACTIVE
            return db.execute(sql, args).rowcount == 1

    def request_stop(self, job_id: str, why: str) -> None:
        """Ask the worker running a job to stop between two steps (``"cancel"`` or ``"interrupt"``)."""
        with self._tx() as db:
            db.execute("UPDATE jobs SET stop=? WHERE id=? AND stop=''", (why, job_id))

    def stop_requested(self, job_id: str) -> str:
        return self._query("SELECT stop FROM jobs WHERE id=?", (job_id,))[0][0]

    def mark_interrupted(self) -> list[str]:
        """At start-up: every job left RUNNING by a stopped server becomes FAILED, interrupted. Returns their ids."""
        with self._tx() as db:
            ids = [r[0] for r in db.execute("SELECT id FROM jobs WHERE state=?", (pb.JOB_STATE_RUNNING,))]
            db.execute("UPDATE jobs SET state=?, finished=?, error_code='UNAVAILABLE', error_message=?, interrupted=1 "
                       "WHERE state=?", (pb.JOB_STATE_FAILED, time.time(), INTERRUPTED_MESSAGE, pb.JOB_STATE_RUNNING))
        return ids

    def add_progress(self, job_id: str, stage: str, done: int, total: int, message: str) -> int:
        with self._tx() as db:
            seq = db.execute("SELECT last_seq FROM jobs WHERE id=?", (job_id,)).fetchone()[0] + 1
            db.execute("INSERT INTO progress VALUES (?,?,?,?,?,?,?)",
                       (job_id, seq, stage, int(done), int(total), message, time.time()))
            db.execute("UPDATE jobs SET last_seq=? WHERE id=?", (seq, job_id))
        return seq

    def progress_after(self, job_id: str, after_seq: int, limit: int = 500) -> list[pb.Progress]:
        rows = self._query("SELECT * FROM progress WHERE job_id=? AND seq>? ORDER BY seq LIMIT ?",
                           (job_id, int(after_seq), limit))
        return [pb.Progress(stage=r["stage"], done=r["done"], total=r["total"], message=r["message"], seq=r["seq"])
                for r in rows]

    def _job(self, r: sqlite3.Row) -> pb.Job:
        job = pb.Job(id=r["id"], kind=r["kind"], state=r["state"], name=r["name"], interrupted=bool(r["interrupted"]),
                     created=r["created"], started=r["started"], finished=r["finished"])
        if r["last_seq"]:
            last = self._query("SELECT * FROM progress WHERE job_id=? AND seq=?", (r["id"], r["last_seq"]))
            if last:
                p = last[0]
                job.progress.CopyFrom(pb.Progress(stage=p["stage"], done=p["done"], total=p["total"],
                                                  message=p["message"], seq=p["seq"]))
        if r["error_code"]:
            job.error.CopyFrom(pb.JobError(code=r["error_code"], message=r["error_message"]))
        if r["result"]:
            job.result.ParseFromString(r["result"])
        return job

    def spec(self, job_id: str) -> jobs_pb2.SubmitRequest:
        spec = jobs_pb2.SubmitRequest()
        spec.ParseFromString(self.job_row(job_id)["spec"])
        return spec
