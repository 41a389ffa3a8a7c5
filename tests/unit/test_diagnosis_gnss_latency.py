"""The GNSS velocity's latency is not negative (magcomp.diagnosis.gps_tilt.gnss_delay).

A receiver's velocity describes motion that has already happened, so a best shift below 0 is the estimate's
scatter about none: on simulated logs (no latency) the grid's best shift was -20..+20 ms, and the tilt built
with a -10 ms one moved theta's x by 1.7 mgauss on the theta-frame test's flight (6.1 -> 4.4 mgauss from the
truth). A level vehicle accelerating back and forth, its GNSS velocity stamped 50 ms *before* the motion it
describes: the grid's best shift is -50 ms, which is no receiver's latency, and is reported as 0.
"""

from __future__ import annotations

import numpy as np

from magcomp.diagnosis.gps_tilt import gnss_delay

G = 9.80665


def _level_flight() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """IMU at 100 Hz, GNSS velocity at 5 Hz, level and heading north, accelerating 2.5 / 1.5 m/s^2 N / E."""
    t = np.arange(0.0, 30.0, 0.01)
    wn, we = 2 * np.pi * 0.25, 2 * np.pi * 0.11
    a_n = np.column_stack([2.5 * np.sin(wn * t), 1.5 * np.sin(we * t), np.zeros_like(t)])
    v_n = np.column_stack([-2.5 / wn * np.cos(wn * t), -1.5 / we * np.cos(we * t), np.zeros_like(t)])
    r_nb = np.repeat(np.eye(3)[None], t.size, axis=0)
    f_b = a_n - np.array([0.0, 0.0, G])  # level: body axes are NED
    k = np.arange(0, t.size, 20)
    return t, f_b, r_nb, t[k], v_n[k]


def test_a_velocity_stamped_before_its_motion_has_no_negative_latency() -> None:
    t, f_b, r_nb, t_g, v_g = _level_flight()
    assert gnss_delay(t, f_b, r_nb, t_g - 0.05, v_g) == 0.0
    got = gnss_delay(t, f_b, r_nb, t_g + 0.1, v_g)  # a positive latency is measured as before
    assert got is not None and abs(got - 0.1) <= 0.02
