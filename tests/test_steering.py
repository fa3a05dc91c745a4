"""Polynomial steering (eq 8-12) checked against scipy integration of the chained system."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from optimizer.chained_form import chained_form
from optimizer.errors import InvalidRequestError, SingularSystemError
from optimizer.model import Robot
from optimizer.steering import (ChainedPath, ConstraintPoint, InputSchedule, solve_polynomial,
                                validate_constraint_points)

D = np.deg2rad


def _chained_rhs(inputs: InputSchedule):
    def f(t, z):
        v = inputs.v(np.array([t]))[0]
        dz = np.empty_like(z)
        dz[0], dz[1] = v
        dz[2:] = z[1:-1] * v[0]
        return dz
    return f


def _integrate_chained(inputs, z0, t_eval):
    sol = solve_ivp(_chained_rhs(inputs), (0, inputs.duration), z0, method="DOP853",
                    rtol=1e-12, atol=1e-13, t_eval=t_eval)
    return sol.y.T


def test_worked_example_coefficients():
    """NOTES §5: at dphi = 34.57 deg, T = 1: c = [-0.21247, 1.38317, -2.10678]."""
    cf = chained_form(Robot())
    z0 = cf.to_chained(D([0, 10, 10, 10]))
    zT = cf.to_chained(D([0, 30, 30, 30]))
    inp = solve_polynomial(D(34.57), 3, z0, zT, 1.0)
    seg = inp.physical_coefficients()[0]
    np.testing.assert_allclose(seg["v1"], [D(34.57)], rtol=1e-15)
    np.testing.assert_allclose(seg["v2"], [-0.21247, 1.38317, -2.10678], atol=1e-4)


@pytest.mark.parametrize("n, T, points", [
    (3, 1.0, ()),
    (3, 10.0, (ConstraintPoint(5.0, 2, -0.2),)),
    (4, 2.0, (ConstraintPoint(0.5, 3, -0.1), ConstraintPoint(1.5, 2, -0.3))),
    (6, 0.5, ()),
])
def test_goal_and_constraint_points_hit(n, T, points):
    """The solved inputs, integrated with scipy in the chained form, hit the goal and pass the
    constraint points; the exact polynomial path agrees with the integration."""
    rng = np.random.default_rng(n)
    z0 = np.concatenate([[0.3], 0.3 * rng.normal(size=n)])
    zT = np.concatenate([[0.0], 0.3 * rng.normal(size=n)])
    inp = solve_polynomial(2.0, n, z0, zT, T, points)
    times = np.array(sorted({0.0, T, *[cp.time for cp in points]}))
    Z = _integrate_chained(inp, z0, times)
    np.testing.assert_allclose(Z[-1, 1:], zT[1:], atol=1e-9)
    assert Z[-1, 0] == pytest.approx(z0[0] + 2.0, abs=1e-12)
    for cp in points:
        k = int(np.nonzero(times == cp.time)[0][0])
        assert Z[k, cp.state - 1] == pytest.approx(cp.value, abs=1e-9)
    exact = ChainedPath.from_inputs(z0, inp).z(times / T)
    np.testing.assert_allclose(exact, Z, atol=1e-9)


def test_varying_v1_path_is_exact():
    """Piecewise inputs with a reversing v1: the exact polynomial path equals integration."""
    inp = InputSchedule(np.array([0.0, 0.4, 1.0]),
                        (np.array([1.0, -2.0]), np.array([-0.5, 0.3, 0.2])),
                        (np.array([0.1, 0.2, -0.3]), np.array([0.0, 1.0])), 3.0)
    z0 = np.array([0.1, -0.2, 0.5, 0.3, 0.0])
    t = np.linspace(0, 3.0, 13)
    np.testing.assert_allclose(ChainedPath.from_inputs(z0, inp).z(t / 3.0),
                               _integrate_chained(inp, z0, t), atol=1e-9)


def test_dphi_zero_is_singular():
    z = np.zeros(4)
    with pytest.raises(SingularSystemError) as exc:
        solve_polynomial(0.0, 3, z, z + 1, 1.0)
    assert exc.value.field == "phi_change" and "Remark 2" in exc.value.message


def test_constraint_point_validation():
    with pytest.raises(InvalidRequestError, match="strictly inside"):
        validate_constraint_points([ConstraintPoint(1.0, 2, 0.0)], 3, 1.0)
    with pytest.raises(InvalidRequestError, match="chained index"):
        validate_constraint_points([ConstraintPoint(0.5, 5, 0.0)], 3, 1.0)
    with pytest.raises(InvalidRequestError, match="repeats"):
        validate_constraint_points([ConstraintPoint(0.5, 2, 0.0), ConstraintPoint(0.5, 2, 1.0)],
                                   3, 1.0)


def test_affine_basis_high_degrees():
    """dz_k/da_i = dphi^(k-2) i! tau^(i+k-1) / (i+k-1)! beyond 20! (no integer overflow)."""
    import math
    from optimizer.steering import affine_basis
    n, p, dphi, tau = 8, 16, 0.7, 0.9
    _, basis = affine_basis(dphi, n, np.zeros(n + 1), p, np.array([tau]))
    for kk in range(n):
        for i in range(p):
            expected = dphi**kk * math.factorial(i) / math.factorial(i + kk + 1) * tau ** (i + kk + 1)
            assert basis[0, kk, i] == pytest.approx(expected, rel=1e-13)


def test_phi_change_of_a_piecewise_schedule_matches_quadrature():
    from scipy.integrate import quad
    from optimizer.steering import InputSchedule
    sched = InputSchedule(np.array([0.0, 0.3, 1.0]),
                          (np.array([0.5, -2.0, 1.5]), np.array([-0.7])),
                          (np.array([0.0]), np.array([0.0])), 2.0)
    expected = sum(quad(lambda x: sched.V(np.array([x]))[0, 0], a, b)[0]
                   for a, b in ((0.0, 0.3), (0.3, 1.0)))
    assert sched.phi_change == pytest.approx(expected, abs=1e-13)
