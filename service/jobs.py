"""What a worker process runs: thin calls into :mod:`optimizer`, plain dicts in and out.

Each job takes the JSON-shaped payload the router built and returns a JSON-safe dict
(:func:`optimizer.results.json_safe`), so nothing heavy crosses the process boundary. No
mathematics happens here: every number comes from the planning library.

Outcome of :func:`run_job` (``body`` is the result already encoded as JSON with orjson, so that
the server never parses or re-encodes a large result in its event loop; a figure's ``body`` is
the image itself)::

    {"ok": True, "body": b"{...}", "seconds": ...}
    {"ok": False, "error": {"code", "message", "field", "diagnostics"}, "seconds": ...}
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

import numpy as np

from optimizer import analysis
from optimizer.chained_form import chained_form
from optimizer.errors import InvalidRequestError, PlannerError
from optimizer.model import Robot
from optimizer.planner import budget, continuation_map, warm_continuation
from optimizer.planner.context import Deadline
from optimizer.planner.plan import plan
from optimizer.planner.replan import replan
from optimizer.planner.shooting import prepare
from optimizer.problem import PlanRequest
from optimizer.results import json_safe

from .encoding import finite_json
from .robot_spec import robot_from
from .schema_fields import MAX_JOINTS, MIN_JOINTS

log = logging.getLogger("service.worker")

Payload = dict[str, Any]


#: Joint counts whose default robot :func:`warm_up` prepares: every count the API accepts, so
#: that no worker pays a build at its first request of a robot (0.15-1.2 s at 4 to 8 joints).
WARM_JOINTS = range(MIN_JOINTS, MAX_JOINTS + 1)


def warm_up() -> dict[str, Any]:
    """Build, in this process: the chained form (CasADi functions) and the shooting NLPs of
    the default robot of every joint count in :data:`WARM_JOINTS`; the 3-joint robot's
    replan maps and reversal-budget NLP; a first figure (:func:`service.figures.warm_up`).

    Returns
    -------
    dict
        ``robots`` (the joint counts), ``seconds`` spent, whether the 3-joint shooting NLP's
        compiled functions are in use (``shooting_compiled``) and the CPU seconds of the
        figure warm-up (``figures_cpu_seconds``, 0 where a parent process had done it).
    """
    t0 = time.perf_counter()
    first = None
    for n in WARM_JOINTS:
        robot = Robot.default(n)
        cf = chained_form(robot)
        q = np.concatenate([[0.0], np.full(n, 0.5)])
        cf.from_chained(cf.to_chained(q))
        cf.symbolic.forward(q, cf.gains)
        # the shooting NLPs (0.03-0.15 s a robot): not paid by the first request. With
        # compiled functions configured, the 3-joint robot's library is looked up (or built, in
        # the background) now; another robot's at its first request (2 ms when the library is
        # in the cache, as in the image): a fresh cache does not compile six libraries at once
        shooting = prepare(robot.gains, robot.exponents, native=n == MIN_JOINTS)
        first = first or shooting
    assert first is not None
    # the 3-joint robot's fatrop on CasADi's virtual machine (50-90 ms): what answers until its
    # compiled library is found or built, and with compiled functions off (other robots
    # build theirs at their first solve; a worker that finds their libraries never needs one)
    if "fatrop" in first.solver_names:
        first.prepare_solver("fatrop")
    robot = Robot.default(MIN_JOINTS)
    # the replans' continuation maps and kernels (0.5-1 s of CPU): not paid by the first replan
    # (the proof's functions, piece_proof.prepare, about as much again, are built per size at
    # the first replan that needs them: every server start in the tests would pay them)
    continuation_map.prepare(robot.gains, robot.exponents)
    # the warm-started NLP of the replans' middle route (its own fatrop cap: another NLP object,
    # the same compiled functions)
    warm_continuation.prepare(robot.gains, robot.exponents)
    # the reversal budget's NLP and solvers (0.3-0.4 s): not paid by the first
    # max_reversals or pareto request
    budget.prepare(robot.gains, robot.exponents)
    # matplotlib, its fonts and writers (about 0.9 s of CPU): loaded once in the forkserver
    # and shared by every worker forked from it, so that a figure's drawing allowance is spent
    # on drawing, not on a cold worker's import (6 s at load 10-14 on two cores)
    from . import figures

    figure_seconds = figures.warm_up()
    return {"robots": list(WARM_JOINTS), "seconds": time.perf_counter() - t0,
            "shooting_compiled": first.compiled, "figures_cpu_seconds": figure_seconds}


def job_plan(payload: Payload) -> dict[str, Any]:
    """``POST /v1/plans``: payload is the plan-request dict.

    The answer keeps its numpy arrays: :func:`service.encoding.finite_json` writes them (and
    any non-finite number as ``null``) without a conversion to Python lists first.
    """
    return with_column_names(plan(PlanRequest.from_dict(payload)).to_dict(plain=False))


def with_column_names(answer: dict[str, Any]) -> dict[str, Any]:
    """``answer`` (a plan's dict) with its path's columns named: ``path.q_names``
    (``phi, th1..thn``) and ``path.u_names`` (``u1``, ``u2``: the rates of phi and th1)."""
    path = answer.get("path")
    if isinstance(path, dict):
        n = int(answer["robot"]["n"])
        path["q_names"] = ["phi", *(f"th{i}" for i in range(1, n + 1))]
        path["u_names"] = ["u1", "u2"]
    return answer


def job_sweep(payload: Payload) -> dict[str, Any]:
    """``POST /v1/sweeps``: ``request`` (plan-request dict), ``lo``, ``hi``, ``points``,
    ``intervals``."""
    req = PlanRequest.from_dict(payload["request"])
    out = analysis.sweep(req, float(payload["lo"]), float(payload["hi"]), int(payload["points"]),
                         intervals=bool(payload.get("intervals", True)))
    out["robot"] = req.robot.as_dict()
    return out


def job_transform(payload: Payload) -> dict[str, Any]:
    """``POST /v1/transforms``: ``robot`` (or None), ``direction``, ``points`` (rows)."""
    points = payload["points"]
    robot = robot_from(payload.get("robot"), len(points[0]) - 1)
    rows = analysis.transform(robot, payload["direction"], points)
    return {
        "direction": payload["direction"],
        "robot": robot.as_dict(),
        "points": [{"values": p.values, "valid": p.valid, "reason": p.reason} for p in rows],
    }


def job_robustness(payload: Payload) -> dict[str, Any]:
    """``POST /v1/robustness``: plan, then replay it open loop from perturbed starts.

    Payload: ``plan`` (plan-request dict), ``starts`` (rows) or ``random`` (``count``,
    ``spread``, ``seed``), ``replay`` (``u`` or ``v``), ``include_paths``.
    """
    nominal, out = _robustness_runs(payload, bool(payload.get("include_paths")))
    if not payload.get("include_paths"):
        for run in out["runs"]:
            run.pop("path_q", None)
    out["phi_change"] = nominal.phi_change
    out["method"] = nominal.method
    return out


def _robustness_runs(payload: Payload, paths: bool) -> tuple[Any, dict[str, Any]]:
    """The plan of a robustness request and its runs: open loop from every start, and with
    ``closed_loop`` each start on a plant with gains off, open and closed loop (``paths``:
    the closed runs' paths too). Its answer and its figure alike; the plan and the runs share
    the request's time limit."""
    req = PlanRequest.from_dict(payload["plan"])
    deadline = Deadline(req.time_limit)
    nominal = plan(req)
    starts = payload.get("starts")
    if starts is None:
        rnd = payload["random"]
        starts = analysis.perturbed_starts(req.start, int(rnd["count"]), float(rnd["spread"]),
                                           int(rnd["seed"]))
    out = analysis.robustness(nominal, starts, payload["replay"], req.goal, deadline=deadline)
    loop = payload.get("closed_loop")
    if loop is not None:
        out["closed_loop"] = analysis.closed_loop_robustness(
            nominal, np.asarray(starts, float), float(loop["gain_error"]),
            float(loop["period"]), float(loop["noise"]), int(loop["seed"]), paths=paths,
            deadline=deadline, identify=bool(loop.get("identify", False)),
            keep_reversals=bool(loop.get("keep_reversals", False)))
    return nominal, out


def job_replan(payload: Payload) -> dict[str, Any]:
    """``POST /v1/replans``: ``plan`` (an answer or its compact form), ``time``, ``state``,
    ``rates`` and ``duration`` (optional)."""
    return replan(payload["plan"], payload["time"], payload["state"], payload.get("rates"),
                  payload.get("duration"), plain=False,
                  time_limit=float(payload.get("time_limit", 10.0)),
                  keep_reversals=bool(payload.get("keep_reversals", False)),
                  gains=payload.get("gains"), fallback=bool(payload.get("fallback", True)))


JOBS: dict[str, Callable[[Payload], Any]] = {
    "plan": job_plan,
    "replan": job_replan,
    "sweep": job_sweep,
    "transform": job_transform,
    "robustness": job_robustness,
}


def run_job(kind: str, payload: Payload, request_id: str | None = None) -> dict[str, Any]:
    """Run one job and report its outcome as a plain dict (never raises).

    ``request_id`` (the HTTP request's) is put on the log line of an unexpected failure, so
    that it can be found from the client's answer.

    A :class:`optimizer.errors.PlannerError` becomes its ``code``/``message``/``field``/
    ``diagnostics``; any other exception (a library bug, a missing module) is logged here with
    its traceback and reported as ``numerical_failure`` without internal details.
    """
    t0 = time.perf_counter()
    try:
        result = JOBS[kind](payload)
        body = result if isinstance(result, bytes) else finite_json(result)
        return {"ok": True, "body": body, "seconds": time.perf_counter() - t0}
    except PlannerError as exc:
        return {"ok": False, "seconds": time.perf_counter() - t0, "error": {
            "code": exc.code, "message": exc.message, "field": exc.field,
            "diagnostics": json_safe(exc.diagnostics)}}
    except Exception as exc:  # noqa: BLE001 - the worker must answer whatever happens
        log.exception("job %s failed unexpectedly", kind, extra={"request_id": request_id})
        return {"ok": False, "seconds": time.perf_counter() - t0, "error": {
            "code": "numerical_failure",
            "message": "the solver failed unexpectedly; the failure was logged",
            "field": None, "diagnostics": {"exception": type(exc).__name__}}}


# ---------------------------------------------------------------------- figures
def job_figure(payload: Payload) -> bytes:
    """``POST /v1/figures/{kind}``: compute the data exactly as the JSON routes do, then draw it.

    Payload: ``figure`` (a kind of :data:`service.figures.KINDS`), ``format`` (``png`` or
    ``svg``) and ``request``: the payload of the ``plan`` job (``joint_angles``,
    ``chained_state``), of the ``sweep`` job (``sweep``) or of the ``robustness`` job
    (``robustness``; the runs' paths are always computed, they are what the figure draws).

    matplotlib is loaded and warmed up before the workers start (:func:`warm_up`, in the
    forkserver), so the drawing allowance is spent on drawing.

    Returns
    -------
    bytes
        The image (PNG or SVG as asked), which :func:`run_job` passes on as the body unchanged.
    """
    from . import figures as _figures
    kind, fmt, inner = payload["figure"], payload["format"], payload["request"]
    data: dict[str, Any]
    if kind in ("joint_angles", "chained_state", "pareto"):
        data = json_safe(job_plan(inner))  # the plain JSON shape the figures are drawn from
        if inner.get("constraint_points"):
            data = {"plan": data, "constraint_points": inner["constraint_points"]}
    elif kind == "sweep":
        data = json_safe(job_sweep(inner))
    elif kind == "robustness":
        nominal, runs = _robustness_runs(inner, True)
        data = {"plan": with_column_names(nominal.to_dict()), "robustness": json_safe(runs)}
    else:
        raise ValueError(f"unknown figure kind {kind!r}")
    image, _media_type = _figures.render(kind, data, fmt)
    return image


JOBS["figure"] = job_figure


def job_figure_of_answer(payload: Payload) -> bytes:
    """``POST /v1/figures/from_plan/*``, ``/v1/figures/from_sweep``: draw an answer the client
    already has (``data``: a plan or sweep answer), without computing it again.

    The data come from the client: what cannot be drawn is the client's error
    (``invalid_request``), not the solver's.
    """
    from . import figures as _figures
    try:
        image, _media_type = _figures.render(payload["figure"], payload["data"],
                                             payload["format"])
    except (ValueError, TypeError, KeyError, IndexError, OverflowError) as exc:
        raise InvalidRequestError(f"the answer cannot be drawn: {exc}") from None
    return image


JOBS["figure_of_answer"] = job_figure_of_answer
