"""What the server and a worker say to each other over the worker's pipe, and how.

One duplex pipe (a Unix socket pair) per worker; each message is pickled and framed as
:class:`multiprocessing.connection.Connection` frames it (a 4-byte big-endian length, or ``-1``
and an 8-byte length), so that the worker's end is a plain blocking ``Connection`` and the
server's end an asyncio transport (:class:`PipeProtocol`) read by the event loop without a
helper thread.

Server -> worker:

* ``(kind, payload, request_id)``: run job ``kind`` of :data:`service.jobs.JOBS` on the
  JSON-shaped ``payload``; the worker answers with the outcome dict of
  :func:`service.jobs.run_job` (``ok``, ``body`` or ``error``, ``seconds``);
* ``(PING, None, None)``: the liveness probe of an idle worker; the answer is :data:`PONG`;
* ``None``: stop (the worker exits);
* and, outside the pipe, :data:`CANCEL_SIGNAL`: drop the job in progress (its client went away).

Worker -> server: first ``("ready", info)`` once warmed up, then one answer per message.
"""

from __future__ import annotations

import asyncio
import logging
import pickle
import signal
import struct
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .worker_handle import WorkerHandle

log = logging.getLogger("service.workers")

#: The pool's liveness probe of an idle worker and its answer.
PING = "ping"
PONG = {"ok": True, "pong": True}

#: The signal that asks a worker to drop its job (see :func:`service.worker_process.worker_main`).
CANCEL_SIGNAL = signal.SIGUSR1

_HEADER = struct.Struct("!i")
_LONG_HEADER = struct.Struct("!Q")


def frame(message: Any) -> list[bytes]:
    """``message`` pickled, with the length header of :class:`multiprocessing.connection`."""
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    n = len(data)
    if n > 0x7FFFFFFF:
        return [_HEADER.pack(-1) + _LONG_HEADER.pack(n), data]
    return [_HEADER.pack(n), data]


class PipeProtocol(asyncio.Protocol):
    """The server's end of a worker's pipe: unframes and unpickles the worker's messages."""

    def __init__(self, worker: WorkerHandle) -> None:
        self.worker = worker
        self.buffer = bytearray()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.worker.transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        buf = self.buffer
        buf += data
        while True:
            n = len(buf)
            if n < 4:
                return
            (size,) = _HEADER.unpack_from(buf)
            start = 4
            if size == -1:
                if n < 12:
                    return
                (size,) = _LONG_HEADER.unpack_from(buf, 4)
                start = 12
            end = start + size
            if n < end:
                return
            try:
                message = pickle.loads(buf[start:end])
            except Exception:  # noqa: BLE001 - a garbled pipe: treat the worker as lost
                log.exception("unreadable message from worker %s", self.worker.ident)
                self.worker.retire()
                self.worker.on_lost()
                return
            del buf[:end]
            self.worker.on_message(message)

    def connection_lost(self, exc: Exception | None) -> None:
        self.worker.on_lost()

