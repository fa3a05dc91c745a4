"""What the replanner reads of a plan: its geometric pieces and its time law.

An answer of ``/v1/plans`` (or ``/v1/replans``, or its compact form) hands out its plan's
exact rates ``u_plan`` on plan time ``sigma`` (``coefficients.segments``) and the time law
that runs them (``time_law``: ``lam(t)`` as phases of constant jerk, ``sigma`` linear in
``lam`` on each knot piece; :meth:`optimizer.timing.TimeLaw.as_dict`). :func:`read_plan` checks
such a dict and turns it into a :class:`PlanState`: the path's pieces on ``lam`` with their
rates per unit ``lam`` (on a piece ``g = slope * u_plan``: the same displacement), and the
law as rows. Laws built here for continuations (:func:`rest_to_rest`, :func:`braking`) use
the same rows.
"""

from __future__ import annotations

import bisect
import functools
import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from ..errors import InvalidRequestError, PlannerError
from ..model import Robot
from ..results import Plan, json_safe
from ..timing import RAMP, Limits, ramp_profile

#: Samples of the handed-out continuation (fewer when less time is left, at least 2 per piece).
DEFAULT_SAMPLES = 101
#: A segment whose rates move an actuator by more than this (rad, rate times the segment's
#: length) is no plan of ours (the NLPs bound each actuator's travel over the whole path to
#: 40 rad). A bound on the rates themselves would refuse our own continuations: their rates
#: are per second of plan time, and the time law runs a tail piece of 6e-6 s of plan time
#: at 1e4 rad/s of it as 2 rad/s of the robot's.
MAX_SEGMENT_TRAVEL = 1e3
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
        # (np.minimum/np.maximum: np.clip costs 2-3 us a call, and a replan makes dozens)
        return np.minimum(np.maximum(k, 0), self.phases.shape[0] - 1)

    def evaluate(self, t: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(sigma, sigma', sigma'')`` at times ``t`` (exact: cubics)."""
        t = np.asarray(t, float)
        P = self.phases[self._phase(t)]
        s = t - P[..., 0]
        j = P[..., 5]
        ds = P[..., 3] + P[..., 4] * s + 0.5 * j * s * s
        sig = P[..., 2] + P[..., 3] * s + 0.5 * P[..., 4] * s * s + j * s ** 3 / 6.0
        return sig, ds, P[..., 4] + j * s

    def at(self, t: float) -> tuple[float, float, float]:
        """``(sigma, sigma', sigma'')`` at one time ``t``: :meth:`evaluate`'s operations on
        floats (a replan reads the law at single times several times; an array of one costs
        about 15 us a call, this about 2)."""
        k = self._phase_at(t)
        t0, _, s0, v0, a0, j = self.phases[k].tolist()
        s = t - t0
        return (s0 + v0 * s + 0.5 * a0 * s * s + j * s ** 3 / 6.0,
                v0 + a0 * s + 0.5 * j * s * s, a0 + j * s)

    def _phase_at(self, t: float) -> int:
        k = bisect.bisect_right(self._starts, t) - 1
        return min(max(k, 0), len(self._starts) - 1)

    @functools.cached_property
    def _starts(self) -> list[float]:
        return self.phases[:, 0].tolist()

    def after(self, t: float) -> "TimeLaw":
        """The law from ``t`` on (the phase holding ``t`` cut there)."""
        k = self._phase_at(t)
        sig, ds, dds = self.at(t)
        first = [t, float(self.phases[k, 0] + self.phases[k, 1] - t), sig, ds, dds,
                 float(self.phases[k, 5])]
        rows = np.vstack([first, self.phases[k + 1:]])
        return TimeLaw(rows[rows[:, 1] > 0.0] if rows.shape[0] > 1 else rows)

    def last_sigma(self) -> float:
        """``sigma`` at the law's end: its last phase's cubic at its length, in floats."""
        _, s, s0, v0, a0, j = self.phases[-1].tolist()
        return s0 + v0 * s + 0.5 * a0 * s * s + j * s ** 3 / 6.0

    def as_dict(self, plan_duration: float, breaks: np.ndarray,
                limits: Limits | None = None) -> dict[str, Any]:
        """The answer's ``time_law`` in the shape of :meth:`optimizer.timing.TimeLaw.as_dict`
        (here ``lam = sigma``: knots of slope 1 at the pieces' ``breaks``); ``stops`` are the
        phase starts at rest and the end; ``limits`` the rate bounds it keeps to (carried
        from the plan: a continuation of this answer keeps to them too)."""
        P = self.phases
        stops = P[np.abs(P[:, 3]) <= REST, 0].tolist() + [self.end]
        return {"rule": LAW_RULE, "plan_duration": plan_duration, "stops": stops,
                "knots": {"lam": breaks, "sigma": breaks, "slope": np.ones(breaks.size - 1)},
                "phases": {"start": P[:, 0], "length": P[:, 1], "lam0": P[:, 2],
                           "v0": P[:, 3], "a0": P[:, 4], "jerk": P[:, 5]},
                "shortest_duration": None, "binding_limit": None,
                "limits": {} if limits is None else limits.as_dict()}

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
        keys = ("start", "length", "lam0", "v0", "a0", "jerk")
        try:
            ph, kn = law["phases"], law["knots"]
            try:    # the six columns in one conversion (a replan reads a law every call)
                table = np.array([ph[k] for k in keys], dtype=float)
            except (ValueError, TypeError):
                table = np.zeros((0,))
            if table.ndim == 2 and bool(np.isfinite(table).all()):
                cols = list(table)
            else:   # the column that is not a list of finite numbers, by name
                cols = [finite_array(ph[k], f"plan.time_law.phases.{k}") for k in keys]
            lam_k = finite_array(kn["lam"], "plan.time_law.knots.lam")
            sig_k = finite_array(kn["sigma"], "plan.time_law.knots.sigma")
            slope = finite_array(kn["slope"], "plan.time_law.knots.slope")
        except (KeyError, TypeError):
            raise invalid("plan.time_law must hold knots (lam, sigma, slope) and phases (start, "
                       "length, lam0, v0, a0, jerk)", "plan.time_law") from None
        sizes = {c.shape for c in cols}
        if (len(sizes) != 1 or cols[0].ndim != 1 or not cols[0].size or lam_k.ndim != 1
                or lam_k.size < 2 or lam_k.shape != sig_k.shape
                or slope.shape != (lam_k.size - 1,) or (cols[1] <= 0.0).any()
                or not (lam_k[1:] > lam_k[:-1]).all() or not (slope > 0.0).all()):
            raise invalid("plan.time_law's phases and knots are not a law of this library",
                       "plan.time_law")
        gaps = cols[0][1:] - cols[0][:-1] - cols[1][:-1]
        if gaps.size and float(np.abs(gaps).max()) > 1e-9:
            raise invalid("plan.time_law.phases must be contiguous", "plan.time_law.phases")
        return cls(np.ascontiguousarray(np.stack(cols, axis=1))), lam_k, sig_k, slope

    @property
    def piecewise_linear(self) -> bool:
        """No jerk phase: constant-direction rates are linear between the phase starts, and
        the linear form with samples there holds them exactly."""
        return not bool((self.phases[:, 5] != 0.0).any())


def read_limits(given: Any) -> Limits:
    """An answer's ``time_law.limits`` (``{"max_u1": ..., ...}``) as :class:`Limits`.

    Raises
    ------
    InvalidRequestError
        Not such a mapping of positive finite numbers (``plan.time_law.limits``).
    """
    if given is None:
        return Limits()
    if not isinstance(given, Mapping):
        raise invalid("plan.time_law.limits must map max_u1, ... to numbers",
                      "plan.time_law.limits")
    known = {name for names in Limits.NAMES for name in names}
    values: dict[str, float] = {}
    for name, value in given.items():
        if name not in known:
            raise invalid(f"plan.time_law.limits has an unknown bound {name!r} (known: "
                          f"{', '.join(sorted(known))})", "plan.time_law.limits")
        if value is None:
            continue
        try:
            v = float(value)
        except (TypeError, ValueError):
            v = math.nan
        if not (math.isfinite(v) and v > 0.0):
            raise invalid(f"plan.time_law.limits.{name} must be a positive number",
                          "plan.time_law.limits")
        values[name] = v
    pairs = [tuple(values.get(name) for name in names) for names in Limits.NAMES]
    return Limits(*pairs)  # type: ignore[arg-type]


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
    return TimeLaw(law_after_stop(t0, t0 + T, b))


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
    limits : Limits
        The rate bounds the plan keeps to (its ``time_law.limits``).
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
    limits: Limits = Limits()

    @property
    def start_time(self) -> float:
        return self.law.start

    def piece_at(self, s: float) -> int:
        """The index of the rate piece that holds the path parameter ``s`` (its last piece
        at and beyond the end; needs ``rates``)."""
        assert self.rates is not None
        return min(max(int(np.searchsorted(self.breaks, s, side="right")) - 1, 0),
                   self.rates.shape[0] - 1)

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
            "time_law": self.law.as_dict(self.plan_duration, self.breaks, self.limits),
        }
        if self.joint_bounds is not None:
            out["joint_bounds"] = [None if b is None else list(b) for b in self.joint_bounds]
        return json_safe(out)  # type: ignore[no-any-return]


def invalid(message: str, field: str) -> InvalidRequestError:
    return InvalidRequestError(message, field=field)


def finite_array(x: Any, field: str, shape: tuple[int, ...] | None = None) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise invalid(f"{field} must hold numbers", field) from None
    # (the array's methods: np.all and the like cost about a microsecond more a call, and a
    # replan reads some twenty arrays)
    if not np.isfinite(a).all() or (shape is not None and a.shape != shape):
        raise invalid(f"{field} must be {'finite numbers' if shape is None else f'{shape} finite numbers'}",
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
        raise invalid(f"plan is not an answer of this service ({type(exc).__name__}: "
                   f"{str(exc)[:120]})", "plan") from None


def _read(plan: Any) -> PlanState:
    if not isinstance(plan, Mapping):
        raise invalid("plan must be an answer of /v1/plans or /v1/replans", "plan")
    if plan.get("status", "success") != "success":
        raise invalid("plan is not a successful answer (status must be 'success')", "plan.status")
    rob = plan.get("robot")
    if not isinstance(rob, Mapping) or rob.get("gains") is None or rob.get("exponents") is None:
        raise invalid("plan.robot must give gains and exponents (as answers do)", "plan.robot")
    try:
        robot = Robot(tuple(rob["gains"]), tuple(rob["exponents"]))
    except PlannerError as exc:
        raise invalid(exc.message, "plan.robot") from None
    except (TypeError, ValueError):
        raise invalid("plan.robot.gains and exponents must be lists of numbers", "plan.robot") from None
    n = robot.n
    if plan.get("goal") is not None:
        goal = finite_array(plan["goal"], "plan.goal", (n,))
    else:
        final = (plan.get("validation") or {}).get("final")
        if final is None:
            raise invalid("plan has neither goal nor validation.final", "plan.goal")
        goal = finite_array(final, "plan.validation.final", (n + 1,))[1:]
    segs = (plan.get("coefficients") or {}).get("segments")
    if not isinstance(segs, list) or not segs:
        raise invalid("plan.coefficients.segments must list the plan's input pieces",
                   "plan.coefficients.segments")
    try:
        breaks = np.array([float(s["t_start"]) for s in segs] + [float(segs[-1]["t_end"])])
        ends = np.array([float(s["t_end"]) for s in segs])
    except (KeyError, TypeError, ValueError):
        raise invalid("each segment needs t_start and t_end", "plan.coefficients.segments") from None
    if (not np.isfinite(breaks).all() or not (breaks[1:] > breaks[:-1]).all()
            or (ends.size > 1 and float(np.abs(ends[:-1] - breaks[1:-1]).max()) > 1e-12)):
        raise invalid("plan.coefficients.segments must be contiguous pieces in time order",
                   "plan.coefficients.segments")
    rates: np.ndarray | None = None
    if all(isinstance(s.get("u"), list) and len(s["u"]) == 2 for s in segs):
        rates = finite_array([s["u"] for s in segs], "plan.coefficients.segments", (len(segs), 2))
        if float((np.abs(rates) * (breaks[1:] - breaks[:-1])[:, None]).max()) > MAX_SEGMENT_TRAVEL:
            raise invalid(f"plan.coefficients.segments move an actuator by more than "
                          f"{MAX_SEGMENT_TRAVEL:g} rad: not a plan of this service",
                          "plan.coefficients.segments")
    T0 = float(breaks[-1])
    law_d = plan.get("time_law")
    if law_d is None:
        law = TimeLaw.identity(breaks)
    elif isinstance(law_d, Mapping):
        law, lam_k, sig_k, slope = TimeLaw.from_answer(law_d)
        if abs(law.last_sigma() - lam_k[-1]) > 1e-7 * max(1.0, lam_k[-1]):
            raise invalid("plan.time_law's phases do not end at its last knot", "plan.time_law")
        if rates is not None:
            # the path on lam: each knot piece at the rate of its segment times its slope
            if abs(sig_k[-1] - breaks[-1]) > 1e-9 * max(1.0, breaks[-1]) or sig_k[0] != breaks[0]:
                raise invalid("plan.time_law.knots.sigma must span the segments",
                           "plan.time_law.knots")
            seg = np.minimum(np.maximum(np.searchsorted(breaks, 0.5 * (sig_k[:-1] + sig_k[1:]),
                                                        side="right") - 1, 0), rates.shape[0] - 1)
            rates = rates[seg] * slope[:, None]
            breaks = lam_k.copy()
            T0 = float(lam_k[-1])
    else:
        raise invalid("plan.time_law must be an object (the answer's)", "plan.time_law")
    dur = plan.get("duration")
    if dur is not None and abs(float(dur) - law.end) > 1e-7 * max(1.0, law.end):
        raise invalid(f"plan.duration {float(dur):.9g} s is not the end of its time law "
                   f"({law.end:.9g} s)", "plan.duration")
    jb = plan.get("joint_bounds")
    bounds = None if jb is None else tuple(None if b is None else (float(b[0]), float(b[1]))
                                           for b in jb)
    path = plan.get("path") or {}
    pt = pu = None
    if rates is None:
        if path.get("t") is None or path.get("u") is None:
            raise invalid("a plan of chained inputs needs its path (t, u) to be continued",
                       "plan.path")
        pt = finite_array(path["t"], "plan.path.t")
        pu = finite_array(path["u"], "plan.path.u")
    given_t = path.get("t")
    samples = int(plan.get("samples") or (0 if given_t is None else len(given_t))
                  or DEFAULT_SAMPLES)
    limits = read_limits(law_d.get("limits")) if isinstance(law_d, Mapping) else Limits()
    return PlanState(robot=robot, goal=goal, breaks=breaks, rates=rates, law=law,
                     plan_duration=T0, joint_bounds=bounds,
                     samples=min(max(samples, 11), DEFAULT_SAMPLES), path_t=pt, path_u=pu,
                     jumps=law_d is None, limits=limits)



def law_after_stop(t_stop: float, T_end: float, breaks: np.ndarray,
                   equal: bool = False) -> np.ndarray:
    """Rows of :func:`rest_to_rest` laws of pieces ``breaks`` run from ``t_stop`` to
    ``T_end``, durations in proportion to their plan time (``equal``: all the same)."""
    breaks = np.asarray(breaks, float)
    L = breaks[1:] - breaks[:-1]
    D = (T_end - t_stop) * (np.full(L.size, 1.0 / L.size) if equal else L / L.sum())
    t0 = np.empty(L.size)
    t0[0] = t_stop
    t0[1:] = t_stop + D[:-1].cumsum()
    D[-1] = T_end - t0[-1]      # the law ends at T_end exactly (not at a rounded sum)
    # ramp_profile of every piece at once: accelerate for r D, cruise, brake for r D
    r = RAMP
    v = L / ((1.0 - r) * D)
    A = v / (r * D)
    s0 = breaks[:-1]
    ramp = 0.5 * A * (r * D) ** 2
    # the three phases of every piece, in order (filled in place: stacking columns cost a
    # replan about 15 us)
    rows = np.zeros((L.size, 3, 6))
    rows[:, 0, 0], rows[:, 0, 1], rows[:, 0, 2], rows[:, 0, 4] = t0, r * D, s0, A
    rows[:, 1, 0], rows[:, 1, 1], rows[:, 1, 2], rows[:, 1, 3] = (
        t0 + r * D, (1.0 - 2.0 * r) * D, s0 + ramp, v)
    rows[:, 2, 0], rows[:, 2, 1], rows[:, 2, 3], rows[:, 2, 4] = t0 + (1.0 - r) * D, r * D, v, -A
    rows[:, 2, 2] = s0 + ramp + v * (1.0 - 2.0 * r) * D
    return rows.reshape(-1, 6)


__all__ = ["DEFAULT_SAMPLES", "LAW_RULE", "MAX_SEGMENT_TRAVEL", "PlanState", "REST", "TimeLaw",
           "braking", "finite_array", "invalid", "law_after_stop", "read_limits",
           "read_plan",
           "rest_to_rest", "stop_and_go"]
