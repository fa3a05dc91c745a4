"""Smoke test of the replanning benchmark (``python -m bench.replan``), so that it cannot rot:
one 3-joint goal, CasADi's virtual machine (no compilers run), the latency and closed-loop
parts, and the report's numbers checked for what they say."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_replan_benchmark_reports_latency_and_the_closed_loop(tmp_path: Path) -> None:
    out = tmp_path / "replan.json"
    proc = subprocess.run(
        [sys.executable, "-m", "bench.replan", "--joints", "3", "--goals", "1", "--replans",
         "3", "--no-native", "--out", str(out)], cwd=ROOT, capture_output=True, text=True,
        timeout=900)  # a hang guard only
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(out.read_text())
    lat = report["latency"]["3"]
    assert lat["replans"] == 3 and sum(lat["routes"].values()) == 3
    assert 0.0 < lat["p50_ms"] <= lat["p99_ms"] and math.isfinite(lat["cold_plan_median_ms"])
    loop = report["closed_loop"]["3"]
    row = loop["rows"][0]
    # the plant's gains off by up to 5 %, the start by up to 0.5 deg: replanning every 0.05 s
    # ends far closer than open loop, inside the region
    assert row["open"] > 1e-4 and row["closed"] < 1e-2 * row["open"]
    assert loop["inside"] == 1
    # the loop's own replans are timed (about 20 of them over a 1 s plan)
    assert 0.0 < loop["replan_p50_ms"] <= loop["replan_p99_ms"]
    assert "its replans p50" in proc.stdout
