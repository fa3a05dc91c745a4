"""How the worker pool finds workers that no longer answer: pings of idle workers, a watch of
busy ones, a look before a worker is handed a request, and the death of an idle one.

* Idle workers are pinged every ``ping_interval`` s; one that does not answer within
  ``ping_timeout`` (stopped, wedged) is killed and replaced.
* Between pings, a worker found stopped (:mod:`service.procstate`) when a request takes it is
  replaced and the request takes another (:meth:`PoolHealth._usable`).
* A worker stopped under a job (looked at every ``ping_timeout`` s, :meth:`PoolHealth._watched`)
  is replaced and its job ends :class:`WorkerLost`, so that the pool runs it on another worker,
  as for a worker that died.
* An idle worker whose pipe closes (OOM kill, an operator) leaves the idle queue and is
  replaced at once (:meth:`PoolHealth._idle_lost`).

:class:`PoolHealth` is a part of :class:`service.workers.WorkerPool` (a mixin): it uses the
pool's idle queue and its way to replace a worker.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from .pool_errors import WorkerLost
from .procstate import is_stopped
from .worker_handle import WorkerHandle
from .worker_protocol import PING

log = logging.getLogger("service.workers")


def _consume(future: asyncio.Future[Any]) -> None:
    """Retrieve the outcome of a future nobody awaits (a ping), so asyncio does not log it."""
    if not future.cancelled():
        future.exception()


class PoolHealth:
    """The pool's health checks (see the module docstring)."""

    # the pool's (service.workers.WorkerPool)
    ping_interval: float
    ping_timeout: float
    _idle: asyncio.Queue[WorkerHandle] | None
    _closing: bool

    def _replace_worker(self, worker: WorkerHandle, reason: str) -> None:
        raise NotImplementedError

    def _return(self, worker: WorkerHandle, exc: BaseException | None,
                timeout_reason: str) -> None:
        raise NotImplementedError

    async def _ping_idle(self) -> None:
        """Probe the idle workers every ``ping_interval`` s."""
        assert self._idle is not None
        idle = self._idle
        while not self._closing:
            await asyncio.sleep(self.ping_interval)
            workers = []
            while not idle.empty():
                workers.append(idle.get_nowait())
            for w in workers:
                if w.dead or w.retired:
                    continue  # died idle: already being replaced
                try:
                    pong = w.begin((PING, None, None), self.ping_timeout, self._pinged)
                except WorkerLost:
                    continue
                pong.add_done_callback(_consume)

    def _pinged(self, worker: WorkerHandle, exc: BaseException | None) -> None:
        """A ping ended: the worker goes back to the idle queue, or is replaced (no answer)."""
        self._return(worker, exc, "unresponsive")

    def _usable(self, worker: WorkerHandle) -> bool:
        """Whether an idle worker just taken from the queue may be handed a request: not dead,
        not killed, and not stopped (a stopped worker, found before its ping noticed, would
        hold the request for its whole time limit: it is replaced)."""
        if worker.dead or worker.retired:
            return False  # (a worker that died idle is being replaced)
        if is_stopped(worker.process.pid):
            worker.unresponsive = True
            self._replace_worker(worker, "unresponsive")
            return False
        return True

    async def _watched(self, worker: WorkerHandle, answer: asyncio.Future[Any]) -> dict[str, Any]:
        """The job's answer (:meth:`_await`), looking every ``ping_timeout`` s whether the
        worker has been stopped meanwhile: a stopped worker's job is ended
        :class:`WorkerLost` (so that the pool gives it to another worker) instead of waiting
        out its time limit."""
        loop = asyncio.get_running_loop()
        timer: list[asyncio.TimerHandle] = []

        def look() -> None:
            if answer.done() or worker.dead or worker.retired:
                return
            if is_stopped(worker.process.pid):
                log.warning("worker %s is stopped under a job", worker.ident)
                worker.unresponsive = True
                worker.retire()
                worker.abandon(WorkerLost(f"worker {worker.ident} stopped under the job"))
                return
            timer[:] = [loop.call_later(self.ping_timeout, look)]

        timer.append(loop.call_later(self.ping_timeout, look))
        try:
            return await self._await(worker, answer)
        finally:
            timer[0].cancel()

    @staticmethod
    async def _await(worker: WorkerHandle, answer: asyncio.Future[Any]) -> dict[str, Any]:
        """The job's answer; when the request is cancelled (its client went away) the worker
        is asked to drop the job (where the method checks its deadline, it stops there)."""
        try:
            return await answer  # type: ignore[no-any-return]
        except asyncio.CancelledError:
            worker.interrupt(answer)
            raise

    def _idle_lost(self, worker: WorkerHandle) -> None:
        """A worker died while idle: take it out of the idle queue (the queue's size counts
        idle workers for admission and /readyz) and replace it at once."""
        if not self._closing:
            self._drop_idle(worker)
            self._replace_worker(worker, "lost")

    def _drop_idle(self, worker: WorkerHandle) -> None:
        # runs on the event loop, like every get and put of the queue: nothing interleaves
        assert self._idle is not None
        keep = []
        while not self._idle.empty():
            w = self._idle.get_nowait()
            if w is not worker:
                keep.append(w)
        for w in keep:
            self._idle.put_nowait(w)
