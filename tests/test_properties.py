"""Property tests: random robots, starts and goals give a verified plan or a typed failure.

Never an unexpected exception, never a non-finite number in the JSON, and every success is
re-integrated independently (the tests' own model) to the goal.
"""

from __future__ import annotations

import json

import numpy as np
from hypothesis import HealthCheck, given, settings, strategies as st

from optimizer.chained_form import chained_form
from optimizer.errors import PlannerError
from optimizer.model import Robot
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest
from optimizer.verify import PlannedInputs

from reference import integrate_model

angle = st.floats(-0.3, 1.9, allow_nan=False)  # mostly inside (0, pi/2), sometimes outside


@st.composite
def requests(draw, methods):
    n = draw(st.integers(3, 5))
    gains = tuple(draw(st.floats(0.3, 1.5)) for _ in range(n - 1))
    exps = tuple(draw(st.integers(1, 4)) for _ in range(n - 1))
    if draw(st.integers(0, 9)) == 0:  # sometimes anywhere, often outside the region
        start = tuple(draw(angle) for _ in range(n))
        goal = tuple(draw(angle) for _ in range(n))
    else:  # inside, joints 2..n moving one way (what the paper's family can reach)
        start = tuple(draw(st.floats(0.05, 1.5)) for _ in range(n))
        sign = draw(st.sampled_from([-1.0, 1.0]))
        goal = tuple(min(max(s + (d if i == 0 else sign * abs(d)), 0.03), 1.54)
                     for i, (s, d) in enumerate(zip(start, [draw(st.floats(-0.5, 0.5))
                                                            for _ in range(n)])))
    return dict(robot=Robot(gains, exps), start=start, goal=goal,
                method=draw(st.sampled_from(methods)),
                objective=draw(st.sampled_from(["tp_then_da", "tp_then_sensitivity"])),
                singularity=draw(st.sampled_from(["full", "z2"])),
                duration=draw(st.floats(0.2, 5.0)), time_limit=3.0, samples=51)


def _check(kwargs):
    try:
        req = PlanRequest(**kwargs)
        p = plan(req)
    except PlannerError as exc:
        assert exc.code in {"invalid_request", "infeasible", "timeout", "numerical_failure"}
        assert exc.message
        json.dumps(exc.diagnostics, allow_nan=False, default=float)
        return
    json.dumps(p.to_dict(), allow_nan=False)
    inputs = PlannedInputs(chained_form(p.robot), p.chained)
    sol = integrate_model(lambda t: inputs.u(np.array([t]))[0], req.q_start(), p.duration,
                          p.robot.gains, p.robot.exponents)
    assert np.max(np.abs(sol.y[1:, -1] - np.array(req.goal))) < 1e-6


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(requests(["polynomial", "constraint_points"]))
def test_polynomial_and_qp_plan_or_fail_cleanly(kwargs):
    _check(kwargs)
