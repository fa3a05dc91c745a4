"""Mechanism studies: many plans, one row per (mechanism, goal), locally or on a Dask cluster.

A designer choosing gains and exponents wants, per candidate mechanism, the share of a workspace
it reaches and the deviation, reversals and sensitivity of its plans. A study is the pure
function ``task -> row`` (:func:`plan_row`) mapped over every (mechanism, goal) pair:

* **Tasks are pure.** A row depends on its task only (the plan is a pure function of its
  request), so a chunk that a lost worker was running can be run again anywhere and gives the
  same rows; the rows of a local run and of a cluster run are the same except ``seconds``.
* **Nothing is lost.** A plan that fails is a row with its status (the error's code,
  :mod:`optimizer.errors`, and its message in ``detail``); an exception no one expected is a
  row with status ``error``. A study never stops for one plan.
* **Chunks.** Plans take 4-150 ms; a task costs the scheduler about 1 ms plus a round trip, so
  tasks are chunks of at least :data:`MIN_CHUNK` plans (< 5 % overhead at 4 ms a plan), and
  about :data:`CHUNKS_PER_WORKER` chunks per worker so that the last ones end together.
* **Resume.** Rows already in the output file (by ``id``) are not planned again.

Engines: a process pool of this machine (``workers``), or a Dask scheduler
(``scheduler="tcp://host:port"``; ``pip install chained-planner[cluster]``) whose workers have
this package installed. This module is the library's top layer: it uses
:func:`optimizer.planner.plan.plan`, and nothing in ``optimizer`` imports it.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import sys
import time
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence, TextIO

from .errors import PlannerError
from .model import Robot
from .planner.plan import plan
from .problem import PlanRequest
from .reachable import BASE_SEED, generate
from .study_io import BASE_COLUMNS, RowWriter, columns, read_rows

#: Fewest plans in one task (chunk).
MIN_CHUNK = 16
#: Most plans in one task (a lost worker costs at most this much work again).
MAX_CHUNK = 256
#: Chunks per worker aimed at: enough for the last chunks to end close together.
CHUNKS_PER_WORKER = 8


@dataclass(frozen=True)
class PlanOptions:
    """The part of every plan request that a study fixes (see :class:`PlanRequest`)."""

    method: str = "auto"
    time_limit: float = 10.0
    samples: int = 101


@dataclass(frozen=True)
class StudyTask:
    """One plan of a study: a mechanism, a start/goal pair (rad) and the options."""

    id: str
    mechanism: str
    gains: tuple[float, ...]
    exponents: tuple[int, ...]
    goal_name: str
    kind: str
    start: tuple[float, ...]
    goal: tuple[float, ...]
    options: PlanOptions = field(default_factory=PlanOptions)


def make_tasks(mechanisms: Sequence[tuple[str, Robot]],
               goals: Sequence[tuple[str, Sequence[float], Sequence[float]]] | None = None, *,
               random: int | None = None, seed: int = BASE_SEED,
               options: PlanOptions = PlanOptions()) -> list[StudyTask]:
    """The tasks of a study, in its order (mechanism by mechanism).

    Parameters
    ----------
    mechanisms : sequence of (name, Robot)
    goals : sequence of (name, start, goal), optional
        Given goals: each mechanism plans those of its own ``n``.
    random : int, optional
        Instead of ``goals``: this many reachable goals per mechanism, generated on its own model
        (:func:`optimizer.reachable.generate` with ``seed``).
    options : PlanOptions

    Raises
    ------
    ValueError
        Neither or both of ``goals`` and ``random``; a mechanism without a goal of its ``n``;
        two tasks with one id.
    """
    if (goals is None) == (random is None):
        raise ValueError("give either goals or random (a number of generated goals)")
    tasks: list[StudyTask] = []
    for name, robot in mechanisms:
        if random is not None:
            mine = [(g.name, g.kind, g.start, g.goal)
                    for g in generate(robot.n, int(random), seed, robot=robot)]
        else:
            mine = [(nm, "", tuple(s), tuple(g)) for nm, s, g in goals or ()
                    if len(s) == robot.n]
            if not mine:
                raise ValueError(f"mechanism {name!r} has n = {robot.n} joints and no goal of "
                                 f"{robot.n} angles in the goals")
        for goal_name, kind, start, goal in mine:
            tasks.append(StudyTask(id=f"{name}/{goal_name}", mechanism=name,
                                   gains=robot.gains, exponents=robot.exponents,
                                   goal_name=goal_name, kind=kind,
                                   start=tuple(float(x) for x in start),
                                   goal=tuple(float(x) for x in goal), options=options))
    ids = [t.id for t in tasks]
    if len(set(ids)) != len(ids):
        raise ValueError("two tasks have the same id (mechanism/goal): give unique names")
    return tasks


def plan_row(task: StudyTask) -> dict[str, Any]:
    """Plan one task; its row, whatever happens (a failure is a row with its status)."""
    row: dict[str, Any] = {k: "" if tp is str else None for k, tp in BASE_COLUMNS.items()}
    row.update(id=task.id, mechanism=task.mechanism, goal=task.goal_name, kind=task.kind,
               n=len(task.start))
    row.update({f"start_{i}": x for i, x in enumerate(task.start, 1)})
    row.update({f"goal_{i}": x for i, x in enumerate(task.goal, 1)})
    t0 = time.perf_counter()
    try:
        req = PlanRequest(start=task.start, goal=task.goal,
                          robot=Robot(task.gains, task.exponents),
                          method=task.options.method, time_limit=task.options.time_limit,
                          samples=task.options.samples)
        result = plan(req)
    except PlannerError as exc:
        row.update(status=exc.code, detail=exc.message)
    except Exception as exc:  # noqa: BLE001 - a study never loses a row
        row.update(status="error", detail=f"{type(exc).__name__}: {exc}")
    else:
        ind = result.indicators
        row.update(status="success", method=result.method, deviation=ind.deviation,
                   reversals=ind.reversals, reversals_phi=ind.reversals_phi,
                   reversals_th1=ind.reversals_th1, d_a=ind.d_a, t_p=ind.t_p,
                   sensitivity=ind.sensitivity, phi_change=result.phi_change,
                   duration=result.duration,
                   terminal_error=result.verification.terminal_error, margin=result.margin)
    row["seconds"] = time.perf_counter() - t0
    return {k: (float(v) if isinstance(v, float) else v) for k, v in row.items()}


def run_chunk(tasks: Sequence[StudyTask]) -> list[dict[str, Any]]:
    """The rows of a chunk of tasks (the unit of work sent to a worker)."""
    return [plan_row(t) for t in tasks]


def chunk_size(remaining: int, workers: int) -> int:
    """Plans per task: about :data:`CHUNKS_PER_WORKER` chunks per worker, within
    [:data:`MIN_CHUNK`, :data:`MAX_CHUNK`]."""
    per = math.ceil(remaining / max(1, workers * CHUNKS_PER_WORKER))
    return max(MIN_CHUNK, min(MAX_CHUNK, per))


def chunks(tasks: Sequence[StudyTask], size: int) -> list[tuple[StudyTask, ...]]:
    """``tasks`` cut into consecutive chunks of ``size``."""
    return [tuple(tasks[i:i + size]) for i in range(0, len(tasks), size)]


class Progress:
    """A one-line progress bar on a terminal (nothing when the stream is not one)."""

    def __init__(self, total: int, done: int = 0, stream: TextIO | None = None) -> None:
        self.stream = sys.stderr if stream is None else stream
        self.active = bool(getattr(self.stream, "isatty", lambda: False)())
        self.total, self.done, self.start_done = total, done, done
        self.failed = 0
        self.t0 = time.monotonic()
        self._draw()

    def update(self, rows: Sequence[Mapping[str, Any]]) -> None:
        self.done += len(rows)
        self.failed += sum(1 for r in rows if r.get("status") != "success")
        self._draw()

    def close(self) -> None:
        if self.active:
            self.stream.write("\n")
            self.stream.flush()

    def _draw(self) -> None:
        if not self.active:
            return
        frac = self.done / self.total if self.total else 1.0
        width = 30
        bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
        rate = (self.done - self.start_done) / max(time.monotonic() - self.t0, 1e-9)
        left = (self.total - self.done) / rate if rate > 0 else float("nan")
        eta = f"{left:.0f} s left" if math.isfinite(left) else ""
        self.stream.write(f"\rstudy [{bar}] {self.done}/{self.total} ({100 * frac:.0f} %) "
                          f"{self.failed} failed, {rate:.1f} plans/s {eta}   ")
        self.stream.flush()


def process_pool(workers: int) -> ProcessPoolExecutor:
    """A pool of ``workers`` processes for :func:`run_study` (``executor=``).

    Workers come from a fork server that has imported the planner once (never a plain fork of
    a process that may hold threads), so a worker starts in milliseconds, not the second or
    two that importing CasADi and scipy takes.
    """
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["optimizer.studies"])
    return ProcessPoolExecutor(max_workers=workers, mp_context=ctx)


def _local(parts: Sequence[tuple[StudyTask, ...]], workers: int,
           executor: Executor | None) -> Iterator[list[dict[str, Any]]]:
    if executor is None and workers == 0:  # in this process (debugging, tiny studies)
        for part in parts:
            yield run_chunk(part)
        return
    pool = executor if executor is not None else process_pool(workers)
    futures = [pool.submit(run_chunk, part) for part in parts]
    try:
        for fut in as_completed(futures):
            yield fut.result()
    finally:
        for fut in futures:
            fut.cancel()
        if executor is None:
            pool.shutdown(wait=True, cancel_futures=True)


def dask_client(scheduler: str, timeout: float = 30.0) -> Any:
    """A client of the Dask scheduler at ``scheduler`` (``tcp://host:port``).

    Raises
    ------
    ValueError
        dask.distributed is not installed, or the scheduler cannot be reached in ``timeout`` s.
    """
    try:
        from distributed import Client
    except ImportError as exc:
        raise ValueError("a study on a Dask cluster needs dask.distributed: "
                         "pip install 'chained-planner[cluster]'") from exc
    try:
        return Client(scheduler, timeout=timeout)
    except (OSError, TimeoutError) as exc:
        raise ValueError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from exc


def _dask(parts: Sequence[tuple[StudyTask, ...]], client: Any,
          retries: int) -> Iterator[list[dict[str, Any]]]:
    from distributed import as_completed as dask_completed

    # pure tasks: a chunk lost with its worker is recomputed by the scheduler; ``retries``
    # covers a task that raised (it should not: plan_row catches every failure)
    futures = client.map(run_chunk, parts, pure=True, retries=retries)
    try:
        for fut in dask_completed(futures):
            yield fut.result()
    finally:
        client.cancel(futures)


@dataclass
class StudyResult:
    """What a study did: every row (the file's, in study order), and how many it planned."""

    rows: list[dict[str, Any]]
    planned: int
    skipped: int
    chunk_size: int
    wall_seconds: float


def run_study(tasks: Sequence[StudyTask], *, out: str | os.PathLike[str] | None = None,
              workers: int | None = None, scheduler: str | None = None,
              client: Any = None, executor: Executor | None = None,
              size: int | None = None, retries: int = 2,
              progress: TextIO | None = None,
              on_chunk: Callable[[list[dict[str, Any]]], None] | None = None) -> StudyResult:
    """Run a study: every task's row, written to ``out`` as the chunks finish.

    Parameters
    ----------
    tasks : sequence of StudyTask
        From :func:`make_tasks`.
    out : path, optional
        ``.csv`` or ``.parquet``. Rows already there (by ``id``) are not planned again; at the
        end the file holds every row in study order.
    workers : int, optional
        Local process pool size (default: the CPU count; 0 plans in this process).
    scheduler : str, optional
        ``tcp://host:port`` of a Dask scheduler: the chunks run on its workers instead.
    client : distributed.Client, optional
        An open Dask client instead of ``scheduler``.
    executor : concurrent.futures.Executor, optional
        A pool to run the chunks on (e.g. :func:`process_pool`, kept warm across studies);
        ``workers`` then only sizes the chunks.
    size : int, optional
        Plans per chunk (default :func:`chunk_size`).
    retries : int
        Dask's retries of a chunk that raised.
    progress : text stream, optional
        Where the progress bar goes if it is a terminal (default standard error).
    on_chunk : callable, optional
        Called with each finished chunk's rows.

    Returns
    -------
    StudyResult
    """
    t0 = time.monotonic()
    n_max = max((len(t.start) for t in tasks), default=3)
    cols = columns(n_max)
    existing: list[dict[str, Any]] = []
    writer = None
    if out is not None:
        header, existing = read_rows(out)
        if header and header != cols:
            raise ValueError(f"{out} holds rows of other columns (another study?): choose "
                             "another output file")
        writer = RowWriter(out, cols, existing)
    done = {str(r["id"]) for r in existing}
    todo = [t for t in tasks if t.id not in done]
    own_client = None
    if scheduler is not None and client is None:
        client = own_client = dask_client(scheduler)
    if client is not None:
        n_workers = max(1, sum(client.nthreads().values()))
    else:
        n_workers = (os.cpu_count() or 1) if workers is None else int(workers)
    csize = size or chunk_size(len(todo), n_workers)
    parts = chunks(todo, csize)
    bar = Progress(len(tasks), len(tasks) - len(todo), progress)
    new_rows: list[dict[str, Any]] = []
    try:
        stream = _dask(parts, client, retries) if client is not None else \
            _local(parts, n_workers, executor)
        for rows in stream:
            new_rows.extend(rows)
            if writer is not None:
                writer.add(rows)
            if on_chunk is not None:
                on_chunk(rows)
            bar.update(rows)
    finally:
        bar.close()
        if own_client is not None:
            own_client.close()
    order = [t.id for t in tasks]
    if writer is not None:
        rows_out = writer.finish(order)
    else:
        rank = {k: i for i, k in enumerate(order)}
        rows_out = sorted(new_rows, key=lambda r: rank[r["id"]])
    return StudyResult(rows=rows_out, planned=len(new_rows), skipped=len(tasks) - len(todo),
                       chunk_size=csize, wall_seconds=time.monotonic() - t0)


def summary(rows: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per mechanism: plans, successes, share reached, median deviation (rad) and reversals."""
    by: dict[str, list[Mapping[str, Any]]] = {}
    for r in rows:
        by.setdefault(str(r["mechanism"]), []).append(r)
    out = []
    for name, rs in by.items():
        ok = [r for r in rs if r.get("status") == "success"]
        dev = sorted(float(r["deviation"]) for r in ok)
        rev = sorted(int(r["reversals"]) for r in ok)
        out.append({"mechanism": name, "plans": len(rs), "success": len(ok),
                    "reached": len(ok) / len(rs) if rs else 0.0,
                    "median_deviation": dev[len(dev) // 2] if dev else None,
                    "median_reversals": rev[len(rev) // 2] if rev else None})
    return out
