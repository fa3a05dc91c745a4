"""The benchmark cases: start and goal joint angles (deg), T = 1 s.

Two kinds (``kind``):

``paper``
    Goals of the paper's type, which its constant-``v1`` polynomial family can reach (every joint
    ``th_2..th_n`` moves in the direction of ``phi``, and a singularity-free ``dphi`` window
    exists).
``beyond``
    Goals the paper's family cannot reach: joints that must move in opposite directions (``phi``
    must reverse), or same-direction moves for which no ``dphi`` of the family stays in the
    singularity-free region. Only the penalty method (and ``auto``, which falls back to it) can
    plan these.

The 4- and 5-joint cases use :meth:`optimizer.model.Robot.default` (assumed constants,
NOTES §3).
"""

from __future__ import annotations

from dataclasses import dataclass

#: Duration of every benchmark path (s).
DURATION = 1.0


@dataclass(frozen=True)
class Case:
    """One start/goal pair.

    Attributes
    ----------
    name : str
        Short identifier used in the table and the JSON.
    start_deg, goal_deg : tuple of float
        ``th_1..th_n`` (deg).
    kind : {"paper", "beyond"}
        Which target applies (see the module docstring).
    note : str
        Why the case is here.
    """

    name: str
    start_deg: tuple[float, ...]
    goal_deg: tuple[float, ...]
    kind: str
    note: str = ""

    @property
    def n(self) -> int:
        """Number of joints."""
        return len(self.start_deg)


CASES: tuple[Case, ...] = (
    Case("p3_1to30", (1, 1, 1), (30, 30, 30), "paper", "paper §3.3 example"),
    Case("p3_5to30", (5, 5, 5), (30, 30, 30), "paper", "paper-type goal"),
    Case("p3_10to30", (10, 10, 10), (30, 30, 30), "paper", "NOTES §5 worked example"),
    Case("p3_20to40", (20, 20, 20), (40, 40, 40), "paper", "issue 8 paper-type goal"),
    Case("p3_40to45", (40, 40, 40), (45, 45, 45), "paper", "issue 8 paper-type goal"),
    Case("opp3_a", (10, 20, 30), (40, 25, 15), "beyond",
         "th2 up, th3 down: phi must reverse"),
    Case("opp3_b", (20, 40, 10), (35, 15, 45), "beyond",
         "th2 down, th3 up: phi must reverse"),
    Case("n4_window", (47.7, 66.9, 44.9, 66.0), (62.6, 72.2, 47.5, 71.9), "paper",
         "4 joints, narrow dphi window of the polynomial family"),
    Case("n4_small", (30, 40, 40, 40), (35, 45, 38, 45), "beyond",
         "4 joints, small moves, th3 against th2/th4"),
    Case("n5_small", (68, 65, 65, 40, 30), (62.6, 69.1, 68.1, 43.2, 36.8), "beyond",
         "5 joints, small moves; no dphi of the family is singularity-free"),
)


def select(names: list[str] | None = None, count: int | None = None) -> list[Case]:
    """The cases to run.

    Parameters
    ----------
    names : list of str, optional
        Case names to keep (all when None).
    count : int, optional
        Keep only the first ``count`` of them.

    Returns
    -------
    list of Case
    """
    cases = list(CASES)
    if names:
        unknown = set(names) - {c.name for c in cases}
        if unknown:
            raise ValueError(f"unknown cases {sorted(unknown)}; known: {[c.name for c in CASES]}")
        cases = [c for c in cases if c.name in names]
    if count is not None:
        cases = cases[:count]
    return cases
