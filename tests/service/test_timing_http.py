"""Limits of the rates and their derivatives through HTTP (issue 25): a duration too short
for them is a 422 naming the binding limit and the shortest duration; the shortest one plans,
rest to rest, with the handed-out rates and slopes within the limits."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer.model import Robot
from replay_support import replay_linear

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

START, GOAL = list(np.radians([10.0, 20.0, 30.0])), list(np.radians([40.0, 25.0, 15.0]))
LIMITS = {"max_u1": 1.0, "max_u2": 1.0, "max_du1": 5.0, "max_du2": 5.0}
BODY = {"start": START, "goal": GOAL, "method": "shooting", "time_limit": 30.0, **LIMITS}


def test_a_duration_too_short_for_the_limits_is_a_422_with_the_shortest(client):
    r = client.post("/v1/plans", json={**BODY, "duration": 0.2})
    assert r.status_code == 422, r.text
    prob = r.json()
    assert prob["code"] == "infeasible" and prob["field"] == "duration"
    shortest = prob["diagnostics"]["shortest_duration"]
    assert shortest > 0.2 and prob["diagnostics"]["binding_limit"] in LIMITS
    assert prob["diagnostics"]["binding_limit"] in prob["detail"]
    assert f"{shortest:.6g}" in prob["detail"]
    ok = client.post("/v1/plans", json={**BODY, "duration": shortest * 1.001})
    assert ok.status_code == 200, ok.text
    assert ok.json()["duration"] == pytest.approx(shortest * 1.001)


def test_limits_without_duration_plan_the_shortest_within_them(client):
    r = client.post("/v1/plans", json=BODY)
    assert r.status_code == 200, r.text
    body = r.json()
    t, u = np.array(body["path"]["t"]), np.array(body["path"]["u"])
    assert np.all(np.diff(t) > 0.0) and np.all(u[0] == 0.0) and np.all(u[-1] == 0.0)
    assert np.abs(u).max() <= 1.01
    assert np.max(np.abs(np.diff(u, axis=0) / np.diff(t)[:, None])) <= 5.05
    law = body["time_law"]
    assert body["duration"] == pytest.approx(law["shortest_duration"])
    assert law["limits"] == LIMITS
    qf, margin = replay_linear(Robot.default(3), t, u, np.concatenate([[0.0], START]))
    assert float(np.max(np.abs(qf[1:] - np.array(GOAL)))) < 1e-6 and margin > 0.0


@pytest.mark.parametrize("field, value", [("max_du1", 0.0), ("max_ddu2", -1.0),
                                          ("max_du2", "fast")])
def test_a_bad_limit_is_a_422_naming_it(client, field, value):
    r = client.post("/v1/plans", json={**BODY, field: value})
    assert r.status_code == 422, r.text
    assert field in r.text
