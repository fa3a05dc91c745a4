"""What a controller executes: the handed-out forms of a plan, corrected and verified.

A plan is proved from its exact input segments, but a controller runs samples under a rule.
Replaying a plan's plain samples misses the goal by 1e-3 to 1e-1 rad (linear interpolation
or zero-order hold of smooth inputs is not the inputs), so each handed-out form is made the
truth: its sample values are corrected until the ORIGINAL model integrated under the form's
own interpolation rule reaches the goal, and the states handed out are that integration's.

Forms (documented for users in ``docs/execution.md``)
-----------------------------------------------------
``linear``
    The default ``path``: rates ``u`` at times ``t``, linearly interpolated. Every time where the
    plan's inputs may jump (an inner break of its input schedule) is in ``t`` twice, first with
    the value just before the break, then with the value just after: a controller that
    interpolates linearly between consecutive samples then reproduces the jump (the
    zero-length interval between the two copies is skipped).
``zoh``
    With ``controller_period``: ``t = k * period`` (the last point ``T``; when ``T`` is not a
    multiple the last interval is shorter) and ``u[k]`` held constant on ``[t_k, t_{k+1})``
    (the last row repeats the last interval's rate; nothing is held after ``T``).
``cubic_hermite``
    The ROS ``trajectory_msgs/JointTrajectory`` form: positions ``(phi, th1)`` and velocities
    ``(u1, u2)`` at points; between points the position is the cubic Hermite interpolant of
    both ends' positions and velocities (what ``joint_trajectory_controller`` does), so the
    rates executed are its derivative.

Correction
----------
Every form is linear in its parameters ``p`` (sample values, or positions and velocities):
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

import dataclasses
import functools
import math
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .chained_form import chained_form
from .dynamics import joint_rate
from .errors import InfeasibleError, InvalidRequestError, NumericalError
from .indicators import Indicators, compute_indicators
from .model import Robot
from .problem import MAX_SAMPLES, PlanRequest
from .region import Region
from .paths import SampledPath
from .verify import CASCADE_NAME, Replay, integrate, integrate_cascade

#: The correction stops once the executed form ends this close to the goal (rad)...
CORRECTION_TARGET = 1e-9
#: ... or after this many steps.
MAX_CORRECTIONS = 6
#: A handed-out form that ends farther than this from the goal (rad) is not a plan.
EXECUTION_TOLERANCE = 1e-6
#: Chebyshev nodes per cascade panel for the forms' replays: their inputs are polynomials of
#: degree <= 2 between knots, so the integrands are smooth on short panels.
REPLAY_NODES = 12
#: Sample times closer than this fraction of ``T`` to a break are moved onto it.
SNAP = 1e-9
#: Gauss-Legendre nodes per interval of the Jacobian's quadrature (and of the region check).
GAUSS = 3

Uexact = Callable[[np.ndarray], np.ndarray]


# ---------------------------------------------------------------------- forms
@dataclass(frozen=True)
class Form:
    """Inputs ``u(t)`` on ``[0, T]`` that are linear in a parameter array ``p`` (m, 2).

    On interval ``k`` (``knots[k] <= t <= knots[k+1]``, ``s = (t - knots[k]) / h_k``),
    ``u_c(t) = sum_r shape_r(s) * scale[k, r] * p[idx[k, r], c]`` for both inputs ``c``.

    Attributes
    ----------
    rule : {"linear", "zoh", "cubic_hermite"}
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
        d = 6.0 * s * s - 6.0 * s  # derivatives of the cubic Hermite basis h00, h01, h10, h11
        return np.column_stack([d, -d, 3.0 * s * s - 4.0 * s + 1.0, 3.0 * s * s - 2.0 * s])

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
        g, w = _gauss(GAUSS + 1)
        sq = (self.shapes(g) ** 2).T @ w                      # (R,)
        h = np.diff(self.knots)
        return _scatter(self.idx, h[:, None] * self.scale ** 2 * sq[None, :], rows)


def _scatter(index: np.ndarray, values: np.ndarray, rows: int) -> np.ndarray:
    """``out[index[i]] += values[i]`` over the leading axes of ``index`` (the trailing axes
    of ``values`` are kept): ``np.bincount``, several times faster than ``np.add.at``."""
    idx = np.asarray(index).ravel()
    vals = np.asarray(values, float).reshape(idx.size, -1)
    out = np.empty((rows, vals.shape[1]))
    for c in range(vals.shape[1]):
        out[:, c] = np.bincount(idx, weights=vals[:, c], minlength=rows)
    return out.reshape((rows,) + np.shape(values)[np.ndim(index):])


@functools.lru_cache(maxsize=8)
def _gauss(k: int) -> tuple[np.ndarray, np.ndarray]:
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


def hermite_form(times: np.ndarray) -> Form:
    """Derivative of the cubic Hermite interpolant of positions and velocities at ``times``
    (strictly increasing); ``p = [positions (m rows); velocities (m rows)]``. The end
    positions (start and goal) and the end velocities (zero: rest to rest) are held."""
    m = times.size
    h = np.diff(times)
    k = np.arange(m - 1)
    idx = np.column_stack([k, k + 1, m + k, m + k + 1])
    scale = np.column_stack([1.0 / h, 1.0 / h, np.ones(m - 1), np.ones(m - 1)])
    free = np.ones(2 * m, bool)
    free[[0, m - 1, m, 2 * m - 1]] = False
    return Form("cubic_hermite", times.copy(), idx, scale, free)


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
                "final": list(self.final)}


def replay_form(robot: Robot, form: Form, p: np.ndarray, q0: np.ndarray,
                t_eval: np.ndarray) -> Replay:
    """The original model under ``form`` with parameters ``p`` (cascade quadrature, panels
    between the form's knots)."""
    K = form.knots.size - 1
    return integrate_cascade(robot, lambda t: form.u(p, t), q0, form.T, t_eval,
                             kinks(form, p), nodes=REPLAY_NODES, initial_panels=1,
                             max_panels=4 * K + 2048)


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
    g, wg = _gauss(GAUSS)
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
    return _scatter(form.idx, contrib, rows).transpose(2, 0, 1)


def _grid(form: Form) -> np.ndarray:
    """Per interval: its start, :data:`GAUSS` Gauss nodes, its end (the Jacobian's grid)."""
    g, _ = _gauss(GAUSS)
    s = np.concatenate([[0.0], g, [1.0]])
    return (form.knots[:-1, None] + np.diff(form.knots)[:, None] * s).ravel()


def correct(robot: Robot, form: Form, p0: np.ndarray, q0: np.ndarray, target: np.ndarray,
            region: Region, t_out: np.ndarray,
            limits: tuple[float | None, float | None] = (None, None),
            initial: Replay | None = None
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
        errors.append(err)
        key = (outside(rep), err)
        if best is None or key < best[0]:
            best, steps = (key, p, rep, off), k
        if err <= CORRECTION_TARGET or k == MAX_CORRECTIONS:
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
        y = np.linalg.lstsq(Js, r, rcond=1e-12)[0]
        p = p - y.reshape(rows, 2) * scale
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


# ---------------------------------------------------------------------- sample grids
def _snap(times: np.ndarray, breaks: np.ndarray, tol: float) -> np.ndarray:
    """``times`` with every time within ``tol`` of a break moved onto it exactly."""
    if breaks.size == 0:
        return times
    j = np.searchsorted(breaks, times)
    hi = breaks[np.minimum(j, breaks.size - 1)]
    lo = breaks[np.maximum(j - 1, 0)]
    near = np.where(np.abs(hi - times) <= np.abs(times - lo), hi, lo)
    out = times.copy()
    close = np.abs(near - times) <= tol
    out[close] = near[close]
    return out


def linear_times(T: float, samples: int, stops: np.ndarray) -> np.ndarray:
    """Times of the linear form: ``samples`` evenly spaced, those within a quarter of the
    spacing of an inner stop moved onto it, and every inner stop once (the rates are
    continuous: no time is repeated)."""
    inner = np.asarray(stops, float)[1:-1]
    # a sample closer to a stop than a quarter of the spacing moves onto it: no sliver
    # intervals next to a stop, and a stop that falls on a sample (up to rounding) is exact
    t = _snap(np.linspace(0.0, T, int(samples)), inner, 0.25 * T / (int(samples) - 1))
    t[0], t[-1] = 0.0, T
    return np.unique(np.concatenate([t, inner]))


def period_times(T: float, period: float, breaks: np.ndarray) -> np.ndarray:
    """``k * period`` for ``k * period < T`` and then ``T`` (a last interval shorter than
    ``SNAP * T`` is merged with the one before); grid points within ``SNAP * T`` of a break
    are moved onto it."""
    k = int(math.floor(T / period * (1.0 + 1e-12)))
    t = np.arange(k + 1) * period
    t = t[t < T * (1.0 - SNAP)]
    t = np.append(t, T)
    return _snap(t, np.asarray(breaks, float)[1:-1], SNAP * T)


def _projection(form: Form, u_exact: Uexact, rows: int, breaks: np.ndarray) -> np.ndarray:
    """The L2 projection of the exact inputs onto the form's functions (the best start of the
    correction: a linear interpolant through the exact values misses peaks, this one matches
    the inputs' integrals against every basis function). Gauss-Legendre on the pieces between
    the form's knots and the plan's breaks; the Gram matrix is banded (neighbouring rows)."""
    from scipy.linalg import solve_banded

    cuts = np.unique(np.concatenate([form.knots, np.asarray(breaks, float)]))
    cuts = cuts[(cuts >= 0.0) & (cuts <= form.T)]
    g, w = _gauss(5)
    h = np.diff(cuts)
    tt = (cuts[:-1, None] + h[:, None] * g).ravel()
    vals = np.asarray(u_exact(tt), float).reshape(h.size, g.size, 2)
    k = np.clip(np.searchsorted(form.knots, tt, side="right") - 1, 0, form.knots.size - 2)
    hk = np.diff(form.knots)[k]
    B = (form.shapes((tt - form.knots[k]) / hk) * form.scale[k]).reshape(h.size, g.size, -1)
    rhs = _scatter(form.idx[k.reshape(h.size, g.size)[:, 0]],
                   np.einsum("kgr,kgc,g,k->krc", B, vals, w, h), rows)
    # the Gram matrix of the basis on the form's own intervals (exact: Gauss on polynomials)
    gk, wk = _gauss(GAUSS + 1)
    S = form.shapes(gk)                                           # (G, R)
    hh = np.diff(form.knots)
    local = np.einsum("gr,gs,g->rs", S, S, wk)                    # (R, R)
    R = form.idx.shape[1]
    # bands (upper, diagonal, lower) in solve_banded's layout: entry (i, j) at [1 + i - j, j]
    rr, cc = np.meshgrid(np.arange(R), np.arange(R), indexing="ij")
    ii, jj = form.idx[:, rr.ravel()], form.idx[:, cc.ravel()]     # (K, R*R)
    val = (hh[:, None] * form.scale[:, rr.ravel()] * form.scale[:, cc.ravel()]
           * local[rr.ravel(), cc.ravel()])
    band = 1 + ii - jj
    if np.any(np.abs(band - 1) > 1):
        raise ValueError("the projection needs a basis that couples neighbouring rows only")
    ab = _scatter(band * rows + jj, val, 3 * rows).reshape(3, rows)
    used = ab[1] > 0.0
    ab[1, ~used] = 1.0                                            # rows no interval uses
    out = solve_banded((1, 1), ab, rhs)
    out[~used] = out[np.maximum(np.nonzero(~used)[0] - 1, 0)]
    return out


# ---------------------------------------------------------------------- the plan's forms
@dataclass(frozen=True)
class Execution:
    """The handed-out forms of one plan.

    Attributes
    ----------
    path : SampledPath
        The executable path (rule ``check.rule``): its ``u`` replays the plan, ``q`` and ``z``
        are the states of that replay.
    check : ExecutionCheck
    joint_trajectory : dict or None
        The ROS ``trajectory_msgs/JointTrajectory`` form, when asked for.
    joint_trajectory_check : ExecutionCheck or None
    seconds : float
        Time spent making and checking the forms.
    indicators : Indicators or None
        Measured on the handed-out path (its replay on ``dense_t``: every sample and three
        points inside every interval), the energy of its rates exactly.
    dense_t, dense_q : ndarray or None
        That replay.
    """

    path: SampledPath
    check: ExecutionCheck
    joint_trajectory: dict[str, Any] | None = None
    joint_trajectory_check: ExecutionCheck | None = None
    seconds: float = 0.0
    indicators: Indicators | None = None
    dense_t: np.ndarray | None = None
    dense_q: np.ndarray | None = None

    def validation(self) -> dict[str, Any]:
        """The ``validation.executed`` (and ``validation.joint_trajectory``) entries."""
        out = {"executed": self.check.as_dict()}
        if self.joint_trajectory_check is not None:
            out["joint_trajectory"] = self.joint_trajectory_check.as_dict()
        return out


def _require(check: ExecutionCheck, what: str, field: str | None, hint: str) -> None:
    """Raise when the form, executed by its rule, leaves the region or misses the goal."""
    if check.singular or not check.margin > 0.0:
        raise InfeasibleError(
            f"the {what} leaves the singularity-free region when executed by its rule "
            f"({check.rule}; margin {check.margin:.3g} rad){hint}", field=field,
            diagnostics={"execution": check.as_dict()})
    if not check.terminal_error <= EXECUTION_TOLERANCE:
        raise NumericalError(
            f"the {what} does not reach the goal when executed by its rule ({check.rule}; "
            f"terminal error {check.terminal_error:.3g} rad){hint}", field=field,
            diagnostics={"execution": check.as_dict()})


def check_period(req: PlanRequest, T: float) -> None:
    """The request's ``controller_period`` against the plan's duration ``T``.

    Raises
    ------
    InvalidRequestError
        The period is above ``T / 2`` or gives more than :data:`MAX_SAMPLES` samples.
    """
    period = req.controller_period
    if period is None:
        return
    if period > 0.5 * T * (1.0 + 1e-12):
        raise InvalidRequestError(
            f"controller_period = {period:g} s must be at most half the duration "
            f"(T = {T:.6g} s)", field="controller_period")
    if math.ceil(T / period * (1.0 - 1e-12)) + 1 > MAX_SAMPLES:
        raise InvalidRequestError(
            f"controller_period = {period:g} s gives {math.ceil(T / period) + 1} samples over "
            f"T = {T:.6g} s, more than {MAX_SAMPLES}", field="controller_period")


def handed_out_times(req: PlanRequest, T: float, stops: np.ndarray, breaks: np.ndarray,
                     exact: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The linear form's times (:func:`linear_times` of the stops, and of the breaks when the
    rates are linear between them: ``exact``), the dense grid the form is replayed on
    (:func:`dense_times`) and the positions of the times in it."""
    times = linear_times(T, req.samples, np.union1d(stops, breaks) if exact else stops)
    dense, at = dense_times(times)
    return times, dense, at


def dense_times(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The form's times and three points inside every interval (where the indicators and the
    region are measured), and the positions of ``times`` in it."""
    h = np.diff(times)
    inner = (times[:-1, None] + h[:, None] * np.array([0.25, 0.5, 0.75])).ravel()
    dense = np.concatenate([times[:-1, None],
                            inner.reshape(-1, 3)], axis=1).ravel()
    dense = np.append(dense, times[-1])
    return dense, np.arange(times.size) * 4


def _energy(form: Form, p: np.ndarray) -> float:
    """``int u1^2 + u2^2 dt`` of a linear or held form, exactly."""
    h = np.diff(form.knots)
    a = p[form.idx[:, 0]]
    if form.rule == "zoh":
        return float(np.sum(h[:, None] * a * a))
    b = p[form.idx[:, 1]]
    return float(np.sum(h[:, None] * (a * a + a * b + b * b)) / 3.0)


def execute(req: PlanRequest, u_exact: Uexact, breaks: np.ndarray, T: float,
            phi_end: float, region: Region | None = None, *,
            stops: np.ndarray | None = None, exact: bool = False,
            initial: Replay | None = None) -> Execution:
    """The handed-out forms of a verified plan: sampled, corrected onto the goal, re-integrated.

    Parameters
    ----------
    req : PlanRequest
        ``samples``, ``controller_period``, ``joint_trajectory``, robot, start, goal, bounds,
        limits.
    u_exact : callable
        The rates to hand out (the plan's path along its time law): times (s), shape (M,)
        -> (M, 2), continuous.
    breaks : ndarray
        Times (s) ``[0, ..., T]`` where the rates may have kinks (the projection's pieces).
    T : float
        Duration (s).
    phi_end : float
        ``phi(T)`` of the plan (the forms end there too).
    region : Region, optional
        The region the executed forms must stay in (default: the request's full region).
    stops : ndarray, optional
        Times (s) where the rates are zero (``0``, the inner stops, ``T``; default ``[0,
        T]``): samples of the linear form, held at zero by the correction.
    exact : bool
        The rates are linear between ``breaks``: the linear form takes them as samples too,
        and holds the rates exactly (its first replay is the plan's path).
    initial : Replay, optional
        With ``exact``: the original model under these rates, its last rows at the dense grid
        of :func:`handed_out_times` (the plan's own replay at the plan times the time law
        reaches there: the same path, so not integrated twice). Ignored on a controller
        period.

    Raises
    ------
    InvalidRequestError
        ``controller_period`` does not fit ``T``.
    NumericalError
        A form does not reach the goal within :data:`EXECUTION_TOLERANCE` when executed.
    InfeasibleError
        A form leaves the region when executed, or its corrected rates leave their limits.
    """
    t_start = time.perf_counter()
    robot = req.robot
    cf = chained_form(robot)
    if region is None:
        region = Region(robot, "full", req.joint_bounds)
    q0 = req.q_start()
    target = np.concatenate([[phi_end], req.goal])
    breaks = np.asarray(breaks, float)
    stops = np.array([0.0, T]) if stops is None else np.asarray(stops, float)
    check_period(req, T)
    if req.controller_period is None:
        times = handed_out_times(req, T, stops, breaks, exact)[0]
        held = np.searchsorted(times, stops)
        form = linear_form(times, held)
        # point samples of continuous rates: the linear interpolant's values and slopes are
        # within the rates' and their derivative's peaks (no overshoot of a limit)
        p0 = np.array(u_exact(times), float)
        p0[held] = 0.0
    else:
        times = period_times(T, float(req.controller_period), stops)
        form = zoh_form(times)
        p0 = _projection(form, u_exact, times.size, np.union1d(breaks, stops))
    limits = (req.max_u1, req.max_u2)
    if form.rule == "linear":
        dense, at = handed_out_times(req, T, stops, breaks, exact)[1:]
    else:
        dense, at = dense_times(times)
    u, qd, check = correct(robot, form, p0, q0, target, region, dense, limits,
                           initial if form.rule == "linear" and exact else None)
    q = qd[at]
    if req.controller_period is None:
        _require(check, f"path of {req.samples} samples", "samples",
                 ": too few samples to hold this plan, ask for more")
    else:
        _require(check, f"path on the controller period {req.controller_period:g} s",
                 "controller_period", ": the period is too long for this plan")
    _require_limits(req, form, u, check)
    if form.rule == "zoh":
        u[-1] = u[-2]
    al, be = cf.input_coefficients(q)
    v = np.column_stack([u[:, 0], al * u[:, 0] + be * u[:, 1]])
    path = SampledPath(t=times, q=q, z=cf.to_chained(q), u=u, v=v)
    ind = dataclasses.replace(compute_indicators(dense, qd, None), energy=_energy(form, u))
    jt = jt_check = None
    if req.joint_trajectory:
        jt, jt_check, _ = joint_trajectory(robot, region, form, path, q0, target, req)
        _require(jt_check, "JointTrajectory form", "joint_trajectory",
                 ": its points are too sparse for this plan (more samples, or a shorter "
                 "controller_period)")
    return Execution(path=path, check=check, joint_trajectory=jt, joint_trajectory_check=jt_check,
                     seconds=time.perf_counter() - t_start, indicators=ind, dense_t=dense,
                     dense_q=qd)


#: The handed-out forms may exceed a limit by this fraction (the correction moves the rates
#: by ~1e-9 of their size; the time law plans 1e-3 inside the limits).
LIMIT_TOLERANCE = 1e-2


def _require_limits(req: PlanRequest, form: Form, u: np.ndarray, check: ExecutionCheck) -> None:
    """Refuse a corrected form whose rates (or, for the linear rule, slopes) leave a limit."""
    peaks = [np.max(np.abs(u), axis=0)]
    names = [("max_u1", "max_u2")]
    if form.rule == "linear":
        h = np.diff(form.knots)
        slope = (u[form.idx[:, 1]] - u[form.idx[:, 0]]) / h[:, None]
        peaks.append(np.max(np.abs(slope), axis=0))
        names.append(("max_du1", "max_du2"))
    for peak, pair in zip(peaks, names):
        for c, name in enumerate(pair):
            lim = getattr(req, name)
            if lim is not None and peak[c] > lim * (1.0 + LIMIT_TOLERANCE):
                raise InfeasibleError(
                    f"the handed-out {form.rule} form reaches {peak[c]:.6g} after its "
                    f"correction, above {name} = {lim:g}: more samples, or a longer duration",
                    field=name, diagnostics={"execution": check.as_dict(),
                                             "peak": float(peak[c])})


def hermite_peaks(form: Form, p: np.ndarray) -> np.ndarray:
    """``max |u_c|``, ``max |u_c'|`` and ``max |u_c''|`` over ``[0, T]`` of each input of a cubic
    Hermite form, exactly, shape (3, 2): on an interval ``u`` is a quadratic in ``s``, whose
    extremes are at the ends or at its vertex; ``u'`` is linear (extremes at the ends) and
    ``u''`` constant."""
    K = form.knots.size - 1
    k = np.repeat(np.arange(K), 3)
    u = form.local(k, np.tile([0.0, 0.5, 1.0], K), p).reshape(K, 3, 2)
    u0, uh, u1 = u[:, 0], u[:, 1], u[:, 2]
    a = 2.0 * (u0 + u1 - 2.0 * uh)                    # u(s) = a s^2 + b s + c
    b = u1 - u0 - a
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(a != 0.0, -b / (2.0 * a), 0.0)
    inside = (s > 0.0) & (s < 1.0)
    vertex = np.where(inside, u0 + s * (b + a * s), 0.0)
    h = np.diff(form.knots)[:, None]
    rate = np.max(np.abs(np.concatenate([u0, u1, vertex])), axis=0)
    accel = np.max(np.abs(np.concatenate([b / h, (2.0 * a + b) / h])), axis=0)
    jerk = np.max(np.abs(2.0 * a / h ** 2), axis=0)
    return np.stack([rate, accel, jerk])


def hermite_peak_rates(form: Form, p: np.ndarray) -> np.ndarray:
    """``max |u_c(t)|`` of a cubic Hermite form (:func:`hermite_peaks`' first row)."""
    return hermite_peaks(form, p)[0]


#: A JointTrajectory stretched for the actuator limits gets this much more time than their
#: ratio asks (its rates come out of a new correction, which moves them by ~1e-9).
STRETCH_MARGIN = 1e-6
#: The request fields of the limits, by derivative order.
LIMIT_NAMES = (("max_u1", "max_u2"), ("max_du1", "max_du2"), ("max_ddu1", "max_ddu2"))


def _stretch_for(peaks: np.ndarray, req: PlanRequest) -> float:
    """The smallest ``f >= 1`` that brings peaks of orders 0, 1, 2 within the request's limits
    (a stretch by ``f`` divides them by ``f``, ``f^2``, ``f^3``)."""
    f = 1.0
    for order, pair in enumerate(LIMIT_NAMES):
        for c, name in enumerate(pair):
            lim = getattr(req, name, None)
            if lim is not None and peaks[order, c] > lim:
                f = max(f, (peaks[order, c] / lim) ** (1.0 / (order + 1)))
    return f


def joint_trajectory(robot: Robot, region: Region, form: Form, path: SampledPath,
                     q0: np.ndarray, target: np.ndarray, req: PlanRequest
                     ) -> tuple[dict[str, Any], ExecutionCheck, np.ndarray]:
    """The ROS ``trajectory_msgs/JointTrajectory`` form of an executable path, corrected for
    cubic Hermite interpolation.

    Points at the path's distinct times (whole nanoseconds); positions ``(phi, th1)`` of the
    path, velocities the rates there (for a held path, the mean of the two rates held around
    the point), zero at the first and last points. The interior positions and velocities are
    then corrected so that the original model driven by the derivative of the cubic Hermite
    interpolant ends at the goal (the end positions and velocities are held).

    With limits in ``req`` the interpolant's rates, their derivatives and second derivatives
    (:func:`hermite_peaks`, exact between the points) are brought within them: the points'
    times are stretched by the smallest factor that does it (times ``1 +``
    :data:`STRETCH_MARGIN`; usually 1, the path's own rates are planned inside them), the
    velocities shrunk by it, and the form is corrected again on those times: the model has no
    drift, so ``u(t / f) / f`` drives it along the same path (``time_scale`` in the answer).

    Returns
    -------
    dict
        ``joint_names``, ``points`` (``positions``, ``velocities``, empty ``accelerations``,
        ``time_from_start`` as ``sec`` and ``nanosec``), ``interpolation`` and
        ``time_scale``.
    ExecutionCheck
    ndarray (3, 2)
        :func:`hermite_peaks` of the form handed out.
    """
    t = path.t
    ns, keep = np.unique(np.rint(t * 1e9).astype(np.int64), return_index=True)
    times = ns * 1e-9
    if form.rule == "zoh":
        held = path.u[:-1]
        vel = np.vstack([held[:1], 0.5 * (held[:-1] + held[1:]), held[-1:]])[keep]
    else:
        vel = path.u[keep].copy()
    vel[[0, -1]] = 0.0
    pos = path.q[keep][:, :2]
    hform = hermite_form(times)
    p, q, check = correct(robot, hform, np.vstack([pos, vel]), q0, target, region, times)
    peaks = hermite_peaks(hform, p)
    m = times.size
    scale = _stretch_for(peaks, req)
    if scale > 1.0:
        scale *= 1.0 + STRETCH_MARGIN
        ns = np.rint(ns * scale).astype(np.int64)
        times = ns * 1e-9
        hform = hermite_form(times)
        p, q, check = correct(robot, hform, np.vstack([p[:m], p[m:] / scale]), q0, target,
                              region, times)
        peaks = hermite_peaks(hform, p)
    for order, pair in enumerate(LIMIT_NAMES):
        for c, name in enumerate(pair):
            lim = getattr(req, name, None)
            if lim is not None and peaks[order, c] > lim * (1.0 + LIMIT_TOLERANCE):
                raise InfeasibleError(
                    f"the JointTrajectory form, interpolated between its points as "
                    f"joint_trajectory_controller does, reaches {peaks[order, c]:.6g}, above "
                    f"{name} = {lim:g}: more samples, or a longer duration",
                    field="joint_trajectory",
                    diagnostics={"joint_trajectory": check.as_dict(),
                                 "peak": float(peaks[order, c]), "limit": name})
    pos, vel = p[:m], p[m:]
    # no accelerations: given positions and velocities only, joint_trajectory_controller
    # interpolates cubically, the rule verified here (with accelerations it would take a
    # quintic, another path)
    points = [{"positions": [float(a), float(b)], "velocities": [float(c), float(d)],
               "accelerations": [], "effort": [],
               "time_from_start": {"sec": int(x // 1_000_000_000),
                                   "nanosec": int(x % 1_000_000_000)}}
              for (a, b), (c, d), x in zip(pos.tolist(), vel.tolist(), ns.tolist())]
    out = {"joint_names": ["phi", "th1"], "points": points,
           "interpolation": "cubic Hermite between consecutive points (positions and "
                            "velocities), as joint_trajectory_controller",
           "time_scale": scale}
    return out, check, peaks


class HandedOutInputs:
    """The rates a plan hands out, executed by their rule, as the open-loop replays take them
    (:func:`optimizer.verify.integrate` and :func:`optimizer.verify.integrate_cascade`).

    Parameters
    ----------
    path : SampledPath
        A plan's ``path``.
    rule : {"linear", "zoh"}
    """

    def __init__(self, path: SampledPath, rule: str) -> None:
        if rule == "linear":
            self.form = linear_form(np.asarray(path.t, float))
        elif rule == "zoh":
            self.form = zoh_form(np.asarray(path.t, float))
        else:
            raise ValueError(f"rule must be 'linear' or 'zoh', not {rule!r}")
        self.p = np.asarray(path.u, float)
        self.T = self.form.T
        self.breaks = self.form.knots

    def u(self, t: np.ndarray) -> np.ndarray:
        """Rates at many times, shape (M, 2)."""
        return self.form.u(self.p, t)

    def u_scalar(self, t: float, _q: np.ndarray | None = None) -> np.ndarray:
        """Rates at one time (the integrators' callback)."""
        return self.form.u(self.p, np.array([t]))[0]

    def replay(self, robot: Robot, q0: np.ndarray, t_eval: np.ndarray) -> Replay:
        """The original model under these rates from ``q0`` (a perturbed start, say).

        Cascade quadrature between the knots (exact for these piecewise polynomials up to
        ~1e-13 rad); a run that meets the region's boundary is integrated again by DOP853,
        which stops there (the replays report where a run became singular).
        """
        rep = integrate_cascade(robot, self.u, q0, self.T, t_eval, self.breaks,
                                nodes=REPLAY_NODES, initial_panels=1,
                                max_panels=4 * self.breaks.size + 2048)
        if rep.success and not rep.singular:
            return rep
        return integrate(robot, self.u_scalar, q0, self.T, t_eval)
