"""Joint-space via points: "joint ``th_j`` passes through ``angle`` (rad) at ``time`` (s)".

A robotics engineer's waypoint, as opposed to the paper's constraint points (values of the
chained states ``z_k`` at times, :mod:`optimizer.steering`). Joints are named as the answer's
columns name them (``path.q_names``: ``th1`` .. ``thn``); times are on the handed-out time
axis (``path.t``, seconds from the start). The methods that plan on the original model
(``shooting``, ``penalty``) honour them exactly (:mod:`optimizer.planner.via`); the paper's
family (``polynomial``, ``retimed``, ``constraint_points``) cannot, and refuses them.

This module is the request's side: the point, parsing from JSON, and the checks that need no
planner (time inside the duration, a joint of the robot, an angle inside the joint's range and
bounds, one angle per joint and time). Every refusal names the field, the limit and what to
send instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

from .errors import InvalidRequestError

#: At most this many via points in one request...
MAX_VIA_POINTS = 24
#: ... at this many distinct times (each becomes a node of the transcription, whose coarsest
#: rung has 12 intervals).
MAX_VIA_TIMES = 8
#: Two via times closer than this (s) are the same time (one node of the transcription).
SAME_TIME = 1e-9


@dataclass(frozen=True)
class ViaPoint:
    """Joint ``joint`` (a name ``th1`` .. ``thn``) at ``angle`` (rad) at ``time`` (s).

    ``time`` lies on the handed-out time axis (``path.t``), strictly inside ``(0, duration)``.
    """

    time: float
    joint: str
    angle: float

    @property
    def index(self) -> int:
        """The joint's index in ``th_1..th_n`` (0-based): ``th2`` -> 1."""
        return int(self.joint[2:]) - 1

    def as_dict(self) -> dict[str, Any]:
        return {"time": self.time, "joint": self.joint, "angle": self.angle}


def joint_names(n: int) -> list[str]:
    """The joints' names of an ``n``-joint robot, as ``path.q_names`` has them after ``phi``."""
    return [f"th{i}" for i in range(1, n + 1)]


def via_points_from(seq: Any) -> tuple[ViaPoint, ...]:
    """Via points from their JSON shape (a list of ``{"time", "joint", "angle"}``), or
    :class:`InvalidRequestError` naming the element and the field that is wrong."""
    if seq is None:
        return ()
    if isinstance(seq, (str, bytes, Mapping)) or not isinstance(seq, Sequence):
        raise InvalidRequestError('via_points must be a list of {"time": s, "joint": "th2", '
                                  '"angle": rad}', field="via_points")
    out = []
    for i, item in enumerate(seq):
        where = f"via_points[{i}]"
        if isinstance(item, ViaPoint):
            out.append(item)
            continue
        if not isinstance(item, Mapping):
            raise InvalidRequestError(f'{where} must be an object {{"time": s, "joint": "th2", '
                                      f'"angle": rad}}', field=where)
        unknown = sorted(set(item) - {"time", "joint", "angle"})
        if unknown:
            raise InvalidRequestError(f"{where} has unknown field(s) {unknown}: a via point is "
                                      "time (s), joint (th1..thn) and angle (rad)",
                                      field=f"{where}.{unknown[0]}")
        for key in ("time", "joint", "angle"):
            if key not in item:
                raise InvalidRequestError(f"{where}.{key} is required", field=f"{where}.{key}")
        for key, unit in (("time", "s"), ("angle", "rad")):
            x = item[key]
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise InvalidRequestError(f"{where}.{key} must be a finite number ({unit})",
                                          field=f"{where}.{key}")
        joint = item["joint"]
        if not isinstance(joint, str):
            raise InvalidRequestError(
                f'{where}.joint must be a joint\'s name as path.q_names has it ("th1", "th2", '
                f'...), not {joint!r}', field=f"{where}.joint")
        out.append(ViaPoint(float(item["time"]), joint, float(item["angle"])))
    return tuple(out)


def _deg(x: float) -> str:
    return f"{math.degrees(x):.1f} deg"


def joint_range(index: int, n: int, bounds: Sequence[Any] | None) -> tuple[float, float, bool]:
    """The range a via angle of joint ``index`` (0-based) may take: ``(lo, hi, open)``.

    Joints ``th_1..th_{n-1}`` lie in the open ``(0, pi/2)`` (where the chained form exists),
    ``th_n`` in ``[-2 pi, 2 pi]``; intersected with the joint's bound when one is given.
    """
    if index < n - 1:
        lo, hi, open_ = 0.0, math.pi / 2, True
    else:
        lo, hi, open_ = -2 * math.pi, 2 * math.pi, False
    if bounds is not None and index < len(bounds) and bounds[index] is not None:
        blo, bhi = float(bounds[index][0]), float(bounds[index][1])
        lo, hi = max(lo, blo), min(hi, bhi)
    return lo, hi, open_


def validate_via_points(points: Sequence[ViaPoint], n: int, duration: float | None,
                        bounds: Sequence[Any] | None) -> None:
    """Refuse via points that no plan can honour, naming the element and the limit.

    Parameters
    ----------
    points : sequence of ViaPoint
    n : int
        The robot's number of joints.
    duration : float or None
        ``T`` (s) the times must lie inside; ``None``: unknown (actuator limits and no
        duration), which via points cannot have (their times are seconds of the answer).
    bounds : sequence or None
        The request's ``joint_bounds``.

    Raises
    ------
    InvalidRequestError
    """
    if len(points) > MAX_VIA_POINTS:
        raise InvalidRequestError(f"via_points has {len(points)} points, at most "
                                  f"{MAX_VIA_POINTS}", field="via_points")
    if not points:
        return
    if duration is None:
        raise InvalidRequestError(
            "via point times are seconds on the answer's time axis: give a duration when "
            "actuator limits (max_u*, max_du*, max_ddu*) are set", field="duration")
    names = joint_names(n)
    seen: dict[tuple[str, float], int] = {}
    for i, vp in enumerate(points):
        where = f"via_points[{i}]"
        if not 0.0 < vp.time < duration:
            raise InvalidRequestError(
                f"{where}.time = {vp.time:g} s must lie strictly inside (0, duration) = (0, "
                f"{duration:g}) s: the start and the goal are the path's ends (move the time "
                f"inside, or lengthen the duration)", field=f"{where}.time",
                diagnostics={"time": vp.time, "duration": duration})
        if vp.joint not in names:
            if vp.joint == "phi":
                hint = " (phi is the first actuator's angle, not a joint)"
            else:
                hint = ' (named as path.q_names names them: "th1" is the first joint)'
            raise InvalidRequestError(
                f"{where}.joint = {vp.joint!r} must be one of {names} (the robot has n = {n} "
                f"joints){hint}", field=f"{where}.joint", diagnostics={"joints": names})
        j = vp.index
        lo, hi, open_ = joint_range(j, n, bounds)
        inside = lo < vp.angle < hi if open_ else lo <= vp.angle <= hi
        if not inside:
            bounded = bounds is not None and j < len(bounds) and bounds[j] is not None
            a, b = ("(", ")") if open_ else ("[", "]")
            where_range = (f"{a}{lo:g}, {hi:g}{b} rad = {a}{math.degrees(lo):.4g}, "
                           f"{math.degrees(hi):.4g}{b} deg")
            why = (f"joint {vp.joint}'s range within its joint_bounds[{j}]" if bounded else
                   f"joint {vp.joint}'s range" + (" (the singularity-free region)" if j < n - 1
                                                   else ""))
            degrees = (" (it looks like degrees: angles are in radians, i.e. "
                       f"{math.radians(vp.angle):.6g})"
                       if hi < abs(vp.angle) <= 360.0 and lo <= math.radians(vp.angle) <= hi
                       else "")
            raise InvalidRequestError(
                f"{where}.angle = {vp.angle:g} rad ({_deg(vp.angle)}) is outside {why} "
                f"{where_range}{degrees}", field=f"{where}.angle",
                diagnostics={"joint": vp.joint, "angle": vp.angle, "range": [lo, hi]})
        for (joint, t), k in seen.items():
            if joint == vp.joint and abs(t - vp.time) <= SAME_TIME:
                raise InvalidRequestError(
                    f"{where} and via_points[{k}] both fix {vp.joint} at t = {vp.time:g} s: "
                    "one angle per joint and time (drop one of them)", field=where,
                    diagnostics={"joint": vp.joint, "time": vp.time, "duplicate_of": k})
        seen[(vp.joint, vp.time)] = i
    times = distinct_times(points)
    if len(times) > MAX_VIA_TIMES:
        raise InvalidRequestError(
            f"via_points has {len(times)} distinct times, at most {MAX_VIA_TIMES} (points of "
            "several joints at one time count once)", field="via_points")


def distinct_times(points: Sequence[ViaPoint]) -> list[float]:
    """The via points' times, sorted, those within :data:`SAME_TIME` of each other once."""
    out: list[float] = []
    for t in sorted(vp.time for vp in points):
        if not out or t - out[-1] > SAME_TIME:
            out.append(t)
    return out
