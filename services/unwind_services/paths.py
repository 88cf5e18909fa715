"""The data root: every path a client names is confined to it, and the server's own files live in ``.unwind/``.

    DATA_ROOT/                      scans an admin puts there (Register takes paths relative to the root)
    DATA_ROOT/.unwind/unwind.sqlite the job and object table (SQLite, WAL)
    DATA_ROOT/.unwind/users/U/...   uploads and job outputs of user U
    DATA_ROOT/.unwind/tmp/          staging of uploads and downloads
"""

from __future__ import annotations

import os
import re
from pathlib import Path, PurePosixPath

from napari_unwind.errors import InvalidInputError, UnwindError

from .errors import PermissionDeniedError

__all__ = ["DataRoot", "check_file_name"]

_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.{}:+-]{0,127}$")


def check_file_name(name: str, what: str = "name") -> str:
    """A plain file name (no folder, no leading dot): what clients may call their outputs and volumes."""
    if not isinstance(name, str) or not _NAME_RE.match(name) or ".." in name:
        raise InvalidInputError(f"{what} must be a plain file name (letters, digits, '_', '-', '.', no folders, "
                                f"not starting with '.'), got {name!r}")
    return name


class DataRoot:
    """Path confinement to one folder."""

    PRIVATE = ".unwind"

    def __init__(self, root: str | os.PathLike):
        root = Path(root).expanduser()
        root.mkdir(parents=True, exist_ok=True)
        self.root = root.resolve()
        self.private = self.root / self.PRIVATE
        for d in (self.private, self.private / "users", self.private / "tmp"):
            d.mkdir(exist_ok=True)
        os.chmod(self.private, 0o700)

    @property
    def database(self) -> Path:
        return self.private / "unwind.sqlite"

    @property
    def tmp(self) -> Path:
        return self.private / "tmp"

    def user_dir(self, user: str) -> Path:
        d = self.private / "users" / user
        d.mkdir(parents=True, exist_ok=True)
        return d

    def inside(self, path: Path) -> bool:
        return os.path.commonpath([str(path), str(self.root)]) == str(self.root)

    def resolve_client_path(self, rel: str) -> Path:
        """The absolute path of a client's path relative to the root; refuses ``..``, absolute paths, symlink
        escapes and the server's own folder (:class:`PermissionDeniedError`)."""
        if not isinstance(rel, str) or not rel.strip() or "\x00" in rel:
            raise InvalidInputError(f"give a path relative to the server's data root, got {rel!r}")
        pure = PurePosixPath(rel.replace("\\", "/"))
        if pure.is_absolute() or re.match(r"^[A-Za-z]:", rel):
            raise PermissionDeniedError(f"absolute paths are not allowed, got {rel!r}; give a path relative to the "
                                        "server's data root")
        if ".." in pure.parts:
            raise PermissionDeniedError(f"'..' is not allowed in paths, got {rel!r}; give a path inside the "
                                        "server's data root")
        full = Path(os.path.realpath(self.root / pure))
        if not self.inside(full):
            raise PermissionDeniedError(f"{rel!r} leads outside the server's data root (through a symbolic link)")
        if os.path.commonpath([str(full), str(self.private)]) == str(self.private):
            raise PermissionDeniedError(f"{rel!r} is inside the server's own folder {self.PRIVATE}/")
        return full

    def check_scan(self, path: Path, *, within: Path | None = None) -> None:
        """Refuse (:class:`PermissionDeniedError`) a scan that would make the server read outside where it may:
        every file the scan consists of is resolved (symbolic links at any depth) and must lie inside ``within``
        (a user's own folder) or, by default, inside the data root and outside the server's own folder.

        What a scan consists of: a folder (an OME-Zarr store, a DICOM series, a slice stack) is walked whole,
        following links to folders (each walked once); a file brings the files its header names (an NRRD's
        ``data file`` entries, a ``.dat``'s ``ObjectFileName``, a stack's numbered siblings, a DICOM series' files).
        The message never names a path outside the root.
        """
        from napari_unwind.session import scan_members

        base = os.path.realpath(within or self.root)
        private = os.path.realpath(self.private)
        where = "your own folder of the server's data root" if within is not None else "the server's data root"

        def check(p: Path, what: str) -> None:
            real = os.path.realpath(p)
            if os.path.commonpath([real, base]) != base or (
                    within is None and os.path.commonpath([real, private]) == private):
                raise PermissionDeniedError(f"{what} lies outside {where} (through a header's file name or a "
                                            "symbolic link): the server reads nothing there")

        path = Path(path)
        check(path, "the scan")
        if not path.exists():
            return  # nothing to read; the reader says it is missing
        if path.is_dir():
            seen: set[str] = set()
            for folder, dirs, files in os.walk(path, followlinks=True):
                real = os.path.realpath(folder)
                if real in seen:  # a link back to a folder already walked
                    dirs[:] = []
                    continue
                seen.add(real)
                check(Path(folder), "a folder of the scan")
                for name in files:
                    check(Path(folder) / name, "a file of the scan")
            return
        for member in scan_members(path):
            check(member, "a file the scan's header names")

    def confinement(self, *, within: Path | None = None):
        """The :class:`~napari_unwind.io._files.ReadConfinement` :meth:`check_scan` applies, for the readers to keep:
        a volume opened under it (``confined_reads``) checks every file again at each chunk read, on the opened
        descriptor, so a symbolic link swapped in after Register and after the open is not followed."""
        from napari_unwind.io._files import ReadConfinement

        if within is not None:
            return ReadConfinement(os.path.realpath(within), "", "your own folder of the server's data root")
        return ReadConfinement(os.path.realpath(self.root), os.path.realpath(self.private), "the server's data root")

    def check_path(self, path: Path, *, within: Path) -> None:
        """The path itself (resolved) lies inside ``within``, else :class:`PermissionDeniedError`."""
        base, real = os.path.realpath(within), os.path.realpath(path)
        if os.path.commonpath([real, base]) != base:
            raise PermissionDeniedError("the volume lies outside your own folder of the server's data root")

    def relative(self, path: Path) -> str:
        return os.path.relpath(path, self.root)

    def absolute(self, rel: str) -> Path:
        """A path stored in the database (relative to the root) as an absolute path, checked to stay inside."""
        full = Path(os.path.realpath(self.root / rel))
        if not self.inside(full):  # pragma: no cover - the database only holds paths the server wrote
            raise PermissionDeniedError(f"{rel!r} leads outside the server's data root")
        return full

    def scrub(self, message: str) -> str:
        """A message without the server's absolute paths (clients see paths relative to the data root)."""
        return message.replace(str(self.root) + os.sep, "").replace(str(self.root), ".")


class RootLock:
    """One server per data root: an exclusive ``flock`` on ``<root>/.unwind/server.lock``, taken before the server
    touches its database or its jobs, held for the server's life and released by the kernel when the process ends
    however it ends (``kill -9`` included). The file names the holder (pid, host, address, start time) so that a
    second server refuses in one line that says who holds the root.

    A forked child (a job worker) drops its copy of the descriptor at once, so a worker that outlives the server
    for a moment never holds the root for it.
    """

    NAME = "server.lock"

    def __init__(self, root: DataRoot):
        import fcntl
        import json
        import socket
        import time

        self.path = root.private / self.NAME
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = json.loads(os.pread(fd, 4096, 0) or b"{}")
            except (ValueError, OSError):
                holder = {}
            os.close(fd)
            who = ", ".join(f"{k} {holder[k]}" for k in ("pid", "host", "address", "since") if holder.get(k))
            raise UnwindError(f"another napari-unwind server ({who or 'holder unknown'}) serves the data root "
                              f"{root.root}: stop it first, or give this one another --data-root") from None
        except BaseException:
            os.close(fd)
            raise
        self._fd: int | None = fd
        self._holder = {"pid": os.getpid(), "host": socket.gethostname(),
                        "since": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        self._write()
        os.register_at_fork(after_in_child=self._forget)

    def _write(self) -> None:
        import json

        if self._fd is None:
            return
        data = json.dumps(self._holder).encode() + b"\n"
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, data, 0)

    def describe(self, address: str) -> None:
        """Record the address the server listens on (after it is bound)."""
        self._holder["address"] = address
        self._write()

    def _forget(self) -> None:
        if self._fd is not None:
            try:
                os.close(self._fd)
            except OSError:
                pass
            self._fd = None

    def release(self) -> None:
        """Give the root up (the server stopped); the file stays, empty of a holder."""
        if self._fd is None:
            return
        try:
            os.ftruncate(self._fd, 0)
        except OSError:
            pass
        self._forget()

