"""A damaged IMU record (a flipped exponent bit in a DataFlash log: 8e35 m/s^2) is dropped by the attitude
stage, not low-passed into the horizontal acceleration the in-flight rows are built from (where it stayed
for minutes and overflowed them: every compass "corrected" with a NaN calibration)."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.core.rotations import dcm_from_euler
from magcomp.core.types import AttitudeSample
from magcomp.service import attitude
from magcomp.service.attitude import AttitudeStage


def test_an_accel_beyond_any_full_scale_is_dropped(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(attitude, "TRACK_ACCEL_H", True)
    phi, theta = math.radians(5.0), math.radians(-7.0)
    a_n = np.array([1.0, -0.5, 0.0])
    f = dcm_from_euler(phi, theta, 0.0).T @ (a_n - np.array([0.0, 0.0, 9.80665]))
    counts: Counter[str] = Counter()
    st = AttitudeStage(Config(), counts)  # type: ignore[arg-type]
    st.on_attitude(AttitudeSample(0.0, phi, theta, 0.0))
    assert st.gyro_yaw_at(0.0, 0.02, 0.05) is None  # asked for: tracked from now
    dt = 0.02
    n = 1000
    for k in range(n):
        acc = (8.1e35, -3.0e34, 2.0e35) if k == n // 2 else tuple(f)
        st.on_imu(k * dt, 0.0, 0.0, 0.0, *acc)
    assert counts["implausible"] == 1
    assert st.accel_norm < 2000.0  # ~204 g: no accelerometer reads more
    got = st.gyro_yaw_at((n - 1) * dt, 0.02, 0.05)
    assert got is not None
    assert np.allclose(got.accel_h_m_s2, a_n[:2], atol=0.05), got.accel_h_m_s2
