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
            val = tuple(float(x) for x in getattr(self, name))
            if len(val) != n:
                raise InvalidRequestError(f"{name} has {len(val)} joint angles but the robot has "
                                          f"n = {n} joints", field=name)
            for i, x in enumerate(val):
                if not math.isfinite(x):
                    raise InvalidRequestError(f"{name}[{i}] must be a finite number (rad)",
                                              field=f"{name}[{i}]")
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
            raise InfeasibleError(
                f"duration {self.duration:g} s is too short for the actuator limits: the "
                f"shortest duration that respects them is {need:.6g} s",
                diagnostics={"shortest_duration": need})
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


def _finite(x: float, name: str) -> None:
    if not isinstance(x, (int, float)) or not math.isfinite(float(x)):
        raise InvalidRequestError(f"{name} must be a finite number", field=name)


def constraint_points_from(seq: Sequence[Mapping[str, Any]]) -> tuple[ConstraintPoint, ...]:
    """Constraint points from dicts with ``time``, ``state``, ``value``."""
    return tuple(ConstraintPoint(float(c["time"]), int(c["state"]), float(c["value"])) for c in seq)
