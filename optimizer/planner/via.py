"""Joint-space via points on the multiple-shooting transcription (``shooting``, ``penalty``).

What a via point asks
---------------------
"Joint ``th_j`` at ``angle`` at ``time``" (:mod:`optimizer.via_points`), with ``time`` on the
handed-out time axis. The transcription (:mod:`.nlp`) has node states ``q_k`` at equal steps
of its normalised time; the model is driftless, so the same nodes joined by the same rates can
be run on ANY increasing schedule of break times (each interval's rates scaled by its length:
the path through the states is the same). So:

1. each distinct via time ``t_i`` gets a node ``k_i`` (:func:`via_nodes`: the node nearest to
   ``t_i / T``, kept increasing and strictly inside), and the node's joint value is fixed to
   the angle by its variable bounds (``lbx = ubx``, :func:`pin_via_nodes`; the one hook in
   :func:`.nlp.variable_bounds`, which ``shooting`` and ``penalty`` share);
2. the plan's own schedule puts node ``k_i`` at ``t_i`` (:func:`via_schedule`: break times
   linear in the node index between the via nodes): interval ``k`` of length ``h_k`` runs the
   NLP's rates ``U_k`` (per unit normalised time, an interval ``1/N`` long) as
   ``u_k = U_k / (N h_k)``;
3. the Newton correction onto the goal (:func:`correct_rates_through_vias`, instead of
   :func:`.correction.correct_rates`) also moves the via nodes of the fine RK4 map (within
   ~1e-12 rad of the exact model) onto their angles: the minimum-norm step of the stacked
   residuals. The state at node ``k`` is the fine end map under the rates with every interval
   from ``k`` on set to zero (no rates, no motion: the model has no drift);
4. the time law keeps the plan's own time at every knot (:func:`optimizer.timing.time_law`
   with ``fixed_times``: without limits it does anyway), so node ``k_i`` is reached at
   ``t_i`` of the answer; the knot is a sample of the linear form (a phase of the law starts
   there), whose replay is the exact path;
5. the handed-out path is checked (:func:`check_handed_out`): the original model integrated
   under the handed-out rates by their rule, from the last sample before ``t_i`` to ``t_i``
   (scipy, tight tolerances) must be within :data:`VIA_TOLERANCE` of the angle
   (:data:`HELD_VIA_TOLERANCE` for a controller period's held form, which is corrected onto
   the goal only); ``diagnostics.via_points`` reports each point's reached angle and error.
"""

from __future__ import annotations

import contextlib
import math
from typing import Any, Iterator

import numpy as np
from scipy.integrate import solve_ivp

from ..actuation import ActuatorSchedule
from ..dynamics import vector_field
from ..errors import InfeasibleError, NumericalError, PlannerError
from ..paths import SampledPath
from ..problem import PlanRequest
from ..via_points import SAME_TIME, ViaPoint, distinct_times

#: A via point is honoured when the handed-out path (the default, linear form) passes within
#: this (rad) of its angle at its time (measured on random goals of 3 to 5 joints: 1e-16 to
#: 4e-8 rad).
VIA_TOLERANCE = 1e-6
#: The same for a controller period's held form (zero-order hold), which is corrected onto
#: the goal only: holding each rate for a period moves the path between the goal's ends.
HELD_VIA_TOLERANCE = 5e-3
#: Newton steps onto the goal and the via angles stop at this residual (rad) or after
#: :data:`MAX_STEPS` steps.
TARGET = 1e-12
MAX_STEPS = 6


def via_nodes(req: PlanRequest, N: int) -> list[tuple[int, float]]:
    """``(k_i, t_i)``: the node of each distinct via time ``t_i`` on ``N`` intervals.

    The node nearest to ``N t_i / T`` (``T`` the plan's own duration), moved to keep the
    nodes strictly increasing and inside ``1..N-1`` (at most :data:`~optimizer.via_points.
    MAX_VIA_TIMES` times, fewer than the coarsest rung's 12 intervals).
    """
    T = req.duration_or_default
    times = distinct_times(req.via_points)
    m = len(times)
    if m > N - 1:  # pragma: no cover - validation caps the times below every rung's N
        raise InfeasibleError(f"{m} via times need more than the transcription's {N} "
                              "intervals", field="via_points")
    out: list[tuple[int, float]] = []
    prev = 0
    for i, t in enumerate(times):
        k = int(round(N * t / T))
        k = min(max(k, prev + 1), N - (m - i))
        out.append((k, t))
        prev = k
    return out


def _node_of(req: PlanRequest, N: int, vp: ViaPoint) -> int:
    for k, t in via_nodes(req, N):
        if abs(t - vp.time) <= SAME_TIME:
            return k
    raise AssertionError("a via time without its node")  # pragma: no cover


def plan_breaks(req: PlanRequest, N: int) -> np.ndarray:
    """The plan's break times (s, ``N + 1``): node ``k_i`` at ``t_i``, linear in the node
    index between them."""
    T = req.duration_or_default
    nodes = via_nodes(req, N)
    ks = [0] + [k for k, _ in nodes] + [N]
    ts = [0.0] + [t for _, t in nodes] + [T]
    return np.interp(np.arange(N + 1, dtype=float), ks, ts)


def via_schedule(req: PlanRequest, rates: np.ndarray) -> ActuatorSchedule:
    """The NLP's rates ``U`` (N, 2; per unit normalised time) on the via points' schedule:
    ``u_k = U_k / (N h_k)``."""
    N = rates.shape[0]
    breaks = plan_breaks(req, N)
    h = np.diff(breaks)
    return ActuatorSchedule(breaks=breaks, rates=np.asarray(rates, float) / (N * h)[:, None])


def pin_via_nodes(req: PlanRequest, N: int, lb: np.ndarray, ub: np.ndarray) -> None:
    """Fix each via point's joint at its node: ``lb = ub = angle`` in the variable tables
    ``(N+1, stride)`` (row ``k``: ``q_k = (phi, th_1..th_n)`` first), in place."""
    for vp in req.via_points:
        k = _node_of(req, N, vp)
        lb[k, 1 + vp.index] = ub[k, 1 + vp.index] = vp.angle


def correct_rates_through_vias(req: PlanRequest, nlp: Any, rates: np.ndarray, phi_end: float,
                               exact_end: np.ndarray | None = None
                               ) -> tuple[np.ndarray, list[float]]:
    """Newton steps that move the rates onto the goal AND the via angles of the fine map.

    As :func:`.correction.correct_rates` (``phi``'s end held at the NLP's ``phi_end``; with
    ``exact_end`` the fine map's error at the end is subtracted from the goal), with one more
    residual row per via point: ``th_j`` at its node ``k`` of the fine map, which is the fine
    end map under the rates with intervals ``k..N-1`` set to zero (the model is driftless),
    and its Jacobian the NLP map's with those columns zero.

    Returns
    -------
    rates : ndarray (N, 2)
        The best rates met.
    errors : list of float
        The largest residual (goal and via points, rad) before each step and after the last.
    """
    N = rates.shape[0]
    q0 = req.q_start()
    target = np.concatenate([[phi_end], req.goal])
    if exact_end is not None:
        target = target - (np.asarray(exact_end, float)
                           - nlp.fine_end(q0, rates, req.robot.gains))
    rows = [(_node_of(req, N, vp), 1 + vp.index, vp.angle) for vp in req.via_points]
    U = np.array(rates, float)
    errors: list[float] = []
    best: tuple[float, np.ndarray] | None = None
    for step in range(MAX_STEPS + 1):
        r_end = nlp.fine_end(q0, U, req.robot.gains) - target
        J_end = nlp.rk4_end_jacobian(q0, U, req.robot.gains)
        r_via, J_via = [], []
        for k, col, angle in rows:
            Uk = U.copy()
            Uk[k:] = 0.0
            r_via.append(float(nlp.fine_end(q0, Uk, req.robot.gains)[col]) - angle)
            Jk = nlp.rk4_end_jacobian(q0, Uk, req.robot.gains)[col].copy()
            Jk[2 * k:] = 0.0
            J_via.append(Jk)
        r = np.concatenate([r_end, r_via])
        err = float(max(np.max(np.abs(r_end[1:])), np.max(np.abs(r_via))))
        errors.append(err)
        if not math.isfinite(err):
            break
        if best is None or err < best[0]:
            best = (err, U)
        if err <= TARGET or step == MAX_STEPS:
            break
        J = np.vstack([J_end, np.array(J_via)])
        U = U - np.linalg.lstsq(J, r, rcond=None)[0].reshape(N, 2)
    return (U if best is None else best[1]), errors


@contextlib.contextmanager
def via_time_law_errors(req: PlanRequest) -> Iterator[None]:
    """Inside: a time law's refusal of fixed times (:func:`optimizer.timing.time_law` with
    ``fixed_times``, worded for constraint points) said in terms of the via points."""
    try:
        yield
    except InfeasibleError as exc:
        if not req.via_points or "constraint points fix" not in exc.message:
            raise
        raise InfeasibleError(
            exc.message.replace("the constraint points fix the plan's times",
                                "the via points fix the plan's times (each via time is a "
                                "node of the path)").replace(": a longer duration",
                                                             ": give a longer duration"),
            field=exc.field, diagnostics=exc.diagnostics) from None


def via_failure(req: PlanRequest, exc: PlannerError) -> PlannerError:
    """A failure to plan a request with via points, naming ``via_points`` when it names no
    other field (the via points are then what the methods could not meet); ``exc`` itself
    otherwise."""
    if not req.via_points or exc.field is not None:
        return exc
    return type(exc)(
        exc.message + " (with via_points: no path was found through every via point at its "
        "time; move a via point's time or angle closer to the straight path, or drop it)",
        field="via_points", diagnostics={**exc.diagnostics,
                                         "via_points": [v.as_dict() for v in req.via_points]})


def _state_at(req: PlanRequest, path: SampledPath, rule: str, t: float) -> np.ndarray:
    """The original model at ``t`` under the handed-out rates ``path.u`` by their ``rule``
    (``linear`` or ``zoh``), from the last sample at or before ``t`` (the answer's own state
    there, which the answer's validation re-integrated): scipy's DOP853, tight tolerances."""
    ts = np.asarray(path.t, float)
    i = int(np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.size - 2))
    q_i = np.asarray(path.q[i], float)
    if abs(t - ts[i]) <= 1e-12 * max(1.0, ts[-1]):
        return q_i
    u = np.asarray(path.u, float)
    t0, t1 = float(ts[i]), float(ts[i + 1])
    gains, exps = req.robot.gains, req.robot.exponents

    def rates(s: float) -> tuple[float, float]:
        if rule == "zoh":
            return float(u[i, 0]), float(u[i, 1])
        w = (s - t0) / (t1 - t0)
        return tuple((1 - w) * u[i] + w * u[i + 1])  # type: ignore[return-value]

    def f(s: float, q: np.ndarray) -> list[float]:
        return vector_field(gains, exps, q, *rates(s))

    sol = solve_ivp(f, (t0, t), q_i, method="DOP853", rtol=1e-12, atol=1e-13)
    return np.asarray(sol.y[:, -1], float)


def check_handed_out(req: PlanRequest, path: SampledPath, rule: str) -> list[dict[str, Any]]:
    """Each via point's angle on the handed-out path at its time; refuse a path that misses
    one by more than :data:`VIA_TOLERANCE` (:data:`HELD_VIA_TOLERANCE` held).

    Returns
    -------
    list of dict
        ``time``, ``joint``, ``angle`` (asked), ``reached`` and ``error`` (rad), in the
        request's order (``diagnostics.via_points``).

    Raises
    ------
    NumericalError
        A via point is missed (naming ``controller_period`` for a held form, ``via_points``
        else).
    """
    tol = HELD_VIA_TOLERANCE if rule == "zoh" else VIA_TOLERANCE
    out: list[dict[str, Any]] = []
    states: dict[float, np.ndarray] = {}
    for vp in req.via_points:
        if vp.time not in states:
            states[vp.time] = _state_at(req, path, rule, vp.time)
        reached = float(states[vp.time][1 + vp.index])
        out.append({**vp.as_dict(), "reached": reached, "error": abs(reached - vp.angle)})
    worst = max(out, key=lambda d: d["error"])
    if not worst["error"] <= tol:
        held = rule == "zoh"
        raise NumericalError(
            f"the handed-out path misses the via point {worst['joint']} = {worst['angle']:g} "
            f"rad at t = {worst['time']:g} s by {worst['error']:.3g} rad (tolerance {tol:g} "
            "rad)" + ("; a shorter controller_period holds the plan closer" if held else ""),
            field="controller_period" if held else "via_points",
            diagnostics={"via_points": out, "tolerance": tol})
    return out

