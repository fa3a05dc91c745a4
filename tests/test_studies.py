"""Mechanism studies (optimizer/studies.py, optimizer/study_io.py, ``chained-planner study``).

* a study's rows carry what the library's own answer says (``Plan.to_dict()``), one per
  (mechanism, goal), and the goals are the generator's reachable ones;
* a plan that fails is a row with its status (the typed error's code), an unexpected exception a
  row with status ``error``: never a lost row;
* an interrupted study resumes: the rows written are kept, a line cut short is planned again,
  and the result equals an uninterrupted run's;
* CSV and Parquet by the extension hold the same rows; the process pool gives the rows of a
  run in this process;
* the CLI end to end, and its answers to bad input (exit 2, naming the option).

The Dask cluster runs are in tests/test_studies_dask.py.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from optimizer import study_io, studies
from optimizer.model import Robot
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest
from optimizer.reachable import generate

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ("default", Robot.default(3))
OTHER = ("wide", Robot((1.0, 0.6), (2, 2)))


def _strip(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


def test_rows_carry_the_plans_answer_and_the_generated_goals() -> None:
    tasks = studies.make_tasks([DEFAULT, OTHER], random=4, seed=7)
    assert [t.id for t in tasks][:2] == ["default/r3_000_same", "default/r3_001_opposite"]
    rows = studies.run_study(tasks, workers=0).rows
    assert len(rows) == 8 and len({r["id"] for r in rows}) == 8
    for mech, robot in (DEFAULT, OTHER):
        goals = generate(3, 4, 7, robot=robot)
        mine = [r for r in rows if r["mechanism"] == mech]
        for g, r in zip(goals, mine):
            assert (r["start_1"], r["start_2"], r["start_3"]) == g.start
            assert (r["goal_1"], r["goal_2"], r["goal_3"]) == g.goal
            assert r["kind"] == g.kind and r["n"] == 3
            ref = plan(PlanRequest(start=g.start, goal=g.goal, robot=robot,
                                   samples=101)).to_dict()
            ind = ref["indicators"]
            assert r["status"] == "success" and r["method"] == ref["method"]
            assert r["deviation"] == pytest.approx(ind["deviation"], rel=1e-9, abs=1e-12)
            assert r["reversals"] == ind["reversals"]["phi"] + ind["reversals"]["th1"]
            assert r["d_a"] == pytest.approx(ind["d_a"], rel=1e-9, abs=1e-12)
            assert r["t_p"] == ind["t_p"]
            assert r["sensitivity"] == pytest.approx(ind["sensitivity"], rel=1e-9)
            assert r["terminal_error"] <= 1e-6
            assert r["seconds"] > 0
    # the same starts and inputs drive both mechanisms: same starts, other goals
    a = [r for r in rows if r["mechanism"] == "default"]
    b = [r for r in rows if r["mechanism"] == "wide"]
    assert [r["start_1"] for r in a] == [r["start_1"] for r in b]
    assert [r["goal_3"] for r in a] != [r["goal_3"] for r in b]


def test_a_failed_plan_is_a_row_with_its_status(monkeypatch: pytest.MonkeyPatch) -> None:
    g = generate(3, 2)
    goals = [("outside", (1.7, 0.5, 0.5), (0.3, 0.3, 0.3)),  # th1 beyond pi/2: not in region
             ("opposed", g[1].start, g[1].goal),  # needs phi to reverse
             ("fine", g[0].start, g[0].goal)]
    poly = studies.make_tasks([DEFAULT], goals, options=studies.PlanOptions(method="polynomial"))
    rows = {r["goal"]: r for r in studies.run_study(poly, workers=0).rows}
    assert len(rows) == 3
    for name, task in zip(("outside", "opposed"), poly):
        with pytest.raises(Exception) as info:  # what the library says about this request
            plan(PlanRequest(start=task.start, goal=task.goal, robot=DEFAULT[1],
                             method="polynomial", samples=101))
        assert rows[name]["status"] == getattr(info.value, "code")
        assert rows[name]["detail"] == getattr(info.value, "message")
        assert rows[name]["deviation"] is None and rows[name]["method"] == ""
    assert rows["outside"]["status"] == "invalid_request"
    assert rows["opposed"]["status"] == "infeasible"
    assert rows["fine"]["status"] == "success"
    # a time limit no solver meets: status timeout
    fast = studies.make_tasks([DEFAULT], goals[1:2],
                              options=studies.PlanOptions(time_limit=1e-5))
    assert studies.run_study(fast, workers=0).rows[0]["status"] == "timeout"

    # an exception nobody expected is still a row
    def boom(req: PlanRequest) -> None:
        raise RuntimeError("solver segfault simulated")
    monkeypatch.setattr(studies, "plan", boom)
    rows2 = studies.run_study(poly, workers=0).rows
    # (the start outside the region is refused by the request's own check, before planning)
    assert [r["status"] for r in rows2] == ["invalid_request", "error", "error"]
    assert "RuntimeError: solver segfault simulated" in rows2[1]["detail"]


def test_resume_keeps_written_rows_and_replans_a_cut_line(tmp_path: Path) -> None:
    tasks = studies.make_tasks([DEFAULT], random=40, seed=3)
    whole = studies.run_study(tasks, workers=0, size=8).rows
    out = tmp_path / "rows.csv"

    class Killed(Exception):
        pass

    seen: list[int] = []

    def kill_after_two(rows: list[dict[str, Any]]) -> None:
        seen.append(len(rows))
        if len(seen) == 2:
            raise Killed
    with pytest.raises(Killed):
        studies.run_study(tasks, out=out, workers=0, size=8, on_chunk=kill_after_two)
    header, kept = study_io.read_rows(out)
    assert len(kept) == 16
    # a kill in the middle of a write: a last line without its newline
    text = out.read_text()
    last = text.splitlines()[-1]
    out.write_text(text + last[: len(last) // 2])
    assert len(study_io.read_rows(out)[1]) == 16
    done = studies.run_study(tasks, out=out, workers=0, size=8)
    assert done.skipped == 16 and done.planned == 24
    assert _strip(done.rows) == _strip(whole)
    _, again = study_io.read_rows(out)
    assert _strip(again) == _strip(whole)  # in study order, each id once
    assert [r["seconds"] for r in again[:16]] == [r["seconds"] for r in kept]
    # a complete file: nothing planned
    assert studies.run_study(tasks, out=out, workers=0).planned == 0


def test_csv_and_parquet_hold_the_same_rows(tmp_path: Path) -> None:
    goals = [("outside", (1.7, 0.5, 0.5), (0.3, 0.3, 0.3))] + [
        (g.name, g.start, g.goal) for g in generate(3, 3)]
    tasks = studies.make_tasks([DEFAULT], goals)
    a = studies.run_study(tasks, out=tmp_path / "r.csv", workers=0).rows
    b = studies.run_study(tasks, out=tmp_path / "r.parquet", workers=0).rows
    _, csv_rows = study_io.read_rows(tmp_path / "r.csv")
    _, pq_rows = study_io.read_rows(tmp_path / "r.parquet")
    assert _strip(csv_rows) == _strip(a) and _strip(pq_rows) == _strip(b)
    assert _strip(csv_rows) == _strip(pq_rows)
    assert csv_rows[0]["deviation"] is None and csv_rows[0]["status"] == "invalid_request"
    with open(tmp_path / "r.csv", newline="") as fh:
        assert next(csv.reader(fh)) == study_io.columns(3)
    with pytest.raises(ValueError, match="extension"):
        study_io.output_format(tmp_path / "r.xlsx")


def test_parquet_without_pyarrow_says_what_to_install(monkeypatch: pytest.MonkeyPatch,
                                                      tmp_path: Path) -> None:
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    with pytest.raises(ValueError, match=r"chained-planner\[cluster\]"):
        study_io.output_format(tmp_path / "r.parquet")
    assert study_io.output_format(tmp_path / "r.csv") == "csv"


def test_process_pool_gives_the_rows_of_this_process() -> None:
    tasks = studies.make_tasks([DEFAULT, OTHER], random=20, seed=11)
    here = studies.run_study(tasks, workers=0).rows
    pool = studies.run_study(tasks, workers=2, size=5).rows
    assert _strip(pool) == _strip(here)


def test_chunks_are_large_enough_and_cover_every_task() -> None:
    assert studies.chunk_size(10_000, 2) == 256
    assert studies.chunk_size(1000, 2) == 63
    assert studies.chunk_size(20, 8) == studies.MIN_CHUNK
    tasks = studies.make_tasks([DEFAULT], [("a", (0.5,) * 3, (0.6,) * 3),
                                           ("b", (0.5,) * 3, (0.7,) * 3),
                                           ("c", (0.5,) * 3, (0.8,) * 3)])
    parts = studies.chunks(tasks, 2)
    assert [len(p) for p in parts] == [2, 1] and sum(parts, ()) == tuple(tasks)


def test_input_files(tmp_path: Path) -> None:
    (tmp_path / "g.json").write_text(json.dumps(
        {"goals": [{"start": [0.5, 0.5, 0.5], "goal": [0.6, 0.6, 0.6], "name": "x"},
                   {"start": [0.5, 0.5, 0.5, 0.5], "goal": [0.6, 0.6, 0.6, 0.6]}]}))
    goals = study_io.read_goals(tmp_path / "g.json")
    assert goals[0] == ("x", (0.5, 0.5, 0.5), (0.6, 0.6, 0.6)) and goals[1][0] == "g00001"
    (tmp_path / "g.csv").write_text("name,start_1,start_2,start_3,goal_1,goal_2,goal_3\n"
                                    "p,0.1,0.2,0.3,0.4,0.5,0.6\n")
    assert study_io.read_goals(tmp_path / "g.csv") == [("p", (0.1, 0.2, 0.3), (0.4, 0.5, 0.6))]
    (tmp_path / "bad.json").write_text(json.dumps([{"start": [0.5, 0.5], "goal": [0.5]}]))
    with pytest.raises(ValueError, match="goal 0"):
        study_io.read_goals(tmp_path / "bad.json")
    (tmp_path / "m.json").write_text(json.dumps(
        [{"gains": [0.9, 0.7], "exponents": [2, 3]},
         {"name": "four", "gains": [0.9, 0.9, 0.7], "exponents": [2, 2, 3]}]))
    mechs = study_io.read_mechanisms(tmp_path / "m.json")
    assert [m[0] for m in mechs] == ["K0.9-0.7_m2-3", "four"] and mechs[1][1].n == 4
    # each mechanism plans the goals of its own n
    tasks = studies.make_tasks(mechs, goals)
    assert [t.id for t in tasks] == ["K0.9-0.7_m2-3/x", "four/g00001"]
    (tmp_path / "m_bad.json").write_text(json.dumps({"gains": [0.9, -1.0], "exponents": [2, 3]}))
    with pytest.raises(ValueError, match=r"robot.gains\[1\]"):
        study_io.read_mechanisms(tmp_path / "m_bad.json")


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "optimizer", "study", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=600,
                          env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})


def test_cli_end_to_end(tmp_path: Path) -> None:
    (tmp_path / "robots.json").write_text(json.dumps(
        {"mechanisms": [{"name": "proto", "gains": [0.88658, 0.7115], "exponents": [2, 3]},
                        {"name": "wide", "gains": [1.0, 0.6], "exponents": [2, 2]}]}))
    done = _cli("--random", "12", "--seed", "5", "--robot", "robots.json", "--workers", "2",
                "--out", "rows.csv", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["rows"] == 24 and report["planned"] == 24
    assert "study [" not in done.stderr  # no progress bar when stderr is not a terminal
    _, rows = study_io.read_rows(tmp_path / "rows.csv")
    assert [r["id"] for r in rows[:2]] == ["proto/r3_000_same", "proto/r3_001_opposite"]
    lib = studies.run_study(studies.make_tasks(
        study_io.read_mechanisms(tmp_path / "robots.json"), random=12, seed=5), workers=0).rows
    assert _strip(rows) == _strip(lib)
    for m in report["mechanisms"]:
        mine = [r for r in rows if r["mechanism"] == m["mechanism"]]
        assert m["success"] == sum(r["status"] == "success" for r in mine)
    again = _cli("--random", "12", "--seed", "5", "--robot", "robots.json", "--out", "rows.csv",
                 "--workers", "0", cwd=tmp_path)
    assert json.loads(again.stdout)["planned"] == 0


@pytest.mark.parametrize("args, needle", [
    (["--random", "0"], "--random 0"),
    (["--random", "3", "--out", "x.txt"], "extension"),
    (["--random", "3", "--time-limit", "-1"], "time_limit"),
    (["--goals", "missing.json"], "cannot read missing.json"),
])
def test_cli_bad_input_exits_2_naming_it(tmp_path: Path, args: list[str], needle: str,
                                         capsys: pytest.CaptureFixture[str],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """The CLI's ``main`` in this process (a process per case imported the library again:
    about 5 s each at load 8); ``test_cli_end_to_end`` runs it as ``python -m optimizer``."""
    from optimizer.__main__ import main
    if "--out" not in args:
        args = args + ["--out", "x.csv"]
    monkeypatch.chdir(tmp_path)
    try:
        code = main(["study", *args])
    except SystemExit as exc:  # argparse refusing the arguments
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert code == 2, err
    assert needle in err and "Traceback" not in err


def test_study_figure_maps_success_and_deviation(tmp_path: Path) -> None:
    from service import figures_study

    goals = [("outside", (1.7, 0.5, 0.5), (0.3, 0.3, 0.3))] + [
        (g.name, g.start, g.goal) for g in generate(3, 5)]
    out = tmp_path / "rows.csv"
    studies.run_study(studies.make_tasks([DEFAULT, OTHER], goals), out=out, workers=0)
    _, rows = study_io.read_rows(out)
    svg = figures_study.study_map(rows, "svg", x="goal_2", y="goal_3").decode()
    for mech in ("default", "wide"):
        mine = [r for r in rows if r["mechanism"] == mech]
        ok = sum(r["status"] == "success" for r in mine)
        assert f"{mech}: {ok} of {len(mine)} reached" in svg
    assert "invalid_request" in svg and "deviation (\u00b0)" in svg
    with pytest.raises(ValueError, match="column 'status'"):
        figures_study.study_map(rows, "png", x="status")
    with pytest.raises(ValueError, match="no rows"):
        figures_study.study_map(rows, "png", mechanism="nope")
    png = tmp_path / "map.png"
    assert figures_study.main([str(out), "-o", str(png), "--mechanism", "wide"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert figures_study.main([str(tmp_path / "missing.csv"), "-o", str(png)]) == 2


def test_study_scaling_benchmark_runs(tmp_path: Path) -> None:
    """The benchmark's command on 20 goals: it runs and its runs agree (no speed asserted)."""
    from bench import study_scaling

    out = tmp_path / "scaling.json"
    assert study_scaling.main(["--goals", "20", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["rows_equal"] is True
    assert set(data["runs"]) == {"1", "2", "2 cold"}
    for run in data["runs"].values():
        assert run["success"] == 20 and 0 < run["busy_share"] <= 1.0


def test_progress_bar_only_on_a_terminal() -> None:
    import io

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True
    tty, pipe = Tty(), io.StringIO()
    tasks = studies.make_tasks([DEFAULT], [("a", (0.5, 0.5, 0.5), (0.6, 0.55, 0.5)),
                                           ("b", (1.7, 0.5, 0.5), (0.3, 0.3, 0.3))])
    studies.run_study(tasks, workers=0, size=1, progress=tty)
    studies.run_study(tasks, workers=0, size=1, progress=pipe)
    assert pipe.getvalue() == ""
    text = tty.getvalue()
    assert "2/2 (100 %) 1 failed" in text and text.endswith("\n")


def test_layering_of_the_study_modules() -> None:
    """studies.py is the library's top layer: only the CLI imports it; the study modules and
    the goal generator import neither the web nor the benchmark."""
    import ast

    pkg = ROOT / "optimizer"
    for path in pkg.rglob("*.py"):
        tree = ast.parse(path.read_text())
        names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {(n.module or "") + ("." + a.name if n.level else "")
                  for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
        if path.name not in ("studies.py", "__main__.py"):
            assert not any("studies" in x.split(".") for x in names), path
        if path.name in ("studies.py", "study_io.py", "reachable.py"):
            assert not any(x.split(".")[0] in ("bench", "service") for x in names), path
