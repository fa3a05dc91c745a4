"""Every planner method and the multiple-shooting baseline on every case, in this process.

For each case: the baseline is built once per number of joints (its build time is timed
separately, ``build_repeats`` times) and its solve is timed after a warm-up solve; then every
planner method's complete ``plan(PlanRequest)`` call (search, sampling and the library's own
verification included) is timed after a warm-up call. The last successful result of each is
re-integrated on the original model (:mod:`bench.reintegrate`).

A method that cannot be imported or raises an unexpected exception is recorded with status
``"error"`` and its message: the benchmark goes on.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .cases import DURATION, Case
from .reintegrate import reintegrate_baseline, reintegrate_plan
from .stats import Timed, summarise, time_repeats

from optimizer.planner.registry import METHODS as REGISTRY

#: Every registered method, then ``auto``.
METHODS: tuple[str, ...] = tuple(REGISTRY) + ("auto",)


@dataclass
class Config:
    """How hard to measure.

    Attributes
    ----------
    repeats : int
        Largest number of timed repeats after the warm-up.
    min_repeats : int
        Smallest number of timed repeats.
    budget : float
        Seconds of timed repeats per (case, method) that decide the repeat count in between.
    build_repeats : int
        Baseline builds timed per number of joints.
    time_limit : float
        ``PlanRequest.time_limit`` (s) of every planner call.
    methods : tuple of str
        Planner methods to run.
    """

    repeats: int = 7
    min_repeats: int = 3
    budget: float = 10.0
    build_repeats: int = 3
    time_limit: float = 10.0
    methods: tuple[str, ...] = METHODS


def configure_native(off: bool = False) -> dict[str, Any]:
    """Compiled NLP functions for the planner (:mod:`optimizer.native`), in the service's
    default cache, or off; what was done, for the results' ``meta``. Libraries are built by
    ``shooting.prepare`` and ``penalty.prepare`` (``wait=True``) before anything is timed
    (:func:`run_method`)."""
    from optimizer import native
    if off:
        native.configure(None)
        return {"on": False, "reason": "--no-native"}
    try:
        cfg = native.configure(native.default_cache_dir())
    except OSError as exc:  # an unusable cache directory: the virtual machine
        return {"on": False, "reason": f"{type(exc).__name__}: {exc}"}
    if cfg is None:
        return {"on": False, "reason": "no C compiler found"}
    from optimizer import cascade_kernel
    # the compiled quadrature, as the service's workers prepare it
    kernel = cascade_kernel.prepare(wait=True)
    return {"on": True, "compiler": cfg.compiler, "cache_dir": str(cfg.cache_dir),
            "cascade_kernel": kernel}


def status_of(exc: BaseException | None) -> str:
    """``success``, the planner's failure code (``infeasible``, ``timeout``,
    ``numerical_failure``, ``invalid_request``) or ``error`` for anything unexpected."""
    if exc is None:
        return "success"
    from optimizer.errors import PlannerError
    if isinstance(exc, PlannerError):
        return str(exc.code)
    return "error"


def describe(exc: BaseException | None) -> str | None:
    """``Type: message`` of an exception, shortened."""
    if exc is None:
        return None
    text = f"{type(exc).__name__}: {exc}"
    return text if len(text) <= 400 else text[:397] + "..."


class Baselines:
    """One :class:`MultipleShootingBaseline` per number of joints, built on first use."""

    def __init__(self, build_repeats: int) -> None:
        self.build_repeats = max(1, build_repeats)
        self._solvers: dict[int, Any] = {}
        self.builds: dict[int, dict[str, Any]] = {}

    def get(self, n: int) -> Any:
        """The baseline for ``n`` joints (default model of the baseline module)."""
        from .baselines.multiple_shooting import MultipleShootingBaseline, default_model
        if n not in self._solvers:
            gains, exps = default_model(n)
            times = []
            solver = None
            for _ in range(self.build_repeats):
                solver = MultipleShootingBaseline(gains, exps, duration=DURATION)
                times.append(solver.build_time)
            self._solvers[n] = solver
            self.builds[n] = {"build_time": summarise(times).as_dict(),
                              "intervals": solver.intervals,  # type: ignore[union-attr]
                              "rk4_substeps": solver.rk4_substeps}  # type: ignore[union-attr]
        return self._solvers[n]


def run_baseline(case: Case, baselines: Baselines, cfg: Config) -> dict[str, Any]:
    """Time and re-integrate the baseline on ``case``."""
    start, goal = np.radians(case.start_deg), np.radians(case.goal_deg)
    out: dict[str, Any] = {"method": "baseline"}
    try:
        bl = baselines.get(case.n)
    except Exception as exc:  # noqa: BLE001 - recorded
        out.update(status="error", error=describe(exc))
        return out
    timed = time_repeats(lambda: bl.solve(start, goal), cfg.repeats, cfg.budget,
                         cfg.min_repeats)
    res = timed.result
    out["build_time"] = baselines.builds[case.n]["build_time"]
    out["first_call"] = timed.first
    out["solve_time"] = timed.summary.as_dict()
    if timed.error is not None or res is None:
        out.update(status="error", error=describe(timed.error))
        return out
    out["status"] = "success" if res.success else "solver_failure"
    out["ipopt_status"] = res.return_status
    out["iterations"] = res.iterations
    out["objective"] = res.objective
    out["reintegration"] = reintegrate_baseline(res, bl.gains, bl.exponents, start,
                                                goal).as_dict()
    return out


def make_request(case: Case, method: str, time_limit: float) -> Any:
    """The :class:`optimizer.problem.PlanRequest` of ``case`` for ``method`` (T = 1 s)."""
    from optimizer.model import Robot
    from optimizer.problem import PlanRequest
    return PlanRequest(start=tuple(np.radians(case.start_deg)),
                       goal=tuple(np.radians(case.goal_deg)), robot=Robot.default(case.n),
                       method=method, duration=DURATION, time_limit=time_limit)


def run_method(case: Case, method: str, cfg: Config) -> dict[str, Any]:
    """Time and re-integrate one planner method on ``case``."""
    out: dict[str, Any] = {"method": method}
    try:
        from optimizer.planner.plan import plan
        req = make_request(case, method, cfg.time_limit)
    except Exception as exc:  # noqa: BLE001 - recorded
        out.update(status="error", error=describe(exc))
        return out
    if method in ("shooting", "penalty", "auto"):
        # their compiled NLP functions (optimizer.native, when configured), built or loaded
        # before the warm-up call: a one-off per machine, reported like the baseline's build
        from optimizer.planner import penalty, shooting
        t0 = time.perf_counter()
        prepares = {"shooting": (shooting.prepare,), "penalty": (penalty.prepare,),
                    "auto": (shooting.prepare, penalty.prepare)}[method]
        out["native_compiled"] = all([prep(req.robot.gains, req.robot.exponents,
                                           wait=True).compiled for prep in prepares])
        out["native_prepare_s"] = time.perf_counter() - t0
    call: Callable[[], Any] = lambda: plan(req)  # noqa: E731
    timed: Timed = time_repeats(call, cfg.repeats, cfg.budget, cfg.min_repeats)
    out["status"] = status_of(timed.error)
    out["error"] = describe(timed.error)
    out["first_call"] = timed.first
    out["time"] = timed.summary.as_dict()
    if timed.repeat_errors:
        # the warm-up's error is reported once above; list only other outcomes, with counts
        warm = None if timed.error is None else f"{type(timed.error).__name__}: {timed.error}"
        out["repeat_failures"] = len(timed.repeat_errors)
        other = Counter(e[:300] for e in timed.repeat_errors if e != warm)
        if other:
            out["repeat_errors"] = dict(other)
    p = timed.result
    if p is None:
        return out
    if timed.error is not None:  # warm-up failed but a repeat succeeded: say so
        out["status"] = "flaky"
    ind = p.indicators
    out["chosen_method"] = p.method
    out["planner"] = {
        "d_a_deg": math.degrees(ind.d_a),
        "t_p": int(ind.t_p),
        "phi_reversals": int(ind.phi_reversals),
        "energy": float(ind.energy),
        "phi_change_deg": math.degrees(p.phi_change),
        "terminal_error_rad": float(p.verification.terminal_error),
        "timing": {k: float(v) for k, v in p.timing.items()},
    }
    out["reintegration"] = reintegrate_plan(p, np.radians(case.start_deg),
                                            np.radians(case.goal_deg)).as_dict()
    return out


def run_case(case: Case, baselines: Baselines, cfg: Config,
             log: Callable[[str], None] = print) -> dict[str, Any]:
    """The baseline and every method on one case, with speed-ups against the baseline's
    solve (same run)."""
    t0 = time.perf_counter()
    base = run_baseline(case, baselines, cfg)
    log(f"  {case.name}: baseline {base.get('status')} "
        f"{base.get('solve_time', {}).get('median', math.nan) * 1e3:.1f} ms")
    ref = base.get("solve_time", {}).get("median", math.nan)
    methods: dict[str, Any] = {}
    for m in cfg.methods:
        r = run_method(case, m, cfg)
        med = r.get("time", {}).get("median", math.nan)
        r["speedup_vs_baseline_solve"] = (ref / med) if (med and med > 0) else math.nan
        methods[m] = r
        log(f"  {case.name}: {m} {r['status']} {med * 1e3:.1f} ms"
            + (f" ({r['error'][:100]})" if r.get("error") else ""))
    return {"case": case.name, "kind": case.kind, "n": case.n, "note": case.note,
            "start_deg": list(case.start_deg), "goal_deg": list(case.goal_deg),
            "duration": DURATION, "baseline": base, "methods": methods,
            "wall_time": time.perf_counter() - t0}
