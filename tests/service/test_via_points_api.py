"""Joint-space via points through HTTP (the shared ``client``): a plan through them, and the
refusals a user meets, each naming the field and what to send instead."""

from __future__ import annotations

import numpy as np
import pytest

from svc_support import DEG, WORKED, assert_problem

BASE = {"start": WORKED["start"], "goal": WORKED["goal"]}
VIA = {"time": 0.37, "joint": "th2", "angle": 35 * DEG}


def test_a_plan_passes_through_its_via_point(client):
    r = client.post("/v1/plans", json={**BASE, "via_points": [VIA]})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["method"] in ("shooting", "penalty")
    path = body["path"]
    t = np.asarray(path["t"])
    col = path["q_names"].index("th2")
    # the via time is a sample of the handed-out path (a knot of its time law)
    k = int(np.argmin(np.abs(t - VIA["time"])))
    assert abs(t[k] - VIA["time"]) < 1e-9
    assert abs(path["q"][k][col] - VIA["angle"]) < 1e-6
    (reported,) = body["diagnostics"]["via_points"]
    assert reported["joint"] == "th2" and reported["error"] < 1e-6
    tried = {x["method"] for x in body["diagnostics"]["auto"]["tried"]}
    assert tried <= {"shooting", "penalty"}


@pytest.mark.parametrize("method", ["polynomial", "retimed", "constraint_points"])
def test_the_papers_family_answers_422_naming_via_points(client, method):
    r = client.post("/v1/plans", json={**BASE, "method": method, "via_points": [VIA]})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "via_points"
    assert "chained-form states" in body["detail"] and "'shooting'" in body["detail"]


@pytest.mark.parametrize("via, field, text", [
    ({**VIA, "time": 1.0}, "via_points[0].time", "(0, 1) s"),
    ({**VIA, "joint": "th4"}, "via_points[0].joint", "['th1', 'th2', 'th3']"),
    ({**VIA, "angle": 20}, "via_points[0].angle", "looks like degrees"),
    ({**VIA, "angle": -0.2}, "via_points[0].angle", "(0, 1.5708) rad"),
])
def test_bad_via_points_are_422_naming_the_element(client, via, field, text):
    r = client.post("/v1/plans", json={**BASE, "via_points": [via]})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == field and text in body["detail"], body


def test_a_duplicate_via_point_is_422(client):
    r = client.post("/v1/plans", json={**BASE, "via_points": [VIA, {**VIA, "angle": 0.5}]})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "via_points[1]" and "one angle per joint" in body["detail"]


def test_a_sweep_refuses_via_points(client):
    r = client.post("/v1/sweeps", json={**BASE, "points": 5, "via_points": [VIA]})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "via_points" and "polynomial family" in body["detail"]
