"""A small pool of solver processes with a bounded queue and enforced time limits.

Design (the simplest one that can kill a single stuck solve)
-----------------------------------------------------------
CasADi/IPOPT are not thread-safe and a solve can overrun its own deadline checks, so every solve
runs in a separate *process*, and a solve that overruns must be killed. A
``concurrent.futures.ProcessPoolExecutor`` cannot kill one task, so the pool is our own:

* ``size`` worker processes, created with the ``forkserver`` (default) or ``spawn`` start
  method, never a plain ``fork`` of the threaded server. The forkserver imports the solver
  modules and warms up once (:data:`PRELOAD`: :mod:`service.preload` builds the default robot's
  CasADi chained form), so that every worker it forks starts ready to plan; each worker is
  connected to the server by **one duplex pipe** (a Unix socket pair) and runs
  :func:`service.worker_process.worker_main`: it warms up (a no-op when the forkserver did),
  says ``ready``, then answers one ``(kind, payload)`` message at a time with a plain dict
  (:func:`service.jobs.run_job`; a result's JSON is encoded by the worker). The messages are
  :mod:`service.worker_protocol`'s.
* The server's end of each pipe is an asyncio transport
  (:class:`service.worker_protocol.PipeProtocol`) owned by a
  :class:`service.worker_handle.WorkerHandle`, which runs one job at a time: a job is
  written to it without blocking and its answer is read by the event loop as it arrives, with
  multiprocessing's framing (so the worker side is a plain blocking
  :class:`multiprocessing.connection.Connection`). No helper thread per request: a thread
  hand-off and its wake-ups cost more CPU than the whole HTTP request.
* Idle workers sit in an ``asyncio.Queue``. A request takes one (waiting if none is idle),
  sends its job and awaits a future that the pipe's protocol resolves.
* **Time limit**: each job arms a timer of ``limit`` seconds (the router passes ``time_limit``
  plus most of the grace, see :data:`service.dispatch.ANSWER_MARGIN`). When it fires, that
  worker is SIGKILLed at once, the request is answered ``timeout`` (504) without waiting for the
  process to be reaped (a helper thread reaps it), and a replacement process is started in the
  background; it joins the idle queue once ready. A worker whose pipe closes (crash, OOM kill)
  is replaced the same way; its job, if it had one, runs once more on another worker (jobs are
  pure functions of their payload), and a second loss raises :class:`WorkerLost` (503
  ``worker_lost``). An idle worker that dies is replaced before any request can take it.
* **A pool that heals**: a replacement that fails to start (dies while warming up, no file
  descriptors, a failed fork) is retried with a growing pause (:data:`RESTART_BACKOFF`) for as
  long as the pool is open, so a slot is never given up. The health checks
  (:mod:`service.pool_health`): idle workers are pinged every
  ``ping_interval`` s; one that does not answer within ``ping_timeout`` (stopped, wedged) is
  killed and replaced. Between pings, a worker found stopped (:mod:`service.procstate`) when a
  request takes it is replaced and the request takes another; one stopped under a job (looked
  at every ``ping_timeout`` s) is replaced and its job runs on another worker, as for a worker
  that died. :attr:`WorkerPool.ready` and :meth:`WorkerPool.live` count the workers
  that are warmed up and not known dead: ``/readyz`` is 503 while none is.
* **Bounded queue**: at most ``queue_size`` requests may wait for a worker; the next one is
  refused at once with :class:`Overloaded` (503 ``overloaded`` with ``Retry-After``), and one
  that waits longer than ``queue_timeout`` gets :class:`QueueTimeout` (also 503).
* **Shutdown**: :meth:`WorkerPool.drain` gives up, at a deadline, the requests still waiting
  and the jobs still running (:class:`ShuttingDown`, 503 ``shutting_down``), so that each is
  answered before the server's own shutdown timeout cancels it.
* The pool's failures are :mod:`service.pool_errors`' (re-exported here).
* A request whose client goes away does not leak its worker: the worker is returned (or
  replaced) by the pipe's protocol or the timer when the job ends, never by the request's
  coroutine. A request cancelled while it waits leaves the queue; one cancelled while its job
  runs sends the worker :data:`service.worker_protocol.CANCEL_SIGNAL`, which makes the job's
  next deadline check fail (:func:`optimizer.planner.context.cancel`), so the worker is free
  again without a restart.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable

from .pool_errors import (JobTimeout, Overloaded, PoolError, QueueTimeout, ShuttingDown,
                          WorkerLost)
from .pool_health import PoolHealth
from .worker_handle import WorkerHandle
from .worker_process import worker_main
from .worker_protocol import PipeProtocol

__all__ = ["PRELOAD", "RESTART_BACKOFF", "JobTimeout", "Overloaded", "PoolError", "PoolStats",
           "QueueTimeout", "ShuttingDown", "WorkerLost", "WorkerPool"]

log = logging.getLogger("service.workers")

#: Modules a forkserver imports once, so that every forked worker starts with them loaded (and
#: warmed up: :mod:`service.preload`).
PRELOAD = ["service.preload"]

#: Seconds between attempts to start a replacement worker: doubled after each failure up to
#: the last value (a failed start is retried for as long as the pool is open).
RESTART_BACKOFF = (0.1, 2.0)


@dataclass(frozen=True)
class PoolStats:
    """A snapshot for ``/readyz`` and the metrics."""

    size: int       # configured
    live: int       # started, warmed up, answering
    idle: int
    busy: int
    waiting: int
    started: bool
    warmed: bool    # some worker has been ready once
    closing: bool
    restarts: int


class WorkerPool(PoolHealth):
    """``size`` solver processes behind a queue of at most ``queue_size`` waiting requests.

    Parameters
    ----------
    size : int
        Number of worker processes.
    queue_size : int
        Requests that may wait for a worker before :class:`Overloaded` is raised.
    start_method : {"forkserver", "spawn"}
    warmup : bool
        Let each worker build the default robot's chained form before it takes work.
    start_timeout : float
        Seconds a worker may take to start and warm up.
    log_level : str
        Level of the workers' JSON logs.
    nice : int
        Niceness added to each worker process after its warm-up (0: none).
    native_cache : str, optional
        Directory of compiled NLP functions (:func:`optimizer.native.configure`); None: off.
    on_restart : callable, optional
        Called with the reason (``"timeout"``, ``"lost"`` or ``"unresponsive"``) whenever a
        worker is replaced.
    queue_timeout : float
        Seconds a request may wait for a worker before :class:`QueueTimeout`.
    ping_interval, ping_timeout : float
        Every ``ping_interval`` s each idle worker must answer a ping within ``ping_timeout``
        s, else it is killed and replaced (a stopped or wedged process would otherwise take
        the next request and hold it for the request's whole time limit).
    """

    def __init__(self, size: int, queue_size: int, *, start_method: str = "forkserver",
                 warmup: bool = True, start_timeout: float = 120.0, log_level: str = "info",
                 nice: int = 0, native_cache: str | None = None,
                 on_restart: Callable[[str], None] | None = None,
                 queue_timeout: float = 30.0, ping_interval: float = 1.0,
                 ping_timeout: float = 1.0) -> None:
        if size < 1:
            raise ValueError("size must be >= 1")
        self.size = size
        self.queue_size = queue_size
        self.warmup = warmup
        self.start_timeout = start_timeout
        self.log_level = log_level
        self.nice = nice
        self.native_cache = native_cache
        self.on_restart = on_restart
        self.queue_timeout = queue_timeout
        self.ping_interval = ping_interval
        self.ping_timeout = ping_timeout
        self._ctx: Any = multiprocessing.get_context(start_method)
        if start_method == "forkserver":
            self._ctx.set_forkserver_preload(PRELOAD)
        # process starts (the first one waits for the forkserver's imports) and reaping only
        self._threads = ThreadPoolExecutor(max_workers=size + 2,
                                           thread_name_prefix="planner-pool")
        self._idle: asyncio.Queue[WorkerHandle] | None = None
        self._all: set[WorkerHandle] = set()
        self._lock = threading.Lock()
        self._waiting = 0
        self._reserved = 0  # places taken by admitted batches whose items have not run yet
        self._restarts = 0
        self._next_ident = 0
        self._started = False
        self._closing = False
        self._drain_at: float | None = None
        self._waits: set[asyncio.Timeout] = set()
        self._warmed = asyncio.Event()
        self._initial_left = size
        self._tasks: set[asyncio.Task[Any]] = set()

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Start the workers; return at once (they start in the background, each slot
        retried until it has a worker).

        :attr:`ready` turns True once every initial worker has started or failed its first
        start, and one at least is live.
        """
        self._idle = asyncio.Queue()
        self._started = True
        self._initial_left = self.size
        for _ in range(self.size):
            self._spawn_task(self._fill_slot(initial=True))
        if self.ping_interval > 0:
            self._spawn_task(self._ping_idle())

    @property
    def ready(self) -> bool:
        """True once started (see :meth:`start`), while not shutting down and while at least
        one worker is live."""
        return (self._started and self._warmed.is_set() and not self._closing
                and self.live() > 0)

    def live(self) -> int:
        """Workers started, warmed up and not known dead or unresponsive."""
        with self._lock:
            return sum(w.live for w in self._all)

    def drain(self, seconds: float) -> None:
        """The server is stopping: whatever has not finished ``seconds`` from now is given up.

        At that moment every request still waiting for a worker and every job still running
        gets :class:`ShuttingDown` (their workers are killed; the pool is closing anyway), so
        that each is answered before the server's own shutdown deadline cancels it.
        """
        loop = asyncio.get_running_loop()
        self._drain_at = at = loop.time() + max(seconds, 0.0)
        for wait in list(self._waits):
            when = wait.when()
            if when is None or when > at:
                wait.reschedule(at)
        loop.call_at(at, self._give_up)

    def _give_up(self) -> None:
        self._closing = True
        with self._lock:
            busy = [w for w in self._all if w.busy]
        if busy or self._waiting:
            log.warning("shutdown deadline: giving up %d running and %d waiting jobs",
                        len(busy), self._waiting)
        for w in busy:
            w.retire()
            w.abandon(ShuttingDown("the server stopped before the job finished"))

    async def close(self) -> None:
        """Stop every worker (gracefully, then by force) and the helper threads."""
        self._closing = True
        for task in list(self._tasks):
            task.cancel()
        loop = asyncio.get_running_loop()
        with self._lock:
            workers = list(self._all)
            self._all.clear()
        for w in workers:
            if w.busy:
                w.retire()
            else:
                w.send_stop()
        if workers:
            await asyncio.gather(*(loop.run_in_executor(self._threads, w.reap, 2.0)
                                   for w in workers), return_exceptions=True)
        for w in workers:
            if w.transport is not None:
                w.transport.abort()
        self._threads.shutdown(wait=False, cancel_futures=True)

    def stats(self) -> PoolStats:
        """Current counts of live, idle, busy and waiting."""
        idle = self._idle.qsize() if self._idle is not None else 0
        with self._lock:
            alive = len(self._all)
            live = sum(w.live for w in self._all)
        return PoolStats(size=self.size, live=live, idle=idle, busy=max(alive - idle, 0),
                         waiting=self._waiting + self._reserved, started=self._started,
                         warmed=self._warmed.is_set(), closing=self._closing,
                         restarts=self._restarts)

    def pids(self) -> list[int]:
        """Process ids of the live workers (for operators and tests)."""
        with self._lock:
            return sorted(w.process.pid for w in self._all if w.process.pid is not None)

    # ------------------------------------------------------------------ jobs
    async def run(self, kind: str, payload: dict[str, Any], limit: float, *,
                  admit: bool = True, request_id: str | None = None) -> dict[str, Any]:
        """Run one job on a worker and return its outcome dict (see :mod:`service.jobs`).

        A job whose worker dies under it is run once more on another worker (jobs are pure
        functions of their payload, so a retry is safe); a second loss raises.

        Parameters
        ----------
        kind : str
            A key of :data:`service.jobs.JOBS`.
        payload : dict
            JSON-shaped job input.
        limit : float
            Seconds to wait for the answer once a worker has the job; on overrun the worker
            is killed and replaced.
        admit : bool
            Apply the queue bound (False for the items of an already admitted batch: each
            takes one of the places :meth:`admit` reserved for it).
        request_id : str, optional
            Put on the worker's log lines about this job.

        Raises
        ------
        Overloaded, QueueTimeout, JobTimeout, WorkerLost, ShuttingDown
        """
        if admit:
            self.admit()
        else:
            self.release(1)
            if self._idle is None or self._closing:
                raise Overloaded("the worker pool is not running")
        message = (kind, payload, request_id)
        try:
            worker = await self._take()
            return await self._watched(worker, worker.begin(message, limit, self._finished))
        except WorkerLost as exc:
            if self._closing:
                raise
            log.warning("%s under a job; running it once more on another worker", exc,
                        extra={"request_id": request_id})
        while True:
            worker = await self._take()
            # whatever killed the first may have killed this one too, its pipe's end not yet
            # read: a process that has ended is left to its replacement
            if worker.process.is_alive():
                return await self._watched(worker, worker.begin(message, limit, self._finished))

    async def _take(self) -> WorkerHandle:
        """An idle worker, waiting at most ``queue_timeout`` s (less when draining)."""
        idle = self._idle
        if idle is None or self._closing:
            raise Overloaded("the worker pool is not running")
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.queue_timeout
        while True:
            if idle.empty():
                at = deadline if self._drain_at is None else min(deadline, self._drain_at)
                self._waiting += 1
                try:
                    async with asyncio.timeout_at(at) as wait:
                        self._waits.add(wait)
                        try:
                            worker = await idle.get()
                        finally:
                            self._waits.discard(wait)
                except TimeoutError:
                    if self._drain_at is not None and loop.time() >= self._drain_at:
                        raise ShuttingDown("the server stopped before a worker became free"
                                           ) from None
                    raise QueueTimeout(f"no worker became free within {self.queue_timeout:g} s"
                                       f" ({self.live()} of {self.size} workers live)") from None
                finally:
                    self._waiting -= 1
            else:
                worker = idle.get_nowait()
            if self._usable(worker):
                return worker

    def admit(self, reserve: int = 0) -> None:
        """Raise :class:`Overloaded` when a new request would exceed the queue bound.

        Parameters
        ----------
        reserve : int
            Places to take at once for an admitted batch's items (they then run with
            ``admit=False``, each taking one; :meth:`release` returns the unused ones). A batch
            is admitted while the queue has room, so the queue holds at most ``queue_size``
            plus one batch.
        """
        if self._idle is None or self._closing:
            raise Overloaded("the worker pool is not running")
        # requests that will wait: those waiting, plus reserved places not yet waiting, less
        # the idle workers those will take
        queued = self._waiting + self._reserved - self._idle.qsize()
        if queued >= self.queue_size:
            raise Overloaded(f"{max(queued, 0)} requests already wait for a worker")
        self._reserved += reserve

    def release(self, count: int) -> None:
        """Return ``count`` places reserved by :meth:`admit`."""
        self._reserved = max(self._reserved - count, 0)

    # ------------------------------------------------------------------ internals
    def _finished(self, worker: WorkerHandle, exc: BaseException | None) -> None:
        """Return the worker to the idle queue, or replace it if it was killed or died."""
        self._return(worker, exc, "timeout")

    def _return(self, worker: WorkerHandle, exc: BaseException | None, timeout_reason: str) -> None:
        if self._closing:
            return
        if isinstance(exc, JobTimeout):
            self._replace_worker(worker, timeout_reason)
        elif worker.unresponsive:
            self._replace_worker(worker, "unresponsive")
        elif isinstance(exc, WorkerLost) or worker.dead or worker.retired:
            self._replace_worker(worker, "lost")
        else:
            assert self._idle is not None
            self._idle.put_nowait(worker)

    def _replace_worker(self, worker: WorkerHandle, reason: str) -> None:
        log.warning("replacing worker %s (%s)", worker.ident, reason)
        with self._lock:
            self._all.discard(worker)
        worker.retire()
        self._threads.submit(worker.reap)  # reap the process in the background
        self._restarts += 1
        if self.on_restart is not None:
            self.on_restart(reason)
        self._spawn_task(self._fill_slot())

    async def _fill_slot(self, initial: bool = False) -> None:
        """Start a worker for one slot, retrying any failed start (a worker that dies while
        starting, no file descriptors left, a fork that fails) with a growing pause, for as
        long as the pool is open: a slot is never given up."""
        pause, longest = RESTART_BACKOFF
        attempt = 0
        while not self._closing:
            attempt += 1
            try:
                await self._start_worker()
                return
            except Exception as exc:  # noqa: BLE001 - whatever failed, the slot is retried
                log.error("a worker failed to start (attempt %d; next in %.1f s): %s: %s",
                          attempt, pause, type(exc).__name__, exc)
            finally:
                if initial and attempt == 1:
                    self._initial_left -= 1
                    if self._initial_left == 0:
                        self._warmed.set()
            await asyncio.sleep(pause)
            pause = min(pause * 2.0, longest)

    async def _start_worker(self) -> WorkerHandle:
        loop = asyncio.get_running_loop()
        worker, sock = await loop.run_in_executor(self._threads, self._new_process)
        ready = worker.begin(None, self.start_timeout)  # before its message can arrive
        try:
            await loop.connect_accepted_socket(lambda: PipeProtocol(worker), sock)
        except BaseException:
            sock.close()
            worker.retire()
            ready.cancel()
            self._threads.submit(worker.reap)
            raise
        with self._lock:
            self._all.add(worker)
        try:
            tag, info = await ready
        except (JobTimeout, WorkerLost):
            with self._lock:
                self._all.discard(worker)
            worker.retire()
            self._threads.submit(worker.reap)
            raise WorkerLost(f"worker {worker.ident} did not start within "
                             f"{self.start_timeout:g} s or ended while starting") from None
        worker.ready_info = info
        if self._closing:
            return worker
        worker.up = True
        worker.on_idle_lost = self._idle_lost
        log.info("worker %s ready", worker.ident, extra={"warmup": worker.ready_info})
        assert self._idle is not None
        self._idle.put_nowait(worker)
        return worker

    def _new_process(self) -> tuple[WorkerHandle, socket.socket]:
        """Start a worker process (blocking: runs in a helper thread); its pipe's socket."""
        ours, theirs = self._ctx.Pipe(duplex=True)
        with self._lock:
            ident = self._next_ident
            self._next_ident += 1
        proc = self._ctx.Process(target=worker_main,
                                 args=(theirs, self.warmup, self.log_level, self.nice,
                                       self.native_cache),
                                 name=f"planner-worker-{ident}", daemon=True)
        t0 = time.perf_counter()
        try:
            proc.start()
        finally:
            theirs.close()
        try:
            # a duplex Pipe is a Unix socket pair: our end becomes an asyncio transport
            sock = socket.socket(fileno=os.dup(ours.fileno()))
            sock.setblocking(False)
        except BaseException:
            proc.kill()
            proc.join(5.0)
            raise
        finally:
            ours.close()
        log.debug("worker %s started in %.3f s", ident, time.perf_counter() - t0)
        return WorkerHandle(process=proc, ident=ident), sock

    def _spawn_task(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("worker pool task failed: %r", task.exception())
