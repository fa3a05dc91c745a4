"""The robot of a request (light: imported by the server process as well as by the workers)."""

from __future__ import annotations

from typing import Any

from optimizer.model import Robot


def robot_from(spec: dict[str, Any] | None, n: int) -> Robot:
    """The robot of a request: the given gains/exponents, else ``Robot.default(n)``.

    Same rule as :meth:`optimizer.problem.PlanRequest.from_dict`.
    """
    if not spec or (spec.get("gains") is None and spec.get("exponents") is None):
        return Robot.default(n)
    return Robot(tuple(spec.get("gains") or ()), tuple(spec.get("exponents") or ()))
