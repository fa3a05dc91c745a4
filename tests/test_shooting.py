"""Method ``shooting``: multiple shooting on the original model, piecewise-constant rates.

Every plan is checked against the tests' own scipy integration of the original model, interval
by interval (the rates jump at the breaks); energies of piecewise-constant rates are exact sums.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from optimizer.analysis import robustness
from optimizer.errors import InfeasibleError, InvalidRequestError, SolverTimeoutError
from optimizer.model import Robot
from optimizer.reachable import Goal, generate
from optimizer.planner.context import Deadline
from optimizer.planner.nlp import ladder
from optimizer.planner.plan import plan
from optimizer.planner.shooting import solve_shooting
from optimizer.problem import PlanRequest
from optimizer.steering import ConstraintPoint

from reference import integrate_model

DEG = math.pi / 180.0
OPP_A = (tuple(np.radians([10, 20, 30])), tuple(np.radians([40, 25, 15])))
OPP_B = (tuple(np.radians([20, 40, 10])), tuple(np.radians([35, 15, 45])))


def request(start, goal, **kw) -> PlanRequest:
    return PlanRequest(start=start, goal=goal, method="shooting", **kw)


def scipy_path(p, req, per_interval: int = 41) -> tuple[np.ndarray, np.ndarray]:
    """Times and states of the original model under the plan's rates (scipy DOP853)."""
    q = req.q_start()
    brk = p.inputs.breaks
    ts, qs = [], []
    for k in range(brk.size - 1):
        uk = p.inputs.rates[k]
        h = brk[k + 1] - brk[k]
        sol = integrate_model(lambda t, uk=uk: uk, q, h, p.robot.gains, p.robot.exponents,
                              t_eval=np.linspace(0.0, h, per_interval))
        ts.append(brk[k] + sol.t)
        qs.append(sol.y.T)
        q = sol.y[:, -1]
    return np.concatenate(ts), np.concatenate(qs)


def line_distance(th: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    d = th - a
    ell = b - a
    perp2 = np.sum(d * d, axis=1) - (d @ ell) ** 2 / float(ell @ ell)
    return float(np.sqrt(np.max(np.maximum(perp2, 0.0))))


@pytest.mark.parametrize("start, goal, robot", [
    (*OPP_A, Robot()),
    (*OPP_B, Robot()),
    (tuple(np.radians([30, 40, 40, 40])), tuple(np.radians([35, 45, 38, 45])), Robot.default(4)),
    (tuple(np.radians([68, 65, 65, 40, 30])), tuple(np.radians([62.6, 69.1, 68.1, 43.2, 36.8])),
     Robot.default(5)),
], ids=["opp3_a", "opp3_b", "n4_opposite", "n5_no_family_window"])
def test_plans_reach_the_goal_inside_the_region(start, goal, robot):
    req = request(start, goal, robot=robot)
    p = plan(req)
    t, q = scipy_path(p, req)
    # the Newton correction puts the exact model on the goal (RK4 alone: 1e-8 to 1e-5 rad)
    assert np.max(np.abs(q[-1, 1:] - np.array(goal))) < 1e-8
    # every joint, th_n included, stays inside (0, pi/2) by default
    th = q[:, 1:robot.n + 1]
    assert np.all((th > 0.0) & (th < np.pi / 2))
    # the returned samples are the model's path run along the answer's time law (the
    # library's own quadrature; the path passes the plan's states at the plan's times
    # time_law.plan_time(t)), and its margin is the smallest distance of th_1..th_n from
    # (0, pi/2) (nodes: monotone pieces)
    sigma = p.time_law.plan_time(p.path.t)
    ref = np.array([np.interp(sigma, t, q[:, j]) for j in range(q.shape[1])]).T
    assert np.max(np.abs(p.path.q - ref)) < 1e-4  # linear interpolation of 41-point pieces
    assert p.margin == pytest.approx(float(np.min(np.minimum(th, np.pi / 2 - th))), abs=1e-6)
    assert p.verification.terminal_error < 1e-6
    # the energy of the handed-out rates (linear interpolation: exact per interval)
    a, b, h = p.path.u[:-1], p.path.u[1:], np.diff(p.path.t)[:, None]
    assert p.indicators.energy == pytest.approx(float(np.sum(h * (a * a + a * b + b * b)) / 3),
                                                rel=1e-8)



@pytest.mark.parametrize("fallback", [False, True], ids=["cascade_mesh", "dop853_grid"])
def test_indicators_are_the_scipy_paths(fallback, monkeypatch):
    """The indicators of an actuator plan (on the quadrature's mesh; on a uniform grid of a
    DOP853 replay when the quadrature is not accepted) against the scipy path's, measured
    densely here: deviation, d_a and the reversals."""
    from optimizer.indicators import ACTUATOR_DEAD_BAND, count_reversals, segment_distance
    from optimizer.planner import finish
    from optimizer.verify import DOP853_NAME, integrate_cascade

    if fallback:  # an estimate no quadrature meets: the DOP853 fallback answers
        monkeypatch.setattr(finish, "integrate_cascade",
                            lambda *a, **k: integrate_cascade(*a, **{**k, "tol": 1e-30,
                                                                     "accept": 1e-30,
                                                                     "max_rounds": 0}))
    req = request(*OPP_B)
    p = plan(req)
    assert (p.verification.integrator == DOP853_NAME) == fallback
    t, q = scipy_path(p, req, per_interval=201)
    th = q[:, 1:]
    ind = p.indicators      # of the handed-out path: the plan's, run along its time law
    assert ind.deviation == pytest.approx(
        segment_distance(th, np.array(OPP_B[0]), np.array(OPP_B[1])), abs=1e-5)
    # d_a (in time): the plan's on its own schedule in plan_indicators; the handed-out
    # path's (the same states along the time law) in indicators and its execution
    tau = t / t[-1]
    line1 = OPP_B[0][0] + tau * (OPP_B[1][0] - OPP_B[0][0])
    assert p.plan_indicators.d_a == pytest.approx(float(np.max(np.abs(th[:, 0] - line1))),
                                                  abs=1e-6)
    th_out = np.linspace(0.0, p.duration, 20001)
    th1 = np.interp(p.time_law.plan_time(th_out), t, th[:, 0])
    line1 = OPP_B[0][0] + th_out / p.duration * (OPP_B[1][0] - OPP_B[0][0])
    handed_out_d_a = float(np.max(np.abs(th1 - line1)))
    assert p.execution.check.d_a == pytest.approx(handed_out_d_a, abs=1e-4)
    assert ind.d_a == pytest.approx(handed_out_d_a, abs=1e-4)
    assert ind.reversals_phi == count_reversals(q[:, 0], ACTUATOR_DEAD_BAND)
    assert ind.reversals_th1 == count_reversals(q[:, 1], ACTUATOR_DEAD_BAND)

def test_the_deviation_term_beats_the_minimum_energy_plan_on_deviation():
    """Default weights against pure minimum energy (weights.d_a = 0): the default plan is closer
    to the line, the minimum-energy plan cheaper; each is optimal for its own objective."""
    a, b = (np.array(x) for x in OPP_A)
    dflt = plan(request(*OPP_A))
    energy_only = plan(request(*OPP_A, objective="weighted",
                               weights={"d_a": 0.0, "energy": 1.0}))
    reqd = request(*OPP_A)
    dev = {}
    energy = {}
    for name, p in (("default", dflt), ("energy", energy_only)):
        _, q = scipy_path(p, reqd)
        dev[name] = line_distance(q[:, 1:], a, b)
        energy[name] = float(np.sum(np.diff(p.inputs.breaks) * np.sum(p.inputs.rates ** 2, 1)))
    assert dev["default"] < dev["energy"] - 1.0 * DEG
    assert energy["energy"] <= energy["default"] + 1e-9


@pytest.mark.parametrize("goal, paper_d_a", [(OPP_A, True), (OPP_B, False)],
                         ids=["opp_a", "opp_b"])
def test_no_larger_deviation_and_no_more_reversals_than_the_user_baseline(goal, paper_d_a):
    """The issue's bar on goals beyond the paper's family: the minimum-energy multiple-shooting
    planner a user would write (bench/baselines), measured by the same scipy integration:
    joint-space deviation no larger, actuator reversals no more (d_a of joint 1 is not what
    the default objective ranks: on the first goal it is compared under ``tp_then_da``; on
    the second, a long move, the paper's objective keeps t_p and gives up d_a). On the second
    the deviation term alone would buy a little straightness with two small wiggles of th1
    at the path's ends; the wiggle-free rung removes them."""
    from bench.baselines.multiple_shooting import MultipleShootingBaseline
    from optimizer.indicators import ACTUATOR_DEAD_BAND, count_reversals

    a, b = (np.array(x) for x in goal)
    robot = Robot()
    base = MultipleShootingBaseline(robot.gains, robot.exponents).solve(a, b)
    assert base.success
    req = request(*goal)
    p = plan(req)
    _, q = scipy_path(p, req)
    qb = [req.q_start()]
    for k in range(base.u.shape[0]):
        uk = base.u[k]
        h = base.t_grid[k + 1] - base.t_grid[k]
        sol = integrate_model(lambda t, uk=uk: uk, qb[-1], h, robot.gains, robot.exponents,
                              t_eval=np.linspace(0.0, h, 41))
        qb.extend(sol.y.T[1:])
    qb = np.array(qb)
    assert line_distance(q[:, 1:], a, b) <= line_distance(qb[:, 1:], a, b)
    # d_a of joint 1: distance from its straight line in time (dense samples of both paths)
    t, _ = scipy_path(p, req)
    tb = np.concatenate([[0.0]] + [base.t_grid[k] + np.linspace(0.0, base.t_grid[k + 1]
                                                                - base.t_grid[k], 41)[1:]
                                   for k in range(base.u.shape[0])])
    d_a_base = np.max(np.abs(qb[:, 1] - (a[0] + (b[0] - a[0]) * tb / base.duration)))
    if paper_d_a:
        paper = plan(request(*goal, objective="tp_then_da"))
        tp, qp = scipy_path(paper, req)
        assert (np.max(np.abs(qp[:, 1] - (a[0] + (b[0] - a[0]) * tp / paper.duration)))
                <= d_a_base)
    for j in (0, 1):  # phi and th1: the actuators' reversals
        assert (count_reversals(q[:, j], ACTUATOR_DEAD_BAND)
                <= count_reversals(qb[:, j], ACTUATOR_DEAD_BAND))


def test_actuator_limits_set_the_duration():
    req = request(*OPP_A, max_u1=0.8, max_u2=0.6)
    p = plan(req)
    # the handed-out rates: within the limits, and the time law cruises at them (planned at
    # 0.999 of them) in the shortest duration
    peak = np.max(np.abs(p.path.u), axis=0)
    assert np.all(peak <= np.array([0.8, 0.6]) * (1 + 1e-9))
    assert max(peak[0] / 0.8, peak[1] / 0.6) == pytest.approx(0.999, rel=1e-6)
    assert p.duration == pytest.approx(p.time_law.shortest)
    with pytest.raises(InfeasibleError, match="too short"):
        plan(request(*OPP_A, max_u1=0.8, max_u2=0.6, duration=0.5 * p.duration))


def test_fixed_phi_change_is_met():
    req = request(*OPP_A, phi_change=-0.1)
    p = plan(req)
    _, q = scipy_path(p, req)
    assert q[-1, 0] - req.phi_start == pytest.approx(-0.1, abs=1e-9)
    assert p.phi_change == pytest.approx(-0.1, abs=1e-9)


def test_constraint_points_and_bad_weights_are_refused():
    with pytest.raises(InvalidRequestError) as exc:
        plan(request(tuple(np.radians([1, 1, 1])), tuple(np.radians([30, 30, 30])),
                     duration=10.0, constraint_points=(ConstraintPoint(5.0, 2, -0.3),)))
    assert exc.value.field == "constraint_points"
    with pytest.raises(InvalidRequestError) as exc:
        plan(request(*OPP_A, objective="weighted", weights={"d_a": 0.0, "energy": 0.0}))
    assert exc.value.field == "weights"


def test_no_time_left_is_a_timeout():
    with pytest.raises(SolverTimeoutError):
        solve_shooting(request(*OPP_A), Deadline(0.0))


def test_replays_use_the_rates():
    p = plan(request(*OPP_A))
    out = robustness(p, np.atleast_2d(np.array(OPP_A[0])), "u", OPP_A[1])
    assert out["runs"][0]["terminal_error"] < 1e-6
    with pytest.raises(InvalidRequestError) as exc:
        robustness(p, np.atleast_2d(np.array(OPP_A[0])), "v", OPP_A[1])
    assert exc.value.field == "replay"


def test_json_carries_the_rates():
    d = plan(request(*OPP_A)).to_dict()
    segs = d["coefficients"]["segments"]
    assert len(segs) == ladder(3)[0].intervals == 12
    assert all(len(s["u"]) == 2 and s["v2"] == [] for s in segs)
    assert d["b0"] is None and d["method"] == "shooting"


def test_fatrop_and_ipopt_find_the_same_solution(monkeypatch):
    """The two solvers of the one NLP, from the same guess, agree (fatrop is the fast path)."""
    import optimizer.planner.shooting as shooting

    req = request(*OPP_B)
    out = {}
    for name in ("fatrop", "ipopt"):
        monkeypatch.setattr(shooting, "ATTEMPTS", ((name, 1.0),))
        sol = solve_shooting(req, Deadline(30.0))
        assert sol.status.startswith(name)
        out[name] = sol
    assert np.max(np.abs(out["fatrop"].nodes - out["ipopt"].nodes)) < 1e-5
    assert np.max(np.abs(out["fatrop"].rates - out["ipopt"].rates)) < 1e-4


#: 4-joint goals: one reachable with neither actuator reversing, one that is not (IPOPT
#: proves the NLP with the signs as bounds infeasible).
MONOTONE_OK = ((0.9485153467317612, 0.7200382259123649, 0.7404923089260628, 0.24007215453742564),
               (0.5781184339994246, 0.8924807223845889, 0.9173855726001914, 0.3287104424261839))
MONOTONE_OUT = ((0.41864712364490614, 1.2321804006447563, 0.471919569842823, 0.538971259274377),
                (1.3440324777976511, 1.4237918195040955, 0.48722684443946523,
                 0.6697966938744493))


def test_soft_signs_find_the_solution_of_the_signs_as_bounds(monkeypatch):
    """The sign-held rung's NLP with the signs as penalised rows (an exact penalty) has the
    solution of the NLP with the signs as bounds, and its rates keep the signs."""
    import optimizer.planner.shooting as shooting
    from optimizer.planner.rules import monotone_signs

    req = PlanRequest(start=MONOTONE_OK[0], goal=MONOTONE_OK[1], robot=Robot.default(4))
    signs = monotone_signs(req)
    assert signs is not None and all(signs)
    soft = solve_shooting(req, Deadline(60.0), None, signs)
    monkeypatch.setattr(shooting, "SOFT_SIGNS", False)
    hard = solve_shooting(req, Deadline(60.0), None, signs)
    assert np.all(soft.rates * np.array(signs) >= 0.0)
    assert np.max(np.abs(soft.nodes - hard.nodes)) < 1e-5
    assert np.max(np.abs(soft.rates - hard.rates)) < 1e-4


#: A 5-joint goal (held-out, not a benchmark goal) whose rung with both actuators' signs held
#: stalls at fatrop's iteration cap under the strict tolerance alone: primal feasible to 1e-11,
#: its objective settled, the dual infeasibility creeping down from 1e-3.
HELD_5 = ((1.2274164296223085, 1.2421657930052286, 0.6943889226415766, 0.910845017125626,
           1.501939300264675),
          (0.41576373908305464, 1.067330009508163, 0.6298083455719308, 0.6354638107470443,
           1.370518298811284))


def test_fatrop_stops_at_an_acceptable_point_that_is_ipopts_solution():
    """fatrop's acceptable point (solvers.FATROP_ACCEPTABLE_TOL) is a converged solution: on
    the sign-held NLP above it is the solution IPOPT converges to from the same guess."""
    from optimizer.planner import nlp
    from optimizer.planner.rules import joint_limits, monotone_signs
    from optimizer.planner.solvers import run_solver

    req = PlanRequest(start=HELD_5[0], goal=HELD_5[1], robot=Robot.default(5))
    signs = monotone_signs(req)
    assert signs is not None and all(signs)
    sol = solve_shooting(req, Deadline(60.0), None, signs)
    assert sol.status == "fatrop: acceptable"
    tr = ladder(5)[0]
    m = nlp.nlp_for(req, tr)
    lo, hi = nlp.node_bounds(req, joint_limits(req))
    lbw, ubw, _ = nlp.variable_bounds(req, m, tr, lo, hi, signs)
    p = nlp.parameters(req, *nlp.objective_weights(req, "shooting"))
    x0 = m.guess(np.array(req.start), np.array(req.goal), req.phi_start, 0.6 * signs[0])
    ref = run_solver(m, "ipopt", x0, p, lbw, ubw, 60.0)
    assert ref.success and ref.x is not None
    nodes, rates = m.unpack(ref.x)
    assert np.max(np.abs(nodes - sol.nodes)) < 2e-3
    assert np.max(np.abs(rates - sol.rates)) < 1e-2


#: A held-out 4-joint goal whose free rung, with the goal as equality rows, stalled at fatrop's
#: iteration cap (steps of 1e-4..1e-7 of Newton's) so that IPOPT answered after it.
FREE_4 = ((0.1633144589858921, 0.7490455388624255, 0.7116404613107901, 1.3114058188103506),
          (0.03217129752277256, 0.6321591950031086, 0.6419756110109304, 1.2669289319494255))


def test_the_free_rung_of_four_joints_takes_the_goal_elastic():
    """nlp.FREE_ELASTIC_FROM_JOINTS: on 4 joints the free rung's goal is an exact penalty
    (fatrop solves the goal above, on the goal), the sign-held rungs' stays equality rows."""
    from optimizer.planner import nlp

    req = PlanRequest(start=FREE_4[0], goal=FREE_4[1], robot=Robot.default(4))
    tr = ladder(4)[0]
    assert nlp.nlp_for(req, tr, free=True).terminal == "elastic"
    assert nlp.nlp_for(req, tr).terminal == "hard"
    sol = solve_shooting(req, Deadline(60.0))
    assert sol.status.startswith("fatrop"), sol.tried
    assert np.max(np.abs(sol.nodes[-1, 1:] - np.array(FREE_4[1]))) < 1e-6


def test_solver_status_reads_fatrops_acceptable_point():
    from optimizer.planner.solvers import FATROP_ACCEPTABLE_FLAG, solver_status

    acceptable = {"return_status": 1, "success": False,
                  "fatrop": {"return_flag": FATROP_ACCEPTABLE_FLAG}}
    assert solver_status("fatrop", acceptable) == ("acceptable", True)
    capped = {"return_status": 1, "success": False, "fatrop": {"return_flag": 1}}
    assert solver_status("fatrop", capped) == ("1", False)
    assert solver_status("ipopt", {"return_status": "Solve_Succeeded", "success": True}) == (
        "Solve_Succeeded", True)


def test_soft_signs_certify_signs_out_of_reach(monkeypatch):
    """Where no path with rates of fixed signs exists (IPOPT's certificate on the NLP with the
    signs as bounds), the soft NLP converges with a slack and the rung is refused as
    infeasible, before fatrop's iteration cap."""
    import optimizer.planner.shooting as shooting
    from optimizer.planner.rules import monotone_signs
    from optimizer.planner.solvers import FATROP_MAX_ITER

    req = PlanRequest(start=MONOTONE_OUT[0], goal=MONOTONE_OUT[1], robot=Robot.default(4))
    signs = monotone_signs(req)
    with pytest.raises(InfeasibleError) as exc:
        solve_shooting(req, Deadline(60.0), None, signs)
    last = exc.value.diagnostics["tried"][-1]
    assert "leave their signs" in last["status"] and last["iterations"] < FATROP_MAX_ITER
    # the independent proof: IPOPT on the signs as bounds detects infeasibility
    monkeypatch.setattr(shooting, "SOFT_SIGNS", False)
    first_converged = shooting.first_converged

    def on_ipopt(nlp, attempts, *args):
        return first_converged(nlp, [dataclasses.replace(at, solver="ipopt")
                                     for at in attempts], *args)

    monkeypatch.setattr(shooting, "first_converged", on_ipopt)
    with pytest.raises(InfeasibleError) as exc:
        solve_shooting(req, Deadline(60.0), None, signs)
    assert "Infeasible_Problem_Detected" in exc.value.diagnostics["tried"][-1]["status"]


def test_random_goals_beyond_the_family_are_planned_and_verified():
    """Seeded random 3- and 4-joint goals (joints moving either way, up to 15 deg): every one
    planned, and the tests' own scipy integration lands on the goal inside the region."""
    rng = np.random.default_rng(7)
    for i in range(12):
        n = 3 if i % 2 == 0 else 4
        a = rng.uniform(8, 70, n)
        b = np.clip(a + rng.uniform(-15, 15, n), 5, 80)
        req = request(tuple(np.radians(a)), tuple(np.radians(b)),
                      robot=Robot() if n == 3 else Robot.default(4))
        p = plan(req)
        _, q = scipy_path(p, req, per_interval=11)
        assert np.max(np.abs(q[-1, 1:] - np.radians(b))) < 1e-8, (a, b)
        assert np.all((q[:, 1:n] > 0) & (q[:, 1:n] < np.pi / 2)), (a, b)


def test_correction_reaches_the_exact_goal_from_the_rk4_rates():
    """The NLP's rates alone miss the goal of the exact model (RK4); the correction's errors,
    measured by its fine end map, fall below its target, and scipy agrees."""
    import optimizer.planner.shooting as shooting

    req = request((0.5236, 0.6981, 0.6981, 0.6981), (0.6109, 0.7854, 0.6632, 0.7854),
                  robot=Robot.default(4))
    sol = solve_shooting(req, Deadline(30.0))
    nlp = shooting.nlp_for(req, shooting.ladder(req.n)[0])
    rates, errors = shooting.correct_rates(req, nlp, sol.rates, float(sol.nodes[-1, 0]))
    assert errors[0] > 1e-9 and errors[-1] <= shooting.CORRECTION_TARGET
    for U, tol_lo, tol_hi in ((sol.rates, 1e-9, 1e-3), (rates, 0.0, 1e-8)):
        q = req.q_start()
        for k in range(U.shape[0]):
            sol_k = integrate_model(lambda t, uk=U[k]: uk, q, 1.0 / U.shape[0],
                                    req.robot.gains, req.robot.exponents)
            q = sol_k.y[:, -1]
        err = np.max(np.abs(q[1:] - np.array(req.goal)))
        assert tol_lo < err < tol_hi
    assert abs(np.sum(rates[:, 0]) - np.sum(sol.rates[:, 0])) < 1e-12  # phi's end is held


@pytest.mark.parametrize("rows_apart", [1.0, 1e-9])
def test_the_newton_step_is_the_least_norm_solution(rows_apart):
    """The correction's step against numpy's SVD least squares: on a well-conditioned
    Jacobian the least-norm solution; on one whose rows are nearly parallel (J J^T singular
    in double precision, the exact solution's entries about 1e7) the SVD's, truncated below
    STEP_RCOND of the largest singular value, so that the weak direction is left out."""
    from optimizer.planner.correction import STEP_RCOND, minimum_norm_step

    rng = np.random.default_rng(11)
    J = rng.normal(size=(5, 24))
    J[2] = J[1] + rows_apart * rng.normal(size=24)
    r = 0.01 * rng.normal(size=5)
    ref = np.linalg.lstsq(J, r, rcond=None if rows_apart == 1.0 else STEP_RCOND)[0]
    x = minimum_norm_step(J, r)
    if rows_apart != 1.0:
        assert np.max(np.abs(np.linalg.lstsq(J, r, rcond=None)[0])) > 1e5
        assert np.max(np.abs(x)) < 1.0
    assert np.all(np.isfinite(x))
    np.testing.assert_allclose(x, ref, rtol=1e-6, atol=1e-9 * np.max(np.abs(ref)))
    if rows_apart == 1.0:
        np.testing.assert_allclose(J @ x, r, atol=1e-12)


def test_correction_with_a_measured_miss_aims_past_the_goal_by_that_miss():
    """Given the exact end state of the rates (a quadrature's), the correction subtracts the
    fine map's error there from the goal: the fine map of the returned rates ends at the goal
    minus that error (a defect correction)."""
    import optimizer.planner.shooting as shooting

    req = request((0.5236, 0.6981, 0.6981, 0.6981), (0.6109, 0.7854, 0.6632, 0.7854),
                  robot=Robot.default(4))
    sol = solve_shooting(req, Deadline(30.0))
    nlp = shooting.nlp_for(req, shooting.ladder(req.n)[0])
    phi_end = float(sol.nodes[-1, 0])
    rates, _ = shooting.correct_rates(req, nlp, sol.rates, phi_end)
    fine_end = np.asarray(nlp.fine_path(req.q_start(), rates.T, req.robot.gains))[:, -1]
    miss = np.array([0.0, 2e-8, -1e-8, 3e-8, 5e-9])
    again, errors = shooting.correct_rates(req, nlp, rates, phi_end, fine_end + miss)
    end = np.asarray(nlp.fine_path(req.q_start(), again.T, req.robot.gains))[:, -1]
    assert np.max(np.abs(end[1:] - (np.array(req.goal) - miss[1:]))) < 1e-12
    assert errors[-1] < 1e-12


def test_a_six_joint_goal_needs_the_finer_transcription():
    """The first rung's NLP (16 intervals) cannot reach this 6-joint goal (it needs faster
    rates than that rung allows); the ladder's 50-interval rung does, and scipy confirms the
    plan."""
    import optimizer.planner.shooting as shooting

    rng = np.random.default_rng(3)
    for n in (5, 5, 5, 6):  # the draw sequence of the goal that the first rung missed
        a = rng.uniform(20, 60, n)
        b = np.clip(a + rng.uniform(-8, 8, n), 5, 80)
    req = request(tuple(np.radians(a)), tuple(np.radians(b)), robot=Robot.default(6),
                  time_limit=60.0)  # about 6 s calm; a loaded 2-core machine takes 20
    with pytest.raises(InfeasibleError):
        solve_shooting(req, Deadline(60.0), shooting.ladder(6)[0])
    p = plan(req)
    assert p.diagnostics["shooting"]["intervals"] == shooting.ladder(6)[1].intervals
    _, q = scipy_path(p, req, per_interval=11)
    assert np.max(np.abs(q[-1, 1:] - np.radians(b))) < 1e-8
    assert np.all((q[:, 1:6] > 0) & (q[:, 1:6] < np.pi / 2))


@pytest.mark.parametrize("kw", [{"duration": 4.0}, {"max_u1": 0.8, "max_u2": 0.6}],
                         ids=["duration", "actuator_limits"])
def test_energy_is_the_physical_one_for_any_duration(kw):
    """int |u|^2 dt of the plan's rates (exact for piecewise-constant rates), whatever T:
    the verification integrates in normalised time, where it is T times larger; the
    indicators' energy is that of the handed-out rates (linear between samples: exact)."""
    p = plan(request(*OPP_A, **kw))
    assert p.duration != pytest.approx(1.0)
    exact = float(np.sum(np.diff(p.inputs.breaks) * np.sum(p.inputs.rates ** 2, axis=1)))
    assert p.verification.energy == pytest.approx(exact, rel=1e-8)
    a, b, h = p.path.u[:-1], p.path.u[1:], np.diff(p.path.t)[:, None]
    assert p.indicators.energy == pytest.approx(float(np.sum(h * (a * a + a * b + b * b)) / 3),
                                                rel=1e-8)


def test_wiggle_free_signs_merges_short_runs_only():
    """Runs of a rate's sign that travel less than WIGGLE_SHARE of the actuator's travel (and
    more than the reversal dead band) take their neighbours' sign, the smallest first; long
    runs, and runs too small to count as reversals, stay."""
    from optimizer.planner.rungs import WIGGLE_SHARE, wiggle_free_signs

    N = 20
    u1 = np.full(N, 2.0)
    u1[-1] = -0.5                      # an end wiggle: 0.025 rad of 1.925 rad (1.3 %)
    u2 = np.r_[np.full(8, 3.0), np.full(8, -3.0), np.full(4, 3.0)]   # three long runs
    signs = wiggle_free_signs(np.column_stack([u1, u2]))
    assert signs is not None
    assert np.all(signs[:, 0] == 1.0)
    assert np.array_equal(signs[:, 1], np.sign(u2))
    # a middle wiggle merges into both neighbours; one that is not small stays
    u1 = np.full(N, 1.0)
    u1[9] = -0.4 * WIGGLE_SHARE * N   # travel 0.4 * share of about 1 rad
    assert np.all(wiggle_free_signs(np.column_stack([u1, np.ones(N)]))[:, 0] == 1.0)
    u1[9] = -3.0 * WIGGLE_SHARE * N
    assert wiggle_free_signs(np.column_stack([u1, np.ones(N)])) is None
    # below the dead band a sign flip is not a reversal: nothing to remove
    u1 = np.full(N, 1.0)
    u1[5] = -1e-6
    assert wiggle_free_signs(np.column_stack([u1, np.ones(N)])) is None
    # zero rates (a sign-held rung's bound) belong to the run before them, leading zeros to
    # the first run: the later long runs keep their own signs
    u2 = np.r_[0.0, 0.0, np.full(8, 3.0), 0.0, np.full(9, -3.0)]
    u1 = np.full(N, 2.0)
    u1[-1] = -0.5                      # the end wiggle again, so that there is a pattern
    signs = wiggle_free_signs(np.column_stack([u1, u2]))
    assert signs is not None
    assert np.array_equal(signs[:, 1], np.r_[np.full(11, 1.0), np.full(9, -1.0)])


def test_finishing_refines_rates_that_the_quadrature_finds_off_the_goal():
    """When the one quadrature of finish_actuator_plan finds the rates off the goal by more
    than the correction's target (here: rates moved by 1e-7 after the correction), the defect
    correction runs once and the handed-out plan ends on the goal; without it, it would not."""
    import optimizer.planner.shooting as shooting
    from optimizer.planner.finish import finish_actuator_plan

    req = request(*OPP_A)
    sol = solve_shooting(req, Deadline(30.0))
    nlp = shooting.nlp_for(req, shooting.ladder(req.n)[0])
    phi_end = float(sol.nodes[-1, 0])
    rates, _ = shooting.correct_rates(req, nlp, sol.rates, phi_end)
    off = rates * (1.0 + 1e-7)
    plain = finish_actuator_plan(req, off, "shooting", sol.nodes, {}, {})
    assert plain.verification.terminal_error > 1e-9
    refined = finish_actuator_plan(
        req, off, "shooting", sol.nodes, {}, {},
        refine=lambda end: shooting.correct_rates(req, nlp, off, phi_end, end)[0])
    assert refined.verification.terminal_error < 1e-10
    _, q = scipy_path(refined, req)
    assert np.max(np.abs(q[-1, 1:] - np.array(req.goal))) < 1e-9


#: Goals whose joints th2, th3 move both ways (generated goals, in degrees).
BOTH_WAYS = [((33.8608, 26.9024, 21.7798), (22.1209, 26.9375, 20.7809)),
             ((8.5655, 75.9792, 77.0036), (25.122, 74.5429, 77.0158)),
             ((67.0844, 33.9927, 56.7857), (84.6182, 33.3439, 58.4467))]


@pytest.mark.parametrize("pair", BOTH_WAYS, ids=["down", "up_steep", "up"])
def test_where_phi_must_reverse_the_th1_held_nlp_alone_gives_the_fewest_reversals(
        pair, monkeypatch):
    """Joints moving both ways need phi to reverse: a path with th1 held to its sign and one
    reversal of phi has the fewest reversals there is. That NLP runs first and the free one
    not at all; the plan is no worse, by the default rule, than the free NLP's, solved here
    apart."""
    import optimizer.planner.shooting as shooting
    from optimizer.planner import rungs
    from optimizer.planner.rules import direction_conflict

    req = request(*(tuple(np.radians(x)) for x in pair))
    assert direction_conflict(req) is not None
    held_signs = []
    solve = shooting.solve_shooting

    def recording(req, deadline, tr=None, monotone=None, start_nodes=None):
        held_signs.append(None if monotone is None else np.asarray(monotone).tolist())
        return solve(req, deadline, tr, monotone, start_nodes)

    monkeypatch.setattr(shooting, "solve_shooting", recording)
    p = plan(req)
    th1_sign = float(np.sign(req.goal[0] - req.start[0]))
    assert held_signs[0] == [0.0, th1_sign] and None not in held_signs
    assert p.indicators.reversals == 1 and p.indicators.reversals_th1 == 0
    free = solve(req, Deadline(30.0), ladder(req.n)[0], None)
    rev, dev = rungs._reversals_and_deviation(req, free.nodes)
    assert (1, p.indicators.deviation) <= (rev, dev + 1e-4)


def _direction_changes(x: np.ndarray, dead_band: float = 1e-4) -> int:
    """Direction changes of a sampled coordinate, each run of one direction travelling more
    than ``dead_band`` (rad) counted (written here, not the library's counter)."""
    changes, direction, anchor = 0, 0, float(x[0])
    for v in x[1:]:
        d = float(v) - anchor
        if direction >= 0 and d < -dead_band:
            changes += direction > 0
            direction, anchor = -1, float(v)
        elif direction <= 0 and d > dead_band:
            changes += direction < 0
            direction, anchor = 1, float(v)
        elif (direction > 0 and v > anchor) or (direction < 0 and v < anchor):
            anchor = float(v)
    return changes


def test_the_correction_keeps_the_held_signs_when_they_end_within_tolerance():
    """A 6-joint goal whose joints move in opposite directions (one reversal of phi is the
    least): the default's sign-held rates end 6.6e-8 rad off the goal before correction, and a
    free correction came 2e-8 rad closer with 4 reversals of th1 (1 + 4 where the
    minimum-energy plan has 1 + 0). Held rates within HELD_ACCEPT are kept: the plan re-
    integrated by scipy reaches the goal within the plan's tolerance with phi reversing once
    and th1 never."""
    from optimizer.planner.correction import HELD_ACCEPT
    from optimizer.planner.rules import TERMINAL_TOLERANCE

    g = generate(6, 5)[4]
    assert g.kind == "opposite"
    req = request(g.start, g.goal, robot=Robot.default(6), time_limit=60.0)
    p = plan(req)
    assert HELD_ACCEPT < TERMINAL_TOLERANCE
    t, q = scipy_path(p, req, per_interval=21)
    assert np.max(np.abs(q[-1, 1:] - np.array(g.goal))) < TERMINAL_TOLERANCE
    assert np.all((q[:, 1:6] > 0) & (q[:, 1:6] < np.pi / 2))
    assert _direction_changes(q[:, 0]) == 1
    assert _direction_changes(q[:, 1]) == 0


def test_a_miss_the_correction_cannot_reach_is_solved_on_the_finer_rung(monkeypatch):
    """Where the first rung's answer ends off the goal along a direction the Newton correction
    cannot reach (the end map's weakest singular value: with the goal hard, a 5-joint goal near
    the region's edge ended 1.5e-6 rad off along a direction of singular value 5e-8 of 0.28),
    finishing it fails with a NumericalError; the next rung, a finer model, starts from that
    path. Here the first rung's finishing is made to fail so: the plan then comes from the
    50-interval rung, and re-integrated by scipy it ends on the goal inside the region."""
    import optimizer.planner.shooting as shooting
    from optimizer.errors import NumericalError
    from optimizer.planner.rules import TERMINAL_TOLERANCE

    g = generate(5, 18, seed=33)[17]      # th4 starts at 81.7 deg
    req = request(g.start, g.goal, robot=Robot.default(5), time_limit=60.0)
    first = ladder(5)[0]
    finish = shooting.finish_solution

    def finish_or_miss(req_, method, nlp, sol, tr, *args):
        if tr == first:
            raise NumericalError("the correction diverged (made to, by the test)")
        return finish(req_, method, nlp, sol, tr, *args)

    monkeypatch.setattr(shooting, "finish_solution", finish_or_miss)
    p = plan(req)
    assert p.diagnostics["shooting"]["refined_from_intervals"] == first.intervals
    assert p.diagnostics["shooting"]["intervals"] == 50
    _, q = scipy_path(p, req, per_interval=11)
    assert np.max(np.abs(q[-1, 1:] - np.array(g.goal))) < TERMINAL_TOLERANCE
    assert np.all((q[:, 1:5] > 0) & (q[:, 1:5] < np.pi / 2))


def test_a_handed_out_path_within_tolerance_is_not_corrected_off_the_plan():
    """A 6-joint goal whose plan (1 reversal of phi, none of th1, 14.8 deg deviation) ends
    1.7e-7 rad off the goal: its linear form's correction took a first step 7 times its
    largest rate along the end map's weakest direction and ended on the goal by a path with
    4 + 12 reversals and 45.9 deg of deviation, so that no form was handed out and every method
    failed. Within the tolerance such steps are not taken: the handed-out path, re-integrated
    by scipy under its linear rule, ends within 1e-6 rad with the plan's reversals."""
    from scipy.integrate import solve_ivp

    from reference import model_rhs

    g = generate(6, 29, seed=41)[28]
    req = PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(6), time_limit=60.0)
    p = plan(req)
    t, u = np.asarray(p.path.t, float), np.asarray(p.path.u, float)
    K, m = p.robot.gains, p.robot.exponents
    sol = solve_ivp(lambda s, q: model_rhs(q, [np.interp(s, t, u[:, 0]), np.interp(s, t, u[:, 1])],
                                           K, m),
                    (t[0], t[-1]), req.q_start(), method="DOP853", rtol=1e-11, atol=1e-12,
                    t_eval=t, max_step=float(np.min(np.diff(t)[np.diff(t) > 0])))
    assert np.max(np.abs(sol.y[1:, -1] - np.array(g.goal))) < 1e-6
    assert np.all((sol.y[1:6] > 0) & (sol.y[1:6] < np.pi / 2))
    assert _direction_changes(sol.y[0]) == p.plan_indicators.reversals_phi == 1
    assert _direction_changes(sol.y[1]) == p.plan_indicators.reversals_th1 == 0


def test_a_shooting_plan_from_the_finer_rung_is_ranked_against_the_family(monkeypatch):
    """Where the first rung's answer misses the goal beyond the correction's reach, the finer
    rung answers, and that answer (not the ladder's) is ranked against the family's
    (``polynomial``). Since the first rung has 16 intervals no generated goal found does this
    (none of 300 of 4 joints and 240 of 5; a 4-joint goal did at 20 intervals: the finer rung
    answered 1 + 1 reversals, the family 0 + 1), so the first rung's finishing is made to
    miss here. The answer is the better by the default's rule of the two tried, and its
    handed-out path, re-integrated by scipy, reverses as it says and ends on the goal inside
    the region."""
    from scipy.integrate import solve_ivp

    import optimizer.planner.shooting as shooting
    from optimizer.errors import NumericalError
    from reference import model_rhs

    first = ladder(4)[0]
    finish = shooting.finish_solution

    def first_rung_misses(req_, method, nlp, sol, tr, *args, **kwargs):
        if tr == first:
            raise NumericalError("the first rung's answer misses the goal (forced)")
        return finish(req_, method, nlp, sol, tr, *args, **kwargs)

    monkeypatch.setattr(shooting, "finish_solution", first_rung_misses)
    g = generate(4, 58, seed=77)[57]
    req = PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(4), time_limit=60.0)
    p = plan(req)
    tried = {t["method"]: t for t in p.diagnostics["auto"]["tried"]}
    assert tried["shooting"]["outcome"] == "plan" and tried["polynomial"]["outcome"] == "plan"
    keys = {m: tuple(t["rank_key"]) for m, t in tried.items()}
    assert p.method == min(keys, key=keys.__getitem__)
    if p.method == "shooting":
        assert p.diagnostics["shooting"]["intervals"] == ladder(4)[1].intervals
    total = p.indicators.reversals_phi + p.indicators.reversals_th1
    assert total == keys[p.method][0]
    t, u = np.asarray(p.path.t, float), np.asarray(p.path.u, float)
    sol = solve_ivp(lambda s, q: model_rhs(q, [np.interp(s, t, u[:, 0]), np.interp(s, t, u[:, 1])],
                                           p.robot.gains, p.robot.exponents),
                    (t[0], t[-1]), req.q_start(), method="DOP853", rtol=1e-11, atol=1e-12,
                    t_eval=t, max_step=float(np.min(np.diff(t)[np.diff(t) > 0])))
    assert np.max(np.abs(sol.y[1:, -1] - np.array(g.goal))) < 1e-6
    assert np.all((sol.y[1:4] > 0) & (sol.y[1:4] < np.pi / 2))
    assert _direction_changes(sol.y[0]) + _direction_changes(sol.y[1]) == total


def test_a_soft_sign_rung_past_a_plans_cap_gives_the_fewest_reversals():
    """nlp.SOFT_SIGNS_MAX_ITER: a 4-joint goal of a seed no benchmark uses whose rung
    with both signs held (soft) converges after fatrop's cap of the other rungs (60; with it
    the plan reversed phi and th1 five times). Counted here on the handed-out linear rates:
    phi and th1 are their integrals, exact quadratics on every interval, and the original
    model under them (scipy) ends on the goal inside the region."""
    assert handed_out_reversals(generate(4, 9, seed=9001)[8]) <= 2


def test_a_rung_past_the_cap_of_four_joints_gives_the_fewest_reversals_from_five():
    """solvers.fatrop_max_iter: from 5 joints fatrop may iterate 120 times, not 60. An 8-joint
    goal of a seed no benchmark uses whose plan reversed phi and th1 twice at the cap of 60
    (a solve that converges past it had failed there) reverses them once."""
    assert handed_out_reversals(generate(8, 8, seed=777)[7]) <= 1


def test_the_elastic_goal_tightened_tenfold_gives_the_fewest_reversals():
    """solvers.ELASTIC_STEP: an elastic goal's next round weighs the goal 10 times more, not
    100 (fatrop then stopped at its cap on most second rounds, and the rung failed). An 8-joint
    goal of a seed no benchmark uses whose plan reversed phi and th1 four times with the
    hundredfold step reverses them twice."""
    assert handed_out_reversals(generate(8, 8, seed=9001)[7]) <= 2


def handed_out_reversals(g: Goal) -> int:
    """The default plan of goal ``g``: the original model under its handed-out linear rates
    (scipy) ends on the goal inside the region; the reversals of phi and th1 counted here on
    those rates, whose integrals are exact quadratics on every interval."""
    from optimizer.indicators import ACTUATOR_DEAD_BAND
    from reference import turns
    from replay_support import linear_integral, replay_linear

    robot = Robot.default(g.n)
    p = plan(PlanRequest(start=g.start, goal=g.goal, robot=robot))
    t, u = np.asarray(p.path.t, float), np.asarray(p.path.u, float)
    q0 = np.array((0.0,) + tuple(g.start))
    final, margin = replay_linear(robot, t, u, q0)
    assert np.max(np.abs(final[1:] - np.array(g.goal))) < 1e-6 and margin > 0.0
    return sum(turns(linear_integral(t, u[:, c], q0[c]), ACTUATOR_DEAD_BAND) for c in (0, 1))
