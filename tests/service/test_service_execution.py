"""The handed-out forms through HTTP: what the answer gives a controller, executed by the
documented rule on the original model (scipy, independently of the planner), reaches the goal."""

from __future__ import annotations

import numpy as np
import pytest

from optimizer.model import Robot
from replay_support import (joint_trajectory_arrays, reachable_goals, replay_linear,
                            replay_quintic, replay_zoh)

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

(START, GOAL), = reachable_goals(3, 1, 19)
BODY = {"start": list(START), "goal": list(GOAL), "method": "retimed", "time_limit": 20.0}
ROBOT = Robot.default(3)
Q0 = np.concatenate([[0.0], START])


def _err(qf):
    return float(np.max(np.abs(np.asarray(qf)[1:] - np.array(GOAL))))


def test_default_path_replays_by_linear_interpolation(client):
    r = client.post("/v1/plans", json=BODY)
    assert r.status_code == 200, r.text
    body = r.json()
    path = body["path"]
    assert path["rule"] == "linear"
    t, u = np.array(path["t"]), np.array(path["u"])
    assert np.all(np.diff(t) > 0.0)   # continuous rates: no time twice (no jump)
    assert np.all(u[0] == 0.0) and np.all(u[-1] == 0.0)   # rest to rest
    qf, margin = replay_linear(ROBOT, t, u, Q0)
    assert _err(qf) < 1e-4 and margin > 0.0
    ex = body["validation"]["executed"]
    assert ex["rule"] == "linear" and ex["terminal_error"] <= 1e-6 and ex["margin"] > 0


def test_controller_period_path_replays_by_zero_order_hold(client):
    r = client.post("/v1/plans", json={**BODY, "controller_period": 0.01})
    assert r.status_code == 200, r.text
    path = r.json()["path"]
    assert path["rule"] == "zoh"
    t, u = np.array(path["t"]), np.array(path["u"])
    assert t.size == 101 and np.allclose(t, 0.01 * np.arange(101), rtol=0, atol=1e-12)
    qf, margin = replay_zoh(ROBOT, t, u, Q0)
    assert _err(qf) < 1e-6 and margin > 0.0


def test_joint_trajectory_replays_by_quintic_hermite(client):
    r = client.post("/v1/plans", json={**BODY, "method": "shooting", "joint_trajectory": True})
    assert r.status_code == 200, r.text
    body = r.json()
    jt = body["joint_trajectory"]
    assert jt["joint_names"] == ["phi", "th1"]
    t, x, v, a = joint_trajectory_arrays(jt)
    qf, margin = replay_quintic(ROBOT, t, x, v, a, Q0)
    assert _err(qf) < 1e-4 and margin > 0.0
    assert body["validation"]["joint_trajectory"]["terminal_error"] <= 1e-6


def test_controller_period_longer_than_half_the_duration_is_refused(client):
    r = client.post("/v1/plans", json={**BODY, "duration": 1.0, "controller_period": 0.6})
    assert r.status_code == 422
    assert r.json()["code"] == "invalid_request"


def test_robustness_replays_the_handed_out_form(client):
    """From the nominal start the u-replay retraces the answer's own path: the held rates on a
    coarse period (the exact inputs part from it by ~2e-2 rad)."""
    plan_body = {**BODY, "controller_period": 0.05}
    plan = client.post("/v1/plans", json=plan_body).json()
    r = client.post("/v1/robustness", json={"plan": plan_body, "starts": [list(START)],
                                            "replay": "u", "include_paths": True})
    assert r.status_code == 200, r.text
    run, = r.json()["runs"]
    assert np.max(np.abs(np.array(run["path_q"]) - np.array(plan["path"]["q"]))) < 1e-8
    assert run["terminal_error"] < 1e-6
