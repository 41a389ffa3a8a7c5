"""The self-check against the gyro (core/selfcheck.py): it applies a correction that is better beyond the
noise, keeps the autopilot's own heading otherwise, and its running form agrees with the batch form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magcomp.core import selfcheck as sc
from magcomp.service.heading import HeadingTrack

Flight = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.random.Generator]


def _flight(seed: int, n_s: float = 300.0, rate_hz: float = 10.0) -> Flight:
    """Times, a true yaw (turns), a gyro-integrated yaw with a small rate bias, and a throttle that climbs and
    descends over seconds (what bends a compass)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, n_s, 1.0 / rate_hz)
    yaw_rate = 0.3 * np.sin(2 * math.pi * t / 23.0) + 0.2 * np.sin(2 * math.pi * t / 7.0)
    yaw = np.cumsum(yaw_rate) / rate_hz
    gyro = yaw + 1e-3 * t  # 1e-3 rad/s of rate bias
    thr = 0.5 + 0.25 * np.sin(2 * math.pi * t / 5.0 + rng.uniform(0, 6)) * (rng.uniform(0.5, 1.0))
    return t, yaw, gyro, thr, rng


def test_a_correction_that_removes_the_throttle_error_applies() -> None:
    t, yaw, gyro, thr, rng = _flight(1)
    noise = np.radians(1.0)
    base = yaw + np.radians(12.0) * thr**2 + rng.normal(0, noise, t.size)  # the current's bias, uncorrected
    cand = yaw + rng.normal(0, noise, t.size)
    chk = sc.compare(base, cand, gyro, sc.window_ids(t), yaw + 0.3)
    assert chk.applies, chk.reason
    assert chk.z > sc.Z_APPLY
    assert chk.candidate_gyro_deg < 0.7 * chk.baseline_gyro_deg
    swapped = sc.compare(cand, base, gyro, sc.window_ids(t), yaw + 0.3)
    assert not swapped.applies
    assert "less consistent with the gyro" in swapped.reason


def test_equal_headings_rarely_apply() -> None:
    """Two candidates of the same quality: the rule applies at most at its nominal rate (Z_APPLY = 2: ~2.3 %
    one-sided); 60 seeds, at most 6 applied (a loose bound that still fails a rule with no noise margin)."""
    applied = 0
    for seed in range(60):
        t, yaw, gyro, _, rng = _flight(100 + seed, n_s=120.0)
        base = yaw + rng.normal(0, np.radians(2.0), t.size)
        cand = yaw + rng.normal(0, np.radians(2.0), t.size)
        applied += sc.compare(base, cand, gyro, sc.window_ids(t), yaw).applies
    assert applied <= 6


def test_worse_against_the_autopilot_yaw_does_not_apply() -> None:
    """Quieter against the gyro but a slow error the gyro windows cannot see (a drift over minutes):
    the autopilot's yaw catches it and the correction is not applied."""
    t, yaw, gyro, thr, rng = _flight(3)
    base = yaw + np.radians(8.0) * thr**2 + rng.normal(0, np.radians(1.0), t.size)
    cand = yaw + np.radians(25.0) * np.sin(2 * math.pi * t / 300.0) + rng.normal(0, np.radians(0.5), t.size)
    chk = sc.compare(base, cand, gyro, sc.window_ids(t), yaw)
    assert chk.candidate_gyro_deg < chk.baseline_gyro_deg
    assert not chk.applies
    assert "autopilot's yaw" in chk.reason


def test_too_short_to_judge() -> None:
    t, yaw, gyro, thr, _ = _flight(4, n_s=19.0)
    base = yaw + np.radians(12.0) * thr**2
    chk = sc.compare(base, yaw, gyro, sc.window_ids(t))
    assert not chk.applies and chk.n_windows < sc.MIN_WINDOWS


def test_running_form_agrees_with_the_batch_form() -> None:
    t, yaw, gyro, thr, rng = _flight(5, n_s=100.0)
    base = yaw + np.radians(10.0) * thr**2 + rng.normal(0, np.radians(1.0), t.size)
    cand = yaw + 0.4 + rng.normal(0, np.radians(1.0), t.size)
    batch = sc.compare(base, cand, gyro, sc.window_ids(t), yaw)
    run = sc.RunningSelfCheck(window_s=sc.WINDOW_S)
    for i in range(t.size):
        run.add(float(t[i]), float(base[i]), float(cand[i]), float(gyro[i]), 0.0, float(yaw[i]))
    run.add(1e9, 0.0, 0.0, 0.0, 0.0, 0.0)  # closes the last window
    v = run.verdict
    assert v is not None and v.applies == batch.applies
    assert v.baseline_gyro_deg == pytest.approx(batch.baseline_gyro_deg, rel=1e-9)
    assert v.candidate_att_deg == pytest.approx(batch.candidate_att_deg, rel=1e-6)


def test_gyro_integral_restarts_at_gaps() -> None:
    t = np.concatenate((np.arange(0, 10, 0.01), np.arange(12, 20, 0.01)))
    yaw, seg = sc.integrate_yaw_rad(t, np.full(t.size, 0.1))
    assert yaw[999] == pytest.approx(0.1 * t[999], rel=1e-9)
    assert seg[0] == 0 and seg[-1] == 1
    assert yaw[-1] - yaw[1000] == pytest.approx(0.1 * (t[-1] - t[1000]), rel=1e-9)


def test_heading_filter_propagates_with_the_integrated_gyro() -> None:
    """A 2 Hz compass in a turn whose rate changes within the interval: propagating with the integrated
    gyro's change keeps the filter on the true heading; the latest rate times the interval does not."""
    dt_imu, dt_mag = 0.005, 0.5
    t = np.arange(0.0, 20.0, dt_imu)
    rate = 1.0 * np.sin(2 * math.pi * t / 1.3)  # rad/s, changes sign within a magnetometer interval
    yaw = np.cumsum(rate) * dt_imu
    every = int(dt_mag / dt_imu)
    errs = {}
    for use_integral in (True, False):
        track = HeadingTrack(tau_s=5.0)
        err = []
        for k in range(0, t.size, every):
            psi = math.degrees(yaw[k]) % 360.0
            gy = float(yaw[k]) if use_integral else math.nan
            track.step(psi, psi, True, k == 0, float(rate[k]), 0.0 if k == 0 else dt_mag, gy, 0.0, dt_imu)
            err.append((track.corrected_deg - psi + 180.0) % 360.0 - 180.0)
        errs[use_integral] = float(np.sqrt(np.mean(np.square(err[4:]))))
    assert errs[True] < 0.01
    assert errs[False] > 5.0


def test_hover_theta_is_recovered_against_the_autopilots_calibration() -> None:
    """A hover with 60 deg of yaw and the throttle between 0.4 and 0.6: theta of eq. (11) is fitted with the
    autopilot's calibration held (core/hover_theta.py) to within 3 sigma and 10 %; a constant throttle gives
    no fit."""
    from magcomp.core.hover_theta import body_from_nav, fit_hover_theta

    rng = np.random.default_rng(7)
    n = 3000
    t = np.arange(n) * 0.1
    roll = np.radians(2.0) * np.sin(t / 3.0)
    pitch = np.radians(2.0) * np.cos(t / 4.0)
    yaw = np.radians(30.0) * np.sin(t / 40.0)
    thr = 0.5 + 0.1 * np.sin(t / 2.3) * np.sin(t / 17.0)
    e_n = np.array([200.0, 10.0, 450.0])
    theta = np.array([-80.0, 140.0, 60.0])
    m = np.einsum("nij,j->ni", body_from_nav(roll, pitch, yaw), e_n) + theta * (thr**2)[:, None]
    m += rng.normal(0, 2.0, m.shape)
    fit = fit_hover_theta(m, roll, pitch, yaw, thr)
    assert fit is not None
    err = fit.theta_mgauss - theta
    assert np.all(np.abs(err) < 3 * fit.theta_sigma_mgauss + 1e-9)
    assert np.linalg.norm(err) < 0.1 * np.linalg.norm(theta)
    assert fit_hover_theta(m, roll, pitch, yaw, np.full(n, 0.5)) is None
