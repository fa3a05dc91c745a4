"""The worker pool's own failures; :mod:`service.dispatch` answers each with its problem
document (503 ``overloaded``, 504 ``timeout``, 503 ``worker_lost``, 503 ``shutting_down``)."""

from __future__ import annotations


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

