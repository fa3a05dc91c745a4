"""What a controller executes reaches the goal: the handed-out forms replayed independently.

Goals: reachable by construction (the true model integrated forward under random smooth inputs
from a random start inside the region, kept when every joint stays inside). Replays: scipy's
DOP853 on the original model, piece by piece between consecutive samples (the inputs are
smooth there), under each form's documented rule -- nothing of the planner's integrators.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from optimizer.errors import InvalidRequestError
from optimizer.model import Robot
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest

HALF_PI = 0.5 * math.pi
RTOL = ATOL = 1e-12


def _rhs(robot: Robot, u_of_t):
    K = np.array(robot.gains)
    m = np.array(robot.exponents, float)

    def f(t, q):
        u = u_of_t(t)
        return np.concatenate([[u[0], u[1]], K * np.cos(q[1:-1]) ** m * u[0]])
    return f


def reachable_goals(n: int, count: int, seed: int) -> list[tuple[tuple[float, ...], tuple[float, ...]]]:
    """Start inside the region, goal = the true model's end under random smooth inputs with
    ``u1 > 0`` (every joint th2..thn then moves one way: the polynomial family applies)."""
    rng = np.random.default_rng(seed)
    robot = Robot.default(n)
    out = []
    while len(out) < count:
        start = rng.uniform(0.3, 1.2, n)
        a = rng.uniform(0.3, 1.0)
        b = rng.uniform(-0.8, 0.8, 3)

        def u(t, a=a, b=b):
            return np.array([a * (1.0 + 0.5 * np.sin(2 * np.pi * t)),
                             b[0] + b[1] * np.cos(np.pi * t) + b[2] * t])
        sol = solve_ivp(_rhs(robot, u), (0.0, 1.0), np.concatenate([[0.0], start]),
                        rtol=1e-10, atol=1e-12, dense_output=True)
        th = sol.sol(np.linspace(0.0, 1.0, 401))[1:]
        if th.min() > 0.15 and th.max() < HALF_PI - 0.15 and np.all(np.abs(th[:, -1] - start) > 0.05):
            out.append((tuple(start), tuple(th[:, -1])))
    return out


GOALS = {n: reachable_goals(n, 1, 16 + n) for n in (3, 4, 5)}


def replay_linear(robot: Robot, t: np.ndarray, u: np.ndarray, q0: np.ndarray) -> tuple[np.ndarray, float]:
    """The original model under linear interpolation of ``u`` over ``t`` (repeated times:
    jumps), piece by piece. Returns the final state and the smallest region margin seen."""
    return _replay(robot, t, q0, lambda k, s: (1.0 - s) * u[k] + s * u[k + 1])


def replay_zoh(robot: Robot, t: np.ndarray, u: np.ndarray, q0: np.ndarray) -> tuple[np.ndarray, float]:
    """The original model with ``u[k]`` held on ``[t_k, t_{k+1})``."""
    return _replay(robot, t, q0, lambda k, s: u[k])


def replay_hermite(robot: Robot, t: np.ndarray, x: np.ndarray, v: np.ndarray,
                   q0: np.ndarray) -> tuple[np.ndarray, float]:
    """The original model driven by the derivative of the cubic Hermite interpolant of
    positions ``x`` and velocities ``v`` at ``t`` (joint_trajectory_controller's rule)."""
    def u(k, s):
        h = t[k + 1] - t[k]
        d = 6 * s * s - 6 * s
        return ((d * x[k] - d * x[k + 1]) / h + (3 * s * s - 4 * s + 1) * v[k]
                + (3 * s * s - 2 * s) * v[k + 1])
    return _replay(robot, t, q0, u)


def _replay(robot, t, q0, u_local):
    q = np.asarray(q0, float)
    margin = math.inf
    for k in range(t.size - 1):
        a, b = t[k], t[k + 1]
        if b <= a:
            continue  # a repeated time: the jump between its two values
        h = b - a
        sol = solve_ivp(_rhs(robot, lambda tt: u_local(k, (tt - a) / h)), (a, b), q,
                        method="DOP853", rtol=RTOL, atol=ATOL, max_step=h / 4,
                        dense_output=True)
        assert sol.success, sol.message
        th = sol.sol(np.linspace(a, b, 5))[1:]
        margin = min(margin, float(np.min(np.minimum(th, HALF_PI - th))))
        q = sol.y[:, -1]
    return q, margin


FAST = ["polynomial", "retimed", "constraint_points", "shooting"]
SLOW = ["penalty", "auto"]  # seconds per plan (the penalty NLP): fewer joint counts
LINEAR_CASES = ([(n, m) for n in (3, 4, 5) for m in FAST] + [(n, m) for n in (3, 4) for m in SLOW])
ZOH_CASES = [(n, m) for n in (3, 4, 5) for m in FAST] + [(3, m) for m in SLOW]


def _plan(n: int, method: str, **kw):
    start, goal = GOALS[n][0]
    req = PlanRequest(start=start, goal=goal, robot=Robot.default(n), method=method,
                      time_limit=30.0, **kw)
    return req, plan(req)


@pytest.mark.parametrize("n, method", LINEAR_CASES)
def test_default_samples_replay_by_linear_interpolation(n, method):
    req, p = _plan(n, method)
    assert p.execution is not None and p.execution.check.rule == "linear"
    qf, margin = replay_linear(p.robot, p.path.t, p.path.u, req.q_start())
    err = float(np.max(np.abs(qf[1:] - np.array(req.goal))))
    assert err < 1e-4, err
    assert margin > 0.0
    d = p.to_dict()
    assert d["path"]["rule"] == "linear"
    assert d["validation"]["executed"]["terminal_error"] <= 1e-6
    assert d["validation"]["executed"]["margin"] > 0.0


@pytest.mark.parametrize("n, method", ZOH_CASES)
def test_controller_period_replays_by_zero_order_hold(n, method):
    req, p = _plan(n, method, controller_period=0.01, joint_trajectory=(method == "auto"))
    t = p.path.t
    assert t[0] == 0.0 and t[-1] == p.duration
    assert np.allclose(np.diff(t)[:-1], 0.01, rtol=0, atol=1e-12)
    qf, margin = replay_zoh(p.robot, t, p.path.u, req.q_start())
    err = float(np.max(np.abs(qf[1:] - np.array(req.goal))))
    assert err < 1e-6, err
    assert margin > 0.0
    if method == "auto":
        _check_joint_trajectory(p, req, 1e-4)


def _check_joint_trajectory(p, req, tol):
    jt = p.to_dict()["joint_trajectory"]
    assert jt["joint_names"] == ["phi", "th1"]
    pts = jt["points"]
    t = np.array([pt["time_from_start"]["sec"] + 1e-9 * pt["time_from_start"]["nanosec"]
                  for pt in pts])
    assert np.all(np.diff(t) > 0) and all(0 <= pt["time_from_start"]["nanosec"] < 10 ** 9
                                          for pt in pts)
    x = np.array([pt["positions"] for pt in pts])
    v = np.array([pt["velocities"] for pt in pts])
    assert np.allclose(x[0], req.q_start()[:2], atol=1e-12)
    qf, margin = replay_hermite(p.robot, t, x, v, req.q_start())
    err = float(np.max(np.abs(qf[1:] - np.array(req.goal))))
    assert err < tol, err
    assert margin > 0.0


@pytest.mark.parametrize("method", ["retimed", "shooting"])
def test_joint_trajectory_replays_by_cubic_hermite(method):
    req, p = _plan(4, method, joint_trajectory=True)
    _check_joint_trajectory(p, req, 1e-4)


def test_shooting_samples_at_breaks_are_the_break_times_with_both_rates():
    """Every rate break of a shooting plan is a sample time exactly, twice: the previous
    interval's rate, then the new one (holding the second copy holds the new rate)."""
    req, p = _plan(3, "shooting")
    sched = p.inputs
    t, u = p.path.t, p.path.u
    for k, b in enumerate(sched.breaks[1:-1]):
        rows = np.nonzero(t == b)[0]
        assert rows.size == 2, (k, b)
        # (to rounding: the samples are the L2 projection of the rates, exact for constants)
        assert np.allclose(u[rows[0]], sched.rates[k], rtol=0, atol=1e-12)
        assert np.allclose(u[rows[1]], sched.rates[k + 1], rtol=0, atol=1e-12)
        # and a zero-order hold from the last copy of the break holds the new interval's rate
        assert np.allclose(u[np.searchsorted(t, b, side="right") - 1], sched.rates[k + 1],
                           rtol=0, atol=1e-12)


def test_controller_period_must_fit_the_duration():
    start, goal = GOALS[3][0]
    for bad in (0.0, -0.01, 5e-5, 0.6, math.inf):
        with pytest.raises(InvalidRequestError):
            PlanRequest(start=start, goal=goal, duration=1.0, controller_period=bad)
    with pytest.raises(InvalidRequestError):  # more samples than MAX_SAMPLES
        PlanRequest(start=start, goal=goal, duration=5.0, controller_period=1e-4)


def test_a_period_that_does_not_divide_the_duration_ends_with_a_shorter_interval():
    start, goal = GOALS[3][0]
    req = PlanRequest(start=start, goal=goal, method="polynomial", duration=1.0,
                      controller_period=0.03)
    p = plan(req)
    t = p.path.t
    assert t[-1] == 1.0 and 0 < t[-1] - t[-2] < 0.03 and t.size == 35
    qf, margin = replay_zoh(p.robot, t, p.path.u, req.q_start())
    assert float(np.max(np.abs(qf[1:] - np.array(req.goal)))) < 1e-6 and margin > 0
