"""Objects a user owns: volumes, segmentations and sessions, as rows in the store and files under the data root."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from napari_unwind.io import Volume, open_volume
from napari_unwind.io._files import confined_reads

from .errors import LimitError
from .paths import DataRoot
from .store import ObjectRow, Store

__all__ = ["Catalog", "Limits"]


@dataclass(frozen=True)
class Limits:
    """What one server accepts (0: no limit)."""

    max_upload_bytes: int = 8 * 1024**3
    max_voxels: int = 4 * 1024**3
    max_message_bytes: int = 64 * 1024**2
    max_jobs_per_user: int = 4

    def check_voxels(self, shape: Any, what: str) -> None:
        n = int(np.prod([int(s) for s in shape], dtype=object))
        if self.max_voxels and n > self.max_voxels:
            raise LimitError(f"{what} has {n} voxels, more than this server's limit of {self.max_voxels}; ask its "
                             "administrator, or crop the scan first")


class Catalog:
    """Look-ups by owner (another user's id is not found) and registration of new objects."""

    def __init__(self, store: Store, root: DataRoot, limits: Limits):
        self.store, self.root, self.limits = store, root, limits
        self._locks: dict[str, threading.Lock] = {}
        self._locks_guard = threading.Lock()

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
            return row, open_volume(path)

    def confinement(self, owner: str, origin: str | None):
        """Where the files of a volume may lie: a registered scan in the data root outside ``.unwind/``, what the
        server wrote for ``owner`` in their own folder."""
        if origin == "register":
            return self.root.confinement()
        return self.root.confinement(within=self.root.private / "users" / owner)

    def check(self, owner: str, row: ObjectRow, path: Path) -> None:
        """Every file a registered volume reads is where it may be, checked at each open (a registered file may
        have been changed since by whoever can write the data root). What the server wrote for a user (uploads,
        job outputs: checked whole when added) lies in that user's folder, which no client writes into: only its
        path is checked here, so that listing many volumes does not walk every store."""
        own = self.root.private / "users" / owner
        if row.meta.get("origin") == "register":
            self.root.check_scan(path)
        else:
            self.root.check_path(path, within=own)

    def add_volume(self, owner: str, path: Path, name: str, origin: str, job_id: str = "",
                   object_id: str | None = None) -> tuple[ObjectRow, Volume]:
        if origin != "register":  # the server wrote it, in the owner's folder (Register checks before this)
            self.root.check_scan(path, within=self.root.private / "users" / owner)
        with confined_reads(self.confinement(owner, origin)):
            volume = open_volume(path)
        self.limits.check_voxels(volume.shape, f"the volume {name!r}")
        row = self.store.add_object(owner, "volume", name, self.root.relative(path), {"origin": origin}, job_id,
                                    object_id=object_id)
        return row, volume

    def segmentation(self, owner: str, segmentation_id: str) -> ObjectRow:
        return self.store.get_object(owner, segmentation_id, "segmentation")

    def session(self, owner: str, session_id: str):
        from napari_unwind.session import load_session

        row = self.store.get_object(owner, session_id, "session")
        return row, load_session(self.path(row))
