"""The autopilot's yaw-follow gain (magcomp.diagnosis.yaw_follow) recovered from simulated flights whose
autopilot has a known compass-correction gain, and a measured log's (log171) far below the simulator's
default (docs/measured-data.md)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from magcomp.diagnosis.yaw_follow import gyro_yaw_integral, yaw_follow_gain
from magcomp.sim import SimConfig, simulate
from magcomp.sim.config import apply_settings

LOG171 = Path(__file__).resolve().parents[2].parent / "shared/data/measured/dronekit_log171_copter33_quad.bin"


@pytest.mark.parametrize(("kp", "seed"), [(0.05, 3), (0.5, 4)])
def test_the_simulated_autopilots_gain_is_recovered(kp: float, seed: int) -> None:
    res = simulate(
        apply_settings(SimConfig(scenario="ordinary", seed=seed, duration_s=240.0), [f"ap_kp_yaw={kp}"])
    )
    s = res.samples
    fit = yaw_follow_gain(s.t_s, s.attitude_rad, s.t_s, s.gyro_rad_s[0], s.t_s, s.mag_mgauss[0])
    assert fit is not None
    assert abs(fit.gain_per_s - kp) < 0.15 * kp + 2.0 * fit.gain_sigma_per_s
    assert fit.gain_sigma_per_s < 0.1 * kp


def test_a_yaw_that_ignores_the_compass_has_no_gain() -> None:
    """An attitude whose yaw is the gyro's own integral (k = 0) whatever the compass says."""
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 200.0, 0.02)
    rate = 0.3 * np.sin(0.05 * t) + 0.1 * np.sin(0.31 * t)
    gyro = np.column_stack([np.zeros_like(t), np.zeros_like(t), rate])
    yaw = gyro_yaw_integral(t, gyro, t, np.zeros((t.size, 3)))
    att = np.column_stack([np.zeros_like(t), np.zeros_like(t), yaw])
    compass_yaw = yaw + np.radians(5.0) * np.sin(0.02 * t) + rng.normal(0.0, 0.01, t.size)
    field = np.column_stack(
        [300.0 * np.cos(compass_yaw), -300.0 * np.sin(compass_yaw), np.full_like(t, 400.0)]
    )
    fit = yaw_follow_gain(t, att, t, gyro, t, field)
    assert fit is not None
    assert abs(fit.gain_per_s) < 3.0 * fit.gain_sigma_per_s + 1e-3
    assert math.degrees(fit.spread_rad) > 2.0


def test_a_yaw_reset_is_a_jump_left_out_not_a_pull() -> None:
    """An autopilot pulling at 0.05 /s whose yaw is realigned once by 15 deg (as an EKF at take-off): the
    window with the jump is left out and the gain stays the pull's; kept, the jump alone moves it."""
    rng = np.random.default_rng(11)
    dt = 0.02
    t = np.arange(0.0, 300.0, dt)
    rate = 0.3 * np.sin(0.05 * t) + 0.1 * np.sin(0.31 * t)
    gyro = np.column_stack([np.zeros_like(t), np.zeros_like(t), rate])
    truth = np.cumsum(rate) * dt
    compass = truth + np.radians(6.0) * np.sin(0.013 * t + 1.0)
    yaw = np.empty_like(t)
    yaw[0] = truth[0]
    for i in range(1, t.size):
        yaw[i] = yaw[i - 1] + rate[i - 1] * dt + 0.05 * (compass[i - 1] - yaw[i - 1]) * dt
        if abs(t[i] - 101.0) < 0.5 * dt:
            yaw[i] += math.radians(15.0)
    att = np.column_stack([np.zeros_like(t), np.zeros_like(t), yaw])
    psi = compass + rng.normal(0.0, 0.005, t.size)
    field = np.column_stack([300.0 * np.cos(psi), -300.0 * np.sin(psi), np.full_like(t, 400.0)])
    fit = yaw_follow_gain(t, att, t, gyro, t, field)
    assert fit is not None and fit.n_left_out >= 1
    assert abs(fit.gain_per_s - 0.05) < 0.01


@pytest.mark.skipif(not LOG171.exists(), reason="needs ../shared/data/measured (not in a user's clone)")
def test_log171s_autopilot_follows_its_compass_far_slower_than_the_simulators_default() -> None:
    from magcomp.adapters.mavlink_source import load_log

    log = load_log(LOG171)
    mag, att, thr = log.mag[0], log.attitude_rad, log.throttle_01
    t_fly = float(thr.t_s[thr.values > 0.1][0])
    fit = yaw_follow_gain(att.t_s, att.values, log.imu_t_s, log.gyro_rad_s, mag.t_s, mag.values,
                          t_end_s=t_fly - 1.0)  # fmt: skip
    assert fit is not None
    # the simulator's default ap_kp_yaw is 0.5 /s; a 2 s time constant would be tens of sigmas away
    assert fit.gain_per_s + 4.0 * fit.gain_sigma_per_s < 0.5 / 4.0


@pytest.mark.skipif(not LOG171.exists(), reason="needs ../shared/data/measured (not in a user's clone)")
def test_diagnose_notes_log171s_yaw_follow_gain_with_the_motors_running() -> None:
    from magcomp.adapters.mavlink_source import load_log
    from magcomp.diagnosis.engine import _yaw_follow

    note, fit = _yaw_follow(load_log(LOG171), 0)
    assert note is not None and note.startswith("the autopilot's yaw follows compass 0's heading at ")
    gain, sigma = (float(x) for x in note.split(" at ")[1].split(" /s")[0].split(" +- "))
    assert abs(gain) < 3.0 * sigma + 0.02 and sigma < 0.05
    assert fit is not None
    assert abs(fit.gain_per_s - gain) < 5e-4  # the fit the gyro check decides on, as the note prints it


def test_nan_rows_and_disorder_are_left_out_not_a_crash() -> None:
    cfg = apply_settings(SimConfig(scenario="ordinary", seed=5, duration_s=200.0), ["ap_kp_yaw=0.3"])
    res = simulate(cfg)
    s = res.samples
    att = s.attitude_rad.copy()
    att[100:140] = np.nan
    gyro = s.gyro_rad_s[0].copy()
    gyro[500] = np.inf
    t_mag = s.t_s.copy()[::-1]
    field = s.mag_mgauss[0][::-1].copy()
    fit = yaw_follow_gain(s.t_s, att, s.t_s, gyro, t_mag, field)
    assert fit is not None and math.isfinite(fit.gain_per_s)
    assert abs(fit.gain_per_s - 0.3) < 0.15 * 0.3 + 2.0 * fit.gain_sigma_per_s
    assert yaw_follow_gain(s.t_s[:1], att[:1], s.t_s, gyro, t_mag, field) is None
