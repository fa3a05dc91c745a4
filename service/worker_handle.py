"""The server's handle on one worker process: its pipe's end and the one job it runs.

Used by :class:`service.workers.WorkerPool`, on the event loop only (but :meth:`reap`, which
blocks and runs in a helper thread).
"""

from __future__ import annotations

import asyncio
import logging
import os
from typing import Any, Callable

from .pool_errors import JobTimeout, WorkerLost
from .worker_protocol import CANCEL_SIGNAL, frame

log = logging.getLogger("service.workers")


class WorkerHandle:
    """One worker process, the server's end of its pipe and the job it runs (if any).

    At most one job (or the wait for ``ready``) is outstanding: :meth:`begin` sends it and arms
    its timer; exactly one of the answer (:meth:`on_message`), the timer (:meth:`_on_timeout`)
    or the pipe closing (:meth:`on_lost`) ends it, resolving the request's future (unless the
    request went away) and calling ``on_end(worker, exc)``.
    """

    def __init__(self, process: Any, ident: int) -> None:
        self.process = process
        self.ident = ident
        self.transport: asyncio.Transport | None = None
        self.ready_info: dict[str, Any] = {}
        self.up = False        # it said ready
        self.dead = False      # its pipe closed
        self.retired = False   # taken out of the pool (killed or stopped)
        self.unresponsive = False  # found stopped (SIGSTOP)
        self.on_idle_lost: Callable[[WorkerHandle], None] | None = None
        self._future: asyncio.Future[Any] | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._on_end: Callable[[WorkerHandle, BaseException | None], None] | None = None
        self._limit = 0.0

    @property
    def busy(self) -> bool:
        return self._future is not None

    @property
    def live(self) -> bool:
        """Started, warmed up and not known to be dead, killed or unresponsive."""
        return self.up and not (self.dead or self.retired)

    def begin(self, message: Any, limit: float,
              on_end: Callable[[WorkerHandle, BaseException | None], None] | None = None,
              ) -> asyncio.Future[Any]:
        """Send ``message`` (unless None) and expect one answer within ``limit`` s."""
        if self.dead or self.retired or (message is not None and self.transport is None):
            raise WorkerLost(f"worker {self.ident} ended unexpectedly")
        data = frame(message) if message is not None else None
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Any] = loop.create_future()
        self._future, self._on_end, self._limit = future, on_end, limit
        self._timer = loop.call_later(limit, self._on_timeout)
        if data is not None and self.transport is not None:
            self.transport.writelines(data)
        return future

    def _end(self, result: Any = None, exc: BaseException | None = None) -> None:
        future, on_end, timer = self._future, self._on_end, self._timer
        self._future = self._on_end = self._timer = None
        if timer is not None:
            timer.cancel()
        if future is not None and not future.done():
            if exc is not None:
                future.set_exception(exc)
            else:
                future.set_result(result)
        if on_end is not None:
            on_end(self, exc)

    def interrupt(self, future: asyncio.Future[Any]) -> None:
        """Ask the process to drop the job of ``future`` if it still runs it (the request
        went away); its answer, a timeout, then ends the job as usual."""
        if self._future is future and not (self.dead or self.retired):
            try:
                os.kill(self.process.pid, CANCEL_SIGNAL)
            except (ProcessLookupError, TypeError):
                pass

    def abandon(self, exc: BaseException) -> None:
        """End the outstanding job with ``exc`` (the pool is giving it up)."""
        if self._future is not None:
            self._end(exc=exc)

    def on_message(self, message: Any) -> None:
        if self._future is None:  # nothing expected (cannot happen: one job at a time)
            log.warning("unexpected message from worker %s", self.ident)
            return
        self._end(result=message)

    def _on_timeout(self) -> None:
        # SIGKILL at once and answer; the process is reaped later (:meth:`reap`), so that the
        # answer does not wait for the kernel to tear the process down
        self.retire()
        self._end(exc=JobTimeout(self._limit))

    def on_lost(self) -> None:
        if self.dead:
            return
        self.dead = True
        if self._future is not None:
            self._end(exc=WorkerLost(f"worker {self.ident} ended unexpectedly"))
        elif not self.retired and self.on_idle_lost is not None:
            self.on_idle_lost(self)

    def retire(self) -> None:
        """SIGKILL the process (if alive) and close the pipe, without waiting."""
        self.retired = True
        if self.process.is_alive():
            self.process.kill()
        if self.transport is not None:
            self.transport.abort()

    def send_stop(self) -> None:
        """Ask the worker to exit (it finishes nothing: call only when it is idle)."""
        self.retired = True
        if self.transport is not None and not self.dead:
            self.transport.writelines(frame(None))

    def reap(self, timeout: float = 5.0) -> None:
        """Wait for the process to end, SIGKILL it after ``timeout`` s (in a helper thread)."""
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(5.0)
