"""``python -m optimizer plan request.json`` prints the same JSON as ``POST /v1/plans``."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from svc_support import same_json

REQUESTS = [
    {"start": np.deg2rad([10, 10, 10]).tolist(), "goal": np.deg2rad([30, 30, 30]).tolist(),
     "method": "polynomial", "samples": 21},
    {"start": np.deg2rad([10, 20, 30]).tolist(), "goal": np.deg2rad([40, 25, 15]).tolist(),
     "method": "polynomial"},
]


def _strip(d: dict) -> dict:
    d = dict(d)
    d.pop("timing", None)
    d.pop("request_id", None)
    d.pop("instance", None)
    for k in ("status", "type", "title"):
        if not isinstance(d.get(k), str):
            d.pop(k, None)
    return d


def test_cli_prints_the_endpoint_json(client, tmp_path):
    for i, body in enumerate(REQUESTS):
        path = tmp_path / f"req{i}.json"
        path.write_text(json.dumps(body))
        cli = subprocess.run([sys.executable, "-m", "optimizer", "plan", str(path)],
                             capture_output=True, text=True, timeout=120)
        out = json.loads(cli.stdout)
        r = client.post("/v1/plans", json=body)
        api = r.json()
        if r.status_code == 200:
            assert cli.returncode == 0
            # the service names the path's columns (q_names, u_names); the rest is the same
            for name in ("q_names", "u_names"):
                api["path"].pop(name)
            # floats to 1e-12: the workers prove with the compiled quadrature, the CLI with
            # numpy's (the same sums in another order)
            assert same_json(_strip(out), _strip(api))[:5] == []
        else:
            assert cli.returncode == 1
            assert out["code"] == api["code"] == "infeasible"
            assert out["detail"] == api["detail"]
