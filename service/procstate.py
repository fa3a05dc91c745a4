"""Whether a process is stopped (SIGSTOP, a debugger, a frozen cgroup), from ``/proc``.

A stopped worker still holds its pipe open and accepts a job's bytes into the pipe's buffer,
so nothing but the job's time limit would tell: the pool asks the kernel instead, before it
hands a worker a job and while the job runs (:mod:`service.workers`). One read of
``/proc/<pid>/stat`` (about 10 us). Where there is no ``/proc`` the answer is False (the pool's
pings still find such a worker, between jobs).
"""

from __future__ import annotations

#: Process states of ``/proc/<pid>/stat`` that run no code: stopped (T), traced (t), frozen.
_STOPPED = frozenset(b"Tt")


def is_stopped(pid: int | None) -> bool:
    """Whether process ``pid`` is stopped (False when it cannot be told, or has ended)."""
    if pid is None:
        return False
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return False
    # "pid (comm) S ...": the state follows the last ")" (comm may hold spaces and parens)
    end = stat.rfind(b")")
    return end >= 0 and len(stat) > end + 2 and stat[end + 2] in _STOPPED
