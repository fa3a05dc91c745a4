"""``python -m bench.forms`` on one goal: every handed-out form, re-integrated by scipy, passes
the issue-25 checks the benchmark records (the benchmark's own criteria, run end to end)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def test_forms_bench_on_one_goal(tmp_path, capsys):
    from bench import forms
    out = tmp_path / "forms.json"
    assert forms.main(["--counts", "3:1", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())
    (d,), (lim,) = rows["default"], rows["limited"]
    assert "error" not in d and "error" not in lim, (d, lim)
    assert d["rest_at_ends"] and d["no_repeated_time"] and d["reaches"] and d["inside"]
    assert d["indicators_equal"] and d["quality_no_worse"], d
    for form in ("linear", "joint_trajectory", "zoh"):
        assert lim[form]["limit_ratio"] <= forms.LIMIT_SHARE, (form, lim[form])
        assert lim[form]["reaches"] and lim[form]["inside"], (form, lim[form])
    assert lim["joint_trajectory"]["positions_consistent"]
    assert "| 3 | 1 |" in capsys.readouterr().out
