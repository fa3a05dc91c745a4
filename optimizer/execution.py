"""What a controller executes: the handed-out forms of a plan, corrected and verified.

A plan is proved from its exact input segments; what is handed out is its path run along its
time law (:mod:`optimizer.timing`: rest to rest, continuous rates, within the request's
limits), and a controller runs samples of those rates under a rule.
Replaying a plan's plain samples misses the goal by 1e-3 to 1e-1 rad (linear interpolation
or zero-order hold of smooth inputs is not the inputs), so each handed-out form is made the
truth: its sample values are corrected until the ORIGINAL model integrated under the form's
own interpolation rule reaches the goal, and the states handed out are that integration's.

Forms (documented for users in ``docs/execution.md``)
-----------------------------------------------------
``linear``
    The default ``path``: rates ``u`` at increasing times ``t``, linearly interpolated; zero
    at the first and last samples and at the time law's stops (held there by the
    correction). When the law's rates are linear between its phases (constant directions, no
    jerk limit) the phases' ends are samples too and the form holds the rates exactly.
``zoh``
    With ``controller_period``: ``t = k * period`` (the last point ``T``; when ``T`` is not a
    multiple the last interval is shorter) and ``u[k]`` held constant on ``[t_k, t_{k+1})``
    (the last row repeats the last interval's rate; nothing is held after ``T``).
``quintic_hermite``
    The ROS ``trajectory_msgs/JointTrajectory`` form (:mod:`optimizer.joint_trajectory`):
    positions ``(phi, th1)``, velocities ``(u1, u2)`` and accelerations at points; between
    points the position is the quintic Hermite interpolant of both ends' positions, velocities
    and accelerations (what ``joint_trajectory_controller`` does when all three are given), so
    the rates executed are its derivative.

The samples are corrected until the original model under the form's rule reaches the goal
(:func:`optimizer.forms.correct`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .chained_form import chained_form
from .errors import InfeasibleError, InvalidRequestError, NumericalError
from .forms import (CORRECTION_TARGET, EXECUTION_TOLERANCE, GAUSS,  # noqa: F401
                    LIMIT_TOLERANCE, MAX_CORRECTIONS, REPLAY_NODES, ExecutionCheck, Form,
                    correct, dense_times, gauss_legendre, linear_form, replay_form,
                    scatter_rows, zoh_form)
from .joint_trajectory import joint_trajectory
from .indicators import Indicators, compute_indicators
from .model import Robot
from .problem import MAX_SAMPLES, PlanRequest
from .region import Region
from .paths import SampledPath
from .verify import Replay, integrate, integrate_cascade

#: Sample times closer than this fraction of ``T`` to a break are moved onto it.
SNAP = 1e-9

Uexact = Callable[[np.ndarray], np.ndarray]


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
    return even_times(0.0, T, samples, np.asarray(stops, float)[1:-1])


def even_times(start: float, end: float, samples: int, inner: np.ndarray) -> np.ndarray:
    """``samples`` times evenly spaced from ``start`` to ``end``, those within a quarter of the
    spacing of a time of ``inner`` (sorted, strictly between ``start`` and ``end``) moved onto
    it, and every time of ``inner`` once."""
    # a sample closer to a stop than a quarter of the spacing moves onto it: no sliver
    # intervals next to a stop, and a stop that falls on a sample (up to rounding) is exact
    t = _snap(np.linspace(start, end, int(samples)), inner,
              0.25 * (end - start) / (int(samples) - 1))
    t[0], t[-1] = start, end
    # np.unique's result (sorted, exact repeats once) without its dispatch: a replan and a
    # plan each make such a grid
    out = np.concatenate([t, inner])
    out.sort()
    keep = np.empty(out.size, bool)
    keep[:1] = True
    np.not_equal(out[1:], out[:-1], out=keep[1:])
    return out[keep]


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
    g, w = gauss_legendre(5)
    h = np.diff(cuts)
    tt = (cuts[:-1, None] + h[:, None] * g).ravel()
    vals = np.asarray(u_exact(tt), float).reshape(h.size, g.size, 2)
    k = np.clip(np.searchsorted(form.knots, tt, side="right") - 1, 0, form.knots.size - 2)
    hk = np.diff(form.knots)[k]
    B = (form.shapes((tt - form.knots[k]) / hk) * form.scale[k]).reshape(h.size, g.size, -1)
    rhs = scatter_rows(form.idx[k.reshape(h.size, g.size)[:, 0]],
                   np.einsum("kgr,kgc,g,k->krc", B, vals, w, h), rows)
    # the Gram matrix of the basis on the form's own intervals (exact: Gauss on polynomials)
    gk, wk = gauss_legendre(GAUSS + 1)
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
    ab = scatter_rows(band * rows + jj, val, 3 * rows).reshape(3, rows)
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
    samples : int
        The evenly spaced samples of the linear form (the request's, or more when the
        planner made it denser: :func:`optimizer.planner.finish.retime_and_execute`).
    """

    path: SampledPath
    check: ExecutionCheck
    joint_trajectory: dict[str, Any] | None = None
    joint_trajectory_check: ExecutionCheck | None = None
    seconds: float = 0.0
    indicators: Indicators | None = None
    dense_t: np.ndarray | None = None
    dense_q: np.ndarray | None = None
    samples: int = 0

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
    """The linear form's times (:func:`linear_times` of the stops and the breaks: the rates'
    kinks, where the time law's phases start, are samples, so the form follows the law's
    ramps however short), the dense grid the form is replayed on (:func:`dense_times`) and
    the positions of the times in it. ``exact``: the rates are linear between the breaks
    (the form holds them exactly)."""
    # a kink within a thousandth of the spacing of a stop or another kink adds a sliver
    # interval, on which the cubic Hermite form's derivatives blow rounding up: not kept
    tol = 1e-3 * T / (int(req.samples) - 1)
    kinks = np.setdiff1d(np.asarray(breaks, float), stops)
    keep = np.concatenate([[True], np.diff(kinks) > tol]) if kinks.size else kinks.astype(bool)
    kinks = kinks[keep]
    if kinks.size and stops.size:
        kinks = kinks[np.min(np.abs(kinks[:, None] - stops[None, :]), axis=1) > tol]
    times = linear_times(T, req.samples, np.union1d(stops, kinks))
    dense, at = dense_times(times)
    return times, dense, at


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
            initial: Replay | None = None,
            grid: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> Execution:
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
        The rates are linear between ``breaks`` (which are samples of the linear form): the
        form holds them exactly (its first replay is the plan's path).
    initial : Replay, optional
        With ``exact``: the original model under these rates, its last rows at the dense grid
        of :func:`handed_out_times` (the plan's own replay at the plan times the time law
        reaches there: the same path, so not integrated twice). Ignored on a controller
        period.
    grid : tuple of ndarray, optional
        :func:`handed_out_times` of these arguments when the caller computed it already.

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
        if grid is None:
            grid = handed_out_times(req, T, stops, breaks, exact)
        times = grid[0]
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
        assert grid is not None
        dense, at = grid[1], grid[2]
    else:
        dense, at = dense_times(times)
    # a linear form that holds the plan's rates exactly is the plan's path: kept as it is
    # when it ends within a tenth of the tolerance (a correction would only move it). It holds
    # them only where every kink is a sample: handed_out_times leaves out a kink within a
    # thousandth of the spacing of another, and the rates' ramps between such kinks are then
    # not in the form (an 8-joint plan's law ran three pieces in 1e-7 s each: its linear form
    # missed the goal by 0.12 rad where the plan's replay, taken for the form's, reached it)
    holds = (form.rule == "linear" and exact
             and _all_samples(breaks[(breaks > 0.0) & (breaks < T)], times)
             and _linear_between(times, p0, u_exact))
    u, qd, check = correct(robot, form, p0, q0, target, region, dense, limits,
                           initial if holds else None,
                           accept_first=0.1 * EXECUTION_TOLERANCE if holds else 0.0)
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
    check = dataclasses.replace(check, reversals=(ind.reversals_phi, ind.reversals_th1),
                                deviation=ind.deviation, d_a=ind.d_a)
    jt = jt_check = None
    if req.joint_trajectory:
        jt, jt_check, _ = joint_trajectory(robot, region, form, path, q0, target, req,
                                           qd if form.rule == "linear" else None)
        _require(jt_check, "JointTrajectory form", "joint_trajectory",
                 ": its points are too sparse for this plan (more samples, or a shorter "
                 "controller_period)")
    return Execution(path=path, check=check, joint_trajectory=jt, joint_trajectory_check=jt_check,
                     seconds=time.perf_counter() - t_start, indicators=ind, dense_t=dense,
                     dense_q=qd, samples=int(req.samples))


#: The rates midway between samples may leave the samples' line by this much in all, as
#: ``sum |gap| * interval`` (rad: the actuator travel such gaps add up to), for the plan's
#: replay to be the linear form's: the end error that replay may have itself
#: (``0.1 * EXECUTION_TOLERANCE``). Pieces of one direction (within ``timing``'s
#: ``PARALLEL_TOLERANCE``, 1e-6) meet with a step of the rates that small: 1e-7 rad/s of
#: 0.5 on a 4-joint plan under limits, 2e-9 rad over its interval of 201 samples; on a
#: 7-joint path of 150 pieces and rates to 134 rad/s, 2.6e-8 rad in all, and its form
#: ended 1.2e-7 rad from the goal (scipy). A spike of the rates on a sample, 0.2 rad/s over
#: 1/260 s, is 4e-4.
LINEAR_CHECK = 1e-7


def _linear_between(times: np.ndarray, p: np.ndarray, u_exact: Uexact) -> bool:
    """The premise of taking the plan's replay for the linear form's, checked where it is
    cheap: midway between consecutive samples ``times`` (values ``p``) the rates ``u_exact``
    are the mean of the two samples, to :data:`LINEAR_CHECK`. A rate that is not linear
    there (a kink that is no sample, or a spike of the rates on a sample) fails it, and the
    form is replayed itself."""
    if times.size < 2:
        return True
    mid = np.asarray(u_exact(0.5 * (times[:-1] + times[1:])), float)
    gap = np.abs(mid - 0.5 * (p[:-1] + p[1:])).max(axis=1)
    return float(gap @ (times[1:] - times[:-1])) <= LINEAR_CHECK


def _all_samples(kinks: np.ndarray, times: np.ndarray) -> bool:
    """Every time of ``kinks`` is one of the sorted ``times`` exactly (np.isin's answer, by
    bisection: a tenth of its time on a plan's hundreds of samples)."""
    if kinks.size == 0:
        return True
    at = np.minimum(np.searchsorted(times, kinks), times.size - 1)
    return bool((times[at] == kinks).all())


def _require_limits(req: PlanRequest, form: Form, u: np.ndarray, check: ExecutionCheck) -> None:
    """Refuse a corrected form whose rates (or, for the linear rule, slopes) leave a limit."""
    if (req.max_u1 is None and req.max_u2 is None and req.max_du1 is None
            and req.max_du2 is None):
        return
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
