"""Type hints are checked: mypy over the library, the service and the benchmarks
(configuration in pyproject.toml)."""

from __future__ import annotations

import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_mypy_clean():
    res = subprocess.run([sys.executable, "-m", "mypy", "optimizer", "service", "bench"], cwd=ROOT,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
