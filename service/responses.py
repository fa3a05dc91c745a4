"""Pydantic v2 models of the service's response bodies (they are the OpenAPI docs).

The routes return the planning library's JSON-safe dicts directly; these models document them
(a test checks the bodies against these schemas). Units: angles in radians, times in seconds,
rates in rad/s.
"""

from typing import Annotated, Any, Literal, Optional

from pydantic import BaseModel, Field

from .schema_fields import ProblemCode

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
    joint_bounds: Optional[list[Optional[list[float]]]] = Field(
        None, description="The request's joint_bounds (rad; null entries: the default), when "
                          "it had them: a replan of this answer keeps them.")
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
