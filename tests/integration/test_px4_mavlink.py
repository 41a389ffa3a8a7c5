"""PX4 over MAVLink: HIGHRES_IMU (gauss), SCALED_IMU2, ATTITUDE_QUATERNION, ACTUATOR_OUTPUT_STATUS,
BATTERY_STATUS, GPS_RAW_INT, SYSTEM_TIME; the autopilot is told by its HEARTBEAT, nothing is configured."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import load_config
from magcomp.adapters.mavlink_emit import stream_to_link, write_tlog
from magcomp.adapters.mavlink_source import load_log, open_source
from magcomp.core.types import (
    AttitudeSample,
    ImuSample,
    MagSample,
    PositionSample,
    ThrottleSample,
    TimeSample,
)
from magcomp.service.daemon import Daemon
from magcomp.service.demo import free_udp_port
from magcomp.service.replay import replay_log
from magcomp.sim import SimConfig, simulate
from tests.configs import QUICK_CALIBRATION
from tests.unit.test_sources import TlogWriter
from tests.waiting import running_daemon


def _wrapped(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def test_px4_tlog_units_and_replay_equal_the_ardupilot_twin(tmp_path: Path) -> None:
    result = simulate(SimConfig(scenario="paper", duration_s=40.0, seed=5))
    ap, px = tmp_path / "ap.tlog", tmp_path / "px4.tlog"
    write_tlog(result, ap)
    write_tlog(result, px, flavour="px4")
    data = load_log(px)
    assert data.autopilot == 12 and sorted(data.mag) == [0, 1]
    s = result.samples
    np.testing.assert_allclose(data.mag[0].values, np.round(s.mag_mgauss[0]), atol=1e-3)  # gauss -> mgauss
    np.testing.assert_allclose(data.gyro_rad_s, s.gyro_rad_s[0], atol=6e-4)  # rad/s, 1 mrad/s quantum
    np.testing.assert_allclose(data.accel_m_s2, s.accel_m_s2[0], atol=6e-3)  # m/s^2, 1 mG quantum
    assert data.throttle_source == "servo:3"  # fixed wing: the PWM_MAIN_FUNCn Motor 1 output
    loc = result.config.location
    assert len(data.position) > 0 and np.all(np.abs(data.position.values[:, 0] - loc.lat_deg) < 1e-6)
    assert abs(data.decimal_year - loc.decimal_year) < 0.01
    cfg = load_config(None)
    a = replay_log(ap, cfg, keep_estimates=True).estimates
    b = replay_log(px, cfg, keep_estimates=True).estimates
    assert len(a) == len(b) == 2 * s.t_s.size
    for idx in (0, 1):
        ha = np.array([e.heading_deg for e in a if e.mag_index == idx])
        hb = np.array([e.heading_deg for e in b if e.mag_index == idx])
        assert np.max(np.abs(_wrapped(ha - hb))) < 0.01  # float32 gauss vs integer mgauss only
    assert np.linalg.norm(b[-2].theta_mgauss) > 10.0  # theta was learned from the PX4 stream


def test_highres_imu_fields_updated_and_shadowing(tmp_path: Path) -> None:
    w = TlogWriter()
    w.heartbeat(mav_type=2, autopilot=12)
    for k in range(10):
        t_us = 1_000_000 + 20_000 * k
        mag_new = 0x1C0 if k % 5 == 0 else 0  # a new compass sample every 5th message only
        w.add("HIGHRES_IMU", time_usec=t_us, xacc=0.0, yacc=0.0, zacc=-9.8, xgyro=0.01, ygyro=0.0, zgyro=0.0,
              xmag=0.21, ymag=-0.02, zmag=0.43, abs_pressure=1013.0, diff_pressure=0.0, pressure_alt=0.0,
              temperature=35.0, fields_updated=0x3F | mag_new | 0x1000, id=0)  # fmt: skip
        c, sn = float(np.cos(0.25)), float(np.sin(0.25))
        w.add("ATTITUDE_QUATERNION", time_boot_ms=t_us // 1000, q1=c, q2=0.0, q3=0.0, q4=sn,
              rollspeed=0.0, pitchspeed=0.0, yawspeed=0.0, repr_offset_q=[0.0] * 4)  # fmt: skip
        w.add("ACTUATOR_OUTPUT_STATUS", time_usec=t_us, active=0x0F, actuator=[1500.0] * 4 + [900.0] * 28)
    w.param("PWM_MAIN_FUNC1", 101)  # after the first outputs: auto throttle re-resolves on parameters
    w.add("SYSTEM_TIME", time_unix_usec=1_735_689_600_000_000, time_boot_ms=1200)  # 2025-01-01
    path = w.write(tmp_path / "px4.tlog")
    with open_source(path) as src:
        samples = list(src.samples())
    mags = [s for s in samples if isinstance(s, MagSample)]
    assert len(mags) == 2 and mags[0].field_b_mgauss == pytest.approx([210.0, -20.0, 430.0], abs=1e-3)
    assert len([s for s in samples if isinstance(s, ImuSample)]) == 10
    att = [s for s in samples if isinstance(s, AttitudeSample)]
    assert len(att) == 10 and att[0].yaw_rad == pytest.approx(0.5, abs=1e-6)  # q = (cos 0.25, 0, 0, sin 0.25)
    thr = [s for s in samples if isinstance(s, ThrottleSample)]
    assert thr and thr[0].throttle_01 == pytest.approx(0.5)  # mean of outputs 1-4 at 1500 us of 1000-2000
    times = [s for s in samples if isinstance(s, TimeSample)]
    assert len(times) == 1 and times[0].decimal_year == pytest.approx(2025.0, abs=1e-6)
    assert not [s for s in samples if isinstance(s, PositionSample)]

    # a compass in SCALED_IMU now shadows HIGHRES_IMU's; SCALED_IMU adds no second IMU 0 stream
    w.scaled_imu(1, 1300, (220, -30, 440))
    w.add("HIGHRES_IMU", time_usec=1_400_000, xacc=0.0, yacc=0.0, zacc=-9.8, xgyro=0.0, ygyro=0.0, zgyro=0.0,
          xmag=0.21, ymag=-0.02, zmag=0.43, abs_pressure=0.0, diff_pressure=0.0, pressure_alt=0.0,
          temperature=35.0, fields_updated=0x1FF, id=0)  # fmt: skip
    with open_source(w.write(tmp_path / "px4b.tlog")) as src:
        later = [s for s in src.samples() if isinstance(s, MagSample | ImuSample) and s.t_s >= 1.3]
        assert src.counts["highres_mag_shadowed"] == 1
    assert [type(s).__name__ for s in later] == ["WireMagSample", "WireImuSample"]
    assert later[0].field_b_mgauss == pytest.approx([220.0, -30.0, 440.0])  # type: ignore[union-attr]


@pytest.mark.slow
def test_live_px4_stream_over_loopback_udp_publishes_corrected_headings() -> None:
    result = simulate(SimConfig(scenario="paper", duration_s=40.0, seed=3))
    port = free_udp_port()
    ests: list[object] = []
    daemon = Daemon(f"udpin:127.0.0.1:{port}", QUICK_CALIBRATION, on_estimate=ests.append)
    with running_daemon(daemon, join_s=10.0) as worker:
        link = stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=20.0, flavour="px4")
        n_mag = result.samples.t_s.shape[0] * result.samples.mag_mgauss.shape[0]
        deadline = time.monotonic() + 10.0  # a loaded machine may drop a datagram: not all are awaited
        while len(ests) < n_mag and time.monotonic() < deadline:
            time.sleep(0.05)
    assert not worker.is_alive()
    # one corrected heading per compass sample, both compasses (a loaded machine may drop a datagram)
    assert 0.98 * n_mag <= len(ests) <= n_mag
    assert link.received.get("MAGCOMP_HEADING", 0) > 0  # sent back to the PX4 vehicle too
    last0 = [e for e in ests if e.mag_index == 0][-1]  # type: ignore[attr-defined]
    truth = np.array(result.compasses[0].theta_mgauss)
    assert np.linalg.norm(last0.theta_mgauss - truth) < 0.5 * np.linalg.norm(truth)  # type: ignore[attr-defined]
    corrected = [e for e in ests if e.heading_deg != e.heading_raw_deg]  # type: ignore[attr-defined]
    assert len(corrected) > 0.2 * n_mag
