"""The proof of an actuator plan by the cascade quadrature, with its error estimate taken into
the decisions (``finish.PROOF_ACCEPT``), on a long path of large rates: a 7-joint plan made in
three legs (tests/data/legs_composite_7_joints.json), whose quadrature estimate stops at a
floor above the quadrature's own default acceptance. Checked against scipy's DOP853 run
piece by piece at rtol 1e-13 (each piece's rates are constant)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from optimizer.errors import NumericalError
from optimizer.model import Robot
from optimizer.planner import finish
from optimizer.planner.finish import PROOF_ACCEPT, actuator_schedule, finish_actuator_plan
from optimizer.planner.rules import TERMINAL_TOLERANCE
from optimizer.problem import PlanRequest
from optimizer.verify import CASCADE_NAME
from replay_support import replay_linear

DATA = Path(__file__).parent / "data" / "legs_composite_7_joints.json"


def _case() -> tuple[PlanRequest, np.ndarray]:
    data = json.loads(DATA.read_text())
    n = int(data["joints"])
    req = PlanRequest(start=tuple(np.radians([data["start_deg"]] * n)),
                      goal=tuple(np.radians([data["goal_deg"]] * n)),
                      robot=Robot.default(n), phi_start=float(data["phi_start"]))
    return req, np.array(data["rates"], float)


def _reference(req: PlanRequest, rates: np.ndarray) -> np.ndarray:
    """States at the schedule's breaks: DOP853 piece by piece on the original model."""
    sched = actuator_schedule(req, rates)
    K = np.array(req.robot.gains)
    m = np.array(req.robot.exponents, float)
    q = req.q_start()
    out = [q]
    for k, u in enumerate(sched.rates):
        def f(t, y, u=u):
            return np.concatenate([[u[0], u[1]], K * np.cos(y[1:-1]) ** m * u[0]])
        sol = solve_ivp(f, (sched.breaks[k], sched.breaks[k + 1]), q, method="DOP853",
                        rtol=1e-13, atol=1e-14)
        q = sol.y[:, -1]
        out.append(q)
    return np.array(out)


def test_a_long_path_of_large_rates_is_proved_by_its_quadrature():
    req, rates = _case()
    ref = _reference(req, rates)
    assert np.max(np.abs(ref[-1, 1:] - np.array(req.goal))) < 1e-9   # the case reaches its goal
    p = finish_actuator_plan(req, rates, "shooting", ref, {}, {})
    ver = p.verification
    assert ver.integrator == CASCADE_NAME
    assert ver.error_estimate is not None and ver.error_estimate <= PROOF_ACCEPT
    # the quadrature's end is scipy's at rtol 1e-13 (DOP853 at the verification's tolerances,
    # the fallback before, ended 2.4e-7 rad off)
    assert np.max(np.abs(np.array(ver.final) - ref[-1])) < 1e-10
    assert ver.terminal_error + ver.error_estimate <= TERMINAL_TOLERANCE
    # the handed-out linear form, replayed independently, reaches the goal inside the region
    final, margin = replay_linear(req.robot, np.asarray(p.path.t, float),
                                  np.asarray(p.path.u, float), req.q_start())
    assert np.max(np.abs(final[1:] - np.array(req.goal))) < 1e-6
    assert margin > 0.0
    assert p.margin == pytest.approx(
        float(np.min(np.minimum(ref[:, 1:], 0.5 * math.pi - ref[:, 1:]))), abs=1e-9)


def test_the_quadratures_estimate_counts_against_the_terminal_error(monkeypatch):
    """An estimate as large as the whole tolerance leaves no room for the terminal error: the
    plan is refused, with the estimate named."""
    req, rates = _case()

    original = finish.integrate_cascade
    monkeypatch.setattr(finish, "integrate_cascade",
                        lambda *a, **k: dataclasses.replace(original(*a, **k),
                                                            error_estimate=TERMINAL_TOLERANCE))
    with pytest.raises(NumericalError, match="estimate"):
        finish_actuator_plan(req, rates, "shooting", _reference(req, rates), {}, {})


def test_a_margin_inside_the_quadratures_estimate_is_not_proved(monkeypatch):
    """A path whose smallest distance from the region's boundary is within the quadrature's
    estimate is not proved to stay inside: refused, the estimate named."""
    from optimizer.errors import InfeasibleError

    req, rates = _case()
    ref = _reference(req, rates)
    margin = float(np.min(np.minimum(ref[:, 1:], 0.5 * math.pi - ref[:, 1:])))
    original = finish.integrate_cascade
    monkeypatch.setattr(finish, "integrate_cascade",
                        lambda *a, **k: dataclasses.replace(original(*a, **k),
                                                            error_estimate=2.0 * margin))
    with pytest.raises(InfeasibleError, match="error estimate"):
        finish_actuator_plan(req, rates, "shooting", ref, {}, {})
