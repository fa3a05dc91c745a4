"""A study on a real Dask cluster: a ``dask scheduler`` and two ``dask worker`` processes on
127.0.0.1, started here as subprocesses and killed at the end.

* a study of 40 goals (n = 3, two mechanisms) on the cluster gives the rows of the same study
  planned in this process (every column but ``seconds``);
* a worker killed mid-study (no nanny to bring it back): the scheduler runs its chunks again on
  the other worker and every row comes back once, equal to the local run's;
* the CLI with ``--scheduler``.

One cluster serves the module (starting one, each worker importing CasADi and scipy, took 15-24 s
on two busy cores); the CLI test needs only one live worker, so it runs whether or not the
lost-worker test has killed the other. 40 goals in chunks of 4 are 10 chunks: after the first
is back, the killed worker's are still to run (120 goals made the test take 150 s at load 8).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import pytest

import distributed  # noqa: F401 - in the test extra: its absence must fail, not skip

from optimizer import study_io, studies
from optimizer.model import Robot

ROOT = Path(__file__).resolve().parents[1]
DASK = str(Path(sys.executable).with_name("dask"))
#: Generous: two busy cores, and each worker imports CasADi and scipy.
START_TIMEOUT = 180.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Cluster:
    """A scheduler and worker processes on loopback."""

    def __init__(self, log_dir: Path) -> None:
        self.port = _free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.log_dir = log_dir
        self.procs: list[subprocess.Popen[bytes]] = []
        self.workers: list[subprocess.Popen[bytes]] = []
        env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
        self.env = env
        self.procs.append(self._start("scheduler", [DASK, "scheduler", "--host", "127.0.0.1",
                                                     "--port", str(self.port),
                                                     "--no-dashboard"]))

    def _start(self, name: str, cmd: list[str]) -> subprocess.Popen[bytes]:
        log = open(self.log_dir / f"{name}.log", "wb")
        return subprocess.Popen(cmd, cwd=ROOT, env=self.env, stdout=log, stderr=log,
                                stdin=subprocess.DEVNULL)

    def add_worker(self) -> subprocess.Popen[bytes]:
        p = self._start(f"worker{len(self.workers)}",
                        [DASK, "worker", self.address, "--host", "127.0.0.1", "--nthreads",
                         "1", "--no-nanny", "--no-dashboard", "--memory-limit", "0",
                         "--name", f"w{len(self.workers)}"])
        self.procs.append(p)
        self.workers.append(p)
        return p

    def logs(self) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text()[-3000:]}"
                         for p in sorted(self.log_dir.glob("*.log")))

    def stop(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                p.kill()
        for p in self.procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                pass


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Cluster, Any]]:
    c = Cluster(tmp_path_factory.mktemp("dask"))
    client = None
    try:
        c.add_worker()
        c.add_worker()
        client = studies.dask_client(c.address, timeout=START_TIMEOUT)
        try:
            client.wait_for_workers(2, timeout=START_TIMEOUT)
        except Exception:  # noqa: BLE001 - show the processes' logs
            pytest.fail("the Dask workers did not start:\n" + c.logs())
        yield c, client
    finally:
        if client is not None:
            client.close()
        c.stop()


def _strip(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


MECHANISMS = [("proto", Robot.default(3)), ("wide", Robot((1.0, 0.6), (2, 2)))]


def test_cluster_rows_equal_local_rows_and_survive_a_lost_worker(
        cluster: tuple[Cluster, Any], tmp_path: Path) -> None:
    c, client = cluster
    tasks = studies.make_tasks(MECHANISMS, random=20, seed=21)
    assert len(tasks) == 40
    local = studies.run_study(tasks, workers=0).rows
    assert sum(r["status"] == "success" for r in local) >= 32  # the rows are plans, mostly

    on_cluster = studies.run_study(tasks, client=client, out=tmp_path / "c.csv")
    assert on_cluster.planned == 40
    assert _strip(on_cluster.rows) == _strip(local)
    assert _strip(study_io.read_rows(tmp_path / "c.csv")[1]) == _strip(local)
    # both workers took part
    assert len(client.nthreads()) == 2

    # lose a worker for good after the first chunk is back: its chunks run again elsewhere
    victim = c.workers[0]
    killed: list[float] = []

    def kill_once(rows: list[dict[str, Any]]) -> None:
        if not killed:
            victim.kill()
            victim.wait(timeout=30)
            killed.append(time.monotonic())
    again = studies.run_study(studies.make_tasks(MECHANISMS, random=20, seed=21), client=client,
                              size=4, on_chunk=kill_once, out=tmp_path / "lost.csv")
    assert killed and victim.poll() is not None
    assert again.planned == 40
    rows = study_io.read_rows(tmp_path / "lost.csv")[1]
    assert [r["id"] for r in rows] == [t.id for t in tasks]  # every row, once
    assert _strip(rows) == _strip(local)


def test_cli_on_the_cluster(cluster: tuple[Cluster, Any], tmp_path: Path) -> None:
    c, _ = cluster
    done = subprocess.run([sys.executable, "-m", "optimizer", "study", "--random", "8",
                           "--scheduler", c.address, "--out", str(tmp_path / "rows.parquet")],
                          capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr + c.logs()
    assert json.loads(done.stdout)["rows"] == 8
    rows = study_io.read_rows(tmp_path / "rows.parquet")[1]
    local = studies.run_study(studies.make_tasks([("default-n3", Robot.default(3))], random=8,
                                                 seed=studies.BASE_SEED), workers=0).rows
    assert _strip(rows) == _strip(local)


def test_an_unreachable_scheduler_is_a_clear_error() -> None:
    port = _free_port()
    with pytest.raises(ValueError, match="cannot reach the Dask scheduler"):
        studies.dask_client(f"tcp://127.0.0.1:{port}", timeout=2.0)
