"""Atomic outputs: write to a hidden sibling, then rename over the target.

A crash, a full disk or Ctrl-C never leaves a half-written file that looks whole: the partial output has a
``.unwind-tmp`` name that no reader opens, and it is removed on error.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path

from ..errors import OutputError

__all__ = ["atomic_output", "check_writable", "final_name", "remove_path"]

TMP_MARK = ".unwind-tmp"
_TMP_RE = re.compile(r"^\.(?P<name>.+)\.[0-9a-f]{8}" + re.escape(TMP_MARK) + r"$")


def final_name(path: str | os.PathLike) -> str:
    """The name a temporary output of :func:`atomic_output` will be renamed to.

    ``.fish.dat.1a2b3c4d.unwind-tmp`` -> ``fish.dat``; any other name is returned unchanged. Writers that put
    companion files beside their output (raw + .dat, .nhdr + data) use it to name them.
    """
    name = Path(path).name
    m = _TMP_RE.match(name)
    return m.group("name") if m else name


def remove_path(path: Path) -> None:
    """Remove a file or a folder tree, if it exists."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def check_writable(path: str | os.PathLike, *, overwrite: bool = True) -> Path:
    """Check up front that ``path`` can be created; returns it as an absolute Path.

    Raises
    ------
    OutputError
        When the parent folder does not exist or is not writable, or when ``path`` exists and ``overwrite``
        is False.
    """
    path = Path(path).expanduser().absolute()
    parent = path.parent
    if not parent.is_dir():
        raise OutputError(f"cannot write {path}: the folder {parent} does not exist; create it first")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write {path}: the folder {parent} is not writable; choose another output path")
    if path.exists() and not overwrite:
        raise OutputError(f"{path} already exists; pass overwrite=True (CLI: --overwrite) or choose another name")
    return path


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary sibling path to write into; on success rename it to ``path``.

    Works for files and for folders (zarr stores, DICOM series). An existing target is replaced only after the
    new output is complete. On any exception the temporary output is deleted and the target is untouched.

    Examples
    --------
    >>> with atomic_output("scan.nrrd") as tmp:          # doctest: +SKIP
    ...     nrrd.write(str(tmp), data)
    """
    path = check_writable(path, overwrite=overwrite)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}{TMP_MARK}")
    try:
        yield tmp
        if not tmp.exists():
            raise OutputError(f"internal error: nothing was written for {path}")
        if path.exists():
            # os.replace cannot replace a non-empty folder: move the old one aside first, drop it after.
            old = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.old{TMP_MARK}")
            os.replace(path, old)
            try:
                os.replace(tmp, path)
            except BaseException:
                os.replace(old, path)
                raise
            remove_path(old)
        else:
            os.replace(tmp, path)
    except PermissionError as exc:
        remove_path(tmp)
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None
    except BaseException:
        remove_path(tmp)
        raise
