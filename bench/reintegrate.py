"""Re-integration of the ORIGINAL kinematic model under a method's actuator inputs, and metrics.

The right-hand side is the model's one definition (:func:`optimizer.dynamics.vector_field`), with
the input energy integrated alongside; the integrator (scipy) is independent of the planner's::

    phi'  = u1
    th1'  = u2
    th_i' = K_i cos(th_{i-1})^m_i u1        (i = 2..n)
    E'    = u1^2 + u2^2                     (input energy, integrated alongside)

It is integrated with scipy ``solve_ivp`` (DOP853, rtol 1e-10, atol 1e-12) piece by piece between
the input schedule's breaks (the planner's polynomial segments, the baseline's shooting
intervals), so that no step straddles a discontinuity of ``u``.

Inputs
------
* planner: ``optimizer.verify.PlannedInputs(chained_form(robot), plan.chained).u_scalar``, the
  actuator inputs as a function of time, as the motors would replay them;
* baseline: its piecewise-constant ``u`` (one row per shooting interval).

Metrics (all from the re-integrated path, on a uniform grid of :data:`GRID` times plus the breaks)
--------------------------------------------------------------------------------------------------
``terminal_error_rad``
    ``max_i |th_i(T) - goal_i|``.
``d_a_deg``
    Joint 1: ``max_t |th1(t) - (th1(0) + t/T (goal_1 - th1(0)))|`` (the paper's d_a).
``joint_space_dev_deg``
    Largest perpendicular distance of ``th(t)`` from the straight LINE through start and goal in
    joint space (eq 17).
``segment_dev_deg``
    Largest distance of ``th(t)`` from the straight SEGMENT start -> goal in joint space: the
    planner's ``deviation`` indicator, measured here on the re-integrated path.
``reversals_phi``, ``reversals_th1``
    Interior extrema of ``phi(t)`` and ``th1(t)`` (reversals of the two actuators), counted by
    :func:`optimizer.indicators.count_reversals` (the one definition) with its actuator dead band
    :data:`DEAD_BAND` rad.
``energy``
    ``integral of u1^2 + u2^2 dt`` (rad^2/s).
``region_margin_deg``
    ``min_t min(th_i, 90 deg - th_i)`` over ``i = 1..n-1``; negative when the path left the region
    where the chained form exists.
``region_margin_all_deg``
    The same over every joint ``i = 1..n``: the product keeps ``th_n`` inside ``(0, 90 deg)`` too.

Only the metrics' formulas are shared with the planner (:mod:`optimizer.indicators`); the path
they are applied to comes from scipy here, never from the planner's own integrator.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy.integrate import solve_ivp

from optimizer.dynamics import vector_field
from optimizer.indicators import (ACTUATOR_DEAD_BAND, count_reversals, joint_space_distance,
                                  segment_distance)

RTOL = 1e-10
ATOL = 1e-12
#: Uniform grid of the metrics (points over [0, T]).
GRID = 4001
#: Dead band of the reversal count (rad): the planner's actuator dead band, so that the
#: re-integrated counts mean what ``reversals_phi``/``reversals_th1`` mean (1e-4 rad = 0.0057 deg).
DEAD_BAND = ACTUATOR_DEAD_BAND

#: ``u(t) -> (u1, u2)`` (any array-like of two numbers).
UFunction = Callable[[float], Any]


@dataclass(frozen=True)
class Segment:
    """One piece of an input schedule: ``u(t)`` on ``[t0, t1]``, smooth inside."""

    t0: float
    t1: float
    u: UFunction


@dataclass(frozen=True)
class PathMetrics:
    """Metrics of one re-integrated path (see the module docstring).

    Attributes
    ----------
    terminal_error_rad, d_a_deg, joint_space_dev_deg : float
    reversals_phi, reversals_th1 : int
    energy : float
    region_margin_deg : float
    final : list of float
        ``[phi, th_1..th_n]`` at ``T``.
    ok : bool
        The integration finished and every number is finite.
    message : str
    segment_dev_deg, region_margin_all_deg : float
        Added after the others (defaults keep older constructions valid).
    """

    terminal_error_rad: float
    d_a_deg: float
    joint_space_dev_deg: float
    reversals_phi: int
    reversals_th1: int
    energy: float
    region_margin_deg: float
    final: list[float]
    ok: bool
    message: str = ""
    segment_dev_deg: float = math.nan
    region_margin_all_deg: float = math.nan

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly copy."""
        return asdict(self)


def joint_trajectory_arrays(jt: Mapping[str, Any]
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points of a handed-out ``joint_trajectory`` (a ROS ``JointTrajectory`` as JSON) as
    arrays: times (s, from ``time_from_start``'s ``sec`` and ``nanosec``), positions,
    velocities and accelerations (one row a point, one column a joint of ``joint_names``).

    What the benchmark and the tests replay a JointTrajectory from: decoded here once, from
    the message as a client receives it."""
    pts = jt["points"]
    t = np.array([p["time_from_start"]["sec"] + 1e-9 * p["time_from_start"]["nanosec"]
                  for p in pts])
    x, v, a = (np.array([p[key] for p in pts], float)
               for key in ("positions", "velocities", "accelerations"))
    return t, x, v, a


def model_rhs(gains: Sequence[float], exponents: Sequence[int]
              ) -> Callable[[float, np.ndarray, np.ndarray], np.ndarray]:
    """The original model plus the energy state, ``x = [phi, th_1..th_n, E]``.

    Parameters
    ----------
    gains : sequence of float
        ``K_2..K_n``.
    exponents : sequence of int
        ``m_2..m_n``.

    Returns
    -------
    callable
        ``rhs(t, x, u) -> x'``.
    """
    K = tuple(float(k) for k in gains)
    m = tuple(int(e) for e in exponents)
    n = len(K) + 1

    def rhs(t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        dx = np.empty_like(x)
        dx[:n + 1] = vector_field(K, m, x, u[0], u[1], np.cos)
        dx[n + 1] = u[0] * u[0] + u[1] * u[1]
        return dx

    return rhs


def line_distance(th: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Largest perpendicular distance of the rows of ``th`` from the line through ``a`` and ``b``.

    Parameters
    ----------
    th : ndarray (N, n)
    a, b : ndarray (n,)

    Returns
    -------
    float
        Same unit as ``th``.
    """
    # joint_space_distance measures from the line through the first and last row; a and b lie
    # on their own line (distance 0), so framing th by them changes nothing else
    return joint_space_distance(np.vstack([a, th, b]))


def integrate(gains: Sequence[float], exponents: Sequence[int], q0: np.ndarray,
              segments: Sequence[Segment], grid: int = GRID
              ) -> tuple[np.ndarray, np.ndarray]:
    """Integrate the original model (with energy) over consecutive segments.

    Parameters
    ----------
    gains, exponents : sequence
        ``K_2..K_n``, ``m_2..m_n``.
    q0 : ndarray (n+1,)
        ``[phi, th_1..th_n]`` at ``t = segments[0].t0``.
    segments : sequence of Segment
        Contiguous, in time order.
    grid : int
        Points of the uniform output grid.

    Returns
    -------
    t : ndarray (N,)
        Output times (the uniform grid and every break).
    x : ndarray (N, n+2)
        ``[phi, th_1..th_n, E]``.

    Raises
    ------
    RuntimeError
        The integrator failed on a segment.
    """
    rhs = model_rhs(gains, exponents)
    t_start, t_end = segments[0].t0, segments[-1].t1
    tg = np.linspace(t_start, t_end, grid)
    x = np.concatenate([np.asarray(q0, float), [0.0]])
    ts: list[np.ndarray] = []
    xs: list[np.ndarray] = []
    for k, seg in enumerate(segments):
        if seg.t1 <= seg.t0:
            continue
        last = k == len(segments) - 1
        inside = tg[(tg > seg.t0) & ((tg < seg.t1) | (last & (tg <= seg.t1)))]
        t_eval = np.unique(np.concatenate([[seg.t0], inside, [seg.t1]]))
        ufun = seg.u
        sol = solve_ivp(lambda t, y: rhs(t, y, np.asarray(ufun(t), float)), (seg.t0, seg.t1), x,
                        method="DOP853", rtol=RTOL, atol=ATOL, t_eval=t_eval)
        if sol.status != 0:
            raise RuntimeError(f"solve_ivp failed on [{seg.t0:g}, {seg.t1:g}]: {sol.message}")
        keep = slice(0, None) if not ts else slice(1, None)  # the break is already stored
        ts.append(sol.t[keep])
        xs.append(sol.y.T[keep])
        x = sol.y[:, -1].copy()
    return np.concatenate(ts), np.concatenate(xs)


def path_metrics(t: np.ndarray, x: np.ndarray, start: np.ndarray, goal: np.ndarray,
                 dead_band: float = DEAD_BAND) -> PathMetrics:
    """Metrics of a re-integrated path.

    Parameters
    ----------
    t : ndarray (N,)
    x : ndarray (N, n+2)
        ``[phi, th_1..th_n, E]`` from :func:`integrate`.
    start, goal : ndarray (n,)
        ``th_1..th_n`` (rad).
    dead_band : float
        Reversal dead band (rad).

    Returns
    -------
    PathMetrics
    """
    n = start.size
    th = x[:, 1:n + 1]
    tau = (t - t[0]) / (t[-1] - t[0])
    line1 = start[0] + tau * (goal[0] - start[0])
    inner = th[:, : n - 1]
    margin = float(np.min(np.minimum(inner, 0.5 * math.pi - inner)))
    margin_all = float(np.min(np.minimum(th, 0.5 * math.pi - th)))
    final = x[-1, : n + 1]
    m = PathMetrics(
        terminal_error_rad=float(np.max(np.abs(final[1:] - goal))),
        d_a_deg=math.degrees(float(np.max(np.abs(th[:, 0] - line1)))),
        joint_space_dev_deg=math.degrees(line_distance(th, start, goal)),
        reversals_phi=count_reversals(x[:, 0], dead_band),
        reversals_th1=count_reversals(th[:, 0], dead_band),
        energy=float(x[-1, n + 1]),
        region_margin_deg=math.degrees(margin),
        final=[float(v) for v in final],
        ok=True,
        segment_dev_deg=math.degrees(segment_distance(th, start, goal)),
        region_margin_all_deg=math.degrees(margin_all),
    )
    finite = all(math.isfinite(v) for v in (m.terminal_error_rad, m.d_a_deg,
                                             m.joint_space_dev_deg, m.energy,
                                             m.region_margin_deg, m.segment_dev_deg,
                                             m.region_margin_all_deg))
    if not finite:
        return PathMetrics(**{**asdict(m), "ok": False, "message": "non-finite metric"})
    return m


def failed_metrics(message: str) -> PathMetrics:
    """Metrics of a path that could not be re-integrated."""
    nan = float("nan")
    return PathMetrics(nan, nan, nan, -1, -1, nan, nan, [], False, message,
                       segment_dev_deg=nan, region_margin_all_deg=nan)


def planner_segments(plan: Any) -> list[Segment]:
    """Segments of a planner's plan: ``PlannedInputs(...).u_scalar`` between its input breaks.

    Parameters
    ----------
    plan : optimizer.results.Plan

    Returns
    -------
    list of Segment
    """
    from optimizer.chained_form import chained_form
    from optimizer.verify import PlannedInputs

    if plan.chained is None:  # actuator rates (method shooting): constant on each interval
        planned: Any = plan.inputs
        breaks = np.asarray(plan.inputs.breaks, float)
    else:
        planned = PlannedInputs(chained_form(plan.robot), plan.chained)
        T = float(plan.chained.inputs.duration)
        breaks = np.asarray(plan.chained.inputs.breaks, float) * T

    def u(t: float) -> np.ndarray:
        return planned.u_scalar(t)

    return [Segment(float(a), float(b), u) for a, b in zip(breaks[:-1], breaks[1:])]


def baseline_segments(result: Any) -> list[Segment]:
    """Segments of a baseline result: one constant ``u`` per shooting interval.

    Parameters
    ----------
    result : bench.baselines.multiple_shooting.BaselineResult

    Returns
    -------
    list of Segment
    """
    def constant(uk: tuple[float, float]) -> UFunction:
        return lambda t: uk

    return [Segment(float(result.t_grid[k]), float(result.t_grid[k + 1]),
                    constant((float(result.u[k, 0]), float(result.u[k, 1]))))
            for k in range(result.u.shape[0])]


def reintegrate_plan(plan: Any, start: np.ndarray, goal: np.ndarray,
                     phi_start: float = 0.0) -> PathMetrics:
    """Re-integrate a planner's plan on the original model and measure it."""
    try:
        t, x = integrate(plan.robot.gains, plan.robot.exponents,
                         np.concatenate([[phi_start], start]), planner_segments(plan))
    except (RuntimeError, FloatingPointError, ValueError) as exc:
        return failed_metrics(f"{type(exc).__name__}: {exc}")
    return path_metrics(t, x, start, goal)


def reintegrate_baseline(result: Any, gains: Sequence[float], exponents: Sequence[int],
                         start: np.ndarray, goal: np.ndarray,
                         phi_start: float = 0.0) -> PathMetrics:
    """Re-integrate a baseline solution (piecewise-constant ``u``) and measure it."""
    try:
        t, x = integrate(gains, exponents, np.concatenate([[phi_start], start]),
                         baseline_segments(result))
    except (RuntimeError, FloatingPointError, ValueError) as exc:
        return failed_metrics(f"{type(exc).__name__}: {exc}")
    return path_metrics(t, x, start, goal)
