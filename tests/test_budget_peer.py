"""The bench's min-max-deviation peer (``bench/baselines/multiple_shooting.py``, issue 26): it
reaches the goal on the original model (the tests' own right-hand side, scipy) and its largest
node distance from the segment start -> goal is no larger than the minimum-energy peer's."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # ``bench`` is not an installed package
    sys.path.insert(0, str(ROOT))

from reference import model_rhs  # noqa: E402

from bench.baselines.multiple_shooting import MultipleShootingBaseline, default_model  # noqa: E402

START = np.radians([10.0, 20.0, 30.0])
GOAL = np.radians([40.0, 25.0, 15.0])


def segment_distance(th: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    d = b - a
    s = np.clip((th - a) @ d / (d @ d), 0.0, 1.0)
    return float(np.max(np.linalg.norm(th - a - s[:, None] * d, axis=1)))


def final_state(res, gains, exps) -> np.ndarray:
    q = res.q_nodes[0].copy()
    for k in range(res.u.shape[0]):
        uk = res.u[k]
        sol = solve_ivp(lambda _t, x: model_rhs(x, uk, gains, exps),
                        (res.t_grid[k], res.t_grid[k + 1]), q, method="DOP853",
                        rtol=1e-10, atol=1e-12)
        q = sol.y[:, -1]
    return q


def test_min_max_peer_is_straighter_at_the_nodes_and_reaches_the_goal() -> None:
    gains, exps = default_model(3)
    out = {}
    for objective in ("energy", "min_max_deviation"):
        bl = MultipleShootingBaseline(gains, exps, objective=objective)
        res = bl.solve(START, GOAL)
        assert res.success, res.return_status
        assert np.max(np.abs(final_state(res, gains, exps)[1:] - GOAL)) < 1e-6
        out[objective] = segment_distance(res.q_nodes[:, 1:], START, GOAL)
    assert out["min_max_deviation"] < out["energy"] - math.radians(1.0)


def test_unknown_objective_is_refused() -> None:
    gains, exps = default_model(3)
    with pytest.raises(ValueError, match="objective"):
        MultipleShootingBaseline(gains, exps, objective="fastest")
