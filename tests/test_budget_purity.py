"""The reversal budget's cached NLPs remember nothing between requests (issues 24 and 26).

The budget's NLP and its solvers (fatrop with the budget's settings, IPOPT) are built once per
robot and transcription and kept (:func:`optimizer.planner.budget.prepare`); the merges start
fatrop from the previous candidate's nodes. A request's answer must still be a function of the
request alone: the same ``pareto`` or ``max_reversals`` request gets the same answer whatever
ran before it, in this process or in a fresh one. Answers are compared whole, except what
measures the run (``timing``, ``seconds``, ``compiled``, and the solvers' CPU time that
``diagnostics.budget.tried`` records).

Also here: the cut that drops NLP answers which cannot be front members, checked against
an objective plan made straighter than any path (every answer is then dominated).
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from optimizer.errors import PlannerError
from optimizer.planner import budget
from optimizer.planner.context import Deadline, PlanContext
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest

ROOT = Path(__file__).resolve().parents[1]
RUN_KEYS = {"timing", "seconds", "compiled", "request_id", "nlp_cpu_seconds",
            "finish_cpu_seconds"}
DEG = math.pi / 180.0

#: Two fronts and two budgets on 3-joint goals (joints moving both ways, and all one way).
REQUESTS: list[dict[str, Any]] = [
    {"start": [10 * DEG, 20 * DEG, 30 * DEG], "goal": [40 * DEG, 25 * DEG, 15 * DEG],
     "pareto": True},
    {"start": [50 * DEG, 20 * DEG, 30 * DEG], "goal": [30 * DEG, 40 * DEG, 50 * DEG],
     "max_reversals": 2},
    {"start": [50 * DEG, 20 * DEG, 30 * DEG], "goal": [30 * DEG, 40 * DEG, 50 * DEG],
     "pareto": True},
    {"start": [10 * DEG, 20 * DEG, 30 * DEG], "goal": [40 * DEG, 25 * DEG, 15 * DEG],
     "max_reversals": 5},
]


def _request(spec: dict[str, Any]) -> PlanRequest:
    # a time limit no search reaches: a search cut by the clock may depend on the machine
    return PlanRequest(samples=31, time_limit=120.0, **spec)


def _strip(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in RUN_KEYS}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _answer(spec: dict[str, Any]) -> Any:
    try:
        p = plan(_request(spec))
    except PlannerError as exc:  # a structured failure is an answer too
        return {"error": type(exc).__name__, "message": str(exc)}
    return _strip({**p.to_dict(), "budget": p.diagnostics.get("budget")})


def _canonical(answers: list[Any]) -> str:
    return json.dumps(answers, sort_keys=True, allow_nan=True, default=float)


@pytest.mark.slow
def test_budget_answers_do_not_depend_on_what_ran_before() -> None:
    order = list(range(len(REQUESTS)))
    forward = [_answer(REQUESTS[i]) for i in order]
    backward = [_answer(REQUESTS[i]) for i in order[::-1]][::-1]
    assert _canonical(backward) == _canonical(forward)
    # the answers are fronts and plans (not errors, which would trivially agree), and the
    # sign-held NLPs ran on the cached fatrop solver (the one that starts from other nodes)
    assert all("error" not in a for a in forward)
    assert len(forward[0]["pareto"]) >= 2 and len(forward[2]["pareto"]) >= 2
    statuses = [t.get("status", "") for a in forward for t in a["budget"]["tried"]]
    assert any(s.startswith("fatrop") for s in statuses)
    # the last request alone in a fresh process: nothing ran before it there
    code = ("import json, sys\n"
            "import test_budget_purity as t\n"
            "print(json.dumps(t._answer(t.REQUESTS[int(sys.argv[1])]), allow_nan=True, "
            "default=float))\n")
    i = len(REQUESTS) - 1
    out = subprocess.run([sys.executable, "-c", code, str(i)], cwd=ROOT,
                         env={"PYTHONPATH": f"{ROOT}:{ROOT / 'tests'}", "PATH": "/usr/bin:/bin",
                              "OPENBLAS_NUM_THREADS": "1"},
                         capture_output=True, text=True, timeout=900, check=True)
    fresh = json.loads(out.stdout.strip().splitlines()[-1])
    assert _canonical([fresh]) == _canonical([forward[i]])


def test_node_deviation_is_the_distance_from_the_segment() -> None:
    a, b = np.array([0.1, 0.2, 0.3]), np.array([0.5, 0.2, 0.6])
    req = _request({"start": a.tolist(), "goal": b.tolist()})
    rng = np.random.default_rng(7)
    th = a + rng.uniform(-0.3, 1.3, (40, 1)) * (b - a) + rng.normal(0.0, 0.05, (40, 3))
    nodes = np.column_stack([np.zeros(40), th])
    # brute force: the nearest of 200001 points of the segment
    seg = a + np.linspace(0.0, 1.0, 200001)[:, None] * (b - a)
    brute = max(float(np.min(np.linalg.norm(seg - q, axis=1))) for q in th)
    assert budget.node_deviation(req, nodes) == pytest.approx(brute, abs=1e-5)


def test_answers_no_straighter_than_the_objective_plan_are_not_finished() -> None:
    req = _request(REQUESTS[0])
    first = plan(_request({k: v for k, v in REQUESTS[0].items() if k != "pareto"}))
    # the objective's plan claimed straighter than any path can be: every NLP answer is
    # dominated by it, so none is finished and no merge is tried
    ideal = dataclasses.replace(first, indicators=dataclasses.replace(first.indicators,
                                                                      deviation=0.0))
    front = budget.build_front(req, PlanContext(Deadline(req.time_limit)), ideal)
    assert [c.origin for c in front.candidates] == ["objective"]
    outcomes = [t.get("outcome") for t in front.tried]
    assert outcomes.count(budget.DOMINATED) == 2  # both straightest NLPs
    assert not any(str(t.get("candidate", "")).startswith("merged") for t in front.tried)
    # with the real plan the same request finishes candidates and merges
    real = budget.build_front(req, PlanContext(Deadline(req.time_limit)), first)
    assert len(real.candidates) > 1
    assert any(str(t.get("candidate", "")).startswith("merged") for t in real.tried)
