"""Smoke test of the load test (``bench/load_test.py``): a 5 s run with 8 locust clients against a
live server must finish, count no error, answer every deliberate bad request with its 4xx and
report throughput, latency percentiles and the workers' memory."""

from __future__ import annotations

import json
import subprocess
import sys

from svc_support import ROOT


def test_the_load_test_runs_for_five_seconds_without_errors(tmp_path):
    out = tmp_path / "load.json"
    done = subprocess.run([sys.executable, "-m", "bench.load_test", "--duration", "5",
                           "--users", "8", "--json", str(out)], cwd=ROOT, capture_output=True,
                          text=True, timeout=240)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    report = json.loads(out.read_text(encoding="utf-8"))
    assert report["errors"] == 0, report["failures"]
    assert report["requests"] > 20 and report["throughput_rps"] > 1
    assert 0 < report["p50_ms"] <= report["p95_ms"] <= report["p99_ms"]
    assert report["deliberate_bad_requests"] == report["deliberate_bad_answered_as_expected"]
    kinds = set(report["per_kind"])
    assert {"POST /v1/plans (fixed dphi)", "POST /v1/transforms", "GET /healthz"} <= kinds
    for when in ("memory_start", "memory_end"):
        workers = report[when]["workers"]
        assert len(workers) == report["workers"] and all(w["rss_mb"] > 10 for w in workers)
    assert "p50" in done.stdout and "memory end" in done.stdout


def test_the_stage_profile_runs_and_accounts_for_every_stage(tmp_path):
    """``bench/http_stages.py`` on two requests: every stage timed, the ASGI app answered
    (200, checked inside), the answer of the size a default plan has."""
    out = tmp_path / "stages.json"
    done = subprocess.run([sys.executable, "-m", "bench.http_stages", "--requests", "2",
                           "--rounds", "1", "--json", str(out)], cwd=ROOT, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    report = json.loads(out.read_text(encoding="utf-8"))
    stages = {row["stage"]: row["cpu_us"] for row in report["stages"]}
    assert len(stages) == 14 and all(v > 0 for v in stages.values())
    assert stages["plan"] > stages["JSON (finite_json)"]
    # (a default answer: 201 samples of 4 angles, 2 rates, 4 chained coordinates and more)
    assert 20_000 < report["sizes"]["answer_json_bytes"] < 200_000
    assert "| worker | plan |" in done.stdout
