"""Closed loop: the continuation of a plan from a measured state, to the same goal, at once.

A controller runs a plan, measures the state ``q_m = (phi, th_1..th_n)`` at time ``t`` and asks
for the rest of the motion from there. :func:`replan` answers with a continuation that

* starts at the rates being commanded at ``t`` (given, or the plan's own at ``t``), so the
  drive sees no jump;
* ends at the plan's goal at rest, by the plan's end or by a new ``duration``;
* is verified on the original model like any plan (cascade quadrature of its exact input
  pieces, the region at every break, the handed-out linear form replayed);
* is a pure function of its arguments (nothing is kept between calls).

How (actuator-rate plans: ``shooting``, ``penalty``, the default)
-----------------------------------------------------------------
A plan's rates are ``u(t) = U(sigma(t)) sigma'(t)``: piecewise-constant *geometric* rates ``U``
on pieces of plan time ``sigma``, run along a time law ``sigma(t)`` (the timing design of
issue 25: phases of constant jerk, ``sigma' = 0`` at every stop; a plan without a time law has
``sigma = t``). The model is driftless, so the state reached at plan time ``sigma`` does not
depend on the time law: the geometry and the timing can be corrected separately.

1. **Kept motion.** The piece that contains ``sigma(t)`` runs on to its end as commanded (its
   direction is the commanded rate over ``sigma'(t)``), along the remaining time law: the
   rates stay continuous, and they reach the next stop at rest. Its end state is integrated
   from ``q_m`` (exactly: a constant-rate piece).
2. **Gauss-Newton on what follows.** The geometric rates of the later pieces start at the
   plan's (the warm start) and take minimum-norm Gauss-Newton steps onto the goal
   (``th_1..th_n``; ``phi`` is free), with the NLP layer's compiled RK4 end map and its
   Jacobian (:meth:`~.nlp.MultipleShootingNLP.fine_end`, ``rk4_end_jacobian``; the pieces
   before are given zero rates, which the driftless model does not move under). The remaining
   time law (the stops) is kept; with a new ``duration`` the later pieces get rest-to-rest
   laws that end then.
3. **Proof.** The continuation's pieces are integrated by cascade quadrature on the original
   model; a miss above :data:`CORRECTION_TARGET` gets one defect-corrected step more.
4. **Fallback: the full planner.** Too few pieces left to correct (``2 M < n``), a correction
   that fails, or a plan with chained (polynomial) inputs: the full planner
   (:func:`~.plan.plan`, method ``shooting``) plans from the end of the kept motion (for a
   chained plan: from a short braking of the commanded rates to rest), its pieces run
   rest-to-rest to the end.

Why keep the current piece: changing its direction mid-motion would jump the rates; a stop is
where the direction may change. The motion after the last replan is what no replan corrects.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, replace
from typing import Any, Callable, Mapping

import casadi as ca
import numpy as np

from ..chained_form import chained_form
from ..dynamics import rk4_step, vector_field
from ..errors import InfeasibleError, InvalidRequestError, NumericalError, PlannerError
from ..execution import EXECUTION_TOLERANCE, REPLAY_NODES, correct, linear_form
from ..indicators import compute_indicators
from ..model import Robot
from ..problem import PlanRequest
from ..results import Plan, json_safe
from ..timing import ramp_profile
from ..verify import integrate_cascade
from .plan import plan as full_plan
from .nlp import BufferedCall, ladder, minimum_norm_step, multiple_shooting_nlp
from .rules import TERMINAL_TOLERANCE, joint_limits, limits_region

#: Gauss-Newton steps stop once the fine end map is this close to the goal (rad)...
CORRECTION_TARGET = 1e-11
#: ... or after this many steps...
MAX_STEPS = 12
#: ... each halved at most this many times until the miss shrinks.
MAX_HALVINGS = 8
#: Rounds of holding at 0 the rates that a correction would reverse.
MAX_HOLDS = 3
#: RK4 steps per piece of the end map built here when no NLP rung fits the pieces.
OWN_SUBSTEPS = 8
#: Seconds over which a chained plan's commanded rates are braked to rest (fallback).
BRAKE_TIME = 0.05
#: Samples of the handed-out continuation (fewer when less time is left, at least 2 per piece).
DEFAULT_SAMPLES = 101
#: Rates above this (rad/s) are no plan of ours.
MAX_RATE = 1e4
#: A rate below this (rad/s) is at rest.
REST = 1e-12
#: ``time_law.rule`` of a continuation (as :meth:`optimizer.timing.TimeLaw.as_dict` says it).
LAW_RULE = ("u(t) = u_plan(sigma) * dsigma/dlam * lam'(t); on phase k, with r = t - start: "
            "lam = lam0 + v0 r + a0 r^2/2 + jerk r^3/6; sigma = sigma_k + slope_k (lam - lam_k) "
            "on the knots' piece k")


# ------------------------------------------------------------------ time laws (issue 25's)
@dataclass(frozen=True)
class TimeLaw:
    """Plan time ``sigma(t)`` as phases of constant jerk: rows ``(t0, dt, sigma0, dsigma0,
    ddsigma0, jerk)`` in time order, contiguous (an answer's ``time_law``, its ``lam`` mapped
    to ``sigma``: :meth:`from_answer`); :meth:`identity` is ``sigma = t`` (a plan without a
    time law: its rates jump at its breaks)."""

    phases: np.ndarray

    @classmethod
    def identity(cls, breaks: np.ndarray) -> "TimeLaw":
        b = np.asarray(breaks, float)
        ph = np.zeros((b.size - 1, 6))
        ph[:, 0], ph[:, 1], ph[:, 2], ph[:, 3] = b[:-1], np.diff(b), b[:-1], 1.0
        return cls(ph)

    @property
    def start(self) -> float:
        return float(self.phases[0, 0])

    @property
    def end(self) -> float:
        return float(self.phases[-1, 0] + self.phases[-1, 1])

    def _phase(self, t: np.ndarray) -> np.ndarray:
        k = np.searchsorted(self.phases[:, 0], t, side="right") - 1
        return np.clip(k, 0, self.phases.shape[0] - 1)

    def evaluate(self, t: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(sigma, sigma', sigma'')`` at times ``t`` (exact: cubics)."""
        t = np.asarray(t, float)
        P = self.phases[self._phase(t)]
        s = t - P[..., 0]
        j = P[..., 5]
        ds = P[..., 3] + P[..., 4] * s + 0.5 * j * s * s
        sig = P[..., 2] + P[..., 3] * s + 0.5 * P[..., 4] * s * s + j * s ** 3 / 6.0
        return sig, ds, P[..., 4] + j * s

    def after(self, t: float) -> "TimeLaw":
        """The law from ``t`` on (the phase holding ``t`` cut there)."""
        k = int(self._phase(np.array(t)))
        sig, ds, dds = self.evaluate(np.array([t]))
        first = [t, float(self.phases[k, 0] + self.phases[k, 1] - t), float(sig[0]),
                 float(ds[0]), float(dds[0]), float(self.phases[k, 5])]
        rows = np.vstack([first, self.phases[k + 1:]])
        return TimeLaw(rows[rows[:, 1] > 0.0] if rows.shape[0] > 1 else rows)

    def _sigma_ends(self) -> np.ndarray:
        P = self.phases
        s = P[:, 1]
        return P[:, 2] + P[:, 3] * s + 0.5 * P[:, 4] * s * s + P[:, 5] * s ** 3 / 6.0

    def as_dict(self, plan_duration: float, breaks: np.ndarray) -> dict[str, Any]:
        """The answer's ``time_law`` in the shape of :meth:`optimizer.timing.TimeLaw.as_dict`
        (here ``lam = sigma``: knots of slope 1 at the pieces' ``breaks``); ``stops`` are the
        phase starts at rest and the end."""
        P = self.phases
        stops = P[np.abs(P[:, 3]) <= REST, 0].tolist() + [self.end]
        return {"rule": LAW_RULE, "plan_duration": plan_duration, "stops": stops,
                "knots": {"lam": breaks, "sigma": breaks, "slope": np.ones(breaks.size - 1)},
                "phases": {"start": P[:, 0], "length": P[:, 1], "lam0": P[:, 2],
                           "v0": P[:, 3], "a0": P[:, 4], "jerk": P[:, 5]},
                "shortest_duration": None, "binding_limit": None, "limits": {}}

    @classmethod
    def from_answer(cls, law: Mapping[str, Any]) -> tuple["TimeLaw", np.ndarray, np.ndarray,
                                                           np.ndarray]:
        """An answer's ``time_law`` (:meth:`optimizer.timing.TimeLaw.as_dict`): the law of its
        geometric parameter ``lam`` (rows), and its knots ``lam``, ``sigma``, ``slope``.

        Raises
        ------
        InvalidRequestError
            Not such a law (``field`` under ``plan.time_law``).
        """
        try:
            ph, kn = law["phases"], law["knots"]
            cols = [_floats(ph[k], f"plan.time_law.phases.{k}")
                    for k in ("start", "length", "lam0", "v0", "a0", "jerk")]
            lam_k = _floats(kn["lam"], "plan.time_law.knots.lam")
            sig_k = _floats(kn["sigma"], "plan.time_law.knots.sigma")
            slope = _floats(kn["slope"], "plan.time_law.knots.slope")
        except (KeyError, TypeError):
            raise _bad("plan.time_law must hold knots (lam, sigma, slope) and phases (start, "
                       "length, lam0, v0, a0, jerk)", "plan.time_law") from None
        sizes = {c.shape for c in cols}
        if (len(sizes) != 1 or cols[0].ndim != 1 or not cols[0].size or lam_k.ndim != 1
                or lam_k.size < 2 or lam_k.shape != sig_k.shape
                or slope.shape != (lam_k.size - 1,) or np.any(cols[1] <= 0.0)
                or not np.all(np.diff(lam_k) > 0.0) or not np.all(slope > 0.0)):
            raise _bad("plan.time_law's phases and knots are not a law of this library",
                       "plan.time_law")
        if not np.allclose(cols[0][1:], cols[0][:-1] + cols[1][:-1], rtol=0.0, atol=1e-9):
            raise _bad("plan.time_law.phases must be contiguous", "plan.time_law.phases")
        return cls(np.column_stack(cols)), lam_k, sig_k, slope

    @property
    def piecewise_linear(self) -> bool:
        """No jerk phase: constant-direction rates are linear between the phase starts, and
        the linear form with samples there holds them exactly."""
        return not bool(np.any(self.phases[:, 5] != 0.0))


def rest_to_rest(t0: float, D: float, sigma0: float, L: float) -> np.ndarray:
    """The default rest-to-rest law of one piece (:func:`optimizer.timing.ramp_profile`):
    ``sigma`` from ``sigma0`` to ``sigma0 + L`` in ``D`` s from ``t0``. Rows as
    :class:`TimeLaw`'s."""
    p = ramp_profile(L, D)
    return np.column_stack([t0 + p.start, p.length, sigma0 + p.x0, p.v0, p.a0, p.jerk])


def stop_and_go(breaks: np.ndarray, T: float, t0: float = 0.0) -> TimeLaw:
    """The time law of the timing design (issue 25) for piecewise-constant rates without
    limits: every piece ``[breaks[k], breaks[k+1]]`` of plan time a :func:`rest_to_rest`
    segment, durations in proportion to plan time, ``t0`` to ``t0 + T``."""
    b = np.asarray(breaks, float)
    return TimeLaw(_law_after_stop(t0, t0 + T, b))


def braking(t0: float, D: float, sigma0: float) -> np.ndarray:
    """``sigma'`` from 1 down to 0 at a constant rate in ``D`` s (``sigma`` travels ``D / 2``):
    rates of a constant direction stay continuous and linear in ``t``. One row."""
    return np.array([[t0, D, sigma0, 1.0, -1.0 / D, 0.0]])


# ------------------------------------------------------------------ the plan, as read
@dataclass(frozen=True)
class PlanState:
    """What the replanner reads of a plan (an answer of ``/v1/plans`` or ``/v1/replans``, its
    compact form, or a :class:`~optimizer.results.Plan`).

    Attributes
    ----------
    robot : Robot
    goal : ndarray (n,)
    breaks : ndarray (N+1,)
        The geometric pieces' ends on the path's parameter (the time law's ``lam``; plan
        time ``sigma`` without a law).
    rates : ndarray (N, 2) or None
        Geometric rates of each piece (rad per unit of that parameter); None for chained
        inputs.
    law : TimeLaw
    plan_duration : float
        ``T0``, the plan time's end.
    joint_bounds : tuple or None
    samples : int
    path_t, path_u : ndarray or None
        The handed-out path (chained plans: their commanded rates are read from it).
    jumps : bool
        No time law: the rates jump at the breaks (``sigma = t``).
    """

    robot: Robot
    goal: np.ndarray
    breaks: np.ndarray
    rates: np.ndarray | None
    law: TimeLaw
    plan_duration: float
    joint_bounds: tuple[tuple[float, float] | None, ...] | None = None
    samples: int = DEFAULT_SAMPLES
    path_t: np.ndarray | None = None
    path_u: np.ndarray | None = None
    jumps: bool = False

    @property
    def start_time(self) -> float:
        return self.law.start

    @property
    def end_time(self) -> float:
        return self.law.end

    def compact(self) -> dict[str, Any]:
        """The compact form of the plan: all :func:`replan` needs (actuator plans)."""
        out: dict[str, Any] = {
            "robot": {"gains": list(self.robot.gains), "exponents": list(self.robot.exponents)},
            "goal": self.goal.tolist(),
            "coefficients": {"segments": [
                {"t_start": float(a), "t_end": float(b), "u": [float(x) for x in r]}
                for a, b, r in zip(self.breaks[:-1], self.breaks[1:],
                                   self.rates if self.rates is not None else [])]},
            "time_law": self.law.as_dict(self.plan_duration, self.breaks),
        }
        if self.joint_bounds is not None:
            out["joint_bounds"] = [None if b is None else list(b) for b in self.joint_bounds]
        return out


def _bad(message: str, field: str) -> InvalidRequestError:
    return InvalidRequestError(message, field=field)


def _floats(x: Any, field: str, shape: tuple[int, ...] | None = None) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise _bad(f"{field} must hold numbers", field) from None
    if not np.all(np.isfinite(a)) or (shape is not None and a.shape != shape):
        raise _bad(f"{field} must be {'finite numbers' if shape is None else f'{shape} finite numbers'}",
                   field)
    return a


def read_plan(plan: Plan | PlanState | Mapping[str, Any]) -> PlanState:
    """A plan (answer dict, compact form or :class:`Plan`) as a :class:`PlanState`.

    Raises
    ------
    InvalidRequestError
        Not a plan of this library (``field`` names what is wrong, under ``plan.``).
    """
    if isinstance(plan, PlanState):
        return plan
    if isinstance(plan, Plan):
        plan = plan.to_dict()
    try:
        return _read(plan)
    except PlannerError:
        raise
    except (TypeError, ValueError, KeyError, AttributeError, IndexError) as exc:
        raise _bad(f"plan is not an answer of this service ({type(exc).__name__}: "
                   f"{str(exc)[:120]})", "plan") from None


def _read(plan: Any) -> PlanState:
    if not isinstance(plan, Mapping):
        raise _bad("plan must be an answer of /v1/plans or /v1/replans", "plan")
    if plan.get("status", "success") != "success":
        raise _bad("plan is not a successful answer (status must be 'success')", "plan.status")
    rob = plan.get("robot")
    if not isinstance(rob, Mapping) or rob.get("gains") is None or rob.get("exponents") is None:
        raise _bad("plan.robot must give gains and exponents (as answers do)", "plan.robot")
    try:
        robot = Robot(tuple(rob["gains"]), tuple(rob["exponents"]))
    except PlannerError as exc:
        raise _bad(exc.message, "plan.robot") from None
    except (TypeError, ValueError):
        raise _bad("plan.robot.gains and exponents must be lists of numbers", "plan.robot") from None
    n = robot.n
    if plan.get("goal") is not None:
        goal = _floats(plan["goal"], "plan.goal", (n,))
    else:
        final = (plan.get("validation") or {}).get("final")
        if final is None:
            raise _bad("plan has neither goal nor validation.final", "plan.goal")
        goal = _floats(final, "plan.validation.final", (n + 1,))[1:]
    segs = (plan.get("coefficients") or {}).get("segments")
    if not isinstance(segs, list) or not segs:
        raise _bad("plan.coefficients.segments must list the plan's input pieces",
                   "plan.coefficients.segments")
    try:
        breaks = np.array([float(s["t_start"]) for s in segs] + [float(segs[-1]["t_end"])])
        ends = np.array([float(s["t_end"]) for s in segs])
    except (KeyError, TypeError, ValueError):
        raise _bad("each segment needs t_start and t_end", "plan.coefficients.segments") from None
    if (not np.all(np.isfinite(breaks)) or not np.all(np.diff(breaks) > 0.0)
            or not np.allclose(ends[:-1], breaks[1:-1], rtol=0.0, atol=1e-12)):
        raise _bad("plan.coefficients.segments must be contiguous pieces in time order",
                   "plan.coefficients.segments")
    rates: np.ndarray | None = None
    if all(isinstance(s.get("u"), list) and len(s["u"]) == 2 for s in segs):
        rates = _floats([s["u"] for s in segs], "plan.coefficients.segments", (len(segs), 2))
        if float(np.max(np.abs(rates))) > MAX_RATE:
            raise _bad(f"plan.coefficients.segments hold rates above {MAX_RATE:g} rad/s: not a "
                       "plan of this service", "plan.coefficients.segments")
    T0 = float(breaks[-1])
    law_d = plan.get("time_law")
    if law_d is None:
        law = TimeLaw.identity(breaks)
    elif isinstance(law_d, Mapping):
        law, lam_k, sig_k, slope = TimeLaw.from_answer(law_d)
        if abs(float(law._sigma_ends()[-1]) - lam_k[-1]) > 1e-7 * max(1.0, lam_k[-1]):
            raise _bad("plan.time_law's phases do not end at its last knot", "plan.time_law")
        if rates is not None:
            # the path on lam: each knot piece at the rate of its segment times its slope
            if abs(sig_k[-1] - breaks[-1]) > 1e-9 * max(1.0, breaks[-1]) or sig_k[0] != breaks[0]:
                raise _bad("plan.time_law.knots.sigma must span the segments",
                           "plan.time_law.knots")
            seg = np.clip(np.searchsorted(breaks, 0.5 * (sig_k[:-1] + sig_k[1:]),
                                          side="right") - 1, 0, rates.shape[0] - 1)
            rates = rates[seg] * slope[:, None]
            breaks = lam_k.copy()
            T0 = float(lam_k[-1])
    else:
        raise _bad("plan.time_law must be an object (the answer's)", "plan.time_law")
    dur = plan.get("duration")
    if dur is not None and abs(float(dur) - law.end) > 1e-7 * max(1.0, law.end):
        raise _bad(f"plan.duration {float(dur):.9g} s is not the end of its time law "
                   f"({law.end:.9g} s)", "plan.duration")
    jb = plan.get("joint_bounds")
    bounds = None if jb is None else tuple(None if b is None else (float(b[0]), float(b[1]))
                                           for b in jb)
    path = plan.get("path") or {}
    pt = pu = None
    if rates is None:
        if path.get("t") is None or path.get("u") is None:
            raise _bad("a plan of chained inputs needs its path (t, u) to be continued",
                       "plan.path")
        pt = _floats(path["t"], "plan.path.t")
        pu = _floats(path["u"], "plan.path.u")
    given_t = path.get("t")
    samples = int(plan.get("samples") or (0 if given_t is None else len(given_t))
                  or DEFAULT_SAMPLES)
    return PlanState(robot=robot, goal=goal, breaks=breaks, rates=rates, law=law,
                     plan_duration=T0, joint_bounds=bounds,
                     samples=min(max(samples, 11), DEFAULT_SAMPLES), path_t=pt, path_u=pu,
                     jumps=law_d is None)


# ------------------------------------------------------------------ end maps
class EndMap:
    """The RK4 end state of ``N`` equal pieces of normalised time under rates ``(N, 2)`` and
    its Jacobian: the NLP's compiled maps when a rung of the ladder has ``N`` intervals, else
    CasADi functions built here (cached)."""

    def __init__(self, robot: Robot, N: int) -> None:
        self.N = N
        self.end: Callable[[np.ndarray, np.ndarray], np.ndarray]
        self.jacobian: Callable[[np.ndarray, np.ndarray], np.ndarray]
        rung = next((tr for tr in ladder(robot.n) if tr.intervals == N), None)
        if rung is not None:
            nlp = multiple_shooting_nlp(tuple(robot.gains), tuple(robot.exponents), False,
                                        rung.intervals, rung.substeps)
            self.end, self.jacobian = nlp.fine_end, nlp.rk4_end_jacobian
        else:
            fe, jac = _own_maps(tuple(robot.gains), tuple(robot.exponents), N)
            nq = robot.n + 1
            self.end = lambda q0, U: fe(q0, U)[0]
            self.jacobian = lambda q0, U: jac(q0, U)[0].reshape(2 * N, nq).T


@functools.lru_cache(maxsize=32)
def _own_maps(gains: tuple[float, ...], exponents: tuple[int, ...], N: int
              ) -> tuple[BufferedCall, BufferedCall]:
    nq = len(gains) + 2
    q, u = ca.SX.sym("q", nq), ca.SX.sym("u", 2)
    step = ca.Function("rk4", [q, u], [rk4_step(
        lambda y, r: ca.vertcat(*vector_field(gains, exponents, y, r[0], r[1], ca.cos)),
        q, u, 1.0 / N, OWN_SUBSTEPS)])
    U = ca.SX.sym("U", 2 * N)
    x = q
    for k in range(N):
        x = step(x, U[2 * k:2 * k + 2])
    end = ca.Function("replan_end", [q, U], [x])
    jac = ca.Function("replan_jac", [q, U], [ca.densify(ca.jacobian(x, U))])
    return BufferedCall(end, 2), BufferedCall(jac, 2)


@functools.lru_cache(maxsize=32)
def end_map(robot: Robot, N: int) -> EndMap:
    return EndMap(robot, N)


# ------------------------------------------------------------------ the replanner
@dataclass(frozen=True)
class Continuation:
    """Geometric pieces from the measured state and the time law that runs them."""

    breaks: np.ndarray          # plan time sigma (s)
    rates: np.ndarray           # (M, 2) rad per s of plan time
    law: TimeLaw
    plan_duration: float
    route: str
    steps: int
    kept: int = 0               # 1: the first piece is the commanded motion run on
    refine: Any = None          # (exact end, free rates) -> free rates (one defect step)


def _law_after_stop(t_stop: float, T_end: float, breaks: np.ndarray) -> np.ndarray:
    """Rest-to-rest laws of pieces ``breaks`` run from ``t_stop`` to ``T_end``, durations in
    proportion to their plan time."""
    L = np.diff(breaks)
    D = (T_end - t_stop) * L / L.sum()
    t0 = t_stop + np.concatenate([[0.0], np.cumsum(D)[:-1]])
    return np.vstack([rest_to_rest(a, d, s, l) for a, d, s, l in zip(t0, D, breaks[:-1], L)])


def _commanded(ps: PlanState, t: float) -> np.ndarray:
    """The rates the plan commands at ``t``."""
    if ps.rates is not None:
        sig, ds, _ = ps.law.evaluate(np.array([t]))
        k = int(np.clip(np.searchsorted(ps.breaks, sig[0], side="right") - 1, 0,
                        ps.rates.shape[0] - 1))
        return ps.rates[k] * float(ds[0])
    assert ps.path_t is not None and ps.path_u is not None
    # a chained plan: its handed-out linear form (the later copy of a doubled sample)
    pt, pu = ps.path_t, ps.path_u
    k = int(np.clip(np.searchsorted(pt, t, side="right") - 1, 0, pt.size - 2))
    a, b = pt[k], pt[k + 1]
    w = 0.0 if b <= a else (t - a) / (b - a)
    return np.asarray((1.0 - w) * pu[k] + w * pu[k + 1], float)


def replan(plan: Plan | PlanState | Mapping[str, Any], time_: float, state: Any,
           rates: Any = None, duration: float | None = None, *,
           plain: bool = True, time_limit: float = 10.0,
           keep_reversals: bool = False) -> dict[str, Any]:
    """The continuation of ``plan`` from the measured ``state`` at ``time_`` (see the module).

    Parameters
    ----------
    plan : Plan, PlanState or dict
        An answer of ``/v1/plans`` or ``/v1/replans`` (or its compact form).
    time_ : float
        Seconds since the plan's start (its time axis: a replan's answer keeps it).
    state : sequence of float
        Measured ``(phi, th_1..th_n)`` (rad).
    rates : sequence of 2 floats, optional
        The rates being commanded at ``time_`` (rad/s); default the plan's.
    duration : float, optional
        A new end time (s, on the plan's time axis); default the plan's end.
    time_limit : float
        Seconds for the full planner, when it runs (the fallback).
    keep_reversals : bool
        Hand out no continuation whose rates reverse ``phi`` or ``th1`` more often than the
        plan's rest does (the fast path keeps every rate's sign; a fallback plan that adds a
        reversal is refused, :class:`InfeasibleError` naming ``keep_reversals``). False (the
        default): the goal first; ``indicators.reversals`` say what the continuation does.
    plain : bool
        True: Python lists and floats (:func:`~optimizer.results.json_safe`); False: numpy
        arrays left in, for an encoder that writes them (the service's orjson).

    Returns
    -------
    dict
        An answer with the shape of a plan's: ``path.t`` runs from ``time_`` to the end.

    Raises
    ------
    InvalidRequestError
        A state outside the region (``state``), a time past the end (``time``), rates of
        the wrong shape (``rates``), a plan that is not one of ours (``plan....``).
    InfeasibleError, NumericalError
        No continuation could be verified.
    """
    t_start = time.perf_counter()
    ps = read_plan(plan)
    n = ps.robot.n
    t = float(time_)
    if not math.isfinite(t) or t < ps.start_time - 1e-12 or t >= ps.end_time:
        raise _bad(f"time = {t!r} s must lie in [{ps.start_time:.6g}, {ps.end_time:.6g}) s, "
                   "the plan's remaining span", "time")
    q_m = _floats(state, "state")
    if q_m.shape != (n + 1,):
        raise _bad(f"state must give phi and th1..th{n} ({n + 1} numbers), not {q_m.size}",
                   "state")
    T_end = ps.end_time if duration is None else float(duration)
    if not math.isfinite(T_end) or T_end <= t:
        raise _bad(f"duration = {duration!r} s must end after time = {t:.6g} s", "duration")
    req = PlanRequest(start=tuple(q_m[1:]), goal=tuple(ps.goal), robot=ps.robot,
                      phi_start=float(q_m[0]), duration=T_end - t, samples=ps.samples,
                      joint_bounds=ps.joint_bounds, time_limit=float(time_limit))
    lo, hi = joint_limits(req)
    for i, (x, a, b) in enumerate(zip(q_m[1:], lo, hi)):
        if not a < x < b:
            raise _bad(f"state[{i + 1}] = th{i + 1} = {x:.6g} rad is outside ({a:.6g}, "
                       f"{b:.6g}) rad, the singularity-free region within the joint bounds: "
                       "no continuation starts there", f"state[{i + 1}]")
    u_c = _commanded(ps, t) if rates is None else _floats(rates, "rates", (2,))
    timing: dict[str, float] = {}
    errors: list[str] = []
    cont: Continuation | None = None
    if ps.rates is not None:
        try:
            cont = _fast(ps, req, t, q_m, u_c, T_end, keep_reversals)
        except PlannerError as exc:
            errors.append(f"{exc.code}: {exc.message}")
    timing["correction"] = time.perf_counter() - t_start
    result: dict[str, Any] | None = None
    if cont is not None:
        try:
            result = _finish(ps, req, t, q_m, u_c, cont, timing)
        except PlannerError as exc:
            errors.append(f"{exc.code}: {exc.message}")
    if result is None:
        cont = _fallback(ps, req, t, q_m, u_c, T_end)
        if keep_reversals and ps.rates is not None:
            sig = float(ps.law.evaluate(np.array([t]))[0][0])
            k = int(np.clip(np.searchsorted(ps.breaks, sig, side="right") - 1, 0,
                            ps.rates.shape[0] - 1))
            had, has = sign_changes(ps.rates[k:]), sign_changes(cont.rates)
            if has > had:
                raise InfeasibleError(
                    f"the only continuation found reverses phi or th1 {has} time(s), the plan's "
                    f"rest {had}: none was handed out (keep_reversals=false accepts it; or run "
                    "on the current plan)", field="keep_reversals",
                    diagnostics={"reversals": has, "plan_reversals": had,
                                 "fast_path_failed": errors})
        result = _finish(ps, req, t, q_m, u_c, cont, timing)
    result["timing"]["total"] = time.perf_counter() - t_start
    if errors:
        result["diagnostics"]["replan"]["fast_path_failed"] = errors
    return json_safe(result) if plain else result


@dataclass(frozen=True)
class Kept:
    """The motion that runs on as commanded: from plan time ``breaks[0]`` (now) to the next
    stop ``breaks[-1]`` (empty at rest), its pieces' rates (the first: the commanded rates
    over ``sigma'``), its law, and ``k``: the first of the plan's pieces after it."""

    k: int
    breaks: np.ndarray
    rates: np.ndarray
    law: TimeLaw

    @property
    def pieces(self) -> int:
        return self.rates.shape[0]

    @property
    def s_stop(self) -> float:
        return float(self.breaks[-1])


def _kept(ps: PlanState, t: float, u_c: np.ndarray) -> Kept:
    """What runs on from ``t`` to the next stop (see :class:`Kept`). A plan without a time law
    jumps at every break: there its next break is the stop."""
    assert ps.rates is not None
    sig, ds, _ = ps.law.evaluate(np.array([t]))
    s_t, v = float(sig[0]), float(ds[0])
    tol = 1e-9 * max(1.0, ps.plan_duration)
    k = int(np.clip(np.searchsorted(ps.breaks, s_t + tol, side="right") - 1, 0,
                    ps.rates.shape[0] - 1))
    if v <= REST:
        if float(np.max(np.abs(u_c))) > 1e-9:
            raise NumericalError("the plan is at rest at this time but rates were given",
                                 field="rates")
        if abs(s_t - ps.breaks[k]) > tol:
            raise NumericalError("the plan is at rest inside a piece")
        return Kept(k, np.array([s_t]), np.zeros((0, 2)), TimeLaw(np.zeros((0, 6))))
    P = ps.law.phases
    if ps.jumps:
        s_stop = float(ps.breaks[k + 1])
        t_stop = float(P[np.argmin(np.abs(P[:, 2] - s_stop)), 0]) if s_stop < ps.breaks[-1] \
            else ps.law.end
    else:
        at_rest = P[(P[:, 0] > t) & (np.abs(P[:, 3]) <= REST), 0]
        t_stop = float(at_rest[0]) if at_rest.size else ps.law.end
        s_stop = float(ps.law.evaluate(np.array([t_stop]))[0][0]) if at_rest.size \
            else float(ps.law._sigma_ends()[-1])
    j = int(np.argmin(np.abs(ps.breaks - s_stop)))
    if abs(ps.breaks[j] - s_stop) > 1e-7 * max(1.0, ps.plan_duration):
        raise NumericalError("the time law stops between the plan's breaks")
    inner = ps.breaks[k + 1:j]
    kb = np.concatenate([[s_t], inner, [ps.breaks[j]]])
    kr = ps.rates[k:j].copy()
    kr[0] = np.asarray(u_c, float) / v
    law = ps.law.after(t)
    kept_rows = law.phases[law.phases[:, 0] < t_stop - 1e-12]
    return Kept(j, kb, kr, TimeLaw(kept_rows))


def _braked(ps: PlanState, t: float, u_c: np.ndarray, T_end: float) -> Kept:
    """The commanded motion braked to rest now: ``sigma'`` from its value down to 0 at a
    constant rate within :data:`BRAKE_TIME` (the rates stay continuous, their slope jumps),
    inside the current piece; what is left of that piece and the later pieces follow. Used
    when no piece is left after the next stop (the plan's last segment)."""
    assert ps.rates is not None
    sig, ds, _ = ps.law.evaluate(np.array([t]))
    s_t, v = float(sig[0]), float(ds[0])
    if v <= REST:
        return _kept(ps, t, u_c)
    k = int(np.clip(np.searchsorted(ps.breaks, s_t, side="right") - 1, 0,
                    ps.rates.shape[0] - 1))
    room = float(ps.breaks[k + 1]) - s_t
    D = min(BRAKE_TIME, 0.25 * (T_end - t), room / v)   # travels v D / 2 <= room / 2
    if D <= 0.0:
        raise NumericalError("no room left to brake the current motion")
    s_b = s_t + 0.5 * v * D
    law = np.array([[t, D, s_t, v, -v / D, 0.0]])
    rates = (np.asarray(u_c, float) / v)[None, :]
    # the rest of the current piece is free: ps.breaks[k + 1:] follow s_b
    return Kept(k, np.array([s_t, s_b]), rates, TimeLaw(law))


def _pieces_end(robot: Robot, q0: np.ndarray, breaks: np.ndarray, rates: np.ndarray
                ) -> np.ndarray:
    """The state after constant-rate pieces: RK4 with :data:`OWN_SUBSTEPS` steps each (as
    close to the exact model as the correction's end map; the continuation's quadrature
    proves the whole)."""
    end, _ = _own_maps(tuple(robot.gains), tuple(robot.exponents), 1)
    q = np.asarray(q0, float)
    for L, r in zip(np.diff(breaks), rates):
        if L > 0.0:
            q = end(q, np.asarray(r, float) * L)[0]
    return q


def _fast(ps: PlanState, req: PlanRequest, t: float, q_m: np.ndarray, u_c: np.ndarray,
          T_end: float, keep_reversals: bool = False) -> Continuation:
    """Steps 1-2 of the module: the kept motion, then Gauss-Newton on the later pieces."""
    assert ps.rates is not None
    kept = _kept(ps, t, u_c)
    n = ps.robot.n
    braked = kept.k >= ps.rates.shape[0]
    if braked:      # the last segment: stop early, what follows is corrected
        kept = _braked(ps, t, u_c, T_end)
    free = np.concatenate([[kept.s_stop], ps.breaks[kept.k + 1:]]) if braked else \
        ps.breaks[kept.k:]
    rates0 = ps.rates[kept.k:]
    M = free.size - 1
    # few pieces left (near the end): split each into equal parts (the same path, more stops)
    # so that the correction has more inputs than joints to move
    split = 1 if 2 * M >= n + 2 else math.ceil((n + 2) / (2 * M))
    if split > 1:
        w = np.arange(split) / split
        free = np.concatenate([(free[:-1, None] + np.diff(free)[:, None] * w).ravel(),
                               free[-1:]])
        rates0 = np.repeat(rates0, split, axis=0)
        M *= split
    N = next((tr.intervals for tr in ladder(n) if tr.intervals >= M), M)
    emap = end_map(ps.robot, N)
    # the end map's intervals are 1/N of normalised time: a piece of plan time L at rate g
    # moves as the rate g L N there
    scale = (np.diff(free) * N)[:, None]
    q_stop = _pieces_end(ps.robot, q_m, kept.breaks, kept.rates)
    U0 = np.zeros((N, 2))
    U0[N - M:] = rates0 * scale
    goal = ps.goal
    # with keep_reversals every rate keeps its sign (a rate that would change sign is held at
    # 0 instead: no reversal is added to phi or th1, which integrate them)
    signs = np.sign(rates0)
    held = np.zeros((M, 2), bool)
    best: tuple[float, np.ndarray] | None = None
    steps = 0
    for _ in range(MAX_HOLDS + 1):
        start = U0.copy()
        start[N - M:][held] = 0.0
        err, U, steps = _gauss_newton(emap, q_stop, goal, start, N - M, ~held)
        if err > 1e-6:
            break
        flipped = (signs != 0.0) & (np.sign(U[N - M:]) == -signs) & ~held
        if not keep_reversals or not flipped.any():
            best = (err, U)
            break
        held |= flipped
    if best is None:
        raise NumericalError("the Gauss-Newton correction of the later pieces' rates did not "
                             "reach the goal" + (" keeping their signs" if keep_reversals else
                                                 f" (miss {err:.3g} rad)"))
    new_rates = best[1][N - M:] / scale
    t_stop = kept.law.end if kept.law.phases.size else t
    if T_end == ps.end_time and split == 1 and not braked:
        later = ps.law.after(t_stop).phases
    else:
        later = _law_after_stop(t_stop, T_end, free)

    def refine(exact_end: np.ndarray, current: np.ndarray) -> np.ndarray:
        # the quadrature's end missed: one step aimed where the fine map must end for the
        # exact model to reach the goal (a defect correction)
        V = np.zeros((N, 2))
        V[N - M:] = current * scale
        r = exact_end[1:] - goal
        J = emap.jacobian(q_stop, V)[1:, 2 * (N - M):]
        return current - minimum_norm_step(J, r).reshape(M, 2) / scale

    return _assemble(kept, free, new_rates, later, ps.plan_duration, "gauss_newton", steps,
                     refine)


def sign_changes(rates: np.ndarray) -> int:
    """Sign changes of ``u1`` and of ``u2`` along pieces (zeros skipped): the reversals of
    ``phi`` and ``th1``, which integrate them."""
    total = 0
    for col in np.asarray(rates, float).T:
        nz = np.sign(col[np.abs(col) > 1e-12])
        total += int(np.sum(nz[1:] != nz[:-1]))
    return total


def _gauss_newton(emap: "EndMap", q0: np.ndarray, goal: np.ndarray, U: np.ndarray, first: int,
                  free: np.ndarray) -> tuple[float, np.ndarray, int]:
    """Gauss-Newton steps of least norm on the rates ``U[first:]`` where ``free`` (the others
    fixed) onto ``th(1) = goal``, each halved until the miss shrinks (a backtracking line
    search: near a reversal the Jacobian is ill-conditioned and a full step overshoots).
    Returns the miss (rad), the rates and the steps taken."""

    def miss(V: np.ndarray) -> tuple[float, np.ndarray]:
        r = emap.end(q0, V)[1:] - goal
        e = float(np.max(np.abs(r)))
        return (e if math.isfinite(e) else math.inf), r

    cols = np.concatenate([np.zeros(2 * first, bool), free.ravel()])
    err, r = miss(U)
    steps = 0
    while err > CORRECTION_TARGET and steps < MAX_STEPS and cols.any():
        J = emap.jacobian(q0, U)[1:, cols]
        if not np.all(np.isfinite(J)):
            break
        flat = np.zeros(U.size)
        try:
            flat[cols] = minimum_norm_step(J, r)
        except np.linalg.LinAlgError:
            break
        step = flat.reshape(U.shape)
        alpha = 1.0
        for _ in range(MAX_HALVINGS + 1):
            V = U - alpha * step
            e2, r2 = miss(V)
            if e2 < err:
                break
            alpha *= 0.5
        else:
            break
        U, err, r = V, e2, r2
        steps += 1
    return err, U, steps


def _assemble(kept: Kept, free: np.ndarray, new_rates: np.ndarray, later: np.ndarray,
              T0: float, route: str, steps: int, refine: Any = None) -> Continuation:
    if kept.pieces:
        breaks = np.concatenate([kept.breaks[:-1], free])
        rates = np.vstack([kept.rates, new_rates])
        phases = np.vstack([kept.law.phases, later])
    else:
        breaks, rates, phases = free.copy(), new_rates, later
        breaks[0] = kept.breaks[0]
    return Continuation(breaks, rates, TimeLaw(phases), T0, route, steps, kept.pieces, refine)


def _fallback(ps: PlanState, req: PlanRequest, t: float, q_m: np.ndarray, u_c: np.ndarray,
              T_end: float) -> Continuation:
    """Step 4 of the module: the kept motion (or a braking), then the full planner."""
    if ps.rates is not None:
        kept = _kept(ps, t, u_c)
        if kept.k >= ps.rates.shape[0]:
            kept = _braked(ps, t, u_c, T_end)
    elif float(np.max(np.abs(u_c))) > REST:
        Db = min(BRAKE_TIME, 0.5 * (T_end - t))
        kept = Kept(0, np.array([0.0, 0.5 * Db]), np.asarray(u_c, float)[None, :],
                    TimeLaw(braking(t, Db, 0.0)))
    else:
        kept = Kept(0, np.array([0.0]), np.zeros((0, 2)), TimeLaw(np.zeros((0, 6))))
    q_stop = _pieces_end(ps.robot, q_m, kept.breaks, kept.rates)
    t_stop = kept.law.end if kept.law.phases.size else t
    if T_end - t_stop <= 1e-9:
        raise NumericalError("nothing is left after the current motion's stop to correct the "
                             "miss: give a later duration", field="duration")
    lo, hi = joint_limits(req)
    if not (np.all(np.isfinite(q_stop)) and np.all(q_stop[1:] > lo) and np.all(q_stop[1:] < hi)):
        raise InfeasibleError("the motion under way leaves the region before its next stop: "
                              "no continuation starts there", field="state")
    sub = replace(req, start=tuple(q_stop[1:]), phi_start=float(q_stop[0]), duration=None,
                  method="shooting", samples=11)
    try:
        p = full_plan(sub)
    except PlannerError:
        p = full_plan(replace(sub, method="penalty"))
    sched = p.inputs
    breaks = kept.s_stop + np.asarray(sched.breaks, float)   # its plan time after the stop
    rates = np.asarray(sched.rates, float)                    # type: ignore[union-attr]
    later = _law_after_stop(t_stop, T_end, breaks)
    return _assemble(kept, breaks, rates, later, kept.s_stop + float(sched.breaks[-1]),
                     "full_planner", 0)


def _piece(breaks: np.ndarray, s: np.ndarray) -> np.ndarray:
    return np.clip(np.searchsorted(breaks, s, side="right") - 1, 0, breaks.size - 2)


def _replay(robot: Robot, q_m: np.ndarray, cont: Continuation, rates: np.ndarray,
            s_eval: np.ndarray) -> Any:
    sb = cont.breaks - cont.breaks[0]
    L = float(sb[-1])
    return integrate_cascade(robot, lambda s: rates[_piece(sb, s)], q_m, L,
                             np.clip(np.concatenate([sb, s_eval]), 0.0, L), sb,
                             nodes=REPLAY_NODES, initial_panels=1, constant_pieces=True)


def _finish(ps: PlanState, req: PlanRequest, t: float, q_m: np.ndarray, u_c: np.ndarray,
            cont: Continuation, timing: dict[str, float]) -> dict[str, Any]:
    """Verify a continuation on the original model and answer it in a plan's shape.

    Raises
    ------
    InfeasibleError
        A joint leaves its limits (checked at every break: each joint is monotone on a piece
        of constant rates).
    NumericalError
        The exact pieces, or the handed-out form, miss the goal by more than
        :data:`~.rules.TERMINAL_TOLERANCE`.
    """
    t0 = time.perf_counter()
    robot, n, goal = ps.robot, ps.robot.n, ps.goal
    law = cont.law
    T_end = law.end
    sb = cont.breaks - cont.breaks[0]
    # the handed-out times: an even grid and every phase start; where the rates jump (a break
    # passed at speed: plans without a time law) the time is there twice
    times = np.unique(np.concatenate([np.linspace(t, T_end, ps.samples), law.phases[:, 0],
                                      [T_end]]))
    times = times[times >= t]
    sig, ds, _ = law.evaluate(times)
    # at the stops sigma' is 0 up to rounding of the cubics: the drive is told exactly 0
    ds[np.abs(ds) <= 1e-12 * max(1.0, float(np.max(np.abs(ds))))] = 0.0
    sl = np.clip(sig - cont.breaks[0], 0.0, float(sb[-1]))
    ph = law.phases
    jump_t = ph[(ph[:, 3] > REST) & np.isin(ph[:, 2], cont.breaks[1:-1]) & (ph[:, 0] > t), 0]
    rates = cont.rates
    rep = _replay(robot, q_m, cont, rates, sl)
    miss = float(np.max(np.abs(rep.final[1:] - goal))) if rep.success else math.inf
    if cont.refine is not None and rep.success and miss > 1e-9:
        free = cont.refine(rep.final, rates[cont.kept:])
        again = np.vstack([rates[:cont.kept], free])
        rep2 = _replay(robot, q_m, cont, again, sl)
        miss2 = float(np.max(np.abs(rep2.final[1:] - goal))) if rep2.success else math.inf
        if miss2 < miss:
            rep, miss, rates = rep2, miss2, again
    timing["verification"] = time.perf_counter() - t0
    if not rep.success or rep.singular:
        raise NumericalError(f"the continuation's re-integration failed: {rep.message}")
    lo, hi = joint_limits(req)
    qb = rep.q[:sb.size, 1:]
    margins = np.minimum(qb - lo, hi - qb)
    margin = float(np.min(margins))
    if not margin > 0.0:
        j = int(np.unravel_index(int(np.argmin(margins)), margins.shape)[1])
        raise InfeasibleError(f"the continuation takes th{j + 1} outside its limits",
                              diagnostics={"margin": margin})
    if not miss <= TERMINAL_TOLERANCE:
        raise NumericalError(f"the continuation misses the goal by {miss:.3g} rad",
                             diagnostics={"terminal_error": miss})
    q = rep.q[sb.size:]
    k = _piece(sb, sl)
    u = rates[k] * ds[:, None]
    u[0] = u_c          # the commanded rates (equal to the plan's up to rounding)
    if jump_t.size:     # the rate before each jump, as the linear form's first copy
        at = np.searchsorted(times, jump_t)
        before = rates[np.maximum(k[at] - 1, 0)] * ds[at][:, None]
        times = np.insert(times, at, jump_t)
        q = np.insert(q, at, q[at], axis=0)
        u = np.insert(u, at, before, axis=0)
    cf = chained_form(robot)
    al, be = cf.input_coefficients(q)
    v = np.column_stack([u[:, 0], al * u[:, 0] + be * u[:, 1]])
    smooth_law = not law.piecewise_linear
    exe_initial = None
    corrections = 0
    if smooth_law:
        # continuous rates: linear interpolation of their samples is not the exact rates; the
        # samples are corrected until the original model under that rule reaches the goal
        # (optimizer.execution.correct), the first (the commanded rates) and the last (rest)
        # held
        form = linear_form(times - t)
        free = form.free.copy()
        free[0] = free[-1] = False
        form = replace(form, free=free)
        target = np.concatenate([[rep.final[0]], goal])
        u, q, check = correct(robot, form, u, q_m, target, limits_region(req), times - t)
        exe_final = np.asarray(check.final)
        exe_integrator = check.integrator
        exe_initial, corrections = check.initial_terminal_error, check.corrections
        if not check.terminal_error <= EXECUTION_TOLERANCE or check.singular or \
                not check.margin > 0.0:
            raise NumericalError(
                f"the handed-out path of {times.size} samples misses the goal by "
                f"{check.terminal_error:.3g} rad when executed (margin {check.margin:.3g} rad)",
                diagnostics={"execution": check.as_dict()})
        al, be = cf.input_coefficients(q)
        v = np.column_stack([u[:, 0], al * u[:, 0] + be * u[:, 1]])
    else:
        exe_final, exe_integrator = rep.final, rep.integrator
    exe_err = float(np.max(np.abs(exe_final[1:] - goal)))
    ind = compute_indicators(times, q, u)
    timing["sampling"] = time.perf_counter() - t0 - timing["verification"]
    out: dict[str, Any] = {
        "status": "success",
        "method": "replan",
        "robot": robot.as_dict(),
        "goal": goal.tolist(),
        "time": t,
        "phi_change": float(rep.final[0] - q_m[0]),
        "b0": None,
        "duration": T_end,
        "feasible_phi_changes": [],
        "coefficients": {
            "basis": "actuator rates u = (u1, u2) (rad per s of plan time) constant on each "
                     "segment of plan time sigma; the rates at time t are u(sigma(t)) "
                     "sigma'(t) (time_law)",
            "segments": [{"t_start": float(a), "t_end": float(b), "v1": [float(r[0])],
                          "v2": [], "u": [float(r[0]), float(r[1])]}
                         for a, b, r in zip(cont.breaks[:-1], cont.breaks[1:], rates)]},
        "time_law": law.as_dict(cont.plan_duration, cont.breaks),
        "indicators": {
            "d_a": ind.d_a, "d_a_per_joint": list(ind.d_a_per_joint),
            "d_a_joint_space": ind.d_a_joint_space, "t_p": ind.t_p,
            "phi_reversals": ind.phi_reversals, "sensitivity": ind.sensitivity,
            "sensitivity_max": ind.sensitivity_max, "energy": ind.energy, "margin": margin,
            "deviation": ind.deviation,
            "reversals": {"phi": ind.reversals_phi, "th1": ind.reversals_th1}},
        "path": {"t": times, "q": q, "z": cf.to_chained(q), "u": u, "v": v, "rule": "linear"},
        "validation": {
            "terminal_error": miss, "phi_error": 0.0, "max_deviation": 0.0, "singular": False,
            "final": rep.final.tolist(), "integrator": f"{rep.integrator} on the original model",
            "error_estimate": rep.error_estimate, "rtol": None, "atol": None,
            "executed": {"rule": "linear", "terminal_error": exe_err, "phi_error":
                         float(abs(exe_final[0] - rep.final[0])), "margin": margin,
                         "singular": False, "initial_terminal_error":
                         exe_err if exe_initial is None else exe_initial,
                         "corrections": corrections, "integrator": f"{exe_integrator} on the original "
                         "model", "final": exe_final.tolist()}},
        "timing": dict(timing),
        "diagnostics": {"replan": {
            "route": cont.route, "gauss_newton_steps": cont.steps,
            "kept_piece": bool(cont.kept), "pieces": int(rates.shape[0]),
            "commanded_rates": [float(x) for x in u_c],
            "start_state": q_m.tolist()}},
    }
    return out


__all__ = ["PlanState", "TimeLaw", "braking", "read_plan", "replan", "rest_to_rest"]
