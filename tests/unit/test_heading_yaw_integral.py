"""The gyro's yaw that the heading filter propagates with and the self-check takes as its reference
(``AttitudeStage.heading_yaw_rad``) converts body rates to the Euler yaw rate with the current roll and pitch,
also between two magnetometer samples. Before, the conversion took the roll and pitch of the last
magnetometer sample: on a 2 Hz ULog compass a banked turn between two samples was integrated as if level
(a 40 deg bank: 23 % of the turn lost). On the development logs this moved luk8426 log 66 compass 0 from
9.0 / 5.9 to 5.8 / 1.9 deg (att / gyro, two-pass; docs/real-flights.md). Both attitude sources: the
autopilot's ATTITUDE (the default) and magcomp's own filter (``[input] attitude = "mahony"``)."""

from __future__ import annotations

import dataclasses
import math
from collections import Counter

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.core.rotations import dcm_from_euler
from magcomp.core.types import AttitudeSample
from magcomp.service.attitude import AttitudeStage

G = 9.80665


def _turn(source: str, bank_deg: float, pitch_deg: float, yaw_rate_deg_s: float, seconds: float) -> float:
    """Level and still for 2 s (the last magnetometer sample's view is taken there), a 0.5 s roll into the
    bank, then a steady turn; returns the yaw the integral gained over the turn (deg)."""
    cfg = Config()
    cfg = dataclasses.replace(cfg, input=dataclasses.replace(cfg.input, attitude=source))
    st = AttitudeStage(cfg, Counter())  # type: ignore[arg-type]
    dt = 0.005  # a 200 Hz IMU, ATTITUDE at 100 Hz
    phi_end, theta_end = math.radians(bank_deg), math.radians(pitch_deg)
    psi_dot = math.radians(yaw_rate_deg_s)
    n_still, n_roll, n_turn = 400, 100, int(seconds / dt)
    y0 = math.nan
    for k in range(n_still + n_roll + n_turn):
        t = k * dt
        a = min(1.0, max(0.0, (k - n_still) / n_roll))  # the roll-in: bank and pitch grow together
        phi, theta = a * phi_end, a * theta_end
        turning = k >= n_still + n_roll
        if k == n_still:
            st.view()  # the magnetometer's last sample: level
        if k == n_still + n_roll:
            y0 = st.heading_yaw_rad
        if turning:  # body rates of a steady turn (ZYX: p = -psi' sin(theta), q, r as below)
            p = -psi_dot * math.sin(theta)
            q = psi_dot * math.sin(phi) * math.cos(theta)
            r = psi_dot * math.cos(phi) * math.cos(theta)
        elif k >= n_still:  # rolling in: the Euler angle rates into body rates (no yaw)
            dphi, dtheta = phi_end / (n_roll * dt), theta_end / (n_roll * dt)
            p = dphi
            q = dtheta * math.cos(phi)
            r = -dtheta * math.sin(phi)
        else:
            p = q = r = 0.0
        f = dcm_from_euler(phi, theta, 0.0).T @ np.array([0.0, 0.0, -G])  # gravity's reaction, body axes
        if k % 2 == 0:
            st.on_attitude(AttitudeSample(t, phi, theta, 0.0))
        st.on_imu(t, p, q, r, float(f[0]), float(f[1]), float(f[2]))
    return math.degrees(st.heading_yaw_rad - y0)


@pytest.mark.parametrize("source", ["auto", "mahony"])
def test_a_banked_turn_between_two_compass_samples_is_integrated_with_its_bank(source: str) -> None:
    for bank, pitch in ((40.0, 0.0), (-30.0, 10.0)):
        got = _turn(source, bank, pitch, 45.0, 2.0)
        # 90 deg of turn; the filter's gyro-bias estimate moves by little in 2.5 s
        assert np.isclose(got, 90.0, atol=2.0), (source, bank, pitch, got)
