"""Every method runs through the suite of plan requests in tests/data/problems.yaml.

A success is checked independently: the original model (the tests' own rhs) integrated with
scipy under the plan's inputs reaches the goal within 1e-6 rad, and the path, sampled densely
and mapped back through the chained form, stays inside the singularity-free region.
"""

from __future__ import annotations

import pathlib

import numpy as np
import pytest
import yaml

from optimizer.chained_form import chained_form
from optimizer.errors import PlannerError
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest
from optimizer.verify import PlannedInputs

from reference import integrate_model

SUITE = yaml.safe_load((pathlib.Path(__file__).parent / "data" / "problems.yaml").read_text())
CASES = [(p["name"], method, outcome, p["request"])
         for p in SUITE for method, outcome in p["expect"].items()]


def to_request(raw: dict, method: str) -> PlanRequest:
    d = {}
    for k, v in raw.items():
        if k.endswith("_deg"):
            d[k[:-4]] = (tuple(np.deg2rad(v).tolist()) if isinstance(v, list)
                         else float(np.deg2rad(v)))
        else:
            d[k] = v
    d["method"] = method
    d.setdefault("time_limit", 60.0)
    return PlanRequest.from_dict(d)


@pytest.mark.parametrize("name, method, outcome, raw", CASES,
                         ids=[f"{c[0]}-{c[1]}" for c in CASES])
def test_suite(name, method, outcome, raw):
    req = to_request(raw, method)
    if outcome != "success":
        with pytest.raises(PlannerError) as exc:
            plan(req)
        assert exc.value.code == outcome, exc.value.message
        assert exc.value.message
        return
    p = plan(req)
    robot = p.robot
    if p.chained is None:  # actuator-rate plan (shooting, penalty)
        check_actuator_plan(p, req)
        return
    cf = chained_form(robot)
    inputs = PlannedInputs(cf, p.chained)
    sol = integrate_model(lambda t: inputs.u(np.array([t]))[0], req.q_start(), p.duration,
                          robot.gains, robot.exponents)
    assert np.max(np.abs(sol.y[1:, -1] - np.array(req.goal))) < 1e-6
    tau = np.linspace(0, 1, 20001)
    inv = cf.from_chained(p.chained.z(tau))
    assert inv.valid.all()
    th = inv.q[:, 1:robot.n]
    assert np.all((th > 0) & (th < np.pi / 2))
    if req.singularity == "z2":
        assert np.max(p.chained.z(tau)[:, 1]) < 0 or method != "polynomial"
    assert p.verification.terminal_error < 1e-6 and not p.verification.singular
    if method != "auto":
        assert p.method == method


def check_actuator_plan(p, req) -> None:
    """A piecewise-constant-rate plan: scipy, interval by interval (the rates jump at the
    breaks), must reach the goal, and th_1..th_{n-1} must stay in (0, pi/2) on a dense grid."""
    robot = p.robot
    q = req.q_start()
    brk = p.inputs.breaks
    th = []
    for k in range(brk.size - 1):
        uk = p.inputs.rates[k]
        tt = np.linspace(brk[k], brk[k + 1], 51)
        sol = integrate_model(lambda t, uk=uk: uk, q, brk[k + 1] - brk[k], robot.gains,
                              robot.exponents, t_eval=tt - brk[k])
        th.append(sol.y[1:robot.n].T)
        q = sol.y[:, -1]
    assert np.max(np.abs(q[1:] - np.array(req.goal))) < 1e-6
    th = np.concatenate(th)
    assert np.all((th > 0) & (th < np.pi / 2))
    assert p.verification.terminal_error < 1e-6 and not p.verification.singular
    assert p.method == req.method if req.method != "auto" else p.method in ("shooting", "penalty")
