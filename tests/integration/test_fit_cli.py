"""`magcomp fit` end to end on a tlog written with pymavlink's encoder, plus the LogData-level path."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from magcomp.cli import main
from magcomp.commands.fit import fit_log
from magcomp.core.rotations import dcm_from_quat, euler_from_quat, quat_from_euler, quat_integrate_body_rate
from magcomp.core.types import LogData, Series
from magcomp.errors import InputError, MagcompError

THETA = np.array([-60.0, 35.0, 20.0])  # mgauss at full throttle
U_N = np.array([240.9, -27.1, 386.2])  # Earth field NED, mgauss
NOISE_MG = 3.0
G = 9.80665
BOOT_OFFSET_US = 1_000_000
KEYS = {"theta", "theta_std", "sigma", "r2", "snr_db", "benchmark_r2", "n", "t_start_s", "t_end_s", "dropped"}


def _scenario(rng: np.random.Generator, sweep: bool) -> dict[str, np.ndarray]:
    """60 s at 50 Hz: hand rotation (0-10 s), bench at rest with a 0 -> 100 % ramp (10-50 s), rotation."""
    dt = 0.02
    t = np.arange(0.0, 60.0, dt)
    moving = (t < 10.0) | (t >= 50.0)
    omega = np.where(moving[:, None], 0.7 * np.sin(2 * np.pi * 0.25 * t[:, None] + np.array([0, 1, 2])), 0.0)
    q = np.empty((len(t), 4))
    q[0] = quat_from_euler(0.05, -0.03, 1.2)
    for i in range(1, len(t)):
        q[i] = quat_integrate_body_rate(q[i - 1], omega[i - 1], dt)
    throttle = np.where(moving, 0.0, np.clip((t - 10.0) / 38.0, 0.0, 1.0)) if sweep else np.full(len(t), 0.3)
    r = np.array([dcm_from_quat(qi) for qi in q])
    u_b = np.einsum("nji,j->ni", r, U_N)
    field = u_b + np.outer(throttle**2, THETA) + NOISE_MG * rng.standard_normal(u_b.shape)  # eq. (12)
    accel = -G * r[:, 2, :]
    gyro = omega + 0.002 * rng.standard_normal(omega.shape)
    euler = np.array([euler_from_quat(qi) for qi in q])
    return {
        "t": t,
        "field": field,
        "accel": accel,
        "gyro": gyro,
        "euler": euler,
        "omega": omega,
        "thr": throttle,
    }


def _write_tlog(path: Path, s: dict[str, np.ndarray]) -> None:
    from pymavlink.dialects.v20 import ardupilotmega as apm

    mav = apm.MAVLink(None, srcSystem=1, srcComponent=1)
    t0_unix = 1.75e9
    events: list[tuple[float, object]] = []
    for i, t in enumerate(s["t"]):
        us = round(t * 1e6) + BOOT_OFFSET_US
        f, a, g = s["field"][i], s["accel"][i] / G * 1000.0, s["gyro"][i] * 1000.0
        events.append(
            (
                t,
                apm.MAVLink_raw_imu_message(
                    us, *[round(x) for x in a], *[round(x) for x in g], *[round(x) for x in f], 0, 0
                ),
            )
        )
        if i % 2 == 0:
            e, w = s["euler"][i], s["omega"][i]
            events.append((t, apm.MAVLink_attitude_message(us // 1000, *e, *w)))
        if i % 5 == 0:
            pwm = round(1000 + 1000 * s["thr"][i])
            events.append((t, apm.MAVLink_servo_output_raw_message(us % 2**32, 0, *([pwm] * 4), *([0] * 12))))
        if i % 50 == 0:
            events.append((t, apm.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)))  # quadrotor, ArduPilot
    with path.open("wb") as fh:
        for t, msg in events:
            fh.write(struct.pack(">Q", round((t0_unix + t) * 1e6)) + msg.pack(mav))  # type: ignore[attr-defined]


def test_fit_cli_recovers_theta_from_generated_tlog(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    s = _scenario(np.random.default_rng(31), sweep=True)
    log = tmp_path / "bench.tlog"
    _write_tlog(log, s)
    out = tmp_path / "fit.json"
    assert main(["fit", str(log), "--json", str(out), "--monte-carlo", "300"]) == 0
    table = capsys.readouterr().out
    assert "benchmark R^2" in table and "theta" in table
    doc = json.loads(out.read_text())
    assert set(doc) == KEYS
    theta, std = np.array(doc["theta"]), np.array(doc["theta_std"])
    assert np.all(np.abs(theta - THETA) < 4.0 * std), (theta, std)
    assert np.all(std < 1.0)
    # quantisation of RAW_IMU (1 mgauss) adds 1/sqrt(12) in quadrature
    np.testing.assert_allclose(doc["sigma"], np.hypot(NOISE_MG, 1 / np.sqrt(12)), rtol=0.1)
    # boot clock = scenario time + 1 s; the sweep is at rest from 10 to 50 s
    assert 11.0 <= doc["t_start_s"] < 12.6 and 49.4 < doc["t_end_s"] <= 51.0, doc
    assert doc["n"] > 1500
    assert len(doc["benchmark_r2"]) == 3 and all(len(b) == 2 for b in doc["benchmark_r2"])
    for r2, (mean, two_sd) in zip(doc["r2"], doc["benchmark_r2"], strict=True):
        assert abs(r2 - mean) <= 1.5 * two_sd + 1e-3


def test_fit_cli_without_sweep_exits_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "hover.tlog"
    _write_tlog(log, _scenario(np.random.default_rng(32), sweep=False))
    assert main(["fit", str(log), "--monte-carlo", "0"]) == 1
    err = capsys.readouterr().err
    assert "no stationary throttle sweep" in err and err.count("\n") == 1


def _fake_log(rng: np.random.Generator) -> LogData:
    t_mag = np.arange(0.0, 40.0, 0.02)
    t_thr = np.arange(0.0, 40.0, 0.2)  # 5 Hz throttle: interpolated onto the 50 Hz compass
    thr = np.clip(t_thr / 30.0, 0.0, 1.0)
    noise = 2.0 * rng.standard_normal((len(t_mag), 3))
    field = U_N + np.outer(np.interp(t_mag, t_thr, thr) ** 2, THETA) + noise
    return LogData(
        source="fake",
        mag={1: Series(t_mag, field)},
        throttle_01=Series(t_thr, thr),
        throttle_source="motors:1,2,3,4",
    )


def test_fit_log_explicit_window_on_fake_logdata() -> None:
    log = _fake_log(np.random.default_rng(33))
    rep = fit_log(log, start_s=2.0, end_s=38.0, n_monte_carlo=0)
    assert rep.mag_index == 1 and rep.t_start_s == 2.0 and rep.t_end_s == 38.0
    assert rep.fit.n == 1801
    assert np.all(np.abs(rep.fit.theta_mgauss - THETA) < 4 * rep.fit.theta_std_mgauss)
    # no gyro and no attitude: automatic window impossible -> clear error
    with pytest.raises(MagcompError, match="no stationary throttle sweep"):
        fit_log(log, n_monte_carlo=0)
    with pytest.raises(InputError, match="no compass 0"):
        fit_log(log, mag_index=0)
    with pytest.raises(InputError, match="empty window"):
        fit_log(log, start_s=30.0, end_s=10.0)
