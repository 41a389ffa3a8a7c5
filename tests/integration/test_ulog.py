"""PX4 ULog as a streamed source: the simulator's ULog replays like its tlog twin; the measured old-format
ULog goes through replay, fit and diagnose with one-line messages where nothing can be done."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import load_config
from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.adapters.mavlink_source import load_log, open_source
from magcomp.adapters.ulog_source import UlogSource
from magcomp.adapters.ulog_writer import MAG_DEVICE_IDS, UlogWriter, write_sim_ulog
from magcomp.cli import main
from magcomp.core.types import (
    HeartbeatSample,
    MagSample,
    ParamSample,
    PositionSample,
    PowerSample,
    ThrottleSample,
)
from magcomp.service.replay import replay_log
from magcomp.sim import SimConfig, simulate
from magcomp.sim.config import Rates

MEASURED = Path(__file__).parents[2].parent / "shared" / "data" / "measured"
ULOG = MEASURED / "pyulog_sample_px4_disarmed.ulg"


def _rates(hz: float) -> Rates:
    return Rates(imu_hz=hz, attitude_hz=min(25.0, hz), servo_hz=min(25.0, hz), rc_hz=min(10.0, hz),
                 vfr_hud_hz=min(10.0, hz), power_hz=min(10.0, hz), heartbeat_hz=min(1.0, hz))  # fmt: skip


def _wrapped(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


@pytest.mark.parametrize("mag_hz", [50.0, 10.0, 2.0])
def test_simulated_ulog_replays_like_its_tlog_twin(tmp_path: Path, mag_hz: float) -> None:
    result = simulate(SimConfig(scenario="paper", duration_s=40.0, seed=5, rates=_rates(mag_hz)))
    tlog, ulg = tmp_path / "twin.tlog", tmp_path / "twin.ulg"
    write_tlog(result, tlog)
    write_sim_ulog(result, ulg)
    cfg = load_config(None)
    # the readers are compared, so the paths that amplify the two formats' own differences are left out:
    # the tlog carries the gyro in 1 mrad/s steps, the ULog in float32, and the in-flight calibration's first
    # seconds on the paper's tumble (hundreds of deg/s, few samples, heading sigma ~15 deg) move by degrees
    # between them; the hand-rotation path, compared here, does not
    cfg = replace(
        cfg, input=replace(cfg.input, attitude="mahony"), inflight=replace(cfg.inflight, enabled=False)
    )
    a = replay_log(tlog, cfg, keep_estimates=True).estimates
    b = replay_log(ulg, cfg, keep_estimates=True).estimates
    assert len(a) == len(b) == 2 * result.samples.t_s.size  # two compasses, every sample published
    for idx in (0, 1):
        ea = [e for e in a if e.mag_index == idx]
        eb = [e for e in b if e.mag_index == idx]
        assert [e.t_s for e in ea] == pytest.approx([e.t_s for e in eb], abs=1e-6)
        d = _wrapped(np.array([e.heading_deg for e in ea]) - np.array([e.heading_deg for e in eb]))
        # float32 storage in the ULog (gyro, attitude quaternion) is the only difference from the tlog
        assert np.sqrt(np.mean(d**2)) < 0.05 and np.max(np.abs(d)) < 1.0
        np.testing.assert_allclose(eb[-1].theta_mgauss, ea[-1].theta_mgauss, atol=0.5)
    if mag_hz == 50.0:  # long enough at this rate to learn theta: the comparison means something
        assert np.linalg.norm(a[-2].theta_mgauss) > 10.0


def test_ulog_stream_is_time_ordered_with_px4_units_and_compasses_by_device_id(tmp_path: Path) -> None:
    result = simulate(SimConfig(scenario="step", duration_s=6.0, seed=2, vehicle="multirotor", n_compasses=2))
    path = tmp_path / "vm.ulg"
    write_sim_ulog(result, path, mag_topic="vehicle_magnetometer")
    with open_source(path) as src:
        assert isinstance(src, UlogSource)
        recs = list(src.records())
    t = np.array([s.t_s for _, s in recs])
    assert np.all(np.diff(t) >= 0.0)
    hb = [s for _, s in recs if isinstance(s, HeartbeatSample)]
    assert [(h.autopilot, h.vehicle_type) for h in hb] == [(12, 2)]  # PX4, rotary wing -> quadrotor
    params = {s.name: s.value for _, s in recs if isinstance(s, ParamSample)}
    assert params["CAL_MAG1_ID"] == MAG_DEVICE_IDS[1]
    s = result.samples
    for j in (0, 1):
        mags = np.array([m.field_b_mgauss for _, m in recs if isinstance(m, MagSample) and m.mag_index == j])
        np.testing.assert_allclose(mags, np.round(s.mag_mgauss[j]), atol=1e-3)  # gauss -> mgauss
    thr = [x for _, x in recs if isinstance(x, ThrottleSample)]
    assert thr[0].source == "actuator_outputs:1,2,3,4" and len(thr[0].motors_01) == 4
    np.testing.assert_allclose([x.throttle_01 for x in thr], s.throttle_01[:: round(s.t_s.size / len(thr))],
                               atol=2e-3)  # fmt: skip
    power = [p for _, p in recs if isinstance(p, PowerSample)]
    assert power and all(abs(p.current_a - c) < 0.006 for p, c in zip(power, s.current_a[::5], strict=False))
    pos = [p for _, p in recs if isinstance(p, PositionSample)]
    loc = result.config.location
    assert pos and all(p.fix_ok and abs(p.lat_deg - loc.lat_deg) < 1e-6 for p in pos)
    data = load_log(path)
    assert abs(data.decimal_year - loc.decimal_year) < 0.01
    assert sorted(data.mag) == [0, 1] and len(data.position) == len(pos)


def test_old_and_new_gps_fields_and_parameter_changes(tmp_path: Path) -> None:
    w = UlogWriter(start_us=1_000_000)
    latlon = [("double", "latitude_deg"), ("double", "longitude_deg"), ("double", "altitude_msl_m")]
    w.topic("sensor_gps", [*latlon, ("uint8_t", "fix_type"), ("uint64_t", "time_utc_usec")])
    w.topic("vehicle_magnetometer", [("uint32_t", "device_id"), ("float[3]", "magnetometer_ga")])
    w.param("CAL_MAG0_ID", 11, is_int=True)
    w.param("CAL_MAG1_ID", 22, is_int=True)
    unix_2024 = 1_704_067_200  # 2024-01-01 00:00 UTC
    for k in range(10):
        t_us = 1_000_000 + 100_000 * k
        w.data(
            "sensor_gps", 0, [t_us, 47.3977, 8.5456, 488.0, 2 if k < 3 else 3, (unix_2024 + k) * 1_000_000]
        )
        w.data("vehicle_magnetometer", 0, [t_us, 22, 0.2, 0.0, 0.4])  # instance 0 is CAL_MAG1's device
        if k == 5:
            w.param_change("CAL_MAG1_ID", 33, is_int=True)
    path = tmp_path / "gps.ulg"
    w.write(path)
    with open_source(path) as src:
        samples = list(src.samples())
        assert src.params["CAL_MAG1_ID"] == 33.0  # the change, after the initial value
    pos = [s for s in samples if isinstance(s, PositionSample)]
    assert [p.fix_ok for p in pos] == [False] * 3 + [True] * 7
    assert all(abs(p.lat_deg - 47.3977) < 1e-9 and p.alt_m == 488.0 for p in pos)
    assert all(abs(p.decimal_year - 2024.0) < 1e-5 for p in pos)
    mags = [s for s in samples if isinstance(s, MagSample)]
    assert {m.mag_index for m in mags} == {1} and mags[0].field_b_mgauss[2] == pytest.approx(400.0)


def test_damaged_ulog_is_one_line_input_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "bad.ulg"
    path.write_bytes(b"ULog\x01\x12\x35\x01" + bytes(8) + b"\xff" * 40)
    assert main(["replay", str(path)]) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error" in err and "Traceback" not in err


def _need_ulog() -> Path:
    if not ULOG.exists():
        pytest.skip(f"measured log {ULOG.name} not available (expected in {MEASURED})")
    return ULOG


@pytest.mark.needs_shared
def test_measured_old_format_ulog_replay_fit_diagnose(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _need_ulog()
    data = load_log(path)
    with open_source(path) as src:
        n_mag = sum(1 for s in src.samples() if isinstance(s, MagSample))
    assert n_mag == len(data.mag[0]) > 1000  # sensor_combined.magnetometer_ga, one row per new sample
    assert main(["replay", str(path), "--json", str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out
    assert f"{n_mag} headings" in out
    # disarmed: no throttle sweep to fit; a one-line reason, no traceback
    assert main(["fit", str(path)]) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "throttle" in err
    assert main(["diagnose", str(path), "--json", str(tmp_path / "d.json")]) == 0


def test_simulate_cli_writes_ulog_with_truth_and_replay_reads_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "sim.ulg"
    args = ["simulate", "--scenario", "step", "--duration", "4", "--imu-rate", "10", "--out", str(out)]
    assert main(args) == 0
    assert (tmp_path / "sim.truth.json").is_file() and (tmp_path / "sim.truth.npz").is_file()
    assert out.read_bytes()[:7] == b"ULog\x01\x12\x35"
    capsys.readouterr()
    assert main(["replay", str(out)]) == 0
    n = sum(1 for s in open_source(out).samples() if isinstance(s, MagSample))
    assert f"{n} headings" in capsys.readouterr().out and n > 0


@pytest.mark.parametrize("mag_hz", [2.0, 10.0])
def test_fit_on_simulated_ulog_equals_its_tlog_twin(
    tmp_path: Path, mag_hz: float, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    result = simulate(
        SimConfig(scenario="bench", duration_s=60.0, seed=3, vehicle="multirotor", rates=_rates(mag_hz))
    )
    write_sim_ulog(result, tmp_path / "b.ulg")
    write_tlog(result, tmp_path / "b.tlog")
    for ext in ("ulg", "tlog"):
        assert main(["fit", str(tmp_path / f"b.{ext}"), "--json", str(tmp_path / f"{ext}.json")]) == 0
    fu = json.loads((tmp_path / "ulg.json").read_text())
    ft = json.loads((tmp_path / "tlog.json").read_text())
    np.testing.assert_allclose(fu["theta"], ft["theta"], atol=0.05)
    truth = np.asarray(result.compasses[0].theta_mgauss)
    assert np.linalg.norm(np.asarray(fu["theta"]) - truth) < 0.25 * np.linalg.norm(truth)


def test_px4_114_topics_vehicle_imu_and_actuator_motors(tmp_path: Path) -> None:
    """PX4 >= 1.13 logs: no sensor_combined magnetometer, IMU from vehicle_imu's integrals, throttle from
    actuator_motors (0..1, NaN = stopped) on CA_ROTOR_COUNT motors, battery current -1 = unknown."""
    w = UlogWriter(start_us=0)
    w.topic("vehicle_imu", [("float[3]", "delta_angle"), ("float[3]", "delta_velocity"),
                            ("uint16_t", "delta_angle_dt"), ("uint16_t", "delta_velocity_dt")])  # fmt: skip
    w.topic("actuator_motors", [("uint64_t", "timestamp_sample"), ("float[12]", "control")])
    w.topic("battery_status", [("float", "voltage_v"), ("float", "current_a")])
    w.topic("vehicle_status", [("uint8_t", "vehicle_type")])
    w.param("CA_ROTOR_COUNT", 4, is_int=True)
    nan = float("nan")
    w.data("vehicle_status", 0, [0, 1])
    for k in range(20):
        t_us = 10_000 * (k + 1)
        # 5000 us integrals of 0.1 rad/s and 9.8 m/s^2 about/along z
        w.data("vehicle_imu", 0, [t_us, 0.0, 0.0, 0.0005, 0.0, 0.0, -0.049, 5000, 5000])
        motors = [nan] * 4 if k < 5 else [0.2, 0.4, 0.6, 0.8]
        w.data("actuator_motors", 0, [t_us, t_us, *motors, *([nan] * 8)])
        w.data("battery_status", 0, [t_us, 16.0, -1.0 if k < 5 else 12.5])
    path = tmp_path / "px4_114.ulg"
    w.write(path)
    data = load_log(path)
    assert data.vehicle_type == 2 and data.autopilot == 12 and not data.mag
    np.testing.assert_allclose(data.gyro_rad_s[:, 2], 0.1, rtol=1e-5)
    np.testing.assert_allclose(data.accel_m_s2[:, 2], -9.8, rtol=1e-5)
    assert data.throttle_source == "actuator_motors" and data.motors_01.values.shape == (20, 4)
    np.testing.assert_allclose(data.throttle_01.values, [0.0] * 5 + [0.5] * 15, atol=1e-6)
    assert np.isnan(data.current_a.values[:5]).all() and data.current_a.values[-1] == pytest.approx(12.5)


def test_compass_indices_follow_cal_mag_ids_before_instance_numbers() -> None:
    from magcomp.adapters.ulog_source import _compass_indices

    params = {"CAL_MAG0_ID": 500.0, "CAL_MAG1_ID": 700.0}
    # instance 0 is an uncalibrated compass, instance 1 is CAL_MAG0's device, instance 2 CAL_MAG1's
    assert _compass_indices(params, [(0, 999), (1, 500), (2, 700)]) == {1: 0, 2: 1, 0: 2}
    assert _compass_indices({}, [(0, 0), (1, 0)]) == {0: 0, 1: 1}
