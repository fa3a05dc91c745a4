"""The benchmark's goals: reachable goals no one tuned for (:mod:`optimizer.reachable`).

The generator lives in the library (the studies of :mod:`optimizer.studies` draw their goals
from it too, and the runtime must not import ``bench``); this module fixes how many goals of
each ``n`` the benchmark plans and re-exports the generator's names for the benchmark's code.
"""

from __future__ import annotations

from optimizer.reachable import (BASE_SEED, KINDS, MIN_MOVE, PATH_MARGIN, RATE_SCALE,
                                 START_MARGIN, Goal, generate, rates_at)

__all__ = ["BASE_SEED", "COUNTS", "KINDS", "MIN_MOVE", "PATH_MARGIN", "RATE_SCALE",
           "START_MARGIN", "Goal", "benchmark_goals", "generate", "rates_at"]

#: Goals per number of joints in the benchmark.
COUNTS = {3: 60, 4: 25, 5: 15, 6: 8, 7: 5, 8: 5}


def benchmark_goals(counts: dict[int, int] | None = None) -> list[Goal]:
    """The benchmark's goals: :data:`COUNTS` per number of joints (or ``counts``)."""
    out: list[Goal] = []
    for n, k in (counts or COUNTS).items():
        out.extend(generate(n, k))
    return out
