"""Property test of ``POST /v1/plans`` through HTTP: random 3-joint starts and goals (mostly
inside the region, sometimes anywhere in the schema's range), criteria and durations. Every
answer is a 200 whose path starts at ``start`` and ends at ``goal`` with a small re-integration
error, or a 4xx problem with a known code; never a 5xx other than a documented timeout, never a
non-finite number."""

from __future__ import annotations

import json
import math

from hypothesis import HealthCheck, event, given, settings, strategies as st

angle_inside = st.floats(0.05, 1.5)
angle_any = st.floats(-2 * math.pi, 2 * math.pi)


@st.composite
def plan_requests(draw):
    anywhere = draw(st.integers(0, 5)) == 5  # (hypothesis favours small draws)
    angle = angle_any if anywhere else angle_inside
    start = [draw(angle) for _ in range(3)]
    if anywhere:
        goal = [draw(angle) for _ in range(3)]
    else:
        sign = draw(st.sampled_from([-1.0, 1.0]))
        steps = [draw(st.floats(-0.5, 0.5)) for _ in range(3)]
        goal = [min(max(s + (d if i == 0 else sign * abs(d)), 0.03), 1.54)
                for i, (s, d) in enumerate(zip(start, steps))]
    body = {"start": start, "goal": goal,
            "method": "polynomial",
            "samples": draw(st.integers(2, 41)), "time_limit": 1.0,
            "singularity": draw(st.sampled_from(["full", "z2"]))}
    if draw(st.booleans()):
        body["duration"] = draw(st.floats(0.2, 5.0))
    return body


def _finite(token: str) -> float:
    raise AssertionError(f"non-finite number {token}")


@settings(max_examples=40, deadline=None, derandomize=True, database=None,
          suppress_health_check=list(HealthCheck))
@given(body=plan_requests())
def test_a_plan_is_verified_or_a_typed_problem(client, body):
    r = client.post("/v1/plans", json=body)
    doc = json.loads(r.text, parse_constant=_finite)
    event(f"{r.status_code} {doc.get('code', 'plan')}")
    if r.status_code == 200:
        q = doc["path"]["q"]
        assert len(q) >= body["samples"]   # plus the time law's stops and kinks
        assert all(abs(a - b) < 1e-9 for a, b in zip(q[0][1:], body["start"]))
        assert all(abs(a - b) < 1e-6 for a, b in zip(q[-1][1:], body["goal"]))
        assert doc["validation"]["terminal_error"] < 1e-6
        assert doc["validation"]["singular"] is False
        assert doc["indicators"]["margin"] > 0
        return
    assert r.headers["content-type"].startswith("application/problem+json")
    assert (r.status_code, doc["code"]) in {(422, "invalid_request"), (422, "infeasible"),
                                            (422, "numerical_failure"), (504, "timeout")}, doc
    assert doc["detail"]
