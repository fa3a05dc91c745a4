"""``scripts/serve.sh`` passes its arguments to ``python -m service``.

``--host``/``--port`` taking effect is checked by the ``live_server`` fixture (conftest), which
starts the server with them; here: ``--help`` and a bad option answer at once, without a server.
"""

from __future__ import annotations

import subprocess
import sys

from svc_support import ROOT


def test_serve_help_prints_usage_and_exits() -> None:
    done = subprocess.run(["bash", str(ROOT / "scripts" / "serve.sh"), "--help"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage:")
    for option in ("--host", "--port", "PLANNER_"):
        assert option in done.stdout
    assert "Uvicorn running" not in done.stdout + done.stderr


def test_bad_port_is_refused_with_usage() -> None:
    done = subprocess.run([sys.executable, "-m", "service", "--port", "70000"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "usage:" in done.stderr and "1..65535" in done.stderr
