"""The plant's gains estimated from its measured motion (optimizer.identification), replans on
them (optimizer.planner.replan's ``gains``), and the closed loop that does both
(optimizer.analysis.closed_loop_run's ``identify``): plants are integrated by scipy on the
tests' own model, independently of the planner."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from optimizer.analysis import closed_loop_run
from optimizer.errors import InvalidRequestError
from optimizer.identification import GainEstimator
from optimizer.model import Robot
from optimizer.planner.plan import plan
from optimizer.planner.replan import replan
from optimizer.problem import PlanRequest

from reference import model_rhs, turns

START, GOAL = (0.3, 0.4, 0.5, 0.6), (0.6, 0.7, 0.75, 0.9)
ERRORS = np.array([0.04, -0.03, 0.05])           # the plant's K_i (1 + e_i)


@pytest.fixture(scope="module")
def four_joint_plan():
    return plan(PlanRequest(start=START, goal=GOAL, robot=Robot.default(4)))


def plant_run(K, m, q0, t, u) -> np.ndarray:
    """The plant from ``q0`` under the rates ``u`` sampled at ``t`` (linear between samples,
    the answer's ``path`` rule), integrated piece by piece between samples."""
    q = np.asarray(q0, float)
    for k in range(len(t) - 1):
        a, b = t[k], t[k + 1]
        ua, ub = u[k], u[k + 1]

        def rhs(s, x, a=a, b=b, ua=ua, ub=ub):
            w = (s - a) / (b - a)
            return model_rhs(x, (1 - w) * ua + w * ub, K, m)
        q = solve_ivp(rhs, (a, b), q, method="DOP853", rtol=1e-12, atol=1e-13).y[:, -1]
    return q


def test_one_period_gives_the_plants_gains(four_joint_plan) -> None:
    """A tenth of a second of the plan, run by scipy on a plant 4 %, -3 % and 5 % off: the
    estimate from the two measured states and the commanded rates is within 1e-8 of the
    plant's gains (the model's are 3-5 % off)."""
    p = four_joint_plan
    t = np.asarray(p.path.t)
    u = np.asarray(p.path.u)
    K = np.asarray(p.robot.gains) * (1.0 + ERRORS)
    m = p.robot.exponents
    sel = (t >= 0.3) & (t <= 0.4)
    ts, us = t[sel], u[sel]
    q_a = np.asarray(p.path.q)[sel][0]
    q_b = plant_run(K, m, q_a, ts, us)

    def rates(s: float) -> np.ndarray:
        return np.array([np.interp(s, ts, us[:, 0]), np.interp(s, ts, us[:, 1])])

    est = GainEstimator(p.robot)
    gains = est.update(q_a, q_b, rates, float(ts[0]), float(ts[-1]), ts)
    assert np.max(np.abs(gains / K - 1.0)) < 1e-8
    assert np.max(np.abs(np.asarray(p.robot.gains) / K - 1.0)) > 0.02
    assert est.periods == 1
    # an encoder glitch: th3 read 0.2 rad off at the period's end; its gain keeps its estimate
    glitch = q_b.copy()
    glitch[3] += 0.2
    again = est.update(q_a, glitch, rates, float(ts[0]), float(ts[-1]), ts)
    assert again[1] == pytest.approx(gains[1], rel=1e-12)
    assert np.max(np.abs(again / K - 1.0)) < 1e-8


def test_a_replan_on_given_gains_is_verified_on_them(four_joint_plan) -> None:
    """A replan told the plant's gains: its answer's robot has them, and its handed-out rates
    run by scipy on that plant from the measured state end on the goal (within 1e-6 rad)."""
    p = four_joint_plan
    answer = p.to_dict()
    K = np.asarray(p.robot.gains) * (1.0 + ERRORS)
    t0 = 0.3
    k = int(np.searchsorted(np.asarray(p.path.t), t0))
    state = np.asarray(p.path.q)[k] + np.radians([0.0, 0.05, -0.05, 0.05, 0.05])
    cont = replan(answer, float(p.path.t[k]), state, gains=K.tolist())
    assert cont["robot"]["gains"] == pytest.approx(K.tolist(), rel=1e-15)
    t = np.asarray(cont["path"]["t"])
    u = np.asarray(cont["path"]["u"])
    end = plant_run(K, p.robot.exponents, state, t, u)
    assert np.max(np.abs(end[1:] - np.asarray(GOAL))) < 1e-6
    with pytest.raises(InvalidRequestError) as err:
        replan(answer, 0.3, state, gains=[1.0, 1.0])
    assert err.value.field == "gains"


def test_the_closed_loop_with_identification_ends_on_the_goal(four_joint_plan) -> None:
    """Plant gains 4 %, -3 %, 5 % off, the start 0.5 deg off: open loop misses by more than
    1e-3 rad, the closed loop on the plan's model by more than 1e-5, the closed loop that
    estimates the gains ends within 1e-7 rad with the plant's gains found to 1e-6, every joint
    inside throughout."""
    answer = four_joint_plan.to_dict()
    start = np.asarray(START) + np.radians([0.5, -0.5, 0.5, -0.5])
    open_loop = closed_loop_run(answer, start, ERRORS, None)
    plain = closed_loop_run(answer, start, ERRORS, 0.05)
    identified = closed_loop_run(answer, start, ERRORS, 0.05, identify=True)
    assert open_loop["terminal_error"] > 1e-3
    assert plain["terminal_error"] > 1e-5
    assert identified["terminal_error"] < 1e-7
    assert identified["margin"] > 0.0
    K = np.asarray(four_joint_plan.robot.gains) * (1.0 + ERRORS)
    assert np.max(np.abs(np.asarray(identified["gains_estimated"]) / K - 1.0)) < 1e-6
    assert math.isfinite(identified["deviation"])


@pytest.mark.parametrize("last_goal", [2.2, 1.2])
def test_the_closed_loop_margin_is_measured_to_the_limits_the_planner_keeps(last_goal) -> None:
    """The last joint has no singularity: a plan whose goal has th3 past pi/2 may move it
    there, one whose start and goal lie inside keeps it in (0, pi/2). The run's margin is
    measured from th1 to the plan's bound (0.1, 1.2), th2 to (0, pi/2) and th3 to (0, pi/2)
    only in the second case (computed here from the executed path)."""
    req = PlanRequest(start=(0.3, 0.4, 0.5), goal=(0.5, 0.6, last_goal), robot=Robot.default(3),
                      joint_bounds=[(0.1, 1.2), None, None])
    answer = plan(req).to_dict()
    run = closed_loop_run(answer, (0.3, 0.4, 0.5), np.zeros(2), None)
    th = np.asarray(run["path_q"])[:, 1:]
    expected = min(np.min(th[:, 0] - 0.1), np.min(1.2 - th[:, 0]),
                   np.min(th[:, 1]), np.min(math.pi / 2 - th[:, 1]))
    if last_goal < math.pi / 2:
        expected = min(expected, np.min(th[:, 2]), np.min(math.pi / 2 - th[:, 2]))
    else:
        assert np.max(th[:, 2]) > math.pi / 2 + 0.3       # the last joint leaves (0, pi/2)
    assert run["margin"] == pytest.approx(expected, abs=1e-12)
    assert run["margin"] > 0.0




def test_the_closed_loop_can_keep_the_plans_reversals() -> None:
    """A 3-joint plan in which neither actuator reverses, a start 0.5 deg off and gains 5 %
    off. The loop that estimates the gains reaches the goal by reversing an actuator; told to
    keep the reversals, it refuses those continuations: the executed path (counted here from
    the plant's states, integrated by scipy in the loop) has none, and the miss it cannot
    remove without one stays."""
    start, goal = (0.149502, 0.688328, 1.308793), (0.893995, 0.565376, 1.188335)
    p = plan(PlanRequest(start=start, goal=goal, robot=Robot.default(3)))
    assert p.indicators.reversals_phi + p.indicators.reversals_th1 == 0
    answer = p.to_dict()
    q0 = np.asarray(start) + np.radians([0.5, -0.4, 0.3])
    errors = np.array([0.05, -0.04])
    open_loop = closed_loop_run(answer, q0, errors, None)
    free = closed_loop_run(answer, q0, errors, 0.05, identify=True)
    kept = closed_loop_run(answer, q0, errors, 0.05, identify=True, keep_reversals=True)
    for run in (free, kept):
        q = np.asarray(run["path_q"])
        run["counted"] = turns(q[:, 0]) + turns(q[:, 1])
        assert run["margin"] > 0.0
    assert open_loop["terminal_error"] > 5e-3
    assert free["terminal_error"] < 1e-9 and free["counted"] >= 1
    assert kept["counted"] == 0 and kept["replan_failures"] > 0
    assert kept["terminal_error"] > 1e-3


def test_a_continuation_that_keeps_the_signs_keeps_them_after_its_defect_step() -> None:
    """A 4-joint closed loop's replan (gains identified, reversals kept; the plan in its
    compact form, saved from the replan benchmark's loop on r4_002): the sign-keeping
    correction reaches the goal to 2e-8 rad, and the defect step after the proof (any sign)
    had turned four positive rates of phi negative, a reversal more in a continuation that
    said it kept every sign. Now: every rate keeps the sign it had in the plan's rest, the
    answer ends within 1e-6 rad on its model (scipy, the handed-out samples)."""
    import json
    from pathlib import Path

    from optimizer.planner.plan_state import read_plan

    case = json.loads((Path(__file__).parent / "data" / "replan_kept_signs_case.json").read_text())
    ps = read_plan(case["plan"])
    cont = replan(case["plan"], case["time"], case["state"], rates=case["rates"],
                  gains=case["gains"], keep_reversals=True)
    assert cont["diagnostics"]["replan"]["signs_kept"] is True
    new = np.array([s["u"] for s in cont["coefficients"]["segments"]])
    k = ps.piece_at(ps.law.at(case["time"])[0])
    before = np.sign(ps.rates[k:])
    assert np.array_equal(np.sign(new[-before.shape[0]:]), before)
    t = np.asarray(cont["path"]["t"])
    u = np.asarray(cont["path"]["u"])
    end = plant_run(np.asarray(case["gains"]), ps.robot.exponents, case["state"], t, u)
    assert np.max(np.abs(end[1:] - np.asarray(ps.goal))) < 1e-6


