"""Smoke test of the benchmark (``python -m bench``), so that it cannot rot.

Runs the documented command in its tiny mode (one case, quick, no HTTP, scaling for n = 3 only)
and checks the JSON: its keys, finite re-integration numbers, and a small terminal error of the
baseline re-integrated on the original model. Also checks the re-integration helpers on cases
with known answers.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.reintegrate import (DEAD_BAND, Segment, integrate, line_distance,  # noqa: E402
                               path_metrics)
from optimizer.indicators import count_reversals  # noqa: E402

FINITE_KEYS = ("terminal_error_rad", "d_a_deg", "joint_space_dev_deg", "energy",
               "region_margin_deg")


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("bench") / "smoke.json"
    page = out.with_name("benchmarks.md")
    proc = subprocess.run(
        [sys.executable, "-m", "bench", "--quick", "--cases", "1", "--no-http", "--joints", "3",
         "--out", str(out), "--report", str(page)], cwd=ROOT, capture_output=True, text=True,
        timeout=900)  # a hang guard only: the run's speed is not what this test checks
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "### Targets" in proc.stdout
    data = json.loads(out.read_text())
    data["page"] = page.read_text(encoding="utf-8")
    return data


def test_results_page_holds_this_run_only(results: dict) -> None:
    page = results["page"]
    assert page.startswith("# Benchmarks\n")
    assert "## Results" in page and "### Targets" in page
    assert results["cases"][0]["case"] in page
    assert results["meta"]["timestamp"] in page
    # no history: no commit hashes or issue numbers, one run
    commit = results["meta"]["commit"].split("+")[0]
    assert commit == "unknown" or commit not in page
    assert "issue" not in page.lower()
    assert page.count("Run 20") == 1


def _finite_metrics(r: dict) -> None:
    assert r["ok"], r.get("message")
    for k in FINITE_KEYS:
        assert isinstance(r[k], float) and math.isfinite(r[k]), (k, r[k])
    assert r["reversals_phi"] >= 0 and r["reversals_th1"] >= 0


def test_json_layout(results: dict) -> None:
    assert {"meta", "config", "cases", "baseline_builds", "http", "scaling",
            "targets"} <= set(results)
    assert results["meta"]["quick"] is True
    assert results["http"] == {"available": False, "reason": "disabled (--no-http)"}
    assert len(results["cases"]) == 1
    case = results["cases"][0]
    assert {"case", "kind", "n", "start_deg", "goal_deg", "baseline", "methods"} <= set(case)
    assert set(case["methods"]) == {"polynomial", "retimed", "constraint_points", "penalty", "shooting",
                                    "auto"}
    for m, r in case["methods"].items():
        assert {"status", "time", "first_call", "speedup_vs_baseline_solve"} <= set(r), m
        if r["status"] == "error":  # a method being worked on: recorded, not hidden
            assert r["error"]
    assert [s["samples"] for s in results["scaling"]["samples"]] == [101, 1001, 10001]
    j = results["scaling"]["joints"][0]
    assert j["n"] == 3 and {"construct", "forward_10k", "inverse_10k",
                            "coarse_scan", "plan"} <= set(j)
    assert results["targets"] and all({"target", "scope", "measured", "met"} <= set(t)
                                      for t in results["targets"])


def test_baseline_reintegrates_to_goal(results: dict) -> None:
    base = results["cases"][0]["baseline"]
    assert base["status"] == "success"
    assert base["solve_time"]["median"] > 0 and base["build_time"]["median"] > 0
    _finite_metrics(base["reintegration"])
    assert base["reintegration"]["terminal_error_rad"] < 1e-6


def test_planner_reintegration_is_finite(results: dict) -> None:
    methods = results["cases"][0]["methods"]
    assert methods["polynomial"]["status"] == "success"
    for m, r in methods.items():
        if r["status"] == "success":
            _finite_metrics(r["reintegration"])
            assert r["reintegration"]["terminal_error_rad"] < 1e-6, m
            assert r["time"]["median"] > 0


def test_reintegration_helpers() -> None:
    # u1 = 0: phi fixed, th2..thn fixed, th1 = th1(0) + u2 t; energy = u2^2 T
    seg = [Segment(0.0, 0.5, lambda t: (0.0, 0.2)), Segment(0.5, 1.0, lambda t: (0.0, 0.2))]
    t, x = integrate((0.88658, 0.7115), (2, 3), np.array([0.0, 0.1, 0.2, 0.3]), seg, grid=11)
    assert t[0] == 0.0 and t[-1] == 1.0 and np.all(np.diff(t) > 0)
    np.testing.assert_allclose(x[-1], [0.0, 0.3, 0.2, 0.3, 0.04], atol=1e-12)
    # the one reversal count, with the benchmark's dead band
    assert count_reversals(np.sin(np.linspace(0, 3 * np.pi, 1001)), DEAD_BAND) == 3
    assert count_reversals(np.linspace(0, 1, 11) + 1e-6 * (-1) ** np.arange(11), DEAD_BAND) == 0
    assert count_reversals(np.r_[0.0, 1.0, 1.0 - 0.5 * DEAD_BAND, 2.0], DEAD_BAND) == 0
    th = np.array([[0.0, 0.0], [0.5, 1.5], [1.0, 1.0]])
    assert line_distance(th, th[0], th[-1]) == pytest.approx(np.sqrt(0.5))


def test_segment_deviation_and_margin_of_every_joint() -> None:
    # a path that overshoots the goal along the line: 0 from the LINE, 0.5 from the SEGMENT
    t = np.linspace(0.0, 1.0, 3)
    th = np.array([[0.2, 0.3], [1.2, 0.3], [0.7, 0.3]])
    x = np.column_stack([np.zeros(3), th, np.zeros(3)])
    start, goal = th[0], th[-1]
    m = path_metrics(t, x, start, goal)
    assert m.joint_space_dev_deg == pytest.approx(0.0, abs=1e-9)
    assert m.segment_dev_deg == pytest.approx(np.degrees(0.5))
    th[1, 1] = 0.05  # the last joint dips below th1's smallest value (0.2)
    x = np.column_stack([np.zeros(3), th, np.zeros(3)])
    m = path_metrics(t, x, start, goal)
    assert m.region_margin_deg == pytest.approx(np.degrees(0.2))     # th1 only (n - 1 = 1)
    assert m.region_margin_all_deg == pytest.approx(np.degrees(0.05))  # th2 included
