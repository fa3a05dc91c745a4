"""Chained form of the n-joint arm: q <-> z and the input map u <-> v (paper eq 4-5, NOTES §2-3).

Coordinates (n joints, chained state ``z = [z1, ..., z_{n+1}]``)::

    z1      = phi
    z_{n+1} = th_n
    z_k     = L_g1 z_{k+1}          (k = n, ..., 2)
    v1      = u1
    v2      = (L_g1 z2) u1 + (L_g2 z2) u2

so that ``z1' = v1, z2' = v2, z_{k+1}' = z_k v1``.

Structure used for the inverse map: ``z_k`` depends on ``th_{k-1}, ..., th_{n-1}`` only and is
affine in ``w_k = cos(th_{k-1})^{m_k}``::

    z_k = a_k(th_k..th_{n-1}) * w_k + b_k(th_k..th_{n-1})
    a_k = K_k * d z_{k+1} / d th_k,   b_k = sum_{j>k} d z_{k+1}/d th_j * K_j cos(th_{j-1})^{m_j}

Going down from ``th_n = z_{n+1}``, each ``th_{k-1} = arccos(w_k^(1/m_k))`` with
``w_k = (z_k - b_k) / a_k``. The map is a diffeomorphism on the region where every ``w_k`` lies
in (0, 1), i.e. ``th_1, ..., th_{n-1}`` in (0, pi/2) (``th_n`` is free): see :mod:`.region`.

Two implementations: a closed form for ``n = 3`` (numpy) and, for any ``n``, expressions derived
symbolically with CasADi (Lie derivatives along g1) once per exponents, the gains an input.

Conditioning: near ``th_i = 0`` the map flattens (``cos(th)^m ~ 1 - m th^2 / 2``), so z holds
``th_i`` only to about ``eps / th_i`` and the inverse amplifies the rounding of z by the map's
condition number, level after level: round trips are exact to ~1e-14 rad for the prototype with
joints above a few degrees, but a z rounded to 6 decimals at th1 = 1 deg maps back to ~0.9 deg,
and for n = 8 near the region's edges errors reach 1e-4 rad. The tests bound the round-trip error
by the condition number of dz/dq.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from . import native
from .dynamics import vector_field
from .model import Robot

#: Boundary tolerance on w_k = cos(th_{k-1})^{m_k}: a point with w_k within this of 0 or 1 is
#: treated as on the boundary (outside the open region).
W_TOL = 1e-12


@dataclass(frozen=True)
class InverseResult:
    """Result of the inverse map z -> q for a batch of points.

    Attributes
    ----------
    q : ndarray, shape (N, n+1)
        Joint-space points; rows that are not valid are filled with zeros (never NaN).
    w : ndarray, shape (N, n-1)
        ``w_k = cos(th_{k-1})^{m_k}`` for k = 2..n (column k-2); valid iff all in (0, 1).
        Entries after the first failing level (going down from k = n) are 0.
    valid : ndarray of bool, shape (N,)
    failed_level : ndarray of int, shape (N,)
        The joint index ``i`` (1..n-1) whose angle would leave (0, pi/2) first, 0 when valid.
    """

    q: np.ndarray
    w: np.ndarray
    valid: np.ndarray
    failed_level: np.ndarray

    def reasons(self) -> list[str | None]:
        """A human-readable reason per point (``None`` for valid points)."""
        out: list[str | None] = []
        for ok, lvl, wrow in zip(self.valid, self.failed_level, self.w):
            if ok:
                out.append(None)
                continue
            k = int(lvl) + 1
            wk = float(wrow[k - 2])
            side = "<= 0" if not wk > W_TOL else ">= 1"
            out.append(f"z{k} maps to cos(th{lvl})^m = {wk:.6g} {side}: th{lvl} would leave (0, pi/2)"
                       if np.isfinite(wk) else
                       f"z{k} cannot be inverted: th{lvl} undefined (a joint at 0 or pi/2)")
        return out


class ChainedForm:
    """The chained-form transform of one robot, compiled once.

    Parameters
    ----------
    robot : Robot
    backend : {"auto", "closed", "casadi"}
        ``"closed"`` uses the n = 3 closed form (numpy), ``"casadi"`` the symbolic derivation;
        ``"auto"`` picks the closed form when ``n == 3``.
    """

    def __init__(self, robot: Robot, backend: str = "auto") -> None:
        if backend not in ("auto", "closed", "casadi"):
            raise ValueError(f"unknown backend {backend!r}")
        if backend == "closed" and robot.n != 3:
            raise ValueError("the closed form exists for n = 3 only")
        self.robot = robot
        self.n = robot.n
        self.backend = "closed" if (backend == "closed" or (backend == "auto" and robot.n == 3)) \
            else "casadi"
        self._sym = symbolic_form(tuple(robot.exponents))
        # the gains, the last input of every symbolic function (a contiguous column)
        self._K = np.ascontiguousarray(robot.gains, dtype=float)
        self._K.setflags(write=False)

    # ------------------------------------------------------------------ forward
    def to_chained(self, q: np.ndarray) -> np.ndarray:
        """Map joint-space points to chained coordinates (eq 4).

        Parameters
        ----------
        q : array_like, shape (n+1,) or (N, n+1)
            ``[phi, th1, ..., thn]``.

        Returns
        -------
        z : ndarray, same shape as ``q``
        """
        q = np.asarray(q, dtype=float)
        qq = np.atleast_2d(q)
        if self.backend == "closed":
            z = _closed_forward(self.robot, qq)
        else:
            z = _eval_columns(self._sym.forward, self._sym.maps["forward"], self._K, qq)
        return z.reshape(q.shape)

    def input_coefficients(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``alpha = L_g1 z2`` and ``beta = L_g2 z2`` (eq 5): ``v2 = alpha u1 + beta u2``."""
        q = np.asarray(q, dtype=float)
        qq = np.atleast_2d(q)
        if self.backend == "closed":
            al, be = _closed_input(self.robot, qq)
        else:
            ab = _eval_columns(self._sym.alpha_beta, self._sym.maps["alpha_beta"], self._K, qq)
            al, be = ab[:, 0], ab[:, 1]
        if q.ndim == 1:
            return al[:1].copy()[0], be[:1].copy()[0]
        return al, be

    def v_from_u(self, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Chained inputs from actuator inputs (eq 5)."""
        u = np.asarray(u, dtype=float)
        al, be = self.input_coefficients(q)
        v = np.empty_like(u)
        v[..., 0] = u[..., 0]
        v[..., 1] = al * u[..., 0] + be * u[..., 1]
        return v

    def u_from_v(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Actuator inputs from chained inputs (eq 5 inverted); needs ``L_g2 z2 != 0``."""
        v = np.asarray(v, dtype=float)
        al, be = self.input_coefficients(q)
        u = np.empty_like(v)
        u[..., 0] = v[..., 0]
        u[..., 1] = (v[..., 1] - al * v[..., 0]) / be
        return u

    def u_from_zv(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Actuator inputs at chained points: ``u_from_v(from_chained(z).q, v)`` in one pass.

        The vectorised hot path of the verification (the planned inputs at a few hundred
        quadrature nodes at once): the n = 3 closed form in plain numpy, for other ``n`` one
        CasADi call on all points (horizontally stacked columns). Points that are not valid
        (some ``w_k`` outside (0, 1), see :meth:`from_chained`) are recomputed through
        :meth:`from_chained` and :meth:`u_from_v`, so the result is the same there too
        (``u2`` not finite).

        Parameters
        ----------
        z : array_like, shape (N, n+1)
        v : array_like, shape (N, 2)

        Returns
        -------
        u : ndarray, shape (N, 2)
        """
        zz = np.atleast_2d(np.asarray(z, dtype=float))
        vv = np.atleast_2d(np.asarray(v, dtype=float))
        if self.backend == "closed":
            u, w = _closed_u_from_zv(self.robot, zz, vv)
        else:
            uw = _eval_columns(self._sym.u_w_from_zv, self._sym.maps["u_w_from_zv"], self._K,
                              zz, vv)
            u, w = uw[:, :2], uw[:, 2:]
        if zz.shape[0] and not (W_TOL < w.min() and w.max() < 1.0 - W_TOL   # NaN fails too
                                and np.isfinite(zz).all()):
            with np.errstate(invalid="ignore"):
                ok = np.isfinite(zz).all(axis=1) & np.all((w > W_TOL) & (w < 1.0 - W_TOL), axis=1)
            # rare (the path leaves the region): the reference path, for identical semantics
            bad = ~ok
            with np.errstate(divide="ignore", invalid="ignore"):
                u[bad] = self.u_from_v(self.from_chained(zz[bad]).q, vv[bad])
        return u

    # ------------------------------------------------------------------ inverse
    def from_chained(self, z: np.ndarray) -> InverseResult:
        """Map chained coordinates back to joint space, saying where that is impossible.

        Parameters
        ----------
        z : array_like, shape (n+1,) or (N, n+1)

        Returns
        -------
        InverseResult
            Always finite; ``valid`` is False where some ``th_i`` (i < n) would leave
            (0, pi/2), and ``failed_level`` names that joint.
        """
        zz = np.atleast_2d(np.asarray(z, dtype=float))
        N, n = zz.shape[0], self.n
        if self.backend == "closed" and N and np.isfinite(zz).all():
            fast = self._from_chained3(zz)
            if fast is not None:
                return fast
        q = np.zeros((N, n + 1))
        w = np.zeros((N, n - 1))
        valid = np.isfinite(zz).all(axis=1)
        failed = np.zeros(N, dtype=int)
        failed[~valid] = n - 1
        q[valid, 0] = zz[valid, 0]
        q[valid, n] = zz[valid, n]
        for k in range(n, 1, -1):  # z_k gives th_{k-1}
            idx = np.nonzero(valid)[0]
            if idx.size == 0:
                break
            if self.backend == "closed":
                a, b = _closed_ab(self.robot, k, q[idx])
            else:
                ab = _eval_columns(self._sym.ab[k], self._sym.maps[f"ab{k}"], self._K, q[idx])
                a, b = ab[:, 0], ab[:, 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                wk = (zz[idx, k - 1] - b) / a
            good = np.isfinite(wk) & (wk > W_TOL) & (wk < 1.0 - W_TOL)
            w[idx, k - 2] = np.where(np.isfinite(wk), wk, 0.0)
            bad = idx[~good]
            valid[bad] = False
            failed[bad] = k - 1
            gi = idx[good]
            q[gi, k - 1] = np.arccos(wk[good] ** (1.0 / self.robot.exponents[k - 2]))
        q[~valid] = 0.0
        return InverseResult(q=q, w=w, valid=valid, failed_level=failed)

    def th1_from_chained(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``th1`` and ``valid`` of :meth:`from_chained` (``th1`` is 0 where not valid), for
        the planner's scans of ``th1`` along paths.

        n = 3 (closed form): the operations of :meth:`from_chained` on the columns ``z2``,
        ``z3`` only (the same values), without assembling the other joints.
        """
        zz = np.atleast_2d(np.asarray(z, dtype=float))
        if self.backend != "closed":
            inv = self.from_chained(zz)
            return inv.q[:, 1], inv.valid
        th1, ok = self.th1_from_z23(zz[:, 1], zz[:, 2])
        ok &= np.isfinite(zz[:, 0]) & np.isfinite(zz[:, 3])
        return np.where(ok, th1, 0.0), ok

    def th1_from_z23(self, z2: np.ndarray, z3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """n = 3: :meth:`th1_from_chained` from ``z2`` and ``z3`` alone (any shapes that
        broadcast), for points whose ``z1`` and ``z4`` are finite: ``th1`` (meaningless where
        not valid) and ``valid``."""
        if self.backend != "closed":
            raise ValueError("th1_from_z23 needs the n = 3 closed form")
        robot = self.robot
        m2, m3 = robot.exponents
        K2, K3 = robot.gains
        with np.errstate(divide="ignore", invalid="ignore"):
            w3 = z3 / K3
            ok = (w3 > W_TOL) & (w3 < 1.0 - W_TOL)        # False for NaN too
            th2 = np.arccos(w3 ** (1.0 / m3))
            c2, s2 = np.cos(th2), np.sin(th2)
            a = -m3 * K2 * K3 * c2 ** (m3 - 1) * s2       # _closed_ab(robot, 2, q)
            w2 = (z2 - 0.0) / a
            ok &= np.isfinite(w2) & (w2 > W_TOL) & (w2 < 1.0 - W_TOL)
            th1 = np.arccos(w2 ** (1.0 / m2))
        return th1, ok

    def _from_chained3(self, zz: np.ndarray) -> InverseResult | None:
        """:meth:`from_chained` (closed form, n = 3) for finite points that are all valid, with
        the same operations on whole columns instead of index arrays; None when some point is
        not valid (the general path then says where and why)."""
        robot = self.robot
        m2, m3 = robot.exponents
        N = zz.shape[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            w3 = zz[:, 2] / robot.gains[1]              # (z3 - b3) / a3 with b3 = 0, a3 = K3
            if not ((w3 > W_TOL) & (w3 < 1.0 - W_TOL)).all():
                return None
            th2 = np.arccos(w3 ** (1.0 / m3))
            a, b = _closed_ab(robot, 2, np.column_stack([zz[:, 0], zz[:, 1], th2, zz[:, 3]]))
            w2 = (zz[:, 1] - b) / a
            if not (np.isfinite(w2) & (w2 > W_TOL) & (w2 < 1.0 - W_TOL)).all():
                return None
        q = np.empty((N, 4))
        q[:, 0] = zz[:, 0]
        q[:, 1] = np.arccos(w2 ** (1.0 / m2))
        q[:, 2] = th2
        q[:, 3] = zz[:, 3]
        return InverseResult(q=q, w=np.column_stack([w2, w3]), valid=np.ones(N, bool),
                             failed_level=np.zeros(N, dtype=int))

    # ------------------------------------------------------------------ symbolic
    @property
    def symbolic(self) -> "SymbolicChainedForm":
        """The CasADi expressions and Functions (for NLPs built on top of the transform); each
        takes the gains as its last input (:attr:`gains`)."""
        return self._sym

    @property
    def gains(self) -> np.ndarray:
        """``K_2..K_n`` as the symbolic functions take them (read only)."""
        return self._K


def _eval_columns(f: ca.Function, maps: dict[int, ca.Function], gains: np.ndarray,
                  *args: np.ndarray) -> np.ndarray:
    """Evaluate ``f`` (column-vector inputs, the gains last, one column-vector output) at many
    points at once.

    ``args[i]`` has one row per point, shape (N, size of input i); ``gains`` is one column
    for all points; the result has one row per point. ``f.map(N)`` with the gains not mapped
    (kept in ``maps``: building it costs more than evaluating it) is called through CasADi's
    copy-free buffer interface: a numpy array with one row per point is, byte for byte, the
    column-major matrix of N columns that the mapped function expects. That avoids the numpy
    <-> DM conversions, which cost as much as the evaluation for a few hundred points (CasADi
    versions without ``Function.buffer`` get the ordinary call).
    """
    N = args[0].shape[0]
    if N == 0:
        return np.empty((0, f.size1_out(0)))
    compiled = _compiled_map(f, len(args)).current()
    if compiled is not None:
        return compiled(gains, args)
    mapped = maps.get(N)
    if mapped is None:
        if len(maps) >= 64:  # the node counts repeat (multiples of the panel size): few sizes
            maps.clear()
        mapped = maps[N] = f.map(N, [False] * len(args) + [True], [False])
    if not hasattr(mapped, "buffer"):
        out = mapped(*[a.T for a in args], gains)
        return np.asarray(out, dtype=float).reshape(-1, N).T.copy()
    cols = [np.ascontiguousarray(a, dtype=float) for a in args]
    res = np.empty((N, f.size1_out(0)))
    buf, run = mapped.buffer()
    # (CasADi's stubs list a byte size as well; the Python binding takes it from the buffer)
    for i, c in enumerate(cols):
        buf.set_arg(i, c.data)  # type: ignore[call-arg]
    buf.set_arg(len(cols), gains.data)  # type: ignore[call-arg]
    buf.set_res(0, res.data)  # type: ignore[call-arg]
    run()
    return res


#: Points per call of a compiled map (:class:`_CompiledMap`; the last call padded with copies
#: of the last point).
COMPILED_ROWS = 64


class _CompiledMap:
    """``f`` mapped over :data:`COMPILED_ROWS` points (the gains not mapped), generated as C
    and compiled (:mod:`optimizer.native`: built once per machine, in the background; CasADi's
    virtual machine answers until then, and when compiled functions are off). The same
    expressions either way, evaluated to the same bits (``tests/test_native.py``); on 130
    points the compiled call took 57-150 us where the virtual machine took 0.1 ms (4 joints),
    0.18-0.34 ms (5) and 3.5-9.6 ms (8: the Lie derivatives' expressions grow with the
    joints): the 4- to 8-joint plans' and replans' chained states and inputs."""

    def __init__(self, f: ca.Function, n_args: int) -> None:
        self.f, self.n_args = f, n_args
        self._cfg: object = None
        self._library: native.Library | None = None
        self._name = ""
        self._call: Any = None

    def current(self, wait: bool = False) -> Any:
        """A callable ``(gains, args) -> rows`` on the compiled library, or None while it is
        not ready (or compiled functions are off); ``wait``: build it now when missing."""
        cfg = native.config()
        if cfg is None:
            return None
        if cfg is not self._cfg:
            self._cfg, self._call = cfg, None
            mapped = self.f.map(COMPILED_ROWS, [False] * self.n_args + [True], [False])
            named = ca.Function(f"{self.f.name()}_rows{COMPILED_ROWS}", mapped.mx_in(),
                                mapped.call(mapped.mx_in()))
            cg = ca.CodeGenerator(f"{named.name()}.c", {"with_header": False})
            cg.add(named)
            self._name = named.name()
            self._library = native.library_for(str(cg.dump()), wait=wait)
        if self._call is not None:
            return self._call
        if self._library is None:
            return None
        path = self._library.ready(0.0 if wait else 1.0)
        if path is None:
            return None
        try:
            function = ca.external(self._name, str(path))
        except Exception:  # noqa: BLE001 - an unloadable library: keep the virtual machine
            self._library = None
            return None
        self._call = _RowsCall(function, self.f.size1_out(0))
        return self._call


class _RowsCall:
    """A compiled map over :data:`COMPILED_ROWS` points called on any number of points."""

    def __init__(self, function: ca.Function, width: int) -> None:
        self.function, self.width = function, width
        self._buffer, self._run = function.buffer()

    def __call__(self, gains: np.ndarray, args: tuple[np.ndarray, ...]) -> np.ndarray:
        N = args[0].shape[0]
        R = COMPILED_ROWS
        total = -(-N // R) * R
        padded = []
        for a in args:
            full = np.empty((total, a.shape[1]))
            full[:N] = a
            full[N:] = a[N - 1]
            padded.append(full)
        res = np.empty((total, self.width))
        buf = self._buffer
        buf.set_arg(len(args), gains.data)  # type: ignore[call-arg]
        for s in range(0, total, R):
            for i, full in enumerate(padded):
                buf.set_arg(i, full[s:s + R].data)  # type: ignore[call-arg]
            block = res[s:s + R]
            buf.set_res(0, block.data)  # type: ignore[call-arg]
            self._run()
        return res[:N].copy() if total != N else res


#: The compiled map of each symbolic function in use (by ``id``; the function is kept in
#: the entry, so that an id is not taken by another while its entry lives).
_COMPILED: dict[int, _CompiledMap] = {}


def prepare_maps(exponents: tuple[int, ...], wait: bool = False) -> bool:
    """Ask for the compiled libraries of the chained form's maps of robots with these
    exponents (``wait``: build the missing ones now; the image build does); True when all are
    in use. With compiled functions off, False."""
    sym = symbolic_form(tuple(exponents))
    maps = [(sym.forward, 1), (sym.alpha_beta, 1), (sym.u_w_from_zv, 2),
            *((f, 1) for f in sym.ab.values())]
    ready = [_compiled_map(f, k).current(wait) is not None for f, k in maps]
    return all(ready)


def _compiled_map(f: ca.Function, n_args: int) -> _CompiledMap:
    entry = _COMPILED.get(id(f))
    if entry is None or entry.f is not f:
        if len(_COMPILED) >= 256:
            _COMPILED.clear()
        entry = _COMPILED[id(f)] = _CompiledMap(f, n_args)
    return entry


# ---------------------------------------------------------------------- closed form n = 3
def _closed_forward(robot: Robot, q: np.ndarray) -> np.ndarray:
    K2, K3 = robot.gains
    m2, m3 = robot.exponents
    c1, c2 = np.cos(q[:, 1]), np.cos(q[:, 2])
    s2 = np.sin(q[:, 2])
    z = np.empty_like(q)
    z[:, 0] = q[:, 0]
    z[:, 1] = -m3 * K2 * K3 * c1 ** m2 * c2 ** (m3 - 1) * s2
    z[:, 2] = K3 * c2 ** m3
    z[:, 3] = q[:, 3]
    return z


def _closed_input(robot: Robot, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K2, K3 = robot.gains
    m2, m3 = robot.exponents
    c1, s1 = np.cos(q[:, 1]), np.sin(q[:, 1])
    c2, s2 = np.cos(q[:, 2]), np.sin(q[:, 2])
    alpha = -m3 * K2 ** 2 * K3 * c1 ** (2 * m2) * (c2 ** m3 - (m3 - 1) * c2 ** (m3 - 2) * s2 ** 2)
    beta = m2 * m3 * K2 * K3 * c1 ** (m2 - 1) * s1 * c2 ** (m3 - 1) * s2
    return alpha, beta


def _closed_u_from_zv(robot: Robot, z: np.ndarray, v: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """n = 3: ``u`` at ``q = Phi^-1(z)`` and the ``w_k`` of the inverse, columns (w2, w3).

    The inverse map of :meth:`ChainedForm.from_chained` (closed backend) and the input map of
    :func:`_closed_input`, written with ``c_i = cos(th_i) = w^(1/m)`` and
    ``s_i = sqrt((1 - c_i)(1 + c_i))`` instead of going through the angles (no arccos, cos,
    sin: the same values to rounding, as well conditioned). No per-level masking: invalid
    points give non-finite or meaningless values here and the caller replaces them.
    """
    K2, K3 = robot.gains
    m2, m3 = robot.exponents
    with np.errstate(divide="ignore", invalid="ignore"):
        w3 = z[:, 2] / K3                       # z3 = K3 c2^m3
        c2 = w3 ** (1.0 / m3)
        s2 = np.sqrt((1.0 - c2) * (1.0 + c2))
        c2m = c2 ** (m3 - 2)                     # c2^(m3-2), reused below
        w2 = z[:, 1] / (-m3 * K2 * K3 * c2m * c2 * s2)  # z2 = a2 c1^m2 (see _closed_ab)
        c1 = w2 ** (1.0 / m2)
        s1 = np.sqrt((1.0 - c1) * (1.0 + c1))
        c1m = c1 ** (m2 - 1)
        alpha = -m3 * K2 ** 2 * K3 * (c1m * c1) ** 2 * c2m * (c2 * c2 - (m3 - 1) * s2 * s2)
        beta = m2 * m3 * K2 * K3 * c1m * s1 * c2m * c2 * s2
        u = np.empty_like(v)
        u[:, 0] = v[:, 0]
        u[:, 1] = (v[:, 1] - alpha * v[:, 0]) / beta
    return u, np.column_stack([w2, w3])


def _closed_ab(robot: Robot, k: int, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K2, K3 = robot.gains
    m3 = robot.exponents[1]
    if k == 3:
        return np.full(q.shape[0], K3), np.zeros(q.shape[0])
    c2, s2 = np.cos(q[:, 2]), np.sin(q[:, 2])
    return -m3 * K2 * K3 * c2 ** (m3 - 1) * s2, np.zeros(q.shape[0])


# ---------------------------------------------------------------------- symbolic, any n
class SymbolicChainedForm:
    """CasADi derivation of the chained form by Lie derivatives along g1 (NOTES §3), once per
    exponents: the gains ``K_2..K_n`` are an input of every function (the last), so that a
    robot of new gains (a design in a study, a plant's estimated gains in closed loop) costs
    no new derivation (6 ms at n = 3, 150 ms at n = 8).

    Attributes
    ----------
    q : casadi.SX, (n+1,)
        The symbolic state.
    K : casadi.SX, (n-1,)
        The symbolic gains.
    z : casadi.SX, (n+1,)
        The chained coordinates as expressions of ``q`` and ``K``.
    forward, alpha_beta : casadi.Function
        ``(q, K) -> z``, ``(q, K) -> (L_g1 z2, L_g2 z2)``.
    a, b, ab : dict of casadi.Function
        ``a[k](q, K)``, ``b[k](q, K)`` for k = 2..n (see the module docstring); ``ab[k]``
        both stacked.
    u_from_zv, u_w_from_zv : casadi.Function
        ``(z, v, K) -> u`` at ``q = Phi^-1(z)`` (eq 5 inverted); the second also returns the
        ``w_k`` of the inverse (validity) and is meant for many points at once (stacked
        columns).
    """

    def __init__(self, exponents: tuple[int, ...]) -> None:
        n = len(exponents) + 1
        q = ca.SX.sym("q", n + 1)
        K = ca.SX.sym("K", n - 1)
        gains = [K[i] for i in range(n - 1)]
        th: list[ca.SX] = [q[0]] + [q[i] for i in range(1, n + 1)]  # th[i] = theta_i, i >= 1

        # the input vector fields of the model, from its one definition (optimizer.dynamics)
        g1 = ca.vertcat(*vector_field(gains, exponents, q, 1, 0, cos=ca.cos))
        g2 = ca.vertcat(*vector_field(gains, exponents, q, 0, 1, cos=ca.cos))
        zs: dict[int, ca.SX] = {n + 1: th[n]}
        a_expr: dict[int, ca.SX] = {}
        b_expr: dict[int, ca.SX] = {}
        for k in range(n, 1, -1):
            zk1 = zs[k + 1]
            zs[k] = ca.jtimes(zk1, q, g1)  # L_g1 z_{k+1}
            a_expr[k] = gains[k - 2] * ca.jacobian(zk1, th[k])
            b = ca.SX(0)
            for j in range(k + 1, n):  # z_{k+1} depends on th_k..th_{n-1}
                b = b + ca.jacobian(zk1, th[j]) * g1[j]
            b_expr[k] = b
        z = ca.vertcat(q[0], *[zs[k] for k in range(2, n + 2)])
        self.n = n
        self.q = q
        self.K = K
        self.z = z
        self.forward = ca.Function("chained_forward", [q, K], [z])
        z2 = zs[2]
        self.alpha_expr = ca.jtimes(z2, q, g1)
        self.beta_expr = ca.jtimes(z2, q, g2)
        self.alpha_beta = ca.Function("lie_z2", [q, K], [ca.vertcat(self.alpha_expr,
                                                                    self.beta_expr)])
        self.a = {k: ca.Function(f"a{k}", [q, K], [a_expr[k]]) for k in a_expr}
        self.b = {k: ca.Function(f"b{k}", [q, K], [b_expr[k]]) for k in b_expr}
        # one call per level in the numeric inverse (the call overhead dominates)
        self.ab = {k: ca.Function(f"ab{k}", [q, K], [ca.vertcat(a_expr[k], b_expr[k])])
                   for k in a_expr}
        self.exponents = exponents
        # u from (z, v) in one call (eq 5 inverted at q = Phi^-1(z)): the integrator's hot path
        zsym = ca.SX.sym("z", n + 1)
        vs = ca.SX.sym("v", 2)
        th_z, w_z = self.inverse_expr(zsym, K)
        qz = ca.vertcat(zsym[0], *th_z)
        al = ca.substitute(self.alpha_expr, q, qz)
        be = ca.substitute(self.beta_expr, q, qz)
        self.u_from_zv = ca.Function("u_from_zv", [zsym, vs, K],
                                     [ca.vertcat(vs[0], (vs[1] - al * vs[0]) / be)])
        # The same with the w_k of the inverse appended (validity), for batched evaluation on
        # many points at once. Common subexpressions are merged: the Lie derivatives repeat
        # terms, and without merging the instruction count grows ~3x per joint (n = 8: 16752
        # instructions instead of ~2100).
        u_w = ca.vertcat(vs[0], (vs[1] - al * vs[0]) / be, *w_z)
        self.u_w_from_zv = ca.Function("u_w_from_zv", [zsym, vs, K], [ca.cse(u_w)])
        # f.map(N) by N of the functions ChainedForm evaluates on many points at once (through
        # the buffer interface of _eval_columns, 3-5x cheaper than a call that converts to and
        # from DM); the gains are not mapped (one column for all points)
        self.maps: dict[str, dict[int, ca.Function]] = {
            name: {} for name in ("forward", "alpha_beta", "u_w_from_zv",
                                  *(f"ab{k}" for k in self.ab))}

    def inverse_expr(self, z: ca.MX | ca.SX, K: Any) -> tuple[list, list]:
        """Symbolic inverse map for NLPs: ``(th, w)`` with ``th[i-1] = theta_i`` and
        ``w[k-2] = cos(th_{k-1})^{m_k}`` (k = 2..n), computed top-down from ``z``, for gains
        ``K`` (symbols or numbers).

        The caller must keep every ``w`` inside (0, 1) (that is the region), otherwise the
        fractional powers and arccos are undefined.
        """
        n = self.n
        qsym: list = [z[0]] + [0] * n
        qsym[n] = z[n]
        ws: list = [None] * (n - 1)
        for k in range(n, 1, -1):
            qvec = ca.vertcat(*qsym)
            a: Any = self.a[k](qvec, K)
            b: Any = self.b[k](qvec, K)
            wk = (z[k - 1] - b) / a
            ws[k - 2] = wk
            qsym[k - 1] = ca.acos(wk ** (1.0 / self.exponents[k - 2]))
        return qsym[1:], ws


@functools.lru_cache(maxsize=16)
def symbolic_form(exponents: tuple[int, ...]) -> SymbolicChainedForm:
    """The (cached) :class:`SymbolicChainedForm` of robots with these exponents."""
    return SymbolicChainedForm(exponents)


@functools.lru_cache(maxsize=64)
def chained_form(robot: Robot) -> ChainedForm:
    """The (cached) :class:`ChainedForm` of ``robot`` with the default backend."""
    return ChainedForm(robot)
