"""One pure-ASGI middleware for every HTTP request: request id, body-size limit, metrics, access
log, and a last-resort guard that turns any unhandled exception into a problem document.

* ``X-Request-ID``: taken from the request when it is a short token (letters, digits, ``._-``),
  otherwise generated; echoed on the response and available as ``request.state.request_id``.
  Every response also gets ``X-Content-Type-Options: nosniff``.
* API keys (:mod:`service.auth`): when configured, a ``/v1`` request without a valid key is
  answered 401 ``unauthorized`` before its body is read.
* Body limit: a ``Content-Length`` above ``max_body_bytes`` is refused at once (413, nothing is
  read); a body without one is read up to the limit and then refused the same way. Accepted
  bodies are buffered (they are small) and handed on unchanged. The whole body must arrive
  within ``body_timeout`` (uvicorn has no such timeout), else 408 ``request_timeout``; a client
  that leaves before its body ends is not answered and is counted as status 499.
* Clients that leave: once a ``POST``'s body is in, the middleware reads the next message
  itself (the app's later reads share it); a disconnect before the answer starts cancels the
  request, so that a job still waiting for a worker leaves the queue, and one running is asked
  to stop at its next deadline check (:meth:`service.workers.WorkerPool.run`; status 499).
* Answers: a large body is sent in chunks of :data:`SEND_CHUNK` bytes, each (and each message of
  a streamed answer) given ``send_timeout`` to leave; a client that stops reading is then
  dropped (the server's ``abort`` from the scope, :mod:`service.server`) instead of holding the
  whole answer in memory for ever. After an answer of 1 MiB or more (sent or dropped) the
  allocator's free memory is handed back to the system (:mod:`service.memory`).
* Cancelled by the server's shutdown (what the worker pool's drain did not answer): 503
  ``shutting_down``, logged and counted, never a 500.
* Fast routes (:mod:`service.fastpath`): a valid ``POST /v1/plans`` is answered here, without
  FastAPI's routing and dependency machinery; any other request (and any invalid one) goes on
  to the app.
* Metrics and the access log label a request by its route (``/v1/plans``): one of the app's
  known paths or path templates (``/v1/figures/from_plan/{kind}``), the explorer's ``/``, ``/static`` for docs assets, ``unmatched`` for anything else (so that scanning
  clients cannot inflate the metrics' cardinality). Bodies are never logged.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import os
import re
import time
from typing import Callable, Protocol, Sequence

from starlette.routing import compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from . import memory
from .auth import (CHALLENGE, CONFLICTING, UNAUTHORIZED_DETAIL, authorized, encode_keys,
                   protected)
from .metrics import Metrics
from .problems import ServiceProblem

access_log = logging.getLogger("service.access")
error_log = logging.getLogger("service.error")

_REQUEST_ID = re.compile(r"^[A-Za-z0-9._-]{1,128}$")
#: The request headers the middleware reads (request id, body, API key).
_HEADERS = frozenset({b"x-request-id", b"content-length", b"content-type", b"x-api-key",
                      b"authorization"})
_COUNTER_MASK = (1 << 64) - 1
#: Headers of which a request may carry one value only (two different keys are refused).
_ONE_KEY = frozenset({"x-api-key", "authorization"})
#: Bytes of an answer handed to the server at a time (see ``send_timeout``).
SEND_CHUNK = 1 << 16
#: The status recorded (metrics, access log) for a request whose client left before its answer
#: (nginx's "client closed request"); nothing is sent.
CLIENT_GONE = 499


class _ClientStalled(Exception):
    """The client did not read its answer within ``send_timeout``; the connection was
    dropped."""


class FastRoute(Protocol):
    """A route answered by the middleware itself (:class:`service.fastpath.FastPlanRoute`)."""

    method: str
    path: str

    async def __call__(self, body: bytes, content_type: str | None, send: Send,
                       request_id: str) -> bool: ...


class RequestContextMiddleware:
    """See the module docstring.

    Parameters
    ----------
    app : ASGI app
    max_body_bytes : int
    metrics : Metrics
    known_paths : callable
        Returns the app's route paths (called once, at the first request).
    api_keys : sequence of str
        Accepted keys for ``/v1`` (empty: no authentication).
    fast_routes : sequence of FastRoute
        Handlers tried first for their ``(method, path)`` once the key and the body size are
        checked (:mod:`service.fastpath`); one that returns False leaves the request to the app.
    body_timeout : float, optional
        Seconds the whole body may take to arrive (None: no limit); then 408.
    send_timeout : float, optional
        Seconds each chunk of an answer may wait for the client to read (None: no limit);
        then the connection is dropped.
    """

    def __init__(self, app: ASGIApp, *, max_body_bytes: int, metrics: Metrics,
                 known_paths: Callable[[], set[str]], api_keys: Sequence[str] = (),
                 fast_routes: Sequence[FastRoute] = (), body_timeout: float | None = None,
                 send_timeout: float | None = None) -> None:
        self.app = app
        self.body_timeout = body_timeout
        self.send_timeout = send_timeout
        self.fast_routes = {(r.method, r.path): r for r in fast_routes}
        self.api_keys = encode_keys(api_keys)
        self.max_body_bytes = max_body_bytes
        self.metrics = metrics
        self._known_paths = known_paths
        self._known: set[str] | None = None
        self._templates: list[tuple[re.Pattern[str], str]] = []
        self._id_prefix = os.urandom(8).hex()
        self._id_counter = itertools.count(int.from_bytes(os.urandom(4), "big"))

    def route_label(self, path: str) -> str:
        """The metrics/log label of a request path."""
        if self._known is None:
            known = set(self._known_paths())
            self._templates = [(compile_path(p)[0], p) for p in sorted(known) if "{" in p]
            self._known = known
        if path in self._known:
            return path
        if path.startswith("/static/"):
            return "/static"
        for pattern, template in self._templates:  # /v1/figures/from_plan/{kind}
            if pattern.match(path):
                return template
        return "unmatched"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        # only the few headers used here (names are lower-case in ASGI; lowered again for
        # servers that do not)
        headers: dict[str, str] = {}
        for k, v in scope.get("headers", ()):
            name = k.lower()
            if name in _HEADERS:
                key, value = name.decode("latin-1"), v.decode("latin-1")
                if key in _ONE_KEY and headers.get(key, value) != value:
                    value = CONFLICTING  # two different keys: refused (service.auth)
                headers[key] = value
        given = headers.get("x-request-id", "")
        request_id = given if given and _REQUEST_ID.match(given) else self._new_id()
        scope.setdefault("state", {})["request_id"] = request_id
        extra_headers = [(b"x-request-id", request_id.encode("latin-1")),
                         (b"x-content-type-options", b"nosniff")]
        abort = scope.get("extensions", {}).get("planner.abort")
        started = time.perf_counter()
        status: list[int] = []
        streamed: list[bool] = []  # the answer comes in several messages
        outcome: list[int] = []  # the status for the metrics when no whole answer was sent
        answer_bytes: list[int] = [0]

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                status.append(int(message["status"]))
                message["headers"] = [*message.get("headers", ()), *extra_headers]
                await send(message)
                return
            body = message.get("body", b"")
            more = message.get("more_body", False)
            answer_bytes[0] += len(body)
            if message["type"] != "http.response.body" or len(body) <= SEND_CHUNK:
                if more or streamed:
                    streamed.append(True)
                    await self._send(send, message, abort)
                else:
                    # a whole small answer in one message: it never waits for the client
                    # (the transport takes it, its buffer being empty before it)
                    await send(message)
                return
            # in chunks, each given send_timeout to leave: a client that stops reading holds
            # one chunk in the transport's buffer, and is dropped, instead of the whole answer
            # for ever
            for i in range(0, len(body), SEND_CHUNK):
                last = i + SEND_CHUNK >= len(body)
                await self._send(send, {"type": "http.response.body",
                                        "body": body[i:i + SEND_CHUNK],
                                        "more_body": more or not last}, abort)

        task = asyncio.current_task()
        watch: asyncio.Future[Message] | None = None
        gone: list[bool] = []
        try:
            if (self.api_keys and protected(scope.get("path", ""), scope.get("method", ""))
                    and not authorized(headers, self.api_keys)):
                await self._problem(send_with_id, ServiceProblem(
                    "unauthorized", UNAUTHORIZED_DETAIL, headers=dict(CHALLENGE)), request_id)
                return
            try:
                checked = await self._checked_body(headers, receive)
            except TimeoutError:
                self._closed("body_timeout")
                await self._problem(send_with_id, ServiceProblem(
                    "request_timeout", f"the request body did not arrive within "
                    f"{self.body_timeout:g} s", headers={"Connection": "close"},
                    diagnostics={"body_timeout": self.body_timeout}), request_id)
                return
            if checked is None:
                await self._problem(send_with_id, ServiceProblem(
                    "invalid_request", f"the request body exceeds {self.max_body_bytes} bytes",
                    status=413, diagnostics={"max_body_bytes": self.max_body_bytes}),
                    request_id)
                return
            body_receive, body = checked
            if body is None:  # the client went away before the end of its body
                outcome.append(CLIENT_GONE)
                self.metrics.cancelled.labels("client_gone").inc()
                return
            if scope.get("method") == "POST" and task is not None:
                # the body is in: the next message is the client leaving (or the answer's
                # end). A client that leaves before its answer starts cancels the request, so
                # that its job leaves the queue (a job already on a worker runs to its end)
                watch = asyncio.ensure_future(receive())

                def on_message(done: asyncio.Future[Message]) -> None:
                    if (not done.cancelled() and done.exception() is None
                            and done.result()["type"] == "http.disconnect" and not status):
                        gone.append(True)
                        task.cancel()

                watch.add_done_callback(on_message)
                body_receive = _replay([{"type": "http.request", "body": body,
                                         "more_body": False}], _shared(watch))
            fast = self.fast_routes.get((scope["method"], scope["path"]))
            if fast is not None and \
                    await fast(body, headers.get("content-type"), send_with_id, request_id):
                return
            await self.app(scope, body_receive, send_with_id)
        except asyncio.CancelledError:
            if task is not None:
                task.uncancel()
            if gone:
                outcome.append(CLIENT_GONE)
                self.metrics.cancelled.labels("client_gone").inc()
                return
            # uvicorn's graceful shutdown ran out of time (the pool's drain answers first, so
            # this is what waited elsewhere): answered, logged and counted as such, never a 500
            self.metrics.cancelled.labels("shutdown").inc()
            error_log.warning("request cancelled by the shutdown",
                              extra={"request_id": request_id})
            if not status:
                await self._problem(send_with_id, ServiceProblem(
                    "shutting_down", "the server stopped before the request finished; retry",
                    headers={"Retry-After": "1", "Connection": "close"}), request_id)
        except _ClientStalled:
            outcome.append(CLIENT_GONE)
            self._closed("send_timeout")
            # the connection's loss is handled before this returns (else uvicorn logs an
            # error: "ASGI callable returned without completing response")
            await asyncio.sleep(0)
        except Exception:  # noqa: BLE001 - last resort: never a 500 nor a stack trace
            error_log.exception("unhandled error", extra={"request_id": request_id})
            if not status:
                await self._problem(send_with_id, ServiceProblem(
                    "numerical_failure", "the request failed unexpectedly; the failure was "
                    "logged with this request id"), request_id)
        finally:
            if watch is not None and not watch.done():
                watch.cancel()
            if answer_bytes[0] >= memory.MMAP_THRESHOLD:
                memory.release_soon()  # the answer's memory goes back to the system
            path = scope.get("path", "")
            method = scope.get("method", "")
            template = self.route_label(path)
            code = outcome[0] if outcome else (status[0] if status else 0)
            seconds = time.perf_counter() - started
            self.metrics.observe_request(template, method, code, seconds)
            if access_log.isEnabledFor(logging.INFO):
                # the record made directly: Logger.info would walk the stack for the caller
                access_log.handle(access_log.makeRecord(
                    access_log.name, logging.INFO, __file__, 0, "%s %s %s",
                    (method, template, code), None, extra={
                        "request_id": request_id, "method": method, "path": str(path)[:200],
                        "route": template, "status": code,
                        "duration_ms": round(seconds * 1000.0, 3)}))

    async def _send(self, send: Send, message: Message, abort: Callable[[], None] | None,
                    ) -> None:
        """``send(message)``, dropping the connection when it cannot leave within
        ``send_timeout`` (the client stopped reading)."""
        if self.send_timeout is None:
            await send(message)
            return
        try:
            async with asyncio.timeout(self.send_timeout):
                await send(message)
        except TimeoutError:
            if abort is not None:
                abort()
            raise _ClientStalled from None

    def _closed(self, reason: str) -> None:
        self.metrics.connections_closed.labels(reason).inc()

    def _new_id(self) -> str:
        """A new request id: 32 hex digits, a random per-process prefix and a counter (as
        unique as a uuid4 across processes, without a system call per request)."""
        return self._id_prefix + format(next(self._id_counter) & _COUNTER_MASK, "016x")

    async def _checked_body(self, headers: dict[str, str], receive: Receive,
                            ) -> tuple[Receive, bytes | None] | None:
        """A receive callable replaying the (size-checked) body and the body (None when the
        client went away before its end), or None when it is too big."""
        length = headers.get("content-length")
        if length is not None:
            if not length.isdigit() or int(length) > self.max_body_bytes:
                return None
        chunks: list[bytes] = []
        size = 0
        async with asyncio.timeout(self.body_timeout):  # the whole body, not each read
            while True:
                message = await receive()
                if message["type"] != "http.request":  # the client left before the end
                    return _replay([message], receive), None
                chunk = message.get("body", b"")
                size += len(chunk)
                if size > self.max_body_bytes:
                    return None
                chunks.append(chunk)
                if not message.get("more_body", False):
                    break
        body = chunks[0] if len(chunks) == 1 else b"".join(chunks)
        return _replay([{"type": "http.request", "body": body, "more_body": False}],
                       receive), body

    @staticmethod
    async def _problem(send: Send, problem: ServiceProblem, request_id: str) -> None:
        response = problem.response(request_id)

        async def no_receive() -> Message:  # pragma: no cover - responses do not read
            return {"type": "http.disconnect"}

        await response({"type": "http"}, no_receive, send)


def _replay(messages: list[Message], receive: Receive) -> Receive:
    """A receive callable that yields ``messages`` first, then defers to ``receive``."""
    pending = list(messages)

    async def replay() -> Message:
        if pending:
            return pending.pop(0)
        return await receive()

    return replay


def _shared(message: "asyncio.Future[Message]") -> Receive:
    """A receive callable answering with ``message`` (the middleware's own read of it)."""

    async def receive() -> Message:
        return await asyncio.shield(message)

    return receive
