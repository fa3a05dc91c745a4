"""Every form an answer hands out, replayed by scipy as handed out, on requests no other test
makes: reachable goals of a seed no benchmark uses, each asked for with the options a user
combines (limits, a held form, a reversal budget, the trade-off front). Each answer's path
(and each front member's) must end within 1e-6 rad of the goal with every joint inside, keep
its limits, and say of itself what the replay measures (reversals, deviation)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optimizer.errors import PlannerError
from optimizer.indicators import ACTUATOR_DEAD_BAND, count_reversals, segment_distance
from optimizer.model import Robot
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest
from optimizer.reachable import generate
from replay_support import linear_states, replay_linear, replay_zoh

#: The goals of n joints: optimizer.reachable.generate's seed SEED + n (4245, 4246: no
#: benchmark and no other test uses them).
SEED = 4242

LIMITS = {"max_u1": 1.0, "max_u2": 1.0, "max_du1": 5.0, "max_du2": 5.0}

VARIANTS = {
    "default": {},
    "limits": LIMITS,
    "held": {"controller_period": 0.02},
    "budget": {"max_reversals": 3},
    "front": {"pareto": True},
    "front_limits": {"pareto": True, **LIMITS},
}


@pytest.mark.slow
@pytest.mark.parametrize("n", [3, 4])
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_every_handed_out_form_reaches_its_goal_as_it_says(n: int, variant: str) -> None:
    kw = VARIANTS[variant]
    robot = Robot.default(n)
    answered = 0
    for g in generate(n, 2, seed=SEED + n):
        req = PlanRequest(start=g.start, goal=g.goal, robot=robot, time_limit=60.0, **kw)
        try:
            answer = plan(req).to_dict()
        except PlannerError as exc:
            # a refusal names its field (a budget below the fewest found, say); never a crash
            assert exc.code in ("infeasible", "timeout"), exc
            continue
        answered += 1
        members = [answer] + list(answer.get("pareto") or [])
        for m in members:
            path = m["path"]
            t, u = np.asarray(path["t"], float), np.asarray(path["u"], float)
            replay = replay_zoh if path["rule"] == "zoh" else replay_linear
            final, margin = replay(robot, t, u, req.q_start())
            assert np.max(np.abs(final[1:] - np.array(g.goal))) < 1e-6, variant
            assert margin > 0.0
            if "max_u1" in kw:
                assert np.all(np.max(np.abs(u), axis=0) <= 1.0 + 1e-6)
            if path["rule"] == "linear":
                Q = linear_states(robot, t, u, req.q_start())
                ind = m["indicators"]
                assert (count_reversals(Q[:, 0], ACTUATOR_DEAD_BAND),
                        count_reversals(Q[:, 1], ACTUATOR_DEAD_BAND)) == (
                    ind["reversals"]["phi"], ind["reversals"]["th1"])
                dev = segment_distance(Q[:, 1:], np.array(g.start), np.array(g.goal))
                assert dev == pytest.approx(ind["deviation"], abs=math.radians(0.01))
        if "max_reversals" in kw:
            r = answer["indicators"]["reversals"]
            assert r["phi"] + r["th1"] <= kw["max_reversals"]
    assert answered >= 1
