"""The building blocks of the service's request models: constrained number types, the
JSON Schema of joint angles, the worked example's values and the base of request models.

Units: angles in radians, times in seconds, rates in rad/s. Numeric fields accept only JSON
numbers (no strings, no ``NaN``/``Infinity``, no values that overflow to infinity).
"""

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, Strict
from pydantic_core import PydanticCustomError

from optimizer.planner.registry import METHODS, method_names
from optimizer.problem import OBJECTIVES, joint_angles_problem

from .settings import LIBRARY_MAX_JOINTS, LIBRARY_MIN_DURATION, LIBRARY_MIN_JOINTS

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
    """Weights of the ``weighted`` objective: w_da d_a + w_s ||J_R||_F + w_e energy + w_tp t_p.

    The methods that plan actuator rates (``shooting``, ``penalty``) weigh their path by w_da
    (on d_a and on the joint-space deviation) and w_e alone; every weight ranks the plans.
    Their NLPs price no direction change (w_tp only ranks): with the defaults (w_da alone) a
    plan may reverse 20 to 50 times on goals whose joints move both ways. For few reversals
    ask for the default objective, or for a budget (``max_reversals``).
    """

    d_a: Weight = Field(1.0, description="Weight of the approximation distance d_a.")  # type: ignore[valid-type]
    sensitivity: Weight = Field(0.0, description="Weight of ||J_R(T)||_F.")  # type: ignore[valid-type]
    energy: Weight = Field(0.0, description="Weight of the input energy.")  # type: ignore[valid-type]
    t_p: Weight = Field(0.0, description="Weight of the number of phi passes t_p.")  # type: ignore[valid-type]
