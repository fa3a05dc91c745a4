"""The generated goals (bench/goals.py) and the benchmark on them (``python -m bench --goals``).

* the generator is deterministic, cycles through its kinds, and each kind is what it says;
* every generated goal is reachable: re-integrating the generator's own inputs with the
  benchmark's scipy integration (not the generator's) ends at the goal, every joint inside;
* a tiny run of the documented command (3 goals of n = 3, 1 of n = 4, one repeat, two methods)
  writes a report whose summary agrees with its own per-goal rows.

Timing targets are the benchmark's business, not this test's: nothing here asserts a speed.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import goals as goals_mod  # noqa: E402
from bench.baselines.multiple_shooting import default_model  # noqa: E402
from bench.goals_run import TERMINAL_TOL, verified  # noqa: E402
from bench.reintegrate import Segment, integrate  # noqa: E402


def test_generate_is_deterministic_and_cycles_kinds() -> None:
    a = goals_mod.generate(3, 7)
    b = goals_mod.generate(3, 7)
    assert a == b  # same seed per (n, index): the same goals on every run
    assert [g.kind for g in a] == [goals_mod.KINDS[k % 3] for k in range(7)]
    assert len({g.name for g in a}) == 7
    # a prefix of a longer request is the same goals (the benchmark's counts may shrink)
    assert goals_mod.generate(3, 3) == a[:3]
    assert goals_mod.generate(3, 3, seed=1) != a[:3]


@pytest.mark.parametrize("n", [3, 4, 5])
def test_kinds_are_what_they_say(n: int) -> None:
    for g in goals_mod.generate(n, 6):
        assert g.n == n
        d = np.subtract(g.goal, g.start)
        assert np.max(np.abs(d)) >= goals_mod.MIN_MOVE
        rest = d[1:]
        opposed = bool(np.any(rest > 1e-6) and np.any(rest < -1e-6))
        # th_i' = K_i cos(th_{i-1})^m_i u1 with cos > 0 inside the region: while u1 keeps one
        # sign every th_2..th_n moves with it, so opposed net changes need u1 to change sign
        # (phi to reverse) -- beyond the paper's family, which keeps v1 constant
        if g.kind == "opposite":
            assert opposed, g
        if g.kind == "same":
            assert not opposed, g
        u1 = np.array([goals_mod.rates_at(g, t)[0] for t in np.linspace(0.0, 1.0, 201)])
        if g.kind == "same":
            assert np.all(u1 > 0) or np.all(u1 < 0), g.name
        else:  # opposite and reversing drive phi back and forth
            assert u1.min() < 0 < u1.max(), g.name


@pytest.mark.parametrize("n", [3, 4, 5])
def test_generated_goals_are_reachable(n: int) -> None:
    gains, exps = default_model(n)
    for g in goals_mod.generate(n, 6):
        seg = [Segment(0.0, 1.0, lambda t, g=g: goals_mod.rates_at(g, t))]
        t, x = integrate(gains, [int(e) for e in exps], np.concatenate([[0.0], g.start]), seg,
                         grid=2001)
        th = x[:, 1:n + 1]
        np.testing.assert_allclose(th[0], g.start, atol=0.0)
        assert np.max(np.abs(th[-1] - np.asarray(g.goal))) < TERMINAL_TOL, g.name
        # every joint, th_n included, strictly inside the region on the whole path
        assert th.min() > 0.0 and th.max() < 0.5 * math.pi, g.name


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], str, str]:
    tmp = tmp_path_factory.mktemp("goals")
    out, md = tmp / "goals.json", tmp / "goals.md"
    proc = subprocess.run(
        [sys.executable, "-m", "bench", "--goals", "--goals-counts", "3:3,4:1", "--repeats", "1",
         "--methods", "polynomial,shooting", "--out", str(out), "--md", str(md)],
        cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(out.read_text()), md.read_text(), proc.stdout


def test_report_structure(run: tuple[dict[str, Any], str, str]) -> None:
    res, md, stdout = run
    assert md in stdout  # printed and written: the same text
    for head in ("### Default request, per n", "### Per method", "against the baseline",
                 "### Targets", "### Goals that miss a target"):
        assert head in md, head
    assert res["config"]["counts"] == {"3": 3, "4": 1}
    assert res["config"]["methods"] == ["polynomial", "shooting"]
    rows = res["goals"]
    assert [r["name"] for r in rows] == [g.name for g in goals_mod.benchmark_goals({3: 3, 4: 1})]
    for r in rows:
        d = r["default"]
        assert {"status", "time", "first_call", "slowest_call", "verified"} <= set(d)
        assert d["time"]["count"] >= 1 and d["slowest_call"] >= d["time"]["median"] > 0
        assert set(r["methods"]) == {"polynomial", "shooting"}
        for m in [d, *r["methods"].values()]:
            rm = m.get("reintegration")
            # the verdict is the documented one, from the re-integrated numbers
            assert m["verified"] == verified(rm)
            if rm is not None:
                assert {"segment_dev_deg", "region_margin_all_deg", "joint_space_dev_deg",
                        "reversals_phi", "reversals_th1"} <= set(rm)
                # a segment is no closer than its line; all joints no farther inside than some
                assert rm["segment_dev_deg"] >= rm["joint_space_dev_deg"] - 1e-9
                assert rm["region_margin_all_deg"] <= rm["region_margin_deg"] + 1e-12
        # the n-joint baseline runs on every n, on the same goal as the default request
        assert r["baseline"] is not None and r["baseline"]["method"] == "baseline"


def test_summary_agrees_with_rows(run: tuple[dict[str, Any], str, str]) -> None:
    res, md, _ = run
    s, rows = res["summary"], res["goals"]
    assert set(s["per_n"]) == {"3", "4"}
    for n, e in s["per_n"].items():
        sub = [r for r in rows if r["n"] == int(n)]
        assert e["goals"] == len(sub)
        assert e["verified"] == sum(r["default"]["verified"] for r in sub)
        times = [r["default"]["time"]["median"] for r in sub]
        assert e["p50"] == pytest.approx(float(np.median(times)))
        assert e["max"] == pytest.approx(max(times))
        assert e["methods"]["shooting"]["success"] == sum(
            r["methods"]["shooting"]["status"] == "success" for r in sub)
        assert f"| {n} | {e['goals']} | {e['verified']} |" in md
    b = s["per_n"]["3"]["baseline"]
    per = b["per_goal"]
    assert b["compared"] == len(per) and b["compared"] + b["baseline_failed"] == 3
    for name, c in per.items():
        r = next(x for x in rows if x["name"] == name)
        dm, bm = r["default"]["reintegration"], r["baseline"]["reintegration"]
        if r["default"]["verified"]:
            assert c["dev_no_larger"] == (math.radians(dm["segment_dev_deg"])
                                          <= math.radians(bm["segment_dev_deg"]) + 1e-6)
            assert c["reversals_no_more"] == (dm["reversals_phi"] + dm["reversals_th1"]
                                              <= bm["reversals_phi"] + bm["reversals_th1"])
            assert c["fewer_reversals"] == (dm["reversals_phi"] + dm["reversals_th1"]
                                            < bm["reversals_phi"] + bm["reversals_th1"])
        assert c["speed_ratio"] == pytest.approx(r["baseline"]["time"]["median"]
                                                 / r["default"]["time"]["median"])
    assert b["dev_no_larger"] == sum(c["dev_no_larger"] for c in per.values())
    assert b["dev_no_larger_or_fewer_reversals"] == sum(
        c["dev_no_larger"] or c["fewer_reversals"] for c in per.values())
    # issue 14's per-goal ratios: the baseline's time over the default plan's, per goal
    ratios = [r["baseline"]["time"]["median"] / r["default"]["time"]["median"]
              for r in rows if r["n"] == 3 and r.get("baseline")
              and r["baseline"].get("verified") and r["default"]["verified"]]
    assert s["per_n"]["3"]["methods"]["default"]["baseline_over_method"] == pytest.approx(
        float(np.median(ratios)))
    # every target is stated with its measurement, and every miss names its goal and reason
    assert {t["target"] for t in s["targets"] if t["n"] == 3} >= {
        "every goal verified", "p95 of the default plan <= 30 ms",
        "no default plan near its time limit",
        "median speed ratio (baseline solve / default plan) >= 3"}
    assert {t["target"] for t in s["targets"] if t["n"] == 4} >= {
        "p95 of the default plan <= 100 ms"}
    if "baseline" in s["per_n"]["4"]:  # issue 24's speed targets where the baseline solved
        assert {t["target"] for t in s["targets"] if t["n"] == 4} >= {
            "median speed ratio (baseline solve / default plan) >= 2",
            "no goal with speed ratio below 1"}
    # the smallest per-goal ratio and the count below 1 agree with the per-goal comparisons
    for e in s["per_n"].values():
        if "baseline" in e:
            rs = [c["speed_ratio"] for c in e["baseline"]["per_goal"].values()]
            assert e["baseline"]["min_speed_ratio"] == pytest.approx(min(rs))
            assert e["baseline"]["goals_below_min_ratio"] == sum(x < 1.0 for x in rs)
    for m in s["misses"]:
        assert m["why"] and f"`{m['name']}`" in md
