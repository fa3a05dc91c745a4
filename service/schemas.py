"""Pydantic v2 models of every request of the service (they are the OpenAPI docs).

Requests forbid unknown fields and accept only JSON numbers for numeric fields
(:mod:`service.schema_fields`). Some bounds come from the settings (``samples <= max_samples``,
``time_limit <= max_time_limit``, batch, sweep, robustness and transform sizes), so those models
are built per :class:`Limits` by :func:`build_schemas` (cached: one set of classes per distinct
limits); the others are fixed. The response bodies are :mod:`service.responses`.
"""

import functools
import math
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Optional

from pydantic import (BaseModel, ConfigDict, Field, ValidationInfo, field_validator,
                      model_validator)
from pydantic_core import PydanticCustomError

from optimizer.problem import (DEFAULT_OBJECTIVE, MAX_REVERSALS, joint_bounds_degrees_problem)
from optimizer.via_points import MAX_VIA_POINTS, MAX_VIA_TIMES

from .responses import SweepResponse
from .schema_fields import (ANGLES_SCHEMA, DEFAULT_JOINTS, MAX_JOINTS, METHOD_HELP,
                            MIN_CONTROLLER_PERIOD, MIN_DURATION, MIN_JOINTS, PI, Q_AT_1_DEG,
                            WORKED_GOAL, WORKED_START, Exponent, Gain, JointAngle, MethodName,
                            Number, ObjectiveName, PhiAngle, RequestModel, StrictInt, Weights,
                            joint_angle_error, num)
from .settings import Limits

# ---------------------------------------------------------------------- fixed requests
class SweepFigureRequest(BaseModel):
    """``POST /v1/figures/from_sweep``: a sweep answer to draw, and the planned dphi to mark."""

    model_config = ConfigDict(extra="forbid")

    sweep: SweepResponse = Field(..., description="The answer of POST /v1/sweeps, unchanged.")
    planned_phi_change: Optional[PhiAngle] = Field(  # type: ignore[valid-type]
        None, description="A plan's dphi (rad), drawn as a dashed line.")


#: Largest time_limit of a replan (s): the fast path takes about a millisecond, the full
#: planner (its fallback) tens.
MAX_REPLAN_TIME_LIMIT = 30.0


class ReplanPath(BaseModel):
    """The part of a plan's ``path`` a replan reads: its times (their count is the samples of
    the continuation) and, for a plan of chained inputs, its rates ``u``. The other samples
    (``q``, ``z``, ``v``: most of an answer's bytes) are not read into Python objects: on a
    3-joint answer of 61 kB that took 0.36 ms of the event loop's 0.54 ms of validation, and
    forwarding them to the worker 0.33 ms more."""

    model_config = ConfigDict(extra="ignore")

    t: Any = Field(None, description="The answer's sample times (s).")
    u: Any = Field(None, description="The answer's rates (rad/s); read for plans of chained "
                                     "inputs, whose continuation starts from them.")


class ReplanPlan(BaseModel):
    """The fields of a plan (an answer as returned, or its compact form) that a replan reads;
    any other field of an answer is accepted and ignored. The library checks the values
    (a 422 naming the field under ``plan.``)."""

    model_config = ConfigDict(extra="ignore")

    status: Any = Field(None, description="An answer's status ('success').")
    robot: Any = Field(None, description="gains and exponents (as answers give them).")
    goal: Any = Field(None, description="th1..thn at the goal (rad); an answer without it "
                                        "gives validation.final.")
    validation: Any = Field(None, description="An answer's validation (its final state).")
    coefficients: Any = Field(None, description="segments: t_start, t_end, u (rad/s).")
    time_law: Any = Field(None, description="An answer's time_law (optional).")
    duration: Any = Field(None, description="An answer's duration (s, optional).")
    joint_bounds: Any = Field(None, description="The plan's joint bounds (optional).")
    samples: Any = Field(None, description="Samples of the continuation (optional).")
    path: Optional[ReplanPath] = Field(None, description="An answer's path (its t and u).")

    def as_payload(self) -> dict[str, Any]:
        """The fields given, as a plain dict for the library (the values as parsed, not
        copied)."""
        out = {name: getattr(self, name) for name in self.model_fields_set if name != "path"}
        if "path" in self.model_fields_set:
            out["path"] = None if self.path is None else {
                name: getattr(self.path, name) for name in self.path.model_fields_set}
        return out


class ReplanRequest(RequestModel):
    """A plan (an answer of /v1/plans or /v1/replans, or its compact form), the time since
    its start, the measured state and the rates being commanded."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"plan": {"robot": {"gains": [0.88658, 0.7115], "exponents": [2, 3]},
                  "goal": [0.9, 1.0, 0.8],
                  "coefficients": {"segments": [
                      {"t_start": 0.0, "t_end": 0.5, "u": [0.6, 1.0]},
                      {"t_start": 0.5, "t_end": 1.0, "u": [0.6, 0.2]}]}},
         "time": 0.25, "state": [0.15, 0.55, 0.6, 0.55]}]})

    plan: ReplanPlan = Field(
        ..., description="An answer of POST /v1/plans or /v1/replans as returned, or its "
                         "compact form: robot (gains, exponents), goal, coefficients.segments "
                         "(t_start, t_end, u), time_law (optional), joint_bounds (optional).")
    time: Number = Field(..., ge=0.0, description="Seconds since the plan's start (on its "
                                                  "time axis), before its end.")
    state: list[Number] = Field(..., min_length=MIN_JOINTS + 1, max_length=MAX_JOINTS + 1,
                                description="Measured [phi, th1, ..., thn] (rad).")
    rates: Optional[list[Number]] = Field(
        None, min_length=2, max_length=2,
        description="Rates [u1, u2] (rad/s) being commanded at time; default the plan's.")
    duration: Optional[num(gt=0.0)] = Field(  # type: ignore[valid-type]
        None, description="A new end time (s, on the plan's time axis); default the plan's.")
    keep_reversals: bool = Field(
        False, description="true: no continuation that reverses phi or th1 more often than the "
                           "plan's rest (a 422 naming keep_reversals instead); false: the goal "
                           "first (indicators.reversals say what the continuation does).")
    gains: Optional[list[num(gt=0.0, hi=100.0)]] = Field(  # type: ignore[valid-type]
        None, min_length=MIN_JOINTS - 1, max_length=MAX_JOINTS - 1,
        description="The plant's K2..Kn as estimated from its measured motion (the library's "
                    "optimizer.identification.GainEstimator); the continuation is planned and "
                    "verified on them and its robot says so. Default: the plan's robot.")
    fallback: bool = Field(
        True, description="false: the fast path and one warm-started NLP only (a 422 naming "
                          "fallback where they fail), never the full planner: a bounded answer "
                          "time for a controller's period.")
    time_limit: num(hi=MAX_REPLAN_TIME_LIMIT, gt=0.0) = Field(  # type: ignore[valid-type]
        5.0, description="Seconds for the job (the full planner is the fast path's fallback).")

    def to_library(self) -> dict[str, Any]:
        return self.model_dump(exclude_none=True, exclude={"time_limit"})


class ClosedLoop(RequestModel):
    """The closed-loop mode of ``POST /v1/robustness``: a plant whose gains are off, replans
    from the measured state every ``period`` s."""

    gain_error: num(0.0, 0.5) = Field(  # type: ignore[valid-type]
        0.05, description="Each run's plant gains K2..Kn are K_i (1 + e_i), e_i drawn "
                          "uniformly in [-gain_error, gain_error] (relative).")
    period: num(gt=0.0, hi=10.0) = Field(  # type: ignore[valid-type]
        0.05, description="Seconds between replans (the first at the start).")
    noise: num(0.0, 0.1) = Field(  # type: ignore[valid-type]
        0.0, description="Standard deviation (rad) of the measurement noise (Gaussian, on "
                         "phi and every joint).")
    seed: StrictInt = Field(0, description="Seed of the gain errors and the noise.")
    identify: bool = Field(
        False, description="true: every period the closed loop estimates the plant's gains "
                           "from the measured motion and replans on them; false: replans on "
                           "the plan's model.")
    keep_reversals: bool = Field(
        False, description="true: a continuation that would reverse phi or th1 more often than "
                           "the plan's rest is refused and the run goes on with the current "
                           "plan (the reversals of the plan kept, the error it cannot remove "
                           "without them left); false: every replan goes for the goal.")


# ---------------------------------------------------------------------- limit-dependent requests
@dataclass(frozen=True)
class Schemas:
    """The request models for one set of limits (responses are fixed)."""

    PlanRequest: type[BaseModel]
    SweepRequest: type[BaseModel]
    TransformRequest: type[BaseModel]
    RobustnessRequest: type[BaseModel]
    BatchRequest: type[BaseModel]


@functools.lru_cache(maxsize=16)
def build_schemas(limits: Limits) -> Schemas:
    """Request models whose bounds come from ``limits``.

    Parameters
    ----------
    limits : Limits

    Returns
    -------
    Schemas
    """
    L = limits
    TimeLimit = num(hi=L.max_time_limit, gt=0.0,
                    description=f"Seconds for the whole solve (at most {L.max_time_limit:g}); "
                                "a job still running then is stopped and answered 504 "
                                "(timeout) within the server's grace (0.5 s by default).")

    class RobotSpec(RequestModel):
        """The arm's constants. Omit both lists for the default robot of the request's n."""

        gains: Optional[list[Gain]] = Field(  # type: ignore[valid-type]
            None, min_length=MIN_JOINTS - 1, max_length=L.max_joints - 1,
            description="Gains K2..Kn (n - 1 entries, each > 0).", examples=[[0.88658, 0.7115]])
        exponents: Optional[list[Exponent]] = Field(
            None, min_length=MIN_JOINTS - 1, max_length=L.max_joints - 1,
            description="Integer exponents m2..mn of cos(th_{i-1}) (n - 1 entries, 1..12).",
            examples=[[2, 3]])

    class ConstraintPoint(RequestModel):
        """A constraint point: the chained state ``z_state`` takes ``value`` at ``time``."""

        time: num(0.0, L.max_duration, description="Time (s), inside (0, duration).") = Field(  # type: ignore[valid-type]
            ..., examples=[0.5])  # inside the default duration (1 s)
        state: StrictInt = Field(..., ge=2, le=L.max_joints + 1,
                                 description="Chained state index k of z_k, 2..n+1.")
        value: num(-1e6, 1e6, description="Value of z_state at time.") = Field(...)  # type: ignore[valid-type]

    class ViaPoint(RequestModel):
        """A joint-space via point: joint ``joint`` passes through ``angle`` at ``time``.

        Honoured exactly by the methods that plan on the original model (``shooting``,
        ``penalty``; ``auto`` then runs only those); the paper's family (``polynomial``,
        ``retimed``, ``constraint_points``) answers 422 naming ``via_points``."""

        model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
            {"time": 0.5, "joint": "th2", "angle": 0.349066}]})

        time: num(0.0, L.max_duration, description="Time (s) on the answer's time axis (path.t), "  # type: ignore[valid-type]
                  "strictly inside (0, duration).") = Field(..., examples=[0.5])
        joint: str = Field(..., max_length=8, examples=["th2"],
                           description="The joint, named as path.q_names names it: th1 .. thn.")
        angle: num(-1e3, 1e3, description="The joint's angle (rad) at time: inside the "  # type: ignore[valid-type]
                   "joint's range (th1..th(n-1) in (0, pi/2), thn in [-2 pi, 2 pi]) and "
                   "joint_bounds.") = Field(..., examples=[0.349066])

    class RandomStarts(RequestModel):
        """Perturbed starts drawn uniformly in ``start +- spread`` (reproducible by ``seed``)."""

        count: StrictInt = Field(..., ge=1, le=L.max_robustness_runs,
                                 description=f"Number of runs (1..{L.max_robustness_runs}).")
        spread: num(hi=1.0, gt=0.0, description="Half-width of the perturbation (rad).") = Field(  # type: ignore[valid-type]
            ..., examples=[0.01])
        seed: StrictInt = Field(0, ge=0, le=2 ** 32 - 1, description="Random seed.")

    class PlanRequest(RequestModel):
        """A motion-planning request (radians, seconds)."""

        model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
            {"start": WORKED_START, "goal": WORKED_GOAL, "method": "polynomial",
             "objective": "tp_then_da", "samples": 51}]})

        robot: Optional[RobotSpec] = Field(
            None, description="Robot constants. Omitted: the 3-joint prototype (start and goal "
                              "must then have 3 angles); for another n give gains and "
                              "exponents, or {} for the assumed default constants of n joints.")
        start: list[Number] = Field(  # type: ignore[valid-type]
            ..., min_length=MIN_JOINTS, max_length=L.max_joints,
            description=f"Start joint angles th1..thn (rad), n in [{MIN_JOINTS}, "
                        f"{L.max_joints}]: th1..th(n-1) in (0, pi/2), thn in [-2 pi, 2 pi].",
            examples=[WORKED_START], json_schema_extra=ANGLES_SCHEMA)
        goal: list[Number] = Field(  # type: ignore[valid-type]
            ..., min_length=MIN_JOINTS, max_length=L.max_joints,
            description="Goal joint angles th1..thn (rad), same ranges as start.",
            examples=[WORKED_GOAL], json_schema_extra=ANGLES_SCHEMA)
        phi_start: num(-1e3, 1e3, description="Initial phi (rad).") = 0.0  # type: ignore[valid-type]
        phi_change: Optional[PhiAngle] = Field(  # type: ignore[valid-type]
            None, description="Fixes dphi = phi(T) - phi(0) (rad); omitted: searched within "
                              "phi_change_bounds.")
        phi_change_bounds: Optional[list[PhiAngle]] = Field(  # type: ignore[valid-type]
            None, min_length=2, max_length=2,
            description="[lo, hi] search range of dphi (rad); default [-pi, pi].")
        duration: Optional[num(MIN_DURATION, L.max_duration)] = Field(  # type: ignore[valid-type]
            None, description="T (s); default 1 s, or the shortest T that respects the "
                              "limits (max_u*, max_du*, max_ddu*) along the path when those "
                              "are given. Too short for the limits: 422 naming the limit and "
                              "the shortest duration.")
        method: MethodName = Field(  # type: ignore[valid-type]
            "auto", description="auto (the default): picks among the methods below and "
                                "returns the best plan by the objective. " + METHOD_HELP)
        objective: ObjectiveName = Field(  # type: ignore[valid-type]
            DEFAULT_OBJECTIVE,
            description="How the best plan is chosen. reversals_then_deviation (default): "
                        "fewest actuator reversals (phi and th1), then the smallest joint-space "
                        "deviation from the straight segment start -> goal; tp_then_da and "
                        "tp_then_sensitivity: the paper's rules (fewest t_p, then smallest d_a "
                        "of joint 1 or ||J_R(T)||_F); weighted: the smallest weighted score.")
        weights: Optional[Weights] = Field(None, description="For objective = weighted.")
        singularity: Literal["full", "z2"] = Field(
            "full", description="Singularity criterion used in the search.")
        constraint_points: Optional[list[ConstraintPoint]] = Field(
            None, max_length=L.max_constraint_points,
            description=f"Constraint points (at most {L.max_constraint_points}).")
        via_points: Optional[list[ViaPoint]] = Field(
            None, max_length=MAX_VIA_POINTS,
            description=f"Joint-space via points (at most {MAX_VIA_POINTS}, at most "
                        f"{MAX_VIA_TIMES} distinct times): the returned path passes through "
                        "each joint angle at its time (within 1e-6 rad on path; "
                        "diagnostics.via_points reports each). Methods shooting, penalty and "
                        "auto; not with constraint_points, max_reversals or pareto; with "
                        "actuator limits a duration is needed (the times are seconds).")
        samples: StrictInt = Field(201, ge=2, le=L.max_samples,
                                   description=f"Time samples of the returned path (2.."
                                               f"{L.max_samples}).")
        time_limit: TimeLimit = Field(  # type: ignore[valid-type]
            L.default_time_limit, description=f"Seconds for the whole solve (default "
                                              f"{L.default_time_limit:g}, at most "
                                              f"{L.max_time_limit:g}).")
        max_u1: Optional[num(hi=1e6, gt=0.0)] = Field(  # type: ignore[valid-type]
            None, description="Limit of |u1| = |phi'| (rad/s).")
        max_u2: Optional[num(hi=1e6, gt=0.0)] = Field(  # type: ignore[valid-type]
            None, description="Limit of |u2| = |th1'| (rad/s).")
        max_du1: Optional[num(hi=1e6, gt=0.0)] = Field(  # type: ignore[valid-type]
            None, description="Limit of |u1'| = |phi''| (rad/s^2), on every handed-out form "
                              "between its samples.")
        max_du2: Optional[num(hi=1e6, gt=0.0)] = Field(  # type: ignore[valid-type]
            None, description="Limit of |u2'| = |th1''| (rad/s^2).")
        max_ddu1: Optional[num(hi=1e9, gt=0.0)] = Field(  # type: ignore[valid-type]
            None, description="Limit of |u1''| (rad/s^3): S-curve time laws; checked on the "
                              "JointTrajectory form (the linear form's second derivative is "
                              "not a function).")
        max_ddu2: Optional[num(hi=1e9, gt=0.0)] = Field(  # type: ignore[valid-type]
            None, description="Limit of |u2''| (rad/s^3).")
        joint_bounds: Optional[list[Optional[Annotated[  # type: ignore[valid-type]
                list[JointAngle], Field(min_length=2, max_length=2)]]]] = Field(
            None, max_length=L.max_joints,
            description="Per joint [lo, hi] (rad) or null; inside the region (0, pi/2).")
        controller_period: Optional[num(MIN_CONTROLLER_PERIOD, L.max_duration / 2)] = Field(  # type: ignore[valid-type]
            None, description="Period (s) of a controller that holds each rate for one period: "
                              "path.t is then k * period (the last point T; a last interval "
                              "shorter when T is not a multiple), path.u the rates to hold "
                              "(rule zoh), planned for that hold; samples is then ignored. At "
                              "most half the duration, and at most max_samples points.")
        joint_trajectory: bool = Field(
            False, description="Also return the plan as a ROS trajectory_msgs/JointTrajectory "
                               "(positions [phi, th1], velocities [u1, u2]; cubic Hermite "
                               "between points).")
        max_reversals: Optional[StrictInt] = Field(
            None, ge=0, le=MAX_REVERSALS,
            description="A budget of actuator direction changes (phi and th1 together, as "
                        "indicators.reversals counts them): the answer is the straightest "
                        "verified path (smallest deviation) with at most that many; 422 "
                        "infeasible naming max_reversals and the fewest found when there is "
                        "none. Method auto or shooting, no constraint points.")
        pareto: bool = Field(
            False, description="Also return the trade-off: the non-dominated verified plans "
                               "over (reversals, deviation), from the fewest reversals to the "
                               "straightest (response field pareto); the main plan is the "
                               "objective's pick (with max_reversals: the budget's). Method "
                               "auto or shooting; costs several plans' time: about 0.5-4 s at "
                               "3 to 5 joints, 2-15 s from 6 (give time_limit 30 there).")

        @field_validator("controller_period")
        @classmethod
        def _period_fits(cls, period: Optional[float],
                         info: ValidationInfo) -> Optional[float]:
            if period is None:
                return period
            d = info.data
            limited = any(d.get(k) is not None for k in ("max_u1", "max_u2", "max_du1",
                                                          "max_du2", "max_ddu1", "max_ddu2"))
            duration = d.get("duration") if d.get("duration") is not None else (
                None if limited else 1.0)
            if duration is not None:
                if period > 0.5 * duration:
                    raise ValueError(f"controller_period = {period} s must be at most half "
                                     f"the duration ({duration} s)")
                if math.ceil(duration / period * (1 - 1e-12)) + 1 > L.max_samples:
                    raise ValueError(f"controller_period = {period} s gives more than "
                                     f"max_samples = {L.max_samples} samples over "
                                     f"{duration} s")
            return period

        @property
        def rows(self) -> int:
            """Path rows the answer will have, about: ``samples``, or the controller
            period's grid over the duration (1 s by default; input breaks add a few)."""
            if self.controller_period is None:
                return self.samples
            duration = self.duration if self.duration is not None else 1.0
            return math.ceil(duration / self.controller_period * (1 - 1e-12)) + 1

        @field_validator("joint_bounds", mode="before")
        @classmethod
        def _bounds_in_radians(cls, bounds: Any) -> Any:
            # before the type's own bounds (|x| <= 2 pi), which would not say "degrees"
            found = joint_bounds_degrees_problem(bounds)
            if found is not None:
                raise PydanticCustomError("joint_bounds_degrees", "{message}",
                                          {"field": found[0], "message": found[1]})
            return bounds

        @field_validator("start", "goal")
        @classmethod
        def _angles(cls, values: list[float], info: ValidationInfo) -> list[float]:
            error = joint_angle_error(str(info.field_name), values)
            if error is not None:
                raise error
            return values

        @model_validator(mode="after")
        def _joint_count(self) -> Any:
            n = len(self.start)
            if len(self.goal) != n:
                raise PydanticCustomError(
                    "joint_count", "goal has {got} angles but start has {n}: give one angle "
                    "per joint in both", {"field": "goal", "got": len(self.goal), "n": n})
            if self.robot is None and n != DEFAULT_JOINTS:
                raise PydanticCustomError(
                    "joint_count", "start has {n} angles but the default robot has "
                    "{default} joints: send {default} angles, or give robot (gains and "
                    "exponents, n - 1 each, or {empty} for the assumed default constants of "
                    "{n} joints)", {"field": "start", "n": n, "default": DEFAULT_JOINTS,
                                    "empty": "{}"})
            return self

        def to_library(self) -> dict[str, Any]:
            """The dict :meth:`optimizer.problem.PlanRequest.from_dict` takes."""
            return self.model_dump(exclude_none=True)

    class SweepRequest(PlanRequest):
        """A plan request plus the dphi range and number of points of the sweep."""

        model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
            {"start": WORKED_START, "goal": WORKED_GOAL, "phi_change_range": [0.5, 0.7],
             "points": 21}]})

        phi_change_range: list[PhiAngle] = Field(  # type: ignore[valid-type]
            [-PI, PI], min_length=2, max_length=2, description="[lo, hi] of dphi (rad).")
        points: StrictInt = Field(181, ge=2, le=L.max_sweep_points,
                                  description=f"Evenly spaced dphi values (2.."
                                              f"{L.max_sweep_points}).")
        intervals: bool = Field(True, description="Also compute the exact feasible intervals.")

        @model_validator(mode="after")
        def _no_via_points(self) -> Any:
            if self.via_points:
                raise PydanticCustomError(
                    "via_points_sweep", "a sweep scans the paper's polynomial family over "
                    "dphi, whose paths cannot honour joint-space via_points: drop them (plan "
                    "with POST /v1/plans instead)", {"field": "via_points"})
            return self

        def to_library(self) -> dict[str, Any]:
            d = self.model_dump(exclude_none=True)
            lo, hi = d.pop("phi_change_range")
            points = d.pop("points")
            intervals = d.pop("intervals")
            return {"request": d, "lo": lo, "hi": hi, "points": points, "intervals": intervals}

    class TransformRequest(RequestModel):
        """Points to map between joint space and chained coordinates."""

        model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
            {"direction": "to_chained", "points": [Q_AT_1_DEG, [0.0] + WORKED_GOAL]}]})

        robot: Optional[RobotSpec] = Field(
            None, description="Default: the default robot for n = row length - 1.")
        direction: Literal["to_chained", "from_chained"] = Field(
            ..., description="to_chained maps q = [phi, th1..thn] to z = [z1..z_{n+1}]; "
                             "from_chained the inverse.")
        points: list[list[Number]] = Field(  # type: ignore[valid-type]
            ..., min_length=1, max_length=L.max_transform_points,
            description="Rows of n + 1 numbers (all rows the same length).")
        time_limit: TimeLimit = Field(L.default_time_limit)  # type: ignore[valid-type]

        @field_validator("points")
        @classmethod
        def _rows(cls, points: list[list[float]]) -> list[list[float]]:
            width = len(points[0])
            if not MIN_JOINTS + 1 <= width <= L.max_joints + 1:
                raise ValueError(f"each point must have n + 1 entries with n in "
                                 f"[{MIN_JOINTS}, {L.max_joints}] joints, not {width}")
            if any(len(row) != width for row in points):
                raise ValueError("all points must have the same number of entries")
            return points

        def to_library(self) -> dict[str, Any]:
            return self.model_dump(exclude_none=True, exclude={"time_limit"})

    class RobustnessRequest(RequestModel):
        """A plan and perturbed starts to replay it from (open loop)."""

        model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
            {"plan": {"start": WORKED_START, "goal": WORKED_GOAL, "method": "polynomial",
                      "phi_change": 0.6034},
             "random": {"count": 5, "spread": 0.01, "seed": 1}, "replay": "u"}]})

        plan: PlanRequest = Field(..., description="The nominal plan (phi_change may fix dphi).")
        starts: Optional[list[Annotated[list[JointAngle],  # type: ignore[valid-type]
                                        Field(min_length=MIN_JOINTS,
                                              max_length=L.max_joints)]]] = Field(
            None, min_length=1, max_length=L.max_robustness_runs,
            description=f"Perturbed start vectors th1..thn (rad), at most "
                        f"{L.max_robustness_runs}.")
        random: Optional[RandomStarts] = Field(None, description="Random perturbed starts.")
        replay: Literal["u", "v"] = Field(
            "u", description="u: the handed-out actuator rates path.u, executed by path.rule; "
                             "v: the chained inputs v through the input map at the actual "
                             "state.")
        include_paths: bool = Field(
            False, description=f"Return each run's path rows (runs x plan.samples at most "
                               f"{L.max_total_samples}).")
        closed_loop: Optional[ClosedLoop] = Field(
            None, description="Also run each start on a plant with gains off, open loop and "
                              "closed loop (replans from the measured state), side by side "
                              "(actuator-rate plans: shooting, penalty, the default auto).")
        time_limit: TimeLimit = Field(  # type: ignore[valid-type]
            L.default_time_limit, description="Seconds for the whole job (plan and replays).")

        @field_validator("include_paths")
        @classmethod
        def _answer_size(cls, include_paths: bool, info: ValidationInfo) -> bool:
            plan, starts, rnd = (info.data.get(k) for k in ("plan", "starts", "random"))
            runs = len(starts) if starts is not None else (rnd.count if rnd is not None else 0)
            if include_paths and plan is not None and runs * plan.rows > L.max_total_samples:
                raise ValueError(f"runs x plan path rows = {runs * plan.rows} exceeds "
                                 f"max_total_samples = {L.max_total_samples} path rows")
            return include_paths

        @model_validator(mode="after")
        def _one_source(self) -> "RobustnessRequest":
            if (self.starts is None) == (self.random is None):
                raise ValueError("give exactly one of starts and random")
            return self

        def to_library(self) -> dict[str, Any]:
            d = self.model_dump(exclude_none=True, exclude={"time_limit"})
            # the top-level limit bounds the whole job; the plan's own, when given, may only
            # tighten it (its default must not)
            given = self.plan.time_limit if "time_limit" in self.plan.model_fields_set \
                else self.time_limit
            d["plan"]["time_limit"] = min(given, self.time_limit)
            return d

    class BatchRequest(RequestModel):
        """Many plan requests, solved in parallel; answers come in the same order."""

        model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
            {"requests": [{"start": WORKED_START, "goal": WORKED_GOAL, "method": "polynomial",
                           "samples": 11},
                          {"start": WORKED_START, "goal": WORKED_GOAL, "method": "polynomial",
                           "phi_change": 0.6034, "samples": 11}]}]})

        requests: list[PlanRequest] = Field(
            ..., min_length=1, max_length=L.max_batch_size,
            description=f"1..{L.max_batch_size} plan requests, with at most "
                        f"{L.max_total_samples} samples in all.")

        @field_validator("requests")
        @classmethod
        def _total(cls, requests: list[Any]) -> list[Any]:
            total = sum(r.rows for r in requests)
            if total > L.max_total_samples:
                raise ValueError(f"the requests ask for {total} samples in all; at most "
                                 f"max_total_samples = {L.max_total_samples}")
            return requests

    return Schemas(PlanRequest=PlanRequest, SweepRequest=SweepRequest,
                   TransformRequest=TransformRequest, RobustnessRequest=RobustnessRequest,
                   BatchRequest=BatchRequest)
