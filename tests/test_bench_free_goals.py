"""The free-goals benchmark (``python -m bench.free_goals``): its draws are the documented
ones, and a tiny run of the documented command plans and reports what it planned."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.free_goals import (HIGH_DEG, LOW_DEG, first_requests,  # noqa: E402
                              first_requests_markdown, free_pairs, markdown)


def test_the_pairs_are_uniform_in_the_range_and_repeatable() -> None:
    pairs = free_pairs(4, 50, 7)
    flat = np.degrees(np.concatenate([np.concatenate(p) for p in pairs]))
    assert flat.min() >= LOW_DEG and flat.max() <= HIGH_DEG
    # uniform: the mean of 400 draws within 4 standard errors of the middle
    half = 0.5 * (HIGH_DEG - LOW_DEG)
    assert abs(flat.mean() - (LOW_DEG + half)) < 4 * half / math.sqrt(3 * flat.size)
    again = free_pairs(4, 3, 7)
    assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
               for a, b in zip(pairs[:3], again))
    assert not np.array_equal(free_pairs(4, 1, 8)[0][0], pairs[0][0])


def test_the_table_says_what_was_planned() -> None:
    rows = [{"n": 6, "goals": 3, "planned": 1, "median_s": 9.5, "slowest_planned_s": 1.9,
             "reversals": [19], "others": {"infeasible": 1, "timeout": 1},
             "uniform": {"seconds": 0.27, "answer": "success", "reversals": 6}},
            {"n": 8, "goals": 1, "planned": 0, "median_s": 10.0,
             "slowest_planned_s": math.nan, "reversals": [], "others": {"timeout": 1},
             "uniform": {"seconds": 12.3, "answer": "infeasible"}}]
    text = markdown(rows, 7)
    assert ("| 6 | 1 of 3 | 9.50 s | 1.90 s | 19-19 | 1 infeasible, 1 timeout "
            "| 0.27 s, 6 reversals |") in text
    assert "| 8 | 0 of 1 | 10.00 s | - | - | 1 timeout | infeasible after 12.3 s |" in text


def test_the_documented_command_runs() -> None:
    proc = subprocess.run([sys.executable, "-m", "bench.free_goals", "--counts", "3:2"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    row = next(line for line in proc.stdout.splitlines() if line.startswith("| 3 |"))
    # 3-joint free goals are planned (every one of 10 in the docs' run)
    assert row.startswith("| 3 | 2 of 2 |")
    assert "reversals |" in row


def test_the_first_requests_are_the_documented_moves_inside_the_region() -> None:
    reqs = first_requests(5)
    assert [name for name, _, _ in reqs][0] == "every joint 10 -> 80"
    for name, a, b in reqs:
        assert a.shape == b.shape == (5,)
        assert np.all((a > 0) & (a < math.pi / 2)) and np.all((b > 0) & (b < math.pi / 2))
    _, a, b = reqs[-1]      # alternating: the joints move in opposite directions
    assert np.all(np.sign(np.diff(np.sign(b - a))) != 0)
    _, a, b = reqs[3]       # the last joint alone
    assert np.count_nonzero(b - a) == 1 and b[-1] - a[-1] > 0


def test_the_first_requests_table_says_answer_time_and_legs() -> None:
    rows = [{"n": 5, "request": "every joint 10 -> 80", "seconds": 5.1, "answer": "success",
             "reversals": 16, "legs": 2},
            {"n": 7, "request": "every joint 10 -> 80", "seconds": 10.0, "answer": "timeout"}]
    text = first_requests_markdown(rows)
    assert "| 5 | every joint 10 -> 80 | success | 5.10 | 16 | 2 |" in text
    assert "| 7 | every joint 10 -> 80 | timeout | 10.00 | - | - |" in text


def test_the_first_requests_command_runs() -> None:
    proc = subprocess.run([sys.executable, "-m", "bench.free_goals", "--first-requests",
                           "--counts", "3:1"], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [line for line in proc.stdout.splitlines() if line.startswith("| 3 |")]
    assert len(rows) == len(first_requests(3))
    # every 3-joint first request is planned in one piece
    assert all("| success |" in row and row.endswith("| 1 |") for row in rows)
