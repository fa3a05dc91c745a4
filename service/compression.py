"""gzip for the clients that accept it, and nothing in the way of those that do not.

Starlette's ``GZipMiddleware`` handles an answer to a client that does not accept gzip too: it
inspects the answer's headers (to add ``Vary: Accept-Encoding``), which cost about a fifth of
the event loop's own CPU per plan request (80 of about 400 us, interleaved batches of
``python -m bench.http_stages``). :class:`GZipWhenAccepted` hands such requests straight to
the app, adding only that ``Vary`` header (to every answer: whether an answer is compressed
depends on ``Accept-Encoding``); requests that accept gzip go through ``GZipMiddleware`` as
before, with the same test (``gzip`` in the first ``Accept-Encoding`` header).

The answers of the paths in ``uncompressed`` (the service's ``/v1/replans``) are never
compressed: a controller replans every few tens of milliseconds and waits for the answer, and
gzip of a 30-40 KB continuation at level 1 took about 0.5 ms of the event loop's CPU per
replan (cProfile of the server under ``python -m bench.replan --http``, whose client, httpx,
accepts gzip by default, as most do), more than sending it uncompressed over a LAN takes.
"""

from __future__ import annotations

from starlette.middleware.gzip import GZipMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

_ACCEPT_ENCODING = b"accept-encoding"
_VARY = (b"vary", b"Accept-Encoding")


def accepts_gzip(scope: Scope) -> bool:
    """Whether the request accepts gzip, as ``GZipMiddleware`` decides it (``gzip`` in the
    value of its first ``Accept-Encoding`` header)."""
    for name, value in scope.get("headers", ()):
        if name.lower() == _ACCEPT_ENCODING:
            return b"gzip" in value
    return False


class GZipWhenAccepted:
    """``GZipMiddleware(app, minimum_size, compresslevel)`` for requests that accept gzip,
    but for those of the paths ``uncompressed``; the others go to ``app`` directly, their
    answers given ``Vary: Accept-Encoding``."""

    def __init__(self, app: ASGIApp, minimum_size: int = 500, compresslevel: int = 9,
                 uncompressed: frozenset[str] = frozenset()) -> None:
        self.app = app
        self.gzip = GZipMiddleware(app, minimum_size=minimum_size, compresslevel=compresslevel)
        self.uncompressed = uncompressed

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or (accepts_gzip(scope)
                                       and scope.get("path") not in self.uncompressed):
            await self.gzip(scope, receive, send)
            return

        async def send_with_vary(message: Message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [*message.get("headers", ()), _VARY]
            await send(message)

        await self.app(scope, receive, send_with_vary)
