"""One wrapper of Clarabel for the planner's convex subproblems (the constraint-point QP and
the time-law LP): ``min 1/2 x' P x + q' x  s.t.  A x <= b``.

Why a wrapper: both callers hand Clarabel small dense problems many times per plan. Building
scipy matrices costs more than the solve (~40 us a constructor), so :class:`Csc` builds the
compressed columns Clarabel reads directly; and a solver built once for a shape can be updated
in place (:func:`solve_nonneg_persistent`, per thread: a solver is not shareable), which the
constraint-point QP's cut rounds use. The solver settings are written here once.
"""

from __future__ import annotations

import threading
from typing import Any

import clarabel
import numpy as np
from scipy import sparse

#: Persistent solvers kept per thread before the cache is cleared (old cut rounds' shapes).
MAX_PERSISTENT = 32
_SOLVERS = threading.local()


def settings(*, keep_pattern: bool = False) -> Any:
    """Clarabel's settings for the planner: quiet; with ``keep_pattern`` presolve off and
    structural zeros kept, so that a solver may be updated in place later."""
    s = clarabel.DefaultSettings()
    s.verbose = False
    if keep_pattern:
        s.presolve_enable = False
        s.input_sparse_dropzeros = False
    return s


class Csc:
    """A CSC matrix with the attributes Clarabel reads (``data``, ``indices``, ``indptr``,
    ``nnz``, ``shape``, ``has_canonical_format``): built from a small dense matrix in a few
    microseconds, where scipy's constructors (format checks, COO round trip) take ~40 us.
    Canonical: row indices sorted within each column, no duplicates, explicit zeros dropped
    (the same arrays as ``scipy.sparse.csc_matrix(dense)``)."""

    has_canonical_format = True

    def __init__(self, data: np.ndarray, indices: np.ndarray, indptr: np.ndarray,
                 shape: tuple[int, int]) -> None:
        # Python lists: Clarabel copies the entries out one by one, and from a list of Python
        # numbers that is several times cheaper than from a numpy array (a scalar object each)
        self.data: list[float] = np.asarray(data, float).tolist()
        self.indices: list[int] = np.asarray(indices).tolist()
        self.indptr: list[int] = np.asarray(indptr).tolist()
        self.nnz = int(self.indptr[-1])
        self.shape = shape

    @classmethod
    def from_dense(cls, A: np.ndarray) -> "Csc":
        mask = A.T != 0.0                                   # (columns, rows): column-major
        indptr = np.zeros(A.shape[1] + 1, np.int64)
        np.cumsum(np.count_nonzero(mask, axis=1), out=indptr[1:])
        return cls(A.T[mask], np.nonzero(mask)[1], indptr, (A.shape[0], A.shape[1]))

    def to_scipy(self) -> sparse.csc_matrix:
        return sparse.csc_matrix((self.data, self.indices, self.indptr), shape=self.shape)


def dense_csc(G: np.ndarray) -> sparse.csc_matrix:
    """CSC storing every entry (explicit zeros too): one sparsity pattern per shape."""
    r, d = G.shape
    return sparse.csc_matrix((G.ravel(order="F"), np.tile(np.arange(r), d),
                              np.arange(0, r * d + 1, r)), shape=(r, d))


def diagonal(d: np.ndarray) -> sparse.csc_matrix:
    """``diag(d)`` as CSC."""
    return sparse.diags(d, format="csc")


def solve(P: Any, q: Any, A: Any, b: Any, *, keep_pattern: bool = False) -> Any:
    """Solve ``min 1/2 x'Px + q'x  s.t.  A x <= b`` once; Clarabel's solution object.

    ``P`` (upper triangle) and ``A`` are CSC (:class:`Csc` or scipy's); a Clarabel that wants
    scipy's own class gets it.
    """
    cones = [clarabel.NonnegativeConeT(len(b))]
    qq, bb = np.asarray(q, float), np.asarray(b, float)
    try:
        solver = clarabel.DefaultSolver(P, qq.tolist() if isinstance(P, Csc) else qq, A,
                                        bb.tolist() if isinstance(A, Csc) else bb, cones,
                                        settings(keep_pattern=keep_pattern))
    except (AttributeError, TypeError):
        to_scipy = (lambda M: M.to_scipy() if isinstance(M, Csc) else M)
        solver = clarabel.DefaultSolver(to_scipy(P), qq, to_scipy(A), bb, cones,
                                        settings(keep_pattern=keep_pattern))
    return solver.solve()


def solve_nonneg_persistent(Pd: np.ndarray, q: np.ndarray, G: np.ndarray, h: np.ndarray) -> Any:
    """:func:`solve` with ``P = diag(Pd)`` and a dense ``G``, reusing the solver built for the
    same shape and objective (updated in place: new ``A`` values and ``b``). A solver whose
    solve did not end Solved is dropped, so that a next problem never inherits its state."""
    cache = getattr(_SOLVERS, "cache", None)
    if cache is None:
        cache = _SOLVERS.cache = {}
    key = (G.shape, Pd.tobytes(), q.tobytes())
    solver = cache.get(key)
    if solver is None:
        if len(cache) > MAX_PERSISTENT:
            cache.clear()
        solver = clarabel.DefaultSolver(diagonal(Pd), q, dense_csc(G), h,
                                        [clarabel.NonnegativeConeT(G.shape[0])],
                                        settings(keep_pattern=True))
        cache[key] = solver
    else:
        solver.update(A=G.ravel(order="F"), b=h)
    sol = solver.solve()
    if not str(sol.status).endswith("Solved") or str(sol.status).endswith("AlmostSolved"):
        cache.pop(key, None)
    return sol
