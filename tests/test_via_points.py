"""Joint-space via points: the handed-out path passes through each joint angle at its time.

Checked independently: the original model (the test's own right-hand side, tests/reference.py)
integrated by scipy under the handed-out rates by their rule (linear interpolation between the
samples, or held for a controller period), interval by interval (the rates are smooth there),
then read at the via time, at the end (the goal) and at every sample (the region).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from optimizer.errors import InfeasibleError, InvalidRequestError, PlannerError
from optimizer.planner.plan import plan
from optimizer.planner.via import HELD_VIA_TOLERANCE, VIA_TOLERANCE
from optimizer.problem import PlanRequest
from optimizer.steering import ConstraintPoint
from optimizer.via_points import ViaPoint

from reference import model_rhs

D = math.radians
START, GOAL = [D(10)] * 3, [D(30)] * 3
#: th2 at 35 deg at 0.37 s: the plain plan has th2 near 17 deg then (checked below).
VIA = {"time": 0.37, "joint": "th2", "angle": D(35)}


def _request(**kw):
    return PlanRequest.from_dict({"start": START, "goal": GOAL, **kw})


def _replay(req, p, until):
    """The original model under ``p.path.u`` by its rule, from the start to each time of
    ``until`` (sorted): scipy DOP853 on every interval between samples."""
    t = np.asarray(p.path.t, float)
    u = np.asarray(p.path.u, float)
    held = p.execution.check.rule == "zoh"
    K, m = req.robot.gains, req.robot.exponents
    q = req.q_start()
    out, states = {}, [q.copy()]
    ends = sorted(set(until))
    for i in range(t.size - 1):
        a, b = t[i], t[i + 1]

        def rates(s, i=i, a=a, b=b):
            return u[i] if held else u[i] + (s - a) / (b - a) * (u[i + 1] - u[i])

        inside = [e for e in ends if a < e <= b and e not in out]
        for e in inside:   # read the state at a via time inside this interval
            sol = solve_ivp(lambda s, y: model_rhs(y, rates(s), K, m), (a, e), q,
                            method="DOP853", rtol=1e-12, atol=1e-13)
            out[e] = sol.y[:, -1]
        sol = solve_ivp(lambda s, y: model_rhs(y, rates(s), K, m), (a, b), q,
                        method="DOP853", rtol=1e-12, atol=1e-13)
        assert sol.success
        q = sol.y[:, -1]
        states.append(q.copy())
    return out, np.array(states)


def _check(req, p):
    """Via angles, goal and region on the independent replay; returns the via errors."""
    at, states = _replay(req, p, [v.time for v in req.via_points])
    tol = HELD_VIA_TOLERANCE if req.controller_period is not None else VIA_TOLERANCE
    errors = []
    for v in req.via_points:
        err = abs(at[v.time][1 + v.index] - v.angle)
        errors.append(err)
        assert err <= tol, (v, err)
    assert np.max(np.abs(states[-1, 1:] - np.array(req.goal))) <= 1e-6
    n = req.n
    assert np.all(states[:, 1:n] > 0.0) and np.all(states[:, 1:n] < math.pi / 2)
    # and the answer reports the same points
    reported = p.diagnostics["via_points"]
    assert [(d["time"], d["joint"], d["angle"]) for d in reported] == \
        [(v.time, v.joint, v.angle) for v in req.via_points]
    assert all(d["error"] <= tol for d in reported)
    return errors


@pytest.mark.parametrize("method", ["shooting", "penalty", "auto"])
def test_the_handed_out_path_passes_the_via_angle_at_the_via_time(method):
    req = _request(method=method, via_points=[VIA])
    p = plan(req)
    assert p.method in ("shooting", "penalty")
    _check(req, p)
    # the via point changed the path: without it th2 is far from 35 deg at 0.37 s
    plain = plan(_request(method=method))
    at, _ = _replay(req, plain, [VIA["time"]])
    assert abs(at[VIA["time"]][2] - VIA["angle"]) > 0.1


def test_several_joints_and_times():
    vias = [{"time": 0.2, "joint": "th1", "angle": D(25)},
            {"time": 0.2, "joint": "th3", "angle": D(5)},
            {"time": 0.7, "joint": "th2", "angle": D(45)}]
    req = _request(via_points=vias)
    _check(req, plan(req))


def test_four_joints_via_on_the_last_joint():
    req = PlanRequest.from_dict({"start": [D(20), D(40), D(30), D(10)],
                                 "goal": [D(40), D(20), D(50), D(60)], "robot": {},
                                 "via_points": [{"time": 0.5, "joint": "th4", "angle": D(80)}]})
    _check(req, plan(req))


def test_a_via_point_with_limits_and_a_duration_keeps_the_limits():
    req = _request(duration=3.0, max_u1=2.0, max_u2=2.0, max_du1=20.0, max_du2=20.0,
                   via_points=[{"time": 1.1, "joint": "th2", "angle": D(20)}])
    p = plan(req)
    assert p.duration == pytest.approx(3.0)
    _check(req, p)
    u = np.asarray(p.path.u)
    assert np.all(np.abs(u) <= np.array([2.0, 2.0]) * (1 + 1e-2))


def test_a_held_form_passes_the_via_within_its_tolerance():
    req = _request(controller_period=0.01, via_points=[VIA])
    p = plan(req)
    assert p.execution.check.rule == "zoh"
    _check(req, p)


def test_auto_runs_only_methods_that_honour_via_points():
    # under tp_then_da auto would run the paper's family first
    req = _request(objective="tp_then_da", via_points=[VIA])
    p = plan(req)
    tried = {t["method"] for t in p.diagnostics["auto"]["tried"]}
    assert tried <= {"shooting", "penalty"} and tried
    without = plan(_request(objective="tp_then_da"))
    assert without.method in ("polynomial", "retimed")  # (so the restriction is what acts)


@pytest.mark.parametrize("method", ["polynomial", "retimed", "constraint_points"])
def test_the_papers_family_refuses_via_points(method):
    with pytest.raises(InvalidRequestError) as err:
        plan(_request(method=method, via_points=[VIA]))
    assert err.value.field == "via_points"
    msg = err.value.message
    assert "chained-form states" in msg and "'shooting'" in msg and "'penalty'" in msg


def _refused(field, *, contains=(), **kw):
    with pytest.raises(InvalidRequestError) as err:
        _request(**kw)
    assert err.value.field == field, err.value.message
    for text in contains:
        assert text in err.value.message, err.value.message
    return err.value


@pytest.mark.parametrize("time", [0.0, 1.0, 1.5, -0.2])
def test_a_via_time_outside_the_duration_is_refused(time):
    _refused("via_points[0].time", contains=("(0, 1) s",),
             via_points=[{**VIA, "time": time}])


def test_a_via_time_outside_a_given_duration_names_it():
    _refused("via_points[0].time", contains=("(0, 2) s",), duration=2.0,
             via_points=[{**VIA, "time": 2.5}])


@pytest.mark.parametrize("joint, hint", [("th4", "n = 3"), ("th0", "th1"), ("phi", "actuator"),
                                         ("2", "th1")])
def test_a_joint_that_is_not_the_robots_is_refused(joint, hint):
    _refused("via_points[0].joint", contains=("['th1', 'th2', 'th3']", hint),
             via_points=[{**VIA, "joint": joint}])


def test_a_joint_number_instead_of_its_name_is_refused():
    _refused("via_points[0].joint", contains=('"th1"',), via_points=[{**VIA, "joint": 2}])


@pytest.mark.parametrize("angle, limit", [(0.0, "(0, 1.5708)"), (D(95), "(0, 1.5708)"),
                                          (-0.1, "(0, 90) deg")])
def test_an_angle_outside_the_region_is_refused(angle, limit):
    _refused("via_points[0].angle", contains=(limit,), via_points=[{**VIA, "angle": angle}])


def test_an_angle_in_degrees_is_recognised():
    e = _refused("via_points[0].angle", contains=("looks like degrees", "0.349066"),
                 via_points=[{**VIA, "angle": 20.0}])
    assert e.diagnostics["range"] == [0.0, math.pi / 2]


def test_an_angle_outside_the_joint_bounds_is_refused():
    _refused("via_points[0].angle", contains=("joint_bounds[1]", "(0.1, 0.55)"),
             joint_bounds=[None, [0.1, 0.55], None], via_points=[VIA])


def test_the_last_joint_is_free_within_two_pi():
    _refused("via_points[0].angle", contains=("[-6.28319, 6.28319]",),
             via_points=[{**VIA, "joint": "th3", "angle": 7.0}])


def test_two_vias_for_one_joint_at_one_time_are_refused():
    e = _refused("via_points[1]", contains=("via_points[0]", "th2", "one angle per joint"),
                 via_points=[VIA, {**VIA, "angle": D(40)}])
    assert e.diagnostics["duplicate_of"] == 0
    # two joints at one time are fine
    _request(via_points=[VIA, {**VIA, "joint": "th1"}])


def test_incompatible_options_are_refused():
    _refused("via_points", contains=("constraint_points",), via_points=[VIA],
             constraint_points=[{"time": 0.5, "state": 2, "value": 0.1}])
    _refused("via_points", contains=("max_reversals",), via_points=[VIA], max_reversals=2)
    _refused("via_points", contains=("pareto",), via_points=[VIA], pareto=True)
    # limits without a duration: the via times have no axis yet
    _refused("duration", contains=("give a duration",), via_points=[VIA], max_u1=1.0)


def test_too_many_via_times_are_refused():
    vias = [{"time": 0.1 * (i + 1), "joint": "th2", "angle": D(20)} for i in range(9)]
    _refused("via_points", contains=("9 distinct times", "at most 8"), via_points=vias)


@pytest.mark.parametrize("bad, field", [("x", "via_points"), ([1], "via_points[0]"),
                                        ([{"time": 0.5, "joint": "th2"}],
                                         "via_points[0].angle"),
                                        ([{**VIA, "time": float("nan")}],
                                         "via_points[0].time"),
                                        ([{**VIA, "speed": 1}], "via_points[0].speed")])
def test_malformed_via_points_are_refused(bad, field):
    _refused(field, via_points=bad)


def test_the_library_takes_via_point_objects():
    req = PlanRequest(start=tuple(START), goal=tuple(GOAL),
                      via_points=(ViaPoint(0.37, "th2", D(35)),))
    assert req.via_points[0].index == 1
    with pytest.raises(InvalidRequestError):
        PlanRequest(start=tuple(START), goal=tuple(GOAL), via_points=(ViaPoint(0.37, "th2", D(35)),),
                    constraint_points=(ConstraintPoint(0.5, 2, 0.1),))


def test_an_unreachable_via_point_is_named():
    # th1 from 10 to 89 deg within 10 ms: beyond the transcription's rates
    with pytest.raises(PlannerError) as err:
        plan(_request(via_points=[{"time": 0.01, "joint": "th1", "angle": D(89)}],
                      time_limit=20.0))
    assert isinstance(err.value, InfeasibleError)
    assert err.value.field == "via_points" and "via point" in err.value.message


def test_the_cli_takes_via_points(tmp_path, capsys):
    from optimizer.__main__ import main
    path = tmp_path / "req.json"
    path.write_text(json.dumps({"start": START, "goal": GOAL, "via_points": [VIA]}))
    assert main(["plan", str(path)]) == 0
    out = json.loads(capsys.readouterr().out)
    (reported,) = out["diagnostics"]["via_points"]
    assert reported["joint"] == "th2" and reported["error"] <= VIA_TOLERANCE
    # and refuses a bad one as the API does, naming the element
    path.write_text(json.dumps({"start": START, "goal": GOAL, "method": "polynomial",
                                "via_points": [VIA]}))
    assert main(["plan", str(path)]) != 0
    out = json.loads(capsys.readouterr().out)
    assert out["code"] == "invalid_request" and out["field"] == "via_points"
