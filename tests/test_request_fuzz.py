"""Random requests, checked on what they hand out: the library's answers to random reachable
goals under random options, and chains of replans from the answers.

Each case draws a robot (the default, or gains off by up to 40 %), a start inside the region and
a goal reached by the ORIGINAL model under random smooth inputs (scipy, the tests' own
right-hand side), then options: method, objective, limits, duration, samples, a controller
period, the JointTrajectory form, joint bounds around the driven path, via points on it, a fixed
phi change. An answer is a typed error (:class:`~optimizer.errors.PlannerError`, nothing
else) or a plan whose handed-out path, executed by its own rule (linear between samples, or
held on the controller period) from the start, ends on the goal inside the region (scipy's
DOP853, :mod:`replay_support`), within the asked rate limits and joint bounds, through the via
points and with the asked phi change; its JSON has finite numbers only. A replan case continues
an answer from states off its path by up to 1 deg, each time from the previous answer (as a
controller does), and replays every continuation from its measured state.

These found, on first runs: a plan refused because its energy's quadrature estimate was above
the states' target; a budget under ``weighted`` that looked for no fewer reversals than the
objective's plan; ``auto`` losing the field and the hint of a refusal; replans refused when an
earlier replan's answer was sent back; 1e-16 s sample intervals in replans; a jerk-limited
6-joint plan refused for its linear form of 4097 samples; slopes 0.19 % above ``max_du1``;
a JointTrajectory form's quadrature that ran out of panels.

``FUZZ_CASES`` sets the number of plan and replan cases (default 16 and 6; the long run of
this session's notes used 120 to 200 per seed on 3..6 joints, ``FUZZ_JOINTS=3,4,5,6``);
``FUZZ_SEED`` changes the seed; ``FUZZ_HIGH_CASES`` the plan cases on 6 to 8 joints (default 6).
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from optimizer.errors import PlannerError
from optimizer.model import Robot
from optimizer.planner.plan import plan
from optimizer.planner.replan import replan
from optimizer.problem import PlanRequest
from reference import model_rhs
from replay_support import joint_trajectory_arrays, replay_linear, replay_quintic, replay_zoh

HALF_PI = 0.5 * math.pi
DEG = math.pi / 180.0
SEED = int(os.environ.get("FUZZ_SEED", "20261127"))
CASES = int(os.environ.get("FUZZ_CASES", "16"))
REPLAN_CASES = max(1, CASES * 3 // 8)
JOINTS = tuple(int(n) for n in os.environ.get("FUZZ_JOINTS", "3,4").split(","))
#: Plan cases on 6 to 8 joints besides (their own seed): at 8 joints a request with max_u2
#: alone was handed out 0.12 rad off its goal (session 15), which 3 and 4 joints never showed.
HIGH_CASES = int(os.environ.get("FUZZ_HIGH_CASES", "6"))
HIGH_JOINTS = (6, 7, 8)
#: The handed-out path's end against the goal (rad): the answers promise 1e-6 on their own
#: quadrature; scipy's replay of the linear form adds its own error.
REACH = 2e-6


def _goal(rng: np.random.Generator, robot: Robot) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A start and the states of the original model driven from it by random smooth inputs
    (kept when every joint stays 2 deg inside the region): ``(start, times, states)``."""
    n = robot.n
    while True:
        th0 = rng.uniform(8 * DEG, 82 * DEG, size=n)
        c = rng.uniform(-1.0, 1.0, size=(2, 4))
        T = float(rng.uniform(0.5, 1.5))

        def u(t: float, c: np.ndarray = c) -> np.ndarray:
            return np.array([c[0, 0] + c[0, 1] * math.sin(3 * t + c[0, 2]) + c[0, 3] * t,
                             c[1, 0] + c[1, 1] * math.sin(4 * t + c[1, 2]) + c[1, 3] * t])
        sol = solve_ivp(lambda t, q: model_rhs(q, u(t), robot.gains, robot.exponents),
                        (0.0, T), np.concatenate([[0.0], th0]), method="DOP853", rtol=1e-11,
                        atol=1e-12, dense_output=True)
        tt = np.linspace(0.0, T, 401)
        Q = sol.sol(tt)
        if Q[1:].min() > 2 * DEG and Q[1:].max() < HALF_PI - 2 * DEG:
            return th0, tt, Q


def _robot(rng: np.random.Generator, joints: tuple[int, ...] = JOINTS) -> Robot:
    base = Robot.default(int(rng.choice(joints)))
    if rng.random() < 0.5:
        return base
    return Robot(tuple(float(k * rng.uniform(0.7, 1.4)) for k in base.gains), base.exponents)


def _options(rng: np.random.Generator, n: int, tt: np.ndarray, Q: np.ndarray) -> dict:
    th = Q[1:].T
    d: dict = {}
    if rng.random() < 0.25:
        d["method"] = str(rng.choice(["shooting", "penalty", "polynomial", "retimed"]))
    if rng.random() < 0.2:
        d["objective"] = str(rng.choice(["weighted", "tp_then_da", "tp_then_sensitivity"]))
    if rng.random() < 0.3:
        for key, lo, hi in (("max_u1", 0.3, 4.0), ("max_u2", 0.3, 4.0), ("max_du1", 1.0, 20.0),
                            ("max_du2", 1.0, 20.0), ("max_ddu1", 5.0, 100.0)):
            if rng.random() < 0.5:
                d[key] = float(rng.uniform(lo, hi))
    if rng.random() < 0.2:
        d["duration"] = float(rng.uniform(0.5, 8.0))
    if rng.random() < 0.2:
        d["samples"] = int(rng.integers(11, 600))
    if rng.random() < 0.15:
        d["controller_period"] = float(rng.uniform(0.004, 0.04))
    if rng.random() < 0.2:
        d["joint_trajectory"] = True
    if rng.random() < 0.2:
        lo = np.maximum(th.min(0) - rng.uniform(0.5, 10.0, n) * DEG, 0.5 * DEG)
        hi = np.minimum(th.max(0) + rng.uniform(0.5, 10.0, n) * DEG, HALF_PI - 0.5 * DEG)
        d["joint_bounds"] = [[float(a), float(b)] if rng.random() < 0.7 else None
                             for a, b in zip(lo, hi)]
    if rng.random() < 0.12 and "method" not in d:
        k, dur = int(rng.integers(100, 300)), float(rng.uniform(1.0, 4.0))
        d["duration"] = dur
        joints = [j for j in range(n) if rng.random() < 0.6] or [0]
        d["via_points"] = [{"time": dur * tt[k] / tt[-1], "joint": f"th{j + 1}",
                            "angle": float(th[k, j])} for j in joints]
    if rng.random() < 0.1 and "method" not in d:
        d["phi_change"] = float(Q[0, -1] - Q[0, 0])
    return d


def _plan_cases(seed: int = SEED, count: int = CASES, joints: tuple[int, ...] = JOINTS,
                name: str = "plan") -> list[tuple[str, dict]]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        robot = _robot(rng, joints)
        th0, tt, Q = _goal(rng, robot)
        d = {"start": th0.tolist(), "goal": Q[1:, -1].tolist(),
             "robot": {"gains": list(robot.gains), "exponents": list(robot.exponents)},
             **_options(rng, robot.n, tt, Q)}
        out.append((f"{name}{i}", d))
    return out


@pytest.mark.parametrize("case", _plan_cases() + _plan_cases(SEED + 7, HIGH_CASES, HIGH_JOINTS,
                                                             "high"), ids=lambda c: c[0])
def test_a_random_request_is_a_typed_error_or_a_plan_its_path_proves(case) -> None:
    _, d = case
    req = PlanRequest.from_dict(d)
    try:
        p = plan(req)
    except PlannerError:
        return  # (a refusal is a typed answer; its message and field are tested elsewhere)
    out = json.loads(json.dumps(p.to_dict(), allow_nan=False))  # finite numbers only
    robot = Robot(tuple(d["robot"]["gains"]), tuple(d["robot"]["exponents"]))
    t, u, q = (np.array(out["path"][k], float) for k in ("t", "u", "q"))
    q0 = np.concatenate([[req.phi_start], d["start"]])
    rule = out["path"]["rule"]
    end, margin = (replay_linear if rule == "linear" else replay_zoh)(robot, t, u, q0)
    assert float(np.max(np.abs(end[1:] - np.array(d["goal"])))) < REACH, (rule, d)
    assert margin > 0.0
    for j, key in enumerate(("max_u1", "max_u2")):
        if key in d:
            assert float(np.max(np.abs(u[:, j]))) <= d[key] * (1 + 1e-6)
    h = np.diff(t)
    for j, key in enumerate(("max_du1", "max_du2")):
        if key in d and rule == "linear":  # the linear rule's derivative: the chords' slopes
            assert float(np.max(np.abs(np.diff(u[:, j])[h > 0] / h[h > 0]))) <= d[key] * (1 + 1e-6)
    for j, bound in enumerate(d.get("joint_bounds") or []):
        if bound is not None:
            assert bound[0] - 1e-9 <= q[:, j + 1].min() and q[:, j + 1].max() <= bound[1] + 1e-9
    for vp in d.get("via_points", []):
        j = int(vp["joint"][2:])
        assert abs(float(np.interp(vp["time"], t, q[:, j])) - vp["angle"]) < 1e-3
    if "phi_change" in d:
        assert abs(float(end[0]) - req.phi_start - d["phi_change"]) < REACH
    if "duration" in d and "via_points" not in d:
        assert t[-1] - t[0] == pytest.approx(d["duration"], abs=1e-9)
    if d.get("joint_trajectory"):  # the quintic Hermite form a ROS controller interpolates
        tj, xj, vj, aj = joint_trajectory_arrays(out["joint_trajectory"])
        end, margin = replay_quintic(robot, tj, xj, vj, aj, q0)
        assert float(np.max(np.abs(end[1:] - np.array(d["goal"])))) < 1e-5
        assert margin > 0.0


def _replan_cases() -> list[tuple[int, int]]:
    return [(i, SEED + 1000 + i) for i in range(REPLAN_CASES)]


@pytest.mark.parametrize("case", _replan_cases(), ids=lambda c: f"replans{c[0]}")
def test_replans_from_random_states_are_typed_errors_or_continuations_that_reach(case) -> None:
    rng = np.random.default_rng(case[1])
    robot = _robot(rng)
    th0, _, Q = _goal(rng, robot)
    ans = plan(PlanRequest(start=tuple(th0), goal=tuple(Q[1:, -1]), robot=robot)).to_dict()
    goal = Q[1:, -1]
    n = robot.n
    for _ in range(4):
        pt, pq = np.array(ans["path"]["t"]), np.array(ans["path"]["q"])
        t = float(rng.uniform(pt[0], pt[0] + 0.9 * (pt[-1] - pt[0])))
        state = np.array([np.interp(t, pt, pq[:, j]) for j in range(n + 1)])
        state[1:] += float(rng.choice([0.01, 0.1, 1.0])) * DEG * rng.uniform(-1.0, 1.0, n)
        keep = bool(rng.random() < 0.3)
        try:
            cont = replan(ans, t, state.tolist(), keep_reversals=keep, time_limit=20.0)
        except PlannerError:
            continue
        json.dumps(cont, allow_nan=False, default=lambda a: np.asarray(a).tolist())
        ct, cu = np.array(cont["path"]["t"], float), np.array(cont["path"]["u"], float)
        assert ct[0] == t
        gaps = np.diff(ct)
        assert np.all((gaps == 0.0) | (gaps > 1e-9))
        end, margin = replay_linear(robot, ct - t, cu, state)
        assert float(np.max(np.abs(end[1:] - goal))) < REACH
        assert margin > 0.0
        ans = cont  # the next replan continues this answer, as a controller does
