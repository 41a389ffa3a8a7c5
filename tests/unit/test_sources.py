"""Log/link sources: unit conversion at the boundary, compass indices, throttle selection, bad input."""

from __future__ import annotations

import math
import socket
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from magcomp.adapters import dialect
from magcomp.adapters.mavlink_source import load_log, open_source
from magcomp.adapters.message_convert import Counts, MessageConverter, PwmRecord
from magcomp.adapters.throttle import parse_throttle_source, pwm_to_01, resolve_throttle
from magcomp.core.types import (
    AttitudeSample,
    HeartbeatSample,
    ImuSample,
    MagSample,
    ParamSample,
    PowerSample,
    TemperatureSample,
    ThrottleSample,
)
from magcomp.errors import InputError

G = 9.80665


class TlogWriter:
    """Builds a .tlog (8-byte big-endian usec + MAVLink 2 packet) from magcomp-dialect message objects."""

    def __init__(self) -> None:
        self.mod = dialect.ensure_dialect()
        self.mav = self.mod.MAVLink(None, srcSystem=1, srcComponent=1)
        self.chunks: list[bytes] = []
        self.wall_us = 1_700_000_000_000_000

    def add(self, name: str, **fields: Any) -> bytes:
        cls = getattr(self.mod, f"MAVLink_{name.lower()}_message")
        pkt = bytes(cls(**fields).pack(self.mav))
        self.wall_us += 1000
        self.chunks.append(self.wall_us.to_bytes(8, "big") + pkt)
        return pkt

    def heartbeat(self, mav_type: int = 2, autopilot: int = 3) -> None:
        self.add(
            "HEARTBEAT",
            type=mav_type,
            autopilot=autopilot,
            base_mode=0,
            custom_mode=0,
            system_status=4,
            mavlink_version=3,
        )

    def raw_imu(
        self,
        t_us: int,
        acc_mg: tuple[int, int, int],
        gyro_mrad: tuple[int, int, int],
        mag: tuple[int, int, int],
        temperature_cdeg: int = 0,
    ) -> None:
        self.add(
            "RAW_IMU",
            time_usec=t_us,
            xacc=acc_mg[0],
            yacc=acc_mg[1],
            zacc=acc_mg[2],
            xgyro=gyro_mrad[0],
            ygyro=gyro_mrad[1],
            zgyro=gyro_mrad[2],
            xmag=mag[0],
            ymag=mag[1],
            zmag=mag[2],
            id=0,
            temperature=temperature_cdeg,
        )

    def scaled_imu(self, n: int, t_ms: int, mag: tuple[int, int, int]) -> None:
        name = "SCALED_IMU" if n == 1 else f"SCALED_IMU{n}"
        self.add(
            name,
            time_boot_ms=t_ms,
            xacc=0,
            yacc=0,
            zacc=-1000,
            xgyro=0,
            ygyro=0,
            zgyro=0,
            xmag=mag[0],
            ymag=mag[1],
            zmag=mag[2],
            temperature=0,
        )

    def servo(self, t_us: int, pwm: list[int]) -> None:
        pwm = pwm + [0] * (16 - len(pwm))
        self.add(
            "SERVO_OUTPUT_RAW", time_usec=t_us, port=0, **{f"servo{i + 1}_raw": v for i, v in enumerate(pwm)}
        )

    def param(self, name: str, value: float) -> None:
        self.add(
            "PARAM_VALUE",
            param_id=name.encode(),
            param_value=value,
            param_type=9,
            param_count=1,
            param_index=0,
        )

    def write(self, path: Path) -> Path:
        path.write_bytes(b"".join(self.chunks))
        return path


def _sys_status(w: TlogWriter, mv: int, ca: int) -> None:
    w.add(
        "SYS_STATUS",
        onboard_control_sensors_present=0,
        onboard_control_sensors_enabled=0,
        onboard_control_sensors_health=0,
        load=0,
        voltage_battery=mv,
        current_battery=ca,
        battery_remaining=50,
        drop_rate_comm=0,
        errors_comm=0,
        errors_count1=0,
        errors_count2=0,
        errors_count3=0,
        errors_count4=0,
    )


def _samples_of(path: Path, kind: type, **kw: Any) -> list[Any]:
    with open_source(path, **kw) as src:
        return [s for s in src.samples() if isinstance(s, kind)]


def test_raw_imu_units_mg_mrad_mgauss_to_si(tmp_path: Path) -> None:
    w = TlogWriter()
    w.raw_imu(2_500_000, (1000, -500, 250), (100, -2000, 35), (210, -35, 402), temperature_cdeg=4150)
    path = w.write(tmp_path / "imu.tlog")
    with open_source(path) as src:
        got = list(src.samples())
    imu = next(s for s in got if isinstance(s, ImuSample))
    mag = next(s for s in got if isinstance(s, MagSample))
    temp = next(s for s in got if isinstance(s, TemperatureSample))
    assert imu.t_s == pytest.approx(2.5) and mag.t_s == pytest.approx(2.5)
    np.testing.assert_allclose(imu.accel_b_m_s2, np.array([1.0, -0.5, 0.25]) * G, rtol=1e-12)
    np.testing.assert_allclose(imu.gyro_b_rad_s, [0.1, -2.0, 0.035], rtol=1e-12)
    np.testing.assert_array_equal(mag.field_b_mgauss, [210.0, -35.0, 402.0])
    assert mag.mag_index == 0 and temp.temperature_degc == pytest.approx(41.5)


def test_scaled_imu2_and_3_are_compasses_1_and_2_and_raw_imu_shadows_scaled_imu(tmp_path: Path) -> None:
    w = TlogWriter()
    for k in range(5):
        w.raw_imu(1_000_000 + 20_000 * k, (0, 0, -1000), (0, 0, 0), (100, 0, 0))
        w.scaled_imu(1, 1000 + 20 * k, (999, 999, 999))  # same compass 0 in ArduPilot: must be ignored
        w.scaled_imu(2, 1000 + 20 * k, (0, 200, 0))
        w.scaled_imu(3, 1000 + 20 * k, (0, 0, 300))
    path = w.write(tmp_path / "mags.tlog")
    mags = _samples_of(path, MagSample)
    by_index = {i: [m for m in mags if m.mag_index == i] for i in (0, 1, 2)}
    assert [len(v) for v in by_index.values()] == [5, 5, 5]
    np.testing.assert_array_equal(by_index[0][0].field_b_mgauss, [100, 0, 0])
    np.testing.assert_array_equal(by_index[1][0].field_b_mgauss, [0, 200, 0])
    np.testing.assert_array_equal(by_index[2][0].field_b_mgauss, [0, 0, 300])
    assert len(_samples_of(path, MagSample, mag_index=2)) == 5
    data = load_log(path)
    assert sorted(data.mag) == [0, 1, 2] and len(data.mag[0]) == 5
    assert np.all(data.mag[0].values[:, 0] == 100)  # RAW_IMU, not SCALED_IMU
    assert data.counts["scaled_imu_shadowed"] == 5


def _quad_log(tmp_path: Path, *, mav_type: int, params: dict[str, float]) -> Path:
    w = TlogWriter()
    w.heartbeat(mav_type)
    for name, value in params.items():
        w.param(name, value)
    w.raw_imu(1_000_000, (0, 0, -1000), (0, 0, 0), (100, 0, 0))
    # channels 1-4: 1100/1200/1300/1400, 5: 1900, 6-8: 1500
    w.servo(1_000_000, [1100, 1200, 1300, 1400, 1900, 1500, 1500, 1500])
    w.add("VFR_HUD", airspeed=0.0, groundspeed=0.0, heading=0, throttle=42, alt=0.0, climb=0.0)
    return w.write(tmp_path / "thr.tlog")


def test_auto_throttle_multirotor_without_params_is_mean_of_channels_1_to_4(tmp_path: Path) -> None:
    path = _quad_log(tmp_path, mav_type=2, params={})
    thr = _samples_of(path, ThrottleSample)
    assert len(thr) == 1 and thr[0].source == "motors:1,2,3,4"
    assert thr[0].throttle_01 == pytest.approx(0.25)  # mean of 0.1, 0.2, 0.3, 0.4
    np.testing.assert_allclose(thr[0].motors_01, [0.1, 0.2, 0.3, 0.4])


def test_auto_throttle_hexa_uses_servo_functions_and_mot_pwm_range(tmp_path: Path) -> None:
    params = {f"SERVO{n}_FUNCTION": 0.0 for n in range(1, 9)}
    params.update(
        {"SERVO5_FUNCTION": 33.0, "SERVO6_FUNCTION": 34.0, "MOT_PWM_MIN": 1100.0, "MOT_PWM_MAX": 1900.0}
    )
    path = _quad_log(tmp_path, mav_type=13, params=params)
    data = load_log(path)
    assert data.throttle_source == "motors:5,6"
    # ch5 1900 -> 1.0, ch6 1500 -> 0.5 with 1100-1900
    np.testing.assert_allclose(data.throttle_01.values, [0.75])
    np.testing.assert_allclose(data.motors_01.values, [[1.0, 0.5]])


def test_auto_throttle_fixed_wing_uses_throttle_function_channel(tmp_path: Path) -> None:
    params = {"SERVO5_FUNCTION": 70.0, "SERVO5_MIN": 1000.0, "SERVO5_MAX": 1900.0}
    data = load_log(_quad_log(tmp_path, mav_type=1, params=params))
    assert data.throttle_source == "servo:5"
    np.testing.assert_allclose(data.throttle_01.values, [1.0])
    data3 = load_log(_quad_log(tmp_path, mav_type=1, params={}), "auto")
    assert data3.throttle_source == "servo:3"
    np.testing.assert_allclose(data3.throttle_01.values, [0.3])


def test_auto_throttle_unknown_vehicle_falls_back_to_vfr_hud_and_explicit_sources_work(
    tmp_path: Path,
) -> None:
    path = _quad_log(tmp_path, mav_type=10, params={})  # ground rover: not a multirotor or plane
    data = load_log(path)
    assert data.throttle_source == "vfr_hud"
    np.testing.assert_allclose(data.throttle_01.values, [0.42])
    assert load_log(path, "servo:2").throttle_01.values[0] == pytest.approx(0.2)
    assert load_log(path, "motors").throttle_01.values[0] == pytest.approx(0.25)


def test_throttle_source_parsing_and_pwm_clipping() -> None:
    assert str(parse_throttle_source("SERVO:3")) == "servo:3"
    for bad in ("servo", "servo:x", "rc:0", "thrust"):
        with pytest.raises(InputError):
            parse_throttle_source(bad)
    assert pwm_to_01(900, 1000, 2000) == 0.0 and pwm_to_01(2100, 1000, 2000) == 1.0
    assert resolve_throttle("auto", -1, {}, frozenset()) is None


def test_sys_status_units_and_unknown_current_is_nan(tmp_path: Path) -> None:
    w = TlogWriter()
    w.raw_imu(1_000_000, (0, 0, -1000), (0, 0, 0), (1, 2, 3))
    _sys_status(w, 16_540, 2_744)
    _sys_status(w, 15_100, -1)
    power = _samples_of(w.write(tmp_path / "p.tlog"), PowerSample)
    assert power[0].voltage_v == pytest.approx(16.54) and power[0].current_a == pytest.approx(27.44)
    assert power[1].voltage_v == pytest.approx(15.1) and math.isnan(power[1].current_a)
    assert power[0].t_s == pytest.approx(1.0)  # no timestamp of its own: the latest source time


def test_attitude_and_heartbeat_samples(tmp_path: Path) -> None:
    w = TlogWriter()
    w.heartbeat(mav_type=6, autopilot=8)  # a GCS: ignored
    w.heartbeat(mav_type=2)
    w.add(
        "ATTITUDE",
        time_boot_ms=5000,
        roll=0.1,
        pitch=-0.2,
        yaw=3.0,
        rollspeed=0.01,
        pitchspeed=0.02,
        yawspeed=0.03,
    )
    w.add(
        "ATTITUDE",
        time_boot_ms=5020,
        roll=float("nan"),
        pitch=0.0,
        yaw=0.0,
        rollspeed=0.0,
        pitchspeed=0.0,
        yawspeed=0.0,
    )
    path = w.write(tmp_path / "att.tlog")
    with open_source(path) as src:
        got = list(src.samples())
        counts = dict(src.counts)
    hbs = [s for s in got if isinstance(s, HeartbeatSample)]
    atts = [s for s in got if isinstance(s, AttitudeSample)]
    assert [h.vehicle_type for h in hbs] == [2]
    assert len(atts) == 1 and atts[0].t_s == pytest.approx(5.0) and atts[0].yaw_rad == pytest.approx(3.0)
    np.testing.assert_allclose(atts[0].rates_b_rad_s, [0.01, 0.02, 0.03], rtol=1e-6)
    assert counts["nonfinite"] == 1


def test_reboot_keeps_time_monotonic_and_small_step_back_is_dropped(tmp_path: Path) -> None:
    w = TlogWriter()
    for t_ms in (100_000, 100_020, 100_010, 100_040):  # 100_010: a step back within the stream
        w.scaled_imu(2, t_ms, (1, 1, 1))
    for t_ms in (500, 520, 540):  # autopilot rebooted (the first new time is believed once confirmed)
        w.scaled_imu(2, t_ms, (1, 1, 1))
    path = w.write(tmp_path / "reboot.tlog")
    with open_source(path) as src:
        t = [s.t_s for s in src.samples() if isinstance(s, MagSample)]
        counts = dict(src.counts)
    assert counts["clock_resets"] == 1 and counts["time_backwards"] == 1
    assert len(t) == 5 and np.all(np.diff(t) >= 0)
    assert t[-1] - t[-2] == pytest.approx(0.02)


def _write(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def _good_log(n: int = 20) -> tuple[TlogWriter, list[bytes]]:
    w = TlogWriter()
    for k in range(n):
        w.scaled_imu(2, 1000 + 10 * k, (k + 1, 0, 0))  # (0, 0, 0) would be 'no data'
    return w, w.chunks


def test_corrupt_crc_is_counted_and_skipped(tmp_path: Path) -> None:
    _, chunks = _good_log()
    bad = bytearray(chunks[5])
    bad[8 + 12] ^= 0xFF  # a payload byte
    chunks[5] = bytes(bad)
    with open_source(_write(tmp_path, "crc.tlog", b"".join(chunks))) as src:
        mags = [s for s in src.samples() if isinstance(s, MagSample)]
        assert src.counts["bad_crc"] == 1
    assert len(mags) == 19 and 6.0 not in [m.field_b_mgauss[0] for m in mags]


def test_garbage_between_messages_and_truncated_tail_are_counted(tmp_path: Path) -> None:
    _, chunks = _good_log()
    rng = np.random.default_rng(3)
    junk = bytes(rng.integers(0, 256, 40, dtype=np.uint8)).replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x01")
    data = b"".join(chunks[:10]) + junk + b"".join(chunks[10:]) + chunks[0][:20]
    with open_source(_write(tmp_path, "junk.tlog", data)) as src:
        mags = [s for s in src.samples() if isinstance(s, MagSample)]
        assert src.counts["garbage_bytes"] >= 40 and src.counts["truncated"] == 1
    assert len(mags) == 20


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("empty.tlog", b"", "empty file"),
        ("notes.tlog", b"this is a text file\nnot a log\n" * 20, "text file"),
        ("noise.tlog", bytes(range(0, 250)) * 4, "no valid MAVLink"),
        ("empty.bin", b"", "empty file"),
        ("noise.bin", bytes(np.random.default_rng(5).integers(0, 253, 3000, dtype=np.uint8)), "DataFlash"),
        ("prose.log", b"hello, world\nnothing here\n", "DataFlash"),
        # ArduCopter 3.0's text log: GPS with the time of week but no week (pymavlink's clock raised a
        # TypeError building its time base: a traceback, ArduPilot LogAnalyzer's robert_lefebvre_octo_PM.log)
        ("old_gps.log", b"FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns\n"
         b"FMT, 130, 10, GPS, BI, Status,TimeMS\nGPS, 3, 1000\nGPS, 3, 1200\n", "DataFlash"),
    ],
)
def test_unreadable_inputs_raise_one_line_input_error(
    tmp_path: Path, name: str, content: bytes, message: str
) -> None:
    path = _write(tmp_path, name, content)
    with pytest.raises(InputError, match=message) as info:
        load_log(path)
    assert "\n" not in str(info.value)


def test_missing_file_is_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        load_log(tmp_path / "nope.tlog")


def test_live_udp_link_yields_samples(tmp_path: Path) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    src = open_source(f"udpin:127.0.0.1:{port}", live_timeout_s=0.05)
    w = TlogWriter()
    w.scaled_imu(2, 7000, (5, 6, 7))
    pkt = w.chunks[-1][8:]
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    got: list[MagSample] = []
    try:
        stream = src.samples()
        for _ in range(40):  # bounded: re-send until the first sample arrives
            sender.sendto(pkt, ("127.0.0.1", port))
            s = next(stream)
            if isinstance(s, MagSample):
                got.append(s)
                break
    finally:
        sender.close()
        src.close()
    assert got and got[0].mag_index == 1 and got[0].t_s == pytest.approx(7.0)


def test_fast_tlog_reader_sees_every_message_mavutil_sees(tmp_path: Path) -> None:
    w = TlogWriter()
    for k in range(3000):
        w.raw_imu(k * 20_000, (0, 0, -1000), (1, 2, 3), (100, 50, 400))
        w.add(
            "ATTITUDE",
            time_boot_ms=k * 20,
            roll=0.0,
            pitch=0.0,
            yaw=0.0,
            rollspeed=0.0,
            pitchspeed=0.0,
            yawspeed=0.0,
        )
        w.add(  # a message the reader does not need
            "LOCAL_POSITION_NED", time_boot_ms=k * 20, x=0.0, y=0.0, z=0.0, vx=0.0, vy=0.0, vz=0.0
        )
    path = w.write(tmp_path / "speed.tlog")
    from pymavlink import mavutil

    def ours() -> int:
        with open_source(path) as src:
            return sum(1 for _ in src.samples())

    def mavutil_loop() -> int:
        conn = mavutil.mavlink_connection(str(path), dialect="magcomp")
        n = 0
        while conn.recv_msg() is not None:
            n += 1
        conn.close()
        return n

    assert ours() == 9000 and mavutil_loop() == 9000


def _bytewise(value: int) -> float:
    """An INT32 parameter as PX4 sends it: its bytes copied into PARAM_VALUE's float."""
    import struct

    return float(struct.unpack("<f", struct.pack("<i", value))[0])


@pytest.mark.parametrize("heartbeat_first", [True, False])
def test_px4_integer_parameters_arrive_bytewise_and_are_decoded(
    tmp_path: Path, heartbeat_first: bool
) -> None:
    """PX4 copies an integer parameter's bytes into PARAM_VALUE (its PWM_MAIN_FUNCn and PWM_MAIN_MINn/MAXn
    are INT32): read as floats they are ~1e-42, which made every PWM range 1e-42 wide and the motors of
    outputs 5-6 unknown. Decoded, outputs 5-6 are the motors, scaled 1100-1900 us."""
    w = TlogWriter()
    if heartbeat_first:
        w.heartbeat(2, autopilot=12)  # MAV_AUTOPILOT_PX4
    ints = {"PWM_MAIN_FUNC5": 101, "PWM_MAIN_FUNC6": 102, "PWM_MAIN_MIN5": 1100, "PWM_MAIN_MAX5": 1900,
            "PWM_MAIN_MIN6": 1100, "PWM_MAIN_MAX6": 1900}  # fmt: skip
    for name, value in ints.items():
        w.add("PARAM_VALUE", param_id=name.encode(), param_value=_bytewise(value), param_type=6,
              param_count=len(ints) + 1, param_index=0)  # fmt: skip
    w.param("MC_ROLL_P", 6.5)  # a REAL32 parameter stays as it is
    if not heartbeat_first:
        w.heartbeat(2, autopilot=12)
    w.raw_imu(1_000_000, (0, 0, -1000), (0, 0, 0), (100, 0, 0))
    w.servo(1_000_000, [900, 900, 900, 900, 1900, 1500, 900, 900])
    path = w.write(tmp_path / "px4.tlog")
    params = {p.name: p.value for p in _samples_of(path, ParamSample)}
    assert params == {**{k: float(v) for k, v in ints.items()}, "MC_ROLL_P": pytest.approx(6.5)}
    data = load_log(path)
    assert data.throttle_source == "motors:5,6"
    np.testing.assert_allclose(data.motors_01.values, [[1.0, 0.5]])


def test_servo_output_raw_channels_per_port_and_extension() -> None:
    """SERVO_OUTPUT_RAW to PWM by channel: servo1..8 of port p are channels 8p+1..8p+8, port 0's servo9..16
    extension channels 9..16 where the sender fills it (0: not filled), and the channels seen stay known."""
    mod = dialect.ensure_dialect()
    conv = MessageConverter(Counts(), mag_index=None, undo_motor_comp=False)

    def servo(t_us: int, port: int, pwm: list[int]) -> dict[int, float]:
        fields = {f"servo{i + 1}_raw": v for i, v in enumerate(pwm + [0] * (16 - len(pwm)))}
        out = conv.mavlink(mod.MAVLink_servo_output_raw_message(time_usec=t_us, port=port, **fields))
        assert [name for name, _ in out] == ["SERVO_OUTPUT_RAW"]
        rec = out[0][1]
        assert isinstance(rec, PwmRecord) and rec.kind == "servo"
        return rec.pwm_us

    first = [1100 + 10 * i for i in range(8)]  # servo1..8, every one distinct
    assert servo(1_000_000, 0, first) == {i + 1: float(v) for i, v in enumerate(first)}
    ext = [1200 + 10 * i for i in range(8)] + [0, 1950, 0, 0, 0, 0, 0, 1010]  # servo10 and servo16 filled
    got = servo(1_020_000, 0, ext)
    assert got == {**{i + 1: float(v) for i, v in enumerate(ext[:8])}, 10: 1950.0, 16: 1010.0}
    port1 = [1500 + 10 * i for i in range(8)] + [1234] * 8  # port 1: channels 9..16; no extension beyond
    got = servo(1_040_000, 1, port1)
    want = {i + 1: float(v) for i, v in enumerate(ext[:8])}
    want |= {i + 9: float(v) for i, v in enumerate(port1[:8])}  # port 0's extension overwritten
    assert got == want
    # a message class without the extension (MAVLink 1 era): servo1..8 only
    old = SimpleNamespace(time_usec=1_060_000, port=0, **{f"servo{i + 1}_raw": 1700 + i for i in range(8)})
    old.get_type = lambda: "SERVO_OUTPUT_RAW"
    (_, rec), = conv.mavlink(old)
    assert isinstance(rec, PwmRecord)
    assert rec.pwm_us == want | {i + 1: float(1700 + i) for i in range(8)}
