"""``POST /v1/replans`` over HTTP: a continuation of a plan's answer as sent back, its rates
continuing the commanded ones, 422s naming the field, and the same request answered the same."""

from __future__ import annotations

import math

import numpy as np
import pytest

from svc_support import TestClient

PLAN = {"start": [0.3, 0.4, 0.5], "goal": [0.9, 1.0, 0.8]}


@pytest.fixture(scope="module")
def answer(client: TestClient) -> dict:
    r = client.post("/v1/plans", json=PLAN)
    assert r.status_code == 200, r.text
    return r.json()


def _state_at(answer: dict, t: float, bump: float = 0.0) -> list[float]:
    """The plan's handed-out state at sample time ``t``, its joints moved by ``bump`` rad."""
    i = int(np.searchsorted(answer["path"]["t"], t))
    q = np.array(answer["path"]["q"][i], float)
    q[1:] += bump
    return q.tolist()


def test_replan_continues_the_answer_to_the_goal(client: TestClient, answer: dict) -> None:
    t = answer["path"]["t"][int(np.searchsorted(answer["path"]["t"], 0.4))]
    r = client.post("/v1/replans", json={"plan": answer, "time": t,
                                          "state": _state_at(answer, 0.4, math.radians(0.5)),
                                          "rates": [0.9, 0.5]})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["path"]["t"][0] == pytest.approx(t, abs=1e-12)
    assert body["path"]["t"][-1] == pytest.approx(answer["duration"], abs=1e-12)
    assert body["path"]["u"][0] == pytest.approx([0.9, 0.5], abs=1e-12)
    assert np.max(np.abs(np.array(body["validation"]["final"][1:]) - PLAN["goal"])) < 1e-6
    # a replan of the replan: the answer is a plan the service takes back
    t2 = body["path"]["t"][len(body["path"]["t"]) // 3]
    q2 = np.array(body["path"]["q"][len(body["path"]["t"]) // 3]) + [0.0, 1e-3, -1e-3, 1e-3]
    r2 = client.post("/v1/replans", json={"plan": body, "time": t2, "state": q2.tolist()})
    assert r2.status_code == 200, r2.text
    assert r2.json()["validation"]["terminal_error"] < 1e-6


def test_a_plan_with_rate_limits_is_continued_within_them(client: TestClient) -> None:
    """Over HTTP too: the limits travel in the answer's time_law, the continuation's samples
    keep to them (finite differences), and a compact form sent back keeps them as well."""
    lim = {"max_u1": 1.0, "max_u2": 1.0, "max_du1": 5.0, "max_du2": 5.0}
    r = client.post("/v1/plans", json={**PLAN, **lim})
    assert r.status_code == 200, r.text
    plan = r.json()
    assert plan["time_law"]["limits"] == lim
    i = len(plan["path"]["t"]) // 2
    t = plan["path"]["t"][i]
    r = client.post("/v1/replans", json={"plan": plan, "time": t,
                                          "state": _state_at(plan, t, math.radians(0.05))})
    assert r.status_code == 200, r.text
    body = r.json()
    tt, u = np.array(body["path"]["t"]), np.array(body["path"]["u"])
    dt = np.diff(tt)
    ok = dt > 1e-12
    assert np.abs(u).max() <= 1.0 * (1 + 1e-6)
    assert (np.abs(np.diff(u, axis=0))[ok] / dt[ok, None]).max() <= 5.0 * (1 + 1e-6)
    assert body["time_law"]["limits"] == lim
    assert body["diagnostics"]["replan"]["limits"]["within"] is True
    compact = {**{k: plan[k] for k in ("robot", "coefficients", "time_law")},
               "goal": plan["validation"]["final"][1:]}
    r = client.post("/v1/replans", json={"plan": compact, "time": t,
                                          "state": _state_at(plan, t, math.radians(0.05))})
    assert r.status_code == 200, r.text
    assert r.json()["diagnostics"]["replan"]["limits"]["bounds"] == lim


def test_same_request_same_answer(client: TestClient, answer: dict) -> None:
    req = {"plan": answer, "time": 0.5, "state": _state_at(answer, 0.5, 0.004)}
    a, b = (client.post("/v1/replans", json=req).json() for _ in range(2))
    for key in ("coefficients", "path", "time_law"):
        assert a[key] == b[key]


@pytest.mark.parametrize("change, field", [
    ({"state": [0.0, 0.5, 1.7, 0.5]}, "state[2]"),           # th2 outside (0, pi/2)
    ({"time": 5.0}, "time"),                                 # past the end
    ({"plan": {"robot": {"gains": [1.0]}}}, "plan.robot"),   # not one of ours
    ({"plan": "x"}, "plan"),
    ({"state": [0.1, 0.2]}, "state"),
    ({"rates": [1.0, 2.0, 3.0]}, "rates"),
    ({"gains": [1.0, 1.0, 1.0]}, "gains"),                 # three for a 3-joint plan
    ({"gains": [1.0, -0.5]}, "gains"),
])
def test_bad_requests_are_422_naming_the_field(client: TestClient, answer: dict,
                                               change: dict, field: str) -> None:
    req = {"plan": answer, "time": 0.5, "state": _state_at(answer, 0.5)}
    req.update(change)
    r = client.post("/v1/replans", json=req)
    assert r.status_code == 422, r.text
    assert r.json()["field"].startswith(field), r.json()


def test_segments_tampered_are_refused(client: TestClient, answer: dict) -> None:
    bad = dict(answer)
    segs = [dict(s) for s in answer["coefficients"]["segments"]]
    segs[2]["t_start"] += 0.01   # no longer contiguous
    bad["coefficients"] = {"basis": "", "segments": segs}
    r = client.post("/v1/replans", json={"plan": bad, "time": 0.5,
                                         "state": _state_at(answer, 0.5)})
    assert r.status_code == 422
    assert r.json()["field"] == "plan.coefficients.segments"


def test_robustness_closed_loop_side_by_side(client: TestClient) -> None:
    """The closed-loop mode: each start on a plant whose gains are off, open and closed loop;
    the closed loop ends closer (the open loop misses by the start error and the gains)."""
    body = {"plan": PLAN, "random": {"count": 2, "spread": math.radians(1.0), "seed": 3},
            "closed_loop": {"gain_error": 0.01, "period": 0.05, "seed": 1}}
    r = client.post("/v1/robustness", json=body)
    assert r.status_code == 200, r.text
    loop = r.json()["closed_loop"]
    assert loop["summary"]["runs"] == 2
    for run in loop["runs"]:
        assert all(abs(e) <= 0.01 for e in run["gain_errors"])
        assert run["closed"]["terminal_error"] < 0.1 * run["open"]["terminal_error"]
        assert run["closed"]["replans"] >= 19 and run["closed"]["margin"] > 0.0
    fig = client.post("/v1/figures/robustness", json={**body, "random": {
        "count": 1, "spread": math.radians(1.0), "seed": 3}})
    assert fig.status_code == 200 and fig.content[:4] == b"\x89PNG"


def test_identified_gains_over_http(client: TestClient, answer: dict) -> None:
    """A replan on gains as a client estimated them answers on those gains; the closed-loop
    mode that estimates them ends far closer than the one on the plan's model, and reports
    its estimate (within 1e-6 of each run's plant)."""
    K = [k * f for k, f in zip(answer["robot"]["gains"], (1.03, 0.98))]
    r = client.post("/v1/replans", json={"plan": answer, "time": 0.5,
                                         "state": _state_at(answer, 0.5), "gains": K})
    assert r.status_code == 200, r.text
    assert r.json()["robot"]["gains"] == pytest.approx(K, rel=1e-15)
    body = {"plan": PLAN, "random": {"count": 2, "spread": math.radians(0.5), "seed": 3},
            "closed_loop": {"gain_error": 0.05, "period": 0.05, "seed": 1}}
    plain = client.post("/v1/robustness", json=body)
    body["closed_loop"]["identify"] = True
    ident = client.post("/v1/robustness", json=body)
    assert plain.status_code == 200 and ident.status_code == 200, ident.text
    assert ident.json()["closed_loop"]["summary"]["identify"] is True
    for a, b in zip(plain.json()["closed_loop"]["runs"], ident.json()["closed_loop"]["runs"]):
        assert b["closed"]["terminal_error"] < 1e-3 * max(a["closed"]["terminal_error"], 1e-9)
        plant = [k * (1 + e) for k, e in zip(answer["robot"]["gains"], b["gain_errors"])]
        assert b["closed"]["gains_estimated"] == pytest.approx(plant, rel=1e-6)


def test_the_closed_loop_mode_can_keep_the_plans_reversals(client: TestClient) -> None:
    """``closed_loop.keep_reversals`` reaches the library: the summary says so and no closed
    run reverses an actuator more often than the plan."""
    body = {"plan": PLAN, "random": {"count": 2, "spread": math.radians(0.5), "seed": 4},
            "closed_loop": {"gain_error": 0.05, "period": 0.05, "seed": 2, "identify": True,
                            "keep_reversals": True}}
    r = client.post("/v1/robustness", json=body)
    assert r.status_code == 200, r.text
    loop = r.json()["closed_loop"]
    assert loop["summary"]["keep_reversals"] is True
    for run in loop["runs"]:
        assert run["closed"]["reversals"] <= loop["summary"]["plan_reversals"]
    bad = client.post("/v1/robustness", json={**body, "closed_loop": {"keep_reversals": "maybe"}})
    assert bad.status_code == 422 and "keep_reversals" in bad.text


def test_robustness_closed_loop_needs_actuator_rates(client: TestClient) -> None:
    body = {"plan": {**PLAN, "method": "polynomial"}, "random": {"count": 1, "spread": 0.01},
            "closed_loop": {"period": 0.1}}
    r = client.post("/v1/robustness", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["field"] == "closed_loop"


def _replan_apps():
    """Two apps (one worker each), with and without the middleware's fast routes."""
    from service.main import create_app
    from service.middleware import RequestContextMiddleware
    from service.settings import default_settings

    def app(fast: bool) -> TestClient:
        a = create_app(default_settings(workers=1, queue_size=8))
        if not fast:
            for m in a.user_middleware:
                if m.cls is RequestContextMiddleware:
                    m.kwargs["fast_routes"] = []
        return TestClient(a, raise_server_exceptions=False)
    return app(True), app(False)


def _comparable(r) -> tuple[int, str, dict]:
    body = r.json()
    for key in ("request_id", "timing"):     # vary from request to request
        body.pop(key, None)
    return r.status_code, r.headers["content-type"], body


def test_the_fast_replan_route_answers_as_the_fastapi_route(answer: dict, monkeypatch) -> None:
    """A valid replan is answered by the middleware (FastReplanRoute), the same body as the
    FastAPI route's; what it does not take (a schema violation, not JSON) goes on to the
    route; the library's own 422 is the same from both."""
    from svc_support import wait_ready

    from service.routers.replans import FastReplanRoute
    taken: list[bool] = []
    original = FastReplanRoute.__call__

    async def spy(self, *args, **kwargs):
        answered = await original(self, *args, **kwargs)
        taken.append(answered)
        return answered

    monkeypatch.setattr(FastReplanRoute, "__call__", spy)
    t = answer["path"]["t"][int(np.searchsorted(answer["path"]["t"], 0.4))]
    ok = {"plan": answer, "time": t, "state": _state_at(answer, 0.4, math.radians(0.2))}
    outside = {**ok, "state": [0.0, 2.0, 0.5, 0.5]}
    schema = {**ok, "time": "soon"}
    fast, slow = _replan_apps()
    with fast, slow:
        wait_ready(fast)
        wait_ready(slow)
        codes = []
        for kwargs in ({"json": ok}, {"json": outside}, {"json": schema},
                       {"content": b'{"plan": {', "headers": {"content-type": "application/json"}}):
            a, b = fast.post("/v1/replans", **kwargs), slow.post("/v1/replans", **kwargs)
            assert _comparable(a) == _comparable(b)
            codes.append((a.status_code, a.json().get("field")))
    assert taken == [True, True, False, False]
    assert codes[0][0] == 200
    assert codes[1] == (422, "state[1]")
    assert codes[2][0] == 422 and codes[3][0] == 400


def test_a_bounded_plan_sent_back_keeps_its_bounds(client: TestClient) -> None:
    """The answer of a plan with joint_bounds says them, and a replan of that answer as sent
    back keeps them: a measured state outside them is a 422 naming the state's joint."""
    bounds = [[0.25, 0.95], None, None]
    r = client.post("/v1/plans", json={**PLAN, "joint_bounds": bounds})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["joint_bounds"] == bounds
    bad = client.post("/v1/replans", json={"plan": body, "time": 0.5,
                                           "state": [0.0, 0.2, 0.5, 0.5]})
    assert bad.status_code == 422, bad.text
    assert "state[1]" in bad.text and "0.25" in bad.text
    ok = client.post("/v1/replans", json={"plan": body, "time": 0.5,
                                          "state": _state_at(body, 0.5, 0.002)})
    assert ok.status_code == 200, ok.text
    assert ok.json()["joint_bounds"] == bounds


def test_the_worker_gets_only_the_fields_a_replan_reads_and_answers_as_the_library(
        client: TestClient, answer: dict) -> None:
    """An answer sent back is mostly its path's samples, which a replan does not read: the
    request's plan keeps the fields :func:`optimizer.planner.plan_state.read_plan` reads (and
    of the path its times and rates), and the continuation is the library's from the whole
    answer."""
    from optimizer.planner.replan import replan
    from service.routers.replans import _payload
    from service.schemas import ReplanRequest

    t = answer["path"]["t"][10]
    request = {"plan": answer, "time": t, "state": _state_at(answer, t, 1e-3)}
    payload = _payload(ReplanRequest.model_validate(request))
    plan = payload["plan"]
    assert set(plan["path"]) == {"t", "u"}
    assert {"q", "z", "v"} & set(plan["path"]) == set()
    assert "indicators" not in plan and "diagnostics" not in plan
    assert {"robot", "coefficients", "time_law", "validation", "duration"} <= set(plan)
    r = client.post("/v1/replans", json=request)
    assert r.status_code == 200, r.text
    lib = replan(answer, t, request["state"])
    body = r.json()
    for key in ("path", "coefficients", "time_law", "validation"):
        assert json_equal(body[key], lib[key]), key


def json_equal(a: object, b: object) -> bool:
    import json
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def test_the_robustness_figure_runs_the_loop_the_request_asks_for(monkeypatch) -> None:
    """The figure's closed loop is the answer's: ``identify`` and ``keep_reversals`` reach
    the library from the figure job as from the JSON job (the runs recorded by a stand-in)."""
    from service import jobs

    seen: list[dict] = []
    real = jobs.analysis.closed_loop_robustness

    def spy(*args, **kwargs):
        seen.append(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(jobs.analysis, "closed_loop_robustness", spy)
    loop = {"gain_error": 0.05, "period": 0.1, "noise": 0.0, "seed": 1, "identify": True,
            "keep_reversals": True}
    request = {"plan": {**PLAN}, "replay": "u", "starts": [[s + 0.005 for s in PLAN["start"]]],
               "closed_loop": loop}
    image = jobs.job_figure({"figure": "robustness", "format": "png", "request": request})
    assert image[:4] == b"\x89PNG"
    answer = jobs.job_robustness(request)
    assert answer["closed_loop"]["summary"]["keep_reversals"] is True
    assert len(seen) == 2
    assert all(k["identify"] is True and k["keep_reversals"] is True for k in seen)
