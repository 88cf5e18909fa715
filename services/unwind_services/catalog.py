"""Objects a user owns: volumes, segmentations and sessions, as rows in the store and files under the data root."""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume, open_volume
from napari_unwind.io._files import confined_reads

from .errors import LimitError
from .paths import DataRoot
from .store import ObjectRow, Store

__all__ = ["Catalog", "Limits"]


#: Seconds a user's stored bytes are remembered before the user's folder is measured again.
STORED_BYTES_TTL = 10.0


#: The smallest message limit a server may have: clients send smaller messages to a server whose limit is below
#: theirs (raw voxels in pieces of 64 KiB or more, MapPoints in batches of 1000 points or more).
MIN_MESSAGE_BYTES = 256 * 1024
DEFAULT_MESSAGE_BYTES = 64 * 1024**2


@dataclass(frozen=True)
class Limits:
    """What one server accepts, in total and per user (0: no limit, unless said otherwise)."""

    max_upload_bytes: int = 8 * 1024**3
    max_voxels: int = 4 * 1024**3
    max_message_bytes: int = DEFAULT_MESSAGE_BYTES
    max_jobs_per_user: int = 4  # queued or running
    max_running_per_user: int = 0  # 0: half of the job workers, at least 1 (see running_per_user)
    max_uploads_per_user: int = 1  # uploads in progress at once
    max_stored_bytes_per_user: int = 0  # what the server keeps for a user: uploads and job outputs
    max_calls_per_user: int = 16  # calls in progress at once (streams included); health and reflection apart
    max_call_rate_per_user: float = 50.0  # calls started per second (bursts of two seconds' worth)
    upload_idle_seconds: float = 30.0  # an upload that sends nothing for this long is aborted
    download_idle_seconds: float = 30.0  # a download whose client reads nothing for this long is cancelled

    def __post_init__(self) -> None:
        for name in ("max_upload_bytes", "max_voxels", "max_message_bytes", "max_jobs_per_user",
                     "max_running_per_user", "max_uploads_per_user", "max_stored_bytes_per_user",
                     "max_calls_per_user", "max_call_rate_per_user", "upload_idle_seconds", "download_idle_seconds"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or value < 0:
                raise InvalidInputError(f"{name} must be a number >= 0 (0: no limit), got {value!r}")
        if 0 < self.max_message_bytes < MIN_MESSAGE_BYTES:  # a job's result, a session, must fit in one message
            raise InvalidInputError(f"max_message_bytes must be at least {MIN_MESSAGE_BYTES} (256 KiB), or 0 for "
                                    f"the default, got {self.max_message_bytes!r}")

    @property
    def message_bytes(self) -> int:
        """Bytes a gRPC message may hold on this server (``max_message_bytes``, 0 for the default 64 MiB)."""
        return int(self.max_message_bytes) or DEFAULT_MESSAGE_BYTES

    def running_per_user(self, workers: int) -> int:
        """Jobs of one user running at once: the limit given, else half of the ``workers`` (at least 1), so that
        one user's queue never holds every worker."""
        return int(self.max_running_per_user) or max(1, int(workers) // 2)

    def check_voxels(self, shape: Any, what: str) -> None:
        n = int(np.prod([int(s) for s in shape], dtype=object))
        if self.max_voxels and n > self.max_voxels:
            raise LimitError(f"{what} has {n} voxels, more than this server's limit of {self.max_voxels}; ask its "
                             "administrator, or crop the scan first")


def _open(path: Path) -> Volume:
    """A stored volume; a multi-channel image (a straighten job with channels) is seen as its first channel, the
    scan's (its download is the whole image)."""
    from napari_unwind.io._formats import detect_format
    from napari_unwind.io.channels import _count

    if path.exists() and _count(path, detect_format(path), {}) > 1:
        return open_volume(path, channel=0)
    return open_volume(path)


class Catalog:
    """Look-ups by owner (another user's id is not found) and registration of new objects."""

    def __init__(self, store: Store, root: DataRoot, limits: Limits):
        self.store, self.root, self.limits = store, root, limits
        self._locks: dict[str, threading.Lock] = {}
        self._locks_guard = threading.Lock()
        self._stored: dict[str, tuple[float, int]] = {}  # owner -> (when measured, bytes)

    def lock(self, object_id: str) -> threading.Lock:
        with self._locks_guard:
            return self._locks.setdefault(object_id, threading.Lock())

    def path(self, row: ObjectRow) -> Path:
        return self.root.absolute(row.path)

    def volume(self, owner: str, volume_id: str) -> tuple[ObjectRow, Volume]:
        row = self.store.get_object(owner, volume_id, "volume")
        path = self.path(row)
        self.check(owner, row, path)
        with confined_reads(self.confinement(owner, row.meta.get("origin"))):  # every chunk read checked again
            return row, _open(path)

    def confinement(self, owner: str, origin: str | None):
        """Where the files of a volume may lie: a registered scan in the data root outside ``.unwind/``, what the
        server wrote for ``owner`` in their own folder."""
        if origin == "register":
            return self.root.confinement()
        return self.root.confinement(within=self.root.user_dir(owner))

    def check(self, owner: str, row: ObjectRow, path: Path) -> None:
        """Every file a registered volume reads is where it may be, checked at each open (a registered file may
        have been changed since by whoever can write the data root). What the server wrote for a user (uploads,
        job outputs: checked whole when added) lies in that user's folder, which no client writes into: only its
        path is checked here, so that listing many volumes does not walk every store."""
        own = self.root.user_dir(owner)
        if row.meta.get("origin") == "register":
            self.root.check_scan(path)
        else:
            self.root.check_path(path, within=own)

    def add_volume(self, owner: str, path: Path, name: str, origin: str, job_id: str = "",
                   object_id: str | None = None) -> tuple[ObjectRow, Volume]:
        if origin != "register":  # the server wrote it, in the owner's folder (Register checks before this)
            self.root.check_scan(path, within=self.root.user_dir(owner))
        with confined_reads(self.confinement(owner, origin)):
            volume = _open(path)
        self.limits.check_voxels(volume.shape, f"the volume {name!r}")
        row = self.store.add_object(owner, "volume", name, self.root.relative(path), {"origin": origin}, job_id,
                                    object_id=object_id)
        return row, volume

    # -- the stored-bytes quota ---------------------------------------------------------------------------------
    def stored_bytes(self, owner: str, fresh: bool = False) -> int:
        """Bytes under the owner's folder (uploads, job outputs and their temporary files), measured at most every
        :data:`STORED_BYTES_TTL` seconds (``fresh``: now). Registered scans are the administrator's: not counted."""
        now = time.monotonic()
        with self._locks_guard:
            cached = self._stored.get(owner)
        if cached is not None and not fresh and now - cached[0] < STORED_BYTES_TTL:
            return cached[1]
        total = _du(self.root.user_dir(owner))
        with self._locks_guard:
            self._stored[owner] = (now, total)
        return total

    def forget_stored_bytes(self, owner: str) -> None:
        """The owner's folder changed (an upload or a job ended): measure it again at the next check."""
        with self._locks_guard:
            self._stored.pop(owner, None)

    def check_quota(self, owner: str, adding: int = 0, what: str = "this") -> None:
        """LimitError when the owner's stored bytes plus ``adding`` exceed the per-user quota."""
        quota = self.limits.max_stored_bytes_per_user
        if not quota:
            return
        used = self.stored_bytes(owner)
        if used + adding > quota:
            raise LimitError(f"your data on this server would be {used + adding} bytes with {what}, more than your "
                             f"quota of {quota}; ask the server's administrator to remove data you no longer need or "
                             "to raise the quota")

    def segmentation(self, owner: str, segmentation_id: str) -> ObjectRow:
        return self.store.get_object(owner, segmentation_id, "segmentation")

    def session(self, owner: str, session_id: str):
        from napari_unwind.session import load_session

        row = self.store.get_object(owner, session_id, "session")
        return row, load_session(self.path(row))


def _du(folder: Path) -> int:
    """Bytes of the files under ``folder`` (symbolic links not followed, files vanishing meanwhile skipped)."""
    total, stack = 0, [str(folder)]
    while stack:
        try:
            entries = os.scandir(stack.pop())
        except OSError:
            continue
        with entries:
            for e in entries:
                try:
                    if e.is_dir(follow_symlinks=False):
                        stack.append(e.path)
                    elif e.is_file(follow_symlinks=False):
                        total += e.stat(follow_symlinks=False).st_size
                except OSError:
                    continue
    return total
