"""The default request ``{"start", "goal"}``: the indicators it is ranked by, the one ranking,
every joint inside, and an ``auto`` that survives a failing method.

Every plan is re-integrated here with scipy on the independent reference model
(:mod:`reference`), piece by piece between the plan's own input breaks.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from optimizer.actuation import ActuatorSchedule
from optimizer.chained_form import chained_form
from optimizer.errors import InvalidRequestError
from optimizer.indicators import (ACTUATOR_DEAD_BAND, compute_indicators, count_reversals,
                                  segment_distance)
from optimizer.model import Robot
from optimizer.planner import registry
from optimizer.planner.plan import plan
from optimizer.planner.ranking import rank_key
from optimizer.problem import PlanRequest
from optimizer.verify import PlannedInputs
from reference import model_rhs

R = math.radians
HALF_PI = 0.5 * math.pi
# the goal of issue 15 on which the shooting method's correction met a singular J J^T
FIVE_JOINT_START = (0.20333377784760726, 1.0432485422591222, 1.3451624597043879,
                    1.362258993867828, 1.1658358884929352)
FIVE_JOINT_GOAL = (0.2450720647174855, 1.1013364340405534, 1.3591470939989174,
                   1.365130736788576, 1.1662624279379248)


def replay(p, req: PlanRequest, per_piece: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """The original model under the plan's exact inputs: times and states ``[phi, th]``."""
    robot = req.robot
    if isinstance(p.inputs, ActuatorSchedule):
        breaks = p.inputs.breaks
        u_of_t = p.inputs.u_scalar
    else:
        planned = PlannedInputs(chained_form(robot), p.chained)
        breaks, u_of_t = planned.breaks, planned.u_scalar
    q = np.array((req.phi_start,) + req.start)
    ts, qs = [np.array([0.0])], [q[None, :]]
    for a, b in zip(breaks[:-1], breaks[1:]):
        mid = 0.5 * (a + b)  # the piece's own input, not the next one's at its end
        sol = solve_ivp(lambda t, x: model_rhs(x, u_of_t(min(max(t, a), b - 1e-15 * b)
                                                          if t < mid else t), robot.gains,
                                               robot.exponents),
                        (a, b), q, method="DOP853", rtol=1e-11, atol=1e-12,
                        t_eval=np.linspace(a, b, per_piece))
        assert sol.success, sol.message
        ts.append(sol.t[1:])
        qs.append(sol.y.T[1:])
        q = sol.y[:, -1]
    return np.concatenate(ts), np.concatenate(qs)


def goals_3() -> list[tuple[tuple[float, ...], tuple[float, ...]]]:
    return [(tuple(map(R, (10, 10, 10))), tuple(map(R, (30, 30, 30)))),
            (tuple(map(R, (10, 20, 30))), tuple(map(R, (40, 25, 15)))),
            (tuple(map(R, (15, 25, 5))), tuple(map(R, (35, 30, 45)))),
            (tuple(map(R, (20, 40, 10))), tuple(map(R, (35, 15, 45))))]


def test_segment_distance_against_a_brute_force_projection() -> None:
    rng = np.random.default_rng(7)
    th = rng.normal(size=(50, 4))
    a, b = th[0], th[-1]
    s = np.linspace(0.0, 1.0, 20001)
    seg = a + s[:, None] * (b - a)
    brute = max(float(np.min(np.linalg.norm(seg - x, axis=1))) for x in th)
    assert segment_distance(th) == pytest.approx(brute, abs=1e-4)
    # beyond the ends the distance is to the end point, not to the infinite line
    pts = np.array([[0.0, 0.0], [2.0, 1.0], [1.0, 0.0]])
    # (the line through them passes at 1 from [2, 1]; the segment's end is sqrt(2) away)
    assert segment_distance(pts) == pytest.approx(math.sqrt(2.0), abs=1e-15)


def test_indicators_against_brute_force_values() -> None:
    """compute_indicators' distances, sensitivities and reversal counts against values
    computed here point by point (the closed form of ||J_R||_F at every sample, the distance
    to the line by projection, the reversal count of each signal on its own)."""
    rng = np.random.default_rng(11)
    t = np.linspace(0.0, 2.0, 401)
    q = np.column_stack([np.sin(3.0 * t + rng.uniform()),
                         0.2 + 0.3 * t + 0.05 * np.sin(7.0 * t),
                         0.4 - 0.1 * t + 0.02 * rng.normal(size=t.size),
                         0.5 + 0.05 * t ** 2])
    ind = compute_indicators(t, q, None)
    s = q[:, 0] - q[0, 0]
    # eq 22 by its sum, sample by sample: sqrt(1 + sum_k (n - k) s^2k / (k!)^2), n = 3
    sens = np.sqrt(1.0 + sum((3 - k) * s ** (2 * k) / math.factorial(k) ** 2 for k in range(3)))
    assert ind.sensitivity == pytest.approx(sens[-1], rel=1e-14)
    assert ind.sensitivity_max == pytest.approx(np.max(sens), rel=1e-14)
    th = q[:, 1:]
    d = (th[-1] - th[0]) / np.linalg.norm(th[-1] - th[0])
    rel = th - th[0]
    line = np.linalg.norm(rel - np.outer(rel @ d, d), axis=1)
    assert ind.d_a_joint_space == pytest.approx(np.max(line), rel=1e-12)
    assert ind.deviation == pytest.approx(segment_distance(th), rel=1e-14)
    assert ind.deviation >= ind.d_a_joint_space
    assert ind.reversals_phi == count_reversals(q[:, 0], ACTUATOR_DEAD_BAND) > 0
    assert ind.reversals_th1 == count_reversals(q[:, 1], ACTUATOR_DEAD_BAND)
    assert ind.t_p == count_reversals(q[:, 1])
    assert ind.phi_reversals == count_reversals(q[:, 0])


@pytest.mark.parametrize("start, goal", goals_3())
def test_default_plan_is_verified_with_every_joint_inside(start, goal) -> None:
    req = PlanRequest(start=start, goal=goal)
    p = plan(req)
    assert req.method == "auto" and req.objective == "reversals_then_deviation"
    t, q = replay(p, req)
    assert np.max(np.abs(q[-1, 1:] - np.array(goal))) < 1e-6
    th = q[:, 1:]
    assert np.all((th > 0.0) & (th < HALF_PI)), np.degrees([th.min(), th.max()])
    # the indicators it was ranked by, measured on the re-integrated path
    ind = p.indicators
    assert ind.deviation == pytest.approx(segment_distance(th, np.array(start), np.array(goal)),
                                          abs=2e-3)
    assert ind.reversals_phi == count_reversals(q[:, 0], ACTUATOR_DEAD_BAND)
    assert ind.reversals_th1 == count_reversals(q[:, 1], ACTUATOR_DEAD_BAND)
    auto = p.diagnostics["auto"]
    assert auto["chosen"] == p.method and auto["tried"]
    assert len(str(auto)) < 2000  # a few lines, not a dump


@pytest.mark.parametrize("start, goal", goals_3()[:3])
def test_auto_is_no_worse_than_any_method_by_the_default_rule(start, goal) -> None:
    req = PlanRequest(start=start, goal=goal)
    best = plan(req)
    for name in registry.METHODS:
        try:
            other = plan(PlanRequest(start=start, goal=goal, method=name))
        except Exception:  # noqa: BLE001 - a method that cannot plan this goal
            continue
        # what auto did not run could not have won (see optimizer.planner.auto); what it ran
        # it ranked: neither may beat its answer by more than the solvers' tolerance
        k_best, k_other = rank_key(best.indicators), rank_key(other.indicators)
        assert k_best[0] <= k_other[0], (name, k_best, k_other)
        if k_best[0] == k_other[0] and name in ("shooting", "penalty"):
            assert k_best[1] <= k_other[1] + 1e-3, (name, k_best, k_other)


def test_the_five_joint_goal_of_the_singular_normal_equations_is_planned() -> None:
    req = PlanRequest(start=FIVE_JOINT_START, goal=FIVE_JOINT_GOAL, robot=Robot.default(5))
    p = plan(req)
    t, q = replay(p, req)
    assert np.max(np.abs(q[-1, 1:] - np.array(FIVE_JOINT_GOAL))) < 1e-6
    assert np.all((q[:, 1:] > 0.0) & (q[:, 1:] < HALF_PI))


#: A 6-joint goal from a state near the region's edge (th2 within 0.1 rad of pi/2: a replan's
#: fallback from a state 0.05 deg off a benchmark plan). The first rung's path ends inside the
#: region at its nodes (RK4) but the original model's left it (th5 at -0.1 rad): every method
#: answered "infeasible" for this reachable goal until such a path went on to the finer rung.
EDGE_SIX_JOINT_START = (1.3190825644222655, 1.4703678493722308, 0.9596915919456086,
                        0.5001038695993614, 0.32344599531308255, 1.1790030071921205)
EDGE_SIX_JOINT_GOAL = (1.3295159807900785, 1.4964891584875029, 0.9632727796345305,
                       0.6246816318890367, 0.5943936540977689, 1.395743208790863)


def test_a_rung_whose_true_path_leaves_the_region_goes_on_to_the_finer_rung() -> None:
    req = PlanRequest(start=EDGE_SIX_JOINT_START, goal=EDGE_SIX_JOINT_GOAL,
                      robot=Robot.default(6))
    p = plan(req)
    t, q = replay(p, req)
    assert np.max(np.abs(q[-1, 1:] - np.array(EDGE_SIX_JOINT_GOAL))) < 1e-6
    assert np.all((q[:, 1:] > 0.0) & (q[:, 1:] < HALF_PI)), np.degrees(q[:, 1:].min())


def test_a_method_that_crashes_is_that_methods_failure(monkeypatch) -> None:
    shooting = registry.get("shooting")

    def broken(req, ctx):
        raise RuntimeError("a bug")

    monkeypatch.setattr(shooting, "run", broken)
    start, goal = goals_3()[0]
    p = plan(PlanRequest(start=start, goal=goal))
    outcomes = {t["method"]: t["outcome"] for t in p.diagnostics["auto"]["tried"]}
    assert outcomes["shooting"] == "internal_error: RuntimeError"
    assert p.method != "shooting"


def test_joint_limits_keep_th_n_inside_unless_widened() -> None:
    start, goal = goals_3()[1]
    wide = PlanRequest(start=start, goal=goal, method="shooting",
                       joint_bounds=(None, None, (-1.0, 2.5)))
    narrow = PlanRequest(start=start, goal=goal, method="shooting",
                         joint_bounds=(None, None, (R(14), R(31))))
    for req in (wide, narrow):
        p = plan(req)
        _, q = replay(p, req)
        lo, hi = req.joint_bounds[2]  # type: ignore[index]
        assert np.all((q[:, 3] > lo) & (q[:, 3] < hi))


def test_unknown_method_names_the_field() -> None:
    start, goal = goals_3()[0]
    with pytest.raises(InvalidRequestError) as exc:
        plan(PlanRequest(start=start, goal=goal, method="magic"))
    assert exc.value.field == "method"


@pytest.mark.parametrize("n", [3, 4, 5])
def test_the_monotone_reach_bound_never_rules_out_a_reached_goal(n) -> None:
    """Goals reached by the original model under rates of fixed signs (scipy, the independent
    reference model) always pass the necessary condition that lets the planner skip an NLP."""
    from optimizer.planner.rules import monotone_reach_ok

    robot = Robot.default(n)
    rng = np.random.default_rng(n)
    checked = 0
    for _ in range(200):
        th0 = rng.uniform(R(10), R(80), size=n)
        s1 = rng.choice([-1.0, 1.0])
        c = rng.uniform(0.1, 0.6, size=(2, 3))
        th1_monotone = bool(rng.integers(2))
        s2 = rng.choice([-1.0, 1.0])

        def u(t: float) -> np.ndarray:
            u1 = s1 * (c[0, 0] + c[0, 1] * t + c[0, 2] * t * t)
            u2 = (s2 * (c[1, 0] + c[1, 1] * t) if th1_monotone
                  else 1.5 * math.sin(2 * math.pi * (c[1, 2] + t)))
            return np.array([u1, u2])

        sol = solve_ivp(lambda t, q: model_rhs(q, u(t), robot.gains, robot.exponents),
                        (0.0, 1.0), np.concatenate([[0.0], th0]), method="DOP853",
                        rtol=1e-11, atol=1e-12, dense_output=True)
        th = sol.sol(np.linspace(0.0, 1.0, 2001))[1:].T
        if not (th.min() > 0.0 and th.max() < HALF_PI):
            continue
        req = PlanRequest(start=tuple(th0), goal=tuple(th[-1]), robot=robot)
        assert monotone_reach_ok(req, False)
        if th1_monotone:
            assert monotone_reach_ok(req, True)
        checked += 1
    assert checked >= 40


@pytest.mark.parametrize("n", [4, 6, 8])
def test_the_joint_triples_bound_never_rules_out_a_reached_goal(n) -> None:
    """The same on robots of random gains (0.6 to 1.5 times the prototype's) and exponents
    (1 to 3), joints from 5 to 85 deg (near pi/2 the triples' integrand is steep), th1
    monotone or not: a goal that the original model reaches (scipy) under rates of those
    signs is never ruled out, the joint triples' bound included."""
    from optimizer.planner.rules import _triples_reach_ok, monotone_reach_ok

    rng = np.random.default_rng(100 + n)
    checked = 0
    for _ in range(200):
        base = Robot.default(n)
        robot = Robot(tuple(float(k * rng.uniform(0.6, 1.5)) for k in base.gains),
                      tuple(int(rng.integers(1, 4)) for _ in base.exponents))
        th0 = rng.uniform(R(5), R(85), size=n)
        s1, s2 = rng.choice([-1.0, 1.0]), rng.choice([-1.0, 1.0])
        c = rng.uniform(0.05, 0.6, size=(2, 3))
        th1_monotone = bool(rng.integers(2))

        def u(t: float) -> np.ndarray:
            return np.array([s1 * (c[0, 0] + c[0, 1] * t + c[0, 2] * math.sin(7 * t) ** 2),
                             s2 * (c[1, 0] * math.cos(5 * t) ** 2 + c[1, 1] * t)
                             if th1_monotone else 1.5 * math.sin(2 * math.pi * (c[1, 2] + t))])

        sol = solve_ivp(lambda t, q: model_rhs(q, u(t), robot.gains, robot.exponents),
                        (0.0, 1.0), np.concatenate([[0.0], th0]), method="DOP853",
                        rtol=1e-11, atol=1e-12, dense_output=True)
        th = sol.sol(np.linspace(0.0, 1.0, 2001))[1:].T
        if not (th.min() > 0.0 and th[:, :-1].max() < HALF_PI):
            continue
        req = PlanRequest(start=tuple(th0), goal=tuple(th[-1]), robot=robot)
        assert _triples_reach_ok(req, False) and monotone_reach_ok(req, False)
        if th1_monotone:
            assert _triples_reach_ok(req, True) and monotone_reach_ok(req, True)
        checked += 1
    assert checked >= 30


@pytest.mark.parametrize("goal_index, need, lowest, highest", [
    (0, 0.04807, 0.04861, 0.04975),      # r4_000: below the least th4 can move
    (3, 0.45172, 0.37842, 0.44861),      # r4_003: above the most
])
def test_the_triples_bound_rules_out_what_the_pairs_bound_lets_through(
        goal_index, need, lowest, highest) -> None:
    """Two goals of the goals benchmark (4 joints) whose NLP with phi and th1 monotone found
    nothing (fatrop's iteration cap; a sign slack): along such a path ``cos(th2)^m3 dth2 =
    (K2/K3) cos(th1)^m2 dth3``, so ``gamma = int cos^m3 dth2`` moves against th3 at a slope
    within th1's range, and th4's move is largest (smallest) for gamma fastest (slowest)
    first. Computed here by trapezoids on fine grids (np.interp inverts gamma): th4's need
    lies outside; the pairs' bound alone lets it through."""
    from bench.goals import generate
    from optimizer.planner.rules import _triples_reach_ok, monotone_reach_ok

    robot = Robot.default(4)
    K, m = robot.gains, robot.exponents
    goal = generate(4, 10)[goal_index]
    a, b = np.array(goal.start), np.array(goal.goal)
    s_lo = K[0] / K[1] * math.cos(max(a[0], b[0])) ** m[0]
    s_hi = K[0] / K[1] * math.cos(min(a[0], b[0])) ** m[0]
    g = np.linspace(a[1], b[1], 200001)                  # th2 from its start to its goal
    gamma = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(g)) * 0.5 * (
        np.cos(g[1:]) ** m[1] + np.cos(g[:-1]) ** m[1]))])
    u = np.linspace(0.0, abs(b[2] - a[2]), 200001)      # th3's travel
    x = a[2] + np.sign(b[2] - a[2]) * u
    L, G = u[-1], gamma[-1]
    moves = []
    for gam in (np.minimum(s_hi * u, G - s_lo * (L - u)), np.maximum(s_lo * u, G - s_hi * (L - u))):
        th2 = np.interp(gam, gamma, g)
        moves.append(K[2] / K[1] * np.trapezoid(np.cos(x) ** m[2] / np.cos(th2) ** m[1], u))
    assert abs(b[3] - a[3]) == pytest.approx(need, abs=1e-5)
    assert min(moves) == pytest.approx(lowest, abs=1e-5)
    assert max(moves) == pytest.approx(highest, abs=1e-5)
    req = PlanRequest(start=tuple(a), goal=tuple(b), robot=robot)
    assert not _triples_reach_ok(req, True)
    assert not monotone_reach_ok(req, True)
    from optimizer.planner import rules
    with pytest.MonkeyPatch.context() as mp:   # the pairs' bound alone
        mp.setattr(rules, "_triples_reach_ok", lambda req, th1_monotone: True)
        assert monotone_reach_ok(req, True)


def test_the_bound_rules_out_a_monotone_th1_on_the_worked_example() -> None:
    """[10, 10, 10] -> [30, 30, 30] deg: with th1 and th2 monotone from 10 to 30 deg, th3 can
    move at most (K3 / K2) int_10^30 cos^3 / cos^2(30 deg) ~ 17 deg, not 20: th1 must overshoot
    (the paper's t_p = 1 there)."""
    from optimizer.planner.rules import monotone_reach_ok

    req = PlanRequest(start=tuple(map(R, (10, 10, 10))), goal=tuple(map(R, (30, 30, 30))))
    K2, K3 = req.robot.gains
    x = np.linspace(R(10), R(30), 100001)
    reach = K3 / K2 * np.trapezoid(np.cos(x) ** 3, x) / math.cos(R(30)) ** 2
    assert math.degrees(reach) < 20.0
    assert not monotone_reach_ok(req, True)
    assert monotone_reach_ok(req, False)


@pytest.mark.parametrize("n", [3, 4, 5])
def test_the_th1_monotone_reach_bound_never_rules_out_a_reached_goal(n) -> None:
    """Goals reached by the original model with th1 monotone and phi reversing (scipy, the
    independent reference model) always pass the necessary condition that lets the planner
    skip the NLP of th1 held monotone."""
    from optimizer.planner.rules import th1_monotone_reach_ok

    robot = Robot.default(n)
    rng = np.random.default_rng(10 + n)
    checked = 0
    for _ in range(200):
        th0 = rng.uniform(R(10), R(80), size=n)
        c = rng.uniform(0.2, 0.8, size=4)
        s2 = rng.choice([-1.0, 1.0])

        def u(t: float) -> np.ndarray:
            return np.array([c[0] * math.sin(2 * math.pi * (c[1] + 1.5 * t)),
                             s2 * (c[2] + c[3] * t)])

        sol = solve_ivp(lambda t, q: model_rhs(q, u(t), robot.gains, robot.exponents),
                        (0.0, 1.0), np.concatenate([[0.0], th0]), method="DOP853",
                        rtol=1e-11, atol=1e-12, dense_output=True)
        q = sol.sol(np.linspace(0.0, 1.0, 2001)).T
        th = q[:, 1:]
        if not (th.min() > 0.0 and th.max() < HALF_PI):
            continue
        assert np.any(np.diff(np.sign(np.diff(q[:, 0]))) != 0)  # phi reverses
        req = PlanRequest(start=tuple(th0), goal=tuple(th[-1]), robot=robot)
        assert th1_monotone_reach_ok(req, 0.0, HALF_PI, slack=0.0)
        # and with th2's own range on the path as its bounds
        assert th1_monotone_reach_ok(req, float(th[:, 1].min()), float(th[:, 1].max()),
                                     slack=1e-9)
        checked += 1
    assert checked >= 40


def test_the_th1_monotone_bound_on_the_worked_example() -> None:
    """[10, 10, 10] -> [30, 30, 30] deg with th1 monotone and phi free: th2 at its lower
    bound while th1 moves gives th3 the most, (K3 / K2) (int_0^30 cos^3 / cos^2(30 deg) -
    int_0^10 cos^3 / cos^2(10 deg)) ~ 19.9 deg, not 20 (quadrature by numpy here)."""
    from optimizer.planner.rules import th1_monotone_reach_ok

    req = PlanRequest(start=tuple(map(R, (10, 10, 10))), goal=tuple(map(R, (30, 30, 30))))
    K2, K3 = req.robot.gains

    def integral(lo: float, hi: float) -> float:
        x = np.linspace(lo, hi, 100001)
        return float(np.trapezoid(np.cos(x) ** 3, x))

    for lo2 in (0.0, R(0.5)):
        reach = K3 / K2 * (integral(lo2, R(30)) / math.cos(R(30)) ** 2
                           - integral(lo2, R(10)) / math.cos(R(10)) ** 2)
        assert R(19.5) < reach < R(20.0)
        assert not th1_monotone_reach_ok(req, lo2, HALF_PI)
    # a goal 0.5 deg nearer passes
    near = PlanRequest(start=req.start, goal=tuple(map(R, (30, 30, 29.5))))
    assert th1_monotone_reach_ok(near, 0.0, HALF_PI)


# a freely chosen 3-joint goal (bench.free_goals, seed 13): the free rung reverses phi and th1
# four times, two of them bought back by merging the runs that travel least
MERGED_START, MERGED_GOAL = (0.4366, 1.0695, 0.4679), (0.7894, 0.3198, 0.6964)


def test_runs_that_travel_least_are_merged_for_fewer_reversals(monkeypatch) -> None:
    """The default rule ranks reversals first: where the free NLP's answer reverses an actuator
    twice or more, the run that travels least is merged into its neighbours and the NLP held to
    that pattern (rungs.MERGE_TRIES). Counted on scipy's re-integration of the plan's exact
    inputs: fewer reversals than without the merging, the goal reached, every joint inside."""
    from optimizer.planner import rungs

    req = PlanRequest(start=MERGED_START, goal=MERGED_GOAL)

    def reversals(p) -> int:
        t, q = replay(p, req)
        assert np.max(np.abs(q[-1, 1:] - np.array(MERGED_GOAL))) < 1e-6
        assert np.all((q[:, 1:] > 0.0) & (q[:, 1:] < HALF_PI))
        return (count_reversals(q[:, 0], ACTUATOR_DEAD_BAND)
                + count_reversals(q[:, 1], ACTUATOR_DEAD_BAND))

    merged = plan(req)
    monkeypatch.setattr(rungs, "MERGE_TRIES", 0)
    unmerged = plan(req)
    assert reversals(merged) < reversals(unmerged)
    assert merged.indicators.reversals == reversals(merged)
