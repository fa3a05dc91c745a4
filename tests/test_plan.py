"""Plans end to end: verified on the original model (independently), bad input, infeasibility."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optimizer.chained_form import chained_form
from optimizer.errors import InfeasibleError, InvalidRequestError, SolverTimeoutError
from optimizer.model import Robot
from optimizer.planner.plan import plan
from optimizer.steering import ChainedPath, InputSchedule
from optimizer.problem import PlanRequest
from optimizer.verify import PlannedInputs

from reference import integrate_model

D = np.deg2rad


def _independent_final(p, req):
    """Integrate the original model (test's own rhs) under the plan's u(t)."""
    inputs = PlannedInputs(chained_form(p.robot), p.chained)
    sol = integrate_model(lambda t: inputs.u(np.array([t]))[0], req.q_start(), p.duration,
                          p.robot.gains, p.robot.exponents)
    return sol.y[:, -1], sol


def _random_feasible(n, seed, count):
    """Random requests that the polynomial family can plan, made by running a random member of
    the family forward from a random start: draw dphi and v2's n coefficients, keep the draw
    when the path stays well inside the region (dense independent check), and ask for the goal
    it reaches. The planner must then find an interval (containing that dphi) by itself."""
    rng = np.random.default_rng(seed)
    robot = Robot.default(n)
    cf = chained_form(robot)
    tau = np.linspace(0, 1, 4001)
    found = []
    for _ in range(2000):
        q0 = np.concatenate([[0.0], D(rng.uniform(10, 80, n))])
        dphi = float(rng.uniform(0.2, 1.2) * rng.choice([-1, 1]))
        v2 = rng.normal(scale=0.3, size=n)
        path = ChainedPath.from_inputs(cf.to_chained(q0), InputSchedule.single([dphi], v2, 1.0))
        inv = cf.from_chained(path.z(tau))
        th = inv.q[:, 1:n]
        if not (inv.valid.all() and th.min() > D(3) and th.max() < D(87)):
            continue
        goal = inv.q[-1, 1:]
        req = PlanRequest(start=tuple(q0[1:]), goal=tuple(goal), robot=robot,
                          method="polynomial", duration=float(rng.uniform(0.5, 5.0)))
        found.append((req, dphi, plan(req)))
        if len(found) == count:
            break
    assert len(found) == count
    return found


@pytest.mark.parametrize("n, seed, count", [(3, 1, 6), (4, 2, 4)])
def test_random_feasible_requests_reach_goal_on_original_model(n, seed, count):
    for req, dphi_drawn, p in _random_feasible(n, seed, count):
        assert any(a <= dphi_drawn <= b for a, b in p.feasible_phi_changes)
        final, sol = _independent_final(p, req)
        assert np.max(np.abs(final[1:] - np.array(req.goal))) < 1e-6
        assert abs(final[0] - (req.phi_start + p.phi_change)) < 1e-6
        assert p.verification.terminal_error < 1e-6
        assert not p.verification.singular and p.margin > 0
        # the sampled path starts and ends where it should, and stays in the region
        np.testing.assert_allclose(p.path.q[0, 1:], req.start, atol=1e-9)
        np.testing.assert_allclose(p.path.q[-1, 1:], req.goal, atol=1e-9)
        assert np.all(p.path.q[:, 1:n] > 0) and np.all(p.path.q[:, 1:n] < math.pi / 2)
        # b0 is dphi / T (NOTES §4)
        assert p.b0 == pytest.approx(p.phi_change / req.duration)


def test_plan_json_is_finite_and_complete():
    p = plan(PlanRequest(start=tuple(D([10, 10, 10])), goal=tuple(D([30, 30, 30])),
                         samples=51))
    d = p.to_dict()
    assert d["status"] == "success" and d["method"] == p.diagnostics["auto"]["chosen"]
    t = np.asarray(d["path"]["t"])
    # the 51 samples asked for (a sample near a stop or a kink of the time law moved onto
    # it), every stop of the time law, no time twice: the rates are continuous, zero at the
    # ends (docs/execution.md)
    assert len(d["path"]["q"][0]) == 4 and np.all(np.diff(t) > 0.0)
    even = np.linspace(0.0, p.duration, 51)
    assert np.max(np.min(np.abs(even[:, None] - t[None, :]), axis=1)) <= 0.25 * even[1]
    assert np.all(np.isin(p.time_law.stops, t))
    u = np.asarray(d["path"]["u"])
    assert np.all(u[0] == 0.0) and np.all(u[-1] == 0.0)
    import json
    json.dumps(d, allow_nan=False)


@pytest.mark.parametrize("kwargs, field", [
    (dict(start=(0.1, 0.2), goal=(0.3, 0.4)), "start"),
    (dict(start=(0.1, 0.2, float("nan")), goal=(0.3, 0.4, 0.5)), "start[2]"),
    (dict(start=(0.1, 0.2, 0.3), goal=(0.3, float("inf"), 0.5)), "goal[1]"),
    (dict(start=(-0.1, 0.2, 0.3), goal=(0.3, 0.4, 0.5)), "start[0]"),
    (dict(start=(0.1, 0.2, 0.3), goal=(0.3, 1.6, 0.5)), "goal[1]"),
    (dict(start=(0.1, 0.2, 0.3), goal=(0.3, 0.4, 0.5), phi_change=0.0, method="polynomial"),
     "phi_change"),
    (dict(start=(0.1, 0.2, 0.3), goal=(0.3, 0.4, 0.5), samples=10 ** 6), "samples"),
    (dict(start=(0.1, 0.2, 0.3), goal=(0.3, 0.4, 0.5), duration=-1.0), "duration"),
    (dict(start=(0.1, 0.2, 0.3), goal=(0.3, 0.4, 0.5), method="magic"), "method"),
    (dict(start=(0.1, 0.2, 0.3), goal=(0.3, 0.4, 0.5), time_limit=0.0), "time_limit"),
])
def test_bad_input_raises_typed_error_naming_the_field(kwargs, field):
    with pytest.raises(InvalidRequestError) as exc:
        plan(PlanRequest(**kwargs))
    assert exc.value.field == field
    assert exc.value.message


def test_opposite_joint_motions_are_infeasible_for_the_polynomial_family():
    with pytest.raises(InfeasibleError) as exc:
        plan(PlanRequest(start=tuple(D([10, 20, 30])), goal=tuple(D([40, 25, 15])),
                         method="polynomial"))
    assert "opposite directions" in exc.value.message
    assert exc.value.diagnostics["blocking"] == "opposite_joint_motion"


def test_fixed_phi_change_outside_interval_is_infeasible_with_crossing_time():
    with pytest.raises(InfeasibleError) as exc:
        plan(PlanRequest(start=tuple(D([10, 10, 10])), goal=tuple(D([30, 30, 30])),
                         method="polynomial", phi_change=float(D(37.5))))
    assert exc.value.diagnostics["margin"] < 0
    assert 0 <= exc.value.diagnostics["first_crossing_tau"] <= 1
    # the closest alternative is the upper end of the worked example's interval (35.256 deg)
    near = exc.value.diagnostics["closest_feasible_phi_change"]
    assert np.rad2deg(near) == pytest.approx(35.256, abs=2e-3)
    p = plan(PlanRequest(start=tuple(D([10, 10, 10])), goal=tuple(D([30, 30, 30])),
                         method="polynomial", phi_change=near))
    assert p.verification.terminal_error < 1e-6


def test_no_interval_in_bounds_is_infeasible():
    with pytest.raises(InfeasibleError) as exc:
        plan(PlanRequest(start=tuple(D([10, 10, 10])), goal=tuple(D([30, 30, 30])),
                         method="polynomial", phi_change_bounds=(D(10.0), D(30.0))))
    assert exc.value.diagnostics["blocking"] == "no_feasible_phi_change"
    assert np.rad2deg(exc.value.diagnostics["closest_feasible_phi_change"]) == pytest.approx(
        33.201, abs=2e-3)


def test_actuator_limits_give_shortest_duration():
    """The path depends on dphi only: with rate limits the plan's path is run by its time law
    (rest to rest) in the shortest duration that keeps them; the returned rates touch a
    limit (the law plans 0.1 % inside it) and never exceed it, also between the samples of
    the exact law."""
    base = dict(start=tuple(D([10, 10, 10])), goal=tuple(D([30, 30, 30])), method="polynomial")
    p1 = plan(PlanRequest(**base))
    lim = (0.2, 0.5)
    p = plan(PlanRequest(**base, max_u1=lim[0], max_u2=lim[1], samples=2001))
    assert p.phi_change == pytest.approx(p1.phi_change, abs=1e-9)
    assert p.duration == pytest.approx(p.time_law.shortest)
    exact = np.abs(p.rates_at(np.linspace(0.0, p.duration, 20001))[0]).max(axis=0)
    assert max(exact[0] / lim[0], exact[1] / lim[1]) == pytest.approx(0.999, rel=2e-3)
    peak = np.abs(p.path.u).max(axis=0)
    assert np.all(peak <= np.array(lim) * (1 + 1e-6))
    assert np.any(peak >= np.array(lim) * (1 - 3e-3))
    with pytest.raises(InfeasibleError) as exc:
        plan(PlanRequest(**base, max_u1=lim[0], max_u2=lim[1], duration=0.5 * p.duration))
    assert exc.value.diagnostics["shortest_duration"] == pytest.approx(p.duration, rel=1e-2)


@pytest.mark.parametrize("method", ["polynomial", "retimed", "shooting"])
@pytest.mark.parametrize("limit", [5e-324, 1e-300, 1e-6])
def test_tiny_actuator_limits_are_infeasible_not_infinite(method, limit):
    """A limit so small that the shortest duration exceeds the largest allowed (even inf:
    5e-324, found by the API fuzzer, made T infinite and the verification never end) is an
    infeasible answer naming the field, in milliseconds."""
    base = dict(start=tuple(D([10, 10, 10])), goal=tuple(D([30, 30, 30])), method=method)
    if method == "shooting":
        base.update(start=tuple(D([10, 20, 30])), goal=tuple(D([40, 25, 15])))
    with pytest.raises(InfeasibleError) as exc:
        plan(PlanRequest(**base, max_u2=limit, time_limit=5.0))
    assert exc.value.field == "max_u2"
    assert "above the largest allowed" in exc.value.message


def test_joint_bounds_are_respected():
    base = dict(start=tuple(D([10, 10, 10])), goal=tuple(D([30, 30, 30])), method="polynomial")
    free = plan(PlanRequest(**base))
    lo1 = float(np.min(free.path.q[:, 1])) + D(0.5)
    p = plan(PlanRequest(**base, joint_bounds=((lo1 - D(1.0), D(60.0)), None, None)))
    assert np.all(p.path.q[:, 1] >= lo1 - D(1.0))
    with pytest.raises(InvalidRequestError):
        PlanRequest(**base, joint_bounds=((-0.1, 1.0), None, None))


def test_time_limit_is_checked():
    with pytest.raises(SolverTimeoutError):
        plan(PlanRequest(start=tuple(D([10, 10, 10])), goal=tuple(D([30, 30, 30])),
                         method="polynomial", time_limit=1e-4))


def test_energy_is_exact_even_for_sharp_inputs():
    """[1,1,1] -> [30,30,30] deg starts 1 deg from th1 = 0, where u2 peaks near 200 rad/s: the
    reported energy is that of the handed-out rates, linear between the samples; it agrees
    with adaptive quadrature of u1^2 + u2^2 of that interpolant (scipy.integrate.quad)."""
    from scipy.integrate import quad
    p = plan(PlanRequest(start=tuple(D([1, 1, 1])), goal=tuple(D([30, 30, 30])),
                         method="polynomial"))
    t, u = p.path.t, p.path.u
    val = sum(quad(lambda s, k=k: float(np.sum(np.array(
        [np.interp(s, t[k:k + 2], u[k:k + 2, c]) for c in range(2)]) ** 2)),
        t[k], t[k + 1], epsabs=1e-14, epsrel=1e-12)[0] for k in range(t.size - 1))
    assert p.indicators.energy == pytest.approx(val, rel=1e-7)


def test_robustness_replays_honour_their_time_limit():
    from optimizer.analysis import perturbed_starts, robustness
    req = PlanRequest(start=tuple(D([10, 10, 10])), goal=tuple(D([30, 30, 30])),
                      method="polynomial")
    p = plan(req)
    with pytest.raises(SolverTimeoutError) as exc:
        robustness(p, perturbed_starts(req.start, 500, 0.01, 1), "v", req.goal, time_limit=0.2)
    assert exc.value.field == "time_limit"


def test_when_every_method_fails_on_one_field_auto_names_it_and_what_to_change():
    """A duration too short for a rate limit: every method auto runs refuses it for the same
    field. The answer names that field (the service's 422 carries it) and keeps each method's
    whole message, the shortest duration included (it was cut at 160 characters, no field);
    each method runs once."""
    with pytest.raises(InfeasibleError) as info:
        plan(PlanRequest(start=(math.radians(10),) * 3, goal=(math.radians(30),) * 3,
                         max_u1=0.2, duration=0.5))
    err = info.value
    assert err.field == "duration"
    tried = err.diagnostics["auto"]["tried"]
    assert len(tried) >= 2 and len({t["method"] for t in tried}) == len(tried)
    for t in tried:
        assert f"{t['method']}: infeasible: duration 0.5 s is too short" in err.message
    assert err.message.count("the shortest duration that respects the limits is") == len(tried)
    # every method proved it: nothing is said to be a mere search
    assert "not a proof" not in err.message
    assert err.diagnostics["auto"]["searched_without_proof"] == []


def test_when_the_searches_find_nothing_auto_does_not_call_it_a_proof(monkeypatch):
    """Where every method fails, the answer is ``infeasible``; where some of them failed
    because their NLP converged nowhere near a path (no proof that none exists: an 8-joint
    goal of every joint +20 deg exhausts every method in 10 s that way), the message says so
    and names them, and the diagnostics list them; a method that proved its own failure
    (here the family, with no feasible dphi) is not among them."""
    from optimizer.planner.registry import get

    def found_nothing(self, req, ctx):
        raise InfeasibleError("the NLP found no path from any start",
                              diagnostics={"blocking": "nlp_failed", "tried": []})

    def proved(self, req, ctx):
        raise InfeasibleError("no phi_change gives a singularity-free path of the family",
                              diagnostics={"blocking": "no_feasible_phi_change"})

    for name in ("shooting", "penalty"):
        monkeypatch.setattr(type(get(name)), "run", found_nothing)
    monkeypatch.setattr(type(get("polynomial")), "run", proved)
    with pytest.raises(InfeasibleError) as info:
        plan(PlanRequest(start=(math.radians(10),) * 3, goal=(math.radians(30),) * 3))
    err = info.value
    tried = [t["method"] for t in err.diagnostics["auto"]["tried"]]
    assert "shooting" in tried and "polynomial" in tried
    searched = err.diagnostics["auto"]["searched_without_proof"]
    assert "polynomial" not in searched and set(searched) <= {"shooting", "legs", "penalty"}
    # the legs (intermediate goals, optimizer.planner.legs) ran between shooting and penalty,
    # and their failure is a search too
    assert "shooting" in searched and "legs" in searched
    assert f"({', '.join(searched)}: a search that found none, not a proof" in err.message


def _handed_out_th1_extrema(p, req) -> int:
    """``t_p`` counted here: the original model under the answer's handed-out linear rates
    (scipy) ends on the goal inside the region, and ``th1`` (the integral of ``u2``, an exact
    quadratic on every interval) is sampled densely and its turns counted."""
    from optimizer.indicators import REVERSAL_DEAD_BAND
    from reference import turns
    from replay_support import linear_integral, replay_linear

    t, u = np.asarray(p.path.t, float), np.asarray(p.path.u, float)
    final, margin = replay_linear(req.robot, t, u, req.q_start())
    assert np.max(np.abs(final[1:] - np.array(req.goal))) < 1e-6 and margin > 0.0
    return turns(linear_integral(t, u[:, 1], req.start[0]), REVERSAL_DEAD_BAND)


def test_under_the_papers_rule_auto_keeps_shootings_plan_when_it_has_fewer_extrema():
    """Under ``tp_then_da`` auto runs ``shooting`` beside the paper's family and ranks them by
    the paper's rule: on this 5-joint goal the family's best turns th1 three times or more,
    shooting's plan not at all (counted here on the handed-out rates)."""
    from optimizer.reachable import generate

    g = generate(5, 4, seed=77)[3]
    req = PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(5), objective="tp_then_da")
    p = plan(req)
    assert [t["method"] for t in p.diagnostics["auto"]["tried"]] == ["polynomial", "retimed",
                                                                     "shooting"]
    family = plan(PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(5),
                              objective="tp_then_da", method="polynomial"))
    assert _handed_out_th1_extrema(p, req) < _handed_out_th1_extrema(family, req)


def test_under_the_papers_rule_a_goal_the_family_misses_goes_to_shooting_at_once():
    """A 5-joint goal the family cannot reach: ``shooting`` plans it before the constraint-point
    search (which found no path on such goals, in 0.4-3 s each) and that search is skipped."""
    from optimizer.reachable import generate

    g = generate(5, 10, seed=77)[9]
    req = PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(5), objective="tp_then_da")
    p = plan(req)
    assert [t["method"] for t in p.diagnostics["auto"]["tried"]] == ["polynomial", "shooting"]
    assert p.method == "shooting"
    _handed_out_th1_extrema(p, req)  # the handed-out path reaches the goal inside the region


def test_a_method_asked_for_by_name_does_not_call_a_failed_search_a_proof(monkeypatch):
    """As ``auto`` does: where the method's NLPs converged nowhere near a path, the answer is
    ``infeasible`` and says it is a search that found none, not a proof (it said only "the
    shooting NLP found no path from any start")."""
    from optimizer.planner.registry import get

    def found_nothing(self, req, ctx):
        raise InfeasibleError("the NLP found no path from any start",
                              diagnostics={"blocking": "nlp_failed", "tried": []})

    monkeypatch.setattr(type(get("shooting")), "run", found_nothing)
    with pytest.raises(InfeasibleError) as info:
        plan(PlanRequest(start=(math.radians(10),) * 3, goal=(math.radians(30),) * 3,
                         method="shooting"))
    err = info.value
    assert err.message.startswith("the NLP found no path from any start (shooting: a search "
                                  "that found none, not a proof that none exists")
    assert err.diagnostics["searched_without_proof"] == ["shooting"]
    assert err.diagnostics["blocking"] == "nlp_failed"
