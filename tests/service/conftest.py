"""Fixtures of the service tests (helpers are in ``svc_support``)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Iterator

import pytest

# the helpers module sits beside this file; make it importable whatever pytest's import mode
sys.path.insert(0, str(Path(__file__).resolve().parent))

from svc_support import (KEYS, ORIGIN, TestClient, free_port, running_app,  # noqa: E402
                         server_process)


@pytest.fixture(scope="session")
def client() -> Iterator[TestClient]:
    """The shared app: 2 workers, a queue large enough for the concurrency test, and the
    largest default time limit (what these tests check is not how fast a plan is: at load 10
    on 2 cores a plan of 20001 samples ran past the default 10 s)."""
    with running_app(workers=2, queue_size=64, default_time_limit=60.0) as c:
        yield c


@pytest.fixture(scope="session")
def keyed_client() -> Iterator[TestClient]:
    """One app with API keys (``KEYS``) and a CORS origin (``ORIGIN``) configured, one worker,
    for every test of keys and CORS (each had started its own worker pool)."""
    with running_app(workers=1, queue_size=8, api_keys=KEYS, cors_origins=[ORIGIN]) as c:
        yield c


@pytest.fixture(scope="session")
def live_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``python -m service --host 127.0.0.1 --port <free>`` with one worker.

    The options are given on the command line (they override the environment's, set here to
    another address) so that every test using this server also checks that they take effect.
    """
    port = free_port()
    log = tmp_path_factory.mktemp("live") / "server.log"
    env = {"PLANNER_HOST": "0.0.0.0", "PLANNER_PORT": str(free_port()), "PLANNER_WORKERS": "1",
           "PLANNER_DEFAULT_TIME_LIMIT": "60"}  # (speed is not what these tests check)
    argv = [sys.executable, "-m", "service", "--host", "127.0.0.1", "--port", str(port)]
    with server_process(argv, env, port, log) as base:
        yield base


