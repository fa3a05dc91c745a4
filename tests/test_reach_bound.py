"""A goal no path can reach within narrow joint bounds is refused at once, and the bound that
refuses it never refuses a path that exists (paths integrated independently with scipy)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from optimizer.errors import InfeasibleError
from optimizer.model import Robot
from optimizer.planner.plan import plan
from optimizer.planner.rules import travel_reach_error
from optimizer.problem import PlanRequest

from reference import integrate_model

#: The issue's request: th1 and th2 held to (0.19, 0.22) rad, th3 to move 12 rad.
NARROW = PlanRequest(start=(0.2, 0.2, -6.0), goal=(0.21, 0.21, 6.0),
                     joint_bounds=((0.19, 0.22), (0.19, 0.22), None))


def test_an_unreachable_goal_in_narrow_bounds_is_refused_before_any_solve():
    t0 = time.perf_counter()
    with pytest.raises(InfeasibleError) as err:
        plan(NARROW)
    elapsed = time.perf_counter() - t0
    assert err.value.field == "joint_bounds"
    assert "th3" in str(err.value) and "joint_bounds" in str(err.value)
    # refused by the bound, not by a search cut at the time limit (10 s)
    assert elapsed < 0.5 * NARROW.time_limit
    assert "phi_travel_bound" in err.value.diagnostics


@pytest.mark.parametrize("n, seed", [(3, 0), (3, 1), (4, 2), (5, 3), (6, 4)])
def test_the_bound_never_refuses_a_path_that_exists(n, seed):
    """Random piecewise-constant rates (scipy, the reference model): with the path's own joint
    ranges as bounds and its own phi travel, its end must pass the bound; so must it at
    several scalings of the ranges' width (narrow ranges are where the bound bites)."""
    rng = np.random.default_rng(seed)
    robot = Robot.default(n)
    K, m = robot.gains, robot.exponents
    checked = 0
    for _ in range(6):
        q = np.concatenate([[0.0], rng.uniform(0.6, 0.9, n)])
        pieces = rng.integers(2, 7)
        rates = rng.normal(0.0, 0.2, (pieces, 2))
        path = [q]
        for u in rates:
            sol = integrate_model(lambda t, u=u: u, q, 1.0, K, m,
                                  t_eval=np.linspace(0.0, 1.0, 41))
            q = sol.y[:, -1]
            path.append(sol.y.T)
        Q = np.vstack(path[1:])
        th = Q[:, 1:]
        if np.any(th[:, :-1] <= 0.02) or np.any(th[:, :-1] >= np.pi / 2 - 0.02):
            continue
        travel = float(np.sum(np.abs(rates[:, 0])))
        bounds = tuple((float(lo) - 1e-9, float(hi) + 1e-9)
                       for lo, hi in zip(th.min(axis=0), th.max(axis=0)))
        req = PlanRequest(start=tuple(th[0]), goal=tuple(th[-1]), robot=robot,
                          joint_bounds=bounds)
        assert travel_reach_error(req, travel) is None
        checked += 1
    assert checked >= 3


def test_the_bound_refuses_what_it_must_on_a_closed_form_case():
    """th1 and th2 pinned (bounds of zero width, up to 1e-9): r is constant, th3 follows th2
    exactly (dth3 = r dth2), so th3 can move only r * dth2 whatever phi does."""
    robot = Robot.default(3)
    a = (0.3, 0.4, 0.5)
    b = (0.3, 0.4 + 1e-10, 0.6)
    bounds = ((0.3 - 1e-9, 0.3 + 1e-9), (0.4 - 1e-9, 0.4 + 2e-9), None)
    req = PlanRequest(start=a, goal=b, robot=robot, joint_bounds=bounds)
    assert travel_reach_error(req, 40.0) is not None
