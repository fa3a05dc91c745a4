"""Tests of the model's one vector field and RK4 (``optimizer/dynamics.py``).

Against ``tests/reference.py`` (the model written independently from the paper's eq 1-3) and
scipy's integration of it; numpy and CasADi evaluate the same definition.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from optimizer.dynamics import field_numpy, rk4_step, vector_field
from optimizer.model import Robot
from reference import integrate_model, model_rhs


@pytest.mark.parametrize("n", [3, 4, 6])
def test_field_equals_the_reference_for_numpy_batches_and_casadi(n):
    robot = Robot.default(n)
    rng = np.random.default_rng(n)
    Q = rng.uniform(-1.0, 2.0, (7, n + 1))
    U = rng.uniform(-3.0, 3.0, (7, 2))
    ref = np.array([model_rhs(q, u, robot.gains, robot.exponents) for q, u in zip(Q, U)])
    assert np.allclose(field_numpy(robot.gains, robot.exponents, Q, (U[:, 0], U[:, 1])), ref,
                       rtol=1e-14, atol=1e-14)
    assert np.allclose([robot.rhs(q, u) for q, u in zip(Q, U)], ref, rtol=1e-14, atol=1e-14)
    x, u = ca.SX.sym("x", n + 1), ca.SX.sym("u", 2)
    f = ca.Function("f", [x, u], [ca.vertcat(*vector_field(robot.gains, robot.exponents, x,
                                                           u[0], u[1], ca.cos))])
    assert np.allclose([np.asarray(f(q, uu)).ravel() for q, uu in zip(Q, U)], ref,
                       rtol=1e-14, atol=1e-14)


def test_rk4_converges_to_scipy_at_fourth_order_in_numpy_and_casadi():
    robot = Robot()
    q0, u = np.array([0.1, 0.3, 0.5, 0.7]), np.array([1.3, -0.8])

    def f(q, uu):
        return field_numpy(robot.gains, robot.exponents, q, uu)

    exact = integrate_model(lambda t: u, q0, 1.0, robot.gains, robot.exponents).y[:, -1]
    errs = []
    for steps in (4, 8):
        errs.append(np.max(np.abs(rk4_step(f, q0, u, 1.0, steps) - exact)))
    assert errs[0] / errs[1] == pytest.approx(16.0, rel=0.15)  # classical RK4: O(h^4)
    x, uu = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    step = ca.Function("s", [x, uu], [rk4_step(
        lambda y, v: ca.vertcat(*vector_field(robot.gains, robot.exponents, y, v[0], v[1],
                                              ca.cos)), x, uu, 1.0, 8)])
    assert np.allclose(np.asarray(step(q0, u)).ravel(), rk4_step(f, q0, u, 1.0, 8),
                       rtol=1e-14, atol=1e-14)
