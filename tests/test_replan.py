"""The replanner (optimizer.planner.replan): closed loop on a plant whose gains are off,
integrated by scipy on the tests' own model; continuations start at the commanded rates;
the same request gives the same answer; bad input is refused naming its field."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from optimizer.errors import InfeasibleError, InvalidRequestError, PlannerError
from optimizer.planner.plan import plan
from optimizer.planner.replan import replan
from optimizer.problem import PlanRequest

from reference import PROTOTYPE_K, PROTOTYPE_M, model_rhs, turns

START, GOAL = (0.3, 0.4, 0.5), (0.9, 1.0, 0.8)


def strip(obj):
    """An answer without its timings (what differs between two runs of the same request)."""
    if isinstance(obj, dict):
        return {k: strip(v) for k, v in obj.items() if k not in ("timing", "seconds")}
    if isinstance(obj, list):
        return [strip(v) for v in obj]
    return obj


@pytest.fixture(scope="module")
def answer() -> dict:
    return plan(PlanRequest(start=START, goal=GOAL)).to_dict()


@pytest.fixture(scope="module")
def timed(answer: dict) -> dict:
    """The answer without its time law: a plan whose rates jump at its breaks (a compact
    form may leave the law out)."""
    return {k: v for k, v in answer.items() if k != "time_law"}


def rates_of(ans: dict, t: float) -> np.ndarray:
    """The rates an answer commands at ``t``, read from its documented representation
    (docs/execution.md): ``u_plan(sigma) dsigma/dlam lam'(t)``, ``lam`` a cubic on each
    phase, ``sigma`` linear in ``lam`` on each knot piece (``sigma = t`` without a law)."""
    segs = ans["coefficients"]["segments"]
    law = ans.get("time_law")
    if law is None:
        sig, ds = t, 1.0
    else:
        ph = law["phases"]
        k = max([i for i, s0 in enumerate(ph["start"]) if s0 <= t] or [0])
        r = min(t - ph["start"][k], ph["length"][k])
        lam = ph["lam0"][k] + ph["v0"][k] * r + ph["a0"][k] * r * r / 2 + ph["jerk"][k] * r ** 3 / 6
        dlam = ph["v0"][k] + ph["a0"][k] * r + ph["jerk"][k] * r * r / 2
        kn = law["knots"]
        j = max([i for i, l0 in enumerate(kn["lam"][:-1]) if l0 <= lam] or [0])
        sig = kn["sigma"][j] + kn["slope"][j] * (lam - kn["lam"][j])
        ds = kn["slope"][j] * dlam
    seg = next((g for g in segs if g["t_start"] <= sig < g["t_end"]), segs[-1])
    return np.array(seg["u"]) * ds


def knots_of(ans: dict) -> list[float]:
    law = ans.get("time_law")
    if law is None:
        return [g["t_start"] for g in ans["coefficients"]["segments"]]
    return list(law["phases"]["start"])


def run_plant(ans: dict, q0: np.ndarray, t0: float, t1: float, K: tuple,
              m: tuple = PROTOTYPE_M) -> np.ndarray:
    """The plant (the tests' own model, gains ``K``, exponents ``m``) under the answer's
    rates, knot to knot."""
    edges = sorted({t0, t1, *(k for k in knots_of(ans) if t0 < k < t1)})
    q = np.asarray(q0, float)
    for a, b in zip(edges[:-1], edges[1:]):
        sol = solve_ivp(lambda t, x: model_rhs(x, rates_of(ans, t), K, m), (a, b), q,
                        method="DOP853", rtol=1e-12, atol=1e-13)
        assert sol.success
        q = sol.y[:, -1]
    return q


def closed_loop(ans: dict, q0: np.ndarray, K: tuple, period: float | None) -> np.ndarray:
    T = ans["duration"]
    t, q, current = 0.0, np.asarray(q0, float), ans
    while t < T - 1e-12:
        if period is not None:
            try:
                current = replan(current, t, q, rates=rates_of(current, t))
            except PlannerError:     # none verified: the controller runs on what it has
                pass
        t_next = T if period is None else min(t + period, T)
        q = run_plant(current, q, t, t_next, K)
        t = t_next
    return q


@pytest.mark.parametrize("law", ["none", "rest_to_rest"])
def test_closed_loop_reaches_the_goal_where_open_loop_misses(answer: dict, timed: dict,
                                                              law: str) -> None:
    ans = timed if law == "none" else answer
    K = (PROTOTYPE_K[0] * 1.005, PROTOTYPE_K[1] * 0.995)     # the plant's gains 0.5 % off
    q0 = np.array([0.0, *START]) + np.radians([0.0, 1.0, -1.0, 1.0])
    open_miss = np.max(np.abs(closed_loop(ans, q0, K, None)[1:] - GOAL))
    closed_miss = np.max(np.abs(closed_loop(ans, q0, K, 0.025)[1:] - GOAL))
    assert open_miss > 1e-2
    assert closed_miss < 1e-4, (open_miss, closed_miss)


@pytest.mark.parametrize("law", ["none", "rest_to_rest"])
def test_a_replan_starts_at_the_given_rates(answer: dict, timed: dict, law: str) -> None:
    ans = timed if law == "none" else answer
    t = 0.37
    given = rates_of(ans, t) * 1.02            # the drive's rates, a little off the plan's
    q = np.array([0.0, *START]) + 0.3 * (np.array([0.6, *GOAL]) - [0.0, *START])
    out = replan(ans, t, q, rates=given)
    path_t, path_u = np.array(out["path"]["t"]), np.array(out["path"]["u"])
    assert path_t[0] == t
    assert np.array_equal(path_u[0], given)
    # the exact rates of the continuation right after t are those rates (no jump)
    assert rates_of(out, t + 1e-9) == pytest.approx(given, rel=1e-6, abs=1e-9)
    # on the handed-out path: the next sample moves at most by the rates' slope
    if law == "none":
        assert np.array_equal(path_u[1], given)
    else:
        du = np.abs(path_u[1] - path_u[0]) / (path_t[1] - path_t[0])
        assert np.all(du < 200.0)      # rad/s^2: a jump of 1e-2 rad/s would read 1e3 here
        assert np.array_equal(path_u[-1], [0.0, 0.0])       # and it ends at rest
    assert out["validation"]["terminal_error"] < 1e-6
    assert out["validation"]["executed"]["terminal_error"] < 1e-6


def test_the_continuation_reaches_the_goal_on_the_tests_model(answer: dict) -> None:
    """The continuation's own rates, integrated on the tests' model from the measured state,
    end at the goal (not only the library's verification says so)."""
    t = 0.25
    q = np.array([0.05, 0.47, 0.58, 0.57])
    out = replan(answer, t, q)
    end = run_plant(out, q, t, out["duration"], PROTOTYPE_K)
    assert np.max(np.abs(end[1:] - GOAL)) < 1e-8


def test_same_request_same_answer(answer: dict) -> None:
    q = np.array([0.05, 0.47, 0.58, 0.57])
    first = replan(answer, 0.25, q)
    replan(answer, 0.6, np.array([0.3, 0.7, 0.8, 0.7]))      # another in between
    again = replan(answer, 0.25, q)
    assert first["coefficients"] == again["coefficients"]
    assert first["path"] == again["path"]


def test_fallback_near_the_end_and_with_a_new_duration(answer: dict) -> None:
    q = np.array([0.9, 0.85, 0.95, 0.78])
    out = replan(answer, 0.8, q, duration=1.5)
    assert out["duration"] == 1.5 and out["path"]["t"][-1] == 1.5
    assert out["validation"]["terminal_error"] < 1e-6
    assert np.array_equal(out["path"]["u"][-1], [0.0, 0.0])


def test_a_chained_plan_is_braked_then_replanned() -> None:
    ans = plan(PlanRequest(start=START, goal=GOAL, method="polynomial")).to_dict()
    t = 0.4
    i = int(np.searchsorted(ans["path"]["t"], t))
    q = np.array(ans["path"]["q"][i]) + [0.0, 0.002, -0.002, 0.002]
    out = replan(ans, ans["path"]["t"][i], q)
    assert out["diagnostics"]["replan"]["route"] == "full_planner"
    assert np.allclose(out["path"]["u"][0], ans["path"]["u"][i], atol=1e-12)
    assert out["validation"]["terminal_error"] < 1e-6
    # a chained plan has no fast path: without the full planner the request is refused
    with pytest.raises(InfeasibleError) as err:
        replan(ans, ans["path"]["t"][i], q, fallback=False)
    assert err.value.field == "fallback"


@pytest.mark.parametrize("kwargs, field", [
    ({"time_": 1.0}, "time"),
    ({"time_": -0.1}, "time"),
    ({"state": [0.0, 0.5, 1.6, 0.5]}, "state[2]"),
    ({"state": [0.0, 0.5, 0.5]}, "state"),
    ({"rates": [1.0]}, "rates"),
    ({"duration": 0.2}, "duration"),
])
def test_bad_input_names_its_field(answer: dict, kwargs: dict, field: str) -> None:
    args = {"time_": 0.5, "state": [0.0, 0.5, 0.5, 0.5], **kwargs}
    with pytest.raises(InvalidRequestError) as err:
        replan(answer, **args)
    assert err.value.field == field


def test_not_our_plan(answer: dict) -> None:
    with pytest.raises(InvalidRequestError) as err:
        replan({"robot": answer["robot"], "goal": list(GOAL)}, 0.5, [0.0, 0.5, 0.5, 0.5])
    assert err.value.field == "plan.coefficients.segments"
    bad = {k: v for k, v in answer.items() if k != "time_law"}
    bad["coefficients"] = {"segments": [dict(s, t_end=s["t_end"] * 2, t_start=s["t_start"] * 2)
                                        for s in answer["coefficients"]["segments"]]}
    with pytest.raises(InvalidRequestError) as err:
        replan(bad, 0.5, [0.0, 0.5, 0.5, 0.5])
    assert err.value.field.startswith("plan.")
    assert math.isfinite(answer["duration"])


def test_keep_reversals_keeps_the_rates_signs(answer: dict) -> None:
    """With keep_reversals the continuation's rates keep the plan's signs (no added reversal
    of phi or th1), or none is handed out (an error naming keep_reversals)."""
    from optimizer.planner.replan import read_plan, sign_changes
    ps = read_plan(answer)
    rng = np.random.default_rng(5)
    for _ in range(6):
        t = float(rng.uniform(0.0, 0.8))
        i = int(np.searchsorted(answer["path"]["t"], t))
        q = np.array(answer["path"]["q"][i]) + [0.0, *rng.uniform(-0.01, 0.01, 3)]
        try:
            out = replan(answer, answer["path"]["t"][i], q, keep_reversals=True)
        except PlannerError as exc:
            assert exc.field == "keep_reversals"
            continue
        rates = np.array([s["u"] for s in out["coefficients"]["segments"]])
        assert sign_changes(rates) <= sign_changes(ps.rates)


def test_a_start_error_alone_is_removed_by_the_first_replan(answer: dict) -> None:
    """Exact gains, a start 1 deg off on every joint: closed loop ends on the goal to the
    integrators' precision (open loop misses by about the start error)."""
    q0 = np.array([0.0, *START]) + np.radians([0.0, 1.0, -1.0, 1.0])
    open_miss = np.max(np.abs(closed_loop(answer, q0, PROTOTYPE_K, None)[1:] - GOAL))
    closed_miss = np.max(np.abs(closed_loop(answer, q0, PROTOTYPE_K, 0.25)[1:] - GOAL))
    assert open_miss > 1e-2
    assert closed_miss < 1e-8


def test_the_compact_form_replans_like_the_answer(answer: dict) -> None:
    """What the replanner reads of an answer (its compact form, a few kB) gives the same
    continuation as the whole answer."""
    import json

    from optimizer.planner.plan_state import read_plan
    compact = json.loads(json.dumps(read_plan(answer).compact()))
    q = np.array([0.05, 0.47, 0.58, 0.57])
    a, b = replan(answer, 0.25, q), replan(compact, 0.25, q)
    assert np.allclose(np.array(a["path"]["u"]), np.array(b["path"]["u"]), rtol=0, atol=1e-12)
    assert a["path"]["t"] == b["path"]["t"]


def test_a_braked_continuation_starts_at_the_rates_and_reaches_the_goal(answer: dict) -> None:
    """Late in the motion, where the rates cannot keep their signs with the motion under way
    run to its piece's end, that motion is braked now and the rest of its piece corrected:
    the continuation still starts at the commanded rates (no jump), adds no reversal, and
    its rates reach the goal on the tests' model (scipy)."""
    from optimizer.planner.replan import read_plan, sign_changes
    ps = read_plan(answer)
    rng = np.random.default_rng(3)
    path_t, path_q = answer["path"]["t"], answer["path"]["q"]
    braked = 0
    for _ in range(16):
        i = int(rng.integers(int(0.8 * len(path_t)), int(0.95 * len(path_t))))
        t = path_t[i]
        q = np.array(path_q[i]) + [0.0, *rng.uniform(-1e-3, 1e-3, 3)]
        out = replan(answer, t, q)
        d = out["diagnostics"]["replan"]
        if not (d["braked"] and d["signs_kept"]):
            continue
        braked += 1
        given = rates_of(answer, t)
        assert rates_of(out, t + 1e-9) == pytest.approx(given, rel=1e-6, abs=1e-9)
        rates = np.array([s["u"] for s in out["coefficients"]["segments"]])
        k = int(np.searchsorted(ps.breaks, ps.law.evaluate(np.array([t]))[0][0],
                                side="right")) - 1
        assert sign_changes(rates) <= sign_changes(ps.rates[k:])
        end = run_plant(out, q, t, out["duration"], PROTOTYPE_K)
        assert np.max(np.abs(end[1:] - GOAL)) < 1e-8
    assert braked >= 1      # the braking path was taken (and checked) at least once


def test_a_replan_a_hair_before_a_stop(answer: dict) -> None:
    """At 1e-7 s before a stop of the plan's law the motion is still under way but its stop
    lies within rounding of plan time: the continuation still starts at the commanded rates
    and reaches the goal (once an IndexError escaped here)."""
    from optimizer.planner.replan import read_plan
    P = read_plan(answer).law.phases
    stops = P[(np.abs(P[:, 3]) <= 1e-12) & (P[:, 0] > 0.0), 0]
    assert stops.size >= 3
    for ts in stops[:3]:
        t = float(ts) - 1e-7
        i = int(np.searchsorted(answer["path"]["t"], t))
        q = np.array(answer["path"]["q"][i])
        out = replan(answer, t, q)
        assert np.array_equal(out["path"]["u"][0], rates_of(answer, t))
        end = run_plant(out, q, t, out["duration"], PROTOTYPE_K)
        assert np.max(np.abs(end[1:] - GOAL)) < 1e-8


def test_a_bounded_plans_answer_replans_within_its_bounds() -> None:
    """The answer of a plan with joint bounds hands them out, and a replan of that answer, as
    returned, keeps them: a measured state outside them (inside (0, pi/2)) is refused naming
    the joint, and a continuation's path stays inside them (checked on its samples here)."""
    bounds = ((0.25, 0.95), None, None)
    ans = plan(PlanRequest(start=START, goal=GOAL, joint_bounds=bounds)).to_dict()
    assert ans["joint_bounds"] == [[0.25, 0.95], None, None]
    with pytest.raises(InvalidRequestError) as err:
        replan(ans, 0.5, [0.0, 0.2, 0.5, 0.5])
    assert err.value.field == "state[1]"
    t = 0.5
    q_mid = run_plant(ans, np.array([0.0, *START]), 0.0, t, PROTOTYPE_K)
    cont = replan(ans, t, q_mid + np.radians([0.0, 0.3, -0.3, 0.3]))
    assert cont["joint_bounds"] == [[0.25, 0.95], None, None]
    th1 = np.asarray(cont["path"]["q"])[:, 1]
    assert np.all((th1 > 0.25) & (th1 < 0.95))
    assert np.max(np.abs(run_plant(cont, q_mid + np.radians([0.0, 0.3, -0.3, 0.3]), t,
                                   cont["duration"], PROTOTYPE_K)[1:] - GOAL)) < 1e-6


def test_a_continuation_that_leaves_the_region_is_named_as_such(answer: dict,
                                                                monkeypatch) -> None:
    """A verified continuation whose joint reaches the region's edge is refused as leaving
    its limits, naming the joint (it was once reported as a failed re-integration, with the
    quadrature's message)."""
    from optimizer.planner import continuation_proof as proof_module

    real = proof_module._replay

    def reaching_the_edge(*args, **kwargs):
        proof = real(*args, **kwargs)
        q = proof.q.copy()
        q[1, 2] = 0.5 * math.pi     # th2 at pi/2 at the first break
        return type(proof)(q, proof.final, proof.error_estimate, True)

    monkeypatch.setattr(proof_module, "_replay", reaching_the_edge)
    t = 0.3 * answer["duration"]
    state = np.array(answer["path"]["q"][int(np.searchsorted(answer["path"]["t"], t))])
    t = float(answer["path"]["t"][int(np.searchsorted(answer["path"]["t"], t))])
    with pytest.raises(InfeasibleError) as err:
        replan(answer, t, state, fallback=False)
    failed = " ".join(err.value.diagnostics["fast_path_failed"])
    assert "th2 outside its limits" in failed
    assert "re-integration failed" not in failed


def test_the_fallback_keeps_to_the_time_limit(answer: dict, monkeypatch) -> None:
    """The full planner's two methods share the replan's time limit: the second gets what the
    first left (on 6-joint states each ran to its own 10 s limit: 20 s for a 10 s replan),
    and none left is a timeout naming ``time_limit``."""
    import time

    from optimizer.errors import NumericalError, SolverTimeoutError
    from optimizer.planner import replan as rp

    def no_fast_path(*args, **kwargs):
        raise NumericalError("the fast path and the warm NLP are not asked here")

    given: list[tuple[str, float]] = []

    def slow_planner(sub):
        given.append((sub.method, sub.time_limit))
        time.sleep(0.3 if sub.method == "shooting" else 0.0)
        raise SolverTimeoutError("found nothing", field="time_limit")

    monkeypatch.setattr(rp, "_fast", no_fast_path)
    monkeypatch.setattr(rp, "_warm", no_fast_path)
    monkeypatch.setattr(rp, "full_plan", slow_planner)
    i = len(answer["path"]["t"]) // 3
    t, state = float(answer["path"]["t"][i]), np.array(answer["path"]["q"][i])
    with pytest.raises(SolverTimeoutError):
        replan(answer, t, state, time_limit=2.0)
    (m1, limit1), (m2, limit2) = given
    assert (m1, m2) == ("shooting", "penalty")
    assert limit1 <= 2.0 and limit2 <= limit1 - 0.3
    # nothing left after the first: a timeout naming the field, the second not run
    given.clear()
    with pytest.raises(SolverTimeoutError) as err:
        replan(answer, t, state, time_limit=0.25)
    assert err.value.field == "time_limit" and [m for m, _ in given] == ["shooting"]


# A 4-joint benchmark goal (r4_002) and a state 0.05 deg off its handed-out path where the
# Gauss-Newton correction of the plan's rest does not reach the goal.
WARM_START = (0.06155288665936719, 1.1146685664563871, 1.0618113844981167, 0.6561993569860203)
WARM_GOAL = (0.5910253096953139, 0.9823358608067385, 1.0344812726248065, 0.6446090051140795)
WARM_SAMPLE = 86
WARM_OFFSET = -np.radians(0.05) * np.array([1.0, -1.0, 1.0, -1.0])


@pytest.fixture(scope="module")
def four_joints() -> dict:
    from optimizer.model import Robot
    return plan(PlanRequest(start=WARM_START, goal=WARM_GOAL, robot=Robot.default(4))).to_dict()


@pytest.mark.parametrize("keep", [False, True])
def test_where_gauss_newton_fails_one_warm_started_nlp_continues(four_joints: dict,
                                                                  keep: bool) -> None:
    """The middle route: the correction of the plan's rest fails, one NLP warm-started on it
    answers (not the full planner); its rates, integrated by scipy on the tests' model from
    the measured state, reach the goal inside the region, start at the commanded rates and,
    with keep_reversals, reverse phi and th1 no more often than the plan's rest."""
    from optimizer.model import Robot
    from optimizer.planner.replan import read_plan, sign_changes
    robot = Robot.default(4)
    t = float(four_joints["path"]["t"][WARM_SAMPLE])
    q = np.array(four_joints["path"]["q"][WARM_SAMPLE]) + np.r_[0.0, WARM_OFFSET]
    out = replan(four_joints, t, q, keep_reversals=keep)
    info = out["diagnostics"]["replan"]
    assert info["route"] == "warm_nlp"
    assert any("Gauss-Newton" in f for f in info["fast_path_failed"])
    assert rates_of(out, t + 1e-9) == pytest.approx(rates_of(four_joints, t), rel=1e-6,
                                                    abs=1e-9)
    end = run_plant(out, q, t, out["duration"], robot.gains, robot.exponents)
    assert np.max(np.abs(end[1:] - np.array(WARM_GOAL))) < 1e-7
    th = np.array(out["path"]["q"])[:, 1:]
    assert np.all((th > 0.0) & (th < math.pi / 2))
    if keep:
        ps = read_plan(four_joints)
        k = ps.piece_at(ps.law.at(t)[0])
        rates = np.array([s["u"] for s in out["coefficients"]["segments"]])
        assert sign_changes(rates) <= sign_changes(ps.rates[k:])


# A 5-joint benchmark goal (r5_000) and a state 0.05 deg off its handed-out path at t = 0.105 s
# (the replan benchmark's): the Gauss-Newton correction fails, and the warm NLP converges in
# 82 fatrop iterations, past a plan's cap of 60.
LONG_START = (0.8515717023649964, 1.4373103098882467, 1.5070077878992296, 0.48589760304936314,
              1.1711319426238491)
LONG_GOAL = (1.2877058594724977, 1.3561836572221437, 1.4910218704514557, 0.48359069885665934,
             0.9159653880698625)
LONG_STATE = (-0.04619740080028006, 0.9135625807020645, 1.4207626795513975, 1.5065959170193017,
              0.48539034301768175, 1.1481328708604215)


def test_the_warm_nlp_iterates_past_a_plans_cap_before_the_full_planner() -> None:
    """The warm NLP makes way for the full planner, not for another cheap attempt: fatrop may
    iterate past a plan's cap there (on this state 82 iterations), and the continuation,
    integrated by scipy from the measured state, reaches the goal inside the region from the
    commanded rates."""
    from optimizer.model import Robot
    from optimizer.planner import solvers
    from optimizer.planner.warm_continuation import WARM_MAX_ITER
    assert WARM_MAX_ITER > solvers.fatrop_max_iter(5)
    robot = Robot.default(5)
    answer = plan(PlanRequest(start=LONG_START, goal=LONG_GOAL, robot=robot)).to_dict()
    t, q = 0.105, np.array(LONG_STATE)
    out = replan(answer, t, q)
    info = out["diagnostics"]["replan"]
    assert info["route"] == "warm_nlp"
    assert rates_of(out, t + 1e-9) == pytest.approx(rates_of(answer, t), rel=1e-6, abs=1e-9)
    end = run_plant(out, q, t, out["duration"], robot.gains, robot.exponents)
    assert np.max(np.abs(end[1:] - np.array(LONG_GOAL))) < 1e-7
    th = np.array(out["path"]["q"])[:, 1:-1]
    assert np.all((th > 0.0) & (th < math.pi / 2))


# ... and a later state of the same plan whose warm NLP takes 111 iterations (t = 0.83 s).
LATER_STATE = (-0.3946337533419238, 1.2631846559260225, 1.3656558218096317, 1.4953593859676206,
               0.48359619006850596, 0.9759204460290515)


def test_a_long_warm_nlp_changes_no_later_answer() -> None:
    """The warm NLP's own solver (its memories per pattern of bounds) keeps nothing from one
    replan to the next: a replan asked before and after another that iterated longer gets
    the same answer."""
    from optimizer.model import Robot

    answer = plan(PlanRequest(start=LONG_START, goal=LONG_GOAL,
                              robot=Robot.default(5))).to_dict()
    first = strip(replan(answer, 0.105, np.array(LONG_STATE)))
    other = replan(answer, 0.83, np.array(LATER_STATE))
    assert other["diagnostics"]["replan"]["route"] == "warm_nlp"
    assert strip(replan(answer, 0.105, np.array(LONG_STATE))) == first


def test_an_nlp_that_iterates_longer_shares_the_compiled_functions() -> None:
    """The iteration cap is fatrop's, not its functions': the warm NLP's variant of the first
    rung is generated from the same functions and finds the same compiled library (other
    functions, other libraries: tests/test_native.py)."""
    from optimizer.model import Robot
    from optimizer.planner.nlp import ladder, nlp_for
    req = PlanRequest(start=LONG_START, goal=LONG_GOAL, robot=Robot.default(5))
    tr = ladder(5)[0]
    plain = nlp_for(req, tr, free=False)
    longer = nlp_for(req, tr, free=False, fatrop_settings=(("max_iter", 150),))
    assert longer is not plain
    assert longer.fingerprint("fatrop") == plain.fingerprint("fatrop")
    # what the service builds at start-up is the NLP the warm route solves
    from optimizer.planner.warm_continuation import WARM_SETTINGS, prepare
    assert prepare(req.robot.gains, req.robot.exponents) is nlp_for(
        req, tr, free=False, fatrop_settings=WARM_SETTINGS)


# A 3-joint goal with th2 near pi/2 (th3 barely follows th2: the end map's third singular
# value is 1e-4 of the first on the plan's rest); a state 0.05 deg off the plan's, th3 too
# high, is one that no Gauss-Newton correction of the rest reaches.
WEAK_START = (0.5743794314462364, 1.4182192902057063, 1.175093552869607)
WEAK_GOAL = (0.8112087585945215, 1.5198626936778183, 1.175436380808428)


@pytest.mark.parametrize("sample", [12, 40])
def test_three_joints_where_gauss_newton_fails_the_warm_nlp_continues(sample: int) -> None:
    """At 3 joints too the warm-started NLP comes before the full planner: its
    continuation, integrated by scipy from the measured state, reaches the goal inside the
    region and starts at the commanded rates."""
    from optimizer.model import Robot
    robot = Robot.default(3)
    answer = plan(PlanRequest(start=WEAK_START, goal=WEAK_GOAL, robot=robot)).to_dict()
    t = float(answer["path"]["t"][sample])
    q = np.array(answer["path"]["q"][sample]) + np.r_[0.0, np.radians(0.05) * np.ones(3)]
    out = replan(answer, t, q)
    info = out["diagnostics"]["replan"]
    assert info["route"] == "warm_nlp"
    assert any("Gauss-Newton" in f for f in info["fast_path_failed"])
    assert rates_of(out, t + 1e-9) == pytest.approx(rates_of(answer, t), rel=1e-6, abs=1e-9)
    end = run_plant(out, q, t, out["duration"], robot.gains, robot.exponents)
    assert np.max(np.abs(end[1:] - np.array(WEAK_GOAL))) < 1e-7
    th = np.array(out["path"]["q"])[:, 1:]
    assert np.all((th > 0.0) & (th < math.pi / 2))


def test_a_three_joint_warm_replan_changes_no_later_answer() -> None:
    """The warm NLP runs on the 3-joint plans' own NLP (its solver memories): a plan asked
    before and after it, and the replan asked twice, get the same answers."""
    from optimizer.model import Robot

    example = PlanRequest(start=(math.radians(10),) * 3, goal=(math.radians(30),) * 3)
    before = strip(plan(example).to_dict())
    answer = plan(PlanRequest(start=WEAK_START, goal=WEAK_GOAL, robot=Robot.default(3))).to_dict()
    t = float(answer["path"]["t"][40])
    q = np.array(answer["path"]["q"][40]) + np.r_[0.0, np.radians(0.05) * np.ones(3)]
    first = replan(answer, t, q)
    assert first["diagnostics"]["replan"]["route"] == "warm_nlp"
    assert strip(plan(example).to_dict()) == before
    assert strip(replan(answer, t, q)) == strip(first)


def plant_reversals(ans: dict, q0: np.ndarray, t0: float, K: tuple) -> int:
    """Direction changes of phi and th1 on the tests' model run under the answer's rates
    from ``q0`` (scipy, knot to knot, 40 samples a knot interval; counted by the tests' own
    rule)."""
    edges = sorted({t0, ans["duration"], *(k for k in knots_of(ans) if t0 < k < ans["duration"])})
    q, path = np.asarray(q0, float), [np.asarray(q0, float)]
    for a, b in zip(edges[:-1], edges[1:]):
        sol = solve_ivp(lambda t, x: model_rhs(x, rates_of(ans, t), K, PROTOTYPE_M), (a, b), q,
                        method="DOP853", rtol=1e-12, atol=1e-13,
                        t_eval=np.linspace(a, b, 41)[1:])
        assert sol.success
        path.extend(sol.y.T)
        q = sol.y[:, -1]
    P = np.array(path)
    return turns(P[:, 0]) + turns(P[:, 1])


def test_at_the_start_at_rest_a_fresh_plan_answers_where_the_correction_reverses_more() -> None:
    """A replan at the plan's start, nothing under way: the corrected plan (the fast path)
    reverses th1 where the plan does not, and a fresh plan from the measured state does not;
    the fresh plan is answered, and it reaches the goal from the measured state."""
    start = (0.6434654828334896, 1.5170547623646518, 0.36430823242705435)
    goal = (1.4689850314167412, 1.495037628413974, 0.3644757153507433)
    measured = (0.6460015892918167, 1.5148684064280735, 0.3593362475532423)
    answer = plan(PlanRequest(start=start, goal=goal)).to_dict()
    q = np.r_[answer["path"]["q"][0][0], measured]
    nominal = plant_reversals(answer, np.r_[answer["path"]["q"][0][0], start], 0.0, PROTOTYPE_K)
    corrected = replan(answer, 0.0, q, fallback=False)      # the fast path alone
    fresh = replan(answer, 0.0, q)
    assert fresh["diagnostics"]["replan"]["route"] == "full_planner"
    assert plant_reversals(corrected, q, 0.0, PROTOTYPE_K) > nominal
    assert plant_reversals(fresh, q, 0.0, PROTOTYPE_K) <= nominal
    end = run_plant(fresh, q, 0.0, fresh["duration"], PROTOTYPE_K)
    assert np.max(np.abs(end[1:] - np.array(goal))) < 1e-7
    # mid-motion (something under way) the correction is answered as before
    i = len(answer["path"]["t"]) // 4
    mid = replan(answer, answer["path"]["t"][i], np.array(answer["path"]["q"][i]))
    assert mid["diagnostics"]["replan"]["route"] == "gauss_newton"


def test_a_plant_off_the_model_stays_inside_in_closed_loop_near_the_edge() -> None:
    """A 4-joint goal whose path passes 0.6 deg from pi/2 (th2), the plant's gains off by up
    to 4 %, reversals kept: a correction that ran the model's path 1e-4 rad from the edge
    let the plant cross it by 2.6e-3 rad; continuations now keep a margin (the plant's path
    is integrated by scipy in optimizer.analysis)."""
    from optimizer.analysis import closed_loop_run
    from optimizer.model import Robot
    goal = (0.39314071194892913, 1.3046926145479274, 1.2356423804917818, 0.4656667382499546)
    nominal = (1.3407553162080403, 1.3400463387457455, 1.2296165497058316, 0.46146682675907086)
    start = (1.3339412082299609, 1.338280231037412, 1.2312153183188388, 0.4571065231577324)
    errors = (0.014411077678212217, 0.040231831901175005, -0.010897036953163478)
    ans = plan(PlanRequest(start=nominal, goal=goal, robot=Robot.default(4))).to_dict()
    run = closed_loop_run(ans, start, errors, 0.05, keep_reversals=True)
    assert run["replans"] >= 3
    th = np.asarray(run["path_q"])[:, 1:]
    assert np.min(np.minimum(th, math.pi / 2 - th)) > 0.0


def test_replans_each_from_the_last_answer_are_accepted_to_the_end() -> None:
    """A controller that replans from its last answer every time: twelve replans, each at 40 %
    of the time left, 0.05 deg off the answer's path. Each answer is taken back (the tail
    pieces get short: their rates, per second of plan time, passed 1e4 at the sixth replan,
    which read_plan refused as 'not a plan of this service'), its samples are no slivers
    (a sample 1e-16 s from a phase start was), and the last one, run on the tests' model
    from its state, ends on the goal."""
    start, goal = tuple(np.radians([10, 20, 30])), tuple(np.radians([40, 25, 15]))
    ans = plan(PlanRequest(start=start, goal=goal)).to_dict()
    offset = np.radians(0.05) * np.array([1.0, -1.0, 1.0])
    for _ in range(12):
        pt, pq = np.array(ans["path"]["t"]), np.array(ans["path"]["q"])
        t = float(pt[0] + 0.4 * (pt[-1] - pt[0]))
        q = np.array([np.interp(t, pt, pq[:, j]) for j in range(4)])
        q[1:] += offset
        ans = replan(ans, t, list(q))
        gaps = np.diff(np.array(ans["path"]["t"]))
        assert np.all((gaps == 0.0) | (gaps > 1e-9)), gaps.min()
    end = run_plant(ans, q, t, ans["duration"], PROTOTYPE_K)
    assert np.max(np.abs(end[1:] - np.array(goal))) < 1e-6


def test_a_full_planner_that_runs_out_of_time_answers_in_the_replans_terms(answer, monkeypatch):
    """Where the fast path and the warm NLP fail and the full planner's penalty NLP runs out
    of its share of the time, the answer names the replan's time_limit (not the share: 'the
    penalty NLP found no path within the time limit of 4.6 s' confused), and keeps the
    planner's words and the fast path's failures in its diagnostics."""
    import optimizer.planner.replan as rp
    from optimizer.errors import NumericalError, SolverTimeoutError

    def failing(*args, **kwargs):
        raise NumericalError("the Gauss-Newton correction did not reach the goal")

    def out_of_time(req):
        raise SolverTimeoutError("the penalty NLP found no path within the time limit of 4.6 s",
                                 field="time_limit")
    monkeypatch.setattr(rp, "_fast", failing)
    monkeypatch.setattr(rp, "_warm", failing)
    monkeypatch.setattr(rp, "full_plan", out_of_time)
    q = np.array([0.0, *START]) + 0.4 * (np.array([0.6, *GOAL]) - [0.0, *START])
    with pytest.raises(SolverTimeoutError) as info:
        replan(answer, 0.4, q, time_limit=7.0)
    err = info.value
    assert err.field == "time_limit"
    assert "within the time limit of 7 s" in err.message and "raise time_limit" in err.message
    assert "4.6 s" in err.diagnostics["full_planner"]
    assert any("Gauss-Newton" in e for e in err.diagnostics["fast_path_failed"])


@pytest.mark.parametrize("equal", [False, True])
def test_the_law_after_a_stop_runs_every_piece_rest_to_rest(equal):
    """:func:`law_after_stop`'s rows, read by the law's own cubics (``TimeLaw.evaluate``):
    contiguous phases from the stop to ``T_end`` (to rounding); at each piece's end the plan time
    is that break (to rounding) and the speed is 0; the pieces' durations are in proportion to
    their lengths (``equal``: all the same); ``last_sigma`` is the law's value at its end."""
    from optimizer.planner.plan_state import TimeLaw, law_after_stop

    rng = np.random.default_rng(11 + int(equal))
    for _ in range(20):
        breaks = np.cumsum(rng.uniform(0.01, 0.4, int(rng.integers(2, 12))))
        t_stop, T_end = float(rng.uniform(0.0, 1.0)), float(rng.uniform(1.5, 4.0))
        law = TimeLaw(law_after_stop(t_stop, T_end, breaks, equal))
        P = law.phases
        assert P[0, 0] == t_stop and law.end == pytest.approx(T_end, abs=1e-12)
        assert np.allclose(P[1:, 0], P[:-1, 0] + P[:-1, 1], rtol=0.0, atol=1e-12)
        ends = P[2::3, 0] + P[2::3, 1]            # each piece is three phases
        sig, ds, _ = law.evaluate(ends)
        assert np.allclose(sig, breaks[1:], rtol=0.0, atol=1e-12)
        assert np.allclose(ds, 0.0, atol=1e-9 * float(np.max(np.abs(P[:, 3]))))
        D = np.diff(np.concatenate([[t_stop], ends]))
        L = np.diff(breaks)
        want = np.full(L.size, (T_end - t_stop) / L.size) if equal else \
            (T_end - t_stop) * L / L.sum()
        assert np.allclose(D, want, rtol=1e-12, atol=1e-12)
        assert law.last_sigma() == pytest.approx(float(law.evaluate(np.array([T_end]))[0][0]),
                                                 abs=1e-12)


@pytest.mark.parametrize("keep", [False, True])
def test_from_four_joints_damped_steps_after_a_singular_kernel_come_last(
        four_joints: dict, keep: bool, monkeypatch) -> None:
    """The fast path's first tries keep every rate's sign whatever the request; after a
    kernel whose system was singular, the damped sign-keeping steps follow at once from 4
    joints only where the request keeps its reversals; otherwise they come after the steps
    with any sign (which mostly answer: the damped ones seldom kept the signs there). The
    kernel is made singular here (the state is one where Gauss-Newton fails)."""
    from optimizer.planner import replan as rp
    calls: list[str] = []

    def singular_kernel(emap, q0, goal, W0, *args, **kwargs):
        calls.append("kernel")
        return math.inf, np.array(W0, float)

    def recorded(name, f):
        def g(*args, **kwargs):
            calls.append(name)
            return f(*args, **kwargs)
        return g

    monkeypatch.setattr(rp, "kernel_correct", singular_kernel)
    monkeypatch.setattr(rp, "damped_correct", recorded("damped", rp.damped_correct))
    monkeypatch.setattr(rp, "halving_correct", recorded("halving", rp.halving_correct))
    t = float(four_joints["path"]["t"][WARM_SAMPLE])
    q = np.array(four_joints["path"]["q"][WARM_SAMPLE]) + np.r_[0.0, WARM_OFFSET]
    try:
        replan(four_joints, t, q, keep_reversals=keep, fallback=False)
    except PlannerError:
        pass
    assert calls[:2] == ["kernel", "damped"] if keep else calls[:3] == ["kernel", "kernel",
                                                                         "halving"]
    assert ("halving" in calls) is not keep
    if not keep:
        assert "damped" in calls        # last, where the steps with any sign failed


def test_a_failed_fast_path_names_the_miss_of_its_steps_with_any_sign(
        four_joints: dict, monkeypatch) -> None:
    """Where every Gauss-Newton try fails from 4 joints (the damped sign-keeping steps last),
    the error says how far the steps with any sign ended from the goal, in rad."""
    from optimizer.planner import replan as rp
    monkeypatch.setattr(rp, "kernel_correct",
                        lambda emap, q0, goal, W0, *a, **k: (math.inf, np.array(W0, float)))
    monkeypatch.setattr(rp, "halving_correct",
                        lambda emap, q0, goal, W0, *a, **k: (0.0123, np.array(W0, float)))
    monkeypatch.setattr(rp, "damped_correct",
                        lambda emap, q0, goal, W0, *a, **k: (0.5, np.array(W0, float), 3))
    t = float(four_joints["path"]["t"][WARM_SAMPLE])
    q = np.array(four_joints["path"]["q"][WARM_SAMPLE]) + np.r_[0.0, WARM_OFFSET]
    with pytest.raises(PlannerError) as info:
        replan(four_joints, t, q, fallback=False)
    assert "miss 0.0123 rad" in info.value.diagnostics["fast_path_failed"][0]


def test_a_continuation_too_coarse_for_its_rates_is_sampled_more_densely() -> None:
    """A 6-joint plan under jerk limits (found by a sweep of generated goals on a robot whose
    gains are off the default) is handed out with 1601 samples over 6.9 s. Its continuation
    from the handed-out state at 18 % of the way, sampled as a continuation is by default
    (about 100 samples), missed the goal by 7e-4 rad when executed by linear interpolation,
    and the replan was refused. Sampled more densely, as the planner does its own path, it is
    handed out and reaches the goal under RK4 of its handed-out rates."""
    from optimizer.model import Robot
    from replay_support import replay_linear_rk4

    req = PlanRequest(
        start=(0.09022211246132794, 0.4427543189736883, 1.2777047427831703,
               1.2979256606969911, 0.8420183118606726, 1.0259765566201433),
        goal=(1.4256337648537185, 0.6334976541767335, 1.361040138280494,
              1.305936819833793, 0.8495143153052945, 1.0503487472277189),
        robot=Robot(gains=(0.7568179390634548, 0.7567386265264985, 0.9408480620507144,
                           0.8016956414006002, 0.6293492403279566),
                    exponents=(2, 2, 2, 2, 3)),
        max_u1=1.0, max_u2=1.0, max_du1=4.0, max_du2=4.0, max_ddu1=31.43340352764829,
        max_ddu2=33.386145471436336, time_limit=30.0)
    answer = plan(req).to_dict()
    t, q = np.asarray(answer["path"]["t"]), np.asarray(answer["path"]["q"])
    k = int(np.searchsorted(t, 0.18 * t[-1]))
    cont = replan(answer, float(t[k]), q[k])
    ct, cu = np.asarray(cont["path"]["t"]), np.asarray(cont["path"]["u"])
    assert ct[0] == t[k] and ct.size > 200
    end, margin = replay_linear_rk4(req.robot, ct - ct[0], cu, q[k])
    assert float(np.max(np.abs(end[1:] - np.array(req.goal)))) < 1e-6
    assert margin > 0.0
