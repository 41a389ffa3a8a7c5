"""Simulator -> MAVLink tlog -> decoders: the laws are recovered statistically from the emitted messages
(decoded with pymavlink), the project's reader gets the same samples back, and mavutil reads it cleanly."""

from __future__ import annotations

import datetime as _dt
import json
import socket
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.adapters.mavlink_emit import stream_to_link, truth_paths, write_tlog, write_truth
from magcomp.sim import SimConfig, SimResult, simulate

G = 9.80665


def decode(path: Path) -> dict[str, list[Any]]:
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(path))
    out: dict[str, list[Any]] = {}
    while (msg := conn.recv_msg()) is not None:
        out.setdefault(msg.get_type(), []).append(msg)
    conn.close()
    return out


def write(tmp: Path, name: str, cfg: SimConfig) -> tuple[SimResult, Path, dict[str, list[Any]]]:
    result = simulate(cfg, np.random.default_rng(cfg.seed))
    path = tmp / f"{name}.tlog"
    write_tlog(result, path)
    return result, path, decode(path)


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimResult, Path, dict[str, list[Any]]]:
    return write(
        tmp_path_factory.mktemp("bench"), "bench", SimConfig(scenario="bench", duration_s=60.0, seed=3)
    )


@pytest.fixture(scope="module")
def tumble(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimResult, Path, dict[str, list[Any]]]:
    return write(
        tmp_path_factory.mktemp("tumble"), "tumble", SimConfig(scenario="tumble", duration_s=40.0, seed=5)
    )


def mag_of(msgs: list[Any]) -> np.ndarray:
    return np.array([[m.xmag, m.ymag, m.zmag] for m in msgs], dtype=float)


def throttle_at(servo: list[Any], t_s: np.ndarray) -> np.ndarray:
    """Logged throttle (SERVO3, fixed wing) held until the next SERVO_OUTPUT_RAW, at times t_s."""
    ts = np.array([m.time_usec for m in servo]) * 1e-6
    thr = (np.array([m.servo3_raw for m in servo]) - 1000.0) / 1000.0
    i = np.clip(np.searchsorted(ts, t_s + 1e-9, side="right") - 1, 0, len(ts) - 1)
    return thr[i]


def test_gyro_noise_sigma_recovered_from_raw_imu(bench: tuple[SimResult, Path, dict[str, list[Any]]]) -> None:
    result, _, msgs = bench
    gyro = np.array([[m.xgyro, m.ygyro, m.zgyro] for m in msgs["RAW_IMU"]]) * 1e-3  # mrad/s
    c = result.compasses[0]
    expected = np.sqrt(c.gyro_noise_rad_s**2 + (1e-3) ** 2 / 12.0)  # noise + 1 mrad/s quantisation
    np.testing.assert_allclose(gyro.std(axis=0), expected, rtol=0.05)
    np.testing.assert_allclose(gyro.mean(axis=0), c.gyro_bias_rad_s, atol=4 * expected / np.sqrt(len(gyro)))


def test_mag_noise_and_bias_law_theta_delta_squared_on_bench_sweep_eq11(
    bench: tuple[SimResult, Path, dict[str, list[Any]]],
) -> None:
    result, _, msgs = bench
    raw = msgs["RAW_IMU"]
    t = np.array([m.time_usec for m in raw]) * 1e-6
    mag = mag_of(raw)
    thr = throttle_at(msgs["SERVO_OUTPUT_RAW"], t)
    c = result.compasses[0]
    # stationary: v = (K u + b) + (K theta) delta^2 + noise, eqs. (1), (11), (14a)
    x = np.column_stack([thr**2, np.ones_like(thr)])
    beta, *_ = np.linalg.lstsq(x, mag, rcond=None)
    np.testing.assert_allclose(beta[0], c.theta_raw_mgauss, atol=2.0)
    resid = mag - x @ beta
    sigma_hat = np.sqrt((resid**2).sum(axis=0) / (len(t) - 2))  # eq. (15)
    expected = np.sqrt(c.noise_mgauss**2 + c.lsb_mgauss**2 / 12.0 + 1.0 / 12.0)
    np.testing.assert_allclose(sigma_hat, expected, rtol=0.06)
    # a linear-in-throttle model fits clearly worse on the axis with most signal
    ax = int(np.argmax(np.abs(c.theta_raw_mgauss)))
    x1 = np.column_stack([thr, np.ones_like(thr)])
    r1 = mag[:, ax] - x1 @ np.linalg.lstsq(x1, mag[:, ax], rcond=None)[0]
    assert r1.std() > 1.1 * resid[:, ax].std()


def test_current_reported_is_throttle_squared_times_imax(
    bench: tuple[SimResult, Path, dict[str, list[Any]]],
) -> None:
    _, _, msgs = bench
    sys_status = msgs["SYS_STATUS"]
    hud = msgs["VFR_HUD"]
    assert len(sys_status) == len(hud)
    current = np.array([m.current_battery for m in sys_status]) * 0.01
    thr = np.array([m.throttle for m in hud]) / 100.0
    np.testing.assert_allclose(current, 20.0 * thr**2, atol=0.25)
    volts = np.array([m.voltage_battery for m in sys_status]) * 1e-3
    assert volts[thr == 1.0].max() < volts[thr == 0.0].min()  # sag under load


def test_field_norm_at_zero_throttle_matches_wmm_after_removing_k_and_b(
    tumble: tuple[SimResult, Path, dict[str, list[Any]]],
) -> None:
    from magcomp.geomag import earth_field_ned_mgauss

    result, path, msgs = tumble
    truth = json.loads(truth_paths(path)[0].read_text()) if truth_paths(path)[0].exists() else None
    assert truth is None  # write_tlog alone writes no truth
    loc = result.config.location
    wmm = float(np.linalg.norm(earth_field_ned_mgauss(loc.lat_deg, loc.lon_deg, loc.alt_m, loc.decimal_year)))
    for j, name in enumerate(("RAW_IMU", "SCALED_IMU2")):
        c = result.compasses[j]
        v = mag_of(msgs[name])
        u = np.linalg.solve(c.k_matrix, (v - c.b_mgauss).T).T  # eq. (2): u = L v - d
        norms = np.linalg.norm(u, axis=1)
        assert norms.mean() == pytest.approx(wmm, abs=1.0 + 3 * c.noise_mgauss / np.sqrt(len(norms)))
        assert norms.std() == pytest.approx(c.noise_mgauss, rel=0.15)
        assert np.linalg.norm(v, axis=1).std() > 5 * c.noise_mgauss  # raw: an off-centre ellipsoid


def test_round_trip_through_the_project_reader_gives_the_same_samples(
    bench: tuple[SimResult, Path, dict[str, list[Any]]],
) -> None:
    mavlink_source = pytest.importorskip("magcomp.adapters.mavlink_source")
    result, path, _ = bench
    s = result.samples
    log = mavlink_source.load_log(path)
    np.testing.assert_allclose(log.mag[0].t_s, s.t_s, atol=1e-6)
    np.testing.assert_allclose(log.mag[0].values, s.mag_mgauss[0], atol=1e-9)
    np.testing.assert_allclose(log.mag[1].values, s.mag_mgauss[1], atol=1e-9)
    np.testing.assert_allclose(log.imu_t_s, s.t_s, atol=1e-6)
    np.testing.assert_allclose(log.gyro_rad_s, s.gyro_rad_s[0], atol=1e-9)
    np.testing.assert_allclose(log.accel_m_s2, s.accel_m_s2[0], atol=1e-6)
    thr_t = log.throttle_01.t_s
    np.testing.assert_allclose(log.throttle_01.values, np.interp(thr_t, s.t_s, s.throttle_01), atol=1.5e-3)
    np.testing.assert_allclose(
        log.current_a.values, np.interp(log.current_a.t_s, s.t_s, s.current_a), atol=0.011
    )
    np.testing.assert_allclose(
        log.voltage_v.values, np.interp(log.voltage_v.t_s, s.t_s, s.voltage_v), atol=0.002
    )
    assert log.params["SERVO3_FUNCTION"] == 70.0
    assert log.vehicle_type == 1


def test_tlog_reads_cleanly_with_mavutil(bench: tuple[SimResult, Path, dict[str, list[Any]]]) -> None:
    from pymavlink import mavutil

    result, path, msgs = bench
    assert "BAD_DATA" not in msgs
    # the robust byte-level reader too, with header checks
    log = mavutil.mavlogfile(str(path), robust_parsing=True)
    n = 0
    stamps = []
    while (m := log.recv_msg()) is not None:
        assert m.get_type() != "BAD_DATA"
        stamps.append(m._timestamp)
        n += 1
    log.close()
    assert n == sum(len(v) for v in msgs.values())
    assert np.all(np.diff(stamps) >= 0.0)
    rates = result.config.rates
    dur = result.config.duration
    assert len(msgs["RAW_IMU"]) == pytest.approx(dur * rates.imu_hz, abs=1)
    assert len(msgs["ATTITUDE"]) == pytest.approx(dur * rates.attitude_hz, abs=1)
    assert len(msgs["SERVO_OUTPUT_RAW"]) == pytest.approx(dur * rates.servo_hz, abs=1)
    names = {m.param_id for m in msgs["PARAM_VALUE"]}
    assert {"SERVO3_FUNCTION", "SERVO3_MIN", "SERVO3_MAX"} <= names
    assert all(m.get_srcSystem() == 1 for m in msgs["HEARTBEAT"])


def test_effects_are_visible_in_the_emitted_field(tmp_path: Path) -> None:
    """time_skew and current_lag on a throttle step, measured from RAW_IMU vs SERVO_OUTPUT_RAW."""

    def edge_delay(effects: dict[str, float]) -> float:
        cfg = SimConfig(scenario="step", duration_s=10.0, seed=11, effects=effects, n_compasses=1)
        result, _, msgs = write(tmp_path, "step", cfg)
        raw = msgs["RAW_IMU"]
        t = np.array([m.time_usec for m in raw]) * 1e-6
        v = mag_of(raw)
        d = result.compasses[0].theta_raw_mgauss / np.linalg.norm(result.compasses[0].theta_raw_mgauss)
        proj = v @ d
        base = proj[t < result.t0_s + 3.5].mean()
        top = proj[t > result.t0_s + 8.0].mean()
        frac = (np.convolve(proj, np.ones(5) / 5, mode="same") - base) / (top - base)
        servo = msgs["SERVO_OUTPUT_RAW"]
        ts = np.array([m.time_usec for m in servo]) * 1e-6
        t_thr = ts[np.argmax(np.array([m.servo3_raw for m in servo]) > 1500)]
        return float(t[np.argmax(frac > 0.5)] - t_thr)

    base = edge_delay({})
    skewed = edge_delay({"time_skew": 0.4})
    lagged = edge_delay({"current_lag": 0.5})
    assert abs(base) < 0.06
    assert skewed - base == pytest.approx(0.4, abs=0.06)
    # half of the final bias when (1 - exp(-t / tau))^2 = 1/2: t = tau * ln(1 / (1 - 1/sqrt(2)))
    assert lagged - base == pytest.approx(0.5 * np.log(1.0 / (1.0 - 2**-0.5)), abs=0.08)


def test_truth_files_hold_theta_k_b_and_arrays(tmp_path: Path) -> None:
    cfg = SimConfig(scenario="step", duration_s=6.0, seed=2, effects={"current_lag": 0.2})
    result = simulate(cfg)
    out = tmp_path / "s.tlog"
    write_tlog(result, out)
    json_path, npz_path = write_truth(result, out)
    assert json_path.name == "s.truth.json" and npz_path.name == "s.truth.npz"
    truth = json.loads(json_path.read_text())
    assert truth["effects"] == {"current_lag": 0.2}
    np.testing.assert_allclose(truth["compasses"][0]["theta_mgauss"], result.compasses[0].theta_mgauss)
    np.testing.assert_allclose(truth["compasses"][1]["K"], result.compasses[1].k_matrix)
    arrays = np.load(npz_path)
    assert arrays["bias_mgauss"].shape == (2, result.samples.t_s.size, 3)
    np.testing.assert_allclose(arrays["t_s"], result.samples.t_s)


def test_live_link_plays_the_stream_and_records_what_comes_back() -> None:
    from pymavlink.dialects.v20 import ardupilotmega as apm

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.2)
    port = sock.getsockname()[1]
    got: list[int] = []
    stop = threading.Event()

    def peer() -> None:  # a ground station: counts datagrams, answers with its own heartbeats
        mav = apm.MAVLink(None, srcSystem=255, srcComponent=190)
        replies = 0
        while not stop.is_set():
            try:
                data, addr = sock.recvfrom(65536)
            except TimeoutError:
                continue
            got.append(len(data))
            if replies < 5:
                sock.sendto(apm.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(mav), addr)
                replies += 1

    th = threading.Thread(target=peer, daemon=True)
    th.start()
    try:
        result = simulate(SimConfig(scenario="step", duration_s=3.0, seed=1, n_compasses=1))
        report = stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=20.0)
    finally:
        stop.set()
        th.join(timeout=2.0)
        sock.close()
    assert report.sent > 300
    assert report.completed
    assert len(got) == report.sent
    assert report.received.get("HEARTBEAT", 0) >= 1
    assert report.wall_s < 10.0 * 3.0 / 20.0 + 2.0  # paced, not real time


# --- ordinary flight and variation knobs (issues 9 and 10) ------------------------------------------------


def ordinary_tlog(
    tmp: Path, settings: list[str], duration_s: float = 20.0, seed: int = 2
) -> tuple[SimResult, Path, dict[str, list[Any]]]:
    from magcomp.sim.config import apply_settings

    cfg = apply_settings(SimConfig(scenario="ordinary", duration_s=duration_s, seed=seed), settings)
    result = simulate(cfg)
    path = tmp / "ordinary.tlog"
    write_tlog(result, path)
    write_truth(result, path)
    return result, path, decode(path)


def message_rate_hz(msgs: list[Any]) -> float:
    t = np.array(
        [m.time_usec * 1e-6 if hasattr(m, "time_usec") else m.time_boot_ms * 1e-3 for m in msgs], dtype=float
    )
    return (len(t) - 1) / (t[-1] - t[0])


@pytest.mark.parametrize(
    ("settings", "expected"),
    [
        (["telemetry_hz=1"], {"RAW_IMU": 1.0, "SCALED_IMU2": 1.0, "ATTITUDE": 1.0, "mag": 1.0}),
        (["telemetry_hz=10"], {"RAW_IMU": 10.0, "ATTITUDE": 10.0, "mag": 10.0}),
        ([], {"RAW_IMU": 50.0, "ATTITUDE": 25.0, "mag": 50.0}),
        (["raw_imu_hz=50", "mag_hz=10", "attitude_hz=1"], {"RAW_IMU": 50.0, "ATTITUDE": 1.0, "mag": 10.0}),
        (["raw_imu_hz=1", "attitude_hz=50"], {"RAW_IMU": 1.0, "ATTITUDE": 50.0, "mag": 1.0}),
        (
            ["mag_hz=100", "raw_imu_hz=100", "attitude_hz=10"],
            {"RAW_IMU": 100.0, "ATTITUDE": 10.0, "mag": 100.0},
        ),
        (
            ["raw_imu_hz=3", "attitude_hz=7", "gps_hz=2"],
            {"RAW_IMU": 3.0, "ATTITUDE": 7.0, "GPS_RAW_INT": 2.0},
        ),
    ],
)
def test_telemetry_rates_are_what_was_asked(
    tmp_path: Path, settings: list[str], expected: dict[str, float]
) -> None:
    _, _, msgs = ordinary_tlog(tmp_path, settings)
    for name, rate in expected.items():
        if name == "mag":  # distinct compass values inside RAW_IMU (a held value repeats)
            raw = msgs["RAW_IMU"]
            mag = mag_of(raw)
            changes = np.any(np.diff(mag, axis=0) != 0, axis=1)
            t = np.array([m.time_usec for m in raw]) * 1e-6
            got = (changes.sum()) / (t[-1] - t[0])
        else:
            got = message_rate_hz(msgs[name])
        assert got == pytest.approx(rate, rel=0.05), name


def test_ordinary_tlog_gps_position_time_and_wmm_field(tmp_path: Path) -> None:
    from magcomp.geomag import decimal_year, earth_field_ned_mgauss

    lat0, lon0, alt0, year = -33.87, 151.21, 40.0, 2027.25
    settings = [f"lat_deg={lat0}", f"lon_deg={lon0}", f"alt_m={alt0}", f"decimal_year={year}"]
    result, path, msgs = ordinary_tlog(tmp_path, settings, duration_s=60.0)
    gps = msgs["GPS_RAW_INT"]
    pos = msgs["GLOBAL_POSITION_INT"]
    assert {m.fix_type for m in gps} == {3}
    lat = np.array([m.lat for m in gps]) * 1e-7
    lon = np.array([m.lon for m in gps]) * 1e-7
    alt = np.array([m.alt for m in gps]) * 1e-3
    assert np.abs(lat - lat0).max() < 0.01 and np.abs(lon - lon0).max() < 0.01  # within ~1 km
    rel = np.array([m.relative_alt for m in pos]) * 1e-3
    np.testing.assert_allclose(alt - alt0, rel, atol=2e-3)
    assert rel.min() > -0.05 and rel.max() > 10.0 and abs(rel[-1]) < 0.05  # took off and landed
    # successive fixes move as the reported velocity says (NED, cm/s)
    t = np.array([m.time_boot_ms for m in pos]) * 1e-3
    north = np.radians(lat - lat0) * 6_378_137.0
    vn = np.array([m.vx for m in pos]) * 1e-2
    np.testing.assert_allclose(np.diff(north), 0.5 * (vn[1:] + vn[:-1]) * np.diff(t), atol=0.05)
    # SYSTEM_TIME: UTC at the configured date, a fixed offset from the boot clock
    st = msgs["SYSTEM_TIME"]
    offsets = np.array([m.time_unix_usec * 1e-6 - m.time_boot_ms * 1e-3 for m in st])
    assert np.ptp(offsets) < 2e-3
    when = _dt.datetime.fromtimestamp(st[0].time_unix_usec * 1e-6, tz=_dt.UTC)
    assert decimal_year(when) == pytest.approx(year, abs=1.0 / 365.0)
    # the simulated Earth field is the WMM at the position and date the log itself carries
    wmm = earth_field_ned_mgauss(float(lat[0]), float(lon[0]), float(alt[0]), decimal_year(when))
    truth = json.loads(truth_paths(path)[0].read_text())
    np.testing.assert_allclose(truth["earth_field_ned_mgauss"], wmm, atol=1.0)
    np.testing.assert_allclose(result.earth_field_ned_mgauss, wmm, atol=1.0)


def test_ordinary_tlog_carries_the_autopilot_calibration_and_truth_maps_it_back(tmp_path: Path) -> None:
    settings = [
        "mag_noise_scale=0",
        "mag_lsb_mgauss=0.01",
        "ap_cal_hard_iron_mgauss=25",
        "ap_cal_soft_iron=0.03",
    ]
    settings.append("n_compasses=3")
    _, path, msgs = ordinary_tlog(tmp_path, settings)
    params = {m.param_id: m.param_value for m in msgs["PARAM_VALUE"]}
    assert params["COMPASS_MOTCT"] == 0.0 and params["COMPASS_PRIMARY"] == 0.0
    truth = json.loads(truth_paths(path)[0].read_text())
    arrays = np.load(truth_paths(path)[1])
    raw_t = np.array([m.time_usec for m in msgs["RAW_IMU"]]) * 1e-6
    rows = np.searchsorted(arrays["t_s"], raw_t - 1e-7)
    for j, (name, suffix) in enumerate((("RAW_IMU", ""), ("SCALED_IMU2", "2"), ("SCALED_IMU3", "3"))):
        ofs = np.array([params[f"COMPASS_OFS{suffix}_{ax}"] for ax in "XYZ"])
        dia = [params[f"COMPASS_DIA{suffix}_{ax}"] for ax in "XYZ"]
        odi = [params[f"COMPASS_ODI{suffix}_{ax}"] for ax in "XYZ"]
        a = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
        logged = mag_of(msgs[name])
        raw = arrays["mag_sensor_mgauss"][j][rows]
        # ArduPilot's correction: field = A (raw + OFS), then whole mgauss on the link
        np.testing.assert_allclose(logged, (raw + ofs) @ a.T, atol=0.5 + 1e-3)
        frame = truth["compasses"][j]["logged_frame"]
        body = logged @ np.array(frame["L"]).T - np.array(frame["d_mgauss"])
        field = arrays["field_earth_b_mgauss"][rows] + arrays["bias_mgauss"][j][rows]
        assert np.abs(body - field).max() < 1.5  # 1 mgauss rounding through L
        assert np.linalg.norm(frame["autopilot"]["residual_hard_iron_mgauss"]) == pytest.approx(25.0)
    yaw_err = arrays["autopilot_yaw_error_deg"]
    att = np.array([m.yaw for m in msgs["ATTITUDE"]])
    assert np.abs(yaw_err).max() < 30.0 and att.size > 0


def test_pre_knob_outputs_are_unchanged(tmp_path: Path) -> None:
    """The shipped sample logs (scripts/make_replay_logs.py) regenerate byte for byte: the knobs at their
    defaults change nothing in the existing scenarios."""
    root = Path(__file__).resolve().parents[2] / "replay_logs"
    if not (root / "bench_clean.tlog").exists():
        pytest.skip("replay_logs/ not in this checkout")
    for stem, cfg in (
        ("bench_clean", SimConfig(scenario="bench", vehicle="fixedwing", duration_s=40.0, seed=1)),
        (
            "flight_multirotor_clean",
            SimConfig(scenario="flight", vehicle="multirotor", duration_s=45.0, seed=2),
        ),
    ):
        assert cfg.legacy
        result = simulate(cfg)
        path = tmp_path / f"{stem}.tlog"
        write_tlog(result, path)
        write_truth(result, path, single_precision=True)
        assert path.read_bytes() == (root / f"{stem}.tlog").read_bytes(), stem
        json_path = truth_paths(path)[0]
        assert json_path.read_text() == (root / json_path.name).read_text(), stem


def test_px4_flavour_follows_the_rate_knobs_and_the_flown_track(tmp_path: Path) -> None:
    from magcomp.sim.config import apply_settings

    cfg = apply_settings(SimConfig(scenario="ordinary", duration_s=40.0, seed=1), ["telemetry_hz=2"])
    result = simulate(cfg)
    path = tmp_path / "px4.tlog"
    write_tlog(result, path, flavour="px4")
    msgs = decode(path)
    assert message_rate_hz(msgs["HIGHRES_IMU"]) == pytest.approx(2.0, rel=0.05)
    lat = np.array([m.lat for m in msgs["GPS_RAW_INT"]]) * 1e-7
    assert np.ptp(lat) > 1e-6  # the fixes follow the vehicle, not the take-off point
