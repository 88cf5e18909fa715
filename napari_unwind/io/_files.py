"""Checks a reader makes on the files a scan names before it reads them (issue 20: metadata that lies).

A path given by the user, a data file named in a header (NRRD ``data file:``, ``.dat`` ``ObjectFileName``) and a
zarr chunk are opened only when they are regular files: a named pipe would block the reader for ever, a device or
a socket would stream without end. :func:`open_regular` opens without blocking and checks what it opened, so
there is no window between the check and the read. :func:`skip_lines` skips a header's ``line skip`` without
reading past the end of the file, and :func:`check_room` refuses, before anything is written, an output that
cannot fit on its disk.

A reader may also be confined (:class:`ReadConfinement`, set with :func:`confined_reads` around the open; the
server confines every scan to its data root): the stores and raw files opened under it remember it, and every
file they read later, at each chunk read, is opened first and then checked where it really lies (the opened
descriptor's own path, not a path resolved before the open), so a symbolic link swapped in after the open is
never followed out.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import stat
from collections.abc import Iterator
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from ..errors import InvalidInputError, OutputError

__all__ = ["ConfinementError", "ReadConfinement", "check_regular", "check_room", "confined_reads",
           "current_confinement", "open_regular", "read_small", "skip_lines"]


def _within(path: str, folder: str) -> bool:
    return os.path.commonpath([path, folder]) == folder


class ConfinementError(PermissionError):
    """A confined reader was led outside where it may read (a PermissionError: the server's PERMISSION_DENIED)."""


@dataclass(frozen=True)
class ReadConfinement:
    """Where a confined reader may read: inside ``base`` and, when ``deny`` is given, not inside ``deny`` (both real
    paths, symbolic links resolved). ``where`` names the place in refusals, which never name the file itself.
    Picklable: it travels with the lazy arrays to dask's workers."""

    base: str
    deny: str = ""
    where: str = "the folder the reader is confined to"

    def check(self, real: str | os.PathLike, role: str = "") -> None:
        """Raise :class:`ConfinementError` (one line, naming no path) unless ``real`` lies where reads may go."""
        real = os.fspath(real)
        if not _within(real, self.base) or (self.deny and _within(real, self.deny)):
            what = f"a {role} file" if role else "a file"
            raise ConfinementError(f"{what} of the scan now lies outside {self.where} (a symbolic link changed since "
                                  "the scan was opened): nothing was read there")


_CONFINEMENT: ContextVar[ReadConfinement | None] = ContextVar("napari_unwind_read_confinement", default=None)


@contextlib.contextmanager
def confined_reads(confinement: ReadConfinement | None) -> Iterator[None]:
    """Readers opened inside the block (in this thread) keep ``confinement`` for every later read."""
    token = _CONFINEMENT.set(confinement)
    try:
        yield
    finally:
        _CONFINEMENT.reset(token)


def current_confinement() -> ReadConfinement | None:
    """The confinement a reader being opened now must keep (None: read anywhere)."""
    return _CONFINEMENT.get()


def _opened_path(fd: int, path: str | os.PathLike) -> str:
    """Where the file open as ``fd`` really lies: the descriptor's own path where the system tells it (Linux), else
    ``path`` resolved, accepted only when it is that very file (same device and inode)."""
    try:
        return os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        real = os.path.realpath(path)
        if not os.path.samestat(os.fstat(fd), os.stat(real)):
            raise ConfinementError("a file of the scan changed while it was opened: nothing was read") from None
        return real

_KINDS = (
    (stat.S_ISFIFO, "a named pipe"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISDIR, "a folder"),
)


def _size(n: float) -> str:
    """A byte count for people: ``"12 bytes"``, ``"3.4 MiB"``, ``"909.5 TiB"``."""
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if n < 1024:
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def _kind(mode: int) -> str:
    for test, name in _KINDS:
        if test(mode):
            return name
    return "not a regular file"


def _refuse(path: Any, role: str, mode: int) -> InvalidInputError:
    what = f"{role} " if role else ""
    return InvalidInputError(f"{path}: the {what}file is {_kind(mode)}, not a regular file; a scan is read from "
                             "files on disk: copy the data into a file and point at that")


def check_regular(path: str | os.PathLike, role: str = "") -> None:
    """Raise :class:`InvalidInputError` unless ``path`` (symlinks followed) is a regular file.

    A missing path is left to the caller (it raises its own FileNotFoundError).
    """
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISREG(mode):
        raise _refuse(path, role, mode)


def open_regular(path: str | os.PathLike, role: str = "", *, confine: ReadConfinement | None = None) -> IO[bytes]:
    """Open ``path`` for binary reading if it is a regular file, without ever blocking on a named pipe.

    With ``confine``, the file opened must lie where it allows (checked on the open descriptor: no window between
    the check and the read).

    Raises
    ------
    FileNotFoundError, PermissionError
        As :func:`open` does; PermissionError too for a file outside ``confine``.
    InvalidInputError
        When ``path`` is a named pipe, a device, a socket or a folder (named in one line with ``role``).
    """
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    try:
        if confine is not None:
            confine.check(_opened_path(fd, path), role)
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise _refuse(path, role, mode)
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_small(path: str | os.PathLike, *, what: str, max_bytes: int, hint: str = "") -> bytes:
    """The bytes of a small file the user names (a session, a collection): at most ``max_bytes``, never blocking.

    ``what`` names the kind of file ("a session"); ``hint`` follows it in a refusal (" (*.unwind.json)"). Opened
    as :func:`open_regular` does and read to at most ``max_bytes`` + 1 bytes, whatever the file's size says.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    InvalidInputError
        ``path`` is a folder, a named pipe, a device or a socket, or holds more than ``max_bytes``.
    """
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    except FileNotFoundError:
        raise FileNotFoundError(f"the {what.split(' ', 1)[-1]} file {path} does not exist") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        raise InvalidInputError(f"{path} is {_kind(mode)}, not {what} file{hint}")
    with os.fdopen(fd, "rb") as fh:
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        raw = fh.read(max_bytes + 1)
    if len(raw) > max_bytes:
        size = max(len(raw), os.stat(path).st_size)
        raise InvalidInputError(f"{path} is {size} bytes, far too large for {what} file (at most {max_bytes}); "
                                f"did you give another file instead of {what}{hint}?")
    return raw


def skip_lines(fh: IO[bytes], count: int, source: Any) -> None:
    """Skip ``count`` lines of ``fh`` (a header's ``line skip``); refuse a count that runs past the end of the file.

    A count larger than the bytes left is refused at once, without reading.
    """
    if count <= 0:
        return
    try:
        left = os.fstat(fh.fileno()).st_size - fh.tell()
    except (OSError, ValueError, AttributeError):
        left = None
    if left is not None and count > left:
        raise InvalidInputError(f"{source}: the header's line skip {count} is more lines than the {left} bytes "
                                "left in the file can hold; fix the header's 'line skip'")
    for done in range(count):
        if not fh.readline():
            raise InvalidInputError(f"{source}: the header's line skip {count} runs past the end of the file "
                                    f"after {done} lines; fix the header's 'line skip'")


def check_room(target: str | os.PathLike, nbytes: int, *, compressed: bool) -> None:
    """Refuse, before anything is written, an output of ``nbytes`` of voxels that cannot fit on its disk.

    An uncompressed output must fit in the free space of its folder; a compressed one is refused only when even
    a 1000:1 compression would not make it fit (metadata that claims far more voxels than any disk holds).
    """
    target = Path(target)
    folder = target.parent
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return  # the writer reports a folder it cannot use
    limit = free * (1000 if compressed else 1)
    if nbytes <= limit:
        return
    how = "even compressed 1000:1 they would not fit" if compressed else "they are written uncompressed"
    raise OutputError(f"cannot write {target}: its voxels take {nbytes:,} bytes ({_size(nbytes)}) and {how} in "
                      f"the {_size(free)} free in {folder}; write fewer voxels (--level, a crop) or to another disk")
