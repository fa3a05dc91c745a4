"""The one door every method goes through: its name, what it can do, and ``plan(request, ctx)``.

A method is an object (in the spirit of rockit's transcriptions and toppra's solver wrappers):
the registry (:mod:`.registry`) lists them, and the request validation, the service's schema and
``auto`` read names and capabilities from there. What a method cannot do is refused here, in
one place, before it runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

from ..errors import InvalidRequestError
from ..problem import PlanRequest
from ..results import Plan
from .context import PlanContext


@dataclass(frozen=True)
class Capabilities:
    """What a method can do.

    Attributes
    ----------
    constraint_points : bool
        Honours the request's constraint points (points of the chained inputs).
    fixed_phi_change : bool
        Honours a fixed ``phi_change``.
    reverses_phi : bool
        May reverse ``phi``: reaches goals where joints move in opposite directions.
    inputs : str
        ``"chained"`` (polynomial chained inputs ``v1, v2``) or ``"actuator"`` (piecewise-
        constant actuator rates planned on the original model).
    max_joints : int
        The largest number of joints it plans for.
    via_points : bool
        Honours joint-space via points (:mod:`optimizer.via_points`).
    """

    constraint_points: bool
    fixed_phi_change: bool
    reverses_phi: bool
    inputs: str
    max_joints: int = 8
    via_points: bool = False

    def as_dict(self) -> dict[str, Any]:
        return {"constraint_points": self.constraint_points,
                "fixed_phi_change": self.fixed_phi_change, "reverses_phi": self.reverses_phi,
                "inputs": self.inputs, "max_joints": self.max_joints,
                "via_points": self.via_points}


class Method:
    """A planning method. Subclasses set :attr:`name`, :attr:`capabilities` and
    :attr:`options` (their own tuning, read-only) and implement :meth:`run`; the registry
    (:mod:`.registry`) holds the line that describes it."""

    name: ClassVar[str]
    capabilities: ClassVar[Capabilities]
    options: ClassVar[Mapping[str, Any]] = {}

    def check(self, req: PlanRequest) -> None:
        """Refuse a request this method cannot honour (:class:`InvalidRequestError`)."""
        cap = self.capabilities
        if req.constraint_points and not cap.constraint_points:
            raise InvalidRequestError(
                f"method {self.name!r} takes no constraint points (they are points of the "
                "chained polynomial inputs: use 'polynomial', 'constraint_points' or 'auto')",
                field="constraint_points")
        if req.via_points and not cap.via_points:
            raise InvalidRequestError(
                f"method {self.name!r} cannot honour via_points: its paths are the paper's "
                "polynomial family in chained form, whose points are chained-form states z_k, "
                "not joint angles; use method 'shooting' or 'penalty' (or 'auto', which then "
                "runs only those)", field="via_points")
        if req.phi_change is not None and not cap.fixed_phi_change:
            raise InvalidRequestError(f"method {self.name!r} does not take a fixed phi_change",
                                      field="phi_change")
        if req.n > cap.max_joints:
            raise InvalidRequestError(f"method {self.name!r} plans for at most "
                                      f"{cap.max_joints} joints", field="start")

    def can_plan(self, req: PlanRequest) -> bool:
        """Whether :meth:`check` would accept ``req``."""
        try:
            self.check(req)
        except InvalidRequestError:
            return False
        return True

    def plan(self, req: PlanRequest, ctx: PlanContext) -> Plan:
        """Check ``req`` against the capabilities, then run the method."""
        self.check(req)
        return self.run(req, ctx)

    def run(self, req: PlanRequest, ctx: PlanContext) -> Plan:  # pragma: no cover - abstract
        raise NotImplementedError
