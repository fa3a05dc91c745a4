"""``max_reversals`` and ``pareto`` over HTTP (issue 26): the budget that cannot be met is a 422
naming the field and the fewest reversals found; bad values are 422 naming the field; a front
answer validates against the documented schema."""

from __future__ import annotations

from svc_support import DEG, assert_problem

#: th2 rises and th3 falls: phi must reverse, so no path has 0 reversals.
OPPOSED = {"start": [10 * DEG, 20 * DEG, 30 * DEG], "goal": [40 * DEG, 25 * DEG, 15 * DEG],
           "samples": 11, "time_limit": 60}


def test_zero_reversals_where_phi_must_reverse_is_422(client) -> None:
    r = client.post("/v1/plans", json={**OPPOSED, "max_reversals": 0})
    body = assert_problem(r, 422, "infeasible")
    assert body["field"] == "max_reversals"
    fewest = body["diagnostics"]["fewest_reversals"]
    assert isinstance(fewest, int) and fewest >= 1
    assert f"at least {fewest}" in body["detail"]


def test_bad_budget_values_name_the_field(client) -> None:
    for value in (-1, 1.5, "2", True, 10 ** 6):
        r = client.post("/v1/plans", json={**OPPOSED, "max_reversals": value})
        body = assert_problem(r, 422, "invalid_request")
        assert "max_reversals" in (body["field"] or ""), body
    r = client.post("/v1/plans", json={**OPPOSED, "pareto": True, "method": "polynomial"})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "pareto"


def test_a_front_answer_matches_its_schema(client) -> None:
    from service.responses import PlanResponse
    r = client.post("/v1/plans", json={**OPPOSED, "pareto": True})
    assert r.status_code == 200, r.text
    body = r.json()
    PlanResponse.model_validate(body)
    members = body["pareto"]
    assert members and sum(m["chosen"] for m in members) == 1
    revs = [m["max_reversals"] for m in members]
    devs = [m["indicators"]["deviation"] for m in members]
    assert revs == sorted(set(revs)) and devs == sorted(devs, reverse=True)
    for m in members:
        assert m["validation"]["terminal_error"] <= 1e-6
        ind = m["indicators"]["reversals"]
        assert ind["phi"] + ind["th1"] == m["max_reversals"]
