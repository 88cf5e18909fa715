"""Atomic outputs: write to a hidden sibling, then rename over the target.

A crash, a full disk or Ctrl-C never leaves a half-written file that looks whole: the partial output has a
``.unwind-tmp`` name that no reader opens, and it is removed on error. The temporary name records the process
that writes it (``.fish.zarr.1a2b3c4d.p4242.s98765.h0badcafe.unwind-tmp``: pid, start time and host), so the
next output to the same target removes what a killed process left behind, and only that.

Without ``overwrite`` the final rename never replaces anything, even when another process created the target
while this one was writing: the second of two runs fails with "already exists" instead of replacing the first.

:func:`check_not_input` refuses an output that is, contains or lies inside one of the inputs, so that writing it
can never destroy what it is made from.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import hashlib
import os
import re
import shutil
import socket
import sys
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path

from ..errors import OutputError

__all__ = ["atomic_output", "check_not_input", "check_writable", "final_name", "remove_path",
           "remove_stale_temps", "temp_path"]

TMP_MARK = ".unwind-tmp"
# .NAME.HEX8[.pPID.sSTART.hHOST][.old].unwind-tmp; names without the owner part come from older versions
_TMP_RE = re.compile(
    r"^\.(?P<name>.+)\.[0-9a-f]{8}(?:\.p(?P<pid>\d+)\.s(?P<start>\d+)\.h(?P<host>[0-9a-f]{8}))?(?P<old>\.old)?"
    + re.escape(TMP_MARK) + r"$"
)


def final_name(path: str | os.PathLike) -> str:
    """The name a temporary output of :func:`atomic_output` will be renamed to.

    ``.fish.dat.1a2b3c4d.p42.s7.h0badcafe.unwind-tmp`` (or ``.fish.dat.1a2b3c4d.unwind-tmp``) -> ``fish.dat``;
    any other name is returned unchanged; a temporary output inside another's (an export writing through a writer
    that is itself atomic) gives the outermost final name. Writers that put companion files beside their output
    (raw + .dat, .nhdr + data) use it to name them.
    """
    name = Path(path).name
    while (m := _TMP_RE.match(name)) is not None:
        name = m.group("name")
    return name


# ------------------------------------------------------------------------------------------------------------------
# who owns a temporary output
# ------------------------------------------------------------------------------------------------------------------
def _host_tag() -> str:
    """8 hex digits naming this host (a hash: any hostname fits in a file name, and equal tags mean one host)."""
    return hashlib.sha256(socket.gethostname().encode("utf-8", "replace")).hexdigest()[:8]


def _start_time(pid: int) -> int:
    """When process ``pid`` started (clock ticks since boot, Linux), or 0 where unknown."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            stat = fh.read()
        return int(stat[stat.rindex(b")") + 2:].split()[19])  # field 22, counting from the state (field 3)
    except (OSError, ValueError, IndexError):
        return 0


def _owner_tag() -> str:
    pid = os.getpid()
    return f"p{pid}.s{_start_time(pid)}.h{_host_tag()}"


def _owner_alive(pid: int, start: int, host: str) -> bool:
    """False only when the process that made a temporary output is certainly gone."""
    if host != _host_tag() or pid <= 0:
        return True  # another host's (or a name we did not make): never ours to judge
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # exists, owned by another user
    # the pid exists: the same process, or a new one that got the number of a dead one
    now = _start_time(pid)
    return not (start and now and now != start)


#: Temporary outputs of this process not yet renamed into place or removed (see :func:`sweep`).
_OPEN_TEMPS: set[Path] = set()


def temp_path(path: str | os.PathLike, *, old: bool = False) -> Path:
    """A new hidden sibling name for writing ``path`` (``old``: for moving the previous output aside)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.{_owner_tag()}{'.old' if old else ''}{TMP_MARK}")
    if len(_OPEN_TEMPS) >= 1000:  # a long-lived process (the server): forget the ones renamed or removed
        _OPEN_TEMPS.difference_update({p for p in _OPEN_TEMPS if not os.path.lexists(p)})
    _OPEN_TEMPS.add(tmp.absolute())
    return tmp


def sweep(*, settle: float = 5.0, quiet: float = 0.5) -> list[Path]:
    """Remove every temporary output of this process that is still there; returns them.

    For a command that was interrupted, once its work has unwound: each output's own removal already ran, but a
    write still in flight (a chunk in a library's IO thread, an interrupt landing in the middle of a removal) can
    have left or made one again, most often on a loaded machine. Each is removed until it stays gone for ``quiet``
    seconds (for up to ``settle`` seconds).
    """
    left = sorted(p for p in _OPEN_TEMPS if os.path.lexists(p))
    for p in left:
        remove_path(p, settle=settle, quiet=quiet)
    _OPEN_TEMPS.difference_update({p for p in _OPEN_TEMPS if not os.path.lexists(p)})
    return left


def remove_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary outputs of ``path`` left by processes of this host that are gone (killed).

    Only siblings named as :func:`temp_path` names them for ``path`` are considered (or for such a temporary
    output itself: a writer may write its output atomically too). A live process's temporary output, another
    host's and one of an older version (no owner recorded) are left alone; so is a previous output moved aside
    while being replaced (``.old``) when the target itself is missing (it is then the only copy). Returns the
    paths removed.
    """
    path = Path(path)
    removed: list[Path] = []
    try:
        entries = [e for e in os.scandir(path.parent) if e.name.endswith(TMP_MARK) and path.name in e.name]
    except OSError:
        return removed
    for entry in entries:
        m = _TMP_RE.match(entry.name)
        if not m or m.group("pid") is None:
            continue
        name = m.group("name")
        while name != path.name and (inner := _TMP_RE.match(name)):
            name = inner.group("name")
        if name != path.name or (m.group("old") and not os.path.lexists(path)):
            continue
        if _owner_alive(int(m.group("pid")), int(m.group("start")), m.group("host")):
            continue
        remove_path(Path(entry.path))
        removed.append(Path(entry.path))
    return removed


# ------------------------------------------------------------------------------------------------------------------
# renames
# ------------------------------------------------------------------------------------------------------------------
_RENAME_NOREPLACE = 1
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _load_renameat2():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_renameat2_fn = _load_renameat2()


def _renameat2(src: Path, dst: Path, flags: int) -> bool:
    """``renameat2(src, dst, flags)``; False when not available here (no such call, or the filesystem refuses)."""
    if _renameat2_fn is None:
        return False
    if _renameat2_fn(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst), flags) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(src), None, str(dst))


def _rename_no_replace(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst``; FileExistsError when anything is at ``dst``, which stays untouched."""
    if _renameat2(src, dst, _RENAME_NOREPLACE):
        return
    if os.name == "nt":
        os.rename(src, dst)  # never replaces on Windows
        return
    if src.is_dir() and not src.is_symlink():
        # rename() replaces an empty folder: reserve the name with one of our own first (mkdir never replaces)
        os.mkdir(dst)
        try:
            os.rename(src, dst)
        except BaseException:
            with contextlib.suppress(OSError):
                os.rmdir(dst)
            raise
        return
    try:
        os.link(src, dst)  # never replaces
    except FileExistsError:
        raise
    except OSError:  # no hard links on this filesystem: check, then rename (a narrow race remains)
        if os.path.lexists(dst):
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(dst)) from None
        os.rename(src, dst)
        return
    os.unlink(src)


def _replace(src: Path, dst: Path) -> None:
    """Rename ``src`` over ``dst``, whatever is there (file or folder); ``dst`` is never missing in between."""
    if not os.path.lexists(dst) or not (src.is_dir() or (dst.is_dir() and not dst.is_symlink())):
        os.replace(src, dst)
        return
    # a folder cannot be renamed over a non-empty folder: swap the two, then drop the old one (now at src)
    try:
        swapped = _renameat2(src, dst, _RENAME_EXCHANGE)
    except FileNotFoundError:  # the target vanished meanwhile
        os.replace(src, dst)
        return
    if swapped:
        remove_path(src)
        return
    old = temp_path(dst, old=True)
    os.replace(dst, old)
    try:
        os.replace(src, dst)
    except BaseException:
        os.replace(old, dst)
        raise
    remove_path(old)


def remove_path(path: Path, *, settle: float = 0.0, quiet: float = 0.1) -> None:
    """Remove a file or a folder tree, if it exists.

    With ``settle`` > 0 a folder is removed again until it stays gone for ``quiet`` seconds (for up to ``settle``
    seconds): after an interrupt, the threads of a computation can still finish the chunk they were writing into it.
    """
    if path.is_dir() and not path.is_symlink():
        deadline = time.monotonic() + settle
        while True:
            shutil.rmtree(path, ignore_errors=True)
            if settle <= 0 or time.monotonic() > deadline:
                return
            time.sleep(quiet)
            if not os.path.lexists(path):
                return
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


# ------------------------------------------------------------------------------------------------------------------
# checks
# ------------------------------------------------------------------------------------------------------------------
def check_writable(path: str | os.PathLike, *, overwrite: bool = True) -> Path:
    """Check up front that ``path`` can be created; returns it as an absolute Path.

    Raises
    ------
    OutputError
        When the parent folder does not exist or is not writable, when ``path`` exists and ``overwrite``
        is False, when ``path`` names no file (``/``, ``..``), is the current folder or holds it, or is a
        device, pipe or socket (``/dev/null``: renaming over it would replace the device).
    """
    path = Path(path).expanduser().absolute()
    if path.name in ("", ".", ".."):
        raise OutputError(f"cannot write {path}: name the file or folder to create, e.g. {path / 'out.zarr'}")
    try:
        here = Path.cwd().resolve()
    except OSError:  # the current folder was removed
        here = None
    if here is not None and path.resolve() in (here, *here.parents):
        raise OutputError(f"cannot write {path}: it is the current folder or holds it; name a new file or folder "
                          "inside it, e.g. out.zarr")
    if path.exists() and not (path.is_file() or path.is_dir()):
        raise OutputError(f"cannot write {path}: it is a device, pipe or socket, not a file or folder; choose "
                          "another output path")
    parent = path.parent
    if not parent.is_dir():
        raise OutputError(f"cannot write {path}: the folder {parent} does not exist; create it first")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write {path}: the folder {parent} is not writable; choose another output path")
    if path.exists() and not overwrite:
        raise OutputError(f"{path} already exists; pass overwrite=True (CLI: --overwrite) or choose another name")
    _refuse_foreign(path)
    return path


#: Suffixes of the files of the folder outputs this program writes (a DICOM series, a stack of 2D slices) and of
#: the files a run --all folder holds.
_OUR_SUFFIXES = frozenset({".dcm", ".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg", ".csv", ".json"})
_ZARR_MARKS = ("zarr.json", ".zgroup", ".zarray")
#: Files a desktop leaves in any folder it shows (not someone's work): ignored when deciding whose a folder is.
_OS_LITTER = frozenset({".DS_Store", "Thumbs.db", "desktop.ini", ".directory"})
#: Output names of formats written as one file (or one zarr store): a folder under such a name is not ours.
_FILE_OUTPUT_SUFFIXES = (".zarr", ".tif", ".tiff", ".btf", ".tf8", ".nrrd", ".nhdr", ".nii", ".nii.gz", ".dat",
                         ".raw", ".json", ".csv", ".parquet", ".png")


def _refuse_foreign(path: Path) -> None:
    """OutputError when ``path`` is a folder holding what this program could not have written (:func:`_foreign`)."""
    why = _foreign(path) if path.is_dir() and not path.is_symlink() else ""
    if why:
        raise OutputError(f"cannot replace {path}: it is a folder that holds {why}, not an output of napari-unwind; "
                          "overwrite replaces only a file or a store this program writes: remove it yourself or "
                          "choose another name")


def _foreign(folder: Path) -> str:
    """What in an existing output ``folder`` this program could not have written ("" when nothing): a folder is
    replaceable when it is empty, a zarr store, or holds only the files of a DICOM series, a slice stack or
    ``run --all``'s table and sessions (and the stores of its specimens)."""
    if any((folder / m).is_file() for m in _ZARR_MARKS):
        return _foreign_in_store(folder)
    ours = _suffixes_of(folder)
    try:
        entries = sorted(os.scandir(folder), key=lambda e: e.name)
    except OSError as exc:
        return f"entries that cannot be listed ({exc.strerror or exc})"
    for e in entries:
        name = e.name
        if e.is_dir(follow_symlinks=False):
            if name.endswith(".zarr") and any(os.path.isfile(os.path.join(e.path, m)) for m in _ZARR_MARKS):
                continue
            if TMP_MARK in name:
                continue
            return f"the folder {name!r}"
        if not e.is_file(follow_symlinks=False):
            return f"{name!r}, which is not a regular file"
        if TMP_MARK in name or name in _OS_LITTER or name.startswith("._"):
            continue
        if Path(name).suffix.lower() not in ours:
            return f"the file {name!r}"
    return ""


def _suffixes_of(folder: Path) -> frozenset[str]:
    """Suffixes of the files an output named ``folder`` could hold: a DICOM series (``x.dicom``, ``x.dcm``) only
    ``.dcm`` slices; an output named as a file (``x.tif``, ``x.nrrd``, ``x.zarr``...) nothing (a folder there is
    someone else's, or an empty one); a folder without a suffix (a slice stack, ``run --all``) any of ours."""
    name = folder.name.lower()
    if name.endswith((".dicom", ".dcm")):
        return frozenset({".dcm"})
    if name.endswith(_FILE_OUTPUT_SUFFIXES):
        return frozenset()
    return _OUR_SUFFIXES


_ZARR_FILE = re.compile(r"(zarr\.json|\.zgroup|\.zarray|\.zattrs|\.zmetadata|[0-9]+([.][0-9]+)*)")


def _foreign_in_store(store: Path) -> str:
    """What in a zarr store no zarr writer puts there ("" when nothing): files other than zarr metadata and chunk
    keys (``0``, ``0.0.0``), anything that is not a regular file or folder (a symlink, a pipe). A thesis saved into
    a store is not replaced with it."""
    for top, dirs, files in os.walk(store, onerror=None):
        for name in dirs:
            if os.path.islink(os.path.join(top, name)):
                return f"{os.path.relpath(os.path.join(top, name), store)!r}, a link inside the zarr store"
        for name in files:
            full = os.path.join(top, name)
            if TMP_MARK in name:
                continue
            if os.path.islink(full) or not os.path.isfile(full):
                return f"{os.path.relpath(full, store)!r}, which is not a regular file, inside the zarr store"
            if not _ZARR_FILE.fullmatch(name):
                return f"the file {os.path.relpath(full, store)!r} inside the zarr store"
    return ""


_NHDR_DATA = re.compile(rb"^data ?file: *(\S.*?)\s*$", re.IGNORECASE | re.MULTILINE)


def _parts(path: Path, *, output: bool) -> list[Path]:
    """The files and folders a path stands for: the path itself plus its companion files.

    ``x.dat`` and ``x.raw`` come in pairs; a detached NRRD header ``x.nhdr`` has a data file (read from an
    existing header, else ``x.raw[.gz|.bz2]``, the names our writer gives); an output slice pattern
    ``folder/s_{:04d}.png`` writes the folder.
    """
    name = path.name.lower()
    if output and "{" in path.name:
        return [path.parent]
    parts = [path]
    if name.endswith(".dat"):
        parts.append(path.with_suffix(".raw"))
    elif name.endswith(".raw"):
        parts.append(path.with_suffix(".dat"))
    elif name.endswith(".nhdr"):
        data = None
        if not output and path.is_file():
            with contextlib.suppress(OSError):
                with open(path, "rb") as fh:
                    m = _NHDR_DATA.search(fh.read(1 << 16))
                if m and not m.group(1).upper().startswith((b"LIST", b"%")) and b" " not in m.group(1):
                    data = path.parent / os.fsdecode(m.group(1))
        stem = path.name[: -len(".nhdr")]
        parts += [data] if data is not None else [path.with_name(stem + s) for s in (".raw", ".raw.gz", ".raw.bz2")]
    return parts


def _resolved(path: Path) -> Path:
    return Path(os.path.realpath(Path(path).expanduser()))


def _relation(out: Path, inp: Path) -> str | None:
    """How the resolved ``out`` stands to the resolved ``inp``: "is", "contains", "lies inside" or None."""
    if out == inp:
        return "is"
    with contextlib.suppress(OSError):
        if out.exists() and inp.exists() and os.path.samefile(out, inp):
            return "is"  # e.g. one file under two names on a case-insensitive filesystem
    if out in inp.parents:
        return "contains"
    if inp in out.parents:
        return "lies inside"
    return None


def check_not_input(outputs: Iterable[str | os.PathLike | None], inputs: Iterable[str | os.PathLike | None]) -> None:
    """Refuse an output that is, contains or lies inside an input: inputs are never modified.

    Paths are compared after resolving relative paths and symbolic links, together with their companion files
    (``.dat``/``.raw`` pairs, a detached NRRD header's data file, the folder of an output slice pattern).
    ``None`` entries are skipped. Call it before any work starts.

    Raises
    ------
    OutputError
        Naming the output and the input.
    """
    ins = [(Path(i), part, _resolved(part)) for i in inputs if i is not None
           for part in _parts(Path(i), output=False)]
    for o in outputs:
        if o is None:
            continue
        o = Path(o)
        for part in _parts(o, output=True):
            out = _resolved(part)
            for given, in_part, inp in ins:
                rel = _relation(out, inp)
                if rel is None:
                    continue
                what = f"the output {o}" if part == o else f"{part}, written with the output {o},"
                which = f"the input {given}" if in_part == given else f"{in_part}, part of the input {given}"
                if str(o) != str(out) or str(given) != str(inp):
                    which += f" (both resolve to {out})" if rel == "is" else f" ({out} {rel} {inp})"
                raise OutputError(f"{what} {rel} {which}; inputs are never modified: choose another output path")


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary sibling path to write into; on success rename it to ``path``.

    Works for files and for folders (zarr stores, DICOM series). An existing target is replaced only after the
    new output is complete. On any exception the temporary output is deleted and the target is untouched.
    Without ``overwrite`` a target that appeared meanwhile (another process) is never replaced: OutputError.
    Temporary outputs of ``path`` left by killed processes of this host are removed first.

    Examples
    --------
    >>> with atomic_output("scan.nrrd") as tmp:          # doctest: +SKIP
    ...     nrrd.write(str(tmp), data)
    """
    path = check_writable(path, overwrite=overwrite)
    remove_stale_temps(path)
    tmp = temp_path(path)
    try:
        yield tmp
        if not os.path.lexists(tmp):
            raise OutputError(f"internal error: nothing was written for {path}")
        if overwrite:
            if os.path.lexists(path) and tmp.is_dir() != (path.is_dir() and not path.is_symlink()):
                what = "a folder" if path.is_dir() else "a file"
                raise OutputError(f"cannot replace {path}: it is {what} and the output is "
                                  f"{'a folder' if tmp.is_dir() else 'a file'}; remove it yourself or choose "
                                  "another name")
            _refuse_foreign(path)  # again: it may have been made while this output was written
            _replace(tmp, path)
        else:
            try:
                _rename_no_replace(tmp, path)
            except FileExistsError:
                raise OutputError(f"{path} already exists (made by another process while this one was writing); "
                                  "pass overwrite=True (CLI: --overwrite) or choose another name") from None
    except PermissionError as exc:
        remove_path(tmp)
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None
    except BaseException:
        remove_path(tmp, settle=5.0)  # an interrupt: running threads may still write their chunk into it
        raise
