"""Figures of plans, sweeps and robustness runs (service.figures) and their CLI."""

from __future__ import annotations

import copy
import json
import math
import os
import struct
import subprocess
import sys
import threading
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from numpy import deg2rad

from optimizer import analysis
from optimizer.planner.plan import plan as make_plan
from optimizer.problem import PlanRequest
from optimizer.steering import ConstraintPoint
from service import figures

REPO = Path(__file__).resolve().parents[1]
VENV_PYTHON = REPO / ".venv" / "bin" / "python"
PYTHON = str(VENV_PYTHON) if VENV_PYTHON.exists() else sys.executable
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SVG_NS = "{http://www.w3.org/2000/svg}"


# ------------------------------------------------------------------ data (real, from the library)
@pytest.fixture(scope="module")
def request_3() -> PlanRequest:
    return PlanRequest(start=tuple(deg2rad([10, 10, 10])), goal=tuple(deg2rad([30, 30, 30])),
                       method="polynomial")


@pytest.fixture(scope="module")
def plan_obj(request_3):
    return make_plan(request_3)


@pytest.fixture(scope="module")
def plan_dict(plan_obj) -> dict:
    # through JSON, exactly as the service returns it and the CLI reads it
    return json.loads(json.dumps(plan_obj.to_dict()))


@pytest.fixture(scope="module")
def cp_plan_dict() -> dict:
    """Figs 4-5 set-up: T = 10 s, one constraint point on z2 at t = 5 s."""
    req = PlanRequest(start=tuple(deg2rad([1, 1, 1])), goal=tuple(deg2rad([30, 30, 30])),
                      duration=10.0, method="polynomial",
                      constraint_points=(ConstraintPoint(5.0, 2, -0.3),))
    return json.loads(json.dumps(make_plan(req).to_dict()))


CP_LIST = [{"time": 5.0, "state": 2, "value": -0.3}]


@pytest.fixture(scope="module")
def sweep_dict(request_3) -> dict:
    return json.loads(json.dumps(analysis.sweep(request_3, deg2rad(30), deg2rad(40), 41)))


@pytest.fixture(scope="module")
def robustness_data(request_3, plan_obj, plan_dict) -> dict:
    starts = analysis.perturbed_starts(request_3.start, 5, deg2rad(0.5), seed=7)
    rob = analysis.robustness(plan_obj, starts, "v", request_3.goal)
    return {"plan": plan_dict, "robustness": json.loads(json.dumps(rob))}


@pytest.fixture(scope="module")
def pareto_dict() -> dict:
    """A trade-off answer (issue 26): several members on this goal."""
    req = PlanRequest(start=tuple(deg2rad([50, 20, 30])), goal=tuple(deg2rad([30, 40, 50])),
                      pareto=True, samples=21, time_limit=120.0)
    return json.loads(json.dumps(make_plan(req).to_dict()))


@pytest.fixture(scope="module")
def all_inputs(plan_dict, cp_plan_dict, sweep_dict, robustness_data, pareto_dict) -> dict:
    return {
        "joint_angles": plan_dict,
        "chained_state": {"plan": cp_plan_dict, "constraint_points": CP_LIST},
        "robustness": robustness_data,
        "sweep": sweep_dict,
        "pareto": pareto_dict,
    }


# ------------------------------------------------------------------ helpers
def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == PNG_MAGIC, "not a PNG"
    length, ctype = struct.unpack(">I4s", data[8:16])
    assert ctype == b"IHDR" and length == 13
    return struct.unpack(">II", data[16:24])


def svg_texts(data: bytes) -> list[str]:
    root = ET.fromstring(data)
    assert root.tag == SVG_NS + "svg"
    return ["".join(el.itertext()).strip() for el in root.iter(SVG_NS + "text")]


def joined(texts: list[str]) -> str:
    return "\n".join(texts)


#: Text every figure's SVG must carry (axis labels with units, legend entries, titles).
EXPECTED = {
    "joint_angles": ["joint angle [deg]", "time t [s]", "phi [deg]", "polynomial plan",
                     "dphi = 34.", "d_a = ", "t_p = 1", "straight reference"],
    "chained_state": ["z2 [-]", "z3 [-]", "z4 = th3 [rad]", "time t [s]", "constraint point",
                      "no inverse transform", "Chained-form state"],
    "robustness": ["joint angle [deg]", "time t [s]", "nominal plan", "perturbed start",
                   "v-replay", "5 runs", "th1", "th3"],
    "sweep": ["d_a [deg]", "t_p [-]", "||J_R(T)||_F [-]", "dphi [deg]",
              "singularity-free", "33.201"],
    "pareto": ["actuator reversals (phi and th1) [-]",
               "deviation from the straight segment [deg]", "main plan", "non-dominated"],
}


# ------------------------------------------------------------------ every figure, both formats
@pytest.mark.parametrize("kind", figures.KINDS)
def test_png(kind, all_inputs, tmp_path):
    data, media = figures.render(kind, all_inputs[kind], "png")
    assert media == "image/png"
    w, h = png_size(data)
    assert 800 <= w <= 2000 and 400 <= h <= 2000, (w, h)
    assert len(data) > 10_000      # something was drawn
    (tmp_path / f"{kind}.png").write_bytes(data)


@pytest.mark.parametrize("kind", figures.KINDS)
def test_svg(kind, all_inputs):
    data, media = figures.render(kind, all_inputs[kind], "svg")
    assert media == "image/svg+xml"
    text = joined(svg_texts(data))
    for want in EXPECTED[kind]:
        assert want in text, f"{kind}: {want!r} not in the SVG text"
    # angles are shown in degrees: no radian-scale title values
    assert "nan" not in text.lower()


def test_direct_functions_match_render(plan_dict, sweep_dict, robustness_data):
    assert png_size(figures.joint_angles(plan_dict)) == png_size(
        figures.render("joint_angles", plan_dict, "png")[0])
    assert figures.chained_state(plan_dict, "svg").startswith(b"<?xml")
    assert figures.sweep(sweep_dict, fmt="SVG").lstrip().startswith(b"<?xml")
    out = figures.robustness(robustness_data["plan"], robustness_data["robustness"], "png")
    assert out[:8] == PNG_MAGIC


def test_svg_is_deterministic(plan_dict):
    a = figures.joint_angles(plan_dict, "svg")
    b = figures.joint_angles(plan_dict, "svg")
    assert a == b


# ------------------------------------------------------------------ content checks
def test_joint_angles_in_degrees(plan_dict):
    """Tick labels span the plan's degree range (10 .. ~42 deg), not radians (0.17 .. 0.74)."""
    texts = svg_texts(figures.joint_angles(plan_dict, "svg"))
    nums = []
    for t in texts:
        try:
            nums.append(float(t.replace("\u2212", "-")))
        except ValueError:
            pass
    assert max(nums) >= 40
    d_a_deg = math.degrees(plan_dict["indicators"]["d_a"])
    assert f"d_a = {d_a_deg:.3f}" in joined(texts)


def test_chained_state_constraint_points_argument(plan_dict):
    text = joined(svg_texts(figures.chained_state(
        plan_dict, "svg", constraint_points=[{"time": 0.5, "state": 3, "value": 0.6}])))
    assert "constraint point" in text
    text = joined(svg_texts(figures.chained_state(plan_dict, "svg")))
    assert "constraint point" not in text
    assert "K3 = 0.7115" in text          # the z3 band bound
    # dataclass constraint points work too
    figures.chained_state(plan_dict, "png", constraint_points=[ConstraintPoint(0.5, 2, -0.3)])
    with pytest.raises(ValueError):
        figures.chained_state(plan_dict, "png",
                              constraint_points=[{"time": 0.5, "state": 9, "value": 0.0}])


def test_robustness_singular_run(robustness_data):
    data = copy.deepcopy(robustness_data)
    run = data["robustness"]["runs"][0]
    run["singular"], run["singular_time"] = True, 0.4
    text = joined(svg_texts(figures.render("robustness", data, "svg")[0]))
    assert "singular run" in text and "1 singular" in text


def test_sweep_without_intervals(request_3):
    sw = analysis.sweep(request_3, deg2rad(30), deg2rad(40), 21, intervals=False)
    text = joined(svg_texts(figures.sweep(sw, "svg")))
    assert "singularity-free dphi: [" in text     # taken from the feasible flags
    # nothing feasible in range
    sw2 = analysis.sweep(request_3, deg2rad(20), deg2rad(25), 6)
    text2 = joined(svg_texts(figures.sweep(sw2, "svg")))
    assert "no singularity-free dphi in this range" in text2


def synthetic_plan(n: int, segments: int = 2, samples: int = 301) -> dict:
    """A plan-shaped dict for an n-joint arm with a reversing phi (shape checks only)."""
    t = np.linspace(0.0, 2.0, samples)
    q = np.empty((samples, n + 1))
    q[:, 0] = 0.4 * np.sin(np.pi * t)
    for j in range(1, n + 1):
        q[:, j] = 0.2 + 0.3 * t / 2 + 0.05 * j * np.sin(np.pi * t / 2)
    z = np.column_stack([q[:, 0]] + [-0.3 + 0.1 * np.sin(t + j) for j in range(n)])
    br = np.linspace(0.0, 2.0, segments + 1)
    return {
        "status": "success", "method": "penalty",
        "robot": {"n": n, "gains": [0.88658] * (n - 2) + [0.7115], "exponents": [2] * (n - 2) + [3],
                  "assumed_constants": True},
        "phi_change": 0.0, "b0": None, "duration": 2.0, "feasible_phi_changes": [],
        "coefficients": {"segments": [{"t_start": a, "t_end": b, "v1": [0.0], "v2": [0.0]}
                                      for a, b in zip(br[:-1], br[1:])]},
        "indicators": {"d_a": 0.1, "t_p": 0},
        "path": {"t": t.tolist(), "q": q.tolist(), "z": z.tolist()},
    }


@pytest.mark.parametrize("n", [4, 8])
def test_n_joints(n):
    p = synthetic_plan(n)
    text = joined(svg_texts(figures.joint_angles(p, "svg")))
    assert f"th{n}" in text and "penalty plan" in text
    text = joined(svg_texts(figures.chained_state(p, "svg")))
    assert f"z{n + 1} = th{n} [rad]" in text and f"K{n} = 0.7115" in text
    w, h = png_size(figures.chained_state(p, "png"))
    assert w >= 800 and h >= 150 * n


# ------------------------------------------------------------------ errors
def test_render_errors(plan_dict, sweep_dict):
    with pytest.raises(ValueError, match="kind"):
        figures.render("histogram", plan_dict, "png")
    with pytest.raises(ValueError, match="format"):
        figures.render("joint_angles", plan_dict, "jpeg")
    with pytest.raises(ValueError, match="format"):
        figures.joint_angles(plan_dict, "pdf")
    with pytest.raises(ValueError):
        figures.render("sweep", plan_dict, "png")         # a plan is not a sweep
    with pytest.raises(ValueError):
        figures.render("joint_angles", sweep_dict, "png")  # nor a sweep a plan
    with pytest.raises(ValueError, match="robustness"):
        figures.render("robustness", plan_dict, "svg")
    with pytest.raises(ValueError, match="status"):
        figures.render("joint_angles", {"status": "infeasible", "path": {}}, "png")
    bad = copy.deepcopy(plan_dict)
    bad["path"]["q"] = bad["path"]["q"][:-1]
    with pytest.raises(ValueError, match="rows"):
        figures.joint_angles(bad)


def test_threads(plan_dict, sweep_dict):
    """Concurrent renders (the service's thread pool) each get complete, correct output."""
    out: dict[int, bytes] = {}
    errors: list[BaseException] = []

    def work(i: int) -> None:
        try:
            if i % 2:
                out[i] = figures.render("sweep", sweep_dict, "svg")[0]
            else:
                out[i] = figures.render("joint_angles", plan_dict, "svg")[0]
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors
    for i, data in out.items():
        want = "||J_R(T)||_F [-]" if i % 2 else "joint angle [deg]"
        assert want in joined(svg_texts(data))


# ------------------------------------------------------------------ CLI
def run_cli(*args: str, stdin: bytes | None = None) -> subprocess.CompletedProcess:
    """``python -m service.figures_cli`` as a process (its entry point, standard input and
    output as bytes)."""
    env = dict(os.environ, MPLBACKEND="Agg")
    return subprocess.run([PYTHON, "-m", "service.figures_cli", *args], cwd=REPO, input=stdin,
                          capture_output=True, timeout=60, env=env)


def cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """The CLI's ``main`` in this process (each process would import numpy and matplotlib
    again: 1-2 s of CPU a call): its exit status (argparse's exit included) and standard
    error."""
    from service import figures_cli
    try:
        code = figures_cli.main(list(args))
    except SystemExit as exc:  # argparse refusing the arguments
        code = int(exc.code or 0)
    return code, capsys.readouterr().err


def test_cli_end_to_end(tmp_path, all_inputs, capsys):
    files = {}
    for kind, data in all_inputs.items():
        files[kind] = tmp_path / f"{kind}.json"
        files[kind].write_text(json.dumps(data))
    # png, explicit format
    out = tmp_path / "ja.png"
    code, err = cli(capsys, "joint_angles", str(files["joint_angles"]), "--format", "png", "-o",
                    str(out))
    assert code == 0 and f"wrote {out} (image/png" in err, err
    assert png_size(out.read_bytes())[0] >= 800
    # svg, format from the extension; the robustness wrapper
    out = tmp_path / "rob.svg"
    code, err = cli(capsys, "robustness", str(files["robustness"]), "-o", str(out))
    assert code == 0, err
    assert "joint angle [deg]" in joined(svg_texts(out.read_bytes()))
    # default output name, next to the input
    code, err = cli(capsys, "sweep", str(files["sweep"]), "--format", "svg")
    assert code == 0, err
    assert "dphi [deg]" in joined(svg_texts((tmp_path / "sweep.sweep.svg").read_bytes()))
    # stdin -> stdout, through the module's entry point in a process of its own
    r = run_cli("chained_state", "-", "--format", "png", "-o", "-",
                stdin=files["chained_state"].read_bytes())
    assert r.returncode == 0, r.stderr.decode()
    assert r.stdout[:8] == PNG_MAGIC


def test_cli_errors(tmp_path, sweep_dict, capsys):
    f = tmp_path / "sweep.json"
    f.write_text(json.dumps(sweep_dict))
    code, err = cli(capsys, "joint_angles", str(f), "-o", str(tmp_path / "x.png"))
    assert code == 2 and "error" in err
    assert not (tmp_path / "x.png").exists()
    code, err = cli(capsys, "pie", str(f))
    assert code == 2 and "invalid choice: 'pie'" in err
    code, err = cli(capsys, "sweep", str(tmp_path / "missing.json"))
    assert code == 2 and "cannot read" in err
    (tmp_path / "bad.json").write_text("{")
    code, err = cli(capsys, "sweep", str(tmp_path / "bad.json"))
    assert code == 2 and "not valid JSON" in err
