"""Imported once by the workers' forkserver (:data:`service.workers.PRELOAD`): the solver
modules, then the warm-up (the default robot's CasADi chained form, and matplotlib with one
figure drawn: :func:`service.jobs.warm_up`), so that every worker forked from it starts ready to
plan and to draw, replacements included. What the forkserver loads, its workers share (their
pages are copied only when written), so matplotlib costs the forkserver's start about 0.9 s of
CPU once, not each worker's.
"""

from __future__ import annotations

import gc
import logging

from . import jobs, worker_process  # noqa: F401 - loaded once for every forked worker

try:
    WARMUP: dict = jobs.warm_up()
except Exception as exc:  # noqa: BLE001 - an optimisation only; each worker warms up again
    WARMUP = {"warmup_error": type(exc).__name__}
    logging.getLogger("service.worker").warning("forkserver warm-up failed: %s",
                                                type(exc).__name__)

# everything loaded so far lives as long as the forkserver and the workers forked from it: out
# of the collector's reach (:func:`service.worker_process.freeze_heap`), so that no worker's
# collections walk them (and, by writing to their headers, copy the pages they share)
gc.collect()
gc.freeze()
