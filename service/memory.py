"""Giving freed memory back to the operating system after large answers.

A large answer (a plan at 20001 samples is about 5 MB of JSON) is one ``bytes`` object held
until it has left or its client is dropped (:mod:`service.middleware`). glibc's allocator
serves such a block with ``mmap`` at first, but its *dynamic* threshold then rises to the size
of the block freed, so that the next answers of that size come from the heap, and freed heap
memory stays with the process: after 200 clients that never read a 5 MB answer were dropped, the
server stayed at about 1 GB. Two measures, both glibc's own (elsewhere they do nothing):

* :func:`fix_mmap_threshold` sets the threshold (``M_MMAP_THRESHOLD``, 1 MiB) once at start,
  which also turns the dynamic raise off: every block from 1 MiB up is its own mapping,
  unmapped when freed;
* :func:`release_soon` (after any answer of at least 1 MiB, sent or dropped) runs
  ``malloc_trim(0)`` about a second later, at most once a second: what smaller objects freed
  (the parsed result, Python's small-object arenas) is handed back too.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import logging
from typing import Any

log = logging.getLogger("service.memory")

#: Blocks from this size up get their own mapping (returned to the system when freed).
MMAP_THRESHOLD = 1 << 20
#: glibc's ``mallopt`` parameter number of ``M_MMAP_THRESHOLD`` (malloc.h).
_M_MMAP_THRESHOLD = -3
#: Seconds between an answer's end and the trim (answers ending meanwhile share it).
TRIM_DELAY = 1.0


def _glibc() -> Any | None:
    name = ctypes.util.find_library("c")
    if not name:
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.malloc_trim, libc.mallopt  # noqa: B018 - glibc only
    except (OSError, AttributeError):
        return None
    return libc


_LIBC = _glibc()
_scheduled: set[asyncio.AbstractEventLoop] = set()


def fix_mmap_threshold(threshold: int = MMAP_THRESHOLD) -> bool:
    """Serve every allocation of ``threshold`` bytes or more with its own mapping (glibc).
    Returns whether it was set."""
    if _LIBC is None:
        return False
    return bool(_LIBC.mallopt(_M_MMAP_THRESHOLD, int(threshold)))


def trim() -> bool:
    """Hand the allocator's free memory back to the system now (glibc's ``malloc_trim``);
    whether any was."""
    if _LIBC is None:
        return False
    return bool(_LIBC.malloc_trim(0))


def release_soon(delay: float = TRIM_DELAY) -> None:
    """:func:`trim` about ``delay`` seconds from now on the running loop, unless one is
    already due."""
    if _LIBC is None:
        return
    try:
        loop = asyncio.get_running_loop()
    except RuntimeError:
        trim()
        return
    if loop in _scheduled:
        return
    _scheduled.add(loop)

    def run() -> None:
        _scheduled.discard(loop)
        trim()

    loop.call_later(delay, run)
