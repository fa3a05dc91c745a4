"""Tests for the direct multiple-shooting baseline (``bench/baselines/multiple_shooting.py``).

Every solution is re-integrated with an independent right-hand side (the tests' own,
``tests/reference.py``, not imported from the baseline) using ``scipy.integrate.solve_ivp``
(rtol 1e-10, atol 1e-12), interval by interval with the piecewise-constant
inputs.  The re-integrated final joint angles must hit the goal within
``GOAL_TOL = 1e-3`` rad.  That tolerance is loose on purpose (the brief's
acceptance bound); the RK4 discretisation error actually observed
(50 intervals x 4 RK4 substeps, T = 1 s) is of order 1e-10 rad, and
``RK4_TOL = 1e-6`` rad checks that the node states the baseline reports agree
with the exact flow of the original model to that tighter level.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # ``bench`` is not an installed package
    sys.path.insert(0, str(ROOT))

from reference import model_rhs as original_rhs  # noqa: E402

from bench.baselines.multiple_shooting import (  # noqa: E402
    PROTOTYPE_EXPONENTS,
    PROTOTYPE_GAINS,
    BaselineResult,
    MultipleShootingBaseline,
    default_model,
)

GOAL_TOL = 1e-3  # rad, re-integrated final th vs goal
RK4_TOL = 1e-6  # rad, baseline node states vs exact flow (observed <= ~5e-10)
BOX = (math.radians(0.5), math.radians(89.5))
BOX_SLACK = 1e-7  # IPOPT may relax bounds by ~1e-8 (bound_relax_factor)



def reintegrate(res: BaselineResult, gains, exponents) -> np.ndarray:
    """Integrate the original model interval by interval from ``q_nodes[0]``.

    Returns the ``(N + 1, n + 1)`` exactly integrated states at the node times.
    """
    q = res.q_nodes[0].astype(float).copy()
    out = [q.copy()]
    for k in range(res.u.shape[0]):
        uk = res.u[k]
        sol = solve_ivp(
            lambda _t, x: original_rhs(x, uk, gains, exponents),
            (res.t_grid[k], res.t_grid[k + 1]),
            q,
            method="DOP853",
            rtol=1e-10,
            atol=1e-12,
        )
        assert sol.success, sol.message
        q = sol.y[:, -1].copy()
        out.append(q.copy())
    return np.array(out)


def check_solution(res, start_deg, goal_deg, gains, exponents, phi_start=0.0):
    n = len(gains) + 1
    start, goal = np.radians(start_deg), np.radians(goal_deg)
    assert res.success, res.return_status
    assert res.return_status in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
    N = res.u.shape[0]
    assert res.t_grid.shape == (N + 1,)
    assert res.q_nodes.shape == (N + 1, n + 1)
    assert res.u.shape == (N, 2)
    assert res.build_time > 0 and res.solve_time > 0
    np.testing.assert_allclose(res.q_nodes[0], np.r_[phi_start, start], atol=1e-9)

    exact = reintegrate(res, gains, exponents)
    # Final joint angles of the exact flow hit the goal.
    assert np.max(np.abs(exact[-1, 1:] - goal)) < GOAL_TOL
    # RK4 discretisation error is small at every node.
    assert np.max(np.abs(exact - res.q_nodes)) < RK4_TOL
    # th1..th_{n-1} inside the box at every node.
    inner = res.q_nodes[:, 1:n]
    assert np.all(inner >= BOX[0] - BOX_SLACK)
    assert np.all(inner <= BOX[1] + BOX_SLACK)
    return exact


@pytest.fixture(scope="module")
def prototype() -> MultipleShootingBaseline:
    return MultipleShootingBaseline(PROTOTYPE_GAINS, PROTOTYPE_EXPONENTS)


def test_prototype_same_direction(prototype):
    start, goal = [10, 10, 10], [30, 30, 30]
    res = prototype.solve(np.radians(start), np.radians(goal))
    check_solution(res, start, goal, PROTOTYPE_GAINS, PROTOTYPE_EXPONENTS)
    assert res.duration == 1.0
    assert res.t_grid[-1] == pytest.approx(1.0)


def test_prototype_opposite_directions_phi_reverses(prototype):
    # th2 must increase while th3 decreases; since th_i' has the sign of u1
    # inside the box, u1 (i.e. phi) has to reverse.
    start, goal = [10, 20, 30], [40, 25, 15]
    res = prototype.solve(np.radians(start), np.radians(goal))
    check_solution(res, start, goal, PROTOTYPE_GAINS, PROTOTYPE_EXPONENTS)
    assert res.u[:, 0].min() < 0.0 < res.u[:, 0].max()


def test_nonzero_phi_start_reuses_solver(prototype):
    start, goal = [10, 10, 10], [30, 30, 30]
    res = prototype.solve(np.radians(start), np.radians(goal), phi_start=0.3)
    check_solution(res, start, goal, PROTOTYPE_GAINS, PROTOTYPE_EXPONENTS, 0.3)
    ref = prototype.solve(np.radians(start), np.radians(goal))
    # phi does not enter the dynamics: same inputs, phi shifted by 0.3.
    np.testing.assert_allclose(res.u, ref.u, atol=1e-6)
    np.testing.assert_allclose(res.q_nodes[:, 0], ref.q_nodes[:, 0] + 0.3, atol=1e-6)
    assert res.build_time == ref.build_time == prototype.build_time


def test_four_joints():
    gains, exponents = default_model(4)
    assert gains == (0.88658, 0.88658, 0.7115)
    assert exponents == (2, 2, 3)
    planner = MultipleShootingBaseline(gains, exponents)
    start, goal = [10, 10, 10, 10], [30, 30, 30, 30]
    res = planner.solve(np.radians(start), np.radians(goal))
    check_solution(res, start, goal, gains, exponents)


def test_u_of_t_piecewise_constant_right_continuous(prototype):
    res = prototype.solve(np.radians([10, 20, 30]), np.radians([40, 25, 15]))
    h = res.duration / res.u.shape[0]
    for k in (0, 1, 17, res.u.shape[0] - 1):
        np.testing.assert_array_equal(res.u_of_t(res.t_grid[k]), res.u[k])
        np.testing.assert_array_equal(res.u_of_t(res.t_grid[k] + 0.5 * h), res.u[k])
    np.testing.assert_array_equal(res.u_of_t(-1.0), res.u[0])
    np.testing.assert_array_equal(res.u_of_t(res.duration), res.u[-1])
    np.testing.assert_array_equal(res.u_of_t(10.0), res.u[-1])


def test_rejects_bad_input(prototype):
    with pytest.raises(ValueError):
        prototype.solve(np.radians([10, 10]), np.radians([30, 30, 30]))
    with pytest.raises(ValueError):  # th2 of the goal outside the box
        prototype.solve(np.radians([10, 10, 10]), np.radians([30, 95, 30]))
    with pytest.raises(ValueError):
        MultipleShootingBaseline((0.88658,), (2,))
