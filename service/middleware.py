"""One pure-ASGI middleware for every HTTP request: request id, body-size limit, metrics, access
log, and a last-resort guard that turns any unhandled exception into a problem document.

* ``X-Request-ID``: taken from the request when it is a short token (letters, digits, ``._-``),
  otherwise generated; echoed on the response and available as ``request.state.request_id``.
  Every response also gets ``X-Content-Type-Options: nosniff``.
* API keys (:mod:`service.auth`): when configured, a ``/v1`` request without a valid key is
  answered 401 ``unauthorized`` before its body is read.
* Body limit: a ``Content-Length`` above ``max_body_bytes`` is refused at once (413, nothing is
  read); a body without one is read up to the limit and then refused the same way. Accepted
  bodies are buffered (they are small) and handed on unchanged.
* Fast routes (:mod:`service.fastpath`): a valid ``POST /v1/plans`` is answered here, without
  FastAPI's routing and dependency machinery; any other request (and any invalid one) goes on
  to the app.
* Metrics and the access log label a request by its route (``/v1/plans``): one of the app's
  known paths, ``/static`` for docs assets, ``unmatched`` for anything else (so that scanning
  clients cannot inflate the metrics' cardinality). Bodies are never logged.
"""

from __future__ import annotations

import itertools
import logging
import os
import re
import time
from typing import Callable, Protocol, Sequence

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .auth import CHALLENGE, UNAUTHORIZED_DETAIL, authorized, encode_keys, protected
from .metrics import Metrics
from .problems import ServiceProblem

access_log = logging.getLogger("service.access")
error_log = logging.getLogger("service.error")

_REQUEST_ID = re.compile(r"^[A-Za-z0-9._-]{1,128}$")
#: The request headers the middleware reads (request id, body, API key).
_HEADERS = frozenset({b"x-request-id", b"content-length", b"content-type", b"x-api-key",
                      b"authorization"})
_COUNTER_MASK = (1 << 64) - 1


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
    """

    def __init__(self, app: ASGIApp, *, max_body_bytes: int, metrics: Metrics,
                 known_paths: Callable[[], set[str]], api_keys: Sequence[str] = (),
                 fast_routes: Sequence[FastRoute] = ()) -> None:
        self.app = app
        self.fast_routes = {(r.method, r.path): r for r in fast_routes}
        self.api_keys = encode_keys(api_keys)
        self.max_body_bytes = max_body_bytes
        self.metrics = metrics
        self._known_paths = known_paths
        self._known: set[str] | None = None
        self._id_prefix = os.urandom(8).hex()
        self._id_counter = itertools.count(int.from_bytes(os.urandom(4), "big"))

    def route_label(self, path: str) -> str:
        """The metrics/log label of a request path."""
        if self._known is None:
            self._known = set(self._known_paths())
        if path in self._known:
            return path
        if path.startswith("/static/"):
            return "/static"
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
                headers[name.decode("latin-1")] = v.decode("latin-1")
        given = headers.get("x-request-id", "")
        request_id = given if given and _REQUEST_ID.match(given) else self._new_id()
        scope.setdefault("state", {})["request_id"] = request_id
        extra_headers = [(b"x-request-id", request_id.encode("latin-1")),
                         (b"x-content-type-options", b"nosniff")]
        started = time.perf_counter()
        status: list[int] = []

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                status.append(int(message["status"]))
                message["headers"] = [*message.get("headers", ()), *extra_headers]
            await send(message)

        try:
            if (self.api_keys and protected(scope.get("path", ""), scope.get("method", ""))
                    and not authorized(headers, self.api_keys)):
                await self._problem(send_with_id, ServiceProblem(
                    "unauthorized", UNAUTHORIZED_DETAIL, headers=dict(CHALLENGE)), request_id)
                return
            checked = await self._checked_body(headers, receive)
            if checked is None:
                await self._problem(send_with_id, ServiceProblem(
                    "invalid_request", f"the request body exceeds {self.max_body_bytes} bytes",
                    status=413, diagnostics={"max_body_bytes": self.max_body_bytes}),
                    request_id)
                return
            body_receive, body = checked
            fast = self.fast_routes.get((scope["method"], scope["path"]))
            if fast is not None and body is not None and \
                    await fast(body, headers.get("content-type"), send_with_id, request_id):
                return
            await self.app(scope, body_receive, send_with_id)
        except Exception:  # noqa: BLE001 - last resort: never a 500 nor a stack trace
            error_log.exception("unhandled error", extra={"request_id": request_id})
            if not status:
                await self._problem(send_with_id, ServiceProblem(
                    "numerical_failure", "the request failed unexpectedly; the failure was "
                    "logged with this request id"), request_id)
        finally:
            path = scope.get("path", "")
            method = scope.get("method", "")
            template = self.route_label(path)
            code = status[0] if status else 0
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
        while True:
            message = await receive()
            if message["type"] != "http.request":
                # a disconnect before the body ended: hand it on as it came
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
