"""Whose slow error: an autopilot yaw reset vs a compass calibration error, told apart by the gyro."""

from __future__ import annotations

import math

import numpy as np

from magcomp.core.selfcheck import offset_removed_rms_deg, window_ids
from magcomp.core.yaw_reference import drift_removed_rms_deg, slow_error_owner


def _flight(seed: int, sweep_deg: float = 300.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """120 s at 10 Hz: a true yaw that turns slowly through ``sweep_deg`` and back, a gyro yaw with a rate
    bias of 0.05 deg/s and an offset, a compass heading with 1 deg of noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 120.0, 0.1)
    psi = np.radians(0.5 * sweep_deg * (1.0 - np.cos(2.0 * math.pi * t / 120.0)))
    gyro = psi + np.radians(0.05) * t + 1.3
    heading = psi + np.radians(1.0) * rng.standard_normal(t.size)
    return t, psi, gyro, heading


def test_an_autopilot_yaw_excursion_is_charged_to_the_autopilot() -> None:
    """PX4 EKF2's in-flight re-alignment (luk8426 log_94): the autopilot's yaw jumps -59 deg and comes
    back 6 s later while the vehicle does not turn. The compass is right; the att metric charges it ~17
    deg."""
    t, psi, gyro, heading = _flight(0)
    yaw = psi.copy()
    yaw[(t >= 60.0) & (t < 66.0)] -= math.radians(59.0)
    att = offset_removed_rms_deg(heading - yaw)
    assert att > 10.0
    got = slow_error_owner(t, heading, yaw, gyro)
    assert got.autopilot_yaw_limited
    assert got.compass_vs_gyro_deg < 1.5  # the compass's noise, its offset and the gyro's drift removed
    assert got.autopilot_vs_gyro_deg > 8.0
    assert got.n_windows == 4


def test_a_compass_calibration_error_is_charged_to_the_compass() -> None:
    """A hard-iron error left by the calibration: a heading error that turns once per revolution (8 deg);
    the autopilot's yaw follows the gyro; the vehicle turns through 1000 deg and back."""
    t, psi, gyro, heading = _flight(1, sweep_deg=1000.0)
    heading = heading + np.radians(8.0) * np.sin(psi - 0.4)
    yaw = psi + np.radians(0.3) * np.random.default_rng(2).standard_normal(t.size)
    got = slow_error_owner(t, heading, yaw, gyro)
    assert not got.autopilot_yaw_limited
    assert got.autopilot_vs_gyro_deg < 0.5
    assert got.compass_vs_gyro_deg > 2.0


def test_drift_removed_rms_removes_a_ramp_but_not_a_step() -> None:
    t = np.arange(0.0, 60.0, 0.1)
    ids = window_ids(t, None, 30.0)
    ramp = np.radians(0.1) * t + 0.5
    assert drift_removed_rms_deg(t, ramp, ids) < 1e-9
    step = np.where(t % 30.0 >= 15.0, math.radians(10.0), 0.0)
    # a 10 deg step in the middle of each window: a line takes out 3/4 of its variance, a quarter of the
    # step stays (rms h/4)
    assert abs(drift_removed_rms_deg(t, step, ids) - 2.5) < 0.1
