"""The heading integral's roll and pitch between two ATTITUDE messages: carried by the gyro, not held.

``AttitudeStage.heading_yaw_rad`` (what the heading filter propagates with) turns body rates into the Euler
yaw rate ``(q sin roll + r cos roll) / cos pitch``. Held between two ATTITUDE messages, the roll lags a fast
roll by up to one interval, and the error, ``pitch rate x roll lag / cos pitch``, accumulates wherever the
pitch rate and the roll's change keep step: luk8426 log_66 (PX4 ATTITUDE at 27 Hz) lost 33 deg of yaw in a
0.5 s manoeuvre at 300 deg/s, which a longer heading filter then carried into the heading
(docs/real-flights.md)."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from magcomp.adapters.config import Config
from magcomp.core.rotations import dcm_from_euler, euler_tilt_step
from magcomp.core.types import AttitudeSample
from magcomp.service.attitude import AttitudeStage

G = 9.80665


def _rocking(amplitude_deg: float, hz: float, seconds: float, att_every: int) -> float:
    """Roll and pitch rocking together, ``A sin(2 pi f t)`` each, no yaw at all (ZYX: p = roll rate, q =
    pitch rate cos roll, r = -pitch rate sin roll); a 200 Hz IMU, ATTITUDE every ``att_every`` IMU samples.
    Returns the yaw the heading integral gained (deg): the truth is 0."""
    st = AttitudeStage(Config(), Counter())  # type: ignore[arg-type]
    dt = 0.005
    a, w = math.radians(amplitude_deg), 2.0 * math.pi * hz
    y0 = math.nan
    n_still = 400  # 2 s level and still: the attitude filter settles
    for k in range(n_still + int(seconds / dt)):
        t = k * dt
        s = max(0.0, t - n_still * dt)
        ang = a * math.sin(w * s) if k >= n_still else 0.0
        rate = a * w * math.cos(w * s) if k >= n_still else 0.0
        phi = theta = ang
        p, q, r = rate, rate * math.cos(phi), -rate * math.sin(phi)
        if k == n_still:
            y0 = st.heading_yaw_rad
        f = dcm_from_euler(phi, theta, 0.0).T @ np.array([0.0, 0.0, -G])
        if k % att_every == 0:
            st.on_attitude(AttitudeSample(t, phi, theta, 0.0))
        st.on_imu(t, p, q, r, float(f[0]), float(f[1]), float(f[2]))
    return math.degrees(st.heading_yaw_rad - y0)


def test_the_heading_integral_carries_roll_and_pitch_between_attitude_messages() -> None:
    # 25 deg at 1.5 Hz (roll and pitch rates up to 236 deg/s), ATTITUDE at 25 Hz: held, the roll lags by
    # up to 40 ms and the integral gains about A^2 w^2 lag / 2 a second: held, 17 deg in 2 s (7 deg with
    # ATTITUDE at 50 Hz)
    got = _rocking(25.0, 1.5, 2.0, att_every=8)
    assert abs(got) < 1.5, got
    # and at every IMU sample (nothing to carry) the same
    assert abs(_rocking(25.0, 1.5, 2.0, att_every=1)) < 1.5


def test_euler_tilt_step_follows_a_known_attitude() -> None:
    """Roll and pitch stepped with the body rates of a ZYX trajectory stay on it (first-order, 1 kHz)."""
    dt, roll, pitch = 0.001, 0.2, -0.1
    for k in range(2000):
        t = k * dt
        droll, dpitch, dyaw = 0.8 * math.cos(t), -0.5 * math.sin(2 * t), 0.3
        r_, p_ = 0.2 + 0.8 * math.sin(t), -0.1 + 0.25 * (math.cos(2 * t) - 1.0)
        # body rates from the Euler rates at the true angles
        p = droll - dyaw * math.sin(p_)
        q = dpitch * math.cos(r_) + dyaw * math.sin(r_) * math.cos(p_)
        r = -dpitch * math.sin(r_) + dyaw * math.cos(r_) * math.cos(p_)
        roll, pitch = euler_tilt_step(roll, pitch, p, q, r, dt)
    t = 2000 * dt
    assert abs(roll - (0.2 + 0.8 * math.sin(t))) < 2e-3
    assert abs(pitch - (-0.1 + 0.25 * (math.cos(2 * t) - 1.0))) < 2e-3
