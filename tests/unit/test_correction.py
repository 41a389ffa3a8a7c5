"""The one correction value (core/correction.py): eq. (2), eq. (11) and eq. (24) on floats and arrays."""

from __future__ import annotations

import numpy as np
import pytest

from magcomp.core.correction import IDENTITY_COEFFS, Correction, converged, headings_deg
from magcomp.core.heading import wrap_deg_180
from magcomp.core.rotations import dcm_from_euler
from magcomp.core.types import FLAG_CALIBRATED, FLAG_THETA_CONVERGED

EARTH_N = np.array([233.0, -26.0, 386.0])  # mgauss, NED (Gainesville-like)


def _flight(rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    """(true body field (n, 3), roll, pitch, yaw, throttle) of a seeded flight."""
    roll, pitch = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)
    yaw = rng.uniform(-np.pi, np.pi, n)
    m_b = np.array([dcm_from_euler(r, p, y).T @ EARTH_N for r, p, y in zip(roll, pitch, yaw, strict=True)])
    return m_b, roll, pitch, yaw, rng.uniform(0.0, 0.9, n)


def _distorting(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A calibration L, d (eq. (2)) and the soft/hard iron it undoes: v = L^-1 (u + d)."""
    calib_l = np.eye(3) + rng.normal(0.0, 0.08, (3, 3))
    calib_d = rng.normal(0.0, 60.0, 3)
    return calib_l, calib_d, np.linalg.inv(calib_l)


def test_apply_undoes_the_distortion_and_the_bias_and_gives_the_true_heading() -> None:
    rng = np.random.default_rng(2024)
    m_b, roll, pitch, yaw, thr = _flight(rng, 400)
    calib_l, calib_d, l_inv = _distorting(rng)
    theta = np.array([60.0, -35.0, 90.0])  # mgauss at full throttle
    raw = ((m_b + theta * (thr * thr)[:, None] + calib_d) @ l_inv.T)  # eq. (2) inverted, eq. (11) added
    cor = Correction.from_solution(calib_l, calib_d, theta, None, heading_sigma_deg=0.4, converged_deg=1.0)
    got = cor.apply(raw[:, 0], raw[:, 1], raw[:, 2], thr)
    assert np.max(np.abs(np.column_stack(got.corrected) - m_b)) < 1e-9
    assert np.max(np.abs(np.column_stack(got.bias) - theta * (thr * thr)[:, None])) < 1e-9
    psi, psi_raw = headings_deg(got, np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch))
    truth = np.degrees(yaw) - np.degrees(np.arctan2(EARTH_N[1], EARTH_N[0]))
    assert np.max(np.abs(wrap_deg_180(psi - truth))) < 1e-6
    # the bias left in (the calibrated field only) moves the heading by degrees at this theta
    assert np.sqrt(np.mean(wrap_deg_180(psi_raw - truth) ** 2)) > 2.0


def test_one_sample_and_arrays_give_the_same_numbers() -> None:
    rng = np.random.default_rng(7)
    raw = rng.normal(0.0, 300.0, (50, 3))
    thr = rng.uniform(0.0, 1.0, 50)
    trig = [np.cos(a) for a in rng.uniform(-0.6, 0.6, 2)]
    cor = Correction(tuple(rng.normal(0.0, 1.0, 12).tolist()), (12.0, -7.0, 30.0), source="hand rotation")
    arr = cor.apply(raw[:, 0], raw[:, 1], raw[:, 2], thr)
    for i in range(50):
        one = cor.apply(float(raw[i, 0]), float(raw[i, 1]), float(raw[i, 2]), float(thr[i]))
        for part, many in zip(one, arr, strict=True):
            assert tuple(part) == tuple(float(c[i]) for c in many)  # bit for bit
        psi, psi_raw = headings_deg(one, trig[0], 0.3, trig[1], -0.2)
        assert isinstance(psi, float) and 0.0 <= psi < 360.0 and psi != psi_raw


def test_per_motor_terms_add_only_what_the_collective_throttle_does_not_explain() -> None:
    motors = ((5.0, 1.0, -2.0), (-5.0, 0.5, 2.0))
    cor = Correction(IDENTITY_COEFFS, (10.0, 20.0, 30.0), motors, source="in flight", needs_throttle=True)
    same = cor.bias(0.5, (0.5, 0.5))  # every motor at the throttle: eq. (11) alone
    assert same == pytest.approx((2.5, 5.0, 7.5), abs=1e-12)
    uneven = cor.bias(0.5, (0.7, 0.3))  # m^2 - delta^2 = +0.24, -0.16
    assert uneven == pytest.approx((2.5 + 5.0 * 0.24 + 5.0 * 0.16, 5.0 + 0.24 - 0.08, 7.5 - 0.48 - 0.32))
    assert cor.bias(0.5) == same  # no motor outputs known: the collective term only
    with pytest.raises(ValueError, match="motor outputs"):
        cor.bias(0.5, (0.5,))


def test_flags_sources_and_the_converged_rule() -> None:
    assert Correction().flags == 0 and not Correction().calibrated
    cal = Correction(IDENTITY_COEFFS, source="stored")
    assert cal.flags == FLAG_CALIBRATED
    conv = Correction(IDENTITY_COEFFS, converged=True, source="stored")
    assert conv.flags == FLAG_CALIBRATED | FLAG_THETA_CONVERGED
    assert converged(0.99, 1.0) and not converged(1.0, 1.0)
    sol = Correction.from_solution(np.eye(3), np.zeros(3), np.ones(3), np.zeros((4, 3)), 2.0, 1.0)
    assert sol.needs_throttle and sol.source == "in flight" and not sol.converged
    assert len(sol.motor_theta_mgauss) == 4
    assert sol.coeffs == IDENTITY_COEFFS
    with pytest.raises(ValueError, match="12 coefficients"):
        Correction((1.0, 0.0))
    with pytest.raises(ValueError, match="unknown correction source"):
        Correction(source="guess")
    uncal = Correction(theta_mgauss=(1.0, 2.0, 3.0))
    assert uncal.calibrate(1.5, -2.0, 3.0) == (1.5, -2.0, 3.0)  # no calibration: the field as logged
