"""The registry of planning methods: the one list of their names and capabilities.

Adding a method is its own module (a :class:`~.base.Method` subclass) and one line here. The
request validation (:func:`get`), the service's schema and ``auto`` read this registry.
"""

from __future__ import annotations

from .base import Method
from .convex import ConstraintPointsMethod
from .penalty import PenaltyMethod
from .polynomial import PolynomialMethod
from .retimed import RetimedMethod
from .shooting import ShootingMethod
from ..errors import InvalidRequestError

#: The orchestrator's name: it picks among the registered methods (:mod:`.auto`).
AUTO = "auto"

METHODS: dict[str, Method] = {m.name: m for m in (
    PolynomialMethod(), RetimedMethod(), ConstraintPointsMethod(), PenaltyMethod(),
    ShootingMethod())}


def method_names() -> tuple[str, ...]:
    """Every name a request may give, ``auto`` first."""
    return (AUTO,) + tuple(METHODS)


def get(name: str) -> Method:
    """The registered method ``name``; :class:`InvalidRequestError` naming the field else."""
    try:
        return METHODS[name]
    except KeyError:
        raise InvalidRequestError(f"method = {name!r} must be one of {list(method_names())}",
                                  field="method") from None
