"""The elastic goal of the 6- to 8-joint NLPs (optimizer.planner.nlp.TERMINAL_MODES).

With the goal as equality rows, the KKT systems of these NLPs are singular wherever the end
map loses rank in a bracket direction, and the solvers stopped ("error in step computation")
on most generated 7- and 8-joint goals. These tests plan goals the benchmark never uses and
check the answers against scipy, independently of the planner's own quadrature.
"""

from __future__ import annotations

import numpy as np
import pytest

from optimizer.model import Robot
from optimizer.planner import nlp as nlp_layer
from optimizer.planner.context import Deadline
from optimizer.planner.plan import plan
from optimizer.planner.shooting import solve_shooting
from optimizer.planner.solvers import ELASTIC_ACCEPT
from optimizer.problem import PlanRequest
from optimizer.reachable import generate

from test_shooting import scipy_path

#: A seed the benchmark's goals do not use.
SEED = 4242


def test_the_terminal_mode_is_elastic_from_five_joints():
    assert nlp_layer.default_terminal(4) == "hard"
    for n in (5, 6, 7, 8):
        assert nlp_layer.default_terminal(n) == "elastic"


@pytest.mark.parametrize("n, index", [(7, 0), (7, 1), (8, 0), (8, 1)])
def test_many_joint_goals_are_planned_and_reached_on_the_original_model(n, index):
    g = generate(n, index + 1, seed=SEED)[index]
    req = PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(n), time_limit=120.0)
    p = plan(req)
    _, q = scipy_path(p, req, per_interval=11)
    assert np.max(np.abs(q[-1, 1:] - np.array(g.goal))) < 1e-6
    assert np.all((q[:, 1:n] > 0.0) & (q[:, 1:n] < np.pi / 2))


def test_the_elastic_nlp_ends_on_its_goal_and_its_miss_is_measured():
    """The NLP's own end (its RK4 nodes) is within the acceptance of the goal, and
    ``goal_miss`` reads that distance from the solution vector."""
    g = generate(7, 3, seed=SEED)[2]
    req = PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(7), time_limit=120.0)
    sol = solve_shooting(req, Deadline(120.0))
    miss = float(np.max(np.abs(sol.nodes[-1, 1:] - np.array(g.goal))))
    assert miss <= ELASTIC_ACCEPT
    tr = nlp_layer.ladder(7)[0]
    nlp = nlp_layer.nlp_for(req, tr)
    assert nlp.terminal == "elastic"
    p = nlp_layer.parameters(req, 1.0, 1.0, 1.0)
    W = np.zeros((nlp.N + 1, nlp.stride))
    W[:, :8] = sol.nodes
    assert nlp.goal_miss(nlp.flat(W), p) == pytest.approx(miss, abs=1e-15)
    # a heavier penalty: the objective's weights (and nothing else) divided
    tight = nlp.tightened(p, 100.0)
    assert np.allclose(tight[15:18], p[15:18] / 100.0)
    assert np.array_equal(np.delete(tight, [15, 16, 17]), np.delete(p, [15, 16, 17]))
