"""A small pool of solver processes with a bounded queue and enforced time limits.

Design (the simplest one that can kill a single stuck solve)
-----------------------------------------------------------
CasADi/IPOPT are not thread-safe and a solve can overrun its own deadline checks, so every solve
runs in a separate *process*, and a solve that overruns must be killed. A
``concurrent.futures.ProcessPoolExecutor`` cannot kill one task, so the pool is our own:

* ``size`` worker processes, created with the ``forkserver`` (default) or ``spawn`` start
  method, never a plain ``fork`` of the threaded server. Each worker is connected to the server
  by **one duplex pipe** and runs :func:`_worker_main`: it warms up once (builds the default
  robot's CasADi chained form, :func:`service.jobs.warm_up`), says ``ready``, then answers one
  ``(kind, payload)`` message at a time with a plain dict (:func:`service.jobs.run_job`).
* Idle workers sit in an ``asyncio.Queue``. A request takes one (waiting if none is idle),
  sends its job and waits for the answer in a helper thread (``loop.run_in_executor``:
  ``conn.poll(limit)`` then ``conn.recv()``), so the event loop never blocks.
* **Time limit**: the helper thread polls at most ``limit`` seconds (the router passes
  ``time_limit`` plus most of the grace, see :data:`service.dispatch.ANSWER_MARGIN`). On overrun
  it SIGKILLs that worker at once, the request is answered ``timeout`` (504) without waiting for
  the process to be reaped, and a replacement process is started in the background; it joins
  the idle queue once warmed up. A worker that dies (crash, OOM kill) is replaced the same way
  (``numerical_failure``).
* **Bounded queue**: at most ``queue_size`` requests may wait for a worker; the next one is
  refused at once with :class:`Overloaded` (503 ``overloaded`` with ``Retry-After``).
* A request whose client goes away does not leak its worker: the worker is returned (or
  replaced) by a callback on the helper thread's future, never by the request's coroutine.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import signal
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, Callable

log = logging.getLogger("service.workers")

#: Modules a forkserver imports once, so that every forked worker starts with them loaded.
PRELOAD = ["service.jobs"]


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


# ---------------------------------------------------------------------------- worker side
def _worker_main(conn: Connection, warmup: bool, log_level: str) -> None:
    """Entry point of a worker process: warm up, then serve jobs until told to stop."""
    # the server decides when workers stop: a SIGINT/SIGTERM sent to the whole process group
    # (Ctrl-C, systemd, some container runtimes) must not kill a job in flight; the server
    # finishes its requests, then stops the workers (and a worker whose server died sees its
    # pipe close and exits)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from . import jobs
    from .logs import configure_logging

    configure_logging(log_level)
    info: dict[str, Any] = {}
    if warmup:
        try:
            info = jobs.warm_up()
        except Exception as exc:  # noqa: BLE001 - warm-up is an optimisation only
            info = {"warmup_error": type(exc).__name__}
    conn.send(("ready", info))
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            break
        if message is None:
            break
        kind, payload = message
        conn.send(jobs.run_job(kind, payload))
    conn.close()


# ---------------------------------------------------------------------------- server side
@dataclass(eq=False)
class _Worker:
    """One worker process and the server's end of its pipe."""

    process: Any
    conn: Connection
    ident: int
    ready_info: dict[str, Any] = field(default_factory=dict)

    def wait_ready(self, timeout: float) -> None:
        """Block until the worker has warmed up (runs in a helper thread)."""
        if not self.conn.poll(timeout):
            self.kill()
            raise WorkerLost(f"worker {self.ident} did not start within {timeout:g} s")
        try:
            tag, info = self.conn.recv()
        except (EOFError, OSError) as exc:
            self.kill()
            raise WorkerLost(f"worker {self.ident} ended while starting") from exc
        self.ready_info = info

    def call(self, message: tuple[str, dict[str, Any]], limit: float) -> dict[str, Any]:
        """Send one job and wait at most ``limit`` s for its answer (runs in a helper thread).

        Raises
        ------
        JobTimeout
            No answer in time; the process has been killed.
        WorkerLost
            The process ended before answering.
        """
        try:
            self.conn.send(message)
            if not self.conn.poll(limit):
                # SIGKILL at once and answer; the process is reaped later (:meth:`kill`), so
                # that the answer does not wait for the kernel to tear the process down
                if self.process.is_alive():
                    self.process.kill()
                raise JobTimeout(limit)
            return self.conn.recv()
        except (EOFError, OSError, BrokenPipeError) as exc:
            self.kill()
            raise WorkerLost(f"worker {self.ident} ended unexpectedly") from exc

    def stop(self, timeout: float = 2.0) -> None:
        """Ask the worker to exit; kill it if it does not within ``timeout``."""
        try:
            self.conn.send(None)
        except (OSError, ValueError):
            pass
        self.process.join(timeout)
        self.kill()

    def kill(self) -> None:
        """SIGKILL the process (if alive), reap it and close the pipe."""
        if self.process.is_alive():
            self.process.kill()
        self.process.join(5.0)
        try:
            self.conn.close()
        except OSError:
            pass


@dataclass(frozen=True)
class PoolStats:
    """A snapshot for ``/readyz`` and the metrics."""

    size: int
    idle: int
    busy: int
    waiting: int
    started: bool
    warmed: bool
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
    on_restart : callable, optional
        Called with the reason (``"timeout"`` or ``"lost"``) whenever a worker is replaced.
    """

    def __init__(self, size: int, queue_size: int, *, start_method: str = "forkserver",
                 warmup: bool = True, start_timeout: float = 120.0, log_level: str = "info",
                 on_restart: Callable[[str], None] | None = None) -> None:
        if size < 1:
            raise ValueError("size must be >= 1")
        self.size = size
        self.queue_size = queue_size
        self.warmup = warmup
        self.start_timeout = start_timeout
        self.log_level = log_level
        self.on_restart = on_restart
        self._ctx: Any = multiprocessing.get_context(start_method)
        if start_method == "forkserver":
            self._ctx.set_forkserver_preload(PRELOAD)
        self._threads = ThreadPoolExecutor(max_workers=2 * size + 2,
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
        self._warmed = asyncio.Event()
        self._tasks: set[asyncio.Task[Any]] = set()

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Start the workers; return at once (they warm up in the background).

        :attr:`ready` turns True when the initial workers have warmed up.
        """
        self._idle = asyncio.Queue()
        self._started = True
        starters = [self._start_worker() for _ in range(self.size)]

        async def _all_started() -> None:
            results = await asyncio.gather(*starters, return_exceptions=True)
            failed = [r for r in results if isinstance(r, BaseException)]
            for exc in failed:
                log.error("a worker failed to start: %s", exc)
            if len(failed) < len(results):
                self._warmed.set()

        self._spawn_task(_all_started())

    @property
    def ready(self) -> bool:
        """True once started, warmed up, and not shutting down."""
        return self._started and self._warmed.is_set() and not self._closing

    async def close(self) -> None:
        """Stop every worker (gracefully, then by force) and the helper threads."""
        self._closing = True
        for task in list(self._tasks):
            task.cancel()
        loop = asyncio.get_running_loop()
        with self._lock:
            workers = list(self._all)
            self._all.clear()
        if workers:
            await asyncio.gather(*(loop.run_in_executor(self._threads, w.stop)
                                   for w in workers), return_exceptions=True)
        self._threads.shutdown(wait=False, cancel_futures=True)

    def stats(self) -> PoolStats:
        """Current counts of idle, busy and waiting."""
        idle = self._idle.qsize() if self._idle is not None else 0
        with self._lock:
            alive = len(self._all)
        return PoolStats(size=self.size, idle=idle, busy=max(alive - idle, 0),
                         waiting=self._waiting + self._reserved, started=self._started,
                         warmed=self._warmed.is_set(), restarts=self._restarts)

    def pids(self) -> list[int]:
        """Process ids of the live workers (for operators and tests)."""
        with self._lock:
            return sorted(w.process.pid for w in self._all if w.process.pid is not None)

    # ------------------------------------------------------------------ jobs
    async def run(self, kind: str, payload: dict[str, Any], limit: float, *,
                  admit: bool = True) -> dict[str, Any]:
        """Run one job on a worker and return its outcome dict (see :mod:`service.jobs`).

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

        Raises
        ------
        Overloaded, JobTimeout, WorkerLost
        """
        if admit:
            self.admit()
        else:
            self.release(1)
            if self._idle is None or self._closing:
                raise Overloaded("the worker pool is not running")
        assert self._idle is not None
        self._waiting += 1
        try:
            worker = await self._idle.get()
        finally:
            self._waiting -= 1
        loop = asyncio.get_running_loop()
        fut: Future[dict[str, Any]] = self._threads.submit(worker.call, (kind, payload), limit)
        fut.add_done_callback(
            lambda f: loop.call_soon_threadsafe(self._finished, worker, f))
        return await asyncio.wrap_future(fut)

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
    def _finished(self, worker: _Worker, fut: Future[dict[str, Any]]) -> None:
        """Return the worker to the idle queue, or replace it if it was killed or died."""
        exc = None if fut.cancelled() else fut.exception()
        if self._closing:
            return
        if isinstance(exc, (JobTimeout, WorkerLost)):
            reason = "timeout" if isinstance(exc, JobTimeout) else "lost"
            log.warning("replacing worker %s (%s)", worker.ident, reason)
            with self._lock:
                self._all.discard(worker)
            self._threads.submit(worker.kill)  # reap it and close its pipe
            self._restarts += 1
            if self.on_restart is not None:
                self.on_restart(reason)
            self._spawn_task(self._replace())
        else:
            assert self._idle is not None
            self._idle.put_nowait(worker)

    async def _replace(self, attempts: int = 3) -> None:
        """Start a replacement worker, retrying a failed start a few times."""
        for attempt in range(attempts):
            try:
                await self._start_worker()
                return
            except WorkerLost as exc:
                log.error("replacement worker failed to start (attempt %d): %s", attempt + 1, exc)
                await asyncio.sleep(1.0)

    async def _start_worker(self) -> _Worker:
        loop = asyncio.get_running_loop()
        worker = await loop.run_in_executor(self._threads, self._new_process)
        with self._lock:
            self._all.add(worker)
        try:
            await loop.run_in_executor(self._threads, worker.wait_ready, self.start_timeout)
        except WorkerLost:
            with self._lock:
                self._all.discard(worker)
            raise
        if self._closing:
            return worker
        log.info("worker %s ready", worker.ident, extra={"warmup": worker.ready_info})
        assert self._idle is not None
        self._idle.put_nowait(worker)
        return worker

    def _new_process(self) -> _Worker:
        ours, theirs = self._ctx.Pipe(duplex=True)
        with self._lock:
            ident = self._next_ident
            self._next_ident += 1
        proc = self._ctx.Process(target=_worker_main, args=(theirs, self.warmup, self.log_level),
                                 name=f"planner-worker-{ident}", daemon=True)
        t0 = time.perf_counter()
        proc.start()
        theirs.close()
        log.debug("worker %s started in %.3f s", ident, time.perf_counter() - t0)
        return _Worker(process=proc, conn=ours, ident=ident)

    def _spawn_task(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("worker start failed: %s", task.exception())
