"""What a first-time user and an operator meet in the first hour (issue 28, item 6): probes,
metrics labels, the served OpenAPI document, errors that teach."""

from __future__ import annotations

from svc_support import DEG, WORKED, assert_problem


def test_head_healthz_and_readyz_answer_200(client):
    for path in ("/healthz", "/readyz"):
        r = client.head(path)
        assert r.status_code == 200, (path, r.status_code)
        assert r.content == b""


def test_the_explorer_and_templated_routes_are_labelled_in_the_metrics(client):
    assert client.get("/").status_code == 200
    plan = client.post("/v1/plans", json={**WORKED, "samples": 21}).json()
    r = client.post("/v1/figures/from_plan/joint_angles", params={"format": "svg"}, json=plan)
    assert r.status_code == 200, r.text
    client.get("/no/such/route")
    metrics = client.get("/metrics").text
    assert 'route="/",status="200"' in metrics
    assert 'route="/v1/figures/from_plan/{kind}",status="200"' in metrics
    assert 'route="unmatched",status="404"' in metrics


def _key_schemes(doc: dict) -> tuple[dict, list]:
    ops = [op for item in doc["paths"].values() for op in item.values()]
    return doc.get("components", {}).get("securitySchemes", {}), [
        op["security"] for op in ops if "security" in op]


def test_the_served_openapi_requires_a_key_only_when_keys_are_set(client, keyed_client):
    schemes, secured = _key_schemes(client.get("/openapi.json").json())
    assert schemes == {} and secured == []
    schemes, secured = _key_schemes(keyed_client.get("/openapi.json").json())
    assert "APIKeyHeader" in schemes and secured


def test_joint_bounds_in_degrees_get_a_hint(client):
    body = {**WORKED, "joint_bounds": [[5, 60], None, None]}
    doc = assert_problem(client.post("/v1/plans", json=body), 422, "invalid_request")
    assert doc["field"] == "joint_bounds[0]", doc
    assert "looks like degrees" in doc["detail"] and "0.0872665, 1.0472" in doc["detail"], doc


def test_a_bound_that_excludes_the_goal_names_the_bound_and_the_joint(client):
    body = {**WORKED, "joint_bounds": [None, [5 * DEG, 25 * DEG], None]}  # goal th2 = 30 deg
    doc = assert_problem(client.post("/v1/plans", json=body), 422, "invalid_request")
    assert doc["field"] == "joint_bounds[1]", doc
    assert "excludes the goal of joint th2" in doc["detail"] and "30.0 deg" in doc["detail"]


def test_a_velocity_limit_too_tight_for_the_duration_names_its_field(client):
    body = {**WORKED, "duration": 1.0, "max_u1": 0.01}
    doc = client.post("/v1/plans", json=body).json()
    # the field is the duration to change; the detail names the limit that binds
    assert doc["status"] == 422 and doc["field"] == "duration", doc
    assert "max_u1" in doc["detail"] and "shortest duration" in doc["detail"], doc
    assert doc["diagnostics"]["binding_limit"] == "max_u1"
    # phi moves about 0.6 rad on this path: at 0.01 rad/s that takes about 60 s at least
    assert doc["diagnostics"]["shortest_duration"] > 50.0


def test_the_library_detects_degrees_and_shape_problems_as_the_api_does(client):
    """One check (optimizer.problem), three front doors: the library (and the CLI, which reads
    the same JSON through PlanRequest.from_dict) says what the API says."""
    import pytest

    from optimizer.errors import InvalidRequestError
    from optimizer.problem import PlanRequest

    cases = [
        ({**WORKED, "start": [10, 10, 10]}, "start"),
        ({**WORKED, "goal": [0.5, 2.0, 0.5]}, "goal[1]"),
        ({**WORKED, "start": [[0.1, 0.2, 0.3]]}, None),  # a nested list: no TypeError
        ({**WORKED, "start": ["0.1", 0.2, 0.3]}, None),
        ({**WORKED, "joint_bounds": [[5, 60], None, None]}, "joint_bounds[0]"),
        ({**WORKED, "joint_bounds": [None, [5 * DEG, 25 * DEG], None]}, "joint_bounds[1]"),
    ]
    for body, field in cases:
        with pytest.raises(InvalidRequestError) as err:
            PlanRequest.from_dict(body)
        api = client.post("/v1/plans", json=body).json()
        assert api["status"] in (400, 422), api
        if field is not None:
            assert err.value.field == field == api["field"], (body, err.value, api)
            assert str(err.value) in api["detail"] or api["detail"] in str(err.value), (
                str(err.value), api["detail"])


def test_a_misspelt_field_gets_did_you_mean(client):
    for body, field, meant in (({**WORKED, "phi_chnage": 0.5}, "phi_chnage", "phi_change"),
                               ({**WORKED, "sample": 21}, "sample", "samples"),
                               ({**WORKED, "robot": {"gain": [1, 1]}}, "robot.gain", "gains")):
        doc = assert_problem(client.post("/v1/plans", json=body), 422, "invalid_request")
        assert doc["field"] == field, doc
        assert f"did you mean '{meant}'?" in doc["detail"], doc
    doc = assert_problem(client.post("/v1/plans", json={**WORKED, "zzzz": 1}), 422,
                         "invalid_request")
    assert "did you mean" not in doc["detail"]


def test_dependencies_and_the_cli_name():
    """pyyaml only for the tests (nothing at run time reads YAML); locust in the bench extra
    (bench/load_test.py uses it); the CLI's --help names the installed command; cvxpy stays a
    runtime dependency."""
    import contextlib
    import io
    import tomllib

    from optimizer.__main__ import main
    from svc_support import ROOT

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    runtime = " ".join(project["dependencies"])
    extras = project["optional-dependencies"]
    assert "pyyaml" not in runtime and any(d.startswith("pyyaml") for d in extras["test"])
    assert "cvxpy" in runtime
    assert any(d.startswith("locust") for d in extras["bench"])
    for tree in ("optimizer", "service"):
        for path in (ROOT / tree).rglob("*.py"):
            assert "import yaml" not in path.read_text(encoding="utf-8"), path
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        main(["--help"])
    assert out.getvalue().startswith("usage: chained-planner")


def test_openapi_examples_of_constraint_times_lie_inside_the_default_duration(client):
    doc = client.get("/openapi.json").json()
    point = doc["components"]["schemas"]["ConstraintPoint"]["properties"]["time"]
    assert point["examples"] and all(0 < t < 1.0 for t in point["examples"]), point


def test_the_explorer_offers_what_the_api_has_and_starts_on_its_defaults(client):
    """The page's method and objective choices come from the planner (registry, objectives),
    the API's defaults selected, so that the page's first plan is the API's default plan."""
    import re

    from optimizer.planner.registry import method_names
    from optimizer.problem import DEFAULT_OBJECTIVE, OBJECTIVES

    page = client.get("/").text

    def options(select: str) -> list[tuple[str, bool]]:
        block = re.search(r'<select id="' + select + r'".*?</select>', page, re.S).group(0)
        return [(v, bool(sel)) for v, sel in
                re.findall(r'<option value="([^"]+)"( selected)?', block)]

    assert [v for v, _ in options("method")] == list(method_names())
    assert [v for v, sel in options("method") if sel] == ["auto"]
    assert [v for v, _ in options("objective")] == list(OBJECTIVES)
    assert [v for v, sel in options("objective") if sel] == [DEFAULT_OBJECTIVE]
    assert "best of polynomial, retimed, penalty" not in page  # the stale label
