"""Reading a bearer token from a file: ``--token-file PATH`` and ``$UNWIND_TOKEN_FILE`` of the remote commands and
:class:`napari_unwind.client.Client`.

A token file holds the token alone on one line (the trailing newline, and spaces around it, are dropped), e.g. the
last line ``unwind serve --tokens FILE --add-token USER`` printed. A missing, unreadable, empty or many-line file is
an :class:`~napari_unwind.errors.InvalidInputError` of one line saying what to do.
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import InvalidInputError

__all__ = ["read_token_file"]

_WHAT_TO_DO = ("save the token your server's administrator gave you (the last line unwind serve --add-token "
               "printed) alone in it, or pass the token itself as --token=VALUE")


def read_token_file(path: str | os.PathLike) -> str:
    """The token held by the file at ``path``; raises InvalidInputError (one line) when there is none."""
    p = Path(path).expanduser()
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InvalidInputError(f"token file {p} does not exist: {_WHAT_TO_DO}") from None
    except IsADirectoryError:
        raise InvalidInputError(f"token file {p} is a folder, not a file: {_WHAT_TO_DO}") from None
    except PermissionError:
        raise InvalidInputError(f"token file {p} cannot be read (permission denied): make it readable by you "
                                f"(chmod 600 {p}), or pass the token itself as --token=VALUE") from None
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else type(exc).__name__
        raise InvalidInputError(f"token file {p} cannot be read ({reason}): {_WHAT_TO_DO}") from None
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if not lines:
        raise InvalidInputError(f"token file {p} is empty: {_WHAT_TO_DO}")
    if len(lines) > 1 or len(lines[0].split()) > 1:
        raise InvalidInputError(f"token file {p} holds more than one word (a token has no spaces and is one line): "
                                f"{_WHAT_TO_DO}")
    return lines[0]
