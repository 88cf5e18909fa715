"""Tokens: a tokens file holds, per line, a user and the SHA-256 of their token (never the token itself).

Format (``#`` starts a comment)::

    alice sha256:9f86d08...   expires=2027-01-31T00:00:00Z
    bob   sha256:60303ae...

:func:`add_token` creates a random token (:func:`new_token`), appends its hash for a user and returns the token
(shown once).
The file is read again when it changes, so tokens are added and revoked without a restart. A change that does not
parse (a typo, a half-written line) keeps the last good table: the server log says once which line of which file
is wrong, and callers see only what any caller with a token the table does not hold sees (UNAUTHENTICATED, no path,
no line of the file).
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import re
import secrets
import string
import threading
from datetime import UTC, datetime, timedelta
from pathlib import Path

from napari_unwind.errors import InvalidInputError

from .errors import AuthError

__all__ = ["TokenAuth", "add_token", "new_token", "hash_token", "check_user", "LOCAL_USER"]

#: The user of every call when the server runs without a tokens file (loopback only).
LOCAL_USER = "local"
log = logging.getLogger("unwind_services.auth")
_USER_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


#: The first character of a new token: a letter or digit, so that no token looks like an option (``-x``) to
#: argparse or to a shell command (``unwind jobs list --token -rluO...`` was "expected one argument").
_FIRST = string.ascii_letters + string.digits


def new_token() -> str:
    """A new random token: a letter or digit, then ``secrets.token_urlsafe(32)`` (A-Z a-z 0-9 - _).

    44 characters, about 262 bits of randomness (the 256 of the 32 bytes plus the first character's). Earlier
    tokens were ``token_urlsafe(32)`` alone, one in 64 starting with "-"; the tokens file holds only hashes, so
    those keep working (pass them as ``--token=VALUE`` or ``--token-file``).
    """
    return secrets.choice(_FIRST) + secrets.token_urlsafe(32)


def hash_token(token: str) -> str:
    """``"sha256:<hex>"`` of a token."""
    return "sha256:" + hashlib.sha256(token.encode("utf-8")).hexdigest()


def check_user(user: str) -> str:
    if not isinstance(user, str) or not _USER_RE.match(user):
        raise InvalidInputError(f"a user name is 1-64 letters, digits, '_', '.' or '-' (starting with a letter or "
                                f"digit), got {user!r}")
    return user


def _parse_time(text: str, where: str) -> datetime:
    try:
        t = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise InvalidInputError(f"{where}: expires= must be an ISO 8601 time such as 2027-01-31T00:00:00Z, "
                                f"got {text!r}") from None
    return t if t.tzinfo else t.replace(tzinfo=UTC)


def read_tokens(path: Path) -> dict[str, tuple[str, datetime | None]]:
    """hash -> (user, expiry) of a tokens file; raises InvalidInputError on a malformed line."""
    entries: dict[str, tuple[str, datetime | None]] = {}
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        where = f"{path} line {n}"
        if len(parts) not in (2, 3) or not parts[1].startswith("sha256:") or len(parts[1]) != 71:
            raise InvalidInputError(f"{where}: expected 'USER sha256:<64 hex digits> [expires=TIME]', got {line!r}")
        expires = None
        if len(parts) == 3:
            if not parts[2].startswith("expires="):
                raise InvalidInputError(f"{where}: the third field must be expires=TIME, got {parts[2]!r}")
            expires = _parse_time(parts[2][len("expires="):], where)
        entries[parts[1]] = (check_user(parts[0]), expires)
    return entries


class TokenAuth:
    """Who a call's bearer token belongs to. Without a tokens file every call is :data:`LOCAL_USER`."""

    def __init__(self, path: str | os.PathLike | None):
        self.path = None if path is None else Path(path)
        self._lock = threading.Lock()
        self._mtime: float | None = None
        self._entries: dict[str, tuple[str, datetime | None]] = {}
        if self.path is not None:
            if not self.path.is_file():
                raise InvalidInputError(f"tokens file {self.path} does not exist; create one with "
                                        "unwind serve --tokens FILE --add-token USER")
            self._reload()

    @property
    def enabled(self) -> bool:
        return self.path is not None

    def _reload(self) -> None:
        assert self.path is not None
        mtime = self.path.stat().st_mtime_ns
        if mtime != self._mtime:
            self._entries = read_tokens(self.path)
            self._mtime = mtime

    def _refresh(self) -> None:
        """:meth:`_reload` while serving: a file being rewritten (gone for a moment) or holding a line that does not
        parse keeps the last good table; a bad version is logged once (its modification time is remembered, so the
        file is parsed again only when it changes again)."""
        try:
            self._reload()
        except OSError:
            pass  # keep the last good table while an admin rewrites the file
        except InvalidInputError as exc:
            try:
                self._mtime = self.path.stat().st_mtime_ns if self.path is not None else None
            except OSError:
                pass
            log.error("tokens file not reloaded, the last good table (%d tokens) is kept: %s", len(self._entries),
                      exc)

    def user_for(self, authorization: str | None) -> str:
        """The user of an ``authorization`` metadata value (``Bearer <token>``); raises AuthError."""
        if self.path is None:
            return LOCAL_USER
        if not authorization:
            raise AuthError("this server needs a token: pass it as 'authorization: Bearer <token>' "
                            "(Client(token=...); on the command line --token=TOKEN, --token-file PATH, "
                            "$UNWIND_TOKEN or $UNWIND_TOKEN_FILE)")
        scheme, _, token = authorization.partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            raise AuthError("the authorization metadata must be 'Bearer <token>'")
        with self._lock:
            self._refresh()
            entries = self._entries
        digest = hash_token(token.strip())
        for known, (user, expires) in entries.items():
            if hmac.compare_digest(known, digest):
                if expires is not None and expires <= datetime.now(UTC):
                    raise AuthError(f"the token of user {user!r} expired on {expires.isoformat()}; ask the server's "
                                    "administrator for a new one")
                return user
        raise AuthError("unknown token; ask the server's administrator for one")


def add_token(path: str | os.PathLike, user: str, *, days: float | None = None) -> str:
    """Create a token for ``user``, append its hash to the tokens file (created with mode 0600) and return it."""
    check_user(user)
    path = Path(path)
    token = new_token()
    line = f"{user} {hash_token(token)}"
    if days is not None:
        if not (days > 0):
            raise InvalidInputError(f"--expires-days must be positive, got {days}")
        expires = datetime.now(UTC) + timedelta(days=days)
        line += " expires=" + expires.strftime("%Y-%m-%dT%H:%M:%SZ")
    old = path.read_text() if path.exists() else "# napari-unwind tokens: USER sha256:<hash> [expires=TIME]\n"
    if old and not old.endswith("\n"):
        old += "\n"
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(old + line + "\n")
    os.replace(tmp, path)
    return token
