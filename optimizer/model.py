"""The n-joint underactuated manipulator's kinematic model (paper eq 1-3, NOTES §1 and §3).

State ``q = [phi, th1, ..., thn]`` (phi is the horizontal actuator's angle), inputs
``u = [u1, u2]``::

    phi'  = u1
    th1'  = u2
    th_i' = K_i cos(th_{i-1})^{m_i} u1        (i = 2..n)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .dynamics import field_numpy
from .errors import InvalidRequestError

#: Prototype constants fitted to the paper's §3.3 example (NOTES §1).
PROTOTYPE_GAINS = (0.88658, 0.7115)
PROTOTYPE_EXPONENTS = (2, 3)
MIN_JOINTS = 3
MAX_JOINTS = 8


@dataclass(frozen=True)
class Robot:
    """Parameters of an n-joint arm driven by two motors through friction disks.

    Parameters
    ----------
    gains : tuple of float
        ``(K2, ..., Kn)``, transmission gains, all > 0.
    exponents : tuple of int
        ``(m2, ..., mn)``, integer exponents >= 1 of ``cos(th_{i-1})``.

    Notes
    -----
    The number of joints is ``n = len(gains) + 1`` and must lie in [3, 8].
    """

    gains: tuple[float, ...] = PROTOTYPE_GAINS
    exponents: tuple[int, ...] = PROTOTYPE_EXPONENTS
    assumed: bool = field(default=False, compare=False)

    def __post_init__(self) -> None:
        gains = tuple(float(k) for k in self.gains)
        try:
            exps_f = [float(m) for m in self.exponents]
        except (TypeError, ValueError) as exc:
            raise InvalidRequestError("robot.exponents must be integers >= 1",
                                      field="robot.exponents") from exc
        if len(gains) != len(exps_f):
            raise InvalidRequestError(
                f"robot.gains has {len(gains)} entries but robot.exponents has {len(exps_f)}; "
                "both list K2..Kn and m2..mn", field="robot.exponents")
        n = len(gains) + 1
        if not MIN_JOINTS <= n <= MAX_JOINTS:
            raise InvalidRequestError(
                f"number of joints n = {n} is outside [{MIN_JOINTS}, {MAX_JOINTS}] "
                f"(robot.gains must have {MIN_JOINTS - 1} to {MAX_JOINTS - 1} entries)",
                field="robot.gains")
        for i, k in enumerate(gains):
            if not math.isfinite(k) or k <= 0.0:
                raise InvalidRequestError(
                    f"robot.gains[{i}] = {k!r} must be a finite number > 0", field="robot.gains")
        for i, m in enumerate(exps_f):
            if not math.isfinite(m) or m != int(m) or m < 1 or m > 12:
                raise InvalidRequestError(
                    f"robot.exponents[{i}] = {m!r} must be an integer in [1, 12]",
                    field="robot.exponents")
        object.__setattr__(self, "gains", gains)
        object.__setattr__(self, "exponents", tuple(int(m) for m in exps_f))

    @classmethod
    def default(cls, n: int = 3) -> "Robot":
        """The prototype for ``n = 3``; for other ``n`` the assumed extension of NOTES §3.

        For ``n > 3`` the paper gives no constants: ``K_i = 0.88658`` (i < n),
        ``K_n = 0.7115``, ``m_i = 2`` (i < n), ``m_n = 3``. This is an assumption and the
        returned robot says so (``assumed=True``).
        """
        if not MIN_JOINTS <= n <= MAX_JOINTS:
            raise InvalidRequestError(f"n = {n} is outside [{MIN_JOINTS}, {MAX_JOINTS}]",
                                      field="n")
        gains = (PROTOTYPE_GAINS[0],) * (n - 2) + (PROTOTYPE_GAINS[1],)
        exps = (PROTOTYPE_EXPONENTS[0],) * (n - 2) + (PROTOTYPE_EXPONENTS[1],)
        return cls(gains, exps, assumed=(n != 3))

    @classmethod
    def from_spec(cls, spec: "dict[str, object] | None", n: int) -> "Robot":
        """The robot of a request: the given ``gains``/``exponents``, else ``default(n)``."""
        if not spec or (spec.get("gains") is None and spec.get("exponents") is None):
            return cls.default(n)
        gains = spec.get("gains") or ()
        exps = spec.get("exponents") or ()
        return cls(tuple(gains), tuple(exps))  # type: ignore[arg-type]

    @property
    def n(self) -> int:
        """Number of joints."""
        return len(self.gains) + 1

    @property
    def state_dim(self) -> int:
        """Dimension of ``q`` (n + 1)."""
        return self.n + 1

    def g1(self, q: np.ndarray) -> np.ndarray:
        """Vector field multiplying ``u1`` (eq 3), for ``q`` of shape (..., n+1)."""
        return field_numpy(self.gains, self.exponents, q, (1.0, 0.0))

    def rhs(self, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``q' = g1(q) u1 + g2(q) u2`` (eq 2) for one state ``q`` and input ``u``."""
        return field_numpy(self.gains, self.exponents, q, (u[0], u[1]))

    def as_dict(self) -> dict[str, object]:
        """JSON-friendly description."""
        return {"n": self.n, "gains": list(self.gains), "exponents": list(self.exponents),
                "assumed_constants": self.assumed}
