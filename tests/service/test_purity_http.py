"""Over HTTP too, the same request gets the same answer whatever the workers served before.

The 2 workers of the shared app both serve the hard request (several times, so each of them
gets it) between two posts of the README's example; the answers are compared whole but for
what measures the run (``timing``, every ``seconds``, ``compiled``) and the request id.
"""

from __future__ import annotations

import pytest

from svc_support import DEG
from test_purity import _strip  # what measures the run, left out of the comparison

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

EXAMPLE = {"start": [10 * DEG] * 3, "goal": [30 * DEG] * 3, "samples": 31, "time_limit": 60}
HARD = {"start": [0.2, 0.2, -6.0], "goal": [0.21, 0.21, 6.0], "samples": 31, "time_limit": 60}


@pytest.mark.slow
def test_the_example_answers_the_same_after_the_hard_request_on_every_worker(client):
    before = client.post("/v1/plans", json=EXAMPLE)
    assert before.status_code == 200, before.text
    for _ in range(4):
        hard = client.post("/v1/plans", json=HARD)
        assert hard.status_code in (200, 422), hard.text
    after = [client.post("/v1/plans", json=EXAMPLE) for _ in range(4)]
    for r in after:
        assert r.status_code == 200, r.text
        assert _strip(r.json()) == _strip(before.json())
