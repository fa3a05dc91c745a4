"""``/v1/sweeps``, ``/v1/transforms``, ``/v1/robustness`` and ``/v1/robots/default`` through HTTP,
checked against the paper's values (NOTES §2, §5) and against each other."""

from __future__ import annotations

import pytest

from svc_support import DEG, WORKED, assert_problem

#: NOTES §2 check values: z2..z4 of the prototype at th = [1,1,1] deg and [30,30,30] deg.
Z_AT_1_DEG = [-0.033007, 0.711175, 0.017453]
Z_AT_30_DEG = [-0.532238, 0.462133, 0.523599]


def test_sweep_finds_the_worked_example_interval(client):
    lo, hi = 30 * DEG, 40 * DEG
    r = client.post("/v1/sweeps", json={"start": WORKED["start"], "goal": WORKED["goal"],
                                         "phi_change_range": [lo, hi], "points": 41})
    assert r.status_code == 200, r.text
    body = r.json()
    assert len(body["phi_change"]) == len(body["feasible"]) == len(body["d_a"]) == 41
    assert body["phi_change"][0] == pytest.approx(lo) and body["phi_change"][-1] == pytest.approx(hi)
    (a, b), = body["feasible_phi_changes"]
    assert a / DEG == pytest.approx(33.201, abs=0.01)
    assert b / DEG == pytest.approx(35.256, abs=0.01)
    for dphi, ok, d_a in zip(body["phi_change"], body["feasible"], body["d_a"]):
        inside = a + 1e-9 < dphi < b - 1e-9
        outside = dphi < a - 1e-9 or dphi > b + 1e-9
        if inside:
            assert ok and d_a is not None
        if outside:
            assert not ok and d_a is None
    assert body["criterion"] == "full"
    assert body["robot"]["n"] == 3


def test_sweep_range_must_be_ordered(client):
    r = client.post("/v1/sweeps", json={**WORKED, "phi_change_range": [0.7, 0.5], "points": 5})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "phi_change_range"
    r = client.post("/v1/sweeps", json={**WORKED, "points": 100000})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "points"


def test_transform_to_chained_matches_the_paper(client):
    q = [[0.0, DEG, DEG, DEG], [0.25] + [30 * DEG] * 3, [0.0, 100 * DEG, 10 * DEG, 10 * DEG]]
    r = client.post("/v1/transforms", json={"direction": "to_chained", "points": q})
    assert r.status_code == 200, r.text
    body = r.json()
    p1, p30, outside = body["points"]
    assert p1["values"][1:] == pytest.approx(Z_AT_1_DEG, abs=1e-6)
    assert p30["values"][1:] == pytest.approx(Z_AT_30_DEG, abs=1e-6)
    assert p30["values"][0] == 0.25  # z1 = phi
    assert p1["valid"] and p30["valid"] and p1["reason"] is None
    assert outside["valid"] is False and "th1" in outside["reason"]
    assert body["robot"]["assumed_constants"] is False


def test_transform_round_trip_and_invalid_inverse(client):
    q = [0.1, 20 * DEG, 35 * DEG, 50 * DEG]
    z = client.post("/v1/transforms", json={"direction": "to_chained",
                                            "points": [q]}).json()["points"][0]["values"]
    r = client.post("/v1/transforms", json={"direction": "from_chained",
                                            "points": [z, [0.0, 5.0, 5.0, 5.0]]})
    assert r.status_code == 200, r.text
    back, bad = r.json()["points"]
    assert back["valid"] and back["values"] == pytest.approx(q, abs=1e-9)
    assert bad["valid"] is False and bad["reason"]


def test_transform_four_joints_uses_the_assumed_default_robot(client):
    r = client.post("/v1/transforms", json={"direction": "to_chained",
                                            "points": [[0.0, 0.3, 0.3, 0.3, 0.3]]})
    assert r.status_code == 200, r.text
    assert r.json()["robot"]["n"] == 4 and r.json()["robot"]["assumed_constants"] is True


def test_transform_rejects_ragged_rows_and_bad_robot(client):
    r = client.post("/v1/transforms", json={"direction": "to_chained",
                                            "points": [[0, 0.1, 0.1, 0.1], [0, 0.1, 0.1]]})
    assert_problem(r, 422, "invalid_request")
    r = client.post("/v1/transforms", json={"direction": "to_chained", "points": [[0, 0.1, 0.1,
                                                                                   0.1]],
                                            "robot": {"gains": [1, 1, 1], "exponents": [2, 2, 3]}})
    assert_problem(r, 422, "invalid_request")


def test_robustness_from_the_nominal_start_reaches_the_goal(client):
    plan = {**WORKED, "phi_change": 34 * DEG, "samples": 51}
    r = client.post("/v1/robustness", json={"plan": plan, "starts": [WORKED["start"]],
                                             "replay": "u"})
    assert r.status_code == 200, r.text
    body = r.json()
    (run,) = body["runs"]
    assert run["terminal_error"] < 1e-6
    assert run["final"] == pytest.approx(WORKED["goal"], abs=1e-6)
    assert run["singular"] is False
    assert "path_q" not in run or run["path_q"] is None
    assert body["phi_change"] == pytest.approx(34 * DEG)
    assert body["summary"]["runs"] == 1 and body["summary"]["replay"] == "u"


def test_robustness_random_starts_are_reproducible(client):
    req = {"plan": {**WORKED, "phi_change": 34 * DEG, "samples": 21},
           "random": {"count": 4, "spread": 0.5 * DEG, "seed": 7}, "replay": "v",
           "include_paths": True}
    a = client.post("/v1/robustness", json=req)
    b = client.post("/v1/robustness", json=req)
    assert a.status_code == b.status_code == 200, a.text
    ra, rb = a.json()["runs"], b.json()["runs"]
    assert len(ra) == 4
    assert [x["start"] for x in ra] == [x["start"] for x in rb]
    for run in ra:
        assert max(abs(s - g) for s, g in zip(run["start"], WORKED["start"])) <= 0.5 * DEG
        assert len(run["path_q"]) == 21 and len(run["path_q"][0]) == 4
        assert 0 < run["terminal_error"] < 0.1  # perturbed: near, not at, the goal


def test_robustness_needs_exactly_one_source_of_starts(client):
    plan = {**WORKED, "phi_change": 34 * DEG}
    assert_problem(client.post("/v1/robustness", json={"plan": plan}), 422, "invalid_request")
    r = client.post("/v1/robustness", json={"plan": plan, "starts": [[0.2, 0.2]]})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "starts[0]"
    r = client.post("/v1/robustness", json={"plan": plan, "random": {"count": 10 ** 6,
                                                                     "spread": 0.01}})
    assert_problem(r, 422, "invalid_request")


def test_robustness_of_an_infeasible_plan_is_a_problem(client):
    plan = {"start": [10 * DEG, 20 * DEG, 30 * DEG], "goal": [40 * DEG, 25 * DEG, 15 * DEG],
            "method": "polynomial"}
    r = client.post("/v1/robustness", json={"plan": plan, "starts": [plan["start"]]})
    assert_problem(r, 422, "infeasible")


@pytest.mark.parametrize("n, assumed", [(3, False), (4, True), (8, True)])
def test_default_robot(client, n, assumed):
    r = client.get("/v1/robots/default", params={"n": n})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["n"] == n and body["assumed_constants"] is assumed
    assert len(body["gains"]) == len(body["exponents"]) == n - 1
    assert body["gains"][-1] == 0.7115 and body["exponents"][-1] == 3
    assert (body["note"] is not None) is assumed


def test_default_robot_bounds(client):
    assert client.get("/v1/robots/default").json()["n"] == 3
    body = assert_problem(client.get("/v1/robots/default", params={"n": 9}), 422,
                          "invalid_request")
    assert body["field"] == "n" and "8" in body["detail"]


def test_robustness_of_a_shooting_plan(client):
    """A shooting plan (actuator rates) replays its rates ('u'); the chained 'v' replay needs
    chained inputs and is refused, naming the field."""
    plan = {"start": [10 * DEG, 20 * DEG, 30 * DEG], "goal": [40 * DEG, 25 * DEG, 15 * DEG],
            "method": "shooting", "samples": 51}
    r = client.post("/v1/robustness", json={"plan": plan, "starts": [plan["start"]],
                                             "replay": "u"})
    assert r.status_code == 200, r.text
    (run,) = r.json()["runs"]
    assert run["terminal_error"] < 1e-6
    r = client.post("/v1/robustness", json={"plan": plan, "starts": [plan["start"]],
                                             "replay": "v"})
    assert_problem(r, 422, "invalid_request")
    assert "replay" in r.text
