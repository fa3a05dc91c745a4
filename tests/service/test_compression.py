"""Large answers are compressed for clients that accept gzip, and the path's columns are named
(issue 28, item 7)."""

from __future__ import annotations

import gzip
import json

import httpx

from svc_support import DEG, WORKED


def test_a_plan_is_gzipped_when_the_client_accepts_it_and_not_otherwise(live_server):
    body = {**WORKED, "phi_change": 34 * DEG, "samples": 201}
    with httpx.Client(base_url=live_server, timeout=60) as client:
        # the fast path (POST /v1/plans answered by the middleware) and the app's routes alike
        for path, payload in (("/v1/plans", body), ("/v1/plans/batch", {"requests": [body]})):
            plain = client.post(path, json=payload, headers={"Accept-Encoding": "identity"})
            assert plain.status_code == 200 and "content-encoding" not in plain.headers
            with client.stream("POST", path, json=payload,
                               headers={"Accept-Encoding": "gzip"}) as r:
                raw = b"".join(r.iter_raw())
            assert r.status_code == 200 and r.headers["content-encoding"] == "gzip"
            assert "Accept-Encoding" in r.headers.get("vary", "")
            # (timing: the only thing two solves may differ in)
            assert _untimed(json.loads(gzip.decompress(raw))) == _untimed(plain.json())
            print(f"\n{path} at 201 samples: {len(plain.content)} bytes, gzip {len(raw)}")
            assert len(raw) < 0.6 * len(plain.content)
        small = client.get("/healthz", headers={"Accept-Encoding": "gzip"})
        assert "content-encoding" not in small.headers  # too small to pay
        # a replan's answer never is (a control loop waits for it: the time to compress it
        # is more than its transfer's)
        plan = client.post("/v1/plans", json={"start": WORKED["start"], "goal": WORKED["goal"]},
                           headers={"Accept-Encoding": "identity"}).json()
        t = plan["path"]["t"][len(plan["path"]["t"]) // 3]
        state = plan["path"]["q"][len(plan["path"]["t"]) // 3]
        with client.stream("POST", "/v1/replans", json={"plan": plan, "time": t,
                                                        "state": state},
                           headers={"Accept-Encoding": "gzip"}) as r:
            raw = b"".join(r.iter_raw())
        assert r.status_code == 200 and "content-encoding" not in r.headers
        assert len(raw) > 5000 and json.loads(raw)["status"] == "success"
        assert "Accept-Encoding" in r.headers.get("vary", "")


def _untimed(doc: object) -> object:
    if isinstance(doc, dict):
        return {k: _untimed(v) for k, v in doc.items() if k != "timing"}
    if isinstance(doc, list):
        return [_untimed(v) for v in doc]
    return doc


def test_the_path_columns_are_named(client):
    plan = client.post("/v1/plans", json={**WORKED, "samples": 11}).json()
    path = plan["path"]
    assert path["q_names"] == ["phi", "th1", "th2", "th3"]
    assert path["u_names"] == ["u1", "u2"]
    assert all(len(row) == len(path["q_names"]) for row in path["q"])
    assert all(len(row) == len(path["u_names"]) for row in path["u"])
    # the named columns are what they say: phi and th1 at the start are the request's
    assert abs(path["q"][0][path["q_names"].index("th1")] - WORKED["start"][0]) < 1e-9
    # an answer with its names is drawn as it is (sent back unchanged)
    r = client.post("/v1/figures/from_plan/joint_angles", params={"format": "svg"}, json=plan)
    assert r.status_code == 200, r.text


def _gzip_app():
    """GZipWhenAccepted around a two-route app: a large JSON answer and a small one."""
    from starlette.applications import Starlette
    from starlette.responses import Response
    from starlette.routing import Route
    from starlette.testclient import TestClient as StarletteClient

    from service.compression import GZipWhenAccepted

    large = json.dumps({"q": [[i * 0.001, i * 0.002] for i in range(600)]}).encode()
    app = Starlette(routes=[
        Route("/large", lambda request: Response(large, media_type="application/json")),
        Route("/small", lambda request: Response(b'{"ok":true}', media_type="application/json")),
    ])
    return StarletteClient(GZipWhenAccepted(app, minimum_size=1400, compresslevel=1)), large


def test_gzip_only_for_clients_that_accept_it_and_vary_on_every_answer():
    client, large = _gzip_app()
    # what GZipMiddleware decides: "gzip" in the first Accept-Encoding header's value
    for accept, compressed in (("gzip", True), ("br, gzip;q=0.5", True), ("identity", False),
                               ("", False), ("deflate", False)):
        with client.stream("GET", "/large", headers={"Accept-Encoding": accept}) as r:
            raw = b"".join(r.iter_raw())
        assert r.status_code == 200
        assert "Accept-Encoding" in r.headers["vary"], accept
        if compressed:
            assert r.headers["content-encoding"] == "gzip", accept
            assert gzip.decompress(raw) == large and len(raw) < len(large) // 2
        else:
            assert "content-encoding" not in r.headers, accept
            assert raw == large and int(r.headers["content-length"]) == len(large)
    small = client.get("/small", headers={"Accept-Encoding": "gzip"})
    assert "content-encoding" not in small.headers and small.content == b'{"ok":true}'


def test_the_paths_kept_uncompressed_are_sent_as_they_are():
    from service.compression import GZipWhenAccepted

    client, large = _gzip_app()
    app = client.app
    assert isinstance(app, GZipWhenAccepted)
    app.uncompressed = frozenset({"/large"})
    with client.stream("GET", "/large", headers={"Accept-Encoding": "gzip"}) as r:
        raw = b"".join(r.iter_raw())
    assert r.status_code == 200 and "content-encoding" not in r.headers and raw == large
    assert "Accept-Encoding" in r.headers["vary"]
