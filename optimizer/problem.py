"""A plan request as the library sees it (validated, radians and seconds).

The service translates its JSON models into :class:`PlanRequest`; the CLI reads the same JSON.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from .errors import InfeasibleError, InvalidRequestError
from .model import Robot
from .steering import ConstraintPoint, validate_constraint_points
from .via_points import ViaPoint, validate_via_points, via_points_from

OBJECTIVES = ("reversals_then_deviation", "tp_then_da", "tp_then_sensitivity", "weighted")
#: Fewest actuator reversals (phi and th1), then the smallest joint-space deviation from the
#: straight segment start -> goal (see :mod:`optimizer.planner.ranking`).
DEFAULT_OBJECTIVE = "reversals_then_deviation"
CRITERIA = ("full", "z2")

#: Library-level limits (the service may set tighter ones).
MAX_SAMPLES = 20001
MIN_SAMPLES = 2
MAX_CONSTRAINT_POINTS = 8
MAX_DURATION = 1e4
MIN_DURATION = 1e-3
MAX_TIME_LIMIT = 600.0
#: Shortest controller period (s).
MIN_CONTROLLER_PERIOD = 1e-4
#: Largest ``max_reversals`` (the finest transcription has 50 intervals per actuator).
MAX_REVERSALS = 100


@dataclass(frozen=True)
class Weights:
    """Weights of the ``weighted`` objective: ``w_da d_a + w_s ||J_R(T)||_F + w_e energy``.

    Plus ``tp`` (weight on t_p, default large so that reversals dominate unless told otherwise).
    """

    d_a: float = 1.0
    sensitivity: float = 0.0
    energy: float = 0.0
    t_p: float = 0.0


@dataclass(frozen=True)
class PlanRequest:
    """Everything a plan needs.

    Parameters
    ----------
    start, goal : tuple of float
        Joint angles ``th_1..th_n`` (rad).
    robot : Robot
    phi_start : float
        Initial ``phi`` (rad).
    phi_change : float or None
        Fixes ``dphi = phi(T) - phi(0)``; ``None`` searches ``phi_change_bounds``.
    phi_change_bounds : (float, float)
    duration : float or None
        ``T`` (s). ``None`` with actuator limits: the shortest ``T`` that respects them;
        ``None`` without: 1 s.
    method : str
        A name of :mod:`optimizer.planner.registry` (checked by the planner).
    objective, singularity : str
    weights : Weights
    constraint_points : tuple of ConstraintPoint
        Values of the chained states ``z_k`` at times (the paper's family only).
    via_points : tuple of ViaPoint
        Joint-space via points: joint ``th_j`` at an angle (rad) at a time (s) of the
        answer's time axis (:mod:`optimizer.via_points`); honoured exactly by ``shooting``
        and ``penalty`` (``auto`` runs only those), refused by the paper's family.
    samples : int
        Number of time samples in the returned path.
    time_limit : float
        Seconds for the whole solve.
    max_u1, max_u2 : float or None
        Actuator rate limits (rad/s).
    max_du1, max_du2 : float or None
        Limits of the rates' derivatives, ``|u_i'|`` (rad/s^2).
    max_ddu1, max_ddu2 : float or None
        Limits of the rates' second derivatives, ``|u_i''|`` (rad/s^3). With any limit and no
        ``duration`` the answer runs its path in the shortest time within them
        (:mod:`optimizer.timing`).
    joint_bounds : tuple of (lo, hi) or None
    controller_period : float or None
        Period (s) of a controller that holds each rate for one period: the returned path is
        then on the grid ``k * period`` (the last point ``T``) under zero-order hold, planned
        for it (:mod:`optimizer.execution`). ``None``: ``samples`` evenly spaced times plus the
        input breaks twice, linear interpolation.
    joint_trajectory : bool
        Also return the ROS ``trajectory_msgs/JointTrajectory`` form (cubic Hermite).
    max_reversals : int or None
        A budget of actuator direction changes (``phi`` and ``th_1`` together, as
        ``indicators.reversals`` counts them): the straightest verified path with at most that
        many (:mod:`optimizer.planner.budget`). ``None``: the objective decides.
    pareto : bool
        Also return the non-dominated plans over (reversals, deviation).
    """

    start: tuple[float, ...]
    goal: tuple[float, ...]
    robot: Robot = field(default_factory=Robot)
    phi_start: float = 0.0
    phi_change: float | None = None
    phi_change_bounds: tuple[float, float] = (-math.pi, math.pi)
    duration: float | None = None
    method: str = "auto"
    objective: str = DEFAULT_OBJECTIVE
    singularity: str = "full"
    weights: Weights = field(default_factory=Weights)
    constraint_points: tuple[ConstraintPoint, ...] = ()
    via_points: tuple[ViaPoint, ...] = ()
    samples: int = 201
    time_limit: float = 10.0
    max_u1: float | None = None
    max_u2: float | None = None
    max_du1: float | None = None
    max_du2: float | None = None
    max_ddu1: float | None = None
    max_ddu2: float | None = None
    joint_bounds: tuple[tuple[float, float] | None, ...] | None = None
    controller_period: float | None = None
    joint_trajectory: bool = False
    max_reversals: int | None = None
    pareto: bool = False

    def __post_init__(self) -> None:
        n = self.robot.n
        for name in ("start", "goal"):
            val = angles_of(getattr(self, name), name)
            if len(val) != n:
                raise InvalidRequestError(f"{name} has {len(val)} joint angles but the robot has "
                                          f"n = {n} joints", field=name)
            for i, x in enumerate(val):
                if not math.isfinite(x):
                    raise InvalidRequestError(f"{name}[{i}] must be a finite number (rad)",
                                              field=f"{name}[{i}]")
            found = joint_angles_problem(name, val)
            if found is not None:
                raise InvalidRequestError(found[1], field=found[0])
            object.__setattr__(self, name, val)
        _finite(self.phi_start, "phi_start")
        if self.phi_change is not None:
            _finite(self.phi_change, "phi_change")
        lo, hi = (float(x) for x in self.phi_change_bounds)
        _finite(lo, "phi_change_bounds[0]")
        _finite(hi, "phi_change_bounds[1]")
        if not lo < hi or max(abs(lo), abs(hi)) > 4 * math.pi:
            raise InvalidRequestError(
                f"phi_change_bounds = [{lo}, {hi}] must satisfy lo < hi within [-4 pi, 4 pi] rad",
                field="phi_change_bounds")
        object.__setattr__(self, "phi_change_bounds", (lo, hi))
        if self.duration is not None:
            _finite(self.duration, "duration")
            if not MIN_DURATION <= self.duration <= MAX_DURATION:
                raise InvalidRequestError(
                    f"duration = {self.duration} s must lie in [{MIN_DURATION}, {MAX_DURATION}] s",
                    field="duration")
        # the method's name is checked against the planner's registry, where methods live
        if not isinstance(self.method, str) or not self.method:
            raise InvalidRequestError("method must be a method's name", field="method")
        for name, allowed in (("objective", OBJECTIVES),
                              ("singularity", CRITERIA)):
            if getattr(self, name) not in allowed:
                raise InvalidRequestError(f"{name} = {getattr(self, name)!r} must be one of "
                                          f"{list(allowed)}", field=name)
        if isinstance(self.weights, Mapping):
            unknown = set(self.weights) - {"d_a", "sensitivity", "energy", "t_p"}
            if unknown:
                raise InvalidRequestError(f"unknown weights {sorted(unknown)}", field="weights")
            object.__setattr__(self, "weights", Weights(**{k: float(v) for k, v in
                                                            self.weights.items()}))
        w = self.weights
        for k in ("d_a", "sensitivity", "energy", "t_p"):
            x = getattr(w, k)
            if not (math.isfinite(x) and x >= 0):
                raise InvalidRequestError(f"weights.{k} = {x} must be finite and >= 0",
                                          field=f"weights.{k}")
        if self.objective == "weighted" and w.d_a + w.sensitivity + w.energy + w.t_p <= 0:
            raise InvalidRequestError("weights must not all be 0 for the weighted objective",
                                      field="weights")
        if not MIN_SAMPLES <= int(self.samples) <= MAX_SAMPLES:
            raise InvalidRequestError(f"samples = {self.samples} must lie in [{MIN_SAMPLES}, "
                                      f"{MAX_SAMPLES}]", field="samples")
        if not (math.isfinite(self.time_limit) and 0 < self.time_limit <= MAX_TIME_LIMIT):
            raise InvalidRequestError(f"time_limit = {self.time_limit} s must lie in (0, "
                                      f"{MAX_TIME_LIMIT}] s", field="time_limit")
        for name, unit in (("max_u1", "rad/s"), ("max_u2", "rad/s"), ("max_du1", "rad/s^2"),
                           ("max_du2", "rad/s^2"), ("max_ddu1", "rad/s^3"),
                           ("max_ddu2", "rad/s^3")):
            x = getattr(self, name)
            if x is not None and not (isinstance(x, (int, float)) and not isinstance(x, bool)
                                      and math.isfinite(x) and x > 0):
                raise InvalidRequestError(f"{name} = {x} must be finite and > 0 ({unit})",
                                          field=name)
        if len(self.constraint_points) > MAX_CONSTRAINT_POINTS:
            raise InvalidRequestError(f"at most {MAX_CONSTRAINT_POINTS} constraint_points",
                                      field="constraint_points")
        if self.constraint_points:
            validate_constraint_points(self.constraint_points, n, self.duration_or_default)
        if self.joint_bounds is not None:
            found = joint_bounds_problem(self.joint_bounds, self.start, self.goal)
            if found is not None:
                i = int(found[0].split("[")[1].rstrip("]"))
                raise InvalidRequestError(found[1], field=found[0], diagnostics={
                    "joint": f"th{i + 1}", "bound": list(self.joint_bounds[i] or ()),
                    "start": self.start[i] if i < len(self.start) else None,
                    "goal": self.goal[i] if i < len(self.goal) else None})
            from .region import Region  # validates shape and that bounds lie in the region
            Region(self.robot, "full", self.joint_bounds)
        if self.controller_period is not None:
            _finite(self.controller_period, "controller_period")
            period = float(self.controller_period)
            if not MIN_CONTROLLER_PERIOD <= period <= MAX_DURATION / 2:
                raise InvalidRequestError(
                    f"controller_period = {period} s must lie in [{MIN_CONTROLLER_PERIOD}, "
                    f"{MAX_DURATION / 2:g}] s", field="controller_period")
            if self.duration is not None:
                if period > 0.5 * self.duration:
                    raise InvalidRequestError(
                        f"controller_period = {period} s must be at most half the duration "
                        f"({self.duration} s)", field="controller_period")
                if math.ceil(self.duration / period * (1 - 1e-12)) + 1 > MAX_SAMPLES:
                    raise InvalidRequestError(
                        f"controller_period = {period} s gives more than {MAX_SAMPLES} "
                        f"samples over the duration {self.duration} s",
                        field="controller_period")
            object.__setattr__(self, "controller_period", period)
        if not isinstance(self.joint_trajectory, bool):
            raise InvalidRequestError("joint_trajectory must be true or false",
                                      field="joint_trajectory")
        if self.max_reversals is not None:
            budget = self.max_reversals
            if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or not \
                    0 <= int(budget) <= MAX_REVERSALS:
                raise InvalidRequestError(
                    f"max_reversals = {budget!r} must be a whole number in [0, "
                    f"{MAX_REVERSALS}] (direction changes of phi and th1 together)",
                    field="max_reversals")
            object.__setattr__(self, "max_reversals", int(budget))
        if not isinstance(self.pareto, bool):
            raise InvalidRequestError("pareto must be true or false", field="pareto")
        self._check_via_points()

    def _check_via_points(self) -> None:
        """Via points: their own checks (:func:`~optimizer.via_points.validate_via_points`),
        and the options they cannot be combined with."""
        vias = via_points_from(self.via_points)
        object.__setattr__(self, "via_points", vias)
        if not vias:
            return
        if self.constraint_points:
            raise InvalidRequestError(
                "via_points and constraint_points cannot be combined: constraint points are "
                "chained-form states, honoured only by the paper's family, which cannot honour "
                "joint-space via points; give the waypoints as via_points alone",
                field="via_points")
        for name in ("max_reversals", "pareto"):
            if getattr(self, name) not in (None, False):
                raise InvalidRequestError(
                    f"via_points cannot be combined with {name}: the reversal budget's "
                    f"candidates do not pass through via points; drop {name} or the via points",
                    field="via_points")
        duration = None if self.duration is None and self.has_limits else \
            self.duration_or_default
        validate_via_points(vias, self.n, duration, self.joint_bounds)

    @property
    def n(self) -> int:
        return self.robot.n

    @property
    def duration_or_default(self) -> float:
        return 1.0 if self.duration is None else float(self.duration)

    @property
    def has_limits(self) -> bool:
        """Whether any rate limit (or limit of its derivatives) is set."""
        return any(getattr(self, f) is not None for f in LIMIT_FIELDS)

    def duration_for_rates(self, peaks: Sequence[float]) -> float:
        """``T`` for a path whose actuator rates per unit normalised time peak at ``peaks =
        (max |U1|, max |U2|)``: the request's duration, or, with actuator limits and no
        duration, the shortest one that respects them.

        Raises
        ------
        InfeasibleError
            The given duration is too short for the limits, or the limits need a duration
            above :data:`MAX_DURATION` (tiny limits: the shortest duration may not even be
            finite).
        """
        limits = (self.max_u1, self.max_u2)
        if all(x is None for x in limits):
            return self.duration_or_default
        need = 0.0
        for peak, lim in zip(peaks, limits):
            if lim is not None:
                need = max(need, float(peak) / float(lim))
        if not need <= MAX_DURATION:  # also inf and nan
            raise InfeasibleError(
                f"the actuator limits max_u1 = {self.max_u1}, max_u2 = {self.max_u2} rad/s need "
                f"a duration of {need:.6g} s for this path, above the largest allowed "
                f"{MAX_DURATION:g} s", field="max_u2" if self.max_u2 is not None else "max_u1",
                diagnostics={"shortest_duration": need if math.isfinite(need) else None})
        if self.duration is None:
            return max(need, MIN_DURATION)
        if self.duration < need * (1 - 1e-12):
            # the limit that binds: the one whose peak rate needs the longest duration
            binding = max((float(peak) / float(lim), name) for peak, lim, name in
                          zip(peaks, limits, ("max_u1", "max_u2")) if lim is not None)[1]
            raise InfeasibleError(
                f"duration {self.duration:g} s is too short for the actuator limits: with "
                f"{binding} = {getattr(self, binding):g} rad/s the shortest duration is "
                f"{need:.6g} s; raise {binding} or the duration (or omit the duration: the "
                f"shortest one is then chosen)", field=binding,
                diagnostics={"shortest_duration": need, "duration": self.duration})
        return float(self.duration)

    def q_start(self) -> np.ndarray:
        return np.array((self.phi_start,) + self.start)

    def q_goal(self, dphi: float) -> np.ndarray:
        return np.array((self.phi_start + dphi,) + self.goal)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "PlanRequest":
        """Build from the JSON shape of ``POST /v1/plans`` (unknown keys are an error)."""
        d = dict(data)
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - known
        if unknown:
            raise InvalidRequestError(f"unknown field(s): {sorted(unknown)}", field=sorted(unknown)[0])
        if "start" not in d or "goal" not in d:
            raise InvalidRequestError("start and goal are required", field="start")
        rob = d.pop("robot", None)
        n_start = len(d["start"]) if isinstance(d["start"], (list, tuple)) else -1
        if not 3 <= n_start <= 8 and (rob is None or not dict(rob).get("gains")):
            raise InvalidRequestError(f"start has {n_start} joint angles: the number of joints "
                                      "must lie in [3, 8]", field="start")
        d["robot"] = rob if isinstance(rob, Robot) else Robot.from_spec(
            None if rob is None else dict(rob), n_start)
        if "weights" in d and d["weights"] is not None and not isinstance(d["weights"], Weights):
            d["weights"] = Weights(**dict(d["weights"]))
        elif d.get("weights") is None:
            d.pop("weights", None)
        cps = d.pop("constraint_points", None) or ()
        d["constraint_points"] = tuple(
            cp if isinstance(cp, ConstraintPoint) else
            ConstraintPoint(float(cp["time"]), int(cp["state"]), float(cp["value"])) for cp in cps)
        d["via_points"] = via_points_from(d.pop("via_points", None))
        if d.get("phi_change_bounds") is None:
            d.pop("phi_change_bounds", None)
        if d.get("joint_bounds") is not None:
            d["joint_bounds"] = tuple(None if b is None else (float(b[0]), float(b[1]))
                                      for b in d["joint_bounds"])
        for k in ("start", "goal"):
            d[k] = tuple(d[k])
        for k in ("method", "objective", "singularity", "samples", "time_limit", "phi_start",
                  "joint_trajectory", "pareto"):
            if k in d and d[k] is None:
                d.pop(k)
        return cls(**d)


#: The request's limits of the rates and their derivatives.
LIMIT_FIELDS = ("max_u1", "max_u2", "max_du1", "max_du2", "max_ddu1", "max_ddu2")


def angles_of(values: Any, name: str) -> tuple[float, ...]:
    """``values`` as a tuple of floats: one number (rad) per joint, else
    :class:`InvalidRequestError` naming ``name`` (a nested list, a string, a mapping...)."""
    if isinstance(values, (str, bytes, Mapping)) or not isinstance(values, Sequence) and \
            not isinstance(values, np.ndarray):
        raise InvalidRequestError(f"{name} must be a list of joint angles (rad), one number per "
                                  f"joint, not {type(values).__name__}", field=name)
    out = []
    for i, x in enumerate(values):
        if isinstance(x, (bool, str, bytes)) or not isinstance(x, (int, float, np.number)):
            raise InvalidRequestError(
                f"{name}[{i}] must be a number (rad), not {type(x).__name__}: {name} is a flat "
                f"list, one angle per joint", field=f"{name}[{i}]")
        out.append(float(x))
    return tuple(out)


def _deg(x: float) -> str:
    return f"{math.degrees(x):.1f} deg"


def joint_angles_problem(name: str, values: Sequence[float]) -> tuple[str, str] | None:
    """Why ``values`` (``start`` or ``goal``, rad) cannot be joint angles, as ``(field,
    message)``, or None. Shared by the library, the CLI and the service (whose 422 says the
    same).

    Joints 1..n-1 must lie in (0, pi/2), where the chained form exists; the last joint is free
    within [-2 pi, 2 pi]. The message names the first offending element and says what to send
    instead; values that all lie in (pi/2, 90] were almost certainly meant as degrees, and the
    message says so.
    """
    n = len(values)
    if n and all(math.pi / 2 < x <= 90.0 for x in values):
        shown = ", ".join(f"{x:g}" for x in values)
        fixed = ", ".join(f"{math.radians(x):.6g}" for x in values)
        return name, (f"{name} = [{shown}] looks like degrees; angles are in radians: convert "
                      f"with radians(), i.e. [{fixed}]")
    bad = [i for i, x in enumerate(values)
           if not (0.0 < x < math.pi / 2 if i < n - 1 else -2 * math.pi <= x <= 2 * math.pi)]
    if not bad:
        return None
    i, x = bad[0], values[bad[0]]
    if i < n - 1:
        where = "(0, pi/2) rad = (0, 90) deg"
    else:
        where = f"[-2 pi, 2 pi] rad = [-360, 360] deg (th{n}, the last joint, is free there)"
    more = "" if len(bad) == 1 else " (also " + ", ".join(f"{name}[{j}]" for j in bad[1:]) + ")"
    return f"{name}[{i}]", (f"{name}[{i}] = {x:g} rad ({_deg(x)}) is outside {where}; angles "
                            f"are in radians{more}")


def joint_bounds_degrees_problem(bounds: Any) -> tuple[str, str] | None:
    """``(field, message)`` when ``joint_bounds`` look like degrees (a value beyond 2 pi, none
    beyond 360), else None (the other checks are :func:`joint_bounds_problem`'s and the
    region's)."""
    if not isinstance(bounds, Sequence) or isinstance(bounds, str):
        return None
    for i, b in enumerate(bounds):
        if not isinstance(b, Sequence) or isinstance(b, str) or len(b) != 2 or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                for x in b):
            continue
        if any(abs(x) > 2 * math.pi for x in b) and all(abs(x) <= 360.0 for x in b):
            lo, hi = (float(x) for x in b)
            return f"joint_bounds[{i}]", (
                f"joint_bounds[{i}] = [{lo:g}, {hi:g}] looks like degrees; bounds are in "
                f"radians: use [{math.radians(lo):.6g}, {math.radians(hi):.6g}]")
    return None


def joint_bounds_problem(bounds: Sequence[Any], start: Sequence[float] | None = None,
                         goal: Sequence[float] | None = None) -> tuple[str, str] | None:
    """``(field, message)`` when ``joint_bounds`` look like degrees, or exclude the start or
    the goal of their joint, else None."""
    found = joint_bounds_degrees_problem(bounds)
    if found is not None:
        return found
    for i, b in enumerate(bounds):
        if b is None:
            continue
        lo, hi = float(b[0]), float(b[1])
        for name, q in (("goal", goal), ("start", start)):
            if q is None or i >= len(q) or lo <= q[i] <= hi:
                continue
            return f"joint_bounds[{i}]", (
                f"joint_bounds[{i}] = [{lo:g}, {hi:g}] rad ([{math.degrees(lo):.1f}, "
                f"{math.degrees(hi):.1f}] deg) excludes the {name} of joint th{i + 1}: "
                f"{name}[{i}] = {q[i]:g} rad ({_deg(q[i])}); widen the bound to include it, "
                f"or move the {name}")
    return None


def _finite(x: float, name: str) -> None:
    if not isinstance(x, (int, float)) or not math.isfinite(float(x)):
        raise InvalidRequestError(f"{name} must be a finite number", field=name)


def constraint_points_from(seq: Sequence[Mapping[str, Any]]) -> tuple[ConstraintPoint, ...]:
    """Constraint points from dicts with ``time``, ``state``, ``value``."""
    return tuple(ConstraintPoint(float(c["time"]), int(c["state"]), float(c["value"])) for c in seq)
