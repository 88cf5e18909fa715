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

from napari_unwind.errors import InvalidInputError

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
