"""Planning in legs (optimizer.planner.legs): a goal that one NLP does not reach, reached through
intermediate goals on the joint-space segment, and proved as one path.

Every plan here is checked independently: the handed-out linear rates replayed with scipy's
DOP853 on the original model from the request's start end on the goal, inside the region."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optimizer.errors import InfeasibleError
from optimizer.model import Robot
from optimizer.planner.context import Deadline, PlanContext
from optimizer.planner.legs import MAX_LEGS, plan_in_legs
from optimizer.planner.plan import plan
from optimizer.planner.registry import get
from optimizer.problem import PlanRequest
from replay_support import replay_linear

D = math.radians


def _replayed(p, req) -> None:
    t, u = np.asarray(p.path.t, float), np.asarray(p.path.u, float)
    final, margin = replay_linear(req.robot, t, u, req.q_start())
    assert np.max(np.abs(final[1:] - np.array(req.goal))) < 1e-6
    assert margin > 0.0


def _short_legs_only(longest: float, whole: PlanRequest, calls: list[PlanRequest],
                     plans: list | None = None):
    """A leg planner that finds no path (as a search: ``nlp_failed``) for a leg longer than
    ``longest`` of the whole segment, and plans the others with ``shooting`` (appended to
    ``plans``)."""
    span = np.max(np.abs(np.subtract(whole.goal, whole.start)))

    def plan_leg(leg: PlanRequest, ctx: PlanContext):
        calls.append(leg)
        if np.max(np.abs(np.subtract(leg.goal, leg.start))) > longest * span + 1e-9:
            raise InfeasibleError("the NLP found no path from any start",
                                  diagnostics={"blocking": "nlp_failed", "tried": []})
        out = get("shooting").plan(leg, ctx)
        if plans is not None:
            plans.append(out)
        return out
    return plan_leg


def test_legs_are_halved_until_each_plans_and_the_whole_path_reaches_the_goal():
    req = PlanRequest(start=(D(10), D(20), D(30)), goal=(D(40), D(25), D(15)))
    calls: list[PlanRequest] = []
    plans: list = []
    p = plan_in_legs(req, PlanContext(Deadline(60.0)),
                     _short_legs_only(0.3, req, calls, plans))
    legs = p.diagnostics["legs"]
    assert legs["count"] == 4 and legs["fractions"] == [0.25, 0.5, 0.75]
    # halves refused, then quarters: 0-0.5 (no), 0-0.25, 0.25-0.5, 0.5-1 (no), 0.5-0.75, 0.75-1
    assert len(calls) == 6
    # the legs that planned: each starts where the one before it ended (its re-integrated end,
    # phi included), which is within the plan's tolerance of the planned point, not at it
    planned = [calls[1], calls[2], calls[4], calls[5]]
    start, goal = np.array(req.start), np.array(req.goal)
    assert planned[0].start == req.start and planned[0].phi_start == 0.0
    for k, leg in enumerate(planned[1:], start=1):
        point = start + 0.25 * k * (goal - start)
        assert np.max(np.abs(np.array(leg.start) - point)) < 1e-8
        assert (leg.phi_start,) + leg.start == plans[k - 1].verification.final
    assert planned[-1].goal == req.goal
    _replayed(p, req)
    # the proof is of the whole path: one schedule from the request's start
    assert p.verification.terminal_error < 1e-8 and p.margin > 0.0


def test_a_leg_that_finds_nothing_at_the_smallest_split_ends_the_legs_with_the_search_named():
    req = PlanRequest(start=(D(10), D(20), D(30)), goal=(D(40), D(25), D(15)))
    calls: list[PlanRequest] = []
    with pytest.raises(InfeasibleError) as info:
        plan_in_legs(req, PlanContext(Deadline(60.0)), _short_legs_only(0.1, req, calls))
    err = info.value
    assert err.diagnostics["blocking"] == "nlp_failed"
    assert f"1/{MAX_LEGS}" in err.message
    # 0-0.5, 0-0.25, 0-0.125: the smallest leg failed and nothing was split further
    assert len(calls) == 3


def test_auto_plans_in_legs_where_shooting_found_no_path_to_the_whole_goal(monkeypatch):
    """``auto`` tries the legs after ``shooting`` (and the family) failed as a search, before
    ``penalty``; the answer is the legs' path, verified here on the handed-out rates."""
    req = PlanRequest(start=(D(10), D(20), D(30)), goal=(D(40), D(25), D(15)))
    shooting = type(get("shooting"))
    real_run = shooting.run

    def whole_move_fails(self, r, ctx):
        if r.start == req.start and r.goal == req.goal:
            raise InfeasibleError("the NLP found no path from any start",
                                  diagnostics={"blocking": "nlp_failed", "tried": []})
        return real_run(self, r, ctx)

    monkeypatch.setattr(shooting, "run", whole_move_fails)
    p = plan(req)
    tried = [t["method"] for t in p.diagnostics["auto"]["tried"]]
    assert tried[0] == "shooting" and "legs" in tried and "penalty" not in tried
    assert p.diagnostics["legs"]["count"] == 2
    _replayed(p, req)


def test_legs_are_not_tried_where_shooting_proved_its_failure_or_the_request_fixes_phi(
        monkeypatch):
    req = PlanRequest(start=(D(10), D(20), D(30)), goal=(D(40), D(25), D(15)))

    def proved(self, r, ctx):
        raise InfeasibleError("th1 cannot reach its goal within its bounds",
                              diagnostics={"blocking": "reach"})

    monkeypatch.setattr(type(get("shooting")), "run", proved)
    monkeypatch.setattr(type(get("penalty")), "run", proved)
    with pytest.raises(InfeasibleError) as info:
        plan(req)
    assert "legs" not in [t["method"] for t in info.value.diagnostics["auto"]["tried"]]


@pytest.mark.slow
def test_five_joints_each_moving_70_deg_is_planned_in_legs():
    """Every joint of a 5-joint arm 10 -> 80 deg: one NLP converges 0.39 rad off the goal
    (``shooting`` and ``penalty`` both found no path before the legs); in legs it plans."""
    req = PlanRequest(start=(D(10),) * 5, goal=(D(80),) * 5, robot=Robot.default(5),
                      time_limit=120.0)
    p = plan(req)
    assert p.diagnostics["legs"]["count"] >= 2
    _replayed(p, req)
