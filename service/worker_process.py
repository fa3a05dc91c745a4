"""What runs in a worker process: warm up, say ready, then answer one message at a time.

The messages are those of :mod:`service.worker_protocol`; a job's work is
:func:`service.jobs.run_job`. Started by :class:`service.workers.WorkerPool` (forked from its
forkserver, which has imported and warmed up the solver modules already).
"""

from __future__ import annotations

import gc
import logging
import os
import signal
from multiprocessing.connection import Connection
from typing import Any

from .worker_protocol import CANCEL_SIGNAL, PING, PONG


def worker_main(conn: Connection, warmup: bool, log_level: str, nice: int = 0,
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
        if info["native"]:
            from optimizer import cascade_kernel

            # the compiled quadrature of the proofs (4 times faster than numpy's), built now
            # when missing (one small C file, about a second once per machine): every worker
            # then proves with the same code, so answers do not depend on which one served
            info["cascade_kernel"] = cascade_kernel.prepare(wait=True)
    if warmup:
        try:
            info.update(jobs.warm_up())
        except Exception as exc:  # noqa: BLE001 - warm-up is an optimisation only
            info["warmup_error"] = type(exc).__name__
    freeze_heap()
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


def freeze_heap() -> None:
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

