"""Result objects of the planner: a verified plan, sampled paths, and their JSON shape."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .actuation import ActuatorSchedule
from .execution import Execution
from .indicators import Indicators
from .model import Robot
from .paths import SampledPath
from .steering import ChainedPath, InputSchedule
from .timing import TimeLaw
from .verify import Verification


@dataclass(frozen=True)
class ParetoMember:
    """One member of the trade-off between actuator reversals and deviation (``pareto``).

    Attributes
    ----------
    plan : Plan
        The member, verified like any plan (its indicators, inputs and handed-out path).
    origin : str
        Which candidate it is (``objective``: the plan the objective picked; ``straightest``;
        ``merged to k``: the straightest's sign pattern with runs merged, see
        :mod:`optimizer.planner.budget`).
    max_reversals : int
        The ``max_reversals`` that asks for this member alone (its reversal count).
    chosen : bool
        It is the answer's main plan.
    """

    plan: "Plan"
    origin: str
    max_reversals: int
    chosen: bool

    def to_dict(self) -> dict[str, Any]:
        """Its JSON shape: the plan's without the front, robot, timing and diagnostics."""
        out = self.plan.to_dict(plain=False)
        for key in ("pareto", "robot", "timing", "diagnostics", "status",
                    "feasible_phi_changes"):
            out.pop(key, None)
        out.update(origin=self.origin, max_reversals=self.max_reversals, chosen=self.chosen)
        return out


@dataclass(frozen=True)
class Plan:
    """A verified, singularity-free plan.

    Attributes
    ----------
    robot : Robot
    method : str
        The method that produced it (``polynomial``, ``constraint_points``, ``penalty``).
    phi_change : float
        ``dphi`` (rad).
    duration : float
        ``T`` (s) of the handed-out path (the plan's path along ``time_law``).
    inputs : InputSchedule or ActuatorSchedule
        Chained inputs (the paper's methods and the penalty method) or piecewise-constant
        actuator rates (``shooting``, planned on the original model), on the plan's own time
        ``sigma`` in ``[0, inputs.duration]``: with ``time_law`` enough to regenerate
        everything.
    chained : ChainedPath or None
        The chained path of chained inputs (None for actuator-rate plans).
    feasible_phi_changes : list of (float, float)
        Singularity-free ``dphi`` intervals of the paper's family (empty when not computed).
    indicators : Indicators
        Measured on the handed-out path (the default form's replay, re-integrated on the
        original model): what a controller executes, ``d_a`` included.
    margin : float
        Region margin of the continuous path (rad, full criterion).
    path : SampledPath
        The handed-out, executable path (:mod:`optimizer.execution`): its ``u`` under its
        rule (linear interpolation, or zero-order hold on ``controller_period``) drives the
        original model to the goal; ``q`` and ``z`` are that replay's states.
    verification : Verification
        The proof from the exact input segments.
    timing : dict of str to float
        Seconds per stage.
    diagnostics : dict
        Extra facts (which start won, solver status, ...).
    execution : Execution or None
        The check of the handed-out forms (``validation.executed``) and the JointTrajectory
        form when asked for.
    time_law : TimeLaw or None
        How the handed-out path runs the plan's: ``u(t) = u_plan(sigma(t)) sigma'(t)``, rest
        to rest (:mod:`optimizer.timing`).
    pareto : tuple of ParetoMember or None
        With ``pareto`` in the request: the non-dominated plans over (reversals, deviation),
        fewest reversals first (:mod:`optimizer.planner.budget`).
    plan_indicators : Indicators or None
        The exact plan's indicators on its own schedule (the input segments on ``sigma``): the
        values the methods optimise and the paper reports (its ``d_a`` is of that timing).
    joint_bounds : tuple or None
        The request's joint bounds (rad, ``None`` entries: the default), handed out so that a
        replan of the answer keeps them.
    """

    robot: Robot
    method: str
    phi_change: float
    duration: float
    inputs: InputSchedule | ActuatorSchedule
    chained: ChainedPath | None
    feasible_phi_changes: list[tuple[float, float]]
    indicators: Indicators
    margin: float
    path: SampledPath
    verification: Verification
    timing: dict[str, float] = field(default_factory=dict)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    execution: Execution | None = None
    time_law: TimeLaw | None = None
    pareto: tuple[ParetoMember, ...] | None = None
    plan_indicators: Indicators | None = None
    joint_bounds: tuple[tuple[float, float] | None, ...] | None = None

    @property
    def b0(self) -> float | None:
        """The paper's constant ``v1 = b0 = dphi / T`` of the plan's own schedule (None when
        ``v1`` varies)."""
        return self.phi_change / self.inputs.duration if self.inputs.constant_v1 else None

    def rates_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The exact rates of the time law and their derivatives at times ``t`` (s), each
        shape (M, 2) (the handed-out samples are these, corrected by ~1e-9 rad/s)."""
        if self.time_law is None:
            raise ValueError("this plan has no time law")
        return self.time_law.rates_and_derivative(np.atleast_1d(np.asarray(t, float)))

    def to_dict(self, *, plain: bool = True) -> dict[str, Any]:
        """The JSON shape of a successful ``POST /v1/plans`` response (finite numbers only).

        Parameters
        ----------
        plain : bool
            True: Python lists, floats and ``None`` for non-finite numbers
            (:func:`json_safe`). False: numpy arrays and scalars are left in, for an encoder
            that writes them itself and maps non-finite numbers to ``null`` (the service's
            orjson), which saves the conversion (~0.3 ms of a 3 ms plan).
        """
        ind = self.indicators
        ver = self.verification
        out: dict[str, Any] = {
            "status": "success",
            "method": self.method,
            "robot": self.robot.as_dict(),
            "phi_change": self.phi_change,
            "b0": self.b0,
            "duration": self.duration,
            "feasible_phi_changes": [[a, b] for a, b in self.feasible_phi_changes],
            "coefficients": {
                "basis": ("v1(t), v2(t) as power series in (t - t_start), t in s"
                          if self.chained is not None else
                          "actuator rates u = (u1, u2) (rad/s) constant on each segment; v1 = u1, "
                          "v2 is not a polynomial (empty)"),
                "segments": self.inputs.physical_coefficients(),
            },
            "indicators": indicators_dict(ind, self.margin),
            "path": {
                "t": self.path.t,
                "q": self.path.q,
                "z": self.path.z,
                "u": self.path.u,
                "v": self.path.v,
            },
            "validation": {
                "terminal_error": ver.terminal_error,
                "phi_error": ver.phi_error,
                "max_deviation": ver.max_deviation,
                "singular": ver.singular,
                "final": list(ver.final),
                "integrator": f"{ver.integrator} on the original model",
                "error_estimate": ver.error_estimate,
                "rtol": ver.rtol,
                "atol": ver.atol,
            },
            "timing": dict(self.timing),
            "diagnostics": dict(self.diagnostics),
        }
        exe = self.execution
        if exe is not None:
            out["path"]["rule"] = exe.check.rule
            out["validation"].update(exe.validation())
            if exe.joint_trajectory is not None:
                out["joint_trajectory"] = exe.joint_trajectory
        if self.time_law is not None:
            out["time_law"] = self.time_law.as_dict()
        if self.pareto is not None:
            out["pareto"] = [m.to_dict() for m in self.pareto]
        if self.plan_indicators is not None:
            out["plan_indicators"] = indicators_dict(self.plan_indicators, self.margin)
        if self.joint_bounds is not None:
            out["joint_bounds"] = [None if b is None else [float(b[0]), float(b[1])]
                                   for b in self.joint_bounds]
        return json_safe(out) if plain else out


def indicators_dict(ind: Indicators, margin: float) -> dict[str, Any]:
    """The JSON shape of indicators (``indicators``, ``plan_indicators``)."""
    return {
        "d_a": ind.d_a,
        "d_a_per_joint": list(ind.d_a_per_joint),
        "d_a_joint_space": ind.d_a_joint_space,
        "t_p": ind.t_p,
        "phi_reversals": ind.phi_reversals,
        "sensitivity": ind.sensitivity,
        "sensitivity_max": ind.sensitivity_max,
        "energy": ind.energy,
        "margin": margin,
        "deviation": ind.deviation,
        "reversals": {"phi": ind.reversals_phi, "th1": ind.reversals_th1},
    }


def json_safe(obj: Any) -> Any:
    """Recursively convert numpy types to Python and refuse non-finite floats (-> None).

    Dict keys become strings, tuples lists, numpy arrays nested lists, numpy scalars Python
    ones; strings, ``None`` and other objects are returned as they are.
    """
    # exact built-in types first (a plan's answer is mostly these): one type() test each
    # instead of a chain of isinstance() tests; subclasses (numpy's float64 is a float) take
    # the general path below, with the same result
    tp = type(obj)
    if tp is float:
        return obj if _isfinite(obj) else None
    if tp is dict:
        return {k if type(k) is str else str(k): json_safe(v) for k, v in obj.items()}
    if tp is list or tp is tuple:
        if tp is list and _finite_floats(obj):
            return obj.copy()  # a new list, as always (the caller may change it)
        return [json_safe(v) for v in obj]
    if tp is str or tp is int or tp is bool or obj is None:
        return obj
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        # the path arrays are large: one vectorised finiteness test, then tolist() (Python
        # floats) without walking every number, unless some entry must become None
        if obj.dtype.kind == "f" and bool(np.isfinite(obj).all()):
            return obj.tolist()
        if obj.dtype.kind in "iub":
            return obj.tolist()
        return json_safe(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return x if math.isfinite(x) else None
    return obj


_isfinite = math.isfinite


def _finite_floats(items: list[Any]) -> bool:
    """Whether a list holds Python floats only, all finite: then :func:`json_safe` would
    return an equal list (the same floats), so the list itself can be used."""
    for x in items:
        if type(x) is not float:
            return False
    # a sum of floats is finite only if every term is (an inf or nan term makes it inf or
    # nan; a finite overflow to inf makes it look non-finite: the slow path decides then)
    return _isfinite(sum(items, 0.0))
