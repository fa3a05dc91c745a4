"""Every request limit, through HTTP: one value past it is a 4xx problem naming the field and the
limit, the value at it is accepted. The app runs with *tightened* settings, which shows that each
limit is a setting; the environment names (``PLANNER_*``) and the ``## Limits`` table of
docs/settings.md are checked too."""

from __future__ import annotations

import json
import math
import re
from typing import Any, Iterator

import pytest

from service.settings import Settings, default_settings
from svc_support import DEG, ROOT, TestClient, running_app

W3 = [10 * DEG] * 3
G3 = [30 * DEG] * 3
#: A cheap request (fixed dphi, few samples).
CHEAP = {"start": W3, "goal": G3, "method": "polynomial", "phi_change": 34 * DEG, "samples": 5}

#: The tightened limits of this module's app. The time limits are tightened too, but not so far
#: that an accepted request runs out of time on a loaded machine: the constraint-points plan at
#: the limit takes 0.9 s of CPU, 8 s at load 10 on 2 cores (it was 504 with 1 s).
LIMITS = dict(max_body_bytes=4096, max_joints=5, max_samples=101, max_constraint_points=2,
              max_batch_size=3, max_robustness_runs=4, max_sweep_points=11,
              max_transform_points=5, max_total_samples=250, max_duration=100.0,
              max_time_limit=30.0, default_time_limit=30.0)


@pytest.fixture(scope="module")
def tight() -> Iterator[TestClient]:
    with running_app(workers=1, queue_size=8, **LIMITS) as c:
        yield c


def _send(client: TestClient, path: str, body: Any) -> Any:
    if body is None:
        return client.get(path)
    if isinstance(body, (str, bytes)):
        return client.post(path, content=body, headers={"content-type": "application/json"})
    return client.post(path, json=body)


def _raw(doc: dict[str, Any], **swap: str) -> str:
    """``doc`` as JSON with some values replaced by raw tokens (NaN, 1e400, ...)."""
    text = json.dumps({**doc, **{k: f"@{k}@" for k in swap}})
    for k, token in swap.items():
        text = text.replace(f'"@{k}@"', token)
    return text


def _padded(size: int) -> bytes:
    """A valid plan request of exactly ``size`` bytes (padded with spaces)."""
    text = json.dumps(CHEAP).encode()
    return text[:-1] + b" " * (size - len(text)) + b"}"


TRANSFORM = {"direction": "to_chained"}
ROBUST = {"plan": CHEAP, "replay": "u"}

# (id, path, body, status, field, text naming the limit)
OVER = [
    ("body_bytes", "/v1/plans", _padded(4097), 413, None, "4096 bytes"),
    ("joints_over", "/v1/plans", {**CHEAP, "start": [0.2] * 6, "goal": [0.5] * 6}, 422,
     "start", "at most 5 items"),
    ("joints_under", "/v1/plans", {**CHEAP, "start": [0.2] * 2, "goal": [0.5] * 2}, 422,
     "start", "at least 3 items"),
    ("robot_gains", "/v1/plans", {**CHEAP, "robot": {"gains": [1.0] * 5,
                                                      "exponents": [2] * 5}}, 422,
     "robot.gains", "at most 4 items"),
    ("robots_default_n", "/v1/robots/default?n=6", None, 422, "n", "less than or equal to 5"),
    ("transform_width", "/v1/transforms", {**TRANSFORM, "points": [[0.0] + [0.2] * 6]}, 422,
     "points", "[3, 5] joints"),
    ("samples", "/v1/plans", {**CHEAP, "samples": 102}, 422, "samples",
     "less than or equal to 101"),
    ("samples_min", "/v1/plans", {**CHEAP, "samples": 1}, 422, "samples",
     "greater than or equal to 2"),
    ("constraint_points", "/v1/plans", {**CHEAP, "constraint_points": [
        {"time": 0.2 * (i + 1), "state": 2, "value": 0.1} for i in range(3)]}, 422,
     "constraint_points", "at most 2 items"),
    ("batch_size", "/v1/plans/batch", {"requests": [CHEAP] * 4}, 422, "requests",
     "at most 3 items"),
    ("batch_total_samples", "/v1/plans/batch", {"requests": [{**CHEAP, "samples": 101}] * 3},
     422, "requests", "max_total_samples = 250"),
    ("controller_period_rows", "/v1/plans", {**CHEAP, "controller_period": 0.005}, 422,
     "controller_period", "max_samples = 101"),
    ("batch_total_period_rows", "/v1/plans/batch",
     {"requests": [{**CHEAP, "controller_period": 0.01}] * 3}, 422, "requests",
     "max_total_samples = 250"),
    ("robustness_random", "/v1/robustness", {**ROBUST, "random": {"count": 5,
                                                                  "spread": 0.01}}, 422,
     "random.count", "less than or equal to 4"),
    ("robustness_starts", "/v1/robustness", {**ROBUST, "starts": [W3] * 5}, 422, "starts",
     "at most 4 items"),
    ("robustness_paths", "/v1/robustness", {**ROBUST, "plan": {**CHEAP, "samples": 101},
                                            "random": {"count": 3, "spread": 0.01},
                                            "include_paths": True}, 422,
     "include_paths", "max_total_samples = 250"),
    ("sweep_points", "/v1/sweeps", {**CHEAP, "phi_change_range": [0.5, 0.7], "points": 12},
     422, "points", "less than or equal to 11"),
    ("transform_points", "/v1/transforms", {**TRANSFORM, "points": [[0.0] + W3] * 6}, 422,
     "points", "at most 5 items"),
    ("nan_start", "/v1/plans", _raw(CHEAP, start="[NaN, 0.2, 0.2]"), 422, "start[0]",
     "finite number"),
    ("infinity_goal", "/v1/plans", _raw(CHEAP, goal="[0.5, Infinity, 0.5]"), 422, "goal[1]",
     "finite number"),
    ("overflow_duration", "/v1/plans", _raw(CHEAP, duration="1e400"), 422, "duration",
     "finite number"),
    ("minus_infinity_phi", "/v1/plans", _raw(CHEAP, phi_change="-Infinity"), 422,
     "phi_change", "finite number"),
    ("nan_time_limit", "/v1/plans", _raw(CHEAP, time_limit="NaN"), 422, "time_limit",
     "finite number"),
    ("nan_transform", "/v1/transforms", '{"direction": "to_chained", "points": '
                                        '[[0.0, 0.2, NaN, 0.2]]}', 422, "points[0][2]",
     "finite number"),
    ("string_number", "/v1/plans", {**CHEAP, "samples": "5"}, 422, "samples",
     "valid integer"),
    ("start_outside_region", "/v1/plans", {**CHEAP, "start": [0.2, 1.6, 0.2]}, 422,
     "start[1]", "1.6 rad (91.7 deg) is outside (0, pi/2) rad = (0, 90) deg"),
    ("goal_on_singularity", "/v1/plans", {**CHEAP, "goal": [0.0, 0.5, 0.5]}, 422, "goal[0]",
     "outside (0, pi/2) rad"),
    ("last_angle_beyond_two_pi", "/v1/plans", {**CHEAP, "start": [0.2, 0.2, 7.0]}, 422,
     "start[2]", "outside [-2 pi, 2 pi] rad"),
    ("start_outside_joint_bound", "/v1/plans",
     {**CHEAP, "joint_bounds": [None, None, [0.3, 1.0]]}, 422, "joint_bounds[2]",
     "excludes the start of joint th3"),
    ("duration_long", "/v1/plans", {**CHEAP, "duration": 100.5}, 422, "duration",
     "less than or equal to 100"),
    ("duration_short", "/v1/plans", {**CHEAP, "duration": 0.0005}, 422, "duration",
     "greater than or equal to 0.001"),
    ("constraint_time", "/v1/plans", {**CHEAP, "constraint_points": [
        {"time": 100.5, "state": 2, "value": 0.1}]}, 422, "constraint_points[0].time",
     "less than or equal to 100"),
    ("time_limit_plan", "/v1/plans", {**CHEAP, "time_limit": 30.5}, 422, "time_limit",
     "less than or equal to 30"),
    ("time_limit_zero", "/v1/plans", {**CHEAP, "time_limit": 0}, 422, "time_limit",
     "greater than 0"),
    ("time_limit_sweep", "/v1/sweeps", {**CHEAP, "phi_change_range": [0.5, 0.7], "points": 3,
                                        "time_limit": 31}, 422, "time_limit",
     "less than or equal to 30"),
    ("time_limit_transform", "/v1/transforms", {**TRANSFORM, "points": [[0.0] + W3],
                                                "time_limit": -1}, 422, "time_limit",
     "greater than 0"),
    ("time_limit_robustness", "/v1/robustness", {**ROBUST, "starts": [W3], "time_limit": 39},
     422, "time_limit", "less than or equal to 30"),
    ("time_limit_batch_item", "/v1/plans/batch", {"requests": [CHEAP, {**CHEAP,
                                                                       "time_limit": 35}]},
     422, "requests[1].time_limit", "less than or equal to 30"),
]


@pytest.mark.parametrize("path, body, status, field, text",
                         [case[1:] for case in OVER], ids=[case[0] for case in OVER])
def test_past_the_limit_is_a_4xx_naming_field_and_limit(tight, path, body, status, field,
                                                       text):
    r = _send(tight, path, body)
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    problem = r.json()
    assert problem["code"] == "invalid_request", problem
    if field is not None:
        assert problem["field"] == field, problem
    if text is not None:
        assert text in problem["detail"], problem["detail"]
    assert "NaN" not in r.text and "Infinity" not in r.text


# (id, path, body): each at its limit, accepted (200)
AT = [
    ("body_bytes", "/v1/plans", _padded(4096)),
    ("joints", "/v1/transforms", {**TRANSFORM, "points": [[0.0] + [0.2] * 5]}),
    ("robots_default_n", "/v1/robots/default?n=5", None),
    ("samples", "/v1/plans", {**CHEAP, "samples": 101}),
    ("constraint_points", "/v1/plans", {
        **CHEAP, "duration": 10.0, "phi_change": None, "method": "constraint_points",
        "constraint_points": [{"time": 5.0, "state": 2, "value": -0.2}]}),
    ("batch", "/v1/plans/batch", {"requests": [{**CHEAP, "samples": 83}] * 3}),
    ("robustness_runs", "/v1/robustness", {**ROBUST, "random": {"count": 4, "spread": 0.01}}),
    ("sweep_points", "/v1/sweeps", {**CHEAP, "phi_change_range": [0.5, 0.7], "points": 11}),
    ("transform_points", "/v1/transforms", {**TRANSFORM, "points": [[0.0] + W3] * 5}),
    ("duration", "/v1/plans", {**CHEAP, "duration": 100.0}),
    ("time_limit", "/v1/plans", {**CHEAP, "time_limit": 30.0}),
]


@pytest.mark.parametrize("path, body", [case[1:] for case in AT], ids=[case[0] for case in AT])
def test_at_the_limit_is_accepted(tight, path, body):
    if isinstance(body, dict):
        body = {k: v for k, v in body.items() if v is not None}
    r = _send(tight, path, body)
    assert r.status_code == 200, r.text


#: Every limit setting: environment value -> the attribute read.
LIMIT_SETTINGS = {
    "max_body_bytes": ("2048", 2048), "max_joints": ("4", 4), "max_samples": ("501", 501),
    "max_constraint_points": ("3", 3), "max_batch_size": ("7", 7),
    "max_robustness_runs": ("9", 9), "max_sweep_points": ("33", 33),
    "max_transform_points": ("77", 77), "max_total_samples": ("1000", 1000),
    "max_duration": ("50", 50.0), "max_time_limit": ("20", 20.0),
    "default_time_limit": ("5", 5.0), "timeout_grace": ("0.25", 0.25),
    "queue_size": ("3", 3), "workers": ("2", 2), "retry_after": ("7", 7),
    "shutdown_timeout": ("12", 12.0),
}


@pytest.mark.parametrize("name", sorted(LIMIT_SETTINGS))
def test_limits_are_settings_from_the_environment(monkeypatch, name):
    raw, value = LIMIT_SETTINGS[name]
    monkeypatch.setenv(f"PLANNER_{name.upper()}", raw)
    assert getattr(Settings(), name) == value


@pytest.mark.parametrize("name, raw", [("max_joints", "9"), ("max_samples", "20002"),
                                       ("max_constraint_points", "9"),
                                       ("max_duration", "1e5"), ("max_time_limit", "601"),
                                       ("max_sweep_points", "5002")])
def test_settings_cannot_loosen_the_library_limits(monkeypatch, name, raw):
    monkeypatch.setenv(f"PLANNER_{name.upper()}", raw)
    with pytest.raises(ValueError):
        Settings()


def test_the_openapi_document_follows_the_limits(tight):
    doc = tight.get("/openapi.json").json()
    plan = doc["components"]["schemas"]["PlanRequest"]["properties"]
    assert plan["samples"]["maximum"] == 101
    assert plan["start"]["maxItems"] == 5
    assert plan["time_limit"]["maximum"] == 30
    assert plan["duration"]["anyOf"][0]["maximum"] == 100
    assert plan["constraint_points"]["anyOf"][0]["maxItems"] == 2
    assert doc["components"]["schemas"]["RandomStarts"]["properties"]["count"]["maximum"] == 4


def test_docs_limits_table_lists_every_limit():
    page = (ROOT / "docs" / "settings.md").read_text(encoding="utf-8")
    section = page.split("\n## Limits", 1)[1].split("\n## ", 1)[0]
    documented = {m.lower() for m in re.findall(r"`PLANNER_([A-Z_]+)`", section)}
    limits = {name for name in LIMIT_SETTINGS if name not in ("workers", "retry_after")}
    assert limits <= documented, limits - documented
    defaults = default_settings()
    for name in limits:
        row = next(line for line in section.splitlines() if f"`PLANNER_{name.upper()}`" in line)
        value = getattr(defaults, name)
        shown = f"{value:g}" if isinstance(value, float) else str(value)
        assert shown in row.replace(",", ""), (name, row)
    assert math.isfinite(defaults.max_duration)
