"""The OpenAPI document: no drift from what the app serves, real bodies match their documented
schemas, and a client generated from the committed file plans against a live server."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from jsonschema import Draft202012Validator

from service.export_openapi import openapi_document, render
from svc_support import DEG, ROOT, WORKED

#: A start inside the region but outside its joint bound: the library refuses it.
OUTSIDE_BOUND = {"start": [0.2, 0.2, 0.2], "joint_bounds": [[0.3, 1.0], None, None]}

COMMITTED = ROOT / "openapi" / "openapi.json"


def committed() -> dict:
    return json.loads(COMMITTED.read_text(encoding="utf-8"))


def test_committed_openapi_matches_the_app():
    assert COMMITTED.read_text(encoding="utf-8") == render(openapi_document()), (
        "openapi/openapi.json is out of date: run `python -m service.export_openapi`")


def test_served_openapi_matches_the_committed_file():
    """An app of the default settings serves the committed document (the shared test client
    runs with a larger default time limit, which the document states, so it is not used)."""
    from fastapi.testclient import TestClient

    from service.main import create_app
    from service.settings import default_settings

    # (without the app's lifespan: the document does not depend on the worker pool, which
    # would start and warm up workers for nothing)
    served = TestClient(create_app(default_settings())).get("/openapi.json")
    assert served.status_code == 200 and served.json() == committed()


def test_openapi_documents_problems_and_bounds():
    doc = committed()
    plan = doc["paths"]["/v1/plans"]["post"]
    for status in ("422", "503", "504"):
        assert list(plan["responses"][status]["content"]) == ["application/problem+json"]
    props = doc["components"]["schemas"]["PlanRequest"]["properties"]
    assert props["samples"]["maximum"] == 20001
    assert doc["components"]["schemas"]["PlanRequest"]["additionalProperties"] is False
    assert "description" in props["start"] and props["start"]["maxItems"] == 8
    assert "HTTPValidationError" not in doc["components"]["schemas"]


def _validator(name: str) -> Draft202012Validator:
    doc = committed()
    return Draft202012Validator({"$ref": f"#/components/schemas/{name}",
                                 "components": doc["components"]})


def test_real_bodies_match_their_schemas(client):
    cases = [
        (client.post("/v1/plans", json={**WORKED, "samples": 11}), "PlanResponse"),
        (client.post("/v1/plans", json={**WORKED, "start": [10 * DEG, 20 * DEG, 30 * DEG],
                                        "goal": [40 * DEG, 25 * DEG, 15 * DEG]}), "Problem"),
        (client.post("/v1/sweeps", json={**WORKED, "phi_change_range": [0.5, 0.7],
                                          "points": 9}), "SweepResponse"),
        (client.post("/v1/transforms", json={"direction": "from_chained",
                                              "points": [[0, 5, 5, 5]]}), "TransformResponse"),
        (client.post("/v1/robustness", json={"plan": {**WORKED, "phi_change": 34 * DEG,
                                                       "samples": 11},
                                              "random": {"count": 2, "spread": 0.01},
                                              "include_paths": True}), "RobustnessResponse"),
        (client.post("/v1/plans/batch", json={"requests": [{**WORKED, "samples": 5},
                                                           {**WORKED, "samples": 1}]}),
         "Problem"),
        (client.post("/v1/plans/batch", json={"requests": [
            {**WORKED, "phi_change": 34 * DEG, "samples": 5},
            {**WORKED, **OUTSIDE_BOUND}]}), "BatchResponse"),
        (client.get("/v1/robots/default", params={"n": 5}), "DefaultRobot"),
        (client.get("/readyz"), "Readiness"),
        (client.get("/healthz"), "Health"),
    ]
    for response, schema in cases:
        errors = sorted(_validator(schema).iter_errors(response.json()), key=str)
        assert not errors, (schema, response.status_code, [e.message for e in errors[:3]])


def test_generated_client_plans_against_a_live_server(live_server, tmp_path):
    out = tmp_path / "client"
    config = tmp_path / "config.yaml"
    config.write_text("project_name_override: planner-client\n"
                      "package_name_override: planner_client\n"
                      "post_hooks: []\n", encoding="utf-8")
    tool = Path(sys.executable).with_name("openapi-python-client")
    cmd = [str(tool) if tool.exists() else "openapi-python-client", "generate",
           "--path", str(COMMITTED), "--output-path", str(out), "--config", str(config)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert (out / "planner_client" / "api" / "plans" / "create_plan.py").exists()

    sys.path.insert(0, str(out))
    try:
        pc = importlib.import_module("planner_client")
        create_plan = importlib.import_module("planner_client.api.plans.create_plan")
        default_robot = importlib.import_module("planner_client.api.robots.default_robot")
        models = importlib.import_module("planner_client.models")
        with pc.Client(base_url=live_server, timeout=httpx.Timeout(60.0)) as api:
            ok = create_plan.sync_detailed(client=api,
                                           body=models.PlanRequest.from_dict({**WORKED,
                                                                              "samples": 21}))
            assert ok.status_code == 200
            plan = ok.parsed
            assert isinstance(plan, models.PlanResponse)
            assert plan.phi_change / DEG == pytest.approx(34.57, abs=0.05)
            assert plan.validation.terminal_error < 1e-6
            assert plan.path.q[-1][1:] == pytest.approx(WORKED["goal"], abs=1e-9)

            bad = create_plan.sync_detailed(client=api, body=models.PlanRequest.from_dict(
                {**WORKED, "start": [10 * DEG, 20 * DEG, 30 * DEG],
                 "goal": [40 * DEG, 25 * DEG, 15 * DEG]}))
            assert bad.status_code == 422
            assert isinstance(bad.parsed, models.Problem)
            assert bad.parsed.code == models.ProblemCode.INFEASIBLE

            robot = default_robot.sync(client=api, n=4)
            assert robot.n == 4 and robot.assumed_constants is True
    finally:
        sys.path.remove(str(out))
        for name in [m for m in sys.modules if m == "planner_client"
                     or m.startswith("planner_client.")]:
            del sys.modules[name]
