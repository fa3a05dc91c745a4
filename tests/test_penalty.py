"""Method ``penalty`` (paper Remark 3): the shooting transcription with the singularity-free
region as an exact l1 penalty instead of hard constraints.

Every plan is checked against the tests' own scipy integration of the original model
(``tests/reference.py``, written independently of the library), interval by interval under the
plan's piecewise-constant rates: it must end on the goal and keep every joint inside
``(0, pi/2)`` (the method's default region) on a dense grid.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from optimizer.actuation import ActuatorSchedule
from optimizer.errors import (InfeasibleError, InvalidRequestError, NumericalError,
                              SolverTimeoutError)
from optimizer.model import Robot
from optimizer.planner import nlp as nlp_layer
from optimizer.planner import solvers
from optimizer.planner import penalty as pen
from optimizer.planner.context import Deadline
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest
from optimizer.steering import ConstraintPoint

from reference import integrate_model

R = math.radians
HALF_PI = math.pi / 2
OPP_A = ((10, 20, 30), (40, 25, 15))
OPP_B = ((20, 40, 10), (35, 15, 45))
#: The benchmark's goals (bench/cases.py), deg.
BENCH_GOALS = [((1, 1, 1), (30, 30, 30)), ((5, 5, 5), (30, 30, 30)),
               ((10, 10, 10), (30, 30, 30)), ((20, 20, 20), (40, 40, 40)),
               ((40, 40, 40), (45, 45, 45)), OPP_A, OPP_B,
               ((47.7, 66.9, 44.9, 66.0), (62.6, 72.2, 47.5, 71.9)),
               ((30, 40, 40, 40), (35, 45, 38, 45)),
               ((68, 65, 65, 40, 30), (62.6, 69.1, 68.1, 43.2, 36.8))]


def request(start_deg, goal_deg, method: str = "penalty", **kw) -> PlanRequest:
    n = len(start_deg)
    return PlanRequest(start=tuple(map(R, start_deg)), goal=tuple(map(R, goal_deg)),
                       robot=Robot.default(n), method=method, duration=1.0, **kw)


def scipy_path(p, req: PlanRequest, per_interval: int = 21) -> np.ndarray:
    """States of the original model under the plan's rates (scipy DOP853), interval by
    interval; shape (samples, n + 1)."""
    q = req.q_start()
    brk = p.inputs.breaks
    qs = []
    for k in range(brk.size - 1):
        uk = p.inputs.rates[k]
        h = brk[k + 1] - brk[k]
        sol = integrate_model(lambda t, uk=uk: uk, q, h, p.robot.gains, p.robot.exponents,
                              t_eval=np.linspace(0.0, h, per_interval))
        qs.append(sol.y.T)
        q = sol.y[:, -1]
    return np.concatenate(qs)


def assert_verified(p, req: PlanRequest) -> np.ndarray:
    """The plan reaches the goal and stays inside (0, pi/2) for every joint (scipy)."""
    q = scipy_path(p, req)
    assert np.max(np.abs(q[-1, 1:] - np.array(req.goal))) < 1e-8
    assert np.all((q[:, 1:] > 0.0) & (q[:, 1:] < HALF_PI))
    return q


def reachable_goal(rng: np.random.Generator, n: int, margin: float = R(3.0)
                   ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """A start inside the region and the goal the TRUE model reaches from it under random
    smooth inputs (a few sines), kept only when every joint stays inside all along."""
    robot = Robot.default(n)
    while True:
        a = rng.uniform(R(15), R(75), n)
        c = rng.normal(0.0, 0.6, (2, 3))
        phase = rng.uniform(0, 2 * np.pi, (2, 3))

        def u(t, c=c, phase=phase):
            k = np.arange(1, 4)
            return np.sum(c * np.sin(2 * np.pi * k * t / 2 + phase), axis=1)

        sol = integrate_model(u, np.concatenate([[0.0], a]), 1.0, robot.gains,
                              robot.exponents, t_eval=np.linspace(0.0, 1.0, 401))
        th = sol.y[1:].T
        inside = np.all((th > margin) & (th < HALF_PI - margin))
        if inside and np.max(np.abs(th[-1] - th[0])) > R(2):
            return tuple(a), tuple(th[-1])


# ---------------------------------------------------------------------- goals and plans
def test_opposite_motion_goal_is_planned_and_verified():
    """[10, 20, 30] -> [40, 25, 15] deg: th2 up and th3 down, which no constant-v1 plan can do
    (phi must reverse)."""
    req = request(*OPP_A)
    p = plan(req)
    assert p.method == "penalty"
    q = assert_verified(p, req)
    assert p.verification.terminal_error < 1e-8
    assert p.indicators.phi_reversals >= 1
    phi = q[:, 0]
    assert phi.max() > max(phi[0], phi[-1]) + 1e-3 or phi.min() < min(phi[0], phi[-1]) - 1e-3
    d = p.diagnostics["penalty"]
    assert d["penalty_weight"] >= pen.RHO_START and d["boundary_distance"] > 0
    assert d["start_reason"] and d["status"].split(":")[0] in ("fatrop", "ipopt")
    import json
    json.dumps(p.to_dict(), allow_nan=False)


@pytest.mark.parametrize("n, seed", [(3, 11), (3, 12), (4, 13), (4, 14), (5, 15)])
def test_random_reachable_goals_are_planned_and_verified(n, seed):
    """Goals reached by the true model under random smooth inputs, from a random start inside
    the region: every one planned and confirmed by scipy."""
    a, b = reachable_goal(np.random.default_rng(seed), n)
    req = PlanRequest(start=a, goal=b, robot=Robot.default(n), method="penalty", duration=1.0)
    p = plan(req)
    assert_verified(p, req)


def test_joint_bounds_are_kept():
    """A request's joint bounds join the region the penalty keeps the path in."""
    free = plan(request(*OPP_A))
    hi = float(np.max(free.path.q[:, 1])) - R(5.0)
    assert hi > R(40.0)
    req = request(*OPP_A, joint_bounds=(( R(5.0), hi), None, None))
    p = plan(req)
    q = assert_verified(p, req)
    assert np.max(q[:, 1]) < hi and np.min(q[:, 1]) > R(5.0)


def test_penalty_weight_grows_while_the_solution_leaves_the_region(monkeypatch):
    """For [20, 40, 10] -> [35, 15, 45] deg the optimum under rho = 10 dips below th3 = 0;
    rho is raised tenfold and the next solution is inside, with th3 on the margin."""
    monkeypatch.setattr(pen, "RHO_START", 10.0)
    req = request(*OPP_B)
    p = plan(req)
    d = p.diagnostics["penalty"]
    # the solves that converged (starts that did not are recorded too)
    solved = [t for t in d["tried"] if "violation" in t]
    first, last = solved[0], d["tried"][-1]
    assert first["rho"] == 10.0 and first["violation"] > 1e-3
    assert last["rho"] == d["penalty_weight"] == 100.0
    assert last["violation"] <= pen.VIOLATION_TOL
    q = assert_verified(p, req)
    # the reported distance from the boundary: the NLP's nodes, which scipy's path at the
    # interval ends matches to the NLP's RK4 accuracy
    ends = q[20::21]
    scipy_distance = float(np.min(np.minimum(ends[:, 1:], HALF_PI - ends[:, 1:])))
    assert d["boundary_distance"] == pytest.approx(scipy_distance, abs=1e-4)
    assert d["boundary_distance"] == pytest.approx(nlp_layer.MARGIN, abs=1e-6)


@pytest.mark.parametrize("start, goal", BENCH_GOALS,
                         ids=[f"{len(s)}j_{s[0]:g}_{g[0]:g}" for s, g in BENCH_GOALS])
def test_no_worse_than_shooting_on_the_same_region(start, goal, monkeypatch):
    """On the benchmark's goals, with shooting given the same region (th_n in (0, pi/2) too)
    and the same objective, the penalty's plan is shooting's: an exact penalty has the
    constrained problem's minimisers. Deviation and reversals are no worse. (The two NLPs are
    compared: shooting's own later step, merging runs for fewer reversals, is off.)"""
    from optimizer.planner import rungs
    monkeypatch.setattr(rungs, "MERGE_TRIES", 0)
    n = len(start)
    bounds = (None,) * (n - 1) + ((0.0, HALF_PI),)
    s = plan(request(start, goal, "shooting", joint_bounds=bounds))
    req = request(start, goal)
    p = plan(req)
    assert_verified(p, req)
    ip, is_ = p.indicators, s.indicators
    # the two NLPs stop at FATROP_TOL of their own optimality conditions: their plans agree to
    # about 1e-5 rad (1.5e-5 in d_a on one goal)
    assert ip.d_a <= is_.d_a + 1e-4
    assert ip.d_a_joint_space <= is_.d_a_joint_space + 1e-4
    assert ip.deviation <= is_.deviation + 1e-4
    assert ip.t_p <= is_.t_p and ip.phi_reversals <= is_.phi_reversals
    # the same minimiser: the planned rates' energy (exact for piecewise-constant rates);
    # the handed-out energy also depends on where the time law stops (a rate held at 0 by
    # one method's wiggle-free signs and not by the other's: 22.63 against 22.96 on OPP_B)
    assert p.verification.energy == pytest.approx(s.verification.energy, rel=1e-3)


# ---------------------------------------------------------------------- warm starts, objectives
def test_warm_start_from_a_plan_is_used_and_stays_put(monkeypatch):
    """From shooting's own plan (actuator rates) the penalty starts there and ends at the same
    plan; from the polynomial optimum (chained inputs) it starts there too. (Shooting's plan of
    its NLPs: its merging of runs for fewer reversals, a step the penalty has not, is off.)"""
    from optimizer.planner import rungs
    monkeypatch.setattr(rungs, "MERGE_TRIES", 0)
    bounds = (None, None, (0.0, HALF_PI))
    shot = plan(request(*OPP_A, method="shooting", joint_bounds=bounds))
    req = request(*OPP_A)
    p = pen.plan_penalty(req, Deadline(30.0), warm_start=shot.inputs)
    # its first NLP starts there (a later one may start from that solution: nlp.solve_rungs)
    assert p.diagnostics["penalty"]["tried"][0]["start"] == "warm_start"
    assert np.max(np.abs(p.inputs.rates - shot.inputs.rates)) < 1e-3
    assert_verified(p, req)
    poly_req = request((10, 10, 10), (30, 30, 30))
    poly = plan(request((10, 10, 10), (30, 30, 30), "polynomial"))
    q = pen.plan_penalty(poly_req, Deadline(30.0), warm_start=poly.inputs)
    assert q.diagnostics["penalty"]["start"] == "warm_start"
    assert "chained" in q.diagnostics["penalty"]["start_reason"]
    assert_verified(q, poly_req)


def test_warm_start_nodes_follow_the_true_path():
    """The node states of a warm start are the original model's (scipy) at the nodes."""
    rates = np.array([[0.8, 0.3], [-0.5, 0.4], [0.6, -0.2], [0.9, 0.1]])
    sched = ActuatorSchedule(breaks=np.linspace(0.0, 2.0, 5), rates=rates)
    req = request((20, 30, 40), (40, 30, 20))
    Q = pen.warm_start_nodes(req, sched, 8)
    q = req.q_start()
    for k in range(4):
        sol = integrate_model(lambda t, uk=rates[k]: uk, q, 0.5, req.robot.gains,
                              req.robot.exponents, t_eval=[0.0, 0.25, 0.5])
        np.testing.assert_allclose(Q[2 * k:2 * k + 3], sol.y.T, atol=1e-9)
        q = sol.y[:, -1]


def test_sensitivity_objective_shortens_phi_travel():
    """||J_R(T)||_F grows with |phi(T) - phi(0)|; with tp_then_sensitivity it is in the
    objective, and the plan's sensitivity is no larger than under tp_then_da."""
    a = plan(request(*OPP_A))
    b = plan(request(*OPP_A, objective="tp_then_sensitivity"))
    assert_verified(b, request(*OPP_A))
    assert b.indicators.sensitivity < a.indicators.sensitivity
    assert abs(b.phi_change) < abs(a.phi_change)


# ---------------------------------------------------------------------- contract
def test_constraint_points_are_refused():
    with pytest.raises(InvalidRequestError) as exc:
        plan(request((10, 10, 10), (30, 30, 30),
                     constraint_points=(ConstraintPoint(0.5, 2, 0.1),)))
    assert exc.value.field == "constraint_points"


def test_tiny_time_limit_answers_quickly():
    """No solve starts after the deadline: a timeout, or (a fast machine, cached solver) a
    verified plan, and in any case promptly. Promptly in CPU time: on a loaded machine the
    wall clock runs 3-5x the CPU time, and a solve run past the deadline costs CPU as well."""
    req = request(*OPP_A, time_limit=0.005)
    t0 = time.process_time()
    try:
        p = plan(req)
    except SolverTimeoutError as exc:
        assert exc.code == "timeout"
    else:
        assert_verified(p, req)
    assert time.process_time() - t0 < 2.0


def test_ipopt_is_stopped_by_the_deadline(monkeypatch):
    """With IPOPT only and a deadline shorter than its solve, the callback stops it and the
    method says it ran out of time."""
    monkeypatch.setattr(pen, "SOLVERS", ("ipopt",))
    req = request(*OPP_B)
    pen.prepare(req.robot.gains, req.robot.exponents)  # built outside the clock
    t0 = time.process_time()  # CPU time: the wall clock of a loaded machine runs 3-5x it
    with pytest.raises(SolverTimeoutError):
        pen.plan_penalty(req, Deadline(0.003))
    assert time.process_time() - t0 < 1.0


def test_solver_exception_becomes_a_numerical_error(monkeypatch):
    """A CasADi exception out of a solver is the library's NumericalError."""
    def raising(self, *args):
        raise RuntimeError("evaluation failed")

    nlp = pen.prepare(Robot().gains, Robot().exponents)
    monkeypatch.setattr(solvers.BufferedCall, "__call__", raising)
    with pytest.raises(NumericalError):
        solvers.run_solver(nlp, "fatrop", np.zeros(nlp.nw), np.zeros(nlp.np),
                             np.full(nlp.nw, -np.inf), np.full(nlp.nw, np.inf), 1.0)


@pytest.mark.parametrize("status, success, kind, error", [
    ("Solve_Succeeded", True, "success", None),
    ("User_Requested_Stop", False, "timeout", SolverTimeoutError),
    ("Maximum_WallTime_Exceeded", False, "timeout", SolverTimeoutError),
    ("Infeasible_Problem_Detected", False, "infeasible", InfeasibleError),
    ("Maximum_Iterations_Exceeded", False, "failure", NumericalError),
])
def test_status_classes_map_to_typed_errors(status, success, kind, error):
    assert solvers.classify(status, success) == kind
    if error is not None:
        assert type(solvers.error_for(kind, "x")) is error


#: A 5-joint robot with gains off the default's (a generated study's) and a goal whose joints
#: move both ways: under ``weighted`` (deviation alone) the first rung's answer chatters
#: (about 50 reversals), and its model ends off the goal where the Newton correction cannot
#: reach (4.7e-6 to 5.7e-6 rad after it).
CHATTER_ROBOT = Robot(gains=(1.0373144131676837, 0.9791494445477504, 0.8872014883250741,
                             0.5456569646140477), exponents=(2, 2, 2, 3))
CHATTER = ((0.5841348926043703, 0.18554478558502518, 0.6124656018127511, 0.2985838665296416,
            0.7566113176999479),
           (0.2048510671315485, 0.18914027569336186, 0.5821118674525504, 0.2795028467631045,
            0.7414803682809198))


def test_a_rung_whose_answer_misses_after_its_correction_goes_on_to_the_finer_rung():
    """As ``shooting`` does: where the first rung's answer cannot be corrected onto the goal,
    the finer rung is solved from its path and that plan is handed out (it was a
    ``numerical_failure``)."""
    from replay_support import replay_linear

    req = PlanRequest(start=CHATTER[0], goal=CHATTER[1], robot=CHATTER_ROBOT, method="penalty",
                      objective="weighted", time_limit=120.0)
    p = plan(req)
    assert p.diagnostics["penalty"]["refined_from_intervals"] == nlp_layer.ladder(5)[0].intervals
    assert_verified(p, req)
    final, margin = replay_linear(req.robot, np.asarray(p.path.t), np.asarray(p.path.u),
                                  req.q_start())
    assert np.max(np.abs(final[1:] - np.array(req.goal))) < 1e-6 and margin > 0.0
