"""Compiled NLP functions (:mod:`optimizer.native`): the same plans as CasADi's virtual
machine, a cache that is built once and found again, and every failure falls back.

The oracle of the compiled functions is the virtual machine evaluating the same expressions (a
different engine), and the plans are checked against the tests' own scipy integration of the
original model, as in ``test_shooting.py``.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from optimizer import native
from optimizer.model import Robot
from optimizer.planner import nlp, penalty, shooting
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest

from test_shooting import OPP_A, OPP_B, scipy_path

pytestmark = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                                reason="no C compiler")


@pytest.fixture(autouse=True)
def fresh():
    """Every test starts and ends with compiled functions off and no cached NLP."""
    native.configure(None)
    nlp._shaped_nlp.cache_clear()
    yield
    native.configure(None)
    nlp._shaped_nlp.cache_clear()
    native._builds.clear()


@pytest.fixture(scope="module")
def default_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One cache directory for the tests of the default robot's shooting library: the first
    of them compiles it (25-30 s at load 8), the others find it there, as a second process
    would (each compiled the same library into a directory of its own before)."""
    return tmp_path_factory.mktemp("native_default")


def wait_for(pattern: str, where: Path, timeout: float = 120.0) -> list[Path]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = list(where.glob(pattern))
        if found and not list(where.glob("*.lock")):
            return found
        time.sleep(0.1)
    raise AssertionError(f"no {pattern} in {where} after {timeout} s")


def _request(robot: Robot = Robot(), pair=OPP_A) -> PlanRequest:
    return PlanRequest(start=pair[0], goal=pair[1], method="shooting", robot=robot)


def test_compiled_plan_equals_the_virtual_machine_and_reaches_the_goal(default_cache):
    req = _request()
    vm = plan(req)
    assert vm.diagnostics["shooting"]["compiled"] is False
    nlp._shaped_nlp.cache_clear()
    assert native.configure(default_cache) is not None
    assert shooting.prepare(req.robot.gains, req.robot.exponents, wait=True).compiled
    p = plan(req)
    assert p.diagnostics["shooting"]["compiled"] is True
    assert len(list(default_cache.glob("*.so"))) == 1   # (3 joints: no soft-sign NLP)
    # the same iterates from the same arithmetic, up to the compiler's reordering
    assert p.diagnostics["shooting"]["iterations"] == vm.diagnostics["shooting"]["iterations"]
    assert np.max(np.abs(p.inputs.rates - vm.inputs.rates)) < 1e-9
    t, q = scipy_path(p, req)
    assert np.max(np.abs(q[-1, 1:] - np.array(req.goal))) < 1e-8
    assert np.all((q[:, 1:3] > 0.0) & (q[:, 1:3] < np.pi / 2))


def _without_timing(answer: dict) -> dict:
    """An answer's dict without what may differ between two runs of one request: its
    timings, and whether the NLP's functions were compiled."""
    answer = {k: v for k, v in answer.items() if k != "timing"}
    diagnostics = dict(answer["diagnostics"])
    diagnostics["shooting"] = {k: v for k, v in diagnostics["shooting"].items()
                               if k != "compiled"}
    diagnostics["auto"] = {k: v for k, v in diagnostics["auto"].items() if k != "tried"}
    answer["diagnostics"] = diagnostics
    return answer


def test_an_answer_before_the_library_is_built_is_the_compiled_answer_bit_for_bit(
        default_cache, monkeypatch):
    """A worker answers from CasADi's virtual machine until the NLP's library is built (a
    fresh machine, a new robot shape) and from the library afterwards: the same request
    must get the same answer either way, bit for bit (the quadrature of the proofs is the
    compiled kernel in both, as in a worker)."""
    from optimizer import cascade_kernel
    native.configure(default_cache)
    assert cascade_kernel.prepare(wait=True)
    req = PlanRequest(start=(math.radians(10),) * 3, goal=(math.radians(30),) * 3)
    with monkeypatch.context() as patched:
        patched.setattr(nlp.MultipleShootingNLP, "load_native",
                        lambda self, *args, **kwargs: False)
        vm = plan(req)
    assert vm.diagnostics["shooting"]["compiled"] is False
    nlp._shaped_nlp.cache_clear()
    assert shooting.prepare(req.robot.gains, req.robot.exponents, wait=True).compiled
    compiled = plan(req)
    assert compiled.diagnostics["shooting"]["compiled"] is True
    a, b = _without_timing(vm.to_dict()), _without_timing(compiled.to_dict())
    assert a.keys() == b.keys()
    for key in a:   # field by field, so that a failure names the field (every float in full)
        assert json.dumps(a[key], default=np.ndarray.tolist) == \
            json.dumps(b[key], default=np.ndarray.tolist), key


def test_the_correction_maps_are_compiled_with_the_nlp(default_cache):
    """The library also holds the correction's fine end map and RK4 end Jacobian: once loaded
    they are the compiled ones, with the virtual machine's values."""
    req = _request()
    native.configure(default_cache)
    m = shooting.prepare(req.robot.gains, req.robot.exponents, wait=True)
    assert m.compiled
    q0 = req.q_start()
    rates = np.random.default_rng(5).uniform(-1.0, 1.0, (m.N, 2))
    K = req.robot.gains
    vm_end = np.asarray(m.fine_path(q0, rates.T, K), float)[:, -1]
    vm_jac = np.asarray(m.end_jacobian(q0, rates.ravel(), K), float)
    for call in (m._fine_end, m._end_jacobian):
        assert call.function.class_name() != "SXFunction"  # loaded from the library
    np.testing.assert_allclose(m.fine_end(q0, rates, K), vm_end, rtol=0, atol=1e-13)
    np.testing.assert_allclose(m.rk4_end_jacobian(q0, rates, K), vm_jac, rtol=0, atol=1e-12)


def test_the_penalty_nlp_is_compiled_too_and_plans_the_same(tmp_path):
    """Every NLP of the shared transcription gets compiled functions: the penalty method's
    (another region mode, another library) gives the virtual machine's plan, on the goal."""
    req = PlanRequest(start=OPP_B[0], goal=OPP_B[1], method="penalty")
    vm = plan(req)
    assert vm.diagnostics["penalty"]["compiled"] is False
    nlp._shaped_nlp.cache_clear()
    native.configure(tmp_path)
    assert penalty.prepare(req.robot.gains, req.robot.exponents, wait=True).compiled
    p = plan(req)
    assert p.diagnostics["penalty"]["compiled"] is True
    assert p.diagnostics["penalty"]["iterations"] == vm.diagnostics["penalty"]["iterations"]
    assert np.max(np.abs(p.inputs.rates - vm.inputs.rates)) < 1e-9
    _, q = scipy_path(p, req)
    assert np.max(np.abs(q[-1, 1:] - np.array(req.goal))) < 1e-8
    assert np.all((q[:, 1:] > 0.0) & (q[:, 1:] < np.pi / 2))


def _cmdline(proc) -> str:
    """A child's command line; "" for one that has exited since it was listed (a zombie not
    yet reaped: the launcher of a detached build, whose waiting thread reaps it next)."""
    import psutil
    try:
        return " ".join(proc.cmdline())
    except (psutil.ZombieProcess, psutil.NoSuchProcess):
        return ""


def test_background_build_is_loaded_when_ready_and_found_by_the_next_process(tmp_path):
    robot = Robot(gains=(0.9, 1.1))            # other expressions: a key of their own
    # a goal whose NLPs fatrop answers (the compiled functions are fatrop's): the worked
    # example, all joints one way; on goals that need phi to reverse fatrop may reach its
    # iteration cap and leave the answer to IPOPT, whatever the library
    req = PlanRequest(start=(math.radians(10.0),) * 3, goal=(math.radians(30.0),) * 3,
                      method="shooting", robot=robot)
    native.configure(tmp_path)
    p = plan(req)
    # the first answer does not wait for the compiler
    assert p.diagnostics["shooting"]["compiled"] is False
    builds = len(native._builds)
    assert builds == 1
    # a detached build: not a child of this process
    import psutil
    assert not any("optimizer.native" in _cmdline(c)
                   for c in psutil.Process().children(recursive=True))
    assert len(wait_for("*.so", tmp_path, 300.0)) == builds
    assert not list(tmp_path.glob("*.c"))  # the source goes once its library is built
    assert not list(tmp_path.glob("*.lock")) and not list(tmp_path.glob("*.tmp"))
    time.sleep(1.05)                         # the library is looked for at most once a second
    assert plan(req).diagnostics["shooting"]["compiled"] is True
    # another process (no cached NLP): found at once, nothing compiled
    nlp._shaped_nlp.cache_clear()
    native._builds.clear()
    native.configure(tmp_path)
    q = plan(req)
    assert q.diagnostics["shooting"]["compiled"] is True
    assert not native._builds
    assert np.max(np.abs(q.inputs.rates - p.inputs.rates)) < 1e-9


def test_an_nlp_built_before_configure_gets_its_library(default_cache):
    """The service's forkserver builds the NLP before a worker configures the cache."""
    nlp = shooting.prepare(Robot().gains, Robot().exponents)
    assert nlp.compiled is False
    native.configure(default_cache)
    assert shooting.prepare(Robot().gains, Robot().exponents, wait=True) is nlp
    assert nlp.compiled is True


def test_a_failed_build_falls_back_and_is_not_retried(tmp_path):
    bad = tmp_path / "bad-cc"
    bad.write_text("#!/bin/sh\necho 'no such luck' >&2\nexit 3\n")
    bad.chmod(0o755)
    cache = tmp_path / "cache"
    native.configure(cache, compiler=str(bad))
    built = shooting.prepare(Robot().gains, Robot().exponents, wait=True)
    assert not built.compiled
    p = plan(_request())
    assert p.diagnostics["shooting"]["compiled"] is False
    failed = list(cache.glob("*.failed"))
    assert len(failed) == 1 and "no such luck" in failed[0].read_text()

    # nor does a second process try again, nor even generate the source
    def no_source() -> str:
        raise AssertionError("the source was generated again")

    assert native.library_for_fingerprint(built.fingerprint("fatrop"), no_source) is None
    assert not native._builds


def test_a_cached_nlp_library_is_found_without_its_source(default_cache, monkeypatch):
    """A process finds an NLP's library by the NLP's fingerprint: neither the C source nor
    the solver on CasADi's virtual machine is built (0.4-1.3 s at 4 to 7 joints)."""
    native.configure(default_cache)
    built = shooting.prepare(Robot().gains, Robot().exponents, wait=True)
    assert built.compiled
    first = nlp.ladder(3)[0]
    fresh = nlp.MultipleShootingNLP(tuple(Robot().exponents), False, first.intervals,
                                    first.substeps)
    assert fresh.fingerprint("fatrop") == built.fingerprint("fatrop")
    monkeypatch.setattr(native, "nlp_source", lambda *a, **k: pytest.fail("source built"))
    assert fresh.load_native(every=0.0) is True
    assert fresh._built["fatrop"].oracle().class_name() == "External"
    assert "ipopt" not in fresh._built  # (built at its first use only)


def test_an_nlp_fingerprint_changes_with_what_its_source_is_generated_from():
    ladder = nlp.ladder(3)[0]
    base = nlp.MultipleShootingNLP((1, 1), False, ladder.intervals, ladder.substeps)
    same = nlp.MultipleShootingNLP((1, 1), False, ladder.intervals, ladder.substeps)
    assert base.fingerprint("fatrop") == same.fingerprint("fatrop")
    others = [nlp.MultipleShootingNLP((1, 2), False, ladder.intervals, ladder.substeps),
              nlp.MultipleShootingNLP((1, 1), True, ladder.intervals, ladder.substeps),
              nlp.MultipleShootingNLP((1, 1), False, ladder.intervals + 1, ladder.substeps)]
    for other in others:
        assert other.fingerprint("fatrop") != base.fingerprint("fatrop")
    # fatrop's own options are the solver's at run time, not the library's functions
    runtime = nlp.MultipleShootingNLP((1, 1), False, ladder.intervals, ladder.substeps,
                                      fatrop_settings=(("max_iter", 7.0), ("mu_init", 0.1)))
    assert runtime.fingerprint("fatrop") == base.fingerprint("fatrop")
    assert base.fingerprint("ipopt") != base.fingerprint("fatrop")


def test_no_compiler_turns_it_off(tmp_path):
    assert native.configure(tmp_path, compiler="no-such-compiler-here") is None
    assert native.config() is None
    assert plan(_request()).diagnostics["shooting"]["compiled"] is False


def test_a_directory_others_can_write_is_refused(tmp_path):
    d = tmp_path / "shared"
    d.mkdir()
    d.chmod(0o777)
    with pytest.raises(PermissionError, match="writable by other users"):
        native.configure(d)
    assert native.config() is None
    d.chmod(0o1777)   # sticky, like /tmp: others may still create files (a planted library)
    with pytest.raises(PermissionError, match="writable by other users"):
        native.configure(d)
    assert native.config() is None
    cfg = native.configure(tmp_path / "new" / "dir")
    assert cfg is not None and stat.S_IMODE(cfg.cache_dir.stat().st_mode) == 0o700


def test_a_library_others_could_have_written_is_not_loaded(tmp_path):
    native.configure(tmp_path)
    lib = native.library_for("int f(void) { return 0; }\n", wait=True)
    assert lib is not None and lib.ready(every=0.0) == lib.path
    lib.path.chmod(0o777)
    assert lib.ready(every=0.0) is None
    lib.path.chmod(0o755)
    assert lib.ready(every=0.0) == lib.path


def test_the_key_follows_the_source_and_the_compiler(tmp_path):
    a = native.configure(tmp_path)
    assert a is not None
    k1 = native.library_key("int f(void){return 1;}", a)
    assert k1 == native.library_key("int f(void){return 1;}", a)
    assert k1 != native.library_key("int f(void){return 2;}", a)
    other = native.NativeConfig(a.cache_dir, "/usr/bin/other-cc")
    assert k1 != native.library_key("int f(void){return 1;}", other)


def test_a_fresh_lock_means_someone_else_builds_and_a_stale_one_is_taken_over(tmp_path):
    cc = shutil.which("cc") or shutil.which("gcc")
    src = tmp_path / "k.c"
    src.write_text("int answer(void) { return 42; }\n")
    target = tmp_path / "k.so"
    lock = tmp_path / "k.lock"
    lock.write_text("")
    assert native.build(cc, src, target) == 0 and not target.exists()   # someone else's
    old = time.time() - native.STALE_LOCK - 10
    os.utime(lock, (old, old))
    assert native.build(cc, src, target) == 0 and target.exists()       # taken over
    assert not lock.exists()
    assert not src.exists()  # a built library's source is removed
    # the command-line entry the background build runs
    target.unlink()
    src.write_text("int answer(void) { return 42; }\n")
    env = dict(os.environ, PYTHONPATH=str(Path(native.__file__).resolve().parents[1]))
    res = subprocess.run([sys.executable, "-m", "optimizer.native", cc, str(src), str(target)],
                         env=env, check=False)
    assert res.returncode == 0 and target.exists()


def test_a_build_asked_to_wait_waits_for_the_one_another_process_runs(tmp_path):
    """Two service workers starting on an empty cache ask for the same library, both waiting:
    the second must get it when the first has built it, not run without it (it then answered
    with numpy's quadrature for its life, the first with the compiled one)."""
    import threading

    cfg = native.configure(tmp_path)
    assert cfg is not None
    source = "int answer(void) { return 42; }\n"
    lib = native.Library(native.library_key(source, cfg), cfg)
    lock = lib.path.with_suffix(".lock")
    lock.write_text("")  # the other process's build, under way

    def other_build_finishes() -> None:
        time.sleep(0.6)
        src = tmp_path / "other.c"
        src.write_text(source)
        assert native.build(cfg.compiler, src, tmp_path / "other.so") == 0
        os.replace(tmp_path / "other.so", lib.path)
        lock.unlink()

    other = threading.Thread(target=other_build_finishes)
    started = time.monotonic()
    other.start()
    got = native.library_for(source, wait=True)
    other.join()
    assert got is not None and got.ready(0.0) == lib.path
    assert time.monotonic() - started >= 0.5  # it waited for the other build
    # a lock left by a build that died is taken over, and the library built here
    native.configure(None)
    cfg = native.configure(tmp_path / "second")
    assert cfg is not None
    lib = native.Library(native.library_key(source, cfg), cfg)
    lock = lib.path.with_suffix(".lock")
    lock.write_text("")
    old = time.time() - native.STALE_LOCK - 10
    os.utime(lock, (old, old))
    got = native.library_for(source, wait=True)
    assert got is not None and got.ready(0.0) == lib.path


def test_a_lock_whose_builder_is_gone_is_stale_at_once(tmp_path, monkeypatch):
    """A build killed while compiling (a container stopped, a session ended) leaves a fresh
    lock: where it names a process of this machine that no longer runs, the next build takes
    it over at once instead of waiting out STALE_LOCK; a running builder's lock, or one of
    another machine (a shared cache), stands until it is old."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = os.uname().nodename
    lock = tmp_path / "k.lock"
    lock.write_text(f"{host} {dead.pid}\n")
    assert native._lock_is_stale(lock)
    lock.write_text(f"{host} {os.getpid()}\n")
    assert not native._lock_is_stale(lock)
    lock.write_text(f"{host}-elsewhere {dead.pid}\n")
    assert not native._lock_is_stale(lock)
    lock.write_text("")
    assert not native._lock_is_stale(lock)
    # build() writes its own name into the lock it holds, and takes a dead builder's over
    cc = shutil.which("cc") or shutil.which("gcc")
    src = tmp_path / "k.c"
    src.write_text("int answer(void) { return 42; }\n")
    lock.write_text(f"{host} {dead.pid}\n")
    seen: list[str] = []
    real_run = subprocess.run

    def run(argv, *args, **kwargs):
        seen.append(lock.read_text())
        return real_run(argv, *args, **kwargs)

    monkeypatch.setattr(native.subprocess, "run", run)
    assert native.build(cc, src, tmp_path / "k.so") == 0
    monkeypatch.undo()
    assert (tmp_path / "k.so").exists() and not lock.exists()
    assert seen == [f"{host} {os.getpid()}\n"]


def test_a_waiting_build_builds_itself_when_the_other_builder_dies(tmp_path):
    """The other process holds the lock and dies mid-build (no library, no .failed): the
    waiting call notices, builds the library itself and returns it."""
    import threading

    cfg = native.configure(tmp_path)
    assert cfg is not None
    source = "int answer(void) { return 7; }\n"
    lib = native.Library(native.library_key(source, cfg), cfg)
    lock = lib.path.with_suffix(".lock")
    builder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(0.5)"])
    lock.write_text(f"{os.uname().nodename} {builder.pid}\n")
    threading.Thread(target=builder.wait).start()  # reaped when it ends: gone, not a zombie
    started = time.monotonic()
    got = native.library_for(source, wait=True)
    assert got is not None and got.ready(0.0) == lib.path
    assert time.monotonic() - started < 0.5 * native.STALE_LOCK


def test_sources_too_large_to_compile_are_left_to_the_virtual_machine(tmp_path, monkeypatch):
    native.configure(tmp_path)
    monkeypatch.setattr(native, "MAX_SOURCE_BYTES", 1000)
    assert native.library_for("/*" + "x" * 2000 + "*/", wait=True) is None
    assert not list(tmp_path.iterdir())
    assert native.library_for("int f(void) { return 0; }\n", wait=True) is not None


def _ipopt_run(m: nlp.MultipleShootingNLP, req: PlanRequest):
    """One run of IPOPT on ``m`` for ``req``, as the shooting method sets it up."""
    from optimizer.planner.rules import joint_limits
    from optimizer.planner.solvers import run_solver
    tr = nlp.ladder(req.n)[0]
    lo, hi = nlp.node_bounds(req, joint_limits(req))
    lbw, ubw, _ = nlp.variable_bounds(req, m, tr, lo, hi, None)
    p = nlp.parameters(req, *nlp.objective_weights(req, "shooting"))
    x0 = m.guess(np.array(req.start), np.array(req.goal), req.phi_start, 0.6)
    return run_solver(m, "ipopt", x0, p, lbw, ubw, 60.0)


def test_ipopt_evaluates_its_own_compiled_library_with_the_same_iterates(tmp_path,
                                                                         monkeypatch):
    """From ``IPOPT_COMPILED_FROM_JOINTS`` joints IPOPT gets a library of its functions (3
    joints here: the cheapest compile): the IPOPT solver loads it, and it takes the virtual
    machine's iterations to the same solution."""
    monkeypatch.setattr(nlp, "IPOPT_COMPILED_FROM_JOINTS", 3)
    req = _request()
    r = req.robot
    tr = nlp.ladder(req.n)[0]

    def fresh_nlp() -> nlp.MultipleShootingNLP:
        nlp._shaped_nlp.cache_clear()
        return nlp.multiple_shooting_nlp(r.gains, r.exponents, False, tr.intervals,
                                         tr.substeps)

    vm = fresh_nlp()
    ref = _ipopt_run(vm, req)
    native.configure(tmp_path)
    m = fresh_nlp()
    assert m.load_native(wait=True) and m.ipopt_compiled
    assert len(list(tmp_path.glob("*.so"))) == 2      # fatrop's library and IPOPT's
    got = _ipopt_run(m, req)
    assert dict(m.solvers)["ipopt"].oracle().class_name() == "External"  # from the library
    assert got.success and ref.success
    assert got.iterations == ref.iterations
    assert np.max(np.abs(got.x - ref.x)) < 1e-9
    # the same library serves a rebuilt solver (spent memories, solver_call)
    assert m._factories["ipopt"]().oracle().class_name() == "External"


def test_ipopt_is_compiled_only_where_it_answers(tmp_path):
    """Below ``IPOPT_COMPILED_FROM_JOINTS`` joints (3 here), IPOPT runs only where fatrop
    failed: no library of its own is compiled."""
    assert nlp.IPOPT_COMPILED_FROM_JOINTS > 3
    native.configure(tmp_path)
    m = shooting.prepare(Robot().gains, Robot().exponents, wait=True)
    assert m.compiled and not m.ipopt_compiled and m.native_ipopt is None


def test_the_chained_forms_compiled_maps_give_the_virtual_machines_bits(tmp_path):
    """4 to 8 joints: the chained form's maps (forward, input coefficients, inverse, u from
    (z, v)) compiled give the same bits as CasADi's virtual machine on the same points, a
    count that is not a multiple of the compiled block among them: a worker answers the same
    before and after its libraries are built."""
    from optimizer.chained_form import chained_form

    rng = np.random.default_rng(3)
    for n in range(4, 9):
        cf = chained_form(Robot.default(n))
        q = np.column_stack([rng.uniform(-1, 1, 130), rng.uniform(0.1, 1.45, (130, n))])
        u = rng.uniform(-1, 1, (130, 2))

        def maps() -> list[np.ndarray]:
            z = cf.to_chained(q)
            al, be = cf.input_coefficients(q)
            v = np.column_stack([u[:, 0], al * u[:, 0] + be * u[:, 1]])
            return [z, al, be, cf.from_chained(z).q, cf.u_from_zv(z, v)]

        native.configure(None)
        vm = maps()
        native.configure(tmp_path)
        maps()  # starts the builds
        deadline = time.monotonic() + 240.0
        from optimizer import chained_form as module
        while time.monotonic() < deadline:
            entries = [e for e in module._COMPILED.values() if e._cfg is native.config()]
            if entries and all(e.current() is not None for e in entries):
                break
            time.sleep(0.2)
        else:
            raise AssertionError("the chained form's maps were not compiled in time")
        compiled = maps()
        for a, b in zip(vm, compiled):
            assert np.array_equal(a, b, equal_nan=True), n
