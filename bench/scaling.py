"""How the cost grows: with the number of samples of a plan, and with the number of joints.

Samples
    The complete polynomial plan of [10, 10, 10] -> [30, 30, 30] deg with ``samples`` = 101,
    1001, 10001 (the returned path's time samples; the searches use their own fixed grids).

Joints (n = 3..8, ``Robot.default(n)``)
    * ``ChainedForm(Robot.default(n))`` construction, cold: the process-wide cache of the
      symbolic derivation (``optimizer.chained_form.symbolic_form``) is cleared before each one, so
      the CasADi Lie-derivative derivation and code generation are included;
    * the forward map ``to_chained`` and the inverse ``from_chained`` of 10^4 random points
      inside the region (``th_1..th_{n-1}`` in [5, 85] deg), and their round-trip error;
    * one ``PolynomialFamily.coarse_margins`` scan over the planner's own ``dphi`` grid
      (0.25 deg steps over (0, pi], 97 time samples per member) for a same-direction move;
    * a complete polynomial plan where one exists: the goal is made by running a member of the
      paper's family forward from a fixed start (``dphi`` and ``v2`` drawn with a fixed seed,
      kept when the path stays at least 3 deg inside the region and the members 0.3 deg on
      either side of that ``dphi`` are singularity-free too), so that the family can reach it
      with a window wider than the planner's 0.25 deg scan step. When no such goal is found within the tries, or the planner fails on it, that is
      recorded and only the transform timings stand.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable

import numpy as np

from .stats import summarise, time_repeats

SAMPLE_COUNTS = (101, 1001, 10001)
JOINTS = tuple(range(3, 9))
MAP_POINTS = 10_000
#: A generated goal is kept when the family's members this far (deg) on either side of the drawn
#: ``dphi`` are singularity-free too (so the window is wider than the planner's scan step).
WINDOW_SIDE_DEG = 0.3


def samples_scaling(repeats: int, budget: float, min_repeats: int,
                    counts: tuple[int, ...] = SAMPLE_COUNTS) -> list[dict[str, Any]]:
    """Polynomial plan time against ``samples``."""
    from optimizer.planner.plan import plan
    from optimizer.problem import PlanRequest
    out = []
    for s in counts:
        req = PlanRequest(start=tuple(np.radians([10.0] * 3)), goal=tuple(np.radians([30.0] * 3)),
                          method="polynomial", duration=1.0, samples=s)
        timed = time_repeats(lambda: plan(req), repeats, budget, min_repeats)
        entry: dict[str, Any] = {"samples": s, "time": timed.summary.as_dict(),
                                 "error": None if timed.error is None else str(timed.error)}
        if timed.result is not None:
            entry["timing_breakdown"] = {k: float(v) for k, v in timed.result.timing.items()}
        out.append(entry)
    return out


def _timeit(fn: Callable[[], Any], repeats: int) -> dict[str, Any]:
    samples = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return summarise(samples).as_dict()


def _feasible_goal(n: int, seed: int, tries: int, time_budget: float
                   ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """A start and a goal the paper's family reaches (see the module docstring)."""
    from optimizer.chained_form import chained_form
    from optimizer.model import Robot
    from optimizer.planner.family import PolynomialFamily
    from optimizer.planner.rules import make_region
    from optimizer.problem import PlanRequest
    from optimizer.steering import ChainedPath, InputSchedule
    rng = np.random.default_rng(seed)
    robot = Robot.default(n)
    cf = chained_form(robot)
    tau = np.linspace(0.0, 1.0, 2001)
    t0 = time.perf_counter()
    for _ in range(tries):
        if time.perf_counter() - t0 > time_budget:
            break
        q0 = np.concatenate([[0.0], np.radians(rng.uniform(15, 75, n))])
        dphi = float(rng.uniform(0.2, 1.2))
        v2 = rng.normal(scale=0.3, size=n)
        path = ChainedPath.from_inputs(cf.to_chained(q0), InputSchedule.single([dphi], [float(x) for x in v2], 1.0))
        inv = cf.from_chained(path.z(tau))
        th = inv.q[:, 1:n]
        if not (inv.valid.all() and th.min() > math.radians(3) and th.max() < math.radians(87)):
            continue
        # the window must be wider than the planner's 0.25 deg scan step (for n >= 5 most
        # windows found this way are narrower than 0.01 deg): members 0.3 deg on either side
        # must be singularity-free too
        goal = inv.q[-1, 1:]
        req = PlanRequest(start=tuple(q0[1:]), goal=tuple(goal), robot=robot,
                          method="polynomial", duration=1.0)
        fam = PolynomialFamily(robot, req.q_start(), req.q_goal(0.0), 1.0, (), make_region(req))
        side = math.radians(WINDOW_SIDE_DEG)
        if np.all(fam.coarse_margins(np.array([dphi - side, dphi, dphi + side]), grid=401) > 0):
            return q0[1:], goal, dphi
    return None


def joint_scaling(repeats: int, plan_repeats: int, budget: float,
                  joints: tuple[int, ...] = JOINTS, goal_tries: int = 400,
                  log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Transform, scan and plan timings for each number of joints."""
    from optimizer import chained_form as cfmod
    from optimizer.model import Robot
    from optimizer.planner.family import PolynomialFamily
    from optimizer.planner.intervals import GRID_STEP
    from optimizer.planner.plan import plan
    from optimizer.planner.rules import make_region
    from optimizer.problem import PlanRequest
    from optimizer.steering import MIN_ABS_DPHI

    rng = np.random.default_rng(0)
    out = []
    for n in joints:
        robot = Robot.default(n)
        entry: dict[str, Any] = {"n": n}

        def build() -> Any:
            cfmod.symbolic_form.cache_clear()  # cold: derive and compile again
            return cfmod.ChainedForm(robot)
        entry["construct"] = _timeit(build, repeats)
        cf = cfmod.chained_form(robot)

        th = np.radians(rng.uniform(5, 85, (MAP_POINTS, n)))
        q = np.column_stack([rng.uniform(-1, 1, MAP_POINTS), th])
        z = cf.to_chained(q)
        entry["forward_10k"] = _timeit(lambda: cf.to_chained(q), repeats)
        entry["inverse_10k"] = _timeit(lambda: cf.from_chained(z), repeats)
        inv = cf.from_chained(z)
        entry["roundtrip_max_error_rad"] = float(np.max(np.abs(inv.q[inv.valid] - q[inv.valid])))
        entry["roundtrip_valid_fraction"] = float(inv.valid.mean())

        start = np.radians(np.full(n, 20.0))
        goal = np.radians(np.full(n, 30.0))
        req = PlanRequest(start=tuple(start), goal=tuple(goal), robot=robot, method="polynomial",
                          duration=1.0)
        fam = PolynomialFamily(robot, req.q_start(), req.q_goal(0.0), 1.0, (), make_region(req))
        eps = 10 * MIN_ABS_DPHI
        k = max(2, int(math.ceil((math.pi - eps) / GRID_STEP)) + 1)
        dphis = np.linspace(eps, math.pi, k)
        entry["coarse_scan"] = _timeit(lambda: fam.coarse_margins(dphis), repeats)
        entry["coarse_scan_members"] = int(dphis.size)

        found = _feasible_goal(n, seed=100 + n, tries=goal_tries, time_budget=budget)
        if found is None:
            entry["plan"] = {"status": "no_goal",
                             "note": f"no goal with a family window wider than "
                                     f"{2 * WINDOW_SIDE_DEG:g} deg found in {budget:g} s of "
                                     f"random draws (at most {goal_tries})"}
        else:
            s, g, dphi = found
            preq = PlanRequest(start=tuple(s), goal=tuple(g), robot=robot, method="polynomial",
                               duration=1.0)
            timed = time_repeats(lambda: plan(preq), plan_repeats, budget, 1)
            entry["plan"] = {
                "status": "success" if timed.error is None else type(timed.error).__name__,
                "error": None if timed.error is None else str(timed.error)[:300],
                "start_deg": np.degrees(s).round(3).tolist(),
                "goal_deg": np.degrees(g).round(3).tolist(),
                "drawn_dphi_deg": math.degrees(dphi),
                "time": timed.summary.as_dict(), "first_call": timed.first,
            }
        log(f"  n={n}: construct {entry['construct']['median'] * 1e3:.0f} ms, fwd+inv 10k "
            f"{(entry['forward_10k']['median'] + entry['inverse_10k']['median']) * 1e3:.1f} ms, "
            f"scan {entry['coarse_scan']['median'] * 1e3:.1f} ms, plan "
            f"{entry['plan']['status']}"
            + (f" {entry['plan']['time']['median'] * 1e3:.0f} ms" if entry['plan'].get('time')
               and entry['plan']['status'] == 'success' else ""))
        out.append(entry)
    return out
