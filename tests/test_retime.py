"""The ``retimed`` method: the paper's geometric path under a d_a-optimal time law.

Checked independently of the planner:
* the Fréchet lower bound on closed-form profiles, and against a brute-force search over
  monotone couplings on a grid;
* the retimed chained path is the same geometric path: z_retimed(tau) = z_geo(sigma(tau)),
  sigma(tau) rebuilt here by linear interpolation of the knots;
* plans: the tests' own scipy integration of the original model reaches the goal, joints stay
  inside (0, pi/2), t_p equals the polynomial method's and d_a is not larger.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from optimizer.chained_form import chained_form
from optimizer.errors import InfeasibleError, InvalidRequestError
from optimizer.planner.plan import plan
from optimizer.planner.retime import frechet_bound, optimal_time_law, retimed_path
from optimizer.problem import PlanRequest
from optimizer.steering import ChainedPath
from optimizer.verify import PlannedInputs

from reference import integrate_model

D = math.radians


def brute_force_frechet(f: np.ndarray, a: float, b: float, levels: int = 801) -> float:
    """Smallest delta with a monotone coupling of the samples of f and a grid on the line
    (discrete Fréchet distance), by bisection on delta and a row-by-row reachability sweep:
    an independent check of the closed form, exact up to the grids' steps."""
    line = np.linspace(a, b, levels)
    cols = np.arange(levels)

    def feasible(delta: float) -> bool:
        ok = np.abs(f[:, None] - line[None, :]) <= delta
        prev = np.zeros(levels, bool)
        for i in range(f.size):
            seed = ok[i] & (prev | np.concatenate([[False], prev[:-1]]))
            if i == 0:
                seed = ok[0] & (cols == 0)
            # a seed reaches every ok cell to its right in the same run of ok cells
            last_seed = np.maximum.accumulate(np.where(seed, cols, -1))
            run_start = np.maximum.accumulate(np.where(~ok[i], cols, -1))
            prev = ok[i] & (last_seed > run_start)
        return bool(prev[-1])

    lo, hi = 0.0, float(np.max(np.abs(f - a)) + abs(b - a))
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if feasible(mid) else (mid, hi)
    return hi


def test_frechet_bound_closed_forms():
    s = np.linspace(0.0, 1.0, 1001)
    assert frechet_bound(s ** 3, 0.0, 1.0) == pytest.approx(0.0)              # monotone
    assert frechet_bound(1.3 * np.sin(np.pi / 2 * s * 1.2) / np.sin(0.6 * np.pi), 0.0, 1.0) \
        == pytest.approx(1.3 / np.sin(0.6 * np.pi) - 1.0, abs=1e-6)            # overshoot
    dip = np.where(s < 0.5, 2 * s, np.where(s < 0.7, 1.0 - 2 * (s - 0.5), 0.6 + (s - 0.7) / 0.75))
    assert frechet_bound(dip, 0.0, 1.0) == pytest.approx(0.2, abs=1e-3)        # backtrack 0.4
    # direction is handled: a decreasing line
    assert frechet_bound(1.0 - dip, 1.0, 0.0) == pytest.approx(0.2, abs=1e-3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_frechet_bound_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, 801)
    f = s + 0.3 * np.sin(2 * np.pi * rng.uniform(1, 3) * s) * np.sin(np.pi * s)
    expected = brute_force_frechet(f, 0.0, 1.0)
    assert expected > 0.02  # the profiles are not monotone
    assert frechet_bound(f, 0.0, 1.0) == pytest.approx(expected, abs=3e-3)


def _request(start_deg, goal_deg, **kw):
    d = {"start": [D(x) for x in start_deg], "goal": [D(x) for x in goal_deg],
         "method": "retimed", "objective": "tp_then_da", "time_limit": 60.0}
    d.update(kw)
    return PlanRequest.from_dict(d)


def test_retimed_inputs_run_the_same_geometric_path():
    req = _request([10, 10, 10], [30, 30, 30], method="polynomial")
    geo = plan(req).chained
    cf = chained_form(req.robot)
    law = optimal_time_law(lambda s: cf.from_chained(geo.z(s)).q[:, 1], D(10), D(30))
    assert np.all(np.diff(law.knots_tau) > 0) and np.all(np.diff(law.knots_sigma) > 0)
    assert law.deviation >= law.bound - 1e-9       # no time law beats the bound
    retimed = ChainedPath.from_inputs(geo.z0, retimed_path(geo, law).inputs)
    tau = np.linspace(0.0, 1.0, 3001)
    sigma = np.interp(tau, law.knots_tau, law.knots_sigma)
    assert np.max(np.abs(retimed.z(tau) - geo.z(sigma))) < 1e-11
    # the composed polynomials the planner uses are the integrated ones
    assert np.max(np.abs(retimed_path(geo, law).z(tau) - retimed.z(tau))) < 1e-11
    # the law does what the LP says on its own samples' scale: d_a close to its value
    th1 = cf.from_chained(retimed.z(tau)).q[:, 1]
    d_a = np.max(np.abs(th1 - (D(10) + tau * D(20))))
    assert d_a == pytest.approx(law.deviation, abs=D(0.5))


@pytest.mark.parametrize("start, goal", [
    ([1, 1, 1], [30, 30, 30]),
    ([5, 5, 5], [30, 30, 30]),
    ([10, 10, 10], [30, 30, 30]),
    ([30, 30, 30], [10, 10, 10]),
    ([47.7, 66.9, 44.9, 66.0], [62.6, 72.2, 47.5, 71.9]),
])
def test_retimed_plan_verified_and_no_worse_than_polynomial(start, goal):
    req = _request(start, goal)
    p = plan(req)
    poly = plan(_request(start, goal, method="polynomial"))
    assert p.method == "retimed"
    assert p.inputs.pieces > 1
    # the tests' own integration of the original model
    cf = chained_form(p.robot)
    inputs = PlannedInputs(cf, p.chained)
    sol = integrate_model(lambda t: inputs.u(np.array([t]))[0], req.q_start(), p.duration,
                          p.robot.gains, p.robot.exponents)
    assert np.max(np.abs(sol.y[1:, -1] - np.array(req.goal))) < 1e-6
    n = p.robot.n
    assert np.all((sol.y[1:n] > 0) & (sol.y[1:n] < np.pi / 2))
    assert p.indicators.t_p == poly.indicators.t_p
    assert p.plan_indicators.d_a <= poly.plan_indicators.d_a + 1e-9
    assert p.plan_indicators.d_a >= p.diagnostics["time_law"]["d_a_lower_bound"] - D(0.05)


def test_retimed_d_a_well_below_constant_v1_on_paper_goals():
    # the Fréchet bound of the chosen member is about 4.8 deg; the constant-v1 optimum 23.1 deg
    p = plan(_request([1, 1, 1], [30, 30, 30]))
    assert math.degrees(p.plan_indicators.d_a) < 12.0
    assert p.indicators.t_p == 1


def test_retimed_refuses_constraint_points():
    with pytest.raises(InvalidRequestError) as exc:
        plan(_request([1, 1, 1], [30, 30, 30], duration=10.0,
                      constraint_points=[{"time": 5.0, "state": 2, "value": -0.3}]))
    assert exc.value.field == "constraint_points"


def test_retimed_opposite_motion_is_infeasible_with_reason():
    with pytest.raises(InfeasibleError) as exc:
        plan(_request([10, 20, 30], [40, 25, 15]))
    assert exc.value.diagnostics["blocking"] == "opposite_joint_motion"


def test_auto_under_the_papers_rule_returns_the_best_of_the_family_and_shooting():
    """Under tp_then_da a goal the family reaches is answered by the best by (t_p, d_a) of the
    polynomial optimum, its retimed path and the shooting plan."""
    p = plan(_request([1, 1, 1], [30, 30, 30], method="auto"))
    r = plan(_request([1, 1, 1], [30, 30, 30]))
    poly = plan(_request([1, 1, 1], [30, 30, 30], method="polynomial"))
    shot = plan(_request([1, 1, 1], [30, 30, 30], method="shooting"))
    auto = p.diagnostics["auto"]
    assert [t["method"] for t in auto["tried"]] == ["polynomial", "retimed", "shooting"]
    assert auto["chosen"] == p.method
    best = min((x.plan_indicators.t_p, x.plan_indicators.d_a) for x in (r, poly, shot))
    assert (p.plan_indicators.t_p, p.plan_indicators.d_a) == best


def test_retimed_speed_bound_and_actuator_limits():
    from optimizer.planner.retime import MAX_SPEEDUP
    p = plan(_request([10, 10, 10], [30, 30, 30]))
    dphi = p.diagnostics["geometric_phi_change"]
    rates = np.array([v[0] for v in p.inputs.v1])          # V1 per piece (dz1/dtau)
    assert np.all(rates > 0) and np.max(rates) <= MAX_SPEEDUP * dphi * (1 + 1e-6)
    # with actuator limits the duration stretches until the sampled rates respect them
    lim = 0.5
    q = plan(_request([10, 10, 10], [30, 30, 30], max_u1=lim, max_u2=lim))
    assert q.duration > 1.0
    assert np.max(np.abs(q.path.u)) <= lim * (1 + 1e-3)
