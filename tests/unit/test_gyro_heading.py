"""The gyro bias's heading wander through tilt (magcomp/diagnosis/gyro_heading.py), seeded.

Oracle: rotation algebra, and the simulator's true attitude for the heading error a body-axis gyro bias makes.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.adapters.mavlink_source import load_log
from magcomp.core.rotations import dcm_from_euler, dcms_from_quats, euler_from_dcms
from magcomp.core.types import Series
from magcomp.diagnosis.attitude import quats_at
from magcomp.diagnosis.gyro_heading import turn_heading, vertical_integrals, with_gyro_bias_heading
from magcomp.diagnosis.inputs import compass_data
from magcomp.sim import SimConfig, simulate


def test_turn_heading_adds_yaw_and_keeps_tilt() -> None:
    r = np.stack([dcm_from_euler(0.2, -0.1, 0.5), dcm_from_euler(-0.3, 0.25, -2.0)])
    out = euler_from_dcms(turn_heading(r, np.array([0.1, -0.4])))
    ref = euler_from_dcms(r)
    np.testing.assert_allclose(out[:, :2], ref[:, :2], atol=1e-12)
    np.testing.assert_allclose(out[:, 2], ref[:, 2] + np.array([0.1, -0.4]), atol=1e-12)


def test_level_flight_has_no_tilt_integrals() -> None:
    t = np.linspace(0.0, 60.0, 601)
    r = np.stack([dcm_from_euler(0.0, 0.0, 0.05 * x) for x in t])
    integ = vertical_integrals(t, r)
    np.testing.assert_allclose(integ, 0.0, atol=1e-9)
    # a constant bank: the x-bias integral is linear in time, with sin(roll) as its slope
    r = np.stack([dcm_from_euler(0.3, 0.0, 0.0) for _ in t])
    integ = vertical_integrals(t, r)
    np.testing.assert_allclose(np.diff(integ[:, 1]) / np.diff(t), math.sin(0.3), atol=1e-9)


def _yaw_error_rms(r_est: np.ndarray, r_true: np.ndarray, t: np.ndarray) -> float:
    d = np.unwrap(euler_from_dcms(r_est)[:, 2] - euler_from_dcms(r_true)[:, 2])
    tt = t - t.mean()
    d = d - np.polyval(np.polyfit(tt, d, 1), tt)  # the linear drift is the model's own parameter
    return float(np.degrees(d.std()))


def test_body_gyro_bias_wander_is_reduced(tmp_path: Path) -> None:
    """A flight with turns, a gyro bias on every body axis (0.01 rad/s) and a 1.1 deg roll / pitch bias in the
    logged attitude (the tilt reference): the heading wanders around its linear drift; the correction,
    fitted from the compass with the paper's model, lowers that wander. (On a clean log it can add ~0.1-0.2
    deg: the fit's own noise; measured in benchmarks/diagnosis_flight_pairs.py by theta against the truth.)"""
    res = simulate(
        SimConfig(scenario="flight", duration_s=90.0, seed=78, vehicle="multirotor", n_compasses=1)
    )
    path = tmp_path / "f.tlog"
    write_tlog(res, path)
    log = load_log(path)
    att = log.attitude_rad.values.copy()
    att[:, :2] += 0.02 * np.array([1.0, -1.0])
    log = replace(
        log,
        gyro_rad_s=log.gyro_rad_s + 0.01 * np.array([1.0, -1.0, 0.5]),
        attitude_rad=Series(log.attitude_rad.t_s, att),
    )
    data = compass_data(log, 0)
    r_true = dcms_from_quats(quats_at(data.t_s, res.t_s, res.motion.q_nb))
    before = _yaw_error_rms(data.r_nb, r_true, data.t_s)
    after = _yaw_error_rms(with_gyro_bias_heading(data).r_nb, r_true, data.t_s)
    assert before > 0.5, before  # the bias does make the heading wander (else the test shows nothing)
    assert after < 0.8 * before, (before, after)
