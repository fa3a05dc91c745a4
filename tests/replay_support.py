"""Independent replays of handed-out plans: scipy's DOP853 on the original model, piece by
piece between consecutive samples, under each form's documented rule; and reachable goals."""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

from bench.reintegrate import joint_trajectory_arrays  # noqa: F401 - the tests decode with it too
from optimizer.model import Robot

HALF_PI = 0.5 * math.pi
RTOL = ATOL = 1e-12


def _rhs(robot: Robot, u_of_t):
    K = np.array(robot.gains)
    m = np.array(robot.exponents, float)

    def f(t, q):
        u = u_of_t(t)
        return np.concatenate([[u[0], u[1]], K * np.cos(q[1:-1]) ** m * u[0]])
    return f


Goal = tuple[tuple[float, ...], tuple[float, ...]]


def reachable_goals(n: int, count: int, seed: int) -> list[Goal]:
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
        inside = th.min() > 0.15 and th.max() < HALF_PI - 0.15
        if inside and np.all(np.abs(th[:, -1] - start) > 0.05):
            out.append((tuple(start), tuple(th[:, -1])))
    return out




def replay_linear(robot: Robot, t: np.ndarray, u: np.ndarray,
                  q0: np.ndarray) -> tuple[np.ndarray, float]:
    """The original model under linear interpolation of ``u`` over ``t`` (repeated times:
    jumps), piece by piece. Returns the final state and the smallest region margin seen."""
    return _replay(robot, t, q0, lambda k, s: (1.0 - s) * u[k] + s * u[k + 1])


def linear_integral(t: np.ndarray, v: np.ndarray, x0: float, per_interval: int = 8
                    ) -> np.ndarray:
    """``x0 + int v`` sampled ``per_interval`` times on every interval of ``t``, ``v`` linear
    between its samples (so ``x`` is an exact quadratic there): an actuator's angle (``phi``
    or ``th1``) under the handed-out rates ``u[:, 0]`` or ``u[:, 1]``, its turns countable."""
    h = np.diff(t)[:, None]
    s = np.linspace(0.0, 1.0, per_interval + 1)[None, :-1]
    a, b = v[:-1, None], v[1:, None]
    knots = x0 + np.concatenate([[0.0], np.cumsum(np.diff(t) * (v[1:] + v[:-1]) / 2.0)])
    inner = knots[:-1, None] + h * (a * s + (b - a) * s * s / 2.0)
    return np.append(inner.ravel(), knots[-1])


def replay_zoh(robot: Robot, t: np.ndarray, u: np.ndarray,
               q0: np.ndarray) -> tuple[np.ndarray, float]:
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


def replay_quintic(robot: Robot, t: np.ndarray, x: np.ndarray, v: np.ndarray, a: np.ndarray,
                   q0: np.ndarray) -> tuple[np.ndarray, float]:
    """The original model driven by the derivative of the quintic Hermite interpolant of
    positions ``x``, velocities ``v`` and accelerations ``a`` at ``t``
    (joint_trajectory_controller's rule when all three are given), built by scipy's
    ``BPoly.from_derivatives``."""
    rates = quintic_rates(t, x, v, a)
    return _replay(robot, t, q0, lambda k, s: rates(t[k] + s * (t[k + 1] - t[k])))


def quintic_rates(t: np.ndarray, x: np.ndarray, v: np.ndarray, a: np.ndarray):
    """``u(t)`` (and, with ``order``, its derivatives) of the quintic Hermite interpolant,
    from scipy's ``BPoly.from_derivatives`` (independent of the planner's basis)."""
    from scipy.interpolate import BPoly

    polys = [BPoly.from_derivatives(t, np.stack([x[:, c], v[:, c], a[:, c]], axis=1))
             for c in range(x.shape[1])]
    # each derivative built once: a replay evaluates the rates some 20,000 times, and building
    # the derivative polynomial at every call was most of a replay's time
    derivatives: dict[int, list[BPoly]] = {}

    def rates(tt, order=0):
        if order not in derivatives:
            derivatives[order] = [bp.derivative(order + 1) for bp in polys]
        return np.stack([np.asarray(d(tt)) for d in derivatives[order]], axis=-1)
    return rates


def linear_states(robot: Robot, t: np.ndarray, u: np.ndarray, q0: np.ndarray,
                  per: int = 8) -> np.ndarray:
    """The original model under linear interpolation of ``u`` over ``t`` from ``q0``,
    piece by piece: ``q0`` and the states at ``per`` points of every interval (after the
    first), for indicators measured densely."""
    out, q = [np.asarray(q0, float)], np.asarray(q0, float)
    for k in range(t.size - 1):
        a, b = t[k], t[k + 1]
        if b <= a:
            continue  # a repeated time: the jump between its two values
        h = b - a
        sol = solve_ivp(_rhs(robot, lambda tt, k=k, a=a, h=h: u[k] + (tt - a) / h
                             * (u[k + 1] - u[k])), (a, b), q, method="DOP853", rtol=RTOL,
                        atol=ATOL, t_eval=np.linspace(a, b, per + 1)[1:])
        assert sol.success, sol.message
        out.extend(sol.y.T)
        q = sol.y[:, -1]
    return np.array(out)


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


def replay_linear_rk4(robot: Robot, t: np.ndarray, u: np.ndarray, q0: np.ndarray,
                      substeps: int = 4) -> tuple[np.ndarray, float]:
    """:func:`replay_linear` by classical RK4, ``substeps`` steps per sample interval (for
    paths of many thousand samples, where a scipy solve per interval takes seconds): the
    inputs are linear within each interval and the model smooth, so on intervals of a
    millisecond the error is far below 1e-10 rad. Returns the final state and the smallest
    region margin at the samples."""
    K = np.array(robot.gains)
    m = np.array(robot.exponents, float)

    def rhs(q: np.ndarray, w: np.ndarray) -> np.ndarray:
        return np.concatenate([[w[0], w[1]], K * np.cos(q[1:-1]) ** m * w[0]])
    q = np.asarray(q0, float).copy()
    margin = math.inf
    for k in range(t.size - 1):
        h = (t[k + 1] - t[k]) / substeps
        if h <= 0.0:
            continue
        du = (u[k + 1] - u[k]) / substeps
        for s in range(substeps):
            w0 = u[k] + s * du
            w1 = w0 + 0.5 * du
            w2 = w0 + du
            k1 = rhs(q, w0)
            k2 = rhs(q + 0.5 * h * k1, w1)
            k3 = rhs(q + 0.5 * h * k2, w1)
            k4 = rhs(q + h * k3, w2)
            q = q + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        th = q[1:]
        margin = min(margin, float(np.min(np.minimum(th, HALF_PI - th))))
    return q, margin
