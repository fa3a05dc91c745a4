"""Deployment files without a Docker engine: docker-compose.yml against the Compose
Specification schema, the Dockerfile's shape, and the container's exact start command run here
with the environment the compose file sets."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest
import yaml
from jsonschema import Draft201909Validator

from svc_support import ROOT, free_port, server_process

#: The schema declares draft 2019-09 (its "$schema" URL is the old http:// spelling).
SCHEMA = ROOT / "tests" / "service" / "data" / "compose_spec.json"


def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text(encoding="utf-8"))


def dockerfile_instructions() -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` with line continuations joined."""
    text = (ROOT / "Dockerfile").read_text(encoding="utf-8")
    text = re.sub(r"\\\n\s*", " ", text)
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def test_compose_file_is_valid_against_the_compose_spec():
    schema = json.loads(SCHEMA.read_text(encoding="utf-8"))
    Draft201909Validator.check_schema(schema)
    errors = list(Draft201909Validator(schema).iter_errors(compose()))
    assert not errors, [e.message for e in errors]


def test_compose_schema_is_not_vacuous():
    schema = json.loads(SCHEMA.read_text(encoding="utf-8"))
    validator = Draft201909Validator(schema)
    bad = compose()
    bad["services"]["planner"]["deploy"]["replicas"] = "three"
    assert list(validator.iter_errors(bad))
    bad = compose()
    bad["services"]["planner"]["healthcheck"]["every"] = "5s"
    assert list(validator.iter_errors(bad))


def _seconds(duration: str) -> float:
    """A Compose duration (``1m30s``, ``40s``, ``500ms``) in seconds."""
    units = {"h": 3600.0, "m": 60.0, "s": 1.0, "ms": 1e-3, "us": 1e-6}
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|us|h|m|s)", str(duration))
    assert parts and "".join(a + b for a, b in parts) == str(duration), duration
    return sum(float(a) * units[b] for a, b in parts)


def test_docker_waits_longer_than_the_graceful_shutdown():
    from service.settings import Settings

    planner = compose()["services"]["planner"]
    timeout = float(planner["environment"].get("PLANNER_SHUTDOWN_TIMEOUT",
                                               Settings.model_fields["shutdown_timeout"].default))
    assert _seconds(planner["stop_grace_period"]) >= timeout + 5


def test_the_load_balancer_waits_for_the_longest_request():
    """nginx waits for a replica's answer (``proxy_read_timeout``) at least as long as the
    longest request a replica may take (waiting for a worker, the largest time limit, the
    grace), and Docker lets nginx's graceful stop last longer than that."""
    from service.settings import Settings

    doc = compose()
    env = doc["services"]["planner"]["environment"]

    def setting(name: str) -> float:
        return float(env.get("PLANNER_" + name.upper(), Settings.model_fields[name].default))

    longest = setting("queue_timeout") + setting("max_time_limit") + setting("timeout_grace")
    conf = (ROOT / "deploy" / "nginx.conf").read_text(encoding="utf-8")
    (read_timeout,) = re.findall(r"proxy_read_timeout (\d+)s;", conf)
    assert longest < float(read_timeout) <= longest + 30, (longest, read_timeout)
    assert _seconds(doc["services"]["lb"]["stop_grace_period"]) >= float(read_timeout) + 5


def test_compose_runs_replicas_behind_a_load_balancer():
    doc = compose()
    planner, lb = doc["services"]["planner"], doc["services"]["lb"]
    assert planner["deploy"]["replicas"] == 3
    assert planner["build"] == "."
    # the load balancer waits for warm workers: readiness, not liveness
    assert "/readyz" in " ".join(planner["healthcheck"]["test"])
    assert all(k.startswith("PLANNER_") for k in planner["environment"])
    assert lb["image"].startswith("nginx")
    assert lb["depends_on"]["planner"]["condition"] == "service_healthy"
    (mount,) = lb["volumes"]
    source = mount.split(":")[0]
    conf = (ROOT / source).read_text(encoding="utf-8")
    assert re.search(r"server\s+planner:8000[ ;]", conf)
    assert "proxy_pass http://planner_replicas;" in conf
    port = planner["environment"]["PLANNER_PORT"]
    assert f"planner:{port}" in conf


def test_dockerfile_shape():
    ins = dockerfile_instructions()
    assert ins[0] == ("FROM", "python:3.11-slim")
    cmd = [json.loads(a) for w, a in ins if w == "CMD"]
    assert cmd[-1] == ["python", "-m", "service"]
    users = [a for w, a in ins if w == "USER"]
    assert users and users[-1] not in ("root", "0")
    (health,) = [a for w, a in ins if w == "HEALTHCHECK"]
    assert "urllib" in health and "/healthz" in health
    assert any(w == "RUN" and "pip install ." in a for w, a in ins)
    ignore = (ROOT / ".dockerignore").read_text(encoding="utf-8").split()
    assert ".venv" in ignore and ".git" in ignore


def test_container_start_command_serves_healthz(tmp_path):
    """Run the image's CMD with the compose file's environment (only the address moved to a
    free loopback port), then its healthcheck command against that port."""
    env = {k: str(v) for k, v in compose()["services"]["planner"]["environment"].items()}
    port = free_port()
    env.update({"PLANNER_HOST": "127.0.0.1", "PLANNER_PORT": str(port)})
    cmd = [json.loads(a) for w, a in dockerfile_instructions() if w == "CMD"][-1]
    assert cmd[0] == "python"
    argv = [sys.executable] + cmd[1:]
    with server_process(argv, env, port, tmp_path / "server.log") as base:
        with urllib.request.urlopen(base + "/healthz", timeout=5) as r:
            assert r.status == 200 and json.loads(r.read()) == {"status": "ok"}
        with urllib.request.urlopen(base + "/readyz", timeout=5) as r:
            assert json.loads(r.read())["workers"] == int(env["PLANNER_WORKERS"])
        check = compose()["services"]["planner"]["healthcheck"]["test"]
        assert check[0] == "CMD" and check[1] == "python"
        code = check[-1].replace("127.0.0.1:8000", f"127.0.0.1:{port}")
        assert code != check[-1]
        done = subprocess.run([sys.executable, "-c", code], timeout=30)
        assert done.returncode == 0
    log = (tmp_path / "server.log").read_text(errors="replace")
    lines = [json.loads(x) for x in log.splitlines() if x.startswith("{")]
    assert any(x.get("route") == "/healthz" and x.get("request_id") for x in lines), log[-2000:]


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                    reason="no C compiler")
def test_the_image_builds_the_default_robots_compiled_nlp(tmp_path):
    """The Dockerfile bakes the default robots' compiled shooting NLPs and the proofs'
    compiled quadrature into the image with ``python -m service.prebuild`` (every joint count
    of the warm-up); here the same module runs for the 3-joint robot (each more joint count
    compiles for 10-40 s), HOME of the image's user replaced by a temporary one."""
    steps = [rest for word, rest in dockerfile_instructions()
             if word == "RUN" and "service.prebuild" in rest]
    assert steps == ["python -m service.prebuild"]
    assert any(word == "RUN" and "gcc" in rest and "libc6-dev" in rest
               for word, rest in dockerfile_instructions())
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PLANNER_", "XDG_"))}
    env["HOME"] = str(tmp_path)
    # the image's `python` is this interpreter here
    env["PATH"] = os.path.dirname(sys.executable) + os.pathsep + env.get("PATH", "")
    res = subprocess.run(["sh", "-c", steps[0] + " --joints 3"], env=env,
                         cwd=Path(__file__).resolve().parents[2], capture_output=True, text=True, timeout=300, check=False)
    assert res.returncode == 0, res.stderr
    assert "compiled: 3=yes kernel=yes" in res.stdout, res.stdout
    assert len(list((tmp_path / ".cache" / "chained-planner" / "native").glob("*.so"))) == 2
