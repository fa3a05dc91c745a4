"""A continuation of a plan asked with rate limits keeps to them (checked on the handed-out
samples by finite differences, independently of the library's own measurement), reaches the
goal on the tests' model (scipy), carries the limits on to the next replan, and ends later
than the plan only as the limits need; a duration too short for them is refused, naming it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optimizer.errors import InfeasibleError
from optimizer.planner.plan import plan
from optimizer.planner.replan import replan
from optimizer.problem import PlanRequest

from reference import PROTOTYPE_K
from test_replan import run_plant

START = (math.radians(10),) * 3
GOAL = (math.radians(30),) * 3
LIMITS = [
    {"max_u1": 1.0, "max_u2": 1.0, "max_du1": 5.0, "max_du2": 5.0},
    {"max_u1": 0.8, "max_u2": 0.8, "max_du1": 4.0, "max_du2": 4.0, "max_ddu1": 40.0,
     "max_ddu2": 40.0},
    {"max_u1": 0.5, "max_u2": 0.5},
]


def peaks(ans: dict) -> tuple[np.ndarray, np.ndarray]:
    """Largest |u_i| of the samples and |u_i'| of their linear interpolant."""
    t = np.asarray(ans["path"]["t"])
    u = np.asarray(ans["path"]["u"])
    dt = np.diff(t)
    ok = dt > 1e-12
    return np.abs(u).max(axis=0), (np.abs(np.diff(u, axis=0))[ok] / dt[ok, None]).max(axis=0)


def within(ans: dict, lim: dict) -> bool:
    u, du = peaks(ans)
    tol = 1.0 + 1e-6
    return all(u[i] <= lim.get(f"max_u{i + 1}", math.inf) * tol
               and du[i] <= lim.get(f"max_du{i + 1}", math.inf) * tol for i in range(2))


@pytest.mark.parametrize("lim", LIMITS, ids=["u_du", "u_du_ddu", "u"])
def test_continuations_keep_to_the_plans_rate_limits(lim: dict) -> None:
    answer = plan(PlanRequest(start=START, goal=GOAL, **lim)).to_dict()
    assert within(answer, lim)
    n = len(answer["path"]["t"])
    offsets = np.radians([0.05, -0.05, 0.05])
    for i in (0, n // 5, n // 2, (4 * n) // 5):
        t = float(answer["path"]["t"][i])
        q = np.array(answer["path"]["q"][i]) + np.r_[0.0, offsets]
        out = replan(answer, t, q)
        assert within(out, lim), (i, peaks(out))
        info = out["diagnostics"]["replan"]["limits"]
        assert info["within"] and info["bounds"] == lim
        assert out["time_law"]["limits"] == lim           # carried on
        end = run_plant(out, q, t, out["duration"], PROTOTYPE_K)
        assert np.max(np.abs(end[1:] - np.array(GOAL))) < 1e-7
        # later than the plan only by what the report says
        assert out["duration"] == pytest.approx(
            answer["duration"] + info["later_than_asked"], abs=1e-9)
        # a continuation of the continuation keeps to them too
        k = len(out["path"]["t"]) // 2
        again = replan(out, float(out["path"]["t"][k]), np.array(out["path"]["q"][k]))
        assert within(again, lim)


def test_a_duration_too_short_for_the_limits_is_refused_naming_it() -> None:
    lim = LIMITS[0]
    answer = plan(PlanRequest(start=START, goal=GOAL, **lim)).to_dict()
    i = len(answer["path"]["t"]) // 2
    t = float(answer["path"]["t"][i])
    q = np.array(answer["path"]["q"][i])
    with pytest.raises(InfeasibleError) as err:
        replan(answer, t, q, duration=t + 0.01)
    assert err.value.field == "duration"
    assert err.value.diagnostics["shortest_end"] > t + 0.01


def test_a_plan_without_limits_hands_out_none() -> None:
    answer = plan(PlanRequest(start=START, goal=GOAL)).to_dict()
    i = len(answer["path"]["t"]) // 2
    out = replan(answer, float(answer["path"]["t"][i]), np.array(answer["path"]["q"][i]))
    assert "limits" not in out["diagnostics"]["replan"]
    assert out["time_law"]["limits"] == {}
    assert out["duration"] == pytest.approx(answer["duration"])


def test_the_laws_peaks_and_slope_jumps_against_closed_forms() -> None:
    """One piece of plan time 2 at geometric rates (0.5, -0.25) within |u| <= 0.2,
    |u'| <= 0.1: sigma' is bounded by 0.2 / 0.5 = 0.4 and sigma'' by 0.2, so the trapezoid
    accelerates for 2 s, cruises 3 s and brakes 2 s (7 s: L / V + V / A); u1 peaks at 0.2 and
    its slope at 0.1, and the slope jumps by 0.1 at each of the four kinks. Under a jerk bound
    the S-curve's slopes are continuous."""
    from optimizer.planner.continuation_law import (LIMIT_MARGIN, law_within_limits,
                                                    measured_limits, slope_jump)
    from optimizer.planner.plan_state import TimeLaw
    from optimizer.timing import Limits

    breaks = np.array([0.0, 2.0])
    rates = np.array([[0.5, -0.25]])
    lim = Limits(rate=(0.2, None), accel=(0.1, None))
    law = TimeLaw(law_within_limits(1.0, 1.5, breaks, rates, lim))
    f = 1.0 - LIMIT_MARGIN
    V, A = 0.4 * f, 0.2 * f
    assert law.end - 1.0 == pytest.approx(2.0 / V + V / A, rel=1e-12)   # later than 1.5
    peaks = measured_limits(law, breaks, rates)
    assert peaks["max_u1"] == pytest.approx(0.2 * f, rel=1e-9)
    assert peaks["max_du1"] == pytest.approx(0.1 * f, rel=1e-9)
    assert peaks["max_u2"] == pytest.approx(0.1 * f, rel=1e-9)
    assert slope_jump(law, breaks, rates) == pytest.approx(0.1 * f, rel=1e-9)
    # time to spare: stretched by T / T_min, the peaks fall by it and its square
    T_min = law.end - 1.0
    slow = TimeLaw(law_within_limits(1.0, 1.0 + 2.0 * T_min, breaks, rates, lim))
    assert slow.end == pytest.approx(1.0 + 2.0 * T_min, rel=1e-12)
    assert measured_limits(slow, breaks, rates)["max_du1"] == pytest.approx(0.025 * f, rel=1e-9)
    jerk = Limits(rate=(0.2, None), accel=(0.1, None), jerk=(0.05, None))
    smooth = TimeLaw(law_within_limits(1.0, 1.5, breaks, rates, jerk))
    assert slope_jump(smooth, breaks, rates) < 1e-12
    assert measured_limits(smooth, breaks, rates)["max_ddu1"] <= 0.05 * (1 + 1e-9)


def test_a_chained_plan_with_limits_is_braked_and_continued_within_them() -> None:
    """A plan of chained inputs (the paper's polynomial method) is braked, then planned
    afresh: its braking too keeps to the acceleration bounds."""
    lim = LIMITS[0]
    answer = plan(PlanRequest(start=START, goal=GOAL, method="polynomial", **lim)).to_dict()
    for f in (0.2, 0.5):
        i = int(f * (len(answer["path"]["t"]) - 1))
        t = float(answer["path"]["t"][i])
        q = np.array(answer["path"]["q"][i]) + np.r_[0.0, 1e-3, 1e-3, 1e-3]
        out = replan(answer, t, q)
        assert out["diagnostics"]["replan"]["route"] == "full_planner"
        assert within(out, lim), peaks(out)
        end = run_plant(out, q, t, out["duration"], PROTOTYPE_K)
        assert np.max(np.abs(end[1:] - np.array(GOAL))) < 1e-7


def test_under_a_jerk_bound_the_motion_under_way_stops_on_an_s_curve() -> None:
    """Near the end (the plan's last piece) the motion under way is braked now: under a jerk
    bound on an S-curve from its speed and acceleration, so the rates' slope does not jump."""
    lim = LIMITS[1]
    answer = plan(PlanRequest(start=START, goal=GOAL, **lim)).to_dict()
    i = int(0.85 * (len(answer["path"]["t"]) - 1))
    t = float(answer["path"]["t"][i])
    q = np.array(answer["path"]["q"][i]) + np.r_[0.0, np.radians(0.05) * np.ones(3)]
    out = replan(answer, t, q)
    info = out["diagnostics"]["replan"]
    assert info["braked"]
    assert info["limits"]["slope_jump"] < 1e-9 and info["limits"]["within"]
    assert within(out, lim)
    end = run_plant(out, q, t, out["duration"], PROTOTYPE_K)
    assert np.max(np.abs(end[1:] - np.array(GOAL))) < 1e-7


def test_the_s_curve_stop_against_its_closed_form() -> None:
    """From speed 1 at rest acceleration, |a| <= 2, |jerk| <= 10: 0.2 s of jerk, 0.3 s held at
    -2, 0.2 s of jerk; 0.35 of distance (average speed 1/2); ends at rest with no
    acceleration."""
    from optimizer.planner.kept_motion import scurve_stop
    rows = scurve_stop(1.0, 0.0, 2.0, 10.0)
    assert rows is not None
    assert rows[:, 1] == pytest.approx([0.2, 0.3, 0.2], rel=1e-12)
    h, x, v, a, j = rows[-1, 1:].tolist()
    assert x + h * (v + h * (a / 2 + h * j / 6)) == pytest.approx(0.35, rel=1e-12)
    assert v + h * (a + h * j / 2) == pytest.approx(0.0, abs=1e-12)
    assert a + h * j == pytest.approx(0.0, abs=1e-12)


def test_where_the_motion_under_way_cannot_stop_within_the_limits_nothing_is_handed_out() -> None:
    """Near the plan's end the motion under way is braked in what is left of its last piece;
    where the acceleration bounds need more room than that, no continuation beyond them is
    handed out: a typed refusal naming the state and the limits (the loop runs on)."""
    from optimizer.errors import NumericalError
    lim = LIMITS[0]
    answer = plan(PlanRequest(start=START, goal=GOAL, **lim)).to_dict()
    n = len(answer["path"]["t"])
    i = int(0.97 * (n - 1))
    t = float(answer["path"]["t"][i])
    q = np.array(answer["path"]["q"][i]) + np.r_[0.0, np.radians(0.05) * np.ones(3)]
    with pytest.raises(NumericalError) as err:
        replan(answer, t, q)
    assert err.value.field == "state" and "max_du1 = 5" in err.value.message
    # with room to stop (earlier in the same piece) the braked continuation keeps to them
    j = int(0.94 * (n - 1))
    tj = float(answer["path"]["t"][j])
    qj = np.array(answer["path"]["q"][j]) + np.r_[0.0, np.radians(0.05) * np.ones(3)]
    out = replan(answer, tj, qj)
    assert out["diagnostics"]["replan"]["braked"] and within(out, lim)


def test_a_piece_no_bound_binds_keeps_a_share_of_the_time() -> None:
    """Bounds on u1 only; the second piece moves th1 alone (u1 = 0): no bound binds it, so
    it has no shortest duration, and where the first piece alone needs more than the time
    left it still gets its share (the law stays finite, its rates too)."""
    from optimizer.planner.continuation_law import law_within_limits
    from optimizer.planner.plan_state import TimeLaw
    from optimizer.timing import Limits

    breaks = np.array([0.0, 1.0, 2.0])
    rates = np.array([[1.0, 0.5], [0.0, 0.5]])
    lim = Limits(rate=(0.1, None), accel=(0.1, None))
    law = TimeLaw(law_within_limits(0.0, 1.0, breaks, rates, lim))
    P = law.phases
    assert np.isfinite(P).all() and (P[:, 1] >= 0.0).all()
    assert law.last_sigma() == pytest.approx(2.0, rel=1e-12)
    # the first piece at |u1| <= 0.1, |u1'| <= 0.1 needs 1 / 0.1 + 0.1 / 0.1 = 11 s (less the
    # margin); the second keeps a positive share
    first = P[P[:, 2] < 1.0 - 1e-12]
    assert first[-1, 0] + first[-1, 1] == pytest.approx(11.0, rel=2e-3)
    assert law.end > first[-1, 0] + first[-1, 1] + 1.0
