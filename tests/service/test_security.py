"""Security: optional API keys on every ``/v1`` call (constant-time comparison, checked before the
body is read), open health/metrics/docs/explorer, no stack traces or internal paths in any
answer, CORS off unless configured, and JSON logs with request ids and without bodies or keys."""

from __future__ import annotations

import json
import sys
from typing import Any

import httpx
import pytest

import service.auth
from service.main import create_app
from service.settings import default_settings
from svc_support import (DEG, KEYS, ORIGIN, ROOT, WORKED, TestClient, assert_problem, free_port,
                         server_process)

#: A start inside the region but outside its joint bound: the library refuses it.
OUTSIDE_BOUND = {"start": [0.2, 0.2, 0.2], "joint_bounds": [[0.3, 1.0], None, None]}

CHEAP = {**WORKED, "phi_change": 34 * DEG, "samples": 5}
LEAKS = ("Traceback", "/work/", str(ROOT), ".py\"", ".py'", "site-packages", 'File "',
         "line ", "RuntimeError", "KeyError")


@pytest.fixture
def keyed(keyed_client: TestClient) -> TestClient:
    """API keys and a CORS origin configured (the shared keyed app)."""
    return keyed_client


def _v1_operations() -> list[tuple[str, str]]:
    doc = create_app(default_settings()).openapi()
    return sorted((method.upper(), path) for path, ops in doc["paths"].items()
                  for method in ops if path.startswith("/v1"))


V1 = _v1_operations()


def test_every_v1_operation_is_listed():
    assert ("POST", "/v1/plans") in V1 and ("GET", "/v1/robots/default") in V1
    assert len(V1) >= 7


@pytest.mark.parametrize("method, path", V1 + [("GET", "/v1/no/such/route"), ("PUT", "/v1/plans"),
                                               ("GET", "/v1"), ("DELETE", "/v1/plans/batch")])
@pytest.mark.parametrize("headers", [{}, {"X-API-Key": "wrong"}, {"X-API-Key": KEYS[0][:-1]},
                                     {"X-API-Key": KEYS[0] + "x"},
                                     {"Authorization": f"Basic {KEYS[0]}"},
                                     {"Authorization": "Bearer"}, {"X-API-Key": ""}],
                         ids=["none", "wrong", "prefix", "longer", "basic", "empty-bearer",
                              "empty"])
def test_v1_without_a_valid_key_is_401(keyed, method, path, headers):
    r = keyed.request(method, path, headers=headers, json=CHEAP if method == "POST" else None)
    body = assert_problem(r, 401, "unauthorized")
    assert "API key" in body["detail"]
    assert r.headers["www-authenticate"].startswith("Bearer")
    assert r.headers["x-request-id"] == body["request_id"]


@pytest.mark.parametrize("headers", [{"X-API-Key": KEYS[1]}, {"Authorization": f"Bearer {KEYS[2]}"},
                                     {"authorization": f"bearer {KEYS[0]}"},
                                     {"X-API-Key": f" {KEYS[0]} "}])
def test_a_valid_key_is_accepted(keyed, headers):
    assert keyed.get("/v1/robots/default", headers=headers).status_code == 200
    r = keyed.post("/v1/plans", json=CHEAP, headers=headers)
    assert r.status_code == 200, r.text


def test_unauthenticated_bodies_are_not_read(keyed):
    """A 401 comes before the body limit: a huge body without a key is not even read."""
    r = keyed.post("/v1/plans", content=b"x" * (2 << 20),
                   headers={"content-type": "application/json"})
    assert_problem(r, 401, "unauthorized")


@pytest.mark.parametrize("path", ["/healthz", "/readyz", "/metrics", "/docs", "/redoc",
                                  "/openapi.json", "/static/favicon.png", "/"])
def test_health_metrics_docs_and_explorer_stay_open(keyed, path):
    r = keyed.get(path)
    assert r.status_code == 200, (path, r.text[:200])


def test_keys_are_compared_in_constant_time_against_every_key(monkeypatch):
    calls: list[tuple[bytes, bytes]] = []
    real = service.auth.hmac.compare_digest

    def counting(a: bytes, b: bytes) -> bool:
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(service.auth.hmac, "compare_digest", counting)
    keys = service.auth.encode_keys(KEYS)
    for given, expected in ((KEYS[0], True), (KEYS[2], True), ("nope", False)):
        calls.clear()
        assert service.auth.authorized({"x-api-key": given}, keys) is expected
        assert len(calls) == len(KEYS)  # no early exit on a match


def test_without_keys_everything_is_open(client):
    assert client.get("/v1/robots/default").status_code == 200


# ---------------------------------------------------------------------- no internal details
def _provoked(client: TestClient) -> list[Any]:
    """Answers to requests made to fail in as many ways as possible."""
    json_ct = {"content-type": "application/json"}
    return [
        client.post("/v1/plans", content=b'{"start": [0.1,', headers=json_ct),
        client.post("/v1/plans", content=b"\xff\xfe\x00garbage", headers=json_ct),
        client.post("/v1/plans", content=b"[" * 100_000, headers=json_ct),
        client.post("/v1/plans", content=b"x" * (2 << 20), headers=json_ct),
        client.post("/v1/plans", content=b"start=1", headers={
            "content-type": "application/x-www-form-urlencoded"}),
        client.post("/v1/plans", json={"start": "1", "goal": None, "extra": {"a": [1]}}),
        client.post("/v1/plans", json={**CHEAP, **OUTSIDE_BOUND}),
        client.post("/v1/plans", json={**WORKED, "start": [10 * DEG, 20 * DEG, 30 * DEG],
                                       "goal": [40 * DEG, 25 * DEG, 15 * DEG]}),
        client.post("/v1/plans", json={**CHEAP, "phi_change": 0.0}),
        client.post("/v1/plans", json={**CHEAP, "method": "constraint_points",
                                       "constraint_points": [{"time": 0.5, "state": 9,
                                                              "value": 1.0}]}),
        client.post("/v1/plans/batch", json={"requests": [CHEAP, {**CHEAP, "samples": 0}]}),
        client.post("/v1/transforms", json={"direction": "from_chained",
                                            "points": [[0, 1e6, -1e6, 1e6]],
                                            "robot": {"gains": [1e3, 1e-300],
                                                      "exponents": [12, 12]}}),
        client.post("/v1/sweeps", json={**CHEAP, "phi_change_range": [0.7, 0.5],
                                        "points": 3}),
        client.post("/v1/robustness", json={"plan": CHEAP, "starts": [[0.2, 0.2]]}),
        client.get("/v1/robots/default", params={"n": "1e400"}),
        client.get("/v1/nothing/../../etc/passwd"),
        client.get("/static/../service/main.py"),
        client.get("/static/%2e%2e/main.py"),
        client.request("PATCH", "/v1/plans"),
        client.post("/v1/plans", json=CHEAP, headers={"X-Request-ID": "x" * 500}),
    ]


def test_no_stack_traces_or_internal_paths_in_any_answer(client):
    answers = _provoked(client)
    statuses = [r.status_code for r in answers]
    assert all(s < 500 for s in statuses), statuses
    assert statuses.count(200) <= 2, statuses  # the odd robot's transform and the long id
    for r in answers:
        for leak in LEAKS:
            assert leak not in r.text, (r.request.url, r.status_code, leak, r.text[:300])
        if r.headers.get("content-type", "").startswith("application/problem+json"):
            assert r.json()["request_id"] == r.headers["x-request-id"]
        assert r.headers["x-content-type-options"] == "nosniff"
        assert "server" not in {k.lower() for k in r.headers}


def test_an_unhandled_exception_is_a_clean_problem():
    app = create_app(default_settings(workers=1))

    async def boom() -> None:
        raise KeyError(f"{ROOT}/service/secret.py")

    app.add_api_route("/boom", boom)
    with TestClient(app, raise_server_exceptions=False) as c:
        r = c.get("/boom")
    body = assert_problem(r, 422, "numerical_failure")
    for leak in LEAKS:
        assert leak not in r.text
    assert body["request_id"]


# ---------------------------------------------------------------------- CORS
def test_cors_is_off_unless_configured(client):
    pre = client.options("/v1/plans", headers={"Origin": ORIGIN,
                                               "Access-Control-Request-Method": "POST"})
    assert "access-control-allow-origin" not in pre.headers
    r = client.get("/v1/robots/default", headers={"Origin": ORIGIN})
    assert r.status_code == 200 and "access-control-allow-origin" not in r.headers


def test_cors_when_configured_allows_only_its_origins(keyed):
    pre = keyed.options("/v1/plans", headers={"Origin": ORIGIN,
                                              "Access-Control-Request-Method": "POST",
                                              "Access-Control-Request-Headers": "x-api-key"})
    assert pre.status_code == 200
    assert pre.headers["access-control-allow-origin"] == ORIGIN
    assert "x-api-key" in pre.headers["access-control-allow-headers"].lower()
    # answers, a 401 too, carry the header so that the browser shows them
    r = keyed.get("/v1/robots/default", headers={"Origin": ORIGIN, "X-API-Key": KEYS[0]})
    assert r.headers["access-control-allow-origin"] == ORIGIN
    assert "x-request-id" in r.headers["access-control-expose-headers"].lower()
    r = keyed.get("/v1/robots/default", headers={"Origin": ORIGIN})
    assert r.status_code == 401 and r.headers["access-control-allow-origin"] == ORIGIN
    other = "http://evil.example.test"
    pre = keyed.options("/v1/plans", headers={"Origin": other,
                                              "Access-Control-Request-Method": "POST"})
    assert pre.status_code == 400 and "access-control-allow-origin" not in pre.headers
    r = keyed.get("/v1/robots/default", headers={"Origin": other, "X-API-Key": KEYS[0]})
    assert "access-control-allow-origin" not in r.headers


# ---------------------------------------------------------------------- logs
def test_logs_are_json_lines_with_request_ids_and_no_bodies_or_keys(tmp_path):
    """A live server (``python -m service``): every line it writes is one JSON object; each
    request has an access line with its id; no body content, key or Authorization value."""
    marker = "body-marker-5b9c"
    port = free_port()
    log = tmp_path / "server.log"
    env = {"PLANNER_HOST": "127.0.0.1", "PLANNER_PORT": str(port), "PLANNER_WORKERS": "1",
           "PLANNER_API_KEYS": ",".join(KEYS), "PLANNER_LOG_LEVEL": "debug"}
    sent = []
    with server_process([sys.executable, "-m", "service"], env, port, log) as base:
        with httpx.Client(base_url=base, timeout=60) as h:
            for i, (method, path, kwargs) in enumerate([
                ("POST", "/v1/plans", {"json": {**CHEAP, "method": marker}}),
                ("POST", "/v1/plans", {"json": {**CHEAP, "robot": {"gains": [1.5, 2.5],
                                                                   "exponents": [2, 3]},
                                                "samples": 7}}),
                ("POST", "/v1/plans", {"content": ('{"start": [0.1, "' + marker + '"').encode(),
                                       "headers": {"content-type": "application/json"}}),
                ("POST", "/v1/transforms", {"json": {"direction": "to_chained",
                                                     "points": [[0.123456789, 0.2, 0.2, 0.2]]}}),
                ("GET", "/v1/robots/default", {}),
            ]):
                rid = f"log-{i}"
                auth = {"X-API-Key": KEYS[i % 3]} if i % 2 == 0 else {
                    "Authorization": f"Bearer {KEYS[i % 3]}"}
                headers = {**kwargs.pop("headers", {}), **auth, "X-Request-ID": rid}
                r = h.request(method, path, headers=headers, **kwargs)
                assert r.headers["x-request-id"] == rid
                sent.append((rid, r.status_code))
            r = h.get("/v1/robots/default", headers={"X-Request-ID": "log-noauth"})
            assert r.status_code == 401
            sent.append(("log-noauth", 401))
    text = log.read_text(encoding="utf-8")
    lines = [json.loads(line) for line in text.splitlines() if line.strip()]
    assert len(lines) == len([ln for ln in text.splitlines() if ln.strip()])
    for doc in lines:
        assert {"ts", "level", "logger", "message"} <= set(doc), doc
    access = {doc["request_id"]: doc for doc in lines if doc["logger"] == "service.access"}
    for rid, status in sent:
        assert access[rid]["status"] == status and access[rid]["duration_ms"] >= 0
    for secret in [marker, "0.123456789", "1.5, 2.5", *KEYS, "Bearer"]:
        assert secret not in text, secret
