"""Errors a new user meets first say what to change (through HTTP, the shared ``client``)."""

from __future__ import annotations

import json
import math

import pytest

from svc_support import DEG, WORKED, assert_problem


def test_degrees_sent_as_radians_are_recognised(client):
    r = client.post("/v1/plans", json={"start": [10, 10, 10], "goal": [30, 30, 30]})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "start"
    assert "looks like degrees" in body["detail"] and "radians()" in body["detail"]
    assert "0.174533" in body["detail"]  # the converted start, ready to paste
    assert "goal = [30, 30, 30] looks like degrees" in body["detail"]


def test_an_angle_outside_the_region_is_given_in_degrees_too(client):
    r = client.post("/v1/plans", json={**WORKED, "start": [10, 0.2, 0.2]})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "start[0]"
    assert body["detail"] == ("start[0] = 10 rad (573.0 deg) is outside (0, pi/2) rad = "
                              "(0, 90) deg; angles are in radians")
    # a mix (one angle plausible in radians) is not taken for degrees
    assert "looks like degrees" not in body["detail"]


def test_the_last_joint_is_free_within_two_pi(client):
    # th_n does not enter the chained form's singular set: 100 deg is a valid goal angle
    r = client.post("/v1/plans", json={**WORKED, "goal": [30 * DEG, 30 * DEG, 100 * DEG],
                                       "phi_change": 0.6, "samples": 5})
    assert r.status_code in (200, 422), r.text
    if r.status_code == 422:
        assert r.json()["code"] != "invalid_request", r.text
    r = client.post("/v1/plans", json={**WORKED, "goal": [0.5, 0.5, 7.0]})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "goal[2]" and "[-2 pi, 2 pi] rad" in body["detail"]


@pytest.mark.parametrize("headers, shown", [({}, "(none)"),
                                            ({"content-type": "text/plain"}, "text/plain")])
def test_a_body_without_the_json_content_type_is_415(client, headers, shown):
    r = client.post("/v1/plans", content=json.dumps(WORKED).encode(), headers=headers)
    body = assert_problem(r, 415, "invalid_request")
    assert "Content-Type: application/json" in body["detail"] and shown in body["detail"]


def test_a_form_post_is_415_too(client):
    r = client.post("/v1/plans", data={"start": "0.2"})
    body = assert_problem(r, 415, "invalid_request")
    assert "application/x-www-form-urlencoded" in body["detail"]


def test_four_angles_without_a_robot_are_refused(client):
    r = client.post("/v1/plans", json={**WORKED, "start": [0.3] * 4, "goal": [0.5] * 4})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "start"
    assert "default robot has 3 joints" in body["detail"] and "robot" in body["detail"]


def test_four_angles_with_an_explicit_robot_reach_the_planner(client):
    r = client.post("/v1/plans", json={**WORKED, "robot": {}, "start": [0.3] * 4,
                                       "goal": [0.5] * 4, "samples": 5})
    if r.status_code == 200:
        assert r.json()["robot"]["n"] == 4 and r.json()["robot"]["assumed_constants"] is True
    else:  # the planner's own answer, not the joint-count refusal
        assert r.json()["code"] in ("infeasible", "numerical_failure", "timeout"), r.text


def test_goal_and_start_of_different_lengths_name_goal(client):
    r = client.post("/v1/plans", json={**WORKED, "goal": [0.5] * 4})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "goal" and "start has 3" in body["detail"]


def test_batch_items_name_their_place(client):
    r = client.post("/v1/plans/batch", json={"requests": [WORKED, {**WORKED, "start": [10] * 3,
                                                                   "goal": [30] * 3}]})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "requests[1].start" and "looks like degrees" in body["detail"]


def test_the_schema_states_the_fixed_range(client):
    doc = client.get("/openapi.json").json()
    props = doc["components"]["schemas"]["PlanRequest"]["properties"]
    for name in ("start", "goal"):
        first, second = props[name]["prefixItems"]
        for item in (first, second):
            assert item["exclusiveMinimum"] == 0
            assert item["exclusiveMaximum"] == pytest.approx(math.pi / 2)
        assert props[name]["items"]["maximum"] == pytest.approx(2 * math.pi)
    assert "415" in doc["paths"]["/v1/plans"]["post"]["responses"]
