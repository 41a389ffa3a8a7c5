"""A gyro logged too slowly to integrate still shows that the vehicle does not rotate."""

from __future__ import annotations

import numpy as np

from magcomp.diagnosis.attitude import MIN_GYRO_HZ, STATIONARY_RATE_RAD_S, attitude_source


def _bench(gyro_hz: float, wander_rad_s: float) -> tuple[str, str]:
    """A 60 s bench log: gyro at ``gyro_hz`` with 5 mrad/s of noise plus a yaw rate ``wander_rad_s`` swinging
    at 0.05 Hz; ATTITUDE at 10 Hz level, its yaw wandering 12 deg (an autopilot pulled by its disturbed
    compass). Returns the chosen source and its note."""
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 60.0, 1.0 / gyro_hz)
    gyro = rng.normal(0.0, 0.005, (t.size, 3))
    gyro[:, 2] += wander_rad_s * np.sin(2 * np.pi * 0.05 * t)
    accel = np.tile([0.0, 0.0, -9.81], (t.size, 1)) + rng.normal(0.0, 0.05, (t.size, 3))
    ta = np.arange(0.0, 60.0, 0.1)
    yaw = np.radians(12.0) * np.sin(2 * np.pi * ta / 60)
    att = np.column_stack([np.zeros_like(ta), np.zeros_like(ta), yaw])
    src = attitude_source(t, gyro, accel, ta, att)
    return src.source, src.note


def test_slow_gyro_that_shows_no_rotation_gives_the_stationary_rotation() -> None:
    """Gyro at 16.7 Hz (RAW_IMU at 20 Hz in a 50 Hz loop, below MIN_GYRO_HZ) and still: stationary, not the
    autopilot's wandering yaw (before: the log's attitude, whose 24 deg yaw span failed the calibration's
    gate on the held-out bench cases)."""
    assert MIN_GYRO_HZ > 50.0 / 3.0
    source, _ = _bench(50.0 / 3.0, 0.0)
    assert source == "stationary"


def test_slow_gyro_that_shows_rotation_is_not_stationary() -> None:
    """The same slow gyro with a yaw rate swinging to 4x the stationary threshold: not stationary."""
    source, note = _bench(50.0 / 3.0, 4.0 * STATIONARY_RATE_RAD_S)
    assert source != "stationary", note
