"""Open-loop steering of the chained form with time-polynomial inputs (paper eq 8-12).

Everything is computed in normalised time ``tau = t / T`` in [0, 1], where the chained system
reads ``dz1/dtau = V1``, ``dz2/dtau = V2``, ``dz_{k+1}/dtau = z_k V1`` with ``V(tau) = T v(T tau)``.
With the paper's constant ``v1 = b0`` one has ``V1 = b0 T = dphi``: the geometric path depends on
``dphi`` only, ``T`` merely re-scales time (NOTES §4), and the linear systems stay well
conditioned whatever ``T`` is.

Inputs are piecewise polynomials in ``tau`` (one piece for the paper's family; several pieces let
``phi`` reverse). The chained state is then piecewise polynomial too, and exact.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numpy.polynomial import polynomial as P

from .errors import InvalidRequestError, SingularSystemError

#: Below this |dphi| (rad) the steering matrix M is treated as singular (Remark 2).
MIN_ABS_DPHI = 1e-6
#: Condition number of the (scaled) steering matrix above which it is singular.
MAX_CONDITION = 1e12


@dataclass(frozen=True)
class ConstraintPoint:
    """A constraint point of eq (9)-(11): the chained state ``z_state`` passes ``value`` at ``time``.

    Parameters
    ----------
    time : float
        Seconds, strictly inside (0, T).
    state : int
        Chained index in 2..n+1 (``z2`` is 2).
    value : float
    """

    time: float
    state: int
    value: float


@dataclass(frozen=True)
class InputSchedule:
    """Chained inputs as piecewise polynomials of normalised time.

    Attributes
    ----------
    breaks : ndarray, shape (S+1,)
        ``0 = tau_0 < ... < tau_S = 1``.
    v1, v2 : tuple of ndarray
        Per piece, coefficients (increasing powers of ``tau - tau_s``) of ``V1 = dz1/dtau``
        and ``V2 = dz2/dtau``.
    duration : float
        ``T`` in seconds.
    """

    breaks: np.ndarray
    v1: tuple[np.ndarray, ...]
    v2: tuple[np.ndarray, ...]
    duration: float

    @classmethod
    def single(cls, v1: Sequence[float], v2: Sequence[float], duration: float) -> "InputSchedule":
        """One polynomial piece on [0, 1]."""
        return cls(np.array([0.0, 1.0]), (np.asarray(v1, float),), (np.asarray(v2, float),),
                   float(duration))

    @property
    def pieces(self) -> int:
        return len(self.v1)

    def piece_index(self, tau: np.ndarray) -> np.ndarray:
        """Index of the piece holding each ``tau`` (right-continuous, last piece closed)."""
        # (the inner breaks only: the same index as searching all breaks and clipping to
        # [0, pieces - 1], without the clip)
        return np.searchsorted(self.breaks[1:-1], tau, side="right")

    def V(self, tau: np.ndarray) -> np.ndarray:
        """``[V1, V2]`` at normalised times, shape (N, 2)."""
        tau = np.atleast_1d(np.asarray(tau, float))
        if self.pieces == 1:
            x = tau - self.breaks[0]
            return np.stack([_horner(self.v1[0], x), _horner(self.v2[0], x)], axis=1)
        idx = self.piece_index(tau)
        x = tau - self.breaks[idx]
        return np.stack([_horner_pieces(self._v1_stack, idx, x),
                         _horner_pieces(self._v2_stack, idx, x)], axis=1)

    @functools.cached_property
    def _v1_stack(self) -> np.ndarray:
        return _stack_pieces([c[None, :] for c in self.v1])[:, 0, :]  # (S, L)

    @functools.cached_property
    def _v2_stack(self) -> np.ndarray:
        return _stack_pieces([c[None, :] for c in self.v2])[:, 0, :]

    def v(self, t: np.ndarray) -> np.ndarray:
        """Physical chained inputs ``[v1, v2]`` (rad/s) at times ``t`` (s), shape (N, 2)."""
        T = self.duration
        return self.V(np.asarray(t, float) / T) / T

    def physical_coefficients(self) -> list[dict[str, object]]:
        """Per piece: start and end times (s) and coefficients of ``v1``, ``v2`` in powers of
        ``(t - t_start)`` seconds (the paper's ``b0`` and ``c_i``, ``d_j``)."""
        T = self.duration
        out = []
        for s in range(self.pieces):
            scale1 = T ** -(np.arange(self.v1[s].size) + 1.0)
            scale2 = T ** -(np.arange(self.v2[s].size) + 1.0)
            out.append({"t_start": float(self.breaks[s] * T), "t_end": float(self.breaks[s + 1] * T),
                        "v1": (self.v1[s] * scale1).tolist(), "v2": (self.v2[s] * scale2).tolist()})
        return out

    @property
    def constant_v1(self) -> bool:
        """True for the paper's family: one piece and ``v1`` constant."""
        return self.pieces == 1 and bool(np.all(self.v1[0][1:] == 0.0))

    @property
    def phi_change(self) -> float:
        """Total change of phi, ``dphi = integral of V1``."""
        tot = 0.0
        if all(c.size == 1 for c in self.v1):
            # constant V1 on every piece (the retimed plans): c_0 h per piece, summed in order
            for x in (self._v1_stack[:, 0] * np.diff(self.breaks)).tolist():
                tot += x
            return tot
        for s in range(self.pieces):
            h = float(self.breaks[s + 1] - self.breaks[s])
            c = self.v1[s]
            # integral over the piece of sum c_k x^k = sum c_k h^(k+1) / (k+1)
            k = np.arange(1, c.size + 1)
            tot += float(np.dot(c, h ** k / k))
        return tot


@dataclass(frozen=True)
class ChainedPath:
    """The exact chained trajectory ``z(tau)`` produced by an :class:`InputSchedule` from ``z0``.

    Attributes
    ----------
    z0 : ndarray, shape (n+1,)
    inputs : InputSchedule
    polys : tuple of ndarray, shape (S,) of (n+1, deg+1)
        Per piece, polynomial coefficients (in ``tau - tau_s``) of each ``z_k``.
    """

    z0: np.ndarray
    inputs: InputSchedule
    polys: tuple[np.ndarray, ...] = field(repr=False)

    @classmethod
    def from_inputs(cls, z0: np.ndarray, inputs: InputSchedule) -> "ChainedPath":
        z0 = np.asarray(z0, float)
        nz = z0.size
        pieces = []
        zs = z0.copy()
        for s in range(inputs.pieces):
            v1, v2 = inputs.v1[s], inputs.v2[s]
            cs: list[np.ndarray]
            if v1.size == 1 and v1[0] != 0.0 and np.isfinite(v1[0]) \
                    and np.isfinite(v2).all() and np.isfinite(zs).all():
                # constant V1 (the paper's family): the same coefficients as below without
                # numpy.polynomial's per-call overhead (a product by a constant is exact)
                c1 = float(v1[0])
                cs = [np.array([zs[0], c1]), _polyint(v2, zs[1])]
                for k in range(2, nz):
                    cs.append(_polyint(_trim(_trim(cs[k - 1]) * c1), zs[k]))
            else:
                cs = [P.polyint(v1, k=zs[0]), P.polyint(v2, k=zs[1])]
                for k in range(2, nz):
                    cs.append(P.polyint(P.polymul(cs[k - 1], v1), k=zs[k]))
            deg = max(c.size for c in cs)
            arr = np.zeros((nz, deg))
            for k, c in enumerate(cs):
                arr[k, :c.size] = c
            pieces.append(arr)
            if s + 1 < inputs.pieces:  # the next piece starts where this one ends
                h = inputs.breaks[s + 1] - inputs.breaks[s]
                zs = np.array([P.polyval(h, c) for c in arr])
        return cls(z0, inputs, tuple(pieces))

    def z(self, tau: np.ndarray) -> np.ndarray:
        """Chained state at normalised times, shape (N, n+1)."""
        tau = np.atleast_1d(np.asarray(tau, float))
        if len(self.polys) == 1:
            x = tau - self.inputs.breaks[0]
            return _horner(self.polys[0].T, x[:, None])
        idx = self.inputs.piece_index(tau)
        x = tau - self.inputs.breaks[idx]
        return _horner_pieces(self._z_stack, idx, x[:, None])

    def z_components(self, tau: np.ndarray, first: int, stop: int) -> np.ndarray:
        """``z[:, first:stop]`` of :meth:`z` (the same values), computing only those
        components; shape (N, stop - first)."""
        tau = np.atleast_1d(np.asarray(tau, float))
        if len(self.polys) == 1:
            x = tau - self.inputs.breaks[0]
            return _horner(self.polys[0][first:stop].T, x[:, None])
        idx = self.inputs.piece_index(tau)
        x = tau - self.inputs.breaks[idx]
        return _horner_pieces(self._z_stack[:, :, first:stop], idx, x[:, None])

    @functools.cached_property
    def _z_stack(self) -> np.ndarray:
        # (S, L, n+1): per piece, powers first (one gather per Horner step in z)
        return _stack_pieces(list(self.polys)).transpose(0, 2, 1).copy()

    def z_end(self) -> np.ndarray:
        return self.z(np.array([1.0]))[0]

    def component_pieces(self, k: int) -> list[tuple[float, float, np.ndarray]]:
        """``[(tau_start, tau_end, coefficients in (tau - tau_start))]`` of ``z_{k+1}`` (0-based k)."""
        b = self.inputs.breaks
        return [(float(b[s]), float(b[s + 1]), arr[k]) for s, arr in enumerate(self.polys)]


def _polyint(c: np.ndarray, k: float) -> np.ndarray:
    """``numpy.polynomial.polynomial.polyint(c, k=k)`` for finite 1-D ``c`` (same values)."""
    n = c.size
    if n == 1 and c[0] == 0.0:
        return np.array([c[0] + k])
    out = np.empty(n + 1)
    out[0] = k                       # polyint: 0 + (k - p(0)), and p(0) = 0 there
    out[1] = c[0]
    out[2:] = c[1:] / np.arange(2, n + 1)
    return out


def _trim(c: np.ndarray) -> np.ndarray:
    """Without trailing zeros (at least one entry), as ``numpy.polynomial`` trims."""
    if c[-1] != 0.0:
        return c
    nz = np.flatnonzero(c)
    return c[:nz[-1] + 1] if nz.size else c[:1]


def _horner(c: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``sum_k c[k] x^k`` by Horner's rule along the first axis of ``c`` (increasing powers),
    with the operations of :func:`numpy.polynomial.polynomial.polyval` in the same order (so the
    same values, bit for bit)."""
    out = c[-1] + x * 0
    for k in range(c.shape[0] - 2, -1, -1):
        out = c[k] + out * x
    return out


def _stack_pieces(arrs: list[np.ndarray]) -> np.ndarray:
    """Per-piece coefficient arrays (C, L_s) as one (S, C, L) array, zero-padded at the top
    (leading zeros leave Horner's values unchanged)."""
    L = max(a.shape[1] for a in arrs)
    if all(a.shape[1] == L for a in arrs):
        return np.stack(arrs).astype(float, copy=False)     # one call (the usual case)
    out = np.zeros((len(arrs), arrs[0].shape[0], L))
    for s, a in enumerate(arrs):
        out[s, :, :a.shape[1]] = a
    return out


def _horner_pieces(stack: np.ndarray, idx: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Piecewise polynomials at points: ``stack`` (S, L, ...) coefficients in increasing
    powers (axis 1) per piece, ``idx`` (N,) the piece of each point, ``x`` (N,) or (N, 1) the
    local times; returns (N, ...). All points at once instead of a loop over pieces."""
    L = stack.shape[1]
    c = stack[idx]                      # one gather; the Horner steps then take views
    out = c[:, L - 1] + x * 0
    for k in range(L - 2, -1, -1):
        out = c[:, k] + out * x
    return out


# ---------------------------------------------------------------------- the paper's family
def affine_basis(dphi: float, n: int, z0: np.ndarray, p: int,
                 tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The chained state under ``V1 = dphi`` is affine in the ``p`` coefficients of ``V2`` (eq 10).

    Parameters
    ----------
    dphi : float
    n : int
        Number of joints (chained states ``z2..z_{n+1}``).
    z0 : ndarray, shape (n+1,)
    p : int
        Number of ``V2`` coefficients (powers 0..p-1 of tau).
    tau : ndarray, shape (N,)

    Returns
    -------
    free : ndarray, shape (N, n)
        ``z_{k}(tau)`` for k = 2..n+1 with ``V2 = 0``: ``sum_l (dphi tau)^(k-l)/(k-l)! z_l(0)``.
    basis : ndarray, shape (N, n, p)
        ``d z_k(tau) / d a_i = dphi^(k-2) i! tau^(i+k-1) / (i+k-1)!``.
    """
    free, basis = affine_basis_batch(np.array([dphi], float), n, z0, p, tau)
    return free[0], basis[0]


def affine_basis_batch(dphi: np.ndarray, n: int, z0: np.ndarray, p: int,
                       tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`affine_basis` for many ``dphi`` at once: shapes (D, N, n) and (D, N, n, p)."""
    dphi = np.asarray(dphi, float)
    tau = np.atleast_1d(np.asarray(tau, float))
    z0 = np.asarray(z0, float)
    x = dphi[:, None] * tau[None, :]                       # (D, N)
    free = np.zeros((dphi.size, tau.size, n))
    for kk in range(n):  # kk = k - 2
        for ll in range(kk + 1):
            free[:, :, kk] += x ** (kk - ll) / math.factorial(kk - ll) * z0[ll + 1]
    kcol = np.arange(n)[:, None]
    irow = np.arange(p)[None, :]
    # i! / (i + k + 1)! as exact integers first (they overflow int64 beyond 20!)
    const = np.array([[math.factorial(i) / math.factorial(i + k + 1) for i in range(p)]
                      for k in range(n)])                   # (n, p)
    powers = tau[:, None, None] ** (irow + kcol + 1)[None]  # (N, n, p)
    dpow = dphi[:, None] ** np.arange(n)[None, :]          # (D, n)
    basis = dpow[:, None, :, None] * (const[None] * powers)[None]
    return free, basis


def steering_system(dphi: float, n: int, z0: np.ndarray, zT: np.ndarray, p: int,
                    points: Sequence[ConstraintPoint] = (), duration: float = 1.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The linear equality ``M a = r`` of eq (11): hit ``z(T) = zT`` and pass the constraint points.

    Returns ``M`` of shape (n + m, p) and ``r`` of shape (n + m,), for ``V2`` coefficients ``a``.
    """
    taus = np.array([1.0] + [cp.time / duration for cp in points])
    free, basis = affine_basis(dphi, n, z0, p, taus)
    rows = [basis[0]]
    rhs = [np.asarray(zT, float)[1:] - free[0]]
    for j, cp in enumerate(points):
        kk = cp.state - 2
        rows.append(basis[j + 1, kk][None, :])
        rhs.append(np.array([cp.value - free[j + 1, kk]]))
    return np.vstack(rows), np.concatenate(rhs)


def validate_constraint_points(points: Sequence[ConstraintPoint], n: int, duration: float) -> None:
    """Raise :class:`InvalidRequestError` for a point outside (0, T), a bad state index,
    a non-finite value or two points on the same state at the same time."""
    seen = set()
    for j, cp in enumerate(points):
        f = f"constraint_points[{j}]"
        if not (math.isfinite(cp.time) and 0.0 < cp.time < duration):
            raise InvalidRequestError(f"{f}.time = {cp.time!r} must lie strictly inside (0, T = {duration})",
                                      field=f"{f}.time")
        if not 2 <= cp.state <= n + 1:
            raise InvalidRequestError(f"{f}.state = {cp.state!r} must be a chained index in 2..{n + 1}",
                                      field=f"{f}.state")
        if not math.isfinite(cp.value):
            raise InvalidRequestError(f"{f}.value must be finite", field=f"{f}.value")
        key = (cp.state, round(cp.time / duration, 12))
        if key in seen:
            raise InvalidRequestError(f"{f} repeats the time and state of an earlier point",
                                      field=f)
        seen.add(key)


def solve_polynomial(dphi: float, n: int, z0: np.ndarray, zT: np.ndarray, duration: float = 1.0,
                     points: Sequence[ConstraintPoint] = (), known_regular: bool = False
                     ) -> InputSchedule:
    """The paper's inputs (eq 8-9): ``v1 = b0``, ``v2`` of degree ``n - 1 + m``; solve eq (11).

    Parameters
    ----------
    dphi : float
        Total change of phi (``b0 T``), rad.
    n : int
        Number of joints.
    z0, zT : ndarray, shape (n+1,)
        Start and goal in chained coordinates (``z1`` entries are ignored).
    duration : float
        ``T``, s.
    points : sequence of ConstraintPoint

    Returns
    -------
    InputSchedule

    Raises
    ------
    SingularSystemError
        ``|dphi|`` below :data:`MIN_ABS_DPHI` (Remark 2), or constraint times making M singular.
    """
    if not math.isfinite(dphi) or abs(dphi) < MIN_ABS_DPHI:
        raise SingularSystemError(
            f"phi_change = {dphi!r}: the steering matrix M(T) is singular when dphi = 0 "
            f"(paper Remark 2); |phi_change| must be at least {MIN_ABS_DPHI} rad",
            field="phi_change")
    p = n + len(points)
    M, r = steering_system(dphi, n, z0, zT, p, points, duration)
    # Column scaling: the powers of dphi make the raw matrix badly scaled for large n.
    scale = np.linalg.norm(M, axis=0)
    scale[scale == 0.0] = 1.0
    Ms = M / scale
    # (known_regular: the caller has shown the test passes, e.g. FamilySystem.surely_regular)
    cond = 1.0 if known_regular else np.linalg.cond(Ms)
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise SingularSystemError(
            f"the steering matrix M(T) is singular (condition number {cond:.3g}): check that the "
            "constraint points have distinct times or states and that phi_change is not 0",
            field="constraint_points" if points else "phi_change",
            diagnostics={"condition_number": float(cond) if np.isfinite(cond) else None})
    a = np.linalg.solve(Ms, r) / scale
    return InputSchedule.single([float(dphi)], a.tolist(), duration)


# ---------------------------------------------------------------------- batched family members
#: Largest ``m * n * k`` of one matrix product in the batched helpers: below OpenBLAS's
#: threading threshold, so that a product never starts (and waits for) BLAS threads; on a
#: loaded machine a threaded product of this size costs milliseconds instead of microseconds.
_MATMUL_CHUNK = 200_000


def matmul_single_thread(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` for 2-D arrays, in row blocks small enough to stay single-threaded."""
    m, k = A.shape
    cols = B.shape[1]
    rows = max(1, _MATMUL_CHUNK // max(1, k * cols))
    if m <= rows:
        return A @ B
    out = np.empty((m, cols))
    for s in range(0, m, rows):
        np.matmul(A[s:s + rows], B, out=out[s:s + rows])
    return out


def polyval_rows(coef: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Evaluate many polynomials at shared points: ``coef`` (..., L) in increasing powers,
    ``x`` (G,); returns (..., G)."""
    coef = np.asarray(coef, float)
    x = np.asarray(x, float)
    L = coef.shape[-1]
    V = np.ones((L, x.size))
    for j in range(1, L):
        np.multiply(V[j - 1], x, out=V[j])
    flat = coef.reshape(-1, L)
    return matmul_single_thread(flat, V).reshape(coef.shape[:-1] + (x.size,))


def polyval_each(coef: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Evaluate row-wise polynomials at row-wise points (Horner): ``coef`` (R, C, L),
    ``x`` (R, T); returns (C, R, T) (component first, so that each component is contiguous)."""
    L = coef.shape[-1]
    cT = coef.transpose(1, 0, 2)                                   # (C, R, L)
    out = np.empty((cT.shape[0], cT.shape[1], x.shape[1]))
    out[...] = cT[:, :, L - 1:L]
    for j in range(L - 2, -1, -1):
        out *= x
        out += cT[:, :, j:j + 1]
    return out


@functools.lru_cache(maxsize=256)
def _family_matrix(k_rows: tuple[int, ...], t_rows: tuple[float, ...], p: int
                   ) -> tuple[np.ndarray, bool, float]:
    """``C`` of :class:`FamilySystem` (read-only), whether it is regular, and ``rho``."""
    # i! / (i + k + 1)! t^(i + k + 1), as exact integer ratios first
    C = np.array([[math.factorial(i) / math.factorial(i + k + 1) * t ** (i + k + 1)
                   for i in range(p)] for k, t in zip(k_rows, t_rows)])
    kmax = int(max(k_rows))
    with np.errstate(all="ignore"):
        try:
            inv_norm = float(np.linalg.norm(np.linalg.inv(C), 2))
        except np.linalg.LinAlgError:
            inv_norm = math.inf
    regular = math.isfinite(inv_norm)
    # The singularity test of solve_polynomial (condition number of the column-scaled
    # matrix M(dphi) = diag(dphi^k_r) C) depends on |dphi| only and is bounded by
    # sqrt(p) ||C||_F ||C^-1|| (max(1, |dphi|) / min(1, |dphi|))^kmax: inside
    # 1/rho < |dphi| < rho it passes for sure; outside it is computed exactly.
    K0 = math.sqrt(p) * float(np.linalg.norm(C)) * inv_norm
    if not regular or K0 >= MAX_CONDITION:
        rho = 1.0
    elif kmax == 0:
        rho = math.inf
    else:
        rho = (MAX_CONDITION / K0) ** (1.0 / kmax)
    C.flags.writeable = False
    return C, regular, rho


class FamilySystem:
    """The paper's family for fixed ``z0``, ``zT``, duration and constraint points, solved for
    many ``dphi`` at once (eq 10-11).

    Every row of the steering matrix targets ``z_{k+2}`` at some time and scales with
    ``dphi^k``: ``M(dphi) = diag(dphi^k_r) C`` with a constant ``C``. So the ``V2``
    coefficients of all members come from one factorisation of ``C``:
    ``a = C^-1 (dphi^-k_r (target_r - free_r(dphi)))``. Members whose (column-scaled) steering
    matrix is singular by the test of :func:`solve_polynomial` are flagged, as there.

    Parameters
    ----------
    n : int
    z0, zT : ndarray (n+1,)
    duration : float
    points : sequence of ConstraintPoint
    """

    def __init__(self, n: int, z0: np.ndarray, zT: np.ndarray, duration: float,
                 points: Sequence[ConstraintPoint] = ()) -> None:
        self.n = n
        self.z0 = np.asarray(z0, float)
        self.zT = np.asarray(zT, float)
        self.p = p = n + len(points)
        self.L = p + n                      # coefficients of z_{n+1} (degree p + n - 1)
        t_rows = [1.0] * n + [cp.time / duration for cp in points]
        k_rows = list(range(n)) + [cp.state - 2 for cp in points]
        targets = list(self.zT[1:]) + [cp.value for cp in points]
        self.t_rows = np.array(t_rows)
        self.k_rows = np.array(k_rows)
        self.targets = np.array(targets, float)
        # the matrix C and its conditioning depend on the rows' times and states only (not on
        # the start or goal): shared by every request with the same n and constraint points
        self.C, self.regular, self.rho = _family_matrix(tuple(k_rows), tuple(t_rows), p)
        self.kmax = kmax = int(max(k_rows))
        # free part of row r (V2 = 0) as a polynomial in dphi:
        # sum_j dphi^j t_r^j / j! z0[k_r - j + 1]   (j = 0..k_r)
        self.F = np.zeros((kmax + 1, len(k_rows)))
        for r, (k, t) in enumerate(zip(k_rows, t_rows)):
            for j in range(k + 1):
                self.F[j, r] = t ** j / math.factorial(j) * self.z0[k - j + 1]
        self.inv_j = 1.0 / np.arange(1, self.L)

    def surely_regular(self, dphi: float) -> bool:
        """Whether the singularity test of :func:`solve_polynomial` passes for ``dphi`` by the
        bound behind ``rho`` (with a factor 2 to spare), so that it need not be computed."""
        ad = abs(float(dphi))
        return self.regular and 2.0 / self.rho < ad < 0.5 * self.rho

    def coefficients(self, dphis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``V2`` coefficients (D, p) of the members and a mask of the regular ones (the others'
        rows are zero)."""
        d = np.atleast_1d(np.asarray(dphis, float))
        D = d.size
        ad = np.abs(d)
        ok = ad >= MIN_ABS_DPHI                        # False for NaN too
        dd = np.where(ok, d, 1.0)
        pw = np.empty((D, self.kmax + 1))              # dphi^j
        pw[:, 0] = 1.0
        for j in range(1, self.kmax + 1):
            np.multiply(pw[:, j - 1], dd, out=pw[:, j])
        free = pw @ self.F if D * self.F.size < 50_000 else matmul_single_thread(pw, self.F)
        dpow = pw[:, self.k_rows]                      # (D, R)
        rhs = (self.targets - free) / dpow
        if not self.regular:
            return np.zeros((D, self.p)), np.zeros(D, bool)
        a = np.linalg.solve(self.C, rhs.T).T
        check = ok & ~((ad > 1.0 / self.rho) & (ad < self.rho))
        if check.any():
            idx = np.nonzero(check)[0]
            M = dpow[idx, :, None] * self.C[None]
            scale = np.linalg.norm(M, axis=1, keepdims=True)
            scale[scale == 0.0] = 1.0
            with np.errstate(all="ignore"):
                cond = np.linalg.cond(M / scale)
            ok[idx] &= np.isfinite(cond) & (cond <= MAX_CONDITION)
        ok &= np.isfinite(a).all(axis=1)
        a[~ok] = 0.0
        return a, ok

    def polys(self, dphis: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Coefficients (D, n+1, L) in increasing powers of ``tau`` of ``z1..z_{n+1}`` of the
        members with ``V1 = dphi`` and ``V2`` coefficients ``a`` (D, p)."""
        d = np.atleast_1d(np.asarray(dphis, float))
        D, n, L, p = d.size, self.n, self.L, self.p
        c = np.zeros((D, n + 1, L))
        c[:, 0, 0] = self.z0[0]
        c[:, 0, 1] = d
        c[:, 1, 0] = self.z0[1]
        c[:, 1, 1:p + 1] = a / np.arange(1, p + 1)
        scale = d[:, None] * self.inv_j[None, :]                     # dphi / (j + 1)
        for k in range(2, n + 1):
            c[:, k, 0] = self.z0[k]
            np.multiply(c[:, k - 1, :-1], scale, out=c[:, k, 1:])
        return c
