"""Chained form (eq 4-5): check values, closed form vs CasADi, round trips, dynamics."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from optimizer.chained_form import ChainedForm
from optimizer.errors import InvalidRequestError
from optimizer.model import Robot

from reference import model_rhs

D = np.deg2rad


@pytest.mark.parametrize("backend", ["closed", "casadi"])
@pytest.mark.parametrize("th, expected", [
    ([1, 1, 1], [-0.033007, 0.711175, 0.017453]),
    ([30, 30, 30], [-0.532238, 0.462133, 0.523599]),
])
def test_check_values_section_3_3(backend, th, expected):
    """NOTES §2 check values (paper: [-0.032, 0.711, 0.018] and [-0.532, 0.462, 0.524])."""
    cf = ChainedForm(Robot(), backend)
    z = cf.to_chained(np.concatenate([[0.0], D(th)]))
    np.testing.assert_allclose(z[1:], expected, atol=1e-6)


def test_closed_form_matches_notes_formula():
    """z2 = -A c1^2 c2^2 s2 with A = 3 K2 K3 (NOTES §2), v2 of eq (5), at random points."""
    K2, K3 = 0.88658, 0.7115
    rng = np.random.default_rng(3)
    q = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(0.01, 1.56, (50, 3))])
    cf = ChainedForm(Robot(), "closed")
    z = cf.to_chained(q)
    c1, s1, c2, s2 = np.cos(q[:, 1]), np.sin(q[:, 1]), np.cos(q[:, 2]), np.sin(q[:, 2])
    np.testing.assert_allclose(z[:, 1], -3 * K2 * K3 * c1**2 * c2**2 * s2, rtol=1e-13)
    np.testing.assert_allclose(z[:, 2], K3 * c2**3, rtol=1e-13)
    al, be = cf.input_coefficients(q)
    np.testing.assert_allclose(al, 3 * K2**2 * K3 * c1**4 * (2 * c2 * s2**2 - c2**3), rtol=1e-12,
                               atol=1e-14)
    np.testing.assert_allclose(be, 6 * K2 * K3 * c1 * s1 * c2**2 * s2, rtol=1e-12)


@pytest.mark.parametrize("exps", [(2, 3), (1, 1), (3, 2), (4, 5)])
def test_closed_and_casadi_agree_n3(exps):
    robot = Robot((0.9, 0.6), exps)
    a, b = ChainedForm(robot, "closed"), ChainedForm(robot, "casadi")
    rng = np.random.default_rng(7)
    q = np.column_stack([rng.uniform(-3, 3, 200), rng.uniform(0.05, 1.5, (200, 2)),
                         rng.uniform(-3, 3, 200)])
    np.testing.assert_allclose(a.to_chained(q), b.to_chained(q), rtol=1e-13, atol=1e-15)
    for x, y in zip(a.input_coefficients(q), b.input_coefficients(q)):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-15)
    z = a.to_chained(q)
    np.testing.assert_allclose(a.from_chained(z).q, b.from_chained(z).q, atol=1e-11)


def _random_q(n, rng, lo_deg, N):
    th = rng.uniform(D(lo_deg), D(90 - lo_deg), (N, n))
    th[:, -1] = rng.uniform(-3, 3, N)  # the last joint is free
    return np.column_stack([rng.uniform(-3, 3, N), th])


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(D(2.0), D(88.0)), min_size=2, max_size=2),
       st.floats(-3.0, 3.0), st.floats(-3.0, 3.0))
def test_round_trip_n3(th12, phi, th3):
    """q -> z -> q to 5e-12 for the prototype, joints 1-2 in [2, 88] deg (hypothesis).

    Near 2 deg the inverse amplifies the rounding of z about as 1 / th: 200 000 random points
    with both joints in [2, 4] deg came back within 1.8e-12 rad (99.9 % within 1.1e-12)."""
    cf = ChainedForm(Robot())
    q = np.array([phi, *th12, th3])
    inv = cf.from_chained(cf.to_chained(q))
    assert inv.valid.all()
    np.testing.assert_allclose(inv.q[0], q, atol=5e-12, rtol=0)


def _jacobian(cf, q, h=1e-6):
    J = np.zeros((q.size, q.size))
    for j in range(q.size):
        e = np.zeros(q.size)
        e[j] = h
        J[:, j] = (cf.to_chained(q + e) - cf.to_chained(q - e)) / (2 * h)
    return J


@pytest.mark.parametrize("n", [4, 5, 6, 8])
def test_round_trip_any_n_within_conditioning(n):
    """For n >= 4 the inverse loses what the map's conditioning loses: the error is bounded by
    1e-14 times the condition number of dz/dq (and is <= 1e-12 where that is below 100)."""
    cf = ChainedForm(Robot.default(n))
    rng = np.random.default_rng(n)
    q = _random_q(n, rng, 5.0, 300)
    inv = cf.from_chained(cf.to_chained(q))
    assert inv.valid.all()
    err = np.abs(inv.q - q).max(axis=1)
    kappa = np.array([np.linalg.cond(_jacobian(cf, qi)) for qi in q])
    assert np.all(err <= 1e-14 * np.maximum(kappa, 100.0))


@pytest.mark.parametrize("n", [3, 4, 5])
def test_z_dynamics_are_the_model_pushed_through_the_map(n):
    """d/dt z(q(t)) = J(q) q' equals the chained system z1'=v1, z2'=v2, z_{k+1}'=z_k v1 with
    v = v(u) of eq (5), at random points and inputs (central differences, no CasADi)."""
    robot = Robot.default(n)
    cf = ChainedForm(robot)
    rng = np.random.default_rng(11 + n)
    for q in _random_q(n, rng, 10.0, 20):
        _assert_chained_dynamics(robot, cf, q, rng.normal(size=2))


def _assert_chained_dynamics(robot, cf, q, u):
    """At ``q`` under rates ``u``: ``d/dt z`` by central differences along the tests' model
    is the chained system of ``v = v(u)``, and ``u_from_v`` inverts ``v_from_u``."""
    n = robot.n
    qdot = model_rhs(q, u, robot.gains, robot.exponents)
    h = 1e-6
    zdot = (cf.to_chained(q + h * qdot) - cf.to_chained(q - h * qdot)) / (2 * h)
    z = cf.to_chained(q)
    v = cf.v_from_u(q, u)
    chained = np.concatenate([[v[0], v[1]], z[1:n] * v[0]])
    np.testing.assert_allclose(zdot, chained, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(cf.u_from_v(q, v), u, rtol=1e-10)


@pytest.mark.parametrize("n", [4, 6])
def test_robots_sharing_exponents_each_get_their_own_gains(n):
    """The symbolic derivation is shared by robots of the same exponents (the gains are an
    input): two robots evaluated in turn each satisfy their own model's chained dynamics
    (central differences of the tests' model, as above) and the top level z_n = K_n
    cos(th_{n-1})^m_n with their own K_n."""
    base = Robot.default(n)
    rng = np.random.default_rng(40 + n)
    other = Robot(tuple(k * f for k, f in zip(base.gains, rng.uniform(0.6, 1.4, n - 1))),
                  base.exponents)
    forms = [(r, ChainedForm(r)) for r in (base, other)]
    points = _random_q(n, rng, 10.0, 6)
    for q in points:
        for robot, cf in forms:
            _assert_chained_dynamics(robot, cf, q, rng.normal(size=2))
            z = cf.to_chained(q)
            assert z[n - 1] == pytest.approx(
                robot.gains[-1] * np.cos(q[n - 1]) ** robot.exponents[-1], rel=1e-13)
            np.testing.assert_allclose(cf.from_chained(z).q[0], q, atol=1e-9)
    # many points at once (the mapped evaluation) as one at a time
    for robot, cf in forms:
        Q = np.vstack(points)
        np.testing.assert_allclose(cf.to_chained(Q), np.vstack([cf.to_chained(q) for q in Q]),
                                   rtol=1e-14, atol=1e-15)


def test_inverse_says_where_it_fails():
    cf = ChainedForm(Robot())
    z_ok = cf.to_chained(np.array([0.0, 0.3, 0.4, 0.5]))
    bad = np.array([
        z_ok * [1, -1, 1, 1],          # z2 > 0: th1 undefined
        z_ok * [1, 1, -1, 1],          # z3 < 0: th2 beyond pi/2
        z_ok + [0, 0, 0.5, 0],         # z3 > K3: th2 below 0
        [0.0, -10.0, 0.4, 0.1],        # |z2| too large: cos(th1)^2 > 1
    ])
    inv = cf.from_chained(np.vstack([z_ok, bad]))
    assert inv.valid.tolist() == [True, False, False, False, False]
    assert np.all(np.isfinite(inv.q)) and np.all(inv.q[1:] == 0.0)
    reasons = inv.reasons()
    assert reasons[0] is None
    assert "th1" in reasons[1] and "th2" in reasons[2] and "th2" in reasons[3] and "th1" in reasons[4]


@pytest.mark.parametrize("gains, exps, field", [
    ((0.9,), (2,), "robot.gains"),                    # n = 2
    ((0.9,) * 8, (2,) * 8, "robot.gains"),            # n = 9
    ((0.9, -0.1), (2, 3), "robot.gains"),
    ((0.9, float("nan")), (2, 3), "robot.gains"),
    ((0.9, 0.7), (2, 2.5), "robot.exponents"),
    ((0.9, 0.7), (0, 3), "robot.exponents"),
    ((0.9, 0.7), (2,), "robot.exponents"),
])
def test_robot_validation(gains, exps, field):
    with pytest.raises(InvalidRequestError) as exc:
        Robot(gains, exps)
    assert exc.value.field == field
    assert exc.value.message


def test_default_robots():
    assert Robot.default(3) == Robot() and not Robot.default(3).assumed
    r = Robot.default(5)
    assert r.n == 5 and r.assumed
    assert r.gains == (0.88658, 0.88658, 0.88658, 0.7115) and r.exponents == (2, 2, 2, 3)
