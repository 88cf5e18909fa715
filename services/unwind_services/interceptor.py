"""The one server interceptor: authentication, malformed messages, and domain errors -> status codes.

In the style of KServe's ``protocol/grpc/interceptors.py``: every handler is wrapped once. The wrapper

- resolves the caller's user from the ``authorization`` metadata (health and reflection need no token);
- turns a request that does not parse into INVALID_ARGUMENT (grpc would answer INTERNAL);
- refuses a request with a field out of its bounds (:func:`unwind_services.convert.check_request`: lengths, NaN,
  infinities, NUL, huge numbers, too many items) before any servicer sees it: INVALID_ARGUMENT naming the field;
- maps exceptions with :func:`unwind_services.errors.status_for`, keeping the core's one-line message (with the
  data root's absolute path removed). Anything unexpected becomes INTERNAL with a generic message and a
  reference; the traceback goes to the server log only, never over the wire.

A refused call leaves one line in the log, at most :data:`MAX_LOG_LINE` characters (a 60 MiB path is cut, never
copied whole); a traceback's lines are cut the same way and it keeps at most :data:`MAX_TRACEBACK` characters.
"""

from __future__ import annotations

import contextvars
import logging
import traceback
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import grpc

from napari_unwind.errors import InvalidInputError

from . import convert
from .auth import TokenAuth
from .errors import INTERNAL_MESSAGE, status_for
from .paths import DataRoot

__all__ = ["ServiceInterceptor", "current_user", "MAX_LOG_LINE", "MAX_MESSAGE", "MAX_TRACEBACK"]

#: Longest line the log holds for a refused call; longest message a caller gets; longest traceback kept.
MAX_LOG_LINE, MAX_MESSAGE, MAX_TRACEBACK = 500, 1000, 20_000

log = logging.getLogger("unwind_services")

_user: contextvars.ContextVar[str] = contextvars.ContextVar("unwind_user")
_OPEN = ("/grpc.health.v1.Health/", "/grpc.reflection.")


def current_user() -> str:
    """The user of the call being served (set by the interceptor)."""
    return _user.get()


class _Malformed:
    def __init__(self, exc: Exception):
        self.exc = exc


def _safe(deserializer: Callable[[bytes], Any] | None) -> Callable[[bytes], Any] | None:
    if deserializer is None:
        return None

    def parse(data: bytes) -> Any:
        try:
            return deserializer(data)
        except Exception as exc:  # noqa: BLE001 - any parse failure is the client's malformed message
            return _Malformed(exc)

    return parse


def _short(text: str, most: int) -> str:
    """``text`` cut to ``most`` characters (saying how long it was)."""
    if len(text) <= most:
        return text
    return f"{text[:most - 40]}... ({len(text)} characters)"


def _bounded_traceback() -> str:
    lines = [_short(line, MAX_LOG_LINE) for line in traceback.format_exc().splitlines()]
    text = "\n".join(lines)
    return text if len(text) <= MAX_TRACEBACK else text[:MAX_TRACEBACK // 2] + "\n...\n" + text[-MAX_TRACEBACK // 2:]


def _check(request: Any) -> Any:
    if isinstance(request, _Malformed):
        raise InvalidInputError("the request message is malformed (it does not parse as the expected protobuf "
                                "message); check the client's contract version (unwind.v1)")
    if hasattr(request, "DESCRIPTOR"):  # not an upload's chunk (ingest.decoder hands those over as memoryviews)
        convert.check_request(request)
    return request


def _checked_stream(requests: Iterator[Any]) -> Iterator[Any]:
    for r in requests:
        yield _check(r)


class ServiceInterceptor(grpc.ServerInterceptor):
    """Authentication and error mapping for every method of the server."""

    def __init__(self, auth: TokenAuth, root: DataRoot):
        self.auth, self.root = auth, root

    def _abort(self, exc: BaseException, context: grpc.ServicerContext, method: str) -> None:
        code, message = status_for(exc)
        method = _short(method, 200)
        if message is None:
            ref = uuid.uuid4().hex[:8]
            log.error("%s failed (reference %s):\n%s", method, ref, _bounded_traceback())
            message = INTERNAL_MESSAGE.format(ref=ref)
        else:
            message = _short(self.root.scrub(message), MAX_MESSAGE)
            log.info("%s", _short(f"{method} -> {code.name}: {message}", MAX_LOG_LINE))
        context.abort(code, message)

    def _user(self, metadata: Any) -> str:
        md = dict(metadata or ())
        return self.auth.user_for(md.get("authorization"))

    def intercept_service(self, continuation, handler_call_details):
        handler = continuation(handler_call_details)
        if handler is None:
            return None
        method = handler_call_details.method
        if method.startswith(_OPEN):
            return handler
        metadata = handler_call_details.invocation_metadata
        abort, user_of = self._abort, self._user

        def begin(context: grpc.ServicerContext) -> None:
            _user.set(user_of(metadata))

        if handler.unary_unary or handler.stream_unary:
            inner = handler.unary_unary or handler.stream_unary
            streaming_in = handler.stream_unary is not None

            def unary(request, context):
                try:
                    begin(context)
                    request = _checked_stream(request) if streaming_in else _check(request)
                    return inner(request, context)
                except Exception as exc:  # noqa: BLE001
                    if isinstance(exc, grpc.RpcError) or context.code() is not None:
                        raise
                    abort(exc, context, method)

            factory = grpc.stream_unary_rpc_method_handler if streaming_in else grpc.unary_unary_rpc_method_handler
        else:
            inner = handler.unary_stream or handler.stream_stream
            streaming_in = handler.stream_stream is not None

            def unary(request, context):  # a generator: the response stream
                try:
                    begin(context)
                    request = _checked_stream(request) if streaming_in else _check(request)
                    yield from inner(request, context)
                except Exception as exc:  # noqa: BLE001
                    if isinstance(exc, grpc.RpcError) or context.code() is not None:
                        raise
                    abort(exc, context, method)

            factory = grpc.stream_stream_rpc_method_handler if streaming_in else grpc.unary_stream_rpc_method_handler
        return factory(unary, request_deserializer=_safe(handler.request_deserializer),
                       response_serializer=handler.response_serializer)
