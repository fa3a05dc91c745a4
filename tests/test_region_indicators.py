"""Region checks on the continuous path, and the indicators against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optimizer.chained_form import chained_form
from optimizer.indicators import (compute_indicators, count_reversals, joint_space_distance,
                                  sensitivity_frobenius)
from optimizer.model import Robot
from optimizer.region import Region
from optimizer.steering import ChainedPath, InputSchedule, solve_polynomial

D = np.deg2rad


def _worked_path(dphi_deg):
    cf = chained_form(Robot())
    z0 = cf.to_chained(D([0, 10, 10, 10]))
    zT = cf.to_chained(D([0, 30, 30, 30]))
    return ChainedPath.from_inputs(z0, solve_polynomial(D(dphi_deg), 3, z0, zT, 1.0))


def _brute_first_crossing(region, path, N=200001):
    tau = np.linspace(0, 1, N)
    h = region.signed_margin_z(path.z(tau))
    bad = np.nonzero(h <= 0)[0]
    return (tau[bad[0]] if bad.size else None), h.min()


@pytest.mark.parametrize("criterion, dphi", [("z2", 37.1035), ("z2", 32.6410),
                                             ("full", 35.2560), ("full", 33.2005)])
def test_crossings_between_samples_are_found(criterion, dphi):
    """Just outside the worked example's intervals the path leaves the region only briefly: a
    9-sample check still finds the excursion, at the time a 200001-sample scan finds."""
    region = Region(Robot(), criterion)
    path = _worked_path(dphi)
    chk = region.check_path(path, grid=9)
    t_brute, _ = _brute_first_crossing(region, path)
    assert t_brute is not None
    assert not chk.ok and chk.margin <= 0
    assert chk.first_crossing_tau == pytest.approx(t_brute, abs=1e-5)


@pytest.mark.parametrize("criterion, dphi", [("z2", 37.10), ("full", 35.255), ("full", 34.0)])
def test_margin_matches_brute_force(criterion, dphi):
    region = Region(Robot(), criterion)
    path = _worked_path(dphi)
    chk = region.check_path(path, grid=9)
    t_brute, h_min = _brute_first_crossing(region, path)
    assert chk.ok and t_brute is None
    assert chk.margin == pytest.approx(h_min, abs=1e-8)


def test_joint_bounds_shrink_region():
    path = _worked_path(34.57)
    free = Region(Robot(), "full").check_path(path)
    tight = Region(Robot(), "full", [(D(9.0), D(80.0)), None, None]).check_path(path)
    assert free.ok
    assert tight.margin == pytest.approx(free.margin - D(9.0), abs=1e-9) or not tight.ok


@pytest.mark.parametrize("s", [0.0, 0.3, 1.0, -2.5])
def test_sensitivity_closed_form_n3(s):
    """||J_R||_F = 2 + (b0 t)^2 / 2 for the 3-joint arm (NOTES §6)."""
    assert sensitivity_frobenius(s, 3) == pytest.approx(2 + s**2 / 2, rel=1e-14)


@pytest.mark.parametrize("n, v1", [(3, [0.6]), (4, [0.6]), (5, [0.4, -1.2, 0.9])])
def test_sensitivity_is_the_jacobian_of_z_wrt_initial_errors(n, v1):
    """J_R = dz(t)/de (eq 20) by finite differences of the exact path w.r.t. z(0), for
    constant and for varying v1: its Frobenius norm equals the formula with s = z1(t) - z1(0)."""
    inp = InputSchedule.single(v1, [0.2, -0.4, 0.1], 1.0)
    z0 = np.array([0.1, -0.3, 0.5, 0.2, 0.1, 0.05][: n + 1])
    taus = np.array([0.0, 0.3, 0.7, 1.0])
    base = ChainedPath.from_inputs(z0, inp)
    J = np.zeros((taus.size, n + 1, n + 1))
    h = 1e-6
    for j in range(n + 1):
        e = np.zeros(n + 1)
        e[j] = h
        J[:, :, j] = (ChainedPath.from_inputs(z0 + e, inp).z(taus)
                      - ChainedPath.from_inputs(z0 - e, inp).z(taus)) / (2 * h)
    s = base.z(taus)[:, 0] - z0[0]
    for k in range(taus.size):
        assert np.allclose(np.triu(J[k], 1), 0, atol=1e-9)  # lower triangular (eq 21)
        assert np.allclose(np.diag(J[k]), 1, atol=1e-9)
        assert np.linalg.norm(J[k]) == pytest.approx(sensitivity_frobenius(s[k], n), rel=1e-8)


@pytest.mark.parametrize("periods, expected", [(0.5, 1), (1.0, 2), (2.0, 4), (0.25, 0)])
def test_count_reversals_of_sines(periods, expected):
    t = np.linspace(0, 1, 5001)
    assert count_reversals(np.sin(2 * math.pi * periods * t)) == expected


def test_count_reversals_dead_band():
    t = np.linspace(0, 1, 2001)
    x = t + 1e-8 * np.sin(40 * math.pi * t)  # wiggles far below the dead band
    assert count_reversals(x) == 0


def test_indicators_closed_forms():
    """d_a of th1 = t + a sin(pi t) is a; joint-space distance of a known bump; energy."""
    t = np.linspace(0, 2.0, 4001)
    a = 0.2
    th1 = 0.1 + 0.3 * t / 2 + a * np.sin(math.pi * t / 2)
    th2 = 0.2 + 0.1 * t / 2
    q = np.column_stack([0.5 * t, th1, th2, th2])
    u = np.column_stack([np.full_like(t, 0.5), np.gradient(th1, t)])
    ind = compute_indicators(t, q, u)
    assert ind.d_a == pytest.approx(a, rel=1e-6)
    assert ind.d_a_per_joint[1] == pytest.approx(0.0, abs=1e-12)
    assert ind.t_p == 1 and ind.phi_reversals == 0
    assert ind.sensitivity == pytest.approx(2 + 1.0**2 / 2)
    # energy = int (0.25 + th1'^2) dt
    expected = 0.25 * 2 + np.trapezoid(np.gradient(th1, t) ** 2, t)
    assert ind.energy == pytest.approx(expected, rel=1e-9)
    # perpendicular distance of the bump from the joint-space line (eq 17)
    assert joint_space_distance(q[:, 1:]) <= ind.d_a + 1e-12
