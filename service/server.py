"""How ``python -m service`` serves the app: uvicorn with bounded connections and a shutdown
that answers what it cannot finish.

uvicorn's own settings do what they can (:func:`serve`): ``timeout_keep_alive``,
``timeout_graceful_shutdown`` and, with h11, ``h11_max_incomplete_event_size``. What uvicorn
cannot do is added to its HTTP protocol, httptools (the default: about 30 % less event-loop CPU
per request than h11) or h11 (``PLANNER_HTTP``), in as little code as it takes
(:func:`protocol_class`):

* **a header size limit** (``max_header_bytes``): both parsers keep a request's head until it
  is complete (httptools without any limit, h11 only bounds one that arrives in pieces), so
  its bytes are counted as they arrive; past the limit the answer is 431;
* **a connection cap** (``max_connections``, lowered to fit the file descriptor limit, whose
  soft value is raised to the hard one at start): a connection past it is answered 503 at once
  and closed, before anything is read. uvicorn's ``limit_concurrency`` answers only when a
  request arrives (a silent connection keeps its descriptor) and with a text/plain body;
* **a header timeout** (``header_timeout``): a connection that has not sent a complete request
  line and headers that long after it opened, or after the first byte of a later request, is
  closed (uvicorn only times out idle keep-alive connections);
* **a bound on an unread body** (:data:`LINGER`, at most ``body_timeout``): a request answered
  before its body arrived (401 before the body is read, 413 past ``max_body_bytes``) leaves the
  rest of its body on the connection. uvicorn reads and drops it for as long as it comes, each
  byte re-arming nothing (its keep-alive timer waits for an idle connection), so a body trickled
  a byte at a time held the connection open for ever. The rest is still read and dropped, so
  that the client, still sending, gets the answer instead of a reset, but only for ``LINGER``
  seconds after the answer; then the connection is closed;
* **a problem document** for malformed HTTP (400; uvicorn's is text/plain);
* the connection's ``abort`` in the request scope (``scope["extensions"]["planner.abort"]``),
  so that the request middleware can drop a client that stops reading its answer
  (:mod:`service.middleware`: ``send_timeout``).

The body read timeout and the answer's write timeout are in the request middleware: uvicorn
has neither.

:class:`Server` tells the worker pool when the shutdown starts (:meth:`WorkerPool.drain`), so
that what is still queued or running shortly before ``shutdown_timeout`` is answered 503
``shutting_down`` instead of being cancelled by uvicorn (a bare 500).
"""

from __future__ import annotations

import asyncio
import logging
import math
import resource
from typing import Any, Callable

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from . import memory
from .encoding import finite_json
from .problems import PROBLEM_MEDIA_TYPE, problem_body
from .settings import Settings

log = logging.getLogger("service.server")

#: File descriptors kept for everything but client connections: the listening socket, the
#: workers' pipes, the forkserver, logs, imports.
RESERVED_FDS = 64
#: Descriptors kept per worker process (its pipe, the process sentinel, a replacement's).
FDS_PER_WORKER = 4
#: Seconds the rest of a body is read (and dropped) after its request was answered early (401,
#: 413) before the connection is closed (at most ``body_timeout``): long enough for a client
#: still sending to read the answer, short enough that trickled bodies cannot hold connections.
LINGER = 2.0


def raise_fd_limit() -> int:
    """Raise the soft limit of open file descriptors to the hard one (where allowed); return
    the soft limit in force."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != soft:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (ValueError, OSError) as exc:
            log.warning("could not raise the open file limit from %d to %d: %s", soft, hard, exc)
    return soft if soft != resource.RLIM_INFINITY else 1 << 20


def connection_cap(settings: Settings, fd_limit: int) -> int:
    """``max_connections``, lowered so that the connections fit in ``fd_limit``."""
    room = fd_limit - RESERVED_FDS - FDS_PER_WORKER * settings.workers
    cap = max(1, min(settings.max_connections, room))
    if cap < settings.max_connections:
        log.warning("max_connections lowered from %d to %d to fit %d file descriptors",
                    settings.max_connections, cap, fd_limit)
    return cap


def _raw_problem(status: int, reason: bytes, code: str, detail: str,
                 diagnostics: dict[str, Any], retry_after: int | None = None) -> bytes:
    """A whole HTTP/1.1 answer carrying a problem document, ending the connection."""
    body = finite_json(problem_body(code, detail, status=status, diagnostics=diagnostics))
    head = [b"HTTP/1.1 %d %s" % (status, reason),
            b"content-type: " + PROBLEM_MEDIA_TYPE.encode(),
            b"content-length: %d" % len(body), b"connection: close",
            b"x-content-type-options: nosniff"]
    if retry_after is not None:
        head.append(b"retry-after: %d" % retry_after)
    return b"\r\n".join(head) + b"\r\n\r\n" + body


class _Bounded(asyncio.Protocol):
    """What uvicorn's HTTP protocols lack (the module docstring), for either of them: mixed in
    before :class:`H11Protocol` or :class:`HttpToolsProtocol`, whose methods ``super()``
    reaches. The limits are class attributes, set by :func:`protocol_class`."""

    transport: asyncio.Transport
    loop: asyncio.AbstractEventLoop
    connections: set[Any]

    max_connections = 1000
    header_timeout = 10.0
    max_header_bytes = 16384
    linger = LINGER
    refusal = b""
    too_large = b""
    malformed = b""
    on_closed: Callable[[str], None] | None = None

    _header_timer: asyncio.TimerHandle | None = None
    _linger_timer: asyncio.TimerHandle | None = None
    _head_bytes = 0     # of the request line and headers being received
    _tail = b""         # the last bytes of them (their end may straddle two reads)

    def _in_head(self) -> bool:
        """Whether the connection waits for (the rest of) a request line and headers."""
        raise NotImplementedError

    def _in_body(self) -> bool:
        """Whether the connection waits for (the rest of) a request's body."""
        raise NotImplementedError

    def on_response_complete(self) -> None:
        super().on_response_complete()  # type: ignore[misc]
        # answered before its body arrived (401, 413): what still comes is read and dropped
        # for ``linger`` seconds at most, however slowly it trickles
        if self._in_body() and not self.transport.is_closing() and self._linger_timer is None:
            self._linger_timer = self.loop.call_later(self.linger, self._linger_expired)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        if len(self.connections) > self.max_connections:
            self.transport.write(self.refusal)
            self.transport.close()
            self._closed("limit")
            return
        self._arm()

    def data_received(self, data: bytes) -> None:
        if self._in_head():
            # the parsers buffer a head until it is complete (httptools without any limit,
            # h11 only when it comes in pieces): its bytes are counted here, before them
            seen = self._tail + data
            end = seen.find(b"\r\n\r\n")
            self._head_bytes += len(data) if end < 0 else end + 4 - len(self._tail)
            self._tail = seen[-3:]
            if self._head_bytes > self.max_header_bytes:
                self._refuse(self.too_large)
                return
        super().data_received(data)
        # waiting for a head: bounded in time; once a request is in, its body is the
        # middleware's and the idle time after it uvicorn's keep-alive timeout
        if self._in_head() and not self.transport.is_closing():
            if self._header_timer is None:
                self._arm()
        else:
            self._disarm()
            self._head_bytes, self._tail = 0, b""
        if self._linger_timer is not None and not self._in_body():
            # the unread body ended in time: the connection goes on as usual
            self._linger_timer.cancel()
            self._linger_timer = None

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        if self._linger_timer is not None:
            self._linger_timer.cancel()
            self._linger_timer = None
        super().connection_lost(exc)

    def _linger_expired(self) -> None:
        self._linger_timer = None
        if self._in_body() and not self.transport.is_closing():
            self.transport.abort()
            self._closed("unread_body")

    def send_400_response(self, msg: str) -> None:
        """A malformed request (uvicorn's own answer is text/plain)."""
        self._refuse(self.malformed)

    def _refuse(self, answer: bytes) -> None:
        self._disarm()
        self.transport.write(answer)
        self.transport.close()
        self._closed("bad_request")

    def _closed(self, reason: str) -> None:
        if self.on_closed is not None:
            self.on_closed(reason)

    def _arm(self) -> None:
        self._header_timer = self.loop.call_later(self.header_timeout, self._header_timed_out)

    def _disarm(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _header_timed_out(self) -> None:
        self._header_timer = None
        if self._in_head() and not self.transport.is_closing():
            self.transport.abort()
            self._closed("header_timeout")

    def _expose_abort(self, scope: Any) -> None:
        if scope is not None:
            scope.setdefault("extensions", {})["planner.abort"] = self.transport.abort


class _BoundedH11(_Bounded, H11Protocol):
    def _in_head(self) -> bool:
        return self.conn.their_state is h11.IDLE

    def _in_body(self) -> bool:
        return self.conn.their_state is h11.SEND_BODY

    def handle_events(self) -> None:
        super().handle_events()
        self._expose_abort(self.scope)


class _BoundedHttpTools(_Bounded, HttpToolsProtocol):
    _head = True  # no request's head complete since the last request's end

    def _in_head(self) -> bool:
        # (a request fully received is still in progress until its answer is complete)
        return self._head and (self.cycle is None or self.cycle.response_complete)

    def _in_body(self) -> bool:
        return not self._head

    def on_headers_complete(self) -> None:
        self._head = False
        super().on_headers_complete()
        self._expose_abort(self.scope)

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self._head = True


def protocol_class(settings: Settings, max_connections: int,
                   on_closed: Callable[[str], None] | None = None) -> type[asyncio.Protocol]:
    """uvicorn's HTTP protocol (``settings.http``) with the bounds of the module docstring.

    ``on_closed`` is called with ``"limit"``, ``"header_timeout"``, ``"bad_request"`` or
    ``"unread_body"`` for every connection the protocol refuses or closes (for the metrics).
    """
    limit = settings.max_header_bytes
    base: type[_Bounded] = _BoundedH11 if settings.http == "h11" else _BoundedHttpTools
    attributes = {
        "max_connections": max_connections,
        "header_timeout": settings.header_timeout,
        "max_header_bytes": limit,
        "linger": min(LINGER, settings.body_timeout),
        "refusal": _raw_problem(503, b"Service Unavailable", "overloaded",
                                f"more than {max_connections} open connections; retry later",
                                {"max_connections": max_connections,
                                 "retry_after": settings.retry_after},
                                retry_after=settings.retry_after),
        "too_large": _raw_problem(431, b"Request Header Fields Too Large", "invalid_request",
                                  f"the request line and headers exceed {limit} bytes",
                                  {"max_header_bytes": limit}),
        "malformed": _raw_problem(400, b"Bad Request", "invalid_request",
                                  "malformed HTTP request", {}),
        "on_closed": staticmethod(on_closed) if on_closed is not None else None,
    }
    return type("Bounded" + base.__name__.lstrip("_"), (base,), attributes)


class Server(uvicorn.Server):
    """uvicorn's server, telling ``on_shutdown`` when a graceful shutdown starts."""

    def __init__(self, config: uvicorn.Config, on_shutdown: Callable[[], None]) -> None:
        super().__init__(config)
        self._on_shutdown = on_shutdown

    async def shutdown(self, sockets: Any = None) -> None:
        try:
            self._on_shutdown()
        except Exception:  # noqa: BLE001 - the shutdown itself must go on
            log.exception("shutdown hook failed")
        await super().shutdown(sockets)


def drain_margin(shutdown_timeout: float) -> float:
    """Seconds before uvicorn's shutdown deadline at which the pool gives up what is left
    (time to send those answers)."""
    return min(1.0, shutdown_timeout / 4.0)


def serve(settings: Settings) -> None:
    """Run the app (:data:`service.main.app`) until SIGTERM/SIGINT."""
    from .main import app

    memory.fix_mmap_threshold()  # large answers' memory returns to the system when freed
    fd_limit = raise_fd_limit()
    cap = connection_cap(settings, fd_limit)
    metrics = app.state.metrics
    protocol = protocol_class(settings, cap,
                              on_closed=lambda reason: metrics.connections_closed.labels(
                                  reason).inc())
    graceful = int(math.ceil(settings.shutdown_timeout))

    def drain() -> None:
        pool = getattr(app.state, "pool", None)
        if pool is not None:
            pool.drain(settings.shutdown_timeout - drain_margin(settings.shutdown_timeout))

    config = uvicorn.Config(app, host=settings.host, port=settings.port, http=protocol,
                            log_level=settings.log_level, log_config=None, access_log=False,
                            proxy_headers=True, server_header=False,
                            h11_max_incomplete_event_size=settings.max_header_bytes,
                            timeout_keep_alive=settings.keep_alive_timeout,
                            # SIGTERM: stop accepting, let requests in flight finish (at most
                            # this long), then the lifespan stops the workers; exit status 0
                            timeout_graceful_shutdown=graceful)
    Server(config, on_shutdown=drain).run()
