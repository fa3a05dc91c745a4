"""The NLP solvers and one call of them: fatrop and IPOPT presets, the deadline, the classes
of their return statuses, and calls through CasADi's buffers on memories that no other
pattern of bounds has used (the bottom of the NLP layer: it knows no transcription).

fatrop (an interior-point solver for stage-structured problems, bundled with CasADi) and IPOPT
take the options of :func:`fatrop_options` and :func:`ipopt_options`. IPOPT is stopped at the
deadline by :class:`DeadlineCallback`; fatrop, which calls no callback, by its iteration cap
:func:`fatrop_max_iter`, and is not started when that cap, at the pace its NLP's solves went
(:class:`SolverPace`), would outlast the time left. :func:`run_solver` runs one of them and
classifies its return status (:data:`SUCCESS`, :data:`TIMEOUT`, :data:`INFEASIBLE`);
:func:`error_for` turns a class into the library's typed error.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Protocol, Sequence

import casadi as ca
import numpy as np

from ..errors import (InfeasibleError, NumericalError, PlannerError, SolverTimeoutError)
from ..problem import MAX_TIME_LIMIT


class SolverPace:
    """Seconds per iteration of each solver of one NLP: the slowest of its last
    :data:`PACE_SOLVES` solves of at least :data:`PACE_MIN_ITERATIONS` iterations (the call,
    with a new memory's set-up where it takes one: the same NLP's solves went at 2.2 and 6.7
    ms an iteration one after the other; a solver's build at its first use is not in it).

    fatrop calls no iteration callback, so nothing stops it at the deadline: a solve started
    with little time left runs to convergence or to its cap (on 7-joint replans with a 0.5 s
    limit, the 50-interval rung's solve on CasADi's virtual machine started 0.04-0.3 s before
    the deadline and took 0.2-1.0 s). :func:`run_solver` starts no such solve whose cap, at
    this pace, would end after the deadline. The pace is the one thing a process remembers of
    earlier solves; it decides only whether a solve starts that would end past the time limit,
    where an answer depends on the machine's speed anyway.

    Parameters
    ----------
    caps : dict
        The iteration cap of each solver that no callback stops (the NLP's own fatrop
        options: :func:`fatrop_max_iter`, or the reversal budget's 150); the others are never
        too slow.
    """

    def __init__(self, caps: dict[str, int]) -> None:
        self.caps = dict(caps)
        self.recent: dict[str, list[float]] = {}

    def record(self, name: str, seconds: float, iterations: int) -> None:
        if iterations >= PACE_MIN_ITERATIONS:
            kept = self.recent.setdefault(name, [])
            kept.append(seconds / iterations)
            del kept[:-PACE_SOLVES]

    def too_slow(self, name: str, seconds_left: float) -> bool:
        """Whether solver ``name``'s iteration cap at its pace would outlast
        ``seconds_left`` (False for a solver without a cap, or whose pace is not known yet)."""
        kept = self.recent.get(name)
        if not kept or name not in self.caps:
            return False
        return max(kept) * self.caps[name] > seconds_left


#: A solve of fewer iterations does not set its solver's pace (its fixed costs would weigh).
PACE_MIN_ITERATIONS = 5
#: The pace is the slowest of this many recent solves.
PACE_SOLVES = 8


class SolvableNLP(Protocol):
    """What :func:`run_solver` needs of an NLP: a call of a solver for given variable bounds,
    the deadline callback and the constraints' bounds (and, optionally, a ``pace``:
    :class:`SolverPace`)."""

    callback: "DeadlineCallback"
    lbg: np.ndarray
    ubg: np.ndarray

    def solver_call(self, name: str, lbx: np.ndarray, ubx: np.ndarray) -> "BufferedCall": ...

    def goal_miss(self, x: np.ndarray, p: np.ndarray) -> float:
        """How far a solution ends from the goal (0 where the goal is a hard constraint)."""
        ...

    def tightened(self, p: np.ndarray, factor: float) -> np.ndarray:
        """Parameters under which the goal's penalty weighs ``factor`` times more."""
        ...


#: An elastic goal (see :data:`optimizer.planner.nlp.TERMINAL_MODES`) is accepted when its
#: solution ends this close to it (rad: a tenth of the plan's terminal tolerance; the Newton
#: correction removes the model's error, and the quadrature proves what is left); else the
#: NLP is solved again from that solution with
#: the goal's penalty :data:`ELASTIC_STEP` times heavier, at most :data:`ELASTIC_ROUNDS` times
#: and only while each round comes ten times closer than the one before.
#: The Newton correction cannot remove a miss along the end map's weak directions (at 7
#: joints its singular values span 0.35 to 1e-11), so the NLP itself must end on the goal.
#: A step of 10, not 100: after a round 100 times heavier fatrop stopped at its iteration cap
#: in 20 of the 35 second rounds logged on 100 held-out 4- to 8-joint goals (seeds 777 and
#: 9001), even from first rounds that missed by 3.1e-7 (likely the scaling: the other
#: weights divided by 100 against the goal's 1e5); the rung failed and the ladder went on.
#: With 10, on the same goals: 15 plans better by (reversals, deviation), none worse, 5-6 %
#: less time in all, the 5-joint goals' slowest 34 -> 19 and 33 -> 24 ms. With the longer caps
#: since (:func:`fatrop_max_iter`, ``nlp.SOFT_SIGNS_MAX_ITER``), 10 against 100 on 10 goals per
#: n = 3..8 of both seeds: 16 plans better, 2 worse (one 1 -> 2 reversals, one 0.3 deg less
#: straight), 9 % and 19 % less time in sum.
ELASTIC_MISS = 3e-7
ELASTIC_STEP = 10.0
ELASTIC_ROUNDS = 2
#: A converged elastic solution that misses its goal by more than this (rad) in two rounds
#: (the second not ten times closer) shows the goal out of reach under the NLP's bounds
#: (rates of fixed signs, joint bounds): no third round.
ELASTIC_GIVE_UP = 1e-4
#: ... and a solution that, after those rounds, still misses by more than this (rad) is none.
ELASTIC_ACCEPT = 3e-7


#: Iteration cap of fatrop (it converged in 15-38 iterations on the bench's goals; a failing run
#: ends early and the next attempt starts)...
FATROP_MAX_ITER = 60
#: ... and from this many joints. Of the 8 solves that stopped at 60 on 40 held-out 5-joint
#: goals (20 of each of seeds 777 and 9001), 4 converged given more, in 70-110 iterations.
#: With 120 from 5 joints, on 10 goals per n = 5..8 of each of those seeds and 12 of the
#: benchmark's: 8 plans better by the default rule (four with fewer reversals: 2 -> 1 three
#: times, 4 -> 2), none worse beyond 1e-9 rad, 1-5 % more time per n in sum. Below 5 joints
#: the same raise cost 10 % (rungs that fail are common there, and each then ran to 120) and
#: gave one better plan in 64.
FATROP_LONG_FROM_JOINTS = 5
FATROP_LONG_MAX_ITER = 120


def fatrop_max_iter(n: int) -> int:
    """fatrop's iteration cap on an ``n``-joint robot's NLPs."""
    return FATROP_LONG_MAX_ITER if n >= FATROP_LONG_FROM_JOINTS else FATROP_MAX_ITER


#: fatrop's convergence tolerance: the optimum to 1e-6 is plenty, the goal's precision comes
#: from the correction on the exact model (1e-8 took one or two more iterations, same plans).
FATROP_TOL = 1e-6


#: fatrop stops at an acceptable point, a success, once its optimality error (dual
#: infeasibility, primal infeasibility and complementarity, scaled) has been below
#: FATROP_ACCEPTABLE_TOL for FATROP_ACCEPTABLE_ITER iterations in a row (IPOPT's
#: ``acceptable_tol`` / ``acceptable_iter``). Why: from 5 joints, a quarter of fatrop's solves
#: stalled at the iteration cap although primal feasible to 1e-11 with the objective settled to
#: 6 digits: the Lagrangian's Hessian is indefinite there, fatrop adds 10-100 to it, and the
#: dual infeasibility creeps down from 1e-3. On 30 held-out 5-joint goals every one of those 19
#: solves (of 76) stopped at an acceptable point within 0.4 % of IPOPT's objective from the
#: same guess, the other 57 moved by at most 3e-6 of their objective, and the solves took 25 %
#: fewer iterations; on 3, 4 and 6 joints (96 solves) no solve changed but one six-joint
#: solve that had failed (0.08 % above IPOPT's objective). A looser tolerance (1e-3) also
#: accepted two soft-sign 4-joint solves 25 % above IPOPT's objective.
FATROP_ACCEPTABLE_TOL = 1e-4
FATROP_ACCEPTABLE_ITER = 5
#: fatrop's ``return_flag`` when it stopped at an acceptable point (0: converged; 1: the
#: iteration cap).
FATROP_ACCEPTABLE_FLAG = 2


#: fatrop's initial barrier parameter. Its default, 0.1, failed from the straight-line guess on
#: some goals; 1.0 converged at the first attempt on 30 of 40 random 3- and 4-joint goals
#: (0.1: 23 of 40) and halved the median time.
FATROP_MU_INIT = 1.0


#: IPOPT options of every NLP here (``max_wall_time``: the library's largest time limit, a
#: backstop; the deadline itself is the callback's).
IPOPT_OPTIONS: dict[str, Any] = {"print_level": 0, "sb": "yes", "tol": 1e-8,
                                 "acceptable_tol": 1e-6, "max_iter": 300,
                                 "max_wall_time": float(MAX_TIME_LIMIT)}


#: Return statuses that are converged solutions (IPOPT's names; fatrop reports ``success``).
SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


#: Return statuses that mean "ran out of time".
TIMEOUT = ("User_Requested_Stop", "Maximum_WallTime_Exceeded", "Maximum_CpuTime_Exceeded")


#: Return statuses that mean "no point satisfies the constraints" (IPOPT's local certificate).
INFEASIBLE = ("Infeasible_Problem_Detected",)



class DeadlineCallback(ca.Callback):
    """IPOPT iteration callback: asks IPOPT to stop once ``stop_at`` (perf_counter) has passed.

    IPOPT options are frozen when an ``nlpsol`` is created, so a cached solver cannot take
    ``max_wall_time = deadline.remaining`` per call; this stops it at the granularity of one
    iteration instead. ``stop_at`` is mutable state of a cached object: one thread per process.
    """

    def __init__(self, nx: int, ng: int, npar: int) -> None:
        ca.Callback.__init__(self)
        self._dims = {"x": nx, "lam_x": nx, "g": ng, "lam_g": ng, "p": npar, "lam_p": npar}
        self.stop_at = math.inf
        self.construct("nlp_deadline", {})

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


def ipopt_options(callback: DeadlineCallback | None = None, **ipopt: Any) -> dict[str, Any]:
    """``nlpsol`` options of IPOPT: :data:`IPOPT_OPTIONS` updated by ``ipopt``, the deadline
    ``callback``, no printing, no exception on failure (the status is classified instead)."""
    opts: dict[str, Any] = {"ipopt": {**IPOPT_OPTIONS, **ipopt}, "print_time": False,
                            "error_on_fail": False}
    if callback is not None:
        opts["iteration_callback"] = callback
    return opts


def fatrop_options(nx: Sequence[int], nu: Sequence[int], ng: Sequence[int],
                   equality: Sequence[bool], *, expand: bool = True,
                   max_iter: int = FATROP_MAX_ITER) -> dict[str, Any]:
    """``nlpsol`` options of fatrop for a stage-wise NLP of ``len(nu) - 1`` intervals
    (``nx``, ``nu``, ``ng``: per stage; ``equality``: per constraint row)."""
    opts: dict[str, Any] = {
        "structure_detection": "manual", "nx": list(nx), "nu": list(nu), "ng": list(ng),
        "N": len(nu) - 1, "equality": list(equality), "print_time": False,
        "error_on_fail": False,
        "fatrop": {"print_level": 0, "tol": FATROP_TOL, "max_iter": max_iter,
                   "mu_init": FATROP_MU_INIT, "tol_acceptable": FATROP_ACCEPTABLE_TOL,
                   "acceptable_iter": FATROP_ACCEPTABLE_ITER}}
    if expand:
        opts["expand"] = True
    return opts


def solver_status(name: str, stats: dict[str, Any]) -> tuple[str, bool]:
    """A solver's return status and whether it is a converged solution: IPOPT's own;
    fatrop's ``return_status``, and ``"acceptable"`` (a success) where it stopped at an
    acceptable point (:data:`FATROP_ACCEPTABLE_TOL`), which CasADi reports as no success."""
    if name == "fatrop":
        flag = (stats.get("fatrop") or {}).get("return_flag")
        if flag == FATROP_ACCEPTABLE_FLAG:
            return "acceptable", True
    return str(stats.get("return_status", "unknown")), bool(stats.get("success"))


def classify(status: str, success: bool) -> str:
    """The class of a solver's return: ``"success"``, ``"timeout"``, ``"infeasible"`` or
    ``"failure"``."""
    if success:
        return "success"
    if status in TIMEOUT:
        return "timeout"
    if status in INFEASIBLE:
        return "infeasible"
    return "failure"


def error_for(kind: str, message: str, *, diagnostics: dict[str, Any] | None = None,
              field: str | None = None) -> PlannerError:
    """The library's typed error of a class of :func:`classify` (``failure``: numerical)."""
    cls: type[PlannerError] = {"timeout": SolverTimeoutError,
                               "infeasible": InfeasibleError}.get(kind, NumericalError)
    return cls(message, field=field, diagnostics=diagnostics)


class BufferedCall:
    """A CasADi Function called through its buffer (``casadi.Function.buffer``).

    An ordinary call converts every numpy argument to a ``DM`` element by element and every
    result back: about 30 us per argument, more than the compiled 3-joint NLP's functions take
    to evaluate, and about 0.3 ms per fatrop solve. Through the buffer the Function reads the
    arguments' memory in place and writes the results into fresh numpy arrays.

    An evaluation that fails (an exception inside CasADi, such as a linear solve of a
    singular system in the virtual machine) is silent through the buffer and leaves the
    results unwritten, memory rather than numbers: such a call answers NaN in every result,
    which callers treat as no answer. (A solver that stops unconverged is not a failed
    evaluation: its status says so.)

    Parameters
    ----------
    function : casadi.Function
    n_args : int
        Arguments every call gives (the first ``n_args`` inputs, dense; the others stay
        unset, which CasADi reads as their defaults).
    outputs : sequence of int
        The outputs computed (the others are not asked for).

    Notes
    -----
    Matrices are column-major: an ``(r, c)`` input is the C-contiguous ``(c, r)`` array, an
    ``(r, c)`` result comes back as the flat column-major vector (``.reshape(c, r).T``).
    Not thread-safe, like the Function.
    """

    def __init__(self, function: Any, n_args: int, outputs: Sequence[int] = (0,)) -> None:
        self.function = function
        self._buffer, self._eval = function.buffer()
        self._sizes = [int(function.nnz_in(i)) for i in range(n_args)]
        self._outputs = [(int(j), int(function.nnz_out(j))) for j in outputs]

    def __call__(self, *args: Any) -> list[np.ndarray]:
        """Evaluate on ``args`` (arrays of the inputs' sizes); the results of ``outputs``.

        Raises
        ------
        ValueError
            An argument of another size.
        RuntimeError
            The evaluation failed (CasADi's exception).
        """
        if len(args) != len(self._sizes):
            raise ValueError(f"{self.function.name()} takes {len(self._sizes)} arguments")
        held = []  # the buffer holds pointers into these until the evaluation is over
        for i, (arg, size) in enumerate(zip(args, self._sizes)):
            a = np.ascontiguousarray(arg, dtype=float).reshape(-1)
            if a.size != size:
                raise ValueError(f"argument {i} of {self.function.name()} has {a.size} "
                                 f"values, not {size}")
            held.append(a)
            self._buffer.set_arg(i, a.data)
        results = []
        for j, size in self._outputs:
            out = np.empty(size)
            results.append(out)
            self._buffer.set_res(j, out.data)
        self._eval()
        if self._buffer.ret() != 0:
            for out in results:
                out.fill(np.nan)
        return results

    def stats(self) -> dict[str, Any]:
        """The Function's statistics of the last evaluation (a solver's status, iterations)."""
        return dict(self._buffer.stats())


@dataclass(frozen=True)
class SolveOutcome:
    """One solver run: its class (:func:`classify`), status, iterations, time and answer."""

    solver: str
    kind: str
    status: str
    iterations: int
    seconds: float
    x: np.ndarray | None

    @property
    def success(self) -> bool:
        return self.kind == "success"


#: Memory held by the spent solver memories of one solver before it is built anew (bytes, as
#: :func:`memory_bytes` estimates them): about 32 solves of the 3-joint NLP, 10 of the 8-joint
#: one on 20 intervals. A compiled solver is built anew in about 1 ms; one on CasADi's virtual
#: machine in 15-80 ms (3 to 8 joints). Measured in one process planning 40 random goals of 3
#: to 6 joints over and over: resident 321 MB after 240 plans and no more after (96 MB: 414;
#: when the estimate counted the work vectors alone, 1,036 MB and 3.6 MB more every plan).
SPENT_MEMORY_BYTES = 48 * 2**20
#: The solvers whose memories are reused, one per pattern of bounds (see
#: :meth:`~.nlp.MultipleShootingNLP.solver_call`); the others take a fresh memory per solve.
REUSED_MEMORIES = frozenset({"fatrop"})


def bound_pattern(lbx: np.ndarray, ubx: np.ndarray, lbg: np.ndarray, ubg: np.ndarray
                  ) -> bytes:
    """Which of the bounds are finite and which pairs are equalities, variables' then
    constraints', as bytes: what fatrop's solver objects are built for (two solves of one
    pattern differ only in the bounds' values)."""
    parts = []
    for lo, hi in ((lbx, ubx), (lbg, ubg)):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        parts += [np.isfinite(lo), np.isfinite(hi), lo == hi]
    return np.concatenate(parts).tobytes()


#: Bytes a memory holds beyond its work vectors, per byte of work vector and fixed: the solver's
#: own objects, built at the memory's first solve. Measured resident growth per fresh memory:
#: fatrop 1.0 MB on 3 joints and 12 intervals (51 KB of work vectors), 2.1 MB on 5 joints and
#: 2.8 MB on 8 (20 intervals; 126 and 208 KB); IPOPT about 0.47 MB on 3 and 8 joints (16 and
#: 42 KB). The estimate is within twice those.
MEMORY_PER_WORK_BYTE = 20
MEMORY_FIXED_BYTES = 2**19


def memory_bytes(solver: Any) -> int:
    """What one memory of ``solver`` holds once it has solved (bytes, an upper estimate: its
    work vectors and the solver's own objects, :data:`MEMORY_PER_WORK_BYTE`)."""
    work = 8 * (int(solver.sz_w()) + int(solver.sz_iw()))
    return MEMORY_PER_WORK_BYTE * work + MEMORY_FIXED_BYTES


def run_solver(nlp: "SolvableNLP", name: str, x0: np.ndarray, p: np.ndarray,
               lbx: np.ndarray, ubx: np.ndarray, seconds: float, *,
               accept_miss: float = ELASTIC_ACCEPT) -> SolveOutcome:
    """Run solver ``name`` of ``nlp`` from ``x0`` for at most about ``seconds`` (IPOPT: the
    deadline callback; fatrop: its iteration cap). An elastic goal's converged answer that
    misses the goal by more than ``accept_miss`` (rad) after its rounds is a failure.

    Raises
    ------
    NumericalError
        The solver raised (CasADi's exceptions are not the library's).
    """
    t0 = time.perf_counter()
    iterations = 0
    best: tuple[float, str, np.ndarray] | None = None  # (miss, status, x) of converged rounds
    pace: SolverPace | None = getattr(nlp, "pace", None)
    x: np.ndarray | None = None
    for round_ in range(ELASTIC_ROUNDS + 1):
        if pace is not None and pace.too_slow(name, t0 + seconds - time.perf_counter()):
            kind, status = "timeout", (f"not started: {pace.caps[name]} iterations at its pace "
                                       "would end after the time limit")
            break
        solver = nlp.solver_call(name, lbx, ubx)
        nlp.callback.stop_at = t0 + seconds
        t_call = time.perf_counter()
        try:
            x = solver(x0, p, lbx, ubx, nlp.lbg, nlp.ubg)[0]
            stats = solver.stats()
        except Exception as exc:  # noqa: BLE001 - CasADi raises RuntimeError on evaluation errors
            raise NumericalError(f"the {name} solver raised: {exc}",
                                 diagnostics={"solver": name}) from exc
        finally:
            nlp.callback.stop_at = math.inf
        status, success = solver_status(name, stats)
        kind = classify(status, success)
        if pace is not None:
            pace.record(name, time.perf_counter() - t_call, int(stats.get("iter_count", -1)))
        iterations += int(stats.get("iter_count", -1))
        if kind != "success" or not np.all(np.isfinite(x)):
            break
        miss = nlp.goal_miss(x, p)
        if miss > ELASTIC_GIVE_UP and best is not None and miss > 0.1 * best[0]:
            # converged away from the goal, and a heavier penalty barely moved it: out of
            # reach under these bounds and signs (a goal that is only expensive to reach,
            # fast rates for a far goal, comes closer as the penalty grows)
            kind, status = "infeasible", f"{status} (the goal missed by {miss:.2g} rad)"
            best = None
            break
        stalled = best is not None and miss > 0.1 * best[0]
        if best is None or miss < best[0]:
            best = (miss, status, x)
        if not miss > ELASTIC_MISS or stalled:
            # on the goal; or a round 100 times heavier that did not come ten times closer
            # (a third round did not either: 6e-5, 3.3e-5, 3.3e-5 rad on a 6-joint rung)
            break
        x0, p = x, nlp.tightened(p, ELASTIC_STEP)
    if best is not None and kind != "timeout":
        # the closest converged round; one that still misses is not an answer
        miss, status, x = best
        kind = "success"
        if miss > accept_miss:
            kind, status = "failure", f"{status} (the goal missed by {miss:.2g} rad)"
    finite = x is not None and bool(np.all(np.isfinite(x)))
    return SolveOutcome(solver=name, kind=kind, status=status, iterations=iterations,
                        seconds=time.perf_counter() - t0, x=x if finite else None)
