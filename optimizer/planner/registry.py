"""The registry of planning methods: the one list of their names.

Adding a method is its own module (a :class:`~.base.Method` subclass, with its capabilities)
and one line here. The request validation (:func:`get`), the service's schema and ``auto`` read
this registry. A method's module is imported when the method is first asked for, so a process
that only validates requests (the service's front process) loads no solver.
"""

from __future__ import annotations

import functools
import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..errors import InvalidRequestError

if TYPE_CHECKING:  # the front process imports the registry without the methods' modules
    from .base import Method

#: The orchestrator's name: it picks among the registered methods (:mod:`.auto`).
AUTO = "auto"


@dataclass(frozen=True)
class Entry:
    """A registered method: its name, where its class lives and what it does, in a line."""

    name: str
    target: str
    summary: str


ENTRIES: tuple[Entry, ...] = (
    Entry("polynomial", "optimizer.planner.polynomial:PolynomialMethod",
          "the paper's family: constant v1 = b0, polynomial v2 through the request's "
          "constraint points; dphi from its singularity-free intervals by the objective"),
    Entry("retimed", "optimizer.planner.retimed:RetimedMethod",
          "the paper's geometric path along the time law that minimises d_a of joint 1 (same "
          "path, t_p and deviation as polynomial; no constraint points)"),
    Entry("constraint_points", "optimizer.planner.convex:ConstraintPointsMethod",
          "the paper's family with constraint points synthesised by a convex QP (Clarabel) "
          "with cutting planes"),
    Entry("penalty", "optimizer.planner.penalty:PenaltyMethod",
          "the paper's Remark 3 on the multiple-shooting transcription of the original model: "
          "the singularity-avoiding inequality (z2 < 0 and the rest of the region, every joint "
          "inside) as an exact penalty in the objective; phi may reverse (no constraint points)"),
    Entry("shooting", "optimizer.planner.shooting:ShootingMethod",
          "direct multiple shooting on the original model: piecewise-constant actuator rates, "
          "minimum energy plus joint-space deviation, the region as hard constraints; phi may "
          "reverse (no constraint points)"),
)
METHODS: dict[str, Entry] = {e.name: e for e in ENTRIES}


def method_names() -> tuple[str, ...]:
    """Every name a request may give, ``auto`` first."""
    return (AUTO,) + tuple(METHODS)


@functools.cache
def _load(target: str) -> Method:
    module, cls = target.split(":")
    method: Method = getattr(importlib.import_module(module), cls)()
    return method


def get(name: str) -> Method:
    """The registered method ``name``; :class:`InvalidRequestError` naming the field else."""
    entry = METHODS.get(name)
    if entry is None:
        raise InvalidRequestError(f"method = {name!r} must be one of {list(method_names())}",
                                  field="method")
    method = _load(entry.target)
    if method.name != name:  # pragma: no cover - a registration mistake
        raise TypeError(f"{entry.target} is named {method.name!r}, registered as {name!r}")
    return method
