"""Pydantic v2 models of every request and response of the service (they are the OpenAPI docs).

Units: angles in radians, times in seconds, rates in rad/s. Requests forbid unknown fields and
accept only JSON numbers for numeric fields (no strings, no ``NaN``/``Infinity``, no values
that overflow to infinity).

Some bounds come from the settings (``samples <= max_samples``, ``time_limit <= max_time_limit``,
batch, sweep, robustness and transform sizes), so the models are built per :class:`Limits` by
:func:`build_schemas` (cached: one set of classes per distinct limits).

Response models document the bodies; the routes return the planning library's JSON-safe dicts
directly (a test checks the bodies against these schemas).
"""

import functools
import math
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Optional

from pydantic import (BaseModel, ConfigDict, Field, Strict, ValidationInfo, field_validator,
                      model_validator)
from pydantic_core import PydanticCustomError

from optimizer.planner.registry import METHODS, method_names
from optimizer.problem import (DEFAULT_OBJECTIVE, MAX_REVERSALS, OBJECTIVES,
                               joint_angles_problem,
                               joint_bounds_degrees_problem)
from optimizer.via_points import MAX_VIA_POINTS, MAX_VIA_TIMES

from .settings import LIBRARY_MAX_JOINTS, LIBRARY_MIN_DURATION, LIBRARY_MIN_JOINTS, Limits

#: The planner's registered methods (and ``auto``) and objectives, as the schema's enums.
MethodName = Literal[method_names()]  # type: ignore[valid-type]
ObjectiveName = Literal[OBJECTIVES]  # type: ignore[valid-type]
METHOD_HELP = " ".join(f"{e.name}: {e.summary}." for e in METHODS.values())

PI = math.pi
MAX_JOINTS = LIBRARY_MAX_JOINTS
MIN_JOINTS = LIBRARY_MIN_JOINTS
MIN_DURATION = LIBRARY_MIN_DURATION
#: Shortest controller_period (s).
MIN_CONTROLLER_PERIOD = 1e-4

# ---------------------------------------------------------------------- scalar types
#: A finite JSON number (ints accepted, strings/booleans/NaN/Infinity refused).
Number = Annotated[float, Strict(), Field(allow_inf_nan=False)]
StrictInt = Annotated[int, Strict()]


def num(lo: float | None = None, hi: float | None = None, *, gt: float | None = None,
        description: str | None = None) -> Any:
    """A finite number type with bounds."""
    return Annotated[float, Strict(), Field(allow_inf_nan=False, ge=lo, le=hi, gt=gt,
                                            description=description)]


JointAngle = num(-2 * PI, 2 * PI, description="Joint angle (rad).")
#: The default robot's number of joints (``robot`` omitted).
DEFAULT_JOINTS = 3
#: JSON Schema of ``start`` and ``goal``: th1 and th2 lie in (0, pi/2) whatever n is (n >= 3;
#: joints 1..n-1 must, the last one is free within [-2 pi, 2 pi]); the validator checks the rest.
_OPEN_QUARTER = {"type": "number", "exclusiveMinimum": 0.0, "exclusiveMaximum": PI / 2}
ANGLES_SCHEMA: dict[str, Any] = {
    "prefixItems": [_OPEN_QUARTER, _OPEN_QUARTER],
    "items": {"type": "number", "minimum": -2 * PI, "maximum": 2 * PI},
}


def joint_angle_error(name: str, values: list[float]) -> PydanticCustomError | None:
    """Why ``values`` (``start`` or ``goal``, rad) cannot be joint angles, or None: the
    library's check (:func:`optimizer.problem.joint_angles_problem`, degrees detected), as a
    pydantic error naming the offending element (``ctx["field"]``)."""
    found = joint_angles_problem(name, values)
    if found is None:
        return None
    kind = "joint_angle_degrees" if "looks like degrees" in found[1] else "joint_angle_range"
    return PydanticCustomError(kind, "{message}", {"field": found[0], "message": found[1]})


PhiAngle = num(-4 * PI, 4 * PI, description="Change of phi (rad).")
Gain = num(hi=1e3, gt=0.0, description="Transmission gain K_i (> 0).")
Exponent = Annotated[int, Strict(), Field(ge=1, le=12, description="Exponent m_i (1..12).")]
Weight = num(0.0, 1e6, description="Weight (>= 0).")
ProblemCode = Literal["invalid_request", "infeasible", "timeout", "numerical_failure",
                      "overloaded", "worker_lost", "shutting_down", "request_timeout",
                      "unauthorized", "not_found", "method_not_allowed"]

DEG = PI / 180.0
WORKED_START: list[Any] = [round(10 * DEG, 9)] * 3
WORKED_GOAL: list[Any] = [round(30 * DEG, 9)] * 3
Q_AT_1_DEG: list[Any] = [0.0] + [round(DEG, 9)] * 3


class RequestModel(BaseModel):
    """Base of request models: unknown fields are an error."""

    model_config = ConfigDict(extra="forbid")


# ---------------------------------------------------------------------- fixed request parts
class Weights(RequestModel):
    """Weights of the ``weighted`` objective: w_da d_a + w_s ||J_R||_F + w_e energy + w_tp t_p."""

    d_a: Weight = Field(1.0, description="Weight of the approximation distance d_a.")  # type: ignore[valid-type]
    sensitivity: Weight = Field(0.0, description="Weight of ||J_R(T)||_F.")  # type: ignore[valid-type]
    energy: Weight = Field(0.0, description="Weight of the input energy.")  # type: ignore[valid-type]
    t_p: Weight = Field(0.0, description="Weight of the number of phi passes t_p.")  # type: ignore[valid-type]


# ---------------------------------------------------------------------- responses
class RobotInfo(BaseModel):
    """The robot a result was computed for."""

    n: int = Field(..., description="Number of joints.")
    gains: list[float] = Field(..., description="K2..Kn.")
    exponents: list[int] = Field(..., description="m2..mn.")
    assumed_constants: bool = Field(
        ..., description="True when the constants are the assumed extension to n != 3 joints "
                         "(the paper gives constants for n = 3 only).")


class DefaultRobot(RobotInfo):
    """``GET /v1/robots/default``."""

    note: Optional[str] = Field(None, max_length=500,
                                description="Why the constants are an assumption.")


class Segment(BaseModel):
    """One piece of the chained inputs, as power series in ``t - t_start`` (t in s)."""

    t_start: float
    t_end: float
    v1: list[float] = Field(..., description="Coefficients of v1, lowest power first.")
    v2: list[float] = Field(..., description="Coefficients of v2, lowest power first (empty "
                                             "for actuator-rate plans: v2 is not polynomial).")
    u: Optional[list[float]] = Field(None, description="Actuator rates [u1, u2] (rad/s), "
                                                       "constant on the segment (method "
                                                       "shooting only).")


class Coefficients(BaseModel):
    """The chained inputs of the plan (enough to regenerate it)."""

    basis: str = Field(..., max_length=500)
    segments: list[Segment]


class Reversals(BaseModel):
    """Direction changes of each actuator (dead band 1e-4 rad)."""

    phi: int = Field(..., description="Direction changes of phi (u1 changes sign).")
    th1: int = Field(..., description="Direction changes of th1 (u2 changes sign).")


class Indicators(BaseModel):
    """Quality indicators of the plan (``null`` where undefined).

    The default objective ranks plans by ``reversals`` (phi and th1 together), then by
    ``deviation``; the paper's objectives by ``t_p``, then ``d_a`` or ``sensitivity``.
    """

    deviation: Optional[float] = Field(
        None, description="Largest distance (rad) in joint space (th1..thn) of the path from the "
                          "straight segment start -> goal. Geometric: retiming cannot change it.")
    reversals: Optional[Reversals] = Field(
        None, description="Direction changes of the two actuators, phi and th1.")
    d_a: Optional[float] = Field(
        None, description="The paper's approximation distance d_a: largest |th1(t) - line(t)| "
                          "of joint 1 against the straight line in time from start to goal (rad).")
    d_a_per_joint: list[Optional[float]] = Field(default_factory=list,
                                                 description="d_a of each joint (rad).")
    d_a_joint_space: Optional[float] = Field(
        None, description="Largest perpendicular distance (rad) of the path from the infinite "
                          "line through start and goal in joint space (the paper's eq 17).")
    t_p: Optional[int] = Field(
        None, description="The paper's t_p: interior extreme points of th1(t), i.e. reversals "
                          "of the actuator driving joint 1 (dead band 1e-6 rad); 0 = th1 "
                          "moves monotonically.")
    phi_reversals: Optional[int] = Field(
        None, description="Interior extreme points of phi(t) (dead band 1e-6 rad).")
    sensitivity: Optional[float] = Field(None, description="||J_R(T)||_F (the paper's eq 22).")
    sensitivity_max: Optional[float] = Field(None, description="max_t ||J_R(t)||_F.")
    energy: Optional[float] = Field(None, description="Input energy: integral of u1^2 + u2^2 "
                                                      "dt (rad^2/s).")
    margin: Optional[float] = Field(None, description="Distance to the singular set (rad).")


class PlanPath(BaseModel):
    """The executable path: one row per time sample (see docs/execution.md).

    ``rule`` says how a controller executes ``u``: ``linear`` (linear interpolation between
    consecutive samples; no time twice, the rates are continuous and zero at both ends) or
    ``zoh`` (with ``controller_period``: ``u[k]`` held on
    ``[t_k, t_{k+1})``, the last row repeats the last interval's rate). Executed by that rule,
    ``u`` drives the original model to the goal (``validation.executed``); ``q`` and ``z`` are
    the states of that execution.
    """

    rule: Optional[Literal["linear", "zoh"]] = Field(
        None, description="How u is executed between samples: linear or zoh.")
    t: list[float] = Field(..., description="Times (s); increasing.")
    q: list[list[Optional[float]]] = Field(..., description="Rows [phi, th1..thn] (rad).")
    q_names: Optional[list[Annotated[str, Field(max_length=8)]]] = Field(
        None, max_length=16, description='The columns of q: ["phi", "th1", ..., "thn"].')
    z: list[list[Optional[float]]] = Field(..., description="Chained state rows [z1..z_{n+1}].")
    u: list[list[Optional[float]]] = Field(..., description="Actuator rates [u1, u2] (rad/s).")
    u_names: Optional[list[Annotated[str, Field(max_length=8)]]] = Field(
        None, max_length=2, description='The columns of u: ["u1", "u2"] (u1 = dphi/dt, '
                                        'u2 = dth1/dt).')
    v: list[list[Optional[float]]] = Field(..., description="Chained inputs [v1, v2].")


class Validation(BaseModel):
    """Re-integration of the original model driven by the planned inputs."""

    terminal_error: Optional[float] = Field(None, description="max |th(T) - goal| (rad).")
    phi_error: Optional[float] = Field(None, description="|phi(T) - planned phi(T)| (rad).")
    max_deviation: Optional[float] = Field(None, description="Largest deviation from the "
                                                             "planned path (rad).")
    singular: bool = Field(..., description="True when the re-integration met a singularity.")
    final: list[Optional[float]] = Field(..., description="Final state [phi, th1..thn] (rad).")
    integrator: str = Field(..., max_length=500,
                            description="'cascade-chebyshev on the original model' (the "
                                        "model's triangular structure integrated joint by "
                                        "joint by adaptive Chebyshev quadrature) or 'DOP853 "
                                        "on the original model' (scipy, the fallback).")
    error_estimate: Optional[float] = Field(None, description="Estimated error of the "
                                                              "re-integration (rad); null for "
                                                              "DOP853.")
    rtol: Optional[float] = None
    atol: Optional[float] = None
    executed: Optional["ExecutedValidation"] = Field(
        None, description="The original model executed from what the answer hands out: "
                          "path.u by path.rule.")
    joint_trajectory: Optional["ExecutedValidation"] = Field(
        None, description="The same for the joint_trajectory form (quintic Hermite), when "
                          "asked for.")


class ExecutedValidation(BaseModel):
    """The original model integrated under a handed-out form, by its documented rule."""

    rule: Literal["linear", "zoh", "cubic_hermite", "quintic_hermite"]
    terminal_error: Optional[float] = Field(None, description="max |th(T) - goal| (rad).")
    phi_error: Optional[float] = Field(None, description="|phi(T) - the plan's phi(T)| (rad).")
    margin: Optional[float] = Field(None, description="Smallest distance of th1..thn to the "
                                                      "region's bounds (rad), at the samples "
                                                      "and three points inside every interval.")
    singular: bool = Field(..., description="A joint left (0, pi/2).")
    initial_terminal_error: Optional[float] = Field(
        None, description="Terminal error before the correction (rad): of the L2 projection "
                          "of the exact rates onto the rule's functions, or for the "
                          "JointTrajectory form of the path's points.")
    corrections: int = Field(..., description="Correction steps taken.")
    error_estimate: Optional[float] = Field(None, description="Estimated error of the "
                                                              "integration (rad).")
    integrator: str = Field(..., max_length=500)
    final: list[Optional[float]] = Field(..., description="Final state [phi, th1..thn] (rad).")
    reversals: Optional[Reversals] = Field(
        None, description="Direction changes of phi and th1 on this form's execution (its "
                          "samples and three points inside every interval).")
    deviation: Optional[float] = Field(
        None, description="Largest joint-space distance (rad) of this form's execution from "
                          "the straight segment start -> goal.")
    d_a: Optional[float] = Field(
        None, description="Largest distance (rad) of this form's th1(t) from the straight "
                          "line in time (indicators.d_a is the handed-out path's; plan_indicators.d_a the "
                          "exact plan's, on its own schedule).")


Validation.model_rebuild()


class TimeFromStart(BaseModel):
    """``builtin_interfaces/Duration``."""

    sec: int
    nanosec: int = Field(..., ge=0, lt=10 ** 9)


class JointTrajectoryPoint(BaseModel):
    """``trajectory_msgs/JointTrajectoryPoint`` (the fields used)."""

    positions: list[float] = Field(..., description="[phi, th1] (rad).")
    velocities: list[float] = Field(..., description="[u1, u2] (rad/s).")
    accelerations: list[float] = Field(default_factory=list,
                                       description="[u1', u2'] (rad/s^2): with positions and "
                                                   "velocities, the controller interpolates "
                                                   "by quintics, the rule verified.")
    effort: list[float] = Field(default_factory=list, description="Empty.")
    time_from_start: TimeFromStart


class JointTrajectory(BaseModel):
    """The plan for position-controlled actuators in the shape of ROS 2
    ``trajectory_msgs/msg/JointTrajectory`` (no header): executed by quintic Hermite
    interpolation between consecutive points (positions, velocities and accelerations), as
    ``joint_trajectory_controller`` does."""

    joint_names: list[Annotated[str, Field(max_length=64)]] = Field(
        ..., description='["phi", "th1"].')
    points: list[JointTrajectoryPoint]
    interpolation: str = Field(..., max_length=64)
    time_scale: float = Field(
        1.0, ge=1.0,
        description="How much longer than the plan these points take: when the quintic "
                    "interpolant would exceed a limit (max_u*, max_du*, max_ddu*) between its "
                    "points, its times are stretched by the smallest factor f that keeps them, "
                    "its velocities divided by f and accelerations by f^2 (the same path: the "
                    "model has no drift); 1 otherwise.")


class ParetoMember(BaseModel):
    """One plan of the trade-off between actuator reversals and deviation (``pareto: true``),
    verified like the main plan: its inputs, indicators, handed-out path and validation."""

    max_reversals: int = Field(..., ge=0, description="Its reversal count (phi and th1): "
                                                      "send it as max_reversals to ask for "
                                                      "this plan alone.")
    origin: str = Field(..., description="objective (the plan the objective picked), "
                                         "straightest (the smallest deviation found) or "
                                         "'merged to k' (the straightest's sign pattern with "
                                         "its shortest runs merged).")
    chosen: bool = Field(..., description="It is the answer's main plan.")
    method: str
    phi_change: float = Field(..., description="dphi = phi(T) - phi(0) (rad).")
    b0: Optional[float] = None
    duration: float = Field(..., description="T (s).")
    coefficients: Coefficients
    indicators: Indicators
    path: PlanPath
    validation: Validation
    joint_trajectory: Optional[JointTrajectory] = None


class PlanResponse(BaseModel):
    """A verified, singularity-free plan."""

    status: Literal["success"]
    method: str = Field(..., max_length=64, description="Method that produced the plan.")
    robot: RobotInfo
    phi_change: float = Field(..., description="dphi = phi(T) - phi(0) (rad).")
    b0: Optional[float] = Field(None, description="Constant v1 = dphi / T (rad/s), null when "
                                                  "v1 varies.")
    duration: float = Field(..., description="T (s).")
    feasible_phi_changes: list[list[float]] = Field(
        ..., description="Singularity-free dphi intervals [lo, hi] (rad) of the polynomial "
                         "family (empty when not searched).")
    coefficients: Coefficients
    indicators: Indicators = Field(
        ..., description="Measured on the handed-out path (path, by its rule, re-integrated on "
                         "the original model): what a controller executes.")
    plan_indicators: Optional[Indicators] = Field(
        None, description="The exact plan's indicators on its own schedule (coefficients on "
                          "sigma): the values the methods optimise and the paper reports.")
    path: PlanPath
    validation: Validation
    joint_trajectory: Optional[JointTrajectory] = Field(
        None, description="With joint_trajectory: true in the request.")
    time_law: Optional[dict[str, Any]] = Field(
        None, description="How the answer runs the plan's path (coefficients, on the plan's "
                          "own time sigma in [0, plan_duration]) from rest to rest: "
                          "u(t) = u_plan(sigma(t)) sigma'(t); phases of constant jerk of the "
                          "parameter lam, knots mapping lam to sigma, the stops (times where "
                          "both rates are 0), the shortest duration within the limits and "
                          "the binding limit (docs/execution.md).")
    pareto: Optional[list[ParetoMember]] = Field(
        None, description="With pareto: true in the request: the non-dominated plans over "
                          "(reversals, deviation), fewest reversals first, each straighter "
                          "than every one before it.")
    timing: dict[str, Optional[float]] = Field(..., description="Seconds per stage.")
    diagnostics: dict[str, Any] = Field(..., description="Extra facts about the solve.")


class Problem(BaseModel):
    """An error (RFC 9457 problem details, ``application/problem+json``)."""

    type: str = Field(..., description="URI identifying the problem type.")
    title: str = Field(..., description="Short summary of the problem type.")
    status: int = Field(..., description="HTTP status code.")
    code: ProblemCode = Field(..., description="Machine-readable code.")
    detail: str = Field(..., description="Human-readable explanation.")
    field: Optional[str] = Field(None, description="The request field concerned, when known.")
    diagnostics: dict[str, Any] = Field(default_factory=dict,
                                        description="Machine-readable details.")
    request_id: Optional[str] = Field(None, description="The request's X-Request-ID.")


class SweepResponse(BaseModel):
    """Indicators and feasibility of the polynomial family over dphi (lists share indices)."""

    phi_change: list[float] = Field(..., description="dphi values (rad).")
    feasible: list[bool]
    margin: list[Optional[float]] = Field(..., description="Region margin (rad), null when "
                                                            "undefined.")
    d_a: list[Optional[float]] = Field(..., description="null where not feasible.")
    t_p: list[Optional[int]] = Field(..., description="null where not feasible.")
    sensitivity: list[Optional[float]]
    energy: list[Optional[float]] = Field(..., description="null where not feasible.")
    criterion: Literal["full", "z2"]
    feasible_phi_changes: Optional[list[list[float]]] = Field(
        None, description="Exact feasible intervals inside the range (null if not asked).")
    robot: RobotInfo


class SweepFigureRequest(BaseModel):
    """``POST /v1/figures/from_sweep``: a sweep answer to draw, and the planned dphi to mark."""

    model_config = ConfigDict(extra="forbid")

    sweep: SweepResponse = Field(..., description="The answer of POST /v1/sweeps, unchanged.")
    planned_phi_change: Optional[PhiAngle] = Field(  # type: ignore[valid-type]
        None, description="A plan's dphi (rad), drawn as a dashed line.")


class TransformedPoint(BaseModel):
    """One mapped point."""

    values: list[float] = Field(..., description="z (to_chained) or q (from_chained); zeros "
                                                 "where no inverse exists.")
    valid: bool = Field(..., description="False outside the region where the transform is a "
                                         "diffeomorphism.")
    reason: Optional[str] = Field(None, description="Why the point is not valid.")


class TransformResponse(BaseModel):
    """``POST /v1/transforms``."""

    direction: Literal["to_chained", "from_chained"]
    robot: RobotInfo
    points: list[TransformedPoint]


class RobustnessRun(BaseModel):
    """One open-loop replay from a perturbed start."""

    start: list[float] = Field(..., description="th1..thn at the start (rad).")
    final: list[Optional[float]] = Field(..., description="th1..thn at T (rad).")
    terminal_error: Optional[float] = Field(None, description="max |th(T) - goal| (rad).")
    d_a: Optional[float] = None
    t_p: Optional[int] = None
    singular: bool
    singular_time: Optional[float] = Field(None, description="When a singularity was met (s).")
    path_q: Optional[list[list[Optional[float]]]] = Field(
        None, description="Rows [phi, th1..thn] (only with include_paths).")


class RobustnessSummary(BaseModel):
    """Aggregates of the runs."""

    runs: int
    singular_runs: int
    terminal_error_max: Optional[float] = None
    terminal_error_mean: Optional[float] = None
    d_a_max: Optional[float] = None
    t_p_max: Optional[int] = None
    nominal_d_a: Optional[float] = None
    nominal_t_p: Optional[int] = None
    sensitivity: Optional[float] = None
    replay: Literal["u", "v"]


class RobustnessResponse(BaseModel):
    """``POST /v1/robustness``."""

    phi_change: float = Field(..., description="dphi of the nominal plan (rad).")
    method: str = Field(..., description="Method of the nominal plan.")
    runs: list[RobustnessRun]
    summary: RobustnessSummary
    closed_loop: Optional[dict[str, Any]] = Field(
        None, description="With closed_loop in the request: per run the plant's gain errors, "
                          "the open-loop and the closed-loop run on that plant (terminal_error "
                          "rad, reversals of phi and th1, deviation rad, margin rad, replans), "
                          "and a summary of both (medians, worst) with their ratio.")


class ReplanResponse(PlanResponse):
    """``POST /v1/replans``: the continuation of a plan, in a plan's shape; ``path.t`` runs
    from ``time`` to the end."""

    goal: list[float] = Field(..., description="th1..thn the continuation ends at (rad): the "
                                               "plan's goal.")
    time: float = Field(..., description="Seconds on the plan's time axis where the "
                                         "continuation starts (path.t[0]).")
    time_law: dict[str, Any] = Field(
        ..., description="sigma(t): plan_duration, stops (s) and phases rows [t0, dt, sigma0, "
                         "dsigma0, ddsigma0, jerk] of constant jerk; the rates at t are "
                         "u(sigma(t)) sigma'(t) with u from coefficients.segments (in plan "
                         "time sigma).")


#: Largest time_limit of a replan (s): the fast path takes about a millisecond, the full
#: planner (its fallback) tens.
MAX_REPLAN_TIME_LIMIT = 30.0


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

    plan: dict[str, Any] = Field(
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


class BatchItem(BaseModel):
    """The outcome of one request of a batch."""

    index: int = Field(..., description="Position of the request in the batch.")
    status: Literal["success", "error"]
    plan: Optional[PlanResponse] = Field(None, description="The plan, on success.")
    problem: Optional[Problem] = Field(None, description="The problem, on error.")


class BatchResponse(BaseModel):
    """``POST /v1/plans/batch``: one item per request, in order."""

    results: list[BatchItem]
    succeeded: int
    failed: int


class Health(BaseModel):
    """``GET /healthz``."""

    status: Literal["ok"]


class Readiness(BaseModel):
    """``GET /readyz``."""

    status: Literal["ready", "starting", "unavailable", "stopping"] = Field(
        ..., description="ready (200) while at least one worker is live; otherwise 503: "
                         "starting (the first workers warm up), unavailable (no worker is live; "
                         "replacements are starting) or stopping.")
    workers: int = Field(..., description="Configured worker processes.")
    live: int = Field(..., description="Worker processes started, warmed up and answering "
                                       "their liveness pings.")
    idle: int
    busy: int
    waiting: int = Field(..., description="Requests waiting for a worker.")
    restarts: int = Field(..., description="Workers replaced since start.")


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
                               "auto or shooting; costs several plans' time.")

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
