"""What a first-time user and an operator meet in the first hour (issue 28, item 6): probes,
metrics labels, the served OpenAPI document, errors that teach."""

from __future__ import annotations

from svc_support import DEG, WORKED, assert_problem, running_app


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


def test_the_served_openapi_requires_a_key_only_when_keys_are_set(client):
    schemes, secured = _key_schemes(client.get("/openapi.json").json())
    assert schemes == {} and secured == []
    with running_app(workers=1, queue_size=2, api_keys=["k1"]) as keyed:
        schemes, secured = _key_schemes(keyed.get("/openapi.json").json())
    assert "APIKeyHeader" in schemes and secured
