"""The compiled cascade quadrature of piecewise-constant rates (``optimizer.cascade_kernel``).

Checked against INDEPENDENT values: scipy's DOP853 (rtol 1e-12) on the tests' own model
(``tests/reference.py``, restarted at every break), for random schedules of 3 to 8 joints,
starts near the region's edges included. The numpy code of the same algorithm is the second
oracle: both must give the same panels, evaluations, singularity and (to rounding) states,
mesh, energy and error estimate. A test forces the numpy fallback (compiled functions off).
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from optimizer import cascade_kernel, native
from optimizer.actuation import ActuatorSchedule
from optimizer.cascade import integrate_cascade
from optimizer.integration import CASCADE_NAME, DOP853_NAME, HALF_PI
from optimizer.model import Robot

from test_verify_cascade import reference

needs_cc = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                              reason="no C compiler")


@pytest.fixture(scope="module")
def kernel_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One cache for the module: the kernel is compiled once (a second or two)."""
    return tmp_path_factory.mktemp("cascade_kernel")


@pytest.fixture
def compiled(kernel_cache: Path):
    """Compiled functions on, the kernel built and loaded; off again afterwards."""
    if native.configure(kernel_cache) is None:
        pytest.skip("no C compiler")
    assert cascade_kernel.prepare(wait=True), "the kernel did not build"
    yield
    native.configure(None)


def schedule(rng: np.random.Generator, pieces: int, scale: float = 1.0) -> ActuatorSchedule:
    widths = rng.uniform(0.05, 0.5, pieces)
    rates = scale * rng.uniform(-0.8, 0.8, (pieces, 2))
    return ActuatorSchedule(breaks=np.concatenate([[0.0], np.cumsum(widths)]), rates=rates)


def start(rng: np.random.Generator, n: int, edge: str | None = None) -> np.ndarray:
    """A start inside the region; ``edge``: th1 (which drives every other joint) 1e-4 rad
    from 0 or from pi/2."""
    q0 = np.concatenate([[rng.uniform(-1.0, 1.0)], rng.uniform(0.3, 1.2, n)])
    if edge == "low":
        q0[1] = 1e-4
    elif edge == "high":
        q0[1] = HALF_PI - 1e-4
    return q0


def both(robot: Robot, sched: ActuatorSchedule, q0: np.ndarray, t: np.ndarray, **kw):
    fast = integrate_cascade(robot, sched.u, q0, sched.duration, t, sched.breaks,
                             constant_pieces=True, **kw)
    slow = integrate_cascade(robot, sched.u, q0, sched.duration, t, sched.breaks,
                             constant_pieces=True, compiled=False, **kw)
    return fast, slow


def assert_same(fast, slow, atol: float = 1e-12) -> None:
    """The compiled and the numpy code: the same run, to rounding."""
    assert fast.integrator == slow.integrator and fast.success == slow.success
    assert fast.panels == slow.panels and fast.evaluations == slow.evaluations
    assert fast.singular == slow.singular
    if slow.singular_time is None:
        assert fast.singular_time is None
    else:
        assert fast.singular_time == pytest.approx(slow.singular_time, abs=1e-12)
    np.testing.assert_allclose(fast.q, slow.q, rtol=0, atol=atol)
    np.testing.assert_allclose(fast.final, slow.final, rtol=0, atol=atol)
    assert fast.energy == pytest.approx(slow.energy, rel=1e-12)
    if slow.mesh_t is not None:
        np.testing.assert_allclose(fast.mesh_t, slow.mesh_t, rtol=0, atol=1e-14)
        np.testing.assert_allclose(fast.mesh_q, slow.mesh_q, rtol=0, atol=atol)
    if slow.error_estimate is not None:
        assert fast.error_estimate == pytest.approx(slow.error_estimate, rel=0.05, abs=1e-15)
    assert fast.message.split("estimate")[0] == slow.message.split("estimate")[0]


@needs_cc
@pytest.mark.parametrize("n", [3, 4, 5, 6, 7, 8])
@pytest.mark.parametrize("edge", [None, "low", "high"])
def test_random_schedules_match_scipy_and_the_numpy_code(compiled, n, edge):
    rng = np.random.default_rng(1000 * n + {None: 0, "low": 1, "high": 2}[edge])
    robot = Robot.default(n)
    for _ in range(3):
        sched = schedule(rng, int(rng.integers(1, 9)))
        q0 = start(rng, n, edge)
        T = sched.duration
        t = np.unique(np.concatenate([np.linspace(0.0, T, 57), sched.breaks,
                                      rng.uniform(0.0, T, 20)]))
        fast, slow = both(robot, sched, q0, t, nodes=12, initial_panels=1)
        assert fast.integrator == CASCADE_NAME, fast.message
        assert fast.error_estimate <= 1e-11
        final, samples, energy = reference(sched.u_scalar, q0, T, robot.gains, robot.exponents,
                                           t, sched.breaks)
        np.testing.assert_allclose(fast.q, samples, rtol=0, atol=1e-10)
        np.testing.assert_allclose(fast.final, final, rtol=0, atol=1e-10)
        assert fast.energy == pytest.approx(energy, rel=1e-10)
        # the singularity test sees what the reference sees at the samples
        inside = np.all((samples[:, 1:n] > 1e-9) & (samples[:, 1:n] < HALF_PI - 1e-9))
        if not inside:
            assert fast.singular
        assert_same(fast, slow)


@needs_cc
@pytest.mark.parametrize("nodes", [8, 12])
def test_refinement_is_the_same_and_correct(compiled, nodes):
    """Long pieces and fast rates: the joints' integrands need many panels (more than the
    kernel's first guess of its output size, 4 per initial panel + 64, with 8 nodes), and
    both codes cut the same panels."""
    robot = Robot.default(4)
    sched = ActuatorSchedule(breaks=np.array([0.0, 3.0, 7.0]),
                             rates=np.array([[2.5, 0.9], [-2.0, -0.8]]))
    q0 = np.array([0.1, 0.4, 0.7, 0.9, 0.5])
    t = np.linspace(0.0, sched.duration, 41)
    fast, slow = both(robot, sched, q0, t, nodes=nodes, initial_panels=1)
    assert fast.panels > 4 * 2 + 64 if nodes == 8 else fast.panels > 2
    assert "0 refinements" not in fast.message
    assert_same(fast, slow, atol=1e-11)
    final, samples, _ = reference(sched.u_scalar, q0, sched.duration, robot.gains,
                                  robot.exponents, t, sched.breaks)
    np.testing.assert_allclose(fast.q, samples, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.final, final, rtol=0, atol=1e-9)


@needs_cc
def test_several_initial_panels_and_widths(compiled):
    rng = np.random.default_rng(7)
    robot = Robot.default(5)
    sched = schedule(rng, 5)
    q0 = start(rng, 5)
    t = np.linspace(0.0, sched.duration, 33)
    for kw in ({"initial_panels": 3}, {"initial_width": 1.0 / 6.0}, {"split": 2},
               {"nodes": 32, "initial_panels": 3}):
        fast, slow = both(robot, sched, q0, t, **kw)
        assert_same(fast, slow)


@needs_cc
def test_singular_path_is_flagged_at_the_same_time(compiled):
    """th1 runs through 0 (u2 < 0 from 0.2 rad): both codes flag it, at the same first node."""
    robot = Robot.default(3)
    sched = ActuatorSchedule(breaks=np.array([0.0, 0.5, 1.0]),
                             rates=np.array([[0.3, -0.1], [0.3, -0.5]]))
    q0 = np.array([0.0, 0.2, 0.5, 0.6])
    t = np.linspace(0.0, 1.0, 11)
    fast, slow = both(robot, sched, q0, t, nodes=12, initial_panels=1)
    assert fast.singular and fast.success
    # th1(t) = 0.2 - 0.05 - 0.5 (t - 0.5) reaches 0 at t = 0.8
    assert 0.8 <= fast.singular_time <= 0.85
    assert_same(fast, slow)


@needs_cc
def test_estimate_above_accept_falls_back_to_dop853(compiled):
    rng = np.random.default_rng(3)
    robot = Robot.default(3)
    sched = schedule(rng, 3)
    q0 = start(rng, 3)
    t = np.linspace(0.0, sched.duration, 9)
    kw = dict(nodes=12, initial_panels=1, tol=1e-30, accept=1e-30, max_rounds=1,
              fallback=sched.u_scalar)
    fast, slow = both(robot, sched, q0, t, **kw)
    assert fast.integrator == slow.integrator == DOP853_NAME
    assert "not accepted" in fast.message
    assert fast.message.split("estimate")[0] == slow.message.split("estimate")[0]
    np.testing.assert_allclose(fast.final, slow.final, rtol=0, atol=1e-10)


@needs_cc
def test_non_finite_states_and_rates_are_reported_as_by_the_numpy_code(compiled):
    robot = Robot.default(3)
    q0 = np.array([0.0, 0.5, 0.5, 0.5])
    t = np.linspace(0.0, 1.0, 5)
    huge = ActuatorSchedule(breaks=np.array([0.0, 1.0]), rates=np.array([[1e300, 1e300]]))
    fast, slow = both(robot, huge, q0, t, nodes=12, initial_panels=1)
    assert not fast.success and fast.message == slow.message == "a state is not finite"
    bad = ActuatorSchedule(breaks=np.array([0.0, 0.5, 1.0]),
                           rates=np.array([[0.1, 0.1], [math.nan, 0.1]]))
    fast, slow = both(robot, bad, q0, t, nodes=12, initial_panels=1)
    assert not fast.success and fast.singular and fast.message == slow.message
    assert fast.singular_time == slow.singular_time


@needs_cc
def test_samples_on_nodes_and_panel_ends(compiled):
    """Samples exactly on a panel's end or a node: the barycentric formula is not finite
    there, and both codes take the value at the point."""
    robot = Robot.default(3)
    sched = ActuatorSchedule(breaks=np.array([0.0, 0.5, 1.25]),
                             rates=np.array([[0.4, 0.2], [-0.3, 0.1]]))
    q0 = np.array([0.0, 0.5, 0.5, 0.5])
    first = integrate_cascade(robot, sched.u, q0, 1.25, np.array([0.3]), sched.breaks,
                              nodes=12, initial_panels=1, constant_pieces=True)
    t = first.mesh_t
    fast, slow = both(robot, sched, q0, t, nodes=12, initial_panels=1)
    assert np.all(np.isfinite(fast.q))
    np.testing.assert_allclose(fast.q, fast.mesh_q, rtol=0, atol=1e-15)
    assert_same(fast, slow)


def test_fallback_without_compiled_functions(tmp_path):
    """Compiled functions off (the default), or no compiler: the numpy code answers, the same
    run as when the kernel is asked for."""
    native.configure(None)
    assert not cascade_kernel.ready() and not cascade_kernel.prepare(wait=True)
    assert native.configure(tmp_path, compiler="no-such-compiler-h24c") is None
    assert not cascade_kernel.ready()
    rng = np.random.default_rng(11)
    robot = Robot.default(4)
    sched = schedule(rng, 4)
    q0 = start(rng, 4)
    t = np.linspace(0.0, sched.duration, 21)
    fast, slow = both(robot, sched, q0, t, nodes=12, initial_panels=1)
    np.testing.assert_array_equal(fast.q, slow.q)
    assert fast.message == slow.message
    final, _, _ = reference(sched.u_scalar, q0, sched.duration, robot.gains, robot.exponents,
                            t, sched.breaks)
    np.testing.assert_allclose(fast.final, final, rtol=0, atol=1e-10)


@needs_cc
def test_a_failed_build_falls_back(tmp_path, monkeypatch):
    """A source the compiler rejects: no library, the numpy code answers."""
    monkeypatch.setattr(cascade_kernel, "source", lambda: "this is not C;\n")
    assert native.configure(tmp_path) is not None
    try:
        assert not cascade_kernel.prepare(wait=True)
        assert list(tmp_path.glob("*.failed"))
        robot = Robot.default(3)
        sched = ActuatorSchedule(breaks=np.array([0.0, 1.0]), rates=np.array([[0.2, 0.1]]))
        rep = integrate_cascade(robot, sched.u, np.array([0.0, 0.5, 0.5, 0.5]), 1.0,
                                np.array([0.5, 1.0]), sched.breaks, nodes=12,
                                initial_panels=1, constant_pieces=True)
        assert rep.success and rep.integrator == CASCADE_NAME
    finally:
        native.configure(None)


@needs_cc
def test_the_quadrature_builds_nothing_and_finds_a_prepared_kernel(tmp_path, monkeypatch):
    """A plan never starts a compiler: the quadrature only looks in the cache, and only in a
    process that called ``prepare`` (its numbers differ from numpy's in the last bits: a
    process opts in). A library prepared there is found again under a new configuration."""
    robot = Robot.default(3)
    sched = ActuatorSchedule(breaks=np.array([0.0, 0.4, 1.0]),
                             rates=np.array([[0.2, 0.1], [-0.3, 0.2]]))
    q0 = np.array([0.0, 0.5, 0.5, 0.5])
    t = np.linspace(0.0, 1.0, 7)
    try:
        assert native.configure(tmp_path) is not None
        rep = integrate_cascade(robot, sched.u, q0, 1.0, t, sched.breaks, nodes=12,
                                initial_panels=1, constant_pieces=True)
        assert rep.success and not cascade_kernel.ready()
        assert not list(tmp_path.iterdir())    # no source, no build started
        assert cascade_kernel.prepare(wait=True)
        native.configure(tmp_path)              # a new configuration: looked up again
        assert cascade_kernel.ready()
        fast, slow = both(robot, sched, q0, t, nodes=12, initial_panels=1)
        assert_same(fast, slow)
        # another process that did not prepare it: the numpy code, the library in the cache
        monkeypatch.setattr(cascade_kernel, "_state", cascade_kernel._Loaded())
        native.configure(tmp_path)
        assert not cascade_kernel.ready() and list(tmp_path.glob("*.so"))
        plain = integrate_cascade(robot, sched.u, q0, 1.0, t, sched.breaks, nodes=12,
                                  initial_panels=1, constant_pieces=True)
        np.testing.assert_array_equal(plain.q, slow.q)
    finally:
        native.configure(None)
        native._builds.clear()


class SmoothInputs:
    """Inputs smooth between breaks (a sine on each piece, jumps at the breaks), with an
    optional steep start ``s / sqrt(t + eps)`` in u2 (a singularity just before t = 0)."""

    def __init__(self, rng: np.random.Generator, pieces: int, steep: float = 0.0,
                 eps: float = 1e-4) -> None:
        self.breaks = np.concatenate([[0.0], np.cumsum(rng.uniform(0.1, 0.5, pieces))])
        self.coef = rng.uniform(-0.6, 0.6, (pieces, 2, 3))
        self.steep, self.eps = steep, eps

    def u(self, t: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, float))
        k = np.clip(np.searchsorted(self.breaks, t, side="right") - 1, 0, self.breaks.size - 2)
        c = self.coef[k]                                        # (N, 2, 3)
        out = c[:, :, 0] + c[:, :, 1] * np.sin(3.0 * t[:, None] + c[:, :, 2])
        out[:, 1] += self.steep / np.sqrt(t + self.eps)
        return out

    def u_scalar(self, t: float, _q=None) -> np.ndarray:
        return self.u(np.array([t]))[0]


@pytest.fixture
def spy(monkeypatch):
    """Counts the compiled general steps that answered."""
    used = {"pass": 0, "outputs": 0}
    real_pass, real_outputs = cascade_kernel.general_pass, cascade_kernel.general_outputs

    def counting_pass(*a, **k):
        out = real_pass(*a, **k)
        used["pass"] += out is not None
        return out

    def counting_outputs(*a, **k):
        out = real_outputs(*a, **k)
        used["outputs"] += out is not None
        return out
    monkeypatch.setattr(cascade_kernel, "general_pass", counting_pass)
    monkeypatch.setattr(cascade_kernel, "general_outputs", counting_outputs)
    return used


def general_both(robot: Robot, inputs: SmoothInputs, q0: np.ndarray, t: np.ndarray, **kw):
    T = float(inputs.breaks[-1])
    fast = integrate_cascade(robot, inputs.u, q0, T, t, inputs.breaks, **kw)
    slow = integrate_cascade(robot, inputs.u, q0, T, t, inputs.breaks, compiled=False, **kw)
    return fast, slow


@needs_cc
@pytest.mark.parametrize("n", [3, 5, 8])
def test_general_inputs_compiled_steps_match_scipy_and_the_numpy_code(compiled, spy, n):
    rng = np.random.default_rng(50 + n)
    robot = Robot.default(n)
    for nodes in (12, 32):
        inputs = SmoothInputs(rng, 4)
        q0 = start(rng, n)
        T = float(inputs.breaks[-1])
        t = np.unique(np.concatenate([np.linspace(0.0, T, 45), inputs.breaks]))
        fast, slow = general_both(robot, inputs, q0, t, nodes=nodes)
        assert fast.integrator == CASCADE_NAME and fast.error_estimate <= 1e-11, fast.message
        assert_same(fast, slow)
        final, samples, energy = reference(inputs.u_scalar, q0, T, robot.gains,
                                           robot.exponents, t, inputs.breaks)
        np.testing.assert_allclose(fast.q, samples, rtol=0, atol=1e-10)
        assert fast.energy == pytest.approx(energy, rel=1e-10)
    assert spy["pass"] >= 2 and spy["outputs"] == 2


@needs_cc
def test_general_steep_start_is_graded_the_same(compiled, spy):
    """u2 steep at t = 0 (a singularity 1e-4 s before): many graded refinements, the same
    panels in both codes, and the reference's answer."""
    rng = np.random.default_rng(9)
    robot = Robot.default(4)
    inputs = SmoothInputs(rng, 2, steep=0.02)
    q0 = start(rng, 4)
    T = float(inputs.breaks[-1])
    t = np.linspace(0.0, T, 31)
    fast, slow = general_both(robot, inputs, q0, t)
    assert "0 refinements" not in fast.message
    assert_same(fast, slow, atol=1e-11)
    assert spy["pass"] >= 1 and spy["outputs"] == 1
    final, samples, _ = reference(inputs.u_scalar, q0, T, robot.gains, robot.exponents, t,
                                  inputs.breaks)
    np.testing.assert_allclose(fast.final, final, rtol=0, atol=1e-9)
