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
  :func:`_worker_main`: it warms up (a no-op when the forkserver did), says ``ready``, then
  answers one ``(kind, payload)`` message at a time with a plain dict
  (:func:`service.jobs.run_job`; a result's JSON is encoded by the worker).
* The server's end of each pipe is an asyncio transport (:class:`_PipeProtocol`): a job is
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
  long as the pool is open, so a slot is never given up. Idle workers are pinged every
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
* A request whose client goes away does not leak its worker: the worker is returned (or
  replaced) by the pipe's protocol or the timer when the job ends, never by the request's
  coroutine. A request cancelled while it waits leaves the queue; one cancelled while its job
  runs sends the worker :data:`CANCEL_SIGNAL`, which makes the job's next deadline check fail
  (:func:`optimizer.planner.context.cancel`), so the worker is free again without a restart.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import multiprocessing
import os
import pickle
import signal
import socket
import struct
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any, Callable

from .procstate import is_stopped

log = logging.getLogger("service.workers")

#: Modules a forkserver imports once, so that every forked worker starts with them loaded (and
#: warmed up: :mod:`service.preload`).
PRELOAD = ["service.preload"]

#: The pool's liveness probe of an idle worker and its answer.
PING = "ping"
PONG = {"ok": True, "pong": True}

#: The signal that asks a worker to drop its job (see :func:`_worker_main`).
CANCEL_SIGNAL = signal.SIGUSR1

#: Seconds between attempts to start a replacement worker: doubled after each failure up to
#: the last value (a failed start is retried for as long as the pool is open).
RESTART_BACKOFF = (0.1, 2.0)


class PoolError(Exception):
    """Base class of the pool's own failures."""


class Overloaded(PoolError):
    """More than ``queue_size`` requests would wait for a worker."""


class JobTimeout(PoolError):
    """The worker did not answer within the job's time limit plus grace; it was killed."""

    def __init__(self, limit: float) -> None:
        super().__init__(f"no answer within {limit:g} s")
        self.limit = limit


class WorkerLost(PoolError):
    """The worker process ended (crashed or was killed) before answering."""


class QueueTimeout(Overloaded):
    """No worker became free within the queue's time limit (none may be alive)."""


class ShuttingDown(PoolError):
    """The server is stopping and its drain deadline came before the job could finish."""


# ---------------------------------------------------------------------------- worker side
def _worker_main(conn: Connection, warmup: bool, log_level: str, nice: int = 0,
                 native_cache: str | None = None) -> None:
    """Entry point of a worker process: warm up, then serve jobs until told to stop."""
    # the server decides when workers stop: a SIGINT/SIGTERM sent to the whole process group
    # (Ctrl-C, systemd, some container runtimes) must not kill a job in flight; the server
    # finishes its requests, then stops the workers (and a worker whose server died sees its
    # pipe close and exits)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from optimizer.planner import context as _plan

    from . import jobs

    # the server's request to drop the job in progress (its client went away): the solve ends
    # at its next deadline check (:func:`optimizer.planner.context.cancel`)
    signal.signal(CANCEL_SIGNAL, lambda signum, frame: _plan.cancel())
    from .logs import configure_logging

    configure_logging(log_level)
    info: dict[str, Any] = {}
    if native_cache:
        from optimizer import native
        try:
            info["native"] = native.configure(native_cache) is not None
        except OSError as exc:  # an unusable directory: the virtual machine serves alone
            logging.getLogger("service.worker").warning(
                "compiled NLP functions off: %s", type(exc).__name__)
            info["native"] = False
    if warmup:
        try:
            info.update(jobs.warm_up())
        except Exception as exc:  # noqa: BLE001 - warm-up is an optimisation only
            info["warmup_error"] = type(exc).__name__
    _freeze_heap()
    if nice > 0:
        # below the event loop: it only routes requests, and a loop descheduled behind two
        # CPU-bound solves is where the latency tail came from (p99 at 8 clients 25-26 ->
        # 19-21 ms on 2 cores, interleaved runs); the solves' total CPU is unchanged
        os.nice(nice)
    conn.send(("ready", info))
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            break
        if message is None:
            break
        kind, payload, request_id = message
        if kind == PING:
            conn.send(PONG)
            continue
        _plan.clear_cancel()
        conn.send(jobs.run_job(kind, payload, request_id))
    conn.close()


def _freeze_heap() -> None:
    """Move every object alive now (the solver modules, CasADi functions, warm-up caches:
    hundreds of thousands of them) out of the garbage collector's reach.

    They live as long as the process. Without this, each of the collector's full passes,
    triggered by the containers a plan allocates, walks all of them again: about 0.2 ms of a
    worker's 3 ms per plan. Objects created later (the jobs') are collected as usual. Called
    after the warm-up; the forkserver does the same before it forks (:mod:`service.preload`),
    which also keeps the collector from writing to (and so copying) the pages the workers
    share with it.
    """
    gc.collect()
    gc.freeze()


# ---------------------------------------------------------------------------- server side
def _consume(future: asyncio.Future[Any]) -> None:
    """Retrieve the outcome of a future nobody awaits (a ping), so asyncio does not log it."""
    if not future.cancelled():
        future.exception()


_HEADER = struct.Struct("!i")
_LONG_HEADER = struct.Struct("!Q")


def _frame(message: Any) -> list[bytes]:
    """``message`` pickled, with the length header of :class:`multiprocessing.connection`."""
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    n = len(data)
    if n > 0x7FFFFFFF:
        return [_HEADER.pack(-1) + _LONG_HEADER.pack(n), data]
    return [_HEADER.pack(n), data]


class _PipeProtocol(asyncio.Protocol):
    """The server's end of a worker's pipe: unframes and unpickles the worker's messages."""

    def __init__(self, worker: "_Worker") -> None:
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


class _Worker:
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
        self.on_idle_lost: Callable[[_Worker], None] | None = None
        self._future: asyncio.Future[Any] | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._on_end: Callable[[_Worker, BaseException | None], None] | None = None
        self._limit = 0.0

    @property
    def busy(self) -> bool:
        return self._future is not None

    @property
    def live(self) -> bool:
        """Started, warmed up and not known to be dead, killed or unresponsive."""
        return self.up and not (self.dead or self.retired)

    def begin(self, message: Any, limit: float,
              on_end: Callable[["_Worker", BaseException | None], None] | None = None,
              ) -> asyncio.Future[Any]:
        """Send ``message`` (unless None) and expect one answer within ``limit`` s."""
        if self.dead or self.retired or (message is not None and self.transport is None):
            raise WorkerLost(f"worker {self.ident} ended unexpectedly")
        frame = _frame(message) if message is not None else None
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Any] = loop.create_future()
        self._future, self._on_end, self._limit = future, on_end, limit
        self._timer = loop.call_later(limit, self._on_timeout)
        if frame is not None and self.transport is not None:
            self.transport.writelines(frame)
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
            self.transport.writelines(_frame(None))

    def reap(self, timeout: float = 5.0) -> None:
        """Wait for the process to end, SIGKILL it after ``timeout`` s (in a helper thread)."""
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(5.0)


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


class WorkerPool:
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
        self._idle: asyncio.Queue[_Worker] | None = None
        self._all: set[_Worker] = set()
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

    async def _watched(self, worker: _Worker, answer: asyncio.Future[Any]) -> dict[str, Any]:
        """:meth:`_await`, looking every ``ping_timeout`` s whether the worker has been
        stopped meanwhile: a stopped worker's job is ended :class:`WorkerLost` (so that
        :meth:`run` gives it to another worker) instead of waiting out its time limit."""
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
    async def _await(worker: _Worker, answer: asyncio.Future[Any]) -> dict[str, Any]:
        """The job's answer; when the request is cancelled (its client went away) the worker
        is asked to drop the job (where the method checks its deadline, it stops there)."""
        try:
            return await answer  # type: ignore[no-any-return]
        except asyncio.CancelledError:
            worker.interrupt(answer)
            raise

    async def _take(self) -> _Worker:
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
            if worker.dead or worker.retired:
                continue  # (a worker that died idle is being replaced: take the next)
            if is_stopped(worker.process.pid):
                # stopped while idle, before its ping noticed: it would hold this request
                # for its whole time limit
                worker.unresponsive = True
                self._replace_worker(worker, "unresponsive")
                continue
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
    def _finished(self, worker: _Worker, exc: BaseException | None) -> None:
        """Return the worker to the idle queue, or replace it if it was killed or died."""
        self._return(worker, exc, "timeout")

    def _pinged(self, worker: _Worker, exc: BaseException | None) -> None:
        self._return(worker, exc, "unresponsive")

    def _return(self, worker: _Worker, exc: BaseException | None, timeout_reason: str) -> None:
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

    async def _ping_idle(self) -> None:
        """Probe the idle workers every ``ping_interval`` s (see the class docstring)."""
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

    def _idle_lost(self, worker: _Worker) -> None:
        """A worker died while idle (OOM kill, an operator): take it out of the idle queue (the
        queue's size counts idle workers for admission and /readyz) and replace it at once."""
        if not self._closing:
            self._drop_idle(worker)
            self._replace_worker(worker, "lost")

    def _drop_idle(self, worker: _Worker) -> None:
        # runs on the event loop, like every get and put of the queue: nothing interleaves
        assert self._idle is not None
        keep = []
        while not self._idle.empty():
            w = self._idle.get_nowait()
            if w is not worker:
                keep.append(w)
        for w in keep:
            self._idle.put_nowait(w)

    def _replace_worker(self, worker: _Worker, reason: str) -> None:
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

    async def _start_worker(self) -> _Worker:
        loop = asyncio.get_running_loop()
        worker, sock = await loop.run_in_executor(self._threads, self._new_process)
        ready = worker.begin(None, self.start_timeout)  # before its message can arrive
        try:
            await loop.connect_accepted_socket(lambda: _PipeProtocol(worker), sock)
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
    def _new_process(self) -> tuple[_Worker, socket.socket]:
        """Start a worker process (blocking: runs in a helper thread); its pipe's socket."""
        ours, theirs = self._ctx.Pipe(duplex=True)
        with self._lock:
            ident = self._next_ident
            self._next_ident += 1
        proc = self._ctx.Process(target=_worker_main, args=(theirs, self.warmup, self.log_level, self.nice,
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
        return _Worker(process=proc, ident=ident), sock

    def _spawn_task(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("worker pool task failed: %r", task.exception())
