"""Operations: health, readiness, metrics, offline docs, API keys, CORS, JSON logs."""

from __future__ import annotations

import json
import logging
import re

import numpy as np
import pytest

from service.encoding import finite_json
from service.logs import JSONFormatter
from service.settings import Settings
from svc_support import DEG, KEYS, ORIGIN, WORKED, assert_problem


def test_health_and_readiness(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    r = client.get("/readyz")
    assert r.status_code == 200
    body = r.json()
    assert body["status"] == "ready" and body["workers"] == 2 and body["live"] == 2
    assert body["idle"] + body["busy"] == 2


def test_metrics_count_requests_and_solves(client):
    assert client.post("/v1/plans", json={**WORKED, "phi_change": 34 * DEG,
                                           "samples": 5}).status_code == 200
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    text = r.text
    assert re.search(r'planner_http_requests_total\{method="POST",route="/v1/plans",'
                     r'status="200"\} [1-9]', text)
    assert 'planner_http_request_duration_seconds_bucket{le="0.005",method="POST",' \
           'route="/v1/plans",status="200"}' in text
    assert re.search(r'planner_solve_duration_seconds_count\{job="plan",method="polynomial",'
                     r'outcome="success"\} [1-9]', text)
    assert 'planner_workers{state="idle"}' in text
    assert "planner_queue_waiting" in text
    # unknown paths are lumped together, never one series per path
    client.get("/no/such/path/scanner-probe-xyz")
    assert "scanner-probe-xyz" not in client.get("/metrics").text


def test_docs_pages_need_no_internet(client):
    for page, asset in (("/docs", "/static/swagger-ui/swagger-ui-bundle.js"),
                        ("/redoc", "/static/redoc/redoc.standalone.js")):
        r = client.get(page)
        assert r.status_code == 200 and asset in r.text
        assert "http://" not in r.text and "https://" not in r.text, page
    for asset, kind in (("/static/swagger-ui/swagger-ui-bundle.js", "javascript"),
                        ("/static/swagger-ui/swagger-ui.css", "css"),
                        ("/static/redoc/redoc.standalone.js", "javascript"),
                        ("/static/favicon.png", "image/png")):
        r = client.get(asset)
        assert r.status_code == 200 and kind in r.headers["content-type"], asset
        assert len(r.content) > 500
    assert client.get("/openapi.json").json()["info"]["title"]


def test_unknown_route_and_method_are_problems(client):
    assert_problem(client.get("/v1/nothing"), 404, "not_found")
    assert_problem(client.get("/v1/plans"), 405, "method_not_allowed")


def test_api_keys_and_cors(keyed_client):
    c = keyed_client
    body = assert_problem(c.get("/v1/robots/default"), 401, "unauthorized")
    assert "API key" in body["detail"]
    assert_problem(c.get("/v1/robots/default", headers={"X-API-Key": "wrong"}), 401,
                   "unauthorized")
    assert c.get("/v1/robots/default", headers={"X-API-Key": KEYS[1]}).status_code == 200
    assert c.get("/v1/robots/default",
                 headers={"Authorization": f"Bearer {KEYS[0]}"}).status_code == 200
    assert c.get("/healthz").status_code == 200  # operations stay open
    pre = c.options("/v1/plans", headers={"Origin": ORIGIN,
                                          "Access-Control-Request-Method": "POST"})
    assert pre.headers["access-control-allow-origin"] == ORIGIN


def test_settings_from_the_environment(monkeypatch):
    monkeypatch.setenv("PLANNER_WORKERS", "3")
    monkeypatch.setenv("PLANNER_API_KEYS", "a, b")
    monkeypatch.setenv("PLANNER_CORS_ORIGINS", '["http://x.test"]')
    monkeypatch.setenv("PLANNER_MAX_SAMPLES", "501")
    s = Settings()
    assert s.workers == 3 and s.api_keys == ["a", "b"] and s.cors_origins == ["http://x.test"]
    assert s.limits.max_samples == 501
    assert Settings.model_fields["max_body_bytes"].default == 1 << 20


def test_access_log_is_json_with_request_id_and_no_body(client, caplog):
    secret = "body-marker-7f3a"
    with caplog.at_level(logging.INFO, logger="service.access"):
        client.post("/v1/plans", json={**WORKED, "robot": {"gains": [1.0, 1.0],
                                                          "exponents": [2, 3]},
                                        "method": secret},
                    headers={"X-Request-ID": "log-test-1"})
    records = [r for r in caplog.records if getattr(r, "request_id", None) == "log-test-1"]
    assert records, "no access log line for the request"
    line = JSONFormatter().format(records[-1])
    doc = json.loads(line)
    assert doc["request_id"] == "log-test-1" and doc["status"] == 422
    assert doc["route"] == "/v1/plans" and doc["duration_ms"] >= 0
    assert all(secret not in JSONFormatter().format(r) for r in caplog.records)


def test_encoder_never_emits_non_finite_numbers():
    raw = finite_json({"a": float("nan"), "b": [float("inf"), -float("inf"), 1.5],
                       "c": np.float64("nan"), "d": np.array([1.0, np.inf]), "e": np.int64(3)})
    assert json.loads(raw) == {"a": None, "b": [None, None, 1.5], "c": None, "d": [1.0, None],
                               "e": 3}
    assert b"NaN" not in raw and b"Infinity" not in raw


def test_encoder_writes_strided_arrays_and_their_non_finite_numbers():
    """Arrays orjson does not take as they are (not C-contiguous) go through ``_default``."""
    a = np.array([[1.0, np.nan, 2.0], [np.inf, 3.0, -np.inf]])
    raw = finite_json({"col": a[:, 1], "t": a.T, "f32": np.float32(0.5)})
    assert json.loads(raw) == {"col": [None, 3.0], "t": [[1.0, None], [None, 3.0],
                                                          [2.0, None]], "f32": 0.5}
    assert b"NaN" not in raw and b"Infinity" not in raw


@pytest.mark.parametrize("method", ["polynomial", "retimed", "shooting"])
def test_plans_keep_numpy_arrays_and_encode_as_the_plain_dict(method):
    """The worker encodes ``to_dict(plain=False)`` (numpy arrays left in): the same JSON
    document as the plain dict of :func:`optimizer.results.json_safe`, encoded by the standard
    library."""
    from optimizer.planner.plan import plan
    from optimizer.problem import PlanRequest

    p = plan(PlanRequest.from_dict({**WORKED, "method": method, "samples": 21}))
    raw = json.loads(finite_json(p.to_dict(plain=False)))
    plain = json.loads(json.dumps(p.to_dict(), allow_nan=False))
    assert raw == plain


def test_unexpected_library_errors_become_clean_problems():
    """A failure that is not a PlannerError (a library bug) is reported as numerical_failure
    with no traceback or internal detail, by the worker itself."""
    from service.jobs import run_job

    out = run_job("transform", {"direction": "to_chained", "points": [[0.0, 0.1, 0.1, 0.1]],
                                "robot": {"gains": ["a", "b"], "exponents": [2, 3]}})
    assert out["ok"] is False
    assert out["error"]["code"] == "numerical_failure"
    assert "Traceback" not in json.dumps(out) and ".py" not in json.dumps(out)
    out = run_job("plan", {**WORKED, "phi_change": 34 * DEG, "samples": 3})
    assert out["ok"] is True and json.loads(out["body"])["status"] == "success"


def test_unhandled_server_errors_are_never_500_and_spawn_workers_work():
    """Any exception escaping a route becomes a clean problem document; the pool also works
    with the ``spawn`` start method."""
    from service.main import create_app
    from service.settings import default_settings
    from svc_support import TestClient, wait_ready

    app = create_app(default_settings(workers=1, start_method="spawn"))

    async def boom() -> None:
        raise RuntimeError("internal detail /secret/path.py")

    app.add_api_route("/boom", boom)
    with TestClient(app, raise_server_exceptions=False) as c:
        wait_ready(c)
        r = c.get("/boom", headers={"X-Request-ID": "boom-1"})
        body = assert_problem(r, 422, "numerical_failure")
        assert body["request_id"] == "boom-1" and r.headers["x-request-id"] == "boom-1"
        assert "secret" not in r.text
        r = c.post("/v1/plans", json={**WORKED, "phi_change": 34 * DEG, "samples": 5})
        assert r.status_code == 200, r.text
