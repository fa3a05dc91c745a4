"""``POST /v1/plans`` and ``/v1/plans/batch`` through HTTP: successes checked against the paper's
worked example, and every failure code produced by a real cause."""

from __future__ import annotations

import math

import pytest

from svc_support import DEG, WORKED, assert_problem

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def test_worked_example_matches_the_paper(client):
    r = client.post("/v1/plans", json={**WORKED, "samples": 101})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/json"
    body = r.json()
    assert body["status"] == "success" and body["method"] == "polynomial"
    assert body["robot"] == {"n": 3, "gains": [0.88658, 0.7115], "exponents": [2, 3],
                             "assumed_constants": False}
    (lo, hi), = body["feasible_phi_changes"]
    assert lo / DEG == pytest.approx(33.201, abs=0.01)
    assert hi / DEG == pytest.approx(35.256, abs=0.01)
    assert body["phi_change"] / DEG == pytest.approx(34.57, abs=0.05)
    assert body["b0"] == pytest.approx(body["phi_change"] / body["duration"])
    assert body["duration"] == 1.0
    assert body["validation"]["terminal_error"] < 1e-6
    assert body["validation"]["singular"] is False
    path = body["path"]
    assert len(path["t"]) == len(path["q"]) == len(path["z"]) == len(path["u"]) == 101
    assert path["t"][0] == 0.0 and path["t"][-1] == pytest.approx(1.0)
    first, last = path["q"][0], path["q"][-1]
    assert first[1:] == pytest.approx(WORKED["start"], abs=1e-9)
    assert last[1:] == pytest.approx(WORKED["goal"], abs=1e-9)
    assert last[0] - first[0] == pytest.approx(body["phi_change"], abs=1e-9)
    assert body["indicators"]["t_p"] == 1
    assert body["indicators"]["margin"] > 0
    assert "NaN" not in r.text and "Infinity" not in r.text


def test_fixed_phi_change_and_request_id(client):
    dphi = 34.0 * DEG
    r = client.post("/v1/plans", json={**WORKED, "phi_change": dphi, "samples": 11,
                                        "duration": 2.0},
                    headers={"X-Request-ID": "plan-test-1"})
    assert r.status_code == 200, r.text
    assert r.headers["x-request-id"] == "plan-test-1"
    body = r.json()
    assert body["phi_change"] == pytest.approx(dphi, abs=1e-12)
    assert body["b0"] == pytest.approx(dphi / 2.0)
    assert body["path"]["t"][-1] == pytest.approx(2.0)
    assert body["feasible_phi_changes"] == []


def test_infeasible_goal_is_a_422_problem(client):
    r = client.post("/v1/plans", json={"start": [10 * DEG, 20 * DEG, 30 * DEG],
                                        "goal": [40 * DEG, 25 * DEG, 15 * DEG],
                                        "method": "polynomial"})
    body = assert_problem(r, 422, "infeasible")
    assert "opposite directions" in body["detail"]
    assert body["request_id"] == r.headers["x-request-id"]


@pytest.mark.parametrize("change, field, words", [
    ({"start": [0.2] * 9, "goal": [0.3] * 9}, "start", "at most 8"),
    ({"start": ["NaN", 0.2, 0.2]}, "start[0]", "valid number"),
    ({"goal": [0.3, 0.3, 1e300]}, "goal[2]", "outside [-2 pi, 2 pi] rad"),
    ({"samples": 100000}, "samples", "20001"),
    ({"samples": "201"}, "samples", "valid integer"),
    ({"time_limit": 1000}, "time_limit", "60"),
    ({"method": "magic"}, "method", "polynomial"),
    ({"colour": "red"}, "colour", "unknown field"),
    ({"robot": {"gains": [1.0, -2.0], "exponents": [2, 3]}}, "robot.gains[1]", "greater than 0"),
])
def test_schema_violations_are_invalid_request(client, change, field, words):
    r = client.post("/v1/plans", json={**WORKED, **change})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == field
    assert words in body["detail"]
    assert "NaN" not in r.text.replace('"NaN"', "")


@pytest.mark.parametrize("raw, field", [
    ('{"start": [1e400, 0.2, 0.2], "goal": [0.5, 0.5, 0.5]}', "start[0]"),
    ('{"start": [0.2, 0.2, 0.2], "goal": [0.5, -1e999, 0.5]}', "goal[1]"),
    ('{"start": [NaN, 0.2, 0.2], "goal": [0.5, 0.5, 0.5]}', "start[0]"),
    ('{"start": [0.2, 0.2, 0.2], "goal": [0.5, 0.5, Infinity]}', "goal[2]"),
])
def test_non_finite_numbers_are_invalid_request(client, raw, field):
    r = client.post("/v1/plans", content=raw, headers={"content-type": "application/json"})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == field
    assert "finite" in body["detail"]
    assert "NaN" not in r.text and "Infinity" not in r.text


def test_library_validation_is_invalid_request(client):
    # gains and exponents of different lengths pass the schema; the library says why not
    r = client.post("/v1/plans", json={**WORKED, "robot": {"gains": [0.9, 0.7],
                                                           "exponents": [2, 3, 3]}})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "robot.exponents"
    # a start outside the singularity-free region is refused by the planner itself
    r = client.post("/v1/plans", json={**WORKED, "joint_bounds": [[0.3, 1.0], None, None]})
    body = assert_problem(r, 422, "invalid_request")
    # (named by the bound that excludes the start, with its joint)
    assert body["field"] == "joint_bounds[0]" and "start of joint th1" in body["detail"]


def test_tiny_time_limit_with_a_big_search_is_a_504(client):
    r = client.post("/v1/plans", json={"robot": {}, "start": [10 * DEG] * 8,
                                        "goal": [30 * DEG] * 8,
                                        "method": "polynomial", "time_limit": 0.05,
                                        "phi_change_bounds": [-4 * math.pi, 4 * math.pi]})
    body = assert_problem(r, 504, "timeout")
    assert "0.05" in body["detail"]


def test_batch_answers_in_order(client):
    requests = [
        {**WORKED, "samples": 11},
        {"start": [10 * DEG, 20 * DEG, 30 * DEG], "goal": [40 * DEG, 25 * DEG, 15 * DEG],
         "method": "polynomial"},
        {**WORKED, "phi_change": 34.0 * DEG, "samples": 21},
        {**WORKED, "joint_bounds": [[0.3, 1.0], None, None]},
    ]
    r = client.post("/v1/plans/batch", json={"requests": requests})
    assert r.status_code == 200, r.text
    body = r.json()
    assert [i["index"] for i in body["results"]] == [0, 1, 2, 3]
    assert [i["status"] for i in body["results"]] == ["success", "error", "success", "error"]
    assert body["succeeded"] == 2 and body["failed"] == 2
    first = body["results"][0]["plan"]
    assert first["phi_change"] / DEG == pytest.approx(34.57, abs=0.05)
    assert body["results"][1]["problem"]["code"] == "infeasible"
    assert body["results"][2]["plan"]["phi_change"] == pytest.approx(34.0 * DEG)
    assert body["results"][3]["problem"]["code"] == "invalid_request"


def test_batch_schema_errors_name_the_item(client):
    r = client.post("/v1/plans/batch", json={"requests": [WORKED, {**WORKED, "samples": 1}]})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "requests[1].samples"
    r = client.post("/v1/plans/batch", json={"requests": []})
    assert_problem(r, 422, "invalid_request")


def test_actuator_limit_sets_the_shortest_duration(client):
    r = client.post("/v1/plans", json={**WORKED, "phi_change": 34 * DEG, "max_u1": 0.3,
                                        "samples": 41})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["duration"] > 1.0
    u1 = [abs(row[0]) for row in body["path"]["u"]]
    # the time law cruises at the limit (planned 0.1 % inside it) and starts at rest
    assert max(u1) <= 0.3 and max(u1) == pytest.approx(0.3, rel=2e-3) and u1[0] == 0.0
    assert body["path"]["t"][-1] == pytest.approx(body["duration"])


@pytest.mark.parametrize("extra", [
    {"objective": "weighted", "weights": {"d_a": 1.0, "energy": 0.5}},
    {"objective": "tp_then_sensitivity"},
    {"singularity": "z2"},
])
def test_objectives_and_criteria_pass_through(client, extra):
    r = client.post("/v1/plans", json={**WORKED, **extra, "samples": 11})
    assert r.status_code == 200, r.text
    body = r.json()
    (lo, hi), = body["feasible_phi_changes"]
    assert lo <= body["phi_change"] <= hi
    assert body["diagnostics"]["objective"] == extra.get("objective", "tp_then_da")
    assert body["validation"]["terminal_error"] < 1e-6


def test_shooting_plan_over_http_carries_its_rates(client):
    """Method shooting through the API: a goal beyond the family, rates in the segments."""
    body = {"start": [10 * DEG, 20 * DEG, 30 * DEG], "goal": [40 * DEG, 25 * DEG, 15 * DEG],
            "method": "shooting", "samples": 51}
    r = client.post("/v1/plans", json=body)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["method"] == "shooting" and out["b0"] is None
    segs = out["coefficients"]["segments"]
    assert segs and all(len(s["u"]) == 2 and s["v2"] == [] for s in segs)
    assert out["validation"]["terminal_error"] < 1e-6
    assert max(abs(x - g) for x, g in zip(out["path"]["q"][-1][1:], body["goal"])) < 1e-6
