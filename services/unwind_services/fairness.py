"""One user cannot stop everyone: per-user counts of calls and uploads in progress, and idle timeouts of transfers.

- :class:`UserSlots` counts what each user has in progress (calls, uploads) against a limit; past it the call is
  refused at once with RESOURCE_EXHAUSTED (:class:`~unwind_services.errors.LimitError`), it never waits. An
  upload counts while its call is alive (not while its handler ends a call gRPC has already ended).
- :class:`UserRate` is a token bucket per user: the calls a user may start per second (bursts of two seconds'
  worth); a call over it waits for its turn (up to a second), past that it is refused with RESOURCE_EXHAUSTED.
- :class:`CallLimiter` is the server interceptor that holds one of the caller's call slots while a call runs (a
  stream: until it ends), and takes one of their tokens when it starts (waiting holds the slot). Health and
  reflection are not counted: a user's flood of calls leaves the server's threads to health checks and to other
  users. With the server's HTTP/2 limit of streams per connection set to the same number of calls, a client's
  calls past its slots wait in the client's own transport and cost the server nothing.
- :func:`idle_limited` reads a client's stream on a thread of its own and stops with
  :class:`~unwind_services.errors.DeadlineError` when nothing arrives for a while (an upload gone silent frees
  its import slot); :func:`idle_sends` cancels a call whose client stops reading a response stream.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import grpc

from .errors import CancelledError, DeadlineError, LimitError
from .interceptor import current_user

__all__ = ["UserSlots", "UserRate", "CallLimiter", "idle_limited", "idle_sends"]

log = logging.getLogger("unwind_services")

#: Seconds between two looks at whether a call is still alive while waiting for its client's next message.
_ALIVE_POLL = 0.25


class UserSlots:
    """How many of something each user has in progress, at most ``limit`` (0: no limit).

    A holder may say how to tell whether its call is still alive (``alive``, e.g. the gRPC context's ``is_active``):
    one whose call is over no longer counts, though its handler may still be ending (e.g. an upload that gRPC cut
    for a message over its size limit, whose handler, late on a busy server, has yet to notice). The client has its
    answer by then and may well start again at once; it must not be refused for the call it has just seen end.
    """

    def __init__(self, limit: int, what: str, advice: str):
        self.limit, self.what, self.advice = int(limit), what, advice
        self._held: dict[str, list[Callable[[], bool] | None]] = {}  # user -> each holder's ``alive``
        self._lock = threading.Lock()

    @staticmethod
    def _counts(alive: Callable[[], bool] | None) -> bool:
        if alive is None:
            return True
        try:
            return bool(alive())
        except Exception:  # noqa: BLE001 - a context that cannot say: count it, as before it could
            return True

    def in_use(self, user: str) -> int:
        """The user's holders whose calls are alive."""
        with self._lock:
            return sum(map(self._counts, self._held.get(user, ())))

    @contextlib.contextmanager
    def hold(self, user: str, alive: Callable[[], bool] | None = None) -> Iterator[None]:
        with self._lock:
            n = sum(map(self._counts, self._held.get(user, ())))
            if self.limit and n >= self.limit:
                raise LimitError(f"you already have {n} {self.what} in progress, this server's limit per user; "
                                 f"{self.advice}")
            self._held.setdefault(user, []).append(alive)
        try:
            yield
        finally:
            with self._lock:
                held = self._held[user]
                held.remove(alive)  # an equal one is as good: the same call, or None
                if not held:
                    del self._held[user]


class UserRate:
    """Calls each user may start per second: a bucket per user that refills at ``rate`` tokens per second and holds
    up to ``burst`` (default two seconds' worth); ``rate`` 0: no limit.

    A call that finds the bucket empty waits for its token when that comes within ``max_wait`` seconds (the token
    is reserved at once, so waiting calls are served in turn at the rate) and is refused otherwise: a flood is
    slowed to the rate rather than answered with refusals as fast as it sends, which would cost the server as much
    as serving it.
    """

    def __init__(self, rate: float, burst: float | None = None, max_wait: float = 1.0):
        self.rate, self.max_wait = float(rate), float(max_wait)
        self.burst = float(burst) if burst is not None else max(1.0, 2.0 * self.rate)
        self._buckets: dict[str, tuple[float, float]] = {}  # user -> (tokens, when counted); below 0: reserved
        self._lock = threading.Lock()

    def reserve(self, user: str) -> float:
        """Take one of ``user``'s tokens: the seconds to wait before the call may start (0: at once); LimitError
        when that would be longer than ``max_wait``."""
        if not self.rate:
            return 0.0
        now = time.monotonic()
        with self._lock:
            tokens, then = self._buckets.get(user, (self.burst, now))
            tokens = min(self.burst, tokens + (now - then) * self.rate)
            wait = max(0.0, (1.0 - tokens) / self.rate)
            if wait > self.max_wait:
                self._buckets[user] = (tokens, now)
                raise LimitError(f"more than {self.rate:g} calls per second, this server's limit per user; wait a "
                                 "moment and retry, with fewer calls")
            self._buckets[user] = (tokens - 1.0, now)
        return wait

    def take(self, user: str) -> None:
        """:meth:`reserve`, then wait for the token."""
        wait = self.reserve(user)
        if wait:
            time.sleep(wait)


_OPEN = ("/grpc.health.v1.Health/", "/grpc.reflection.")


class CallLimiter(grpc.ServerInterceptor):
    """Hold one of the caller's call slots while each call of the services runs, and take one of their tokens
    (:class:`UserRate`) when it starts (installed after :class:`~unwind_services.interceptor.ServiceInterceptor`, which
    knows the user and maps the refusal)."""

    def __init__(self, limit: int, rate: float = 0.0):
        self.slots = UserSlots(limit, "calls", "wait for some to end (e.g. fewer parallel requests)")
        self.rate = UserRate(rate)

    def intercept_service(self, continuation, handler_call_details):
        handler = continuation(handler_call_details)
        if handler is None or handler_call_details.method.startswith(_OPEN) or not (self.slots.limit or
                                                                                    self.rate.rate):
            return handler
        slots, rate = self.slots, self.rate

        @contextlib.contextmanager
        def admitted():
            user = current_user()
            with slots.hold(user):  # until the handler ends: one that never looks at its call must not pile up
                rate.take(user)
                yield

        if handler.unary_unary or handler.stream_unary:
            inner = handler.unary_unary or handler.stream_unary

            def unary(request, context):
                with admitted():
                    return inner(request, context)

            factory = grpc.stream_unary_rpc_method_handler if handler.stream_unary else \
                grpc.unary_unary_rpc_method_handler
        else:
            inner = handler.unary_stream or handler.stream_stream

            def unary(request, context):
                with admitted():
                    yield from inner(request, context)

            factory = grpc.stream_stream_rpc_method_handler if handler.stream_stream else \
                grpc.unary_stream_rpc_method_handler
        return factory(unary, request_deserializer=handler.request_deserializer,
                       response_serializer=handler.response_serializer)


_END = object()


def idle_limited(requests: Iterator[Any], seconds: float, message: str,
                 is_active: Callable[[], bool] = lambda: True) -> Iterator[Any]:
    """The messages of ``requests``; DeadlineError(``message``) when none comes for ``seconds`` (0: wait forever);
    CancelledError as soon as the call is over (``is_active()`` False: the client went away, or gRPC ended the call
    itself, e.g. on a message over its size limit, without the request iterator ever ending).

    A thread of its own reads the stream (gRPC's request iterator blocks until a message comes or the call ends);
    when the caller stops early the call ends with it and the reader thread with the call.
    """
    if not seconds:
        yield from requests
        return
    box: queue.Queue = queue.Queue(maxsize=2)  # a few chunks ahead at most
    done = threading.Event()

    def put(item: Any) -> bool:
        while not done.is_set():
            try:
                box.put(item, timeout=0.5)
                return True
            except queue.Full:
                continue
        return False

    def read() -> None:
        try:
            for r in requests:
                if not put((True, r)):
                    return
            put((True, _END))
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer (e.g. the call was cancelled)
            put((False, exc))

    reader = threading.Thread(target=read, name="unwind-upload-read", daemon=True)
    reader.start()
    try:
        while True:
            quiet_until = time.monotonic() + seconds
            while True:
                try:
                    ok, item = box.get(timeout=min(_ALIVE_POLL, max(0.0, quiet_until - time.monotonic())))
                    break
                except queue.Empty:
                    if not is_active():
                        raise CancelledError("the upload's call ended before its last message") from None
                    if time.monotonic() >= quiet_until:
                        raise DeadlineError(message) from None
            if not ok:
                raise item
            if item is _END:
                return
            yield item
    finally:
        done.set()


def idle_sends(context: grpc.ServicerContext, messages: Iterator[Any], seconds: float, what: str) -> Iterator[Any]:
    """The response stream ``messages``, cancelled when one message waits more than ``seconds`` to be taken by the
    client (gRPC's send blocks the serving thread until the client reads: a client that stops reading would hold
    it forever). Time the server spends making the next message does not count. The client sees CANCELLED; the
    server log says why."""
    if not seconds:
        yield from messages
        return
    user = current_user()
    sending: list[float | None] = [None]  # since when the message handed to gRPC waits to be sent
    stop = threading.Event()

    def watch() -> None:
        while not stop.wait(min(1.0, seconds / 4)):
            since = sending[0]
            if since is not None and time.monotonic() - since > seconds:
                log.warning("%s of %s: the client read nothing for %g s; cancelled", what, user, seconds)
                context.cancel()
                return

    watcher = threading.Thread(target=watch, name="unwind-send-watch", daemon=True)
    watcher.start()
    try:
        for m in messages:
            sending[0] = time.monotonic()
            yield m
            sending[0] = None
    finally:
        stop.set()
        close = getattr(messages, "close", None)
        if close is not None:
            close()  # now, not at garbage collection: the stream's temporary files go with it
