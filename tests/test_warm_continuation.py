"""The replanner's middle route's pieces (optimizer.planner.warm_continuation)."""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from optimizer.model import Robot
from optimizer.planner.plan_state import PlanState, TimeLaw
from optimizer.planner.warm_continuation import interval_signs, nodes_along, rest_of_plan
from reference import model_rhs


def test_interval_signs_against_sampling_each_interval() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        breaks = np.concatenate([[0.0], np.cumsum(rng.uniform(0.05, 0.3, 9))])
        rates = rng.choice([-1.0, 0.0, 1.0], size=(9, 2)) * rng.uniform(0.5, 2.0, (9, 2))
        grid = np.linspace(0.0, breaks[-1], 7)
        got = interval_signs(breaks, rates, grid)
        for j in range(6):
            # the pieces an interval overlaps, found by sampling it densely
            s = np.linspace(grid[j], grid[j + 1], 2001)[1:-1]
            k = np.unique(np.clip(np.searchsorted(breaks, s, side="right") - 1, 0, 8))
            for c in range(2):
                seen = {float(v) for v in np.sign(rates[k, c]) if v != 0.0}
                assert got[j, c] == (seen.pop() if len(seen) == 1 else 0.0), (j, c, seen)


def test_the_nodes_follow_the_plans_rest_on_the_original_model() -> None:
    robot = Robot.default(4)
    breaks = np.array([0.0, 0.3, 0.5, 0.9, 1.2])
    rates = np.array([[1.0, 0.4], [-0.5, 0.8], [0.7, -0.3], [1.2, 0.1]])
    ps = PlanState(robot=robot, goal=np.zeros(4), breaks=breaks, rates=rates,
                   law=TimeLaw.identity(breaks), plan_duration=1.2)
    rest_b, rest_r = rest_of_plan(ps, 0.4)
    assert rest_b.tolist() == [0.4, 0.5, 0.9, 1.2] and np.array_equal(rest_r, rates[1:])
    q0 = np.array([0.1, 0.5, 0.6, 0.7, 0.8])
    grid = np.linspace(0.4, 1.2, 9)
    nodes = nodes_along(ps, q0, rest_b, rest_r, grid)
    q = q0
    for a, b in zip(grid[:-1], grid[1:]):
        cuts = np.union1d([a, b], rest_b[(rest_b > a) & (rest_b < b)])
        for c0, c1 in zip(cuts[:-1], cuts[1:]):
            u = rest_r[np.searchsorted(rest_b, 0.5 * (c0 + c1)) - 1]
            q = solve_ivp(lambda t, x: model_rhs(x, u, robot.gains, robot.exponents), (c0, c1),
                          q, method="DOP853", rtol=1e-12, atol=1e-13).y[:, -1]
        assert np.max(np.abs(nodes[np.searchsorted(grid, b)] - q)) < 1e-6
