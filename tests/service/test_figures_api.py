"""``POST /v1/figures/{kind}`` through HTTP: real plans, sweeps and robustness runs drawn as PNG
and SVG in the workers; failures stay problem documents."""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET

import pytest

from service.routers.figures import negotiate
from svc_support import DEG, WORKED, assert_problem

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SVG_NS = "{http://www.w3.org/2000/svg}"

#: The worked example (start 10 deg, goal 30 deg, polynomial) as each figure's request.
BODIES = {
    "joint_angles": {**WORKED, "samples": 101},
    "chained_state": {**WORKED, "samples": 101},
    "sweep": {**WORKED, "phi_change_range": [30 * DEG, 38 * DEG], "points": 41},
    "robustness": {"plan": {**WORKED, "samples": 101}, "replay": "u",
                   "random": {"count": 4, "spread": 0.5 * DEG, "seed": 3}},
}
#: Axis label (or title) text each SVG must carry.
LABELS = {
    "joint_angles": ["joint angle [deg]", "phi [deg]", "time t [s]"],
    "chained_state": ["z2 [-]", "time t [s]"],
    "sweep": ["deviation d_a [deg]", "reversals t_p [-]", "sensitivity ||J_R(T)||_F [-]",
              "phi change dphi [deg]"],
    "robustness": ["joint angle [deg]", "time t [s]"],
}
INFEASIBLE = {**WORKED, "start": [10 * DEG, 20 * DEG, 30 * DEG],
              "goal": [40 * DEG, 25 * DEG, 15 * DEG]}


def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == PNG_MAGIC
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def svg_texts(data: bytes) -> str:
    root = ET.fromstring(data)
    assert root.tag == SVG_NS + "svg"
    return " ".join("".join(el.itertext()) for el in root.iter(SVG_NS + "text"))


@pytest.mark.parametrize("kind", list(BODIES))
def test_png_and_svg(client, kind):
    png = client.post(f"/v1/figures/{kind}", params={"format": "png"}, json=BODIES[kind])
    assert png.status_code == 200, png.text
    assert png.headers["content-type"] == "image/png"
    assert png.headers["content-disposition"] == f'inline; filename="{kind}.png"'
    width, height = png_size(png.content)
    assert width >= 400 and height >= 200

    svg = client.post(f"/v1/figures/{kind}", params={"format": "svg"}, json=BODIES[kind])
    assert svg.status_code == 200, svg.text
    assert svg.headers["content-type"].startswith("image/svg+xml")
    text = svg_texts(svg.content)
    for label in LABELS[kind]:
        assert label in text, (kind, label)


def test_the_figure_shows_the_plan_it_was_asked_for(client):
    # the joint-angle title carries dphi and d_a of the worked example's plan (34.57, 21.62 deg)
    svg = client.post("/v1/figures/joint_angles", params={"format": "svg"}, json=WORKED)
    text = svg_texts(svg.content)
    assert "polynomial plan" in text and "34.57" in text and "21.62" in text
    # the sweep title lists the exact feasible interval 33.20..35.26 deg
    sweep = client.post("/v1/figures/sweep", params={"format": "svg"}, json=BODIES["sweep"])
    assert "singularity-free dphi: [33.201\u00b0, 35.256\u00b0]" in svg_texts(sweep.content)


def test_accept_header_chooses_the_format(client):
    svg = client.post("/v1/figures/chained_state", json=WORKED,
                      headers={"Accept": "image/svg+xml"})
    assert svg.status_code == 200 and svg.headers["content-type"].startswith("image/svg+xml")
    assert "Accept" in [v.strip() for v in svg.headers["vary"].split(",")]
    png = client.post("/v1/figures/chained_state", json=WORKED)  # default: png
    assert png.headers["content-type"] == "image/png"
    # the query parameter wins over Accept
    q = client.post("/v1/figures/chained_state", params={"format": "png"}, json=WORKED,
                    headers={"Accept": "image/svg+xml"})
    assert q.headers["content-type"] == "image/png"


def test_negotiation_rules():
    assert negotiate("svg", "image/png") == "svg"
    assert negotiate(None, None) == "png"
    assert negotiate(None, "application/json") == "png"
    assert negotiate(None, "image/svg+xml,image/png;q=0.5") == "svg"
    assert negotiate(None, "image/svg+xml;q=0.4, image/*;q=0.8") == "png"
    assert negotiate(None, "*/*, image/svg+xml") == "svg"


def test_infeasible_is_a_problem_document(client):
    r = client.post("/v1/figures/joint_angles", params={"format": "png"}, json=INFEASIBLE)
    body = assert_problem(r, 422, "infeasible")
    assert body["detail"]
    r = client.post("/v1/figures/robustness", json={"plan": INFEASIBLE, "starts": [[0.2] * 3]})
    assert_problem(r, 422, "infeasible")


def test_invalid_requests(client):
    assert_problem(client.post("/v1/figures/joint_angles", params={"format": "gif"},
                               json=WORKED), 422, "invalid_request")
    body = assert_problem(client.post("/v1/figures/sweep", json={**WORKED, "points": 1}),
                          422, "invalid_request")
    assert body["field"] == "points"
    body = assert_problem(client.post("/v1/figures/robustness", json={
        "plan": WORKED, "starts": [[0.2, 0.2]]}), 422, "invalid_request")
    assert body["field"] == "starts[0]"
    body = assert_problem(client.post("/v1/figures/robustness", json={
        "plan": {**WORKED, "samples": 20001}, "random": {"count": 20, "spread": 0.01}}),
        422, "invalid_request")
    assert body["field"] == "plan.samples"
    assert_problem(client.post("/v1/figures/pie_chart", json=WORKED), 404, "not_found")


def test_figures_are_documented_in_openapi(client):
    doc = client.get("/openapi.json").json()
    for kind in BODIES:
        op = doc["paths"][f"/v1/figures/{kind}"]["post"]
        assert set(op["responses"]["200"]["content"]) == {"image/png", "image/svg+xml"}
        assert list(op["responses"]["422"]["content"]) == ["application/problem+json"]
        assert [p["name"] for p in op["parameters"]] == ["format"]
    assert doc["paths"]["/v1/figures/sweep"]["post"]["requestBody"]["content"][
        "application/json"]["schema"]["$ref"].endswith("/SweepRequest")


# ------------------------------------------------------------------ figures of answers
@pytest.mark.parametrize("kind", ["joint_angles", "chained_state"])
def test_a_plan_answer_is_drawn_without_planning_again(client, kind):
    plan = client.post("/v1/plans", json=BODIES[kind]).json()
    svg = client.post(f"/v1/figures/from_plan/{kind}", params={"format": "svg"}, json=plan)
    assert svg.status_code == 200, svg.text
    text = svg_texts(svg.content)
    for label in LABELS[kind]:
        assert label in text, (label, text)
    # drawn from the answer sent: its method and dphi are in the title
    assert f"{plan['method']} plan: dphi = {plan['phi_change'] / DEG:.3f}" in text
    png = client.post(f"/v1/figures/from_plan/{kind}", json=plan)
    assert png.status_code == 200 and png_size(png.content)[0] >= 400


def test_a_sweep_answer_is_drawn_with_the_planned_dphi(client):
    sweep = client.post("/v1/sweeps", json=BODIES["sweep"]).json()
    r = client.post("/v1/figures/from_sweep", params={"format": "svg"},
                    json={"sweep": sweep, "planned_phi_change": 34.57 * DEG})
    assert r.status_code == 200, r.text
    text = svg_texts(r.content)
    assert "planned dphi" in text and "34.57" in text
    assert f"{len(sweep['phi_change'])} points" in text


def test_an_answer_that_cannot_be_drawn_is_invalid_request(client):
    plan = client.post("/v1/plans", json=BODIES["joint_angles"]).json()
    cut = {**plan, "path": {**plan["path"], "t": plan["path"]["t"][:3]}}
    body = assert_problem(client.post("/v1/figures/from_plan/joint_angles", json=cut), 422,
                          "invalid_request")
    assert "path.t" in body["detail"]
    body = assert_problem(client.post("/v1/figures/from_plan/sweep", json=plan), 422,
                          "invalid_request")
    assert body["field"] == "kind"
    body = assert_problem(client.post("/v1/figures/from_sweep", json={"sweep": plan}), 422,
                          "invalid_request")
    assert body["field"].startswith("sweep.")
    # the drawing's cost is bounded before a worker is taken
    big = {**plan, "robot": {**plan["robot"], "n": 40}}
    body = assert_problem(client.post("/v1/figures/from_plan/chained_state", json=big), 422,
                          "invalid_request")
    assert body["field"] == "robot.n" and "[3, 8]" in body["detail"]


def test_a_plan_answers_strings_are_bounded_before_a_worker_draws_them(client):
    """The method (drawn in the title) and every other string of an answer sent back have a
    length limit: an 80,000-character method took 6 s of a worker to draw, 100,000 a 504."""
    plan = client.post("/v1/plans", json=BODIES["joint_angles"]).json()
    for field, value in (("method", "m" * 80_000),
                         ("coefficients.basis", "b" * 10_000),
                         ("validation.integrator", "i" * 10_000)):
        doc = {**plan}
        head, _, last = field.rpartition(".")
        if head:
            doc[head] = {**plan[head], last: value}
        else:
            doc[last] = value
        body = assert_problem(client.post("/v1/figures/from_plan/joint_angles", json=doc), 422,
                              "invalid_request")
        assert body["field"] == field and "at most" in body["detail"], body


def _replaced(text: str, key: str, value: str) -> str:
    """The JSON ``text`` with the first number after ``"key":`` (or ``"key": [``) replaced
    by ``value``."""
    import re
    out, n = re.subn(r'("' + key + r'":\s*\[?)(-?[0-9][0-9.eE+-]*)',
                     lambda m: m.group(1) + value, text, count=1)
    assert n == 1, key
    return out


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity", "1e309", '"0.5"'])
def test_answers_sent_back_must_hold_finite_json_numbers(client, value):
    """NaN, Infinity, 1e309 (read as infinite) and numbers as strings are refused with a 422
    naming the field, as the service's own requests refuse them (all were drawn, 200)."""
    import json
    plan_text = client.post("/v1/plans", json=BODIES["joint_angles"]).text
    for key, field in (("duration", "duration"), ("phi_change", "phi_change")):
        r = client.post("/v1/figures/from_plan/joint_angles", content=_replaced(
            plan_text, key, value), headers={"Content-Type": "application/json"})
        body = assert_problem(r, 422, "invalid_request")
        assert body["field"] == field, body
    sweep = client.post("/v1/sweeps", json=BODIES["sweep"]).json()
    text = json.dumps({"sweep": sweep})
    r = client.post("/v1/figures/from_sweep", content=_replaced(text, "phi_change", value),
                    headers={"Content-Type": "application/json"})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "sweep.phi_change[0]", body


def test_figure_titles_fit_inside_the_figure(client, monkeypatch):
    """Every text of the figures of a plan (method, dphi, d_a, t_p, T in the title) lies inside
    the figure: the chained-state title ran past both edges."""
    from service import figures

    plan = client.post("/v1/plans", json={**BODIES["chained_state"], "method": "auto"}).json()
    drawn: list = []
    real = figures._save

    def keep(fig, fmt):
        out = real(fig, fmt)  # (drawn: the layout is done)
        drawn.append(fig)
        return out

    monkeypatch.setattr(figures, "_save", keep)
    for kind in ("joint_angles", "chained_state"):
        figures.render(kind, plan, "png")
        fig = drawn[-1]
        renderer = fig.canvas.get_renderer()
        box = fig.bbox
        for ax in fig.axes:
            title = ax.title
            if not title.get_text():
                continue
            ext = title.get_window_extent(renderer)
            assert box.x0 - 1 <= ext.x0 and ext.x1 <= box.x1 + 1, (kind, title.get_text())


@pytest.mark.parametrize("method", ["auto", "shooting", "penalty", "retimed"])
def test_every_methods_answer_is_drawn_as_sent_back(client, method):
    """The strict check of an answer sent back accepts what the service itself answers, for
    every kind of plan (a shooting plan's basis text is longer than a polynomial's)."""
    body = {key: WORKED[key] for key in ("start", "goal")}
    r = client.post("/v1/plans", json={**body, "method": method, "samples": 41})
    if r.status_code != 200:
        pytest.skip(f"{method} gives no plan here: {r.json()['code']}")
    drawn = client.post("/v1/figures/from_plan/joint_angles", params={"format": "svg"},
                        json=r.json())
    assert drawn.status_code == 200, drawn.text
