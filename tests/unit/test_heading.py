"""Heading, eq. (24) and its tilt-compensated generalisation."""

from __future__ import annotations

import numpy as np

from magcomp.core.heading import (
    heading_from_quat_deg,
    heading_level_deg,
    tilt_compensated_heading_deg,
    wrap_deg_180,
)
from magcomp.core.rotations import dcm_from_euler, quat_from_euler

H_MG, Z_MG, DEC_DEG = 240.9, 386.2, -6.4  # Gainesville-like field (mgauss) and declination


def _field_n() -> np.ndarray:
    d = np.radians(DEC_DEG)
    return np.array([H_MG * np.cos(d), H_MG * np.sin(d), Z_MG])


def _random_attitudes(rng: np.random.Generator, n: int, max_tilt_deg: float) -> np.ndarray:
    tilt = np.radians(max_tilt_deg)
    yaw = rng.uniform(-np.pi, np.pi, n)
    return np.column_stack([rng.uniform(-tilt, tilt, n), rng.uniform(-tilt, tilt, n), yaw])


def test_tilt_compensated_heading_matches_truth_for_random_tilts() -> None:
    rng = np.random.default_rng(24)
    eul = _random_attitudes(rng, 500, 75.0)
    m_b = np.array([dcm_from_euler(*e).T @ _field_n() for e in eul])
    got = tilt_compensated_heading_deg(m_b, eul[:, 0], eul[:, 1])
    truth = np.mod(np.degrees(eul[:, 2]) - DEC_DEG, 360.0)  # magnetic heading = yaw - declination
    assert np.max(np.abs(wrap_deg_180(got - truth))) < 1e-9
    assert np.all((got >= 0.0) & (got < 360.0))
    true_heading = tilt_compensated_heading_deg(m_b, eul[:, 0], eul[:, 1], declination_deg=DEC_DEG)
    assert np.max(np.abs(wrap_deg_180(true_heading - np.degrees(eul[:, 2])))) < 1e-9
    # scalar and quaternion forms agree with the vectorised one
    for i in range(0, 500, 50):
        one = float(tilt_compensated_heading_deg(m_b[i], eul[i, 0], eul[i, 1]))
        assert abs(float(wrap_deg_180(one - got[i]))) < 1e-9
        q = quat_from_euler(*eul[i])
        assert abs(float(wrap_deg_180(heading_from_quat_deg(m_b[i], q) - got[i]))) < 1e-9


def test_ignoring_tilt_gives_large_errors() -> None:
    """Control: eq. (24) on a tilted body field is wrong by many degrees (inclination ~58 deg)."""
    rng = np.random.default_rng(25)
    eul = _random_attitudes(rng, 200, 30.0)
    m_b = np.array([dcm_from_euler(*e).T @ _field_n() for e in eul])
    naive = heading_level_deg(m_b[:, 0], m_b[:, 1])
    truth = np.mod(np.degrees(eul[:, 2]) - DEC_DEG, 360.0)
    assert np.max(np.abs(wrap_deg_180(naive - truth))) > 20.0


def test_level_case_reduces_to_eq24() -> None:
    rng = np.random.default_rng(26)
    psi = rng.uniform(-89.0, 89.0, 100)  # eq. (24) uses atan: valid for |psi| < 90 deg
    m = np.array([dcm_from_euler(0.0, 0.0, np.radians(p)).T @ np.array([H_MG, 0.0, Z_MG]) for p in psi])
    eq24 = np.degrees(-np.arctan(m[:, 1] / m[:, 0]))  # eq. (24)
    got = tilt_compensated_heading_deg(m, 0.0, 0.0)
    np.testing.assert_allclose(wrap_deg_180(got), eq24, atol=1e-9)
    np.testing.assert_allclose(wrap_deg_180(got), psi, atol=1e-9)
    # cardinal points, quadrants resolved
    cardinal = heading_level_deg([1.0, 0.0, -1.0, 0.0], [0.0, -1.0, 0.0, 1.0])
    np.testing.assert_allclose(cardinal, [0, 90, 180, 270])
