"""How ``python -m service`` serves the app: uvicorn with h11, bounded connections and a
shutdown that answers what it cannot finish.

uvicorn's own settings do what they can (:func:`serve`): h11 (its httptools parser has no
header size limit) with ``h11_max_incomplete_event_size`` (the request line and headers, more
is refused), ``timeout_keep_alive`` and ``timeout_graceful_shutdown``. What uvicorn cannot do is
added to its h11 protocol (:func:`protocol_class`), in as little code as it takes:

* **a connection cap** (``max_connections``, lowered to fit the file descriptor limit, whose
  soft value is raised to the hard one at start): a connection past it is answered 503 at once
  and closed, before anything is read. uvicorn's ``limit_concurrency`` answers only when a
  request arrives (a silent connection keeps its descriptor) and with a text/plain body;
* **a header timeout** (``header_timeout``): a connection that has not sent a complete request
  line and headers that long after it opened, or after the first byte of a later request, is
  closed (uvicorn only times out idle keep-alive connections);
* **problem documents** for malformed HTTP: 400, or 431 for headers over the limit (uvicorn's
  are text/plain);
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

from .encoding import finite_json
from .problems import PROBLEM_MEDIA_TYPE, problem_body
from .settings import Settings

log = logging.getLogger("service.server")

#: File descriptors kept for everything but client connections: the listening socket, the
#: workers' pipes, the forkserver, logs, imports.
RESERVED_FDS = 64
#: Descriptors kept per worker process (its pipe, the process sentinel, a replacement's).
FDS_PER_WORKER = 4


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


def protocol_class(settings: Settings, max_connections: int,
                   on_closed: Callable[[str], None] | None = None) -> type[H11Protocol]:
    """uvicorn's h11 protocol with the bounds of the module docstring.

    ``on_closed`` is called with ``"limit"``, ``"header_timeout"`` or ``"bad_request"`` for
    every connection the protocol refuses or closes (for the metrics).
    """
    header_timeout = settings.header_timeout
    max_header_bytes = settings.max_header_bytes
    refusal = _raw_problem(503, b"Service Unavailable", "overloaded",
                           f"more than {max_connections} open connections; retry later",
                           {"max_connections": max_connections, "retry_after":
                            settings.retry_after}, retry_after=settings.retry_after)

    def closed(reason: str) -> None:
        if on_closed is not None:
            on_closed(reason)

    too_large = _raw_problem(431, b"Request Header Fields Too Large", "invalid_request",
                             f"the request line and headers exceed {max_header_bytes} bytes",
                             {"max_header_bytes": max_header_bytes})

    class BoundedH11Protocol(H11Protocol):
        _header_timer: asyncio.TimerHandle | None = None
        _head_bytes = 0     # of the request line and headers being received
        _tail = b""         # the last bytes of them (their end may straddle two reads)

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            if len(self.connections) > max_connections:
                transport.write(refusal)
                transport.close()
                closed("limit")
                return
            self._arm()

        def data_received(self, data: bytes) -> None:
            if self.conn.their_state is h11.IDLE:
                # h11 bounds only a head that arrives in pieces (max_incomplete_event_size);
                # one read can hold a whole 64 MB head: count it here
                seen = self._tail + data
                end = seen.find(b"\r\n\r\n")
                self._head_bytes += len(data) if end < 0 else end + 4 - len(self._tail)
                self._tail = seen[-3:]
                if self._head_bytes > max_header_bytes:
                    self._disarm()
                    self.transport.write(too_large)
                    self.transport.close()
                    closed("bad_request")
                    return
            super().data_received(data)
            if self.conn.their_state is not h11.IDLE:
                self._head_bytes, self._tail = 0, b""
            # waiting for (the rest of) a request line and headers: bounded in time; once a
            # request is in, its body is the middleware's and its idle end uvicorn's keep-alive
            if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
                if self._header_timer is None:
                    self._arm()
            else:
                self._disarm()

        def handle_events(self) -> None:
            super().handle_events()
            if self.scope is not None:
                extensions: dict[str, Any] = self.scope.setdefault(  # type: ignore[assignment]
                    "extensions", {})
                extensions["planner.abort"] = self.transport.abort

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm()
            super().connection_lost(exc)

        def send_400_response(self, msg: str) -> None:
            self._disarm()
            buffered = len(self.conn.trailing_data[0])
            if buffered > max_header_bytes:
                status, code, detail = 431, "invalid_request", (
                    f"the request line and headers exceed {max_header_bytes} bytes")
            else:
                status, code, detail = 400, "invalid_request", "malformed HTTP request"
            body = finite_json(problem_body(code, detail, status=status,
                                            diagnostics={"max_header_bytes": max_header_bytes}))
            headers = [(b"content-type", PROBLEM_MEDIA_TYPE.encode()),
                       (b"connection", b"close")]
            try:
                reason = b"Request Header Fields Too Large" if status == 431 else b"Bad Request"
                for event in (h11.Response(status_code=status, headers=headers, reason=reason),
                              h11.Data(data=body), h11.EndOfMessage()):
                    self.transport.write(self.conn.send(event) or b"")
            except h11.LocalProtocolError:  # a state h11 cannot answer from: just close
                pass
            self.transport.close()
            closed("bad_request")

        def _arm(self) -> None:
            self._header_timer = self.loop.call_later(header_timeout, self._header_timed_out)

        def _disarm(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _header_timed_out(self) -> None:
            self._header_timer = None
            if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
                self.transport.abort()
                closed("header_timeout")

    return BoundedH11Protocol


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
