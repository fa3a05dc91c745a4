"""Time laws: closed forms of the rest-to-rest profiles, and plans that start and end at rest
with continuous rates inside the request's limits, checked independently.

The profiles against their textbook durations (trapezoid, S-curve) and a dense grid of their
own derivatives; the plans against scipy's DOP853 replay of the original model under each
handed-out form's documented rule (tests/replay_support.py), the forms' rates and their
derivatives evaluated on dense grids from the handed-out numbers alone (linear interpolation's
slopes, the cubic Hermite basis), and the indicators re-measured on a dense scipy replay.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from optimizer.errors import InfeasibleError, PlannerError
from optimizer.indicators import compute_indicators
from optimizer.model import Robot
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest
from optimizer.timing import (Limits, geometric_path, ramp_profile, scurve_profile,
                              smooth_profile, time_law, trapezoid_profile)
from replay_support import (joint_trajectory_arrays, quintic_rates, reachable_goals, replay_linear,
                            replay_quintic, replay_zoh)

GOALS = {n: reachable_goals(n, 1, 16 + n) for n in (3, 4)}
REVERSING = (tuple(np.radians([10.0, 20.0, 30.0])), tuple(np.radians([40.0, 25.0, 15.0])))


def _dense(profile, points=200001):
    t = np.linspace(0.0, profile.duration, points)
    return t, profile.evaluate(t)


# ---------------------------------------------------------------------- closed forms
@pytest.mark.parametrize("L, V, A", [(2.0, 1.0, 5.0), (0.1, 1.0, 5.0), (3.0, 0.7, 0.2)])
def test_trapezoid_duration_is_the_textbook_one(L, V, A):
    p = trapezoid_profile(L, V, A)
    expected = L / V + V / A if L >= V * V / A else 2.0 * math.sqrt(L / A)
    assert p.duration == pytest.approx(expected, rel=1e-12)
    _, (x, v, a, _) = _dense(p)
    assert x[0] == 0.0 and x[-1] == pytest.approx(L, rel=1e-12)
    assert v[0] == 0.0 and abs(v[-1]) < 1e-12
    assert v.max() <= V * (1 + 1e-12) and np.abs(a).max() <= A * (1 + 1e-12)
    assert np.max(np.abs(np.diff(v))) < 1e-4          # continuous speed


def _scurve_duration(L, V, A, J):
    """The S-curve's duration from the four textbook cases (peak speed V or not, peak
    acceleration A or not), written independently of the implementation."""
    # V reached?
    ta_v = V / A + A / J if V * J >= A * A else 2.0 * math.sqrt(V / J)
    if V * ta_v <= L:
        return L / V + ta_v
    # V not reached: the rise and fall meet; A reached or not
    v = (L * L * J / 4.0) ** (1.0 / 3.0)
    if v * J <= A * A:
        return 4.0 * (L / (2.0 * J)) ** (1.0 / 3.0)
    roots = np.roots([1.0 / A, A / J, -L])           # v^2 / A + v A / J = L
    v = float(max(r.real for r in roots if abs(r.imag) < 1e-12))
    return 2.0 * (v / A + A / J)


@pytest.mark.parametrize("L, V, A, J", [
    (2.0, 1.0, 2.0, 20.0),     # V and A reached
    (2.0, 1.0, 5.0, 20.0),     # V reached, A not
    (0.01, 1.0, 5.0, 20.0),    # neither
    (0.5, 3.0, 1.0, 50.0),     # A reached, V not
])
def test_scurve_duration_is_the_textbook_one(L, V, A, J):
    p = scurve_profile(L, V, A, J)
    assert p.duration == pytest.approx(_scurve_duration(L, V, A, J), rel=1e-9)
    _, (x, v, a, j) = _dense(p)
    assert x[-1] == pytest.approx(L, rel=1e-9) and abs(v[-1]) < 1e-9 and abs(a[-1]) < 1e-9
    assert v.max() <= V * (1 + 1e-9) and np.abs(a).max() <= A * (1 + 1e-9)
    assert np.abs(j).max() <= J * (1 + 1e-12)
    assert np.max(np.abs(np.diff(a))) < 1e-2          # continuous acceleration


def test_ramp_and_smooth_profiles_peaks():
    L, D = 1.7, 2.3
    _, (x, v, a, _) = _dense(ramp_profile(L, D))
    assert x[-1] == pytest.approx(L) and v.max() == pytest.approx(4 * L / (3 * D), rel=1e-9)
    assert np.abs(a).max() == pytest.approx(16 * L / (3 * D * D), rel=1e-9)
    _, (x, v, a, j) = _dense(smooth_profile(L, D))
    assert x[-1] == pytest.approx(L) and v.max() == pytest.approx(2 * L / D, rel=1e-6)
    assert np.abs(a).max() == pytest.approx(8 * L / D ** 2, rel=1e-4)


# ---------------------------------------------------------------------- the law on a path
def _steps(rates, breaks):
    rates, breaks = np.asarray(rates, float), np.asarray(breaks, float)

    def u(s):
        k = np.clip(np.searchsorted(breaks, s, side="right") - 1, 0, len(rates) - 1)
        return rates[k]
    return u


def test_the_law_stops_only_where_the_direction_turns():
    """Rates (1, 2) then (2, 4) (same direction, twice the speed) then (1, -1): one stop
    inside, at the turn; across the parallel break the rates stay continuous."""
    u = _steps([[1, 2], [2, 4], [1, -1]], [0, 0.5, 0.7, 1.0])
    path = geometric_path(u, np.array([0, 0.5, 0.7, 1.0]), constant=True)
    assert path.stop.tolist() == [True, False, True, True]
    law = time_law(path, Limits(), None, 2.0)
    assert law.T == pytest.approx(2.0) and law.stops.size == 3
    t = np.linspace(0.0, law.T, 400001)
    r = law.rates(t)
    assert np.all(r[0] == 0) and np.allclose(r[-1], 0, atol=1e-12)
    assert np.max(np.abs(np.diff(r, axis=0))) < 1e-3            # no jump anywhere
    assert np.allclose(law.rates(law.stops[1:2]), 0.0, atol=1e-12)
    # the path is the plan's: the integral of the rates is the plan's displacement
    disp = np.trapezoid(r, t, axis=0)
    assert np.allclose(disp, [0.5 + 0.4 + 0.3, 1.0 + 0.8 - 0.3], atol=1e-6)


def test_a_stop_at_every_break_keeps_the_plans_timing_and_path():
    """Constant rates turning at every break (the shooting plans): a stop at every break, at
    the plan's own times scaled to T; in each piece the speed ramps over a quarter of it and
    cruises at the piece's mean speed / 0.75; the rates integrate to the plan's
    displacement; the same law as the segment-by-segment construction."""
    from optimizer.timing import RAMP, _assemble, _plan_timed

    rates = np.array([[1.0, 2.0], [-0.5, 1.0], [2.0, -1.0], [0.3, 0.3], [-1.0, -2.0]])
    breaks = np.array([0.0, 0.1, 0.35, 0.5, 0.8, 1.0])
    path = geometric_path(_steps(rates, breaks), breaks, constant=True)
    assert path.stop.all()
    T = 2.0
    law = time_law(path, Limits(), None, T)
    assert np.allclose(law.stops, T * breaks, atol=1e-15)
    mids = 0.5 * (law.stops[:-1] + law.stops[1:])
    D, d = np.diff(law.stops), np.diff(breaks)
    assert np.allclose(law.rates(mids), rates * (d / D / (1.0 - RAMP))[:, None], rtol=1e-12)
    assert np.allclose(law.rates(law.stops), 0.0, atol=1e-12)
    t = np.linspace(0.0, T, 200001)
    disp = np.trapezoid(law.rates(t), t, axis=0)
    assert np.allclose(disp, d @ rates, atol=1e-8)
    scale = T / breaks[-1]
    parts = [_plan_timed(path, k, k + 1, scale) for k in range(rates.shape[0])]
    ref = _assemble(path, parts, None, None, Limits())
    for f in ("start", "length", "x0", "v0", "a0", "jerk"):
        assert np.array_equal(getattr(law.phases, f), getattr(ref.phases, f)), f
    assert np.array_equal(law.stops, ref.stops)


def test_the_shortest_duration_within_limits_and_a_too_short_one():
    u = _steps([[1, 2], [1, -1]], [0, 0.5, 1.0])
    path = geometric_path(u, np.array([0, 0.5, 1.0]), constant=True)
    lim = Limits((1.0, 1.0), (5.0, 5.0))
    law = time_law(path, lim, None, 1.0, margin=0.0)
    # segment 1: |u2| = 2 lam' binds: V = 0.5, A = 2.5, L = 0.5; segment 2: V = 1, A = 5,
    # L = 0.5 (trapezoids, independently)
    expect = (0.5 / 0.5 + 0.5 / 2.5) + (2 * math.sqrt(0.5 / 5.0) if 0.5 < 1 / 5 else
                                        0.5 / 1.0 + 1.0 / 5.0)
    assert law.shortest == pytest.approx(expect, rel=1e-12) and law.T == law.shortest
    t = np.linspace(0.0, law.T, 200001)
    r, dr = law.rates_and_derivative(t)
    assert np.abs(r).max() <= 1.0 + 1e-9 and np.abs(dr).max() <= 5.0 * (1 + 1e-6)
    with pytest.raises(InfeasibleError) as err:
        time_law(path, lim, 0.9 * expect, 1.0, margin=0.0)
    assert err.value.field == "duration"
    assert err.value.diagnostics["shortest_duration"] == pytest.approx(expect)
    assert err.value.diagnostics["binding_limit"] in ("max_u1", "max_u2", "max_du1", "max_du2")
    longer = time_law(path, lim, 2.0 * expect, 1.0, margin=0.0)
    assert longer.T == pytest.approx(2.0 * expect)
    r2 = longer.rates(np.linspace(0.0, longer.T, 20001))
    assert np.abs(r2).max() == pytest.approx(0.5 * np.abs(r).max(), rel=1e-3)


# ---------------------------------------------------------------------- plans
LIMITS = {"max_u1": 1.0, "max_u2": 1.0, "max_du1": 5.0, "max_du2": 5.0}
LIMITED = [(3, m) for m in ("polynomial", "retimed", "constraint_points", "shooting",
                            "penalty")] + [(4, m) for m in ("retimed", "shooting")]


def _request(n, method, goal=None, **kw):
    start, end = goal if goal is not None else GOALS[n][0]
    return PlanRequest(start=start, goal=end, robot=Robot.default(n), method=method,
                       time_limit=60.0, **kw)


def _at_rest_and_continuous(p):
    t, u = p.path.t, p.path.u
    assert np.all(np.diff(t) > 0.0)                         # no repeated time: no jump
    assert np.array_equal(u[0], [0.0, 0.0]) and np.array_equal(u[-1], [0.0, 0.0])


def _goal_error(qf, req):
    return float(np.max(np.abs(qf[1:] - np.array(req.goal))))


def _quintic_peaks(t, x, v, a, points=201):
    """Peaks of the rates, their derivatives and second derivatives of the quintic Hermite
    interpolant (scipy's BPoly) on a dense grid per interval."""
    rates = quintic_rates(t, x, v, a)
    s = np.linspace(0.0, 1.0, points)[:, None]
    dense = (t[:-1] + s * np.diff(t)).ravel()
    return tuple(np.max(np.abs(rates(dense, order)), axis=0) for order in range(3))


@pytest.mark.parametrize("n, method", LIMITED)
def test_limited_plans_keep_their_limits_in_every_form(n, method):
    """max_u = 1, max_du = 5: the shortest duration along the path; every form's rates and
    derivatives within 1 % of the limits between the samples; each form replayed by scipy
    reaches the goal within 1e-6 rad, inside the region."""
    req = _request(n, method, **LIMITS, joint_trajectory=True)
    p = plan(req)
    assert p.time_law is not None and p.duration == pytest.approx(p.time_law.shortest)
    _at_rest_and_continuous(p)
    t, u = p.path.t, p.path.u
    # the linear form: its extremes are at the samples, its derivative the chords' slopes
    assert np.abs(u).max() <= 1.0 * 1.01
    assert np.max(np.abs(np.diff(u, axis=0) / np.diff(t)[:, None])) <= 5.0 * 1.01
    qf, margin = replay_linear(p.robot, t, u, req.q_start())
    assert _goal_error(qf, req) < 1e-6 and margin > 0.0
    # the exact law on a dense grid
    r, dr = p.rates_at(np.linspace(0.0, p.duration, 50001))
    assert np.abs(r).max() <= 1.0 * 1.01 and np.abs(dr).max() <= 5.0 * 1.01
    # the JointTrajectory form between its points
    tj, xj, vj, aj = joint_trajectory_arrays(p.to_dict()["joint_trajectory"])
    assert np.array_equal(vj[0], [0.0, 0.0]) and np.array_equal(vj[-1], [0.0, 0.0])
    peak_u, peak_du, _ = _quintic_peaks(tj, xj, vj, aj)
    assert peak_u.max() <= 1.0 * 1.01 and peak_du.max() <= 5.0 * 1.01, (peak_u, peak_du)
    qf, margin = replay_quintic(p.robot, tj, xj, vj, aj, req.q_start())
    assert _goal_error(qf, req) < 1e-6 and margin > 0.0


@pytest.mark.parametrize("method", ["retimed", "shooting"])
def test_limited_held_form_keeps_the_rate_limits(method):
    req = _request(3, method, **LIMITS, controller_period=0.01)
    p = plan(req)
    assert np.abs(p.path.u).max() <= 1.0 * 1.01
    qf, margin = replay_zoh(p.robot, p.path.t, p.path.u, req.q_start())
    assert _goal_error(qf, req) < 1e-6 and margin > 0.0


def test_a_jerk_limit_gives_s_curves_the_joint_trajectory_keeps():
    """With max_ddu the law of a shooting plan is made of S-curves; the JointTrajectory form's
    second derivative (constant per interval for a cubic Hermite) stays within it."""
    lim = dict(LIMITS, max_ddu1=40.0, max_ddu2=40.0)
    req = _request(3, "shooting", goal=REVERSING, **lim, joint_trajectory=True)
    p = plan(req)
    assert np.any(p.time_law.phases.jerk != 0.0)
    t = np.linspace(0.0, p.duration, 100001)
    r, dr = p.rates_at(t)
    assert np.abs(r).max() <= 1.01 and np.abs(dr).max() <= 5.05
    ddr = np.diff(dr, axis=0) / np.diff(t)[:, None]
    assert np.abs(ddr).max() <= 40.0 * 1.01
    tj, xj, vj, aj = joint_trajectory_arrays(p.to_dict()["joint_trajectory"])
    _, _, ddu = _quintic_peaks(tj, xj, vj, aj)
    assert ddu.max() <= 40.0 * 1.01
    qf, margin = replay_quintic(p.robot, tj, xj, vj, aj, req.q_start())
    assert _goal_error(qf, req) < 1e-6 and margin > 0.0


def test_a_duration_too_short_for_the_limits_names_them():
    req = _request(3, "shooting", **LIMITS, duration=0.05)
    with pytest.raises(InfeasibleError) as err:
        plan(req)
    e = err.value
    assert e.field == "duration" and "shortest duration" in str(e)
    shortest = e.diagnostics["shortest_duration"]
    assert shortest > 0.05 and e.diagnostics["binding_limit"] in LIMITS
    ok = plan(_request(3, "shooting", **LIMITS, duration=shortest * 1.01))
    assert ok.duration == pytest.approx(shortest * 1.01)


def _dense_replay(robot, t, u, q0, per_interval=24):
    """scipy's replay of the linear form, with states at many points of every interval."""
    K = np.array(robot.gains)
    m = np.array(robot.exponents, float)
    q = np.asarray(q0, float)
    ts, qs = [t[:1]], [q[None]]
    for k in range(t.size - 1):
        a, b = t[k], t[k + 1]
        h = b - a

        def f(tt, y, k=k, a=a, h=h):
            w = (tt - a) / h
            uu = (1 - w) * u[k] + w * u[k + 1]
            return np.concatenate([[uu[0], uu[1]], K * np.cos(y[1:-1]) ** m * uu[0]])
        grid = np.linspace(a, b, per_interval + 1)[1:]
        sol = solve_ivp(f, (a, b), q, method="DOP853", rtol=1e-12, atol=1e-12, t_eval=grid)
        q = sol.y[:, -1]
        ts.append(grid)
        qs.append(sol.y.T)
    return np.concatenate(ts), np.vstack(qs)


@pytest.mark.parametrize("n, method, goal", [
    (3, "auto", None), (4, "auto", None), (3, "shooting", REVERSING),
    (3, "polynomial", None), (3, "retimed", None), (3, "constraint_points", None)])
def test_indicators_are_those_of_the_handed_out_path(n, method, goal):
    """The answer's reversals and deviation equal those of scipy's dense replay of the
    handed-out linear form (deviation within 0.01 deg)."""
    req = _request(n, method, goal=goal)
    p = plan(req)
    _at_rest_and_continuous(p)
    td, qd = _dense_replay(p.robot, p.path.t, p.path.u, req.q_start())
    ref = compute_indicators(td, qd, None)
    ind = p.indicators
    assert (ind.reversals_phi, ind.reversals_th1) == (ref.reversals_phi, ref.reversals_th1)
    assert abs(ind.deviation - ref.deviation) <= math.radians(0.01)
    assert _goal_error(qd[-1], req) < 1e-6


def test_a_correction_that_adds_a_reversal_is_refused():
    """The guard against a handed-out path that is not the plan's: told that the plan had
    one reversal fewer than the handed-out path has, the finishing step refuses it."""
    from optimizer.planner import finish

    req = _request(3, "shooting", goal=REVERSING)
    p = plan(req)
    assert p.indicators.reversals >= 1
    fewer = p.indicators.__class__(**{**p.indicators.__dict__,
                                      "reversals_phi": p.indicators.reversals_phi - 1,
                                      "deviation": p.indicators.deviation})
    with pytest.raises(InfeasibleError) as err:
        finish.retime_and_execute(req, p.inputs.u, p.inputs.breaks, True,
                                  float(p.verification.final[0]), fewer, "shooting")
    assert err.value.field == "samples" and "reverses" in str(err.value)
    smaller = p.indicators.__class__(**{**p.indicators.__dict__, "deviation": 0.5 *
                                        p.indicators.deviation - 0.01})
    with pytest.raises(InfeasibleError):
        finish.retime_and_execute(req, p.inputs.u, p.inputs.breaks, True,
                                  float(p.verification.final[0]), smaller, "shooting")


def test_the_six_joint_goal_of_issue_25_is_honest_or_refused():
    """Issue 25's 6-joint goal: on the landed main the correction blew the handed-out rates
    up to 23.7 rad/s with 6 + 6 reversals while the indicators told the exact plan's 1 + 2.
    Now it is either refused with a typed error, or handed out with the indicators of what is
    handed out (checked on scipy's replay) and sane rates."""
    D = np.radians
    req = PlanRequest.from_dict({
        "robot": {}, "start": list(D([50.13, 55.38, 25.31, 37.52, 55.82, 54.66])),
        "goal": list(D([22.05, 53.86, 26.64, 41.97, 59.09, 55.36])), "time_limit": 20.0})
    try:
        p = plan(req)
    except PlannerError as e:
        assert e.diagnostics is not None
        return
    td, qd = _dense_replay(p.robot, p.path.t, p.path.u, req.q_start())
    ref = compute_indicators(td, qd, None)
    assert (p.indicators.reversals_phi, p.indicators.reversals_th1) == (
        ref.reversals_phi, ref.reversals_th1)
    assert abs(p.indicators.deviation - ref.deviation) <= math.radians(0.01)
    assert np.abs(p.path.u).max() < 10.0


def test_an_inaccurate_convex_retiming_warns_no_one(monkeypatch):
    """cvxpy warns when Clarabel ends "optimal_inaccurate"; the retiming keeps such a law
    (its limits are checked on the handed-out path like any other) and its warning must not
    reach the caller's (the service's) stderr."""
    import warnings

    import cvxpy as cp

    solve = cp.Problem.solve
    calls = []

    def inaccurate(self, *args, **kwargs):
        calls.append(1)
        warnings.warn("Solution may be inaccurate. Try another solver, adjusting the solver "
                      "settings, or solve with verbose=True for more information.", UserWarning)
        return solve(self, *args, **kwargs)

    monkeypatch.setattr(cp.Problem, "solve", inaccurate)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p = plan(_request(3, "retimed", **LIMITS))
    assert calls  # the convex retiming ran
    assert np.abs(p.path.u).max() <= 1.0 * 1.01


@pytest.mark.parametrize("seed", range(4))
def test_the_rates_are_linear_between_the_laws_kinks_even_on_them(seed):
    """Pieces of one direction and different speeds (no stop between them: the slopes keep
    ``g`` continuous), as a plan whose ``th1`` rests while ``phi`` moves: the law's rates at
    its kinks (the phases' starts, where the linear form samples them) and midway between
    them lie on one line per interval, so the linear form holds them exactly. A ``lam`` within
    rounding of a knot once took the next piece's rates with this piece's slope: a spike at
    the sample (a 4-joint plan's linear form ended 6e-4 rad off its goal)."""
    from optimizer.actuation import ActuatorSchedule

    rng = np.random.default_rng(seed)
    N = 30
    speeds = rng.uniform(0.2, 3.0, N)
    rates = np.column_stack([speeds, np.zeros(N)])
    rates[N // 2:, 1] = -0.5 * speeds[N // 2:]          # one turn: a stop inside
    breaks = np.linspace(0.0, 1.0, N + 1)
    sched = ActuatorSchedule(breaks=breaks, rates=rates)
    path = geometric_path(sched.u, breaks, constant=True)
    assert not path.stop[1:N // 2].any()
    law = time_law(path, Limits(), None, 1.0)
    assert law.piecewise_linear
    kinks = np.union1d(law.phases.start, law.stops)
    at = law.rates(kinks)
    mid = law.rates(0.5 * (kinks[:-1] + kinks[1:]))
    peak = float(np.max(np.abs(at)))
    assert np.max(np.abs(mid - 0.5 * (at[:-1] + at[1:]))) <= 1e-12 * peak
