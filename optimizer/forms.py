"""Forms of actuator rates linear in their parameters, their replay and their correction.

A form is a rule that turns parameters (samples, or positions, velocities and accelerations)
into rates ``u(t)``: linear interpolation, zero-order hold, the derivative of a cubic or a
quintic Hermite interpolant (:class:`Form`; the handed-out forms of a plan,
:mod:`optimizer.execution`).

Correction
----------
Every form is linear in its parameters ``p`` (sample values, or positions, velocities and
accelerations):
``u(t) = sum_j B_j(t) p_j``. The linear and held forms start from the L2 projection of the
exact rates onto their functions (point samples of a sharp rate peak, near a joint at the
region's edge, miss its integral: the projection keeps it; measured end errors of the
projection alone: 1e-16 to 1e-5 rad for the linear form at 201 samples, 1e-6 to 1e-3 rad for
a 10 ms hold, against up to 2e-2 and 6e-2 rad for plain samples). Gauss-Newton steps of least L2
norm (the diagonal of the basis' Gram matrix weighs the parameters; a rate with a limit
changes in proportion to its headroom) then cancel the end error of the original model: the
residual from :func:`~optimizer.verify.integrate_cascade` (Chebyshev quadrature on panels
between the form's knots, error estimate ~1e-13 rad), the Jacobian
``int Phi(T, s) G(q(s)) B_j(s) ds`` from the adjoint of the linearised cascade, integrated by
the trapezoidal rule on a grid of three Gauss-Legendre nodes per interval (the Jacobian only
steers: the residual is exact). Zero to three steps reach :data:`CORRECTION_TARGET`. The
parameters kept are the best met, those whose path stays inside the region first: a step
can bring the end closer along a path that leaves it.

The region is checked on the same integration at the knots and three interior points of every
interval; the reported ``margin`` is the smallest distance of ``th_1..th_n`` to the region's
bounds there.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .dynamics import joint_rate
from .errors import NumericalError
from .model import Robot
from .region import Region
from .verify import CASCADE_NAME, Replay, integrate_cascade

#: The correction stops once the executed form ends this close to the goal (rad)...
CORRECTION_TARGET = 1e-9
#: ... or after this many steps.
MAX_CORRECTIONS = 6
#: From parameters that already end within :data:`EXECUTION_TOLERANCE`, a step that changes
#: a parameter by more than this fraction of the largest is not taken (the best parameters
#: met stay; a held form's first miss, 1e-4 rad, may need larger ones). A miss along the end map's weakest directions (from 6
#: joints its singular values reach 1e-11 of the largest) asks for steps many times the rates
#: themselves: from 1.7e-7 rad off, a 6-joint plan's linear form took a first step of 7 times
#: its largest rate and ended on the goal 6 steps later along a path with 16 more reversals
#: and 31 deg more deviation. On 90 generated goals of 3 to 8 joints the linear form needed a
#: step 7 times, each from 1.2e-7 to 2.2e-7 rad off (within the tolerance), each first step
#: 1.7 to 775 times the largest rate.
STEP_LIMIT = 1e-2
#: From any parameters, a step that changes a parameter by more than this fraction of the
#: largest is not taken, and the correction ends with the best parameters met: a form the
#: model's linearisation says needs rates that large is not the plan's path (a linear form is
#: then made denser, a held one refused), and replaying such rates was the cost of these
#: failures (the cascade quadrature on rates that swing by tens of times their size: 0.2-0.75 s
#: a replay on 8 joints). Measured on 72 plans of 3 to 8 joints under jerk limits, controller
#: periods and JointTrajectory forms (generated goals of a seed the benchmark does not use):
#: of the corrections that reached the goal, one took a step above this (1.9 times its largest
#: rate, on 6 joints: the denser form holds the plan then); of the 27 that did not reach it,
#: 22 began with a step of 1.5 to 470 times the largest rate, and each replayed up to six
#: such steps before giving up.
MAX_STEP = 1.0
#: A replay that ends this many times farther from the goal than the best met ends the
#: correction: the linearisation no longer describes the map (a step of a tenth of the rates
#: took a 5-joint form from 2.5e-5 rad off to 0.12 rad, and its next five steps converged onto
#: a path outside the region).
DIVERGENCE = 10.0
#: A handed-out form that ends farther than this from the goal (rad) is not a plan.
EXECUTION_TOLERANCE = 1e-6
#: Chebyshev nodes per cascade panel for the forms' replays: their inputs are polynomials of
#: degree <= 2 between knots, so the integrands are smooth on short panels.
REPLAY_NODES = 12
#: Gauss-Legendre nodes per interval of the Jacobian's quadrature (and of the region check).
GAUSS = 3
#: The handed-out forms may exceed a limit by this fraction: rounding (the time law plans 1e-3
#: inside the limits, and a correction of 1e-9 of the rates stays there). A form whose
#: correction takes it past a limit is made denser instead (its correction is then smaller):
#: with 1e-2 a 4-joint penalty plan under a jerk limit handed out slopes 0.19 % above
#: max_du1 (its 247-sample form, 1.3e-3 rad off before the correction); at 401 samples it
#: keeps the limit.
LIMIT_TOLERANCE = 1e-6


# ---------------------------------------------------------------------- forms
@dataclass(frozen=True)
class Form:
    """Inputs ``u(t)`` on ``[0, T]`` that are linear in a parameter array ``p`` (m, 2).

    On interval ``k`` (``knots[k] <= t <= knots[k+1]``, ``s = (t - knots[k]) / h_k``),
    ``u_c(t) = sum_r shape_r(s) * scale[k, r] * p[idx[k, r], c]`` for both inputs ``c``.

    Attributes
    ----------
    rule : {"linear", "zoh", "cubic_hermite", "quintic_hermite"}
    knots : ndarray (K+1,)
        Interval ends, strictly increasing, ``knots[0] = 0``, ``knots[-1] = T``.
    idx : ndarray (K, R) of int
    scale : ndarray (K, R)
    free : ndarray (m,) of bool
        Parameter rows the correction may change.
    """

    rule: str
    knots: np.ndarray
    idx: np.ndarray
    scale: np.ndarray
    free: np.ndarray

    @property
    def T(self) -> float:
        return float(self.knots[-1])

    def shapes(self, s: np.ndarray) -> np.ndarray:
        """Shape functions at local coordinates ``s`` (M,), shape (M, R)."""
        if self.rule == "zoh":
            return np.ones((s.size, 1))
        if self.rule == "linear":
            return np.column_stack([1.0 - s, s])
        return np.polynomial.polynomial.polyval(s, SHAPE_COEFFICIENTS[self.rule].T).T

    def derivative_coefficients(self, p: np.ndarray, order: int = 0) -> np.ndarray:
        """``d^order u / dt^order`` on each interval as a polynomial in the local ``s``,
        coefficients by ascending power, shape (K, 2, D) (the Hermite rules only)."""
        C = SHAPE_COEFFICIENTS[self.rule]                         # (R, D)
        h = np.diff(self.knots)
        coef = np.einsum("kr,krc,rd->kcd", self.scale, p[self.idx], C)
        for _ in range(order):
            coef = np.polynomial.polynomial.polyder(coef, axis=2) / h[:, None, None]
        return coef

    def local(self, k: np.ndarray, s: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``u`` on intervals ``k`` at local coordinates ``s``, shape (M, 2)."""
        w = self.shapes(s) * self.scale[k]
        return np.einsum("mr,mrc->mc", w, p[self.idx[k]])

    def u(self, p: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``u(t)``, shape (M, 2) (right-continuous at the knots, the last interval closed)."""
        t = np.atleast_1d(np.asarray(t, float))
        k = np.clip(np.searchsorted(self.knots, t, side="right") - 1, 0, self.knots.size - 2)
        if self.rule == "zoh":  # the replays call this often: the two plain forms directly
            return p[self.idx[k, 0]]
        s = (t - self.knots[k]) / (self.knots[k + 1] - self.knots[k])
        if self.rule == "linear":
            a = p[self.idx[k, 0]]
            return a + s[:, None] * (p[self.idx[k, 1]] - a)
        return self.local(k, s, p)

    def gram_diagonal(self, rows: int) -> np.ndarray:
        """``int B_j(t)^2 dt`` per parameter row (the L2 weight of a change of row ``j``)."""
        g, w = gauss_legendre(GAUSS + 1)
        sq = (self.shapes(g) ** 2).T @ w                      # (R,)
        h = np.diff(self.knots)
        return scatter_rows(self.idx, h[:, None] * self.scale ** 2 * sq[None, :], rows)


#: The shape functions of the Hermite rules, polynomials in the local ``s`` (ascending
#: powers): the derivatives ``dH/ds`` of the Hermite bases (cubic: values and first
#: derivatives at both ends; quintic: values, first and second derivatives), in the order of
#: the parameters (positions, velocities, accelerations; left end first).
SHAPE_COEFFICIENTS = {
    "cubic_hermite": np.array([[0.0, -6.0, 6.0], [0.0, 6.0, -6.0],
                               [1.0, -4.0, 3.0], [0.0, -2.0, 3.0]]),
    "quintic_hermite": np.array([
        [0.0, 0.0, -30.0, 60.0, -30.0],           # H0 = 1 - 10 s^3 + 15 s^4 - 6 s^5
        [0.0, 0.0, 30.0, -60.0, 30.0],            # H1 = 10 s^3 - 15 s^4 + 6 s^5
        [1.0, 0.0, -18.0, 32.0, -15.0],           # H2 = s - 6 s^3 + 8 s^4 - 3 s^5
        [0.0, 0.0, -12.0, 28.0, -15.0],           # H3 = -4 s^3 + 7 s^4 - 3 s^5
        [0.0, 1.0, -4.5, 6.0, -2.5],              # H4 = (s^2 - 3 s^3 + 3 s^4 - s^5) / 2
        [0.0, 0.0, 1.5, -4.0, 2.5]]),             # H5 = (s^3 - 2 s^4 + s^5) / 2
}


def scatter_rows(index: np.ndarray, values: np.ndarray, rows: int) -> np.ndarray:
    """``out[index[i]] += values[i]`` over the leading axes of ``index`` (the trailing axes
    of ``values`` are kept): ``np.bincount``, several times faster than ``np.add.at``."""
    idx = np.asarray(index).ravel()
    vals = np.asarray(values, float).reshape(idx.size, -1)
    out = np.empty((rows, vals.shape[1]))
    for c in range(vals.shape[1]):
        out[:, c] = np.bincount(idx, weights=vals[:, c], minlength=rows)
    return out.reshape((rows,) + np.shape(values)[np.ndim(index):])


@functools.lru_cache(maxsize=8)
def gauss_legendre(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on [0, 1]."""
    x, w = np.polynomial.legendre.leggauss(k)
    return 0.5 * (x + 1.0), 0.5 * w


def _intervals_of(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct knots of a nondecreasing time list and, per interval, the row of its left
    end (the last copy of a repeated time: the value after the jump)."""
    nxt = np.nonzero(np.diff(times) > 0.0)[0]           # row j starts an interval to j + 1
    knots = np.concatenate([times[nxt], times[-1:]])
    return knots, nxt


def linear_form(times: np.ndarray, held: np.ndarray | None = None) -> Form:
    """Linear interpolation of samples at ``times`` (repeated times: jumps); the rows
    ``held`` (indices) keep their values in the correction (the rests: zero rates)."""
    knots, left = _intervals_of(times)
    idx = np.column_stack([left, left + 1])
    free = np.ones(times.size, bool)
    if held is not None:
        free[np.asarray(held, np.intp)] = False
    return Form("linear", knots, idx, np.ones(idx.shape), free)


def zoh_form(times: np.ndarray) -> Form:
    """Zero-order hold of ``u[k]`` on ``[t_k, t_{k+1})`` (the last row is not used)."""
    free = np.ones(times.size, bool)
    free[-1] = False
    return Form("zoh", times.copy(), np.arange(times.size - 1)[:, None],
                np.ones((times.size - 1, 1)), free)


def hermite_form(times: np.ndarray, quintic: bool = False) -> Form:
    """Derivative of the Hermite interpolant at ``times`` (strictly increasing) of positions
    and velocities (cubic), or positions, velocities and accelerations (``quintic``);
    ``p = [positions (m rows); velocities (m rows); accelerations (m rows, quintic)]``. The
    end positions (start and goal), velocities (zero: rest to rest) and accelerations are
    held."""
    m = times.size
    h = np.diff(times)
    k = np.arange(m - 1)
    one = np.ones(m - 1)
    blocks = 3 if quintic else 2
    idx = np.column_stack([j * m + k + e for j in range(blocks) for e in (0, 1)])
    scale = np.column_stack([f for f in (1.0 / h, one, h)[:blocks] for _ in (0, 1)])
    free = np.ones(blocks * m, bool)
    free[[j * m + e for j in range(blocks) for e in (0, m - 1)]] = False
    return Form("quintic_hermite" if quintic else "cubic_hermite", times.copy(), idx, scale,
                free)


def dense_times(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The form's times and three points inside every interval (where the indicators and the
    region are measured), and the positions of ``times`` in it."""
    h = np.diff(times)
    inner = (times[:-1, None] + h[:, None] * np.array([0.25, 0.5, 0.75])).ravel()
    dense = np.concatenate([times[:-1, None],
                            inner.reshape(-1, 3)], axis=1).ravel()
    dense = np.append(dense, times[-1])
    return dense, np.arange(times.size) * 4


# ---------------------------------------------------------------------- replay, correction
@dataclass(frozen=True)
class ExecutionCheck:
    """The original model integrated under a handed-out form, by its rule.

    Attributes
    ----------
    rule : str
    terminal_error : float
        ``max_i |th_i(T) - goal_i|`` (rad).
    phi_error : float
        ``|phi(T) - phi(T) of the plan|`` (rad).
    margin : float
        Smallest distance of ``th_1..th_n`` to the region's bounds at the knots and three
        interior points of every interval (rad; negative: outside).
    singular : bool
        A joint left (0, pi/2) during the integration.
    initial_terminal_error : float
        The same error before any correction (from the start: the L2 projection of the exact
        rates; for the JointTrajectory form, the executable path's points).
    corrections : int
        Correction steps taken.
    errors : tuple of float
        ``max |q(T) - target|`` (phi included) before each step and after the last.
    reversals : tuple of (int, int) or None
        Direction changes of ``phi`` and ``th1`` on this form's replay (its samples and
        three points inside every interval; :mod:`optimizer.indicators`' dead band).
    deviation : float or None
        Largest joint-space distance (rad) of that replay from the straight segment.
    d_a : float or None
        Largest distance (rad) of its ``th1(t)`` from the straight line in time.
    error_estimate : float or None
        The cascade quadrature's error estimate (rad).
    integrator : str
    final : tuple of float
    """

    rule: str
    terminal_error: float
    phi_error: float
    margin: float
    singular: bool
    initial_terminal_error: float
    corrections: int
    error_estimate: float | None
    integrator: str
    final: tuple[float, ...]
    errors: tuple[float, ...] = ()
    reversals: tuple[int, int] | None = None
    deviation: float | None = None
    d_a: float | None = None

    @property
    def ok(self) -> bool:
        return (self.terminal_error <= EXECUTION_TOLERANCE and self.margin > 0.0
                and not self.singular)

    def as_dict(self) -> dict[str, Any]:
        return {"rule": self.rule, "terminal_error": self.terminal_error,
                "phi_error": self.phi_error, "margin": self.margin, "singular": self.singular,
                "initial_terminal_error": self.initial_terminal_error,
                "corrections": self.corrections, "error_estimate": self.error_estimate,
                "integrator": f"{self.integrator} on the original model",
                "final": list(self.final),
                "reversals": (None if self.reversals is None else
                              {"phi": self.reversals[0], "th1": self.reversals[1]}),
                "deviation": self.deviation, "d_a": self.d_a}


def replay_form(robot: Robot, form: Form, p: np.ndarray, q0: np.ndarray,
                t_eval: np.ndarray) -> Replay:
    """The original model under ``form`` with parameters ``p`` (cascade quadrature, panels
    between the form's knots)."""
    K = form.knots.size - 1
    # up to 16 panels a knot: a 5-joint JointTrajectory form of fast rates (accelerations of
    # thousands of rad/s^2) stopped at 4 a knot 1.5e-8 rad above the 1e-8 target, and its
    # plan was refused; the panels cost time only where they are needed
    return integrate_cascade(robot, lambda t: form.u(p, t), q0, form.T, t_eval,
                             kinks(form, p), nodes=REPLAY_NODES, initial_panels=1,
                             max_panels=16 * K + 2048)


def kinks(form: Form, p: np.ndarray) -> np.ndarray:
    """The knots where ``u`` under ``p`` is not smooth: the panels of a replay need start only
    there. For the linear rule a knot where ``u`` is continuous with the same slope on both
    sides (to rounding: the rows of a piecewise-constant plan between its breaks) is not one;
    the integrand is still evaluated exactly, so this only saves panels."""
    knots = form.knots
    if form.rule != "linear" or knots.size <= 2:
        return knots
    a, b = p[form.idx[:, 0]], p[form.idx[:, 1]]
    h = np.diff(knots)
    tol = 1e-12 * (1.0 + float(np.max(np.abs(p))))
    jump = np.max(np.abs(b[:-1] - a[1:]), axis=1)
    bend = np.max(np.abs((b[:-1] - a[:-1]) / h[:-1, None] - (b[1:] - a[1:]) / h[1:, None]),
                  axis=1) * np.minimum(h[:-1], h[1:])
    smooth = (jump <= tol) & (bend <= tol)
    return np.concatenate([knots[:1], knots[1:-1][~smooth], knots[-1:]])


def _jacobian(robot: Robot, form: Form, p: np.ndarray, q: np.ndarray, rows: int) -> np.ndarray:
    """``d q(T) / d p``, shape (n+1, rows, 2), from the adjoint of the linearised model.

    ``q`` holds the states on the grid of :func:`_grid` (per interval: its start, the Gauss
    nodes, its end).
    """
    n = robot.n
    K = form.knots.size - 1
    g, wg = gauss_legendre(GAUSS)
    s = np.concatenate([[0.0], g, [1.0]])
    h = np.diff(form.knots)
    kk = np.repeat(np.arange(K), s.size)
    u1 = form.local(kk, np.tile(s, K), p)[:, 0]
    tt = (form.knots[:-1, None] + h[:, None] * s).ravel()
    Kg = np.asarray(robot.gains, float)
    m = np.asarray(robot.exponents, float)
    th = q[:, 1:n]                                   # th_1..th_{n-1}: drive th_2..th_n
    c, sn = np.cos(th), np.sin(th)
    # A[j, j-1] = d th_j' / d th_{j-1} (j = 2..n), the only nonzero entries of d f / d q
    a = -Kg * m * c ** (m - 1.0) * sn * u1[:, None]  # (M, n-1), column j-2
    dt = np.diff(tt)
    M = tt.size
    lam = np.zeros((M, n + 1, n + 1))                # lam[t, i, j] = d q_i(T) / d q_j(t)
    lam[:, np.arange(n + 1), np.arange(n + 1)] = 1.0
    for j in range(n - 1, 0, -1):                    # th_j drives th_{j+1}: descend the chain
        f = lam[:, :, j + 1] * a[:, j - 1][:, None]  # (M, n+1)
        seg = 0.5 * (f[1:] + f[:-1]) * dt[:, None]
        tail = np.concatenate([np.cumsum(seg[::-1], axis=0)[::-1], np.zeros((1, n + 1))])
        lam[:, :, j] += tail
    # F_c = lam G(q)[:, c]: u2 drives th1; u1 drives phi and th_j with K_j cos(th_{j-1})^m_j
    F1 = lam[:, :, 1]
    g1 = np.stack([joint_rate(robot.gains, robot.exponents, i, th[:, i - 2], 1.0)
                   for i in range(2, n + 1)], axis=1)   # th_i' per unit u1 (i = 2..n)
    F0 = lam[:, :, 0] + np.einsum("mij,mj->mi", lam[:, :, 2:], g1)
    inner = np.arange(1, 1 + GAUSS)
    F = np.stack([F0, F1], axis=-1).reshape(K, s.size, n + 1, 2)[:, inner]   # (K, G, n+1, 2)
    W = form.shapes(g) * wg[:, None]                 # (G, R)
    contrib = np.einsum("kgic,gr,kr->krci", F, W, form.scale * h[:, None])   # (K, R, 2, n+1)
    return scatter_rows(form.idx, contrib, rows).transpose(2, 0, 1)


def _grid(form: Form) -> np.ndarray:
    """Per interval: its start, :data:`GAUSS` Gauss nodes, its end (the Jacobian's grid)."""
    g, _ = gauss_legendre(GAUSS)
    s = np.concatenate([[0.0], g, [1.0]])
    return (form.knots[:-1, None] + np.diff(form.knots)[:, None] * s).ravel()


def correct(robot: Robot, form: Form, p0: np.ndarray, q0: np.ndarray, target: np.ndarray,
            region: Region, t_out: np.ndarray,
            limits: tuple[float | None, float | None] = (None, None),
            initial: Replay | None = None, accept_first: float = 0.0
            ) -> tuple[np.ndarray, np.ndarray, ExecutionCheck]:
    """Correct the parameters of ``form`` until the original model under it ends at ``target``.

    Parameters
    ----------
    p0 : ndarray (m, 2)
        Initial parameters (the exact plan sampled by the form's rule).
    q0, target : ndarray (n+1,)
        Start and wanted end ``[phi, th_1..th_n]``.
    region : Region
        For the margin.
    t_out : ndarray
        Times at which the states are returned.
    limits : (float or None, float or None)
        Bounds of ``|u1|, |u2|`` when the parameters are rates (the linear and the held
        forms): the start is clipped to them and a step changes a rate in proportion to its
        headroom (none at the bound), so the corrected rates stay within them.
    initial : Replay, optional
        The original model under ``form`` with ``p0`` (within ``limits``), its last
        ``len(t_out)`` rows at ``t_out``: the first replay, not integrated again (its rows
        before those count for the margin).
    accept_first : float
        The start is kept, with no step, when it ends this close to the target (rad): for a
        form that holds the plan's rates exactly, a step that buys a few 1e-8 rad of end error
        can move the path by a tenth of a degree (measured: a 6-joint shooting plan, 2.4e-8
        -> 1.2e-8 rad, deviation +0.12 deg).

    Returns
    -------
    p : ndarray (m, 2)
        The corrected parameters (the best ones met).
    q : ndarray (len(t_out), n+1)
        States of the original model under them at ``t_out``.
    check : ExecutionCheck
    """
    # the Jacobian's grid, built when a step needs it (a given first replay on the goal
    # needs none)
    grid: np.ndarray | None = None

    def replay_on_grid(p: np.ndarray) -> tuple[Replay, int]:
        """The replay of ``p`` on the grid, then ``t_out``; and the grid's size."""
        nonlocal grid
        if grid is None:
            grid = _grid(form)
        return replay_form(robot, form, p, q0, np.concatenate([grid, t_out])), grid.size

    rows = p0.shape[0]
    p = p0.copy()
    lim = np.array([np.inf if x is None else float(x) for x in limits])
    bounded = np.isfinite(lim)
    if bounded.any():
        p = np.clip(p, -lim, lim)
        if not np.array_equal(p, p0):  # the given replay is of other rates
            initial = None
    lo, hi = np.asarray(region.lower, float), np.asarray(region.upper, float)

    def outside(r: Replay) -> bool:
        th = r.q[:, 1:]
        return bool(r.singular) or not float(np.min(np.minimum(th - lo, hi - th))) > 0.0

    # the best parameters met: inside the region first, then the smallest end error (a step
    # can bring the end closer along a path that leaves the region: it is not kept)
    best: tuple[tuple[bool, float], np.ndarray, Replay, int] | None = None
    first_error = math.inf
    steps = 0
    errors: list[float] = []
    for k in range(MAX_CORRECTIONS + 1):
        given = initial if k == 0 else None
        if given is not None:
            rep, off = given, given.q.shape[0] - t_out.size
        else:
            rep, off = replay_on_grid(p)
        if not rep.success:
            break
        r = rep.final - target
        err = float(np.max(np.abs(r)))
        if k == 0:
            first_error = float(np.max(np.abs(r[1:])))
        diverged = bool(errors) and err > DIVERGENCE * min(errors)
        errors.append(err)
        key = (outside(rep), err)
        if best is None or key < best[0]:
            best, steps = (key, p, rep, off), k
        if (err <= CORRECTION_TARGET or k == MAX_CORRECTIONS or diverged
                or (k == 0 and err <= accept_first)):
            break
        if given is not None:  # the given first replay has no states on the Jacobian's grid
            rep, off = replay_on_grid(p)
            if not rep.success:
                break
        J = _jacobian(robot, form, p, rep.q[:off], rows)         # (n+1, rows, 2)
        gram = form.gram_diagonal(rows)
        free = form.free & (gram > 0.0)
        sw = np.zeros(rows)
        sw[free] = 1.0 / np.sqrt(gram[free])             # least L2 norm of the change of u
        scale = np.repeat(sw[:, None], 2, axis=1)
        if bounded.any():
            head = np.clip((lim - np.abs(p)) / np.where(bounded, lim, 1.0), 0.0, 1.0)
            scale = scale * np.where(bounded, head, 1.0)
        Js = (J * scale[None]).reshape(J.shape[0], -1)
        step = np.linalg.lstsq(Js, r, rcond=1e-12)[0].reshape(rows, 2) * scale
        size = float(np.max(np.abs(step))) / max(float(np.max(np.abs(p))), np.finfo(float).tiny)
        if size > MAX_STEP or (err <= EXECUTION_TOLERANCE and size > STEP_LIMIT):
            break  # along a direction the end barely moves in (MAX_STEP, STEP_LIMIT)
        p = p - step
    if best is None:
        raise NumericalError(f"the {form.rule} form could not be integrated: {rep.message}",
                             diagnostics={"rule": form.rule})
    _, p, rep, off = best
    th = rep.q[:, 1:]
    margin = float(np.min(np.minimum(th - lo, hi - th)))
    check = ExecutionCheck(
        rule=form.rule, terminal_error=float(np.max(np.abs(rep.final[1:] - target[1:]))),
        phi_error=abs(float(rep.final[0] - target[0])), margin=margin,
        singular=bool(rep.singular), initial_terminal_error=first_error, corrections=steps,
        errors=tuple(errors),
        error_estimate=rep.error_estimate, integrator=rep.integrator or CASCADE_NAME,
        final=tuple(float(x) for x in rep.final))
    return p, rep.q[off:], check
