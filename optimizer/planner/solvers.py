"""What every NLP of the planner shares with its solver: the deadline callback and the statuses.

A leaf below the methods (imports nothing of the planner).
"""

from __future__ import annotations

import math
import time
from typing import Any, Sequence

import casadi as ca

#: IPOPT statuses of a converged solve.
SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
#: IPOPT statuses of a solve stopped by the clock.
TIMEOUT = ("User_Requested_Stop", "Maximum_WallTime_Exceeded", "Maximum_CpuTime_Exceeded")


class DeadlineCallback(ca.Callback):
    """IPOPT iteration callback: asks IPOPT to stop once ``stop_at`` (perf_counter) has passed.

    ``stop_at`` is mutable state of a cached object: one thread per process only.
    """

    def __init__(self, nx: int, ng: int, npar: int) -> None:
        ca.Callback.__init__(self)
        self._dims = {"x": nx, "lam_x": nx, "g": ng, "lam_g": ng, "p": npar, "lam_p": npar}
        self.stop_at = math.inf
        self.construct("penalty_deadline", {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "ret"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        name = ca.nlpsol_out(i)
        return ca.Sparsity.scalar() if name == "f" else ca.Sparsity.dense(self._dims[name], 1)

    def eval(self, arg: Sequence[Any]) -> list:  # type: ignore[override]
        # a nonzero return makes IPOPT stop with User_Requested_Stop
        return [1 if time.perf_counter() > self.stop_at else 0]
