"""The gyro's yaw that the heading filter propagates with and the self-check takes as its reference
(``AttitudeStage.heading_yaw_rad``) converts body rates to the Euler yaw rate with the current roll and pitch,
also between two magnetometer samples. Before, the conversion took the roll and pitch of the last
magnetometer sample: on a 2 Hz ULog compass a banked turn between two samples was integrated as if level
(a 40 deg bank: 23 % of the turn lost). On the development logs this moved luk8426 log 66 compass 0 from
9.0 / 5.9 to 5.8 / 1.9 deg (att / gyro, two-pass; docs/benchmarks.md). Where the heading's roll and pitch
come from the own attitude filter alone (``[input] attitude = "mahony"``), they still change at the
magnetometer's samples."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from magcomp.adapters.config import Config
from magcomp.core.types import AttitudeSample
from magcomp.service.attitude import AttitudeStage


def _turn(bank_deg: float, pitch_deg: float, yaw_rate_deg_s: float, seconds: float) -> float:
    """A steady turn entered from level flight, the magnetometer's view taken only once, before it;
    returns the integrated yaw change (deg)."""
    counts: Counter[str] = Counter()
    st = AttitudeStage(Config(), counts)  # type: ignore[arg-type]
    dt = 0.005  # a 200 Hz IMU
    st.on_attitude(AttitudeSample(0.0, 0.0, 0.0, 0.0))
    for k in range(200):  # one second level, still: the filter starts and settles
        st.on_imu(k * dt, 0.0, 0.0, 0.0, 0.0, 0.0, -9.80665)
    st.view()  # the last magnetometer sample's view: level
    y0 = st.heading_yaw_rad
    phi, theta, psi_dot = math.radians(bank_deg), math.radians(pitch_deg), math.radians(yaw_rate_deg_s)
    # body rates of a steady turn at this bank and pitch (ZYX Euler: p = -psi' sin(theta),
    # q = psi' sin(phi) cos(theta), r = psi' cos(phi) cos(theta))
    p = -psi_dot * math.sin(theta)
    q = psi_dot * math.sin(phi) * math.cos(theta)
    r = psi_dot * math.cos(phi) * math.cos(theta)
    g = 9.80665
    f = (g * math.sin(theta), -g * math.sin(phi) * math.cos(theta), -g * math.cos(phi) * math.cos(theta))
    t0 = 200 * dt
    n = int(seconds / dt)
    for k in range(n):
        t = t0 + k * dt
        if k % 2 == 0:  # ATTITUDE at 100 Hz
            st.on_attitude(AttitudeSample(t, phi, theta, 0.0))
        st.on_imu(t, p, q, r, *f)
    return math.degrees(st.heading_yaw_rad - y0)


def test_a_banked_turn_between_two_compass_samples_is_integrated_with_its_bank() -> None:
    for bank, pitch in ((40.0, 0.0), (-30.0, 10.0)):
        got = _turn(bank, pitch, 45.0, 2.0)
        # 90 deg of turn; the filter's gyro-bias estimate moves by little in 2 s
        assert np.isclose(got, 90.0, atol=2.0), (bank, pitch, got)
