"""The workers' warm-up prepares the default robot of every joint count the API accepts: a
worker's first request of any of them builds no NLP (each took 0.15-1.2 s at 4 to 8 joints,
paid once per worker and joint count)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = r"""
import json
from service import jobs
from service.schema_fields import MAX_JOINTS, MIN_JOINTS
info = jobs.warm_up()
from optimizer.planner import nlp
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest
from optimizer.reachable import generate
built = []
original = nlp.MultipleShootingNLP.__init__
def counting(self, *args, **kwargs):
    built.append(len(args[0]) + 1)
    original(self, *args, **kwargs)
nlp.MultipleShootingNLP.__init__ = counting
methods = {}
for n in range(MIN_JOINTS, MAX_JOINTS + 1):
    goal = generate(n, 1, seed=5)[0]
    p = plan(PlanRequest.from_dict({"start": list(goal.start), "goal": list(goal.goal)}))
    methods[n] = p.method
print(json.dumps({"info": info, "built": built, "methods": methods,
                  "joints": [MIN_JOINTS, MAX_JOINTS]}))
"""


def test_a_worker_plans_its_first_request_of_any_joint_count_without_building():
    out = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, capture_output=True,
                         text=True, timeout=600, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    lo, hi = got["joints"]
    assert got["info"]["robots"] == list(range(lo, hi + 1))
    assert set(got["methods"].values()) == {"shooting"}
    # every NLP the first plans used was built by the warm-up
    assert got["built"] == []
