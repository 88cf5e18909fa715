"""Errors the services add to the core's, and the one mapping of every error to a gRPC status code.

The core raises :class:`~napari_unwind.errors.UnwindError` subclasses with one-line messages; the services add
the conditions only a server has (another user's object, limits, cancellation, shutting down, tokens). The
interceptor (:mod:`unwind_services.interceptor`) and the job runner both use :func:`status_for`, so a failed job
and a failed call report the same code and message.
"""

from __future__ import annotations

import errno

import grpc

from napari_unwind.errors import InvalidInputError, OutputError, UnwindError
from napari_unwind.scheduler import SchedulerError

__all__ = [
    "AuthError",
    "CancelledError",
    "DeadlineError",
    "LimitError",
    "NotFoundError",
    "PermissionDeniedError",
    "ShuttingDownError",
    "StateError",
    "disk_full",
    "status_for",
    "DISK_FULL_MESSAGE",
    "INTERNAL_MESSAGE",
]

#: What a client sees for a bug: the traceback stays in the server log.
INTERNAL_MESSAGE = "internal server error (reference {ref}); the server log holds the details"


class NotFoundError(UnwindError, LookupError):
    """No such volume, segmentation, session or job for this user (another user's objects are not found either)."""


class PermissionDeniedError(UnwindError, PermissionError):
    """A path outside the data root, or a folder the server keeps for itself."""


class LimitError(UnwindError):
    """A configured limit (upload bytes, voxels, concurrent jobs per user) would be exceeded."""


class StateError(UnwindError):
    """The object is not in a state that allows this (e.g. a job that has not finished)."""


class CancelledError(UnwindError):
    """The job was cancelled by its owner."""


class DeadlineError(UnwindError, TimeoutError):
    """The job ran longer than the time it was given."""


class ShuttingDownError(UnwindError):
    """The server is shutting down and accepts no new work."""


class AuthError(UnwindError):
    """No token, an unknown token, or an expired one."""


#: Error numbers of a full disk or an exhausted quota.
_FULL = (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC))
DISK_FULL_MESSAGE = "the server's disk is full; try again later or ask its operator to free some space"


def disk_full(exc: BaseException) -> bool:
    """True when ``exc`` or an error it was raised from (``__cause__``, ``__context__``) is a full disk or quota:
    an OSError ENOSPC or EDQUOT (the core wraps those in its OutputError, libraries in their own) or SQLite's
    "database or disk is full"."""
    import sqlite3

    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        if isinstance(cause, OSError) and cause.errno in _FULL:
            return True
        if isinstance(cause, sqlite3.Error) and getattr(cause, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL:
            return True
        cause = cause.__cause__ or cause.__context__
    return False


def status_for(exc: BaseException) -> tuple[grpc.StatusCode, str | None]:
    """The status code of an exception and the message a client may see (None: INTERNAL, hide the message).

    A full disk is RESOURCE_EXHAUSTED whatever wraps it (the core's OutputError would otherwise read as
    FAILED_PRECONDITION, SQLite's error as INTERNAL)."""
    if disk_full(exc):
        return grpc.StatusCode.RESOURCE_EXHAUSTED, DISK_FULL_MESSAGE
    msg = str(exc) or type(exc).__name__
    table: tuple[tuple[type[BaseException] | tuple, grpc.StatusCode], ...] = (
        (AuthError, grpc.StatusCode.UNAUTHENTICATED),
        ((NotFoundError, FileNotFoundError), grpc.StatusCode.NOT_FOUND),
        ((PermissionDeniedError, PermissionError), grpc.StatusCode.PERMISSION_DENIED),
        ((LimitError, MemoryError), grpc.StatusCode.RESOURCE_EXHAUSTED),
        (CancelledError, grpc.StatusCode.CANCELLED),
        ((DeadlineError, TimeoutError), grpc.StatusCode.DEADLINE_EXCEEDED),
        ((ShuttingDownError, SchedulerError), grpc.StatusCode.UNAVAILABLE),  # SchedulerError: the cluster lost it
        (InvalidInputError, grpc.StatusCode.INVALID_ARGUMENT),  # UnknownFormatError and SeriesSelectionError too
        ((OutputError, StateError, UnwindError), grpc.StatusCode.FAILED_PRECONDITION),
    )
    for kinds, code in table:
        if isinstance(exc, kinds):
            return code, msg
    if isinstance(exc, OSError) and exc.errno == errno.ENAMETOOLONG:  # a client's path, past PATH_MAX with the root
        return grpc.StatusCode.INVALID_ARGUMENT, "a path or file name is too long for the server's file system"
    return grpc.StatusCode.INTERNAL, None
