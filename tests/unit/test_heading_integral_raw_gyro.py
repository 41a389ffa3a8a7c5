"""The heading integral takes the gyro as the autopilot logged it, not the attitude filter's corrected rate.

In flight a multicopter's accelerometer measures thrust and drag, not gravity: the Mahony filter (eq. (18),
ref. [23]) reads that as a tilt error and its bias adaptation learns it as a gyro bias (on log171 1.1 deg/s
about z, on peterbarker 1.BIN 1.6 deg/s, where the raw gyro's yaw drifts from the autopilot's by 0.1-0.3
deg/s). The heading filter propagates with this integral; a longer filter carries the false rate into the
heading (docs/real-flights.md)."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from magcomp.adapters.config import Config
from magcomp.core.types import AttitudeSample
from magcomp.service.attitude import AttitudeStage

G = 9.80665


def test_a_multicopters_accelerometer_does_not_bend_the_heading_integral() -> None:
    """A steady banked turn (20 deg of bank, 8 deg nose down, 10 deg/s) with an exact gyro; the accelerometer
    reads thrust along body z and 0.8 m/s^2 of drag, as a multicopter's does. The integral's yaw over 58 s
    must follow the turn; the attitude filter's bias estimate does not (it takes up several deg/s)."""
    st = AttitudeStage(Config(), Counter())  # type: ignore[arg-type]
    dt = 0.005
    phi, theta, psi_dot = math.radians(20.0), math.radians(-8.0), math.radians(10.0)
    n_still = 400
    y0 = t0 = math.nan
    for k in range(n_still + int(60.0 / dt)):
        t = k * dt
        if k < n_still:  # level and still: the filter settles
            ph = th = p = q = r = 0.0
            f = (0.0, 0.0, -G)
        else:
            ph, th = phi, theta
            p = -psi_dot * math.sin(th)
            q = psi_dot * math.sin(ph) * math.cos(th)
            r = psi_dot * math.cos(ph) * math.cos(th)
            f = (-0.8, 0.0, -G / (math.cos(ph) * math.cos(th)))
        if k == n_still + 200:
            y0, t0 = st.heading_yaw_rad, t
        if k % 4 == 0:
            st.on_attitude(AttitudeSample(t, ph, th, 0.0))
        st.on_imu(t, p, q, r, *f)
    assert st.mahony is not None
    assert float(np.max(np.abs(np.degrees(st.mahony.b)))) > 1.0  # the false bias is there
    gained = math.degrees(st.heading_yaw_rad - y0)
    turned = math.degrees(psi_dot * (t - t0))
    assert abs(gained - turned) < 1.0, (gained, turned)
