"""The simulator's MAVLink output: encode a :class:`~magcomp.sim.SimResult` as an ArduPilot-like stream,
write it as a ``.tlog`` (+ truth files), or play it to a live endpoint as a fake flight controller.

Conventions (ArduPilot, MAVLink 2, system 1 / component 1):
    PARAM_VALUE   SERVOn_FUNCTION/MIN/MAX (n = 1..8), BATT_CAPACITY, FRAME_CLASS once at the start
    HEARTBEAT     heartbeat_hz; MAV_TYPE_FIXED_WING or MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA
    RAW_IMU       imu_hz; time_usec since boot, accel mG, gyro mrad/s, mag mgauss, temp. cdegC (compass 0)
    SCALED_IMU2/3 imu_hz; the same units for compasses 1 and 2
    ATTITUDE      attitude_hz; the simulated autopilot's estimate (yaw from the uncompensated compass)
    SERVO_OUTPUT_RAW servo_hz; PWM 1000-2000: fixed wing elevons 1/2, throttle 3; quad motors 1-4
    RC_CHANNELS   rc_hz; throttle stick on channel 3
    VFR_HUD       vfr_hud_hz; heading, throttle %, speeds, altitude, climb
    SYS_STATUS, BATTERY_STATUS  power_hz; voltage mV, current cA, remaining %

Timestamps are the simulated boot clock (``SimResult.samples.t_s``); a tlog record's 8-byte big-endian
header is the UNIX time in microseconds = ``start_unix_s + t_s`` (stack-notes §2).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.files import write_file
from magcomp.adapters.sim_log_rows import (
    BATTERY_CAPACITY_MAH,
    body_rates,
    compass_params,
    default_start_unix_s,
    elevons_pwm,
    pwm_us,
    px4_motor_outputs,
    px4_outputs,
    quantised_imu,
    rate_indices,
    raw_imu_rows,
    servo_params,
    true_yaw_deg,
)
from magcomp.core.identity import uid2_bytes, uid64
from magcomp.core.types import STANDARD_GRAVITY_M_S2
from magcomp.errors import InputError
from magcomp.sim.simulate import SimResult

F64 = NDArray[np.float64]
#: names kept importable from here (they moved to :mod:`magcomp.adapters.sim_log_rows`)
__all__ = ["default_start_unix_s", "rate_indices"]
_rate_indices = rate_indices

MAV_TYPE_FIXED_WING = 1
MAV_TYPE_QUADROTOR = 2
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_STATE_ACTIVE = 4
MAV_PARAM_TYPE_REAL32 = 9
MAV_BATTERY_TYPE_LIPO = 1
MAV_BATTERY_CHARGE_STATE_OK = 1
SENSORS_PRESENT = 1 | 2 | 4 | 8 | (1 << 25)  # gyro, accel, mag, baro, battery
UINT16_UNUSED = 65535
INT16_UNKNOWN = 32767

@dataclass(frozen=True)
class LinkReport:
    """What a live run did: packets sent, messages received back (by type) and the first few of them."""

    url: str
    sent: int
    received: dict[str, int] = field(default_factory=dict)
    first_received: list[dict[str, Any]] = field(default_factory=list)
    wall_s: float = 0.0
    completed: bool = True


def _gps_messages(result: SimResult, start_unix_s: float) -> list[tuple[float, int, Any]]:
    """GPS_RAW_INT and GLOBAL_POSITION_INT at gps_hz, SYSTEM_TIME (UTC = start_unix_s + boot time) at
    system_time_hz. With yaw_source = truth, GPS_RAW_INT carries the (GPS) yaw."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    s = result.samples
    cfg = result.config
    gps = s.gps
    assert gps is not None
    n = s.t_s.size
    t = s.t_s
    alt0 = cfg.location.alt_m
    yaw_true_deg = true_yaw_deg(result)
    events: list[tuple[float, int, Any]] = []
    for i in rate_indices(n, cfg.rates.imu_hz, min(cfg.rates.gps_hz, cfg.rates.imu_hz)):
        lat, lon = gps.lat_lon_e7(i)
        alt_mm = round(float(gps.alt_msl_m[i]) * 1000.0)
        v = gps.vel_n_m_s[i]
        ground = math.hypot(float(v[0]), float(v[1]))
        cog = round(math.degrees(math.atan2(float(v[1]), float(v[0]))) * 100.0) % 36000 if ground > 0.5 else 0
        gps_yaw = 0
        if cfg.variation.yaw_source == "truth":
            gps_yaw = round(float(yaw_true_deg[i]) * 100.0) % 36000 or 36000  # 0 = unknown, north = 36000
        t_us = round(float(t[i]) * 1e6)
        events.append(
            (
                float(t[i]),
                10,
                apm.MAVLink_gps_raw_int_message(
                    t_us,
                    3,
                    lat,
                    lon,
                    alt_mm,
                    80,
                    120,
                    round(ground * 100.0),
                    cog,
                    14,
                    alt_mm,
                    800,
                    1200,
                    150,
                    0,
                    gps_yaw,
                ),
            )
        )
        hdg = round(float(np.degrees(s.attitude_rad[i, 2])) * 100.0) % 36000
        events.append(
            (
                float(t[i]),
                11,
                apm.MAVLink_global_position_int_message(
                    round(float(t[i]) * 1e3),
                    lat,
                    lon,
                    alt_mm,
                    round((float(gps.alt_msl_m[i]) - alt0) * 1000.0),
                    round(float(v[0]) * 100.0),
                    round(float(v[1]) * 100.0),
                    round(float(v[2]) * 100.0),
                    hdg,
                ),
            )
        )
    for i in rate_indices(n, cfg.rates.imu_hz, min(cfg.rates.system_time_hz, cfg.rates.imu_hz)):
        unix_us = round((start_unix_s + float(t[i])) * 1e6)
        events.append((float(t[i]), 12, apm.MAVLink_system_time_message(unix_us, round(float(t[i]) * 1e3))))
    return events


Event = tuple[float, int, Any]


def _autopilot_version(apm: Any, uid: str) -> Any:
    """AUTOPILOT_VERSION naming the simulated board's unique id (uid2, and its first 8 bytes in uid), as an
    autopilot answers a ground station's request at connect."""
    return apm.MAVLink_autopilot_version_message(0, 0, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, uid64(uid),
                                                 uid2_bytes(uid))  # fmt: skip


def _param_events(apm: Any, result: SimResult, params: list[tuple[str, float]]) -> list[Event]:
    """PARAM_VALUE of every parameter, then AUTOPILOT_VERSION, at the first sample's time."""
    t_first = float(result.samples.t_s[0])
    events: list[Event] = []
    for i, (name, value) in enumerate(params):
        msg = apm.MAVLink_param_value_message(name.encode(), value, MAV_PARAM_TYPE_REAL32, len(params), i)
        events.append((t_first, -1, msg))
    events.append((t_first, -1, _autopilot_version(apm, result.config.uid)))
    return events


def _heartbeat_events(apm: Any, result: SimResult, autopilot: int) -> list[Event]:
    cfg = result.config
    t = result.samples.t_s
    vtype = MAV_TYPE_QUADROTOR if cfg.vehicle == "multirotor" else MAV_TYPE_FIXED_WING
    flags = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MAV_MODE_FLAG_SAFETY_ARMED
    return [
        (float(t[i]), 0, apm.MAVLink_heartbeat_message(vtype, autopilot, flags, 0, MAV_STATE_ACTIVE, 3))
        for i in rate_indices(t.size, cfg.rates.imu_hz, cfg.rates.heartbeat_hz)
    ]


def _boot_us_ms(t: F64) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Boot times (s) as the messages' time_usec and time_boot_ms."""
    return np.round(t * 1e6).astype(np.int64), np.round(t * 1e3).astype(np.int64)


def _ints(*vectors: Any) -> list[int]:
    """The values of integer vectors, in order, as Python ints (a message's fields)."""
    return [int(v) for vec in vectors for v in vec]


def _ardupilot_imu_events(apm: Any, result: SimResult) -> list[Event]:
    """RAW_IMU (compass 0; time_usec) and SCALED_IMU2/3 (compasses 1, 2; time_boot_ms): accel mG, gyro
    mrad/s, mag mgauss, temperature cdegC."""
    s = result.samples
    t = s.t_s
    acc_mg = np.round(s.accel_m_s2 / STANDARD_GRAVITY_M_S2 * 1000.0).astype(np.int64)
    gyro_mrad = np.round(s.gyro_rad_s * 1000.0).astype(np.int64)
    mag = np.round(s.mag_mgauss).astype(np.int64)
    temp_cdeg = np.round(s.imu_temp_degc * 100.0).astype(np.int64)
    t_us, t_ms = _boot_us_ms(t)
    events: list[Event] = []
    for i in raw_imu_rows(result):
        fields = _ints(acc_mg[0, i], gyro_mrad[0, i], mag[0, i])
        msg = apm.MAVLink_raw_imu_message(int(t_us[i]), *fields, 0, int(temp_cdeg[0, i]))
        events.append((float(t[i]), 1, msg))
        for j in range(1, mag.shape[0]):
            cls = apm.MAVLink_scaled_imu2_message if j == 1 else apm.MAVLink_scaled_imu3_message
            fields = _ints(acc_mg[j, i], gyro_mrad[j, i], mag[j, i])
            events.append((float(t[i]), 1 + j, cls(int(t_ms[i]), *fields, int(temp_cdeg[j, i]))))
    return events


def _attitude_events(apm: Any, result: SimResult) -> list[Event]:
    s = result.samples
    t, att, rates_b = s.t_s, s.attitude_rad, body_rates(result)
    t_ms = _boot_us_ms(t)[1]
    events: list[Event] = []
    for i in rate_indices(t.size, result.config.rates.imu_hz, result.config.rates.attitude_hz):
        values = (float(v) for v in (*att[i], *rates_b[i]))
        events.append((float(t[i]), 4, apm.MAVLink_attitude_message(int(t_ms[i]), *values)))
    return events


def _output_events(apm: Any, result: SimResult) -> list[Event]:
    """SERVO_OUTPUT_RAW (quad: motors 1-4; fixed wing: elevons 1/2 mixing pitch and roll demands from the
    body rates around 1500, throttle 3) and RC_CHANNELS (throttle stick on channel 3)."""
    cfg = result.config
    s = result.samples
    t, rates = s.t_s, cfg.rates
    multirotor = cfg.vehicle == "multirotor"
    motors_pwm = pwm_us(s.motors_01)
    thr_pwm = pwm_us(s.throttle_01)
    elevon_l, elevon_r = elevons_pwm(result)
    t_us, t_ms = _boot_us_ms(t)
    events: list[Event] = []
    for i in rate_indices(t.size, rates.imu_hz, rates.servo_hz):
        ch = [0] * 16
        if multirotor:
            ch[0:4] = [int(v) for v in motors_pwm[i, :4]]
        else:
            ch[0], ch[1], ch[2] = int(elevon_l[i]), int(elevon_r[i]), int(thr_pwm[i])
        t_u32 = int(t_us[i]) & 0xFFFFFFFF
        events.append((float(t[i]), 5, apm.MAVLink_servo_output_raw_message(t_u32, 0, *ch)))
    for i in rate_indices(t.size, rates.imu_hz, rates.rc_hz):
        rc = [1500, 1500, int(thr_pwm[i]), 1500, 1000, 1000, 1000, 1000] + [UINT16_UNUSED] * 10
        events.append((float(t[i]), 6, apm.MAVLink_rc_channels_message(int(t_ms[i]), 8, *rc, 255)))
    return events


def _vfr_hud_events(apm: Any, result: SimResult) -> list[Event]:
    s = result.samples
    t = s.t_s
    events: list[Event] = []
    for i in rate_indices(t.size, result.config.rates.imu_hz, result.config.rates.vfr_hud_hz):
        heading = round(math.degrees(float(s.attitude_rad[i, 2]))) % 360
        msg = apm.MAVLink_vfr_hud_message(float(s.airspeed_m_s[i]), float(s.groundspeed_m_s[i]), heading,
                                          round(100.0 * float(s.throttle_01[i])), float(s.alt_m[i]),
                                          float(s.climb_m_s[i]))  # fmt: skip
        events.append((float(t[i]), 7, msg))
    return events


def _power_events(apm: Any, result: SimResult) -> list[Event]:
    """SYS_STATUS and BATTERY_STATUS (voltage mV, current cA, remaining % from the consumed charge)."""
    s = result.samples
    t, rates = s.t_s, result.config.rates
    dt = 1.0 / rates.imu_hz
    consumed_mah = np.cumsum(s.current_a) * dt / 3.6
    energy_hj = np.cumsum(s.current_a * s.voltage_v) * dt / 100.0
    events: list[Event] = []
    for i in rate_indices(t.size, rates.imu_hz, rates.power_hz):
        mv = round(float(s.voltage_v[i]) * 1000.0)
        ca = round(float(s.current_a[i]) * 100.0)
        remaining = int(np.clip(round(100.0 * (1.0 - consumed_mah[i] / BATTERY_CAPACITY_MAH) * 0.95), 0, 100))
        present = SENSORS_PRESENT
        sys_status = apm.MAVLink_sys_status_message(present, present, present, 300, mv, ca, remaining,
                                                    0, 0, 0, 0, 0, 0)  # fmt: skip
        battery = apm.MAVLink_battery_status_message(0, 0, MAV_BATTERY_TYPE_LIPO, INT16_UNKNOWN,
                                                     [mv] + [UINT16_UNUSED] * 9, ca, int(consumed_mah[i]),
                                                     int(energy_hj[i]), remaining, 0,
                                                     MAV_BATTERY_CHARGE_STATE_OK)  # fmt: skip
        events += [(float(t[i]), 8, sys_status), (float(t[i]), 9, battery)]
    return events


def build_messages(result: SimResult, start_unix_s: float | None = None) -> list[Event]:
    """All messages as (boot time s, priority, unpacked MAVLink message object), in send order.

    start_unix_s: UTC of boot for SYSTEM_TIME (default :func:`default_start_unix_s`, the config's date)."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    cfg = result.config
    params = servo_params(cfg.vehicle)
    if not cfg.legacy:
        params += compass_params(result)
    events = _param_events(apm, result, params)
    events += _heartbeat_events(apm, result, MAV_AUTOPILOT_ARDUPILOTMEGA)
    events += _ardupilot_imu_events(apm, result)
    events += _attitude_events(apm, result)
    events += _output_events(apm, result)
    events += _vfr_hud_events(apm, result)
    events += _power_events(apm, result)
    if cfg.gps:
        events += _gps_messages(
            result, default_start_unix_s(result) if start_unix_s is None else start_unix_s
        )
    events.sort(key=lambda e: (e[0], e[1]))
    return _apply_link_loss(events, result)


def _apply_link_loss(events: list[Event], result: SimResult) -> list[Event]:
    """A lossy telemetry link (``link_loss``): each message lost independently (seeded), parameters kept."""
    cfg = result.config
    loss = cfg.variation.link_loss
    if loss <= 0.0:
        return events
    keep = np.random.default_rng([cfg.seed, 0x1055]).random(len(events)) >= loss
    return [e for e, k in zip(events, keep, strict=True) if k or e[1] < 0]


MAV_AUTOPILOT_PX4 = 12
PX4_FN_MOTOR1 = 101  # PWM_MAIN_FUNCn Motor1
HIGHRES_ALL_IMU = 0x3F | 0x1000  # accel, gyro, temperature
HIGHRES_MAG = 0x1C0


def _px4_params(vehicle: str) -> list[tuple[str, float]]:
    """PWM_MAIN_FUNCn/MINn/MAXn: motors 1-4 (quad) or the throttle on output 3."""
    motor_channels = px4_motor_outputs(vehicle)
    params: list[tuple[str, float]] = []
    for ch in range(1, 9):
        fn = PX4_FN_MOTOR1 + motor_channels.index(ch) if ch in motor_channels else 0
        params += [
            (f"PWM_MAIN_FUNC{ch}", float(fn)),
            (f"PWM_MAIN_MIN{ch}", 1000.0),
            (f"PWM_MAIN_MAX{ch}", 2000.0),
        ]
    return params


def _px4_imu_events(apm: Any, result: SimResult) -> list[Event]:
    """HIGHRES_IMU (accel m/s^2 and gyro rad/s quantised as ArduPilot's, compass 0 in gauss) and SCALED_IMU2/3
    (compasses 1, 2 in mgauss)."""
    s = result.samples
    t = s.t_s
    g = STANDARD_GRAVITY_M_S2
    gyro, acc = quantised_imu(result)
    mag = np.round(s.mag_mgauss).astype(np.int64)
    t_us, t_ms = _boot_us_ms(t)
    events: list[Event] = []
    for i in raw_imu_rows(result):
        a, w, m = acc[0, i], gyro[0, i], mag[0, i]
        events.append((float(t[i]), 1, apm.MAVLink_highres_imu_message(
            int(t_us[i]), *(float(v) for v in a), *(float(v) for v in w), *(float(v) * 1e-3 for v in m),
            1013.25, 0.0, 0.0, float(s.imu_temp_degc[0, i]), HIGHRES_ALL_IMU | HIGHRES_MAG, 0)))  # fmt: skip
        for j in range(1, mag.shape[0]):
            cls = apm.MAVLink_scaled_imu2_message if j == 1 else apm.MAVLink_scaled_imu3_message
            aj = np.round(s.accel_m_s2[j, i] / g * 1000.0).astype(np.int64)
            wj = np.round(s.gyro_rad_s[j, i] * 1000.0).astype(np.int64)
            events.append((float(t[i]), 1 + j, cls(int(t_ms[i]), *_ints(aj, wj, mag[j, i]), 0)))
    return events


def _px4_attitude_output_events(apm: Any, result: SimResult) -> list[Event]:
    """ATTITUDE_QUATERNION and ACTUATOR_OUTPUT_STATUS (PWM us; unused outputs 900)."""
    from magcomp.core.rotations import quats_from_euler

    cfg = result.config
    s = result.samples
    t, rates = s.t_s, cfg.rates
    att = s.attitude_rad
    q = quats_from_euler(att[:, 0], att[:, 1], att[:, 2])
    rates_b = body_rates(result)
    t_us, t_ms = _boot_us_ms(t)
    events: list[Event] = []
    for i in rate_indices(t.size, rates.imu_hz, rates.attitude_hz):
        qi, wi = (float(v) for v in q[i]), (float(v) for v in rates_b[i])
        msg = apm.MAVLink_attitude_quaternion_message(int(t_ms[i]), *qi, *wi, [0.0] * 4)
        events.append((float(t[i]), 4, msg))
    for i in rate_indices(t.size, rates.imu_hz, rates.servo_hz):
        out = px4_outputs(result, int(i), 32)
        events.append((float(t[i]), 5, apm.MAVLink_actuator_output_status_message(int(t_us[i]), 0xFF, out)))
    return events


def _px4_power_gps_events(apm: Any, result: SimResult) -> list[Event]:
    """BATTERY_STATUS, GPS_RAW_INT (the flown track with ``gps`` on, else the home location) and SYSTEM_TIME
    at power_hz."""
    cfg = result.config
    s = result.samples
    t, rates, loc = s.t_s, cfg.rates, cfg.location
    start_unix = default_start_unix_s(result)
    t_us, t_ms = _boot_us_ms(t)
    events: list[Event] = []
    for i in rate_indices(t.size, rates.imu_hz, rates.power_hz):
        mv = round(float(s.voltage_v[i]) * 1000.0)
        ca = round(float(s.current_a[i]) * 100.0)
        events.append((float(t[i]), 8, apm.MAVLink_battery_status_message(
            0, 0, MAV_BATTERY_TYPE_LIPO, INT16_UNKNOWN, [mv] + [UINT16_UNUSED] * 9, ca, -1, -1, -1, 0,
            MAV_BATTERY_CHARGE_STATE_OK)))  # fmt: skip
        lat_e7, lon_e7, alt_mm = (
            round(loc.lat_deg * 1e7),
            round(loc.lon_deg * 1e7),
            round(float(s.alt_m[i]) * 1e3),
        )
        if s.gps is not None:
            lat_e7, lon_e7 = s.gps.lat_lon_e7(i)
            alt_mm = round(float(s.gps.alt_msl_m[i]) * 1e3)  # the flown track (``gps`` on)
        gps = apm.MAVLink_gps_raw_int_message(int(t_us[i]), 3, lat_e7, lon_e7, alt_mm, 100, 150, 0, 0, 12)
        events.append((float(t[i]), 9, gps))
        unix_us = round((start_unix + float(t[i])) * 1e6)
        events.append((float(t[i]), 10, apm.MAVLink_system_time_message(unix_us, int(t_ms[i]) & 0xFFFFFFFF)))
    return events


def build_px4_messages(result: SimResult) -> list[Event]:
    """The same vehicle as a PX4 autopilot sends it (MAV_AUTOPILOT_PX4): PARAM_VALUE PWM_MAIN_FUNCn/MINn/
    MAXn and CAL_MAGn_ID; HIGHRES_IMU (imu_hz: accel m/s^2, gyro rad/s, compass 0 in gauss, fields_updated);
    SCALED_IMU2/3 (compasses 1, 2 in mgauss); ATTITUDE_QUATERNION; ACTUATOR_OUTPUT_STATUS (PWM us);
    BATTERY_STATUS; GPS_RAW_INT and SYSTEM_TIME (power_hz). Same quantisation as the ArduPilot stream."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    events = _param_events(apm, result, _px4_params(result.config.vehicle))
    events += _heartbeat_events(apm, result, MAV_AUTOPILOT_PX4)
    events += _px4_imu_events(apm, result)
    events += _px4_attitude_output_events(apm, result)
    events += _px4_power_gps_events(apm, result)
    events.sort(key=lambda e: (e[0], e[1]))
    return _apply_link_loss(events, result)


def encode_stream(
    result: SimResult,
    src_system: int = 1,
    src_component: int = 1,
    start_unix_s: float | None = None,
    flavour: str = "ardupilot",
) -> list[tuple[float, bytes]]:
    """Packed MAVLink 2 packets in send order: (boot time s, bytes); sequence numbers run 0..255.
    ``flavour``: ``ardupilot`` (:func:`build_messages`) or ``px4`` (:func:`build_px4_messages`)."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    if flavour not in ("ardupilot", "px4"):
        raise InputError(f"MAVLink flavour {flavour!r}: ardupilot or px4")
    mav = apm.MAVLink(None, srcSystem=src_system, srcComponent=src_component)
    built = build_px4_messages(result) if flavour == "px4" else build_messages(result, start_unix_s)
    out = []
    for i, (t, _, msg) in enumerate(built):
        mav.seq = i & 0xFF  # pack() does not advance it (send() would); a receiver counts gaps in it
        out.append((t, bytes(msg.pack(mav))))
    return out


def write_tlog(
    result: SimResult,
    path: str | os.PathLike[str],
    start_unix_s: float | None = None,
    flavour: str = "ardupilot",
) -> int:
    """Write the stream as a tlog (8-byte big-endian UNIX usec + packet per record). Returns the count."""
    start = default_start_unix_s(result) if start_unix_s is None else float(start_unix_s)
    packets = encode_stream(result, start_unix_s=start, flavour=flavour)
    chunks = []
    for t, pkt in packets:
        chunks.append(round((start + t) * 1e6).to_bytes(8, "big"))
        chunks.append(pkt)
    write_file(path, b"".join(chunks))
    return len(packets)


class TruthPaths(NamedTuple):
    """Where a simulated log's truth is written beside it."""

    json: Path
    npz: Path


def truth_paths(out_path: str | os.PathLike[str]) -> TruthPaths:
    """``FILE.tlog`` -> (``FILE.truth.json``, ``FILE.truth.npz``)."""
    p = Path(out_path)
    stem = p.with_suffix("") if p.suffix else p
    return TruthPaths(stem.with_name(stem.name + ".truth.json"), stem.with_name(stem.name + ".truth.npz"))


_NEW_RATE_KEYS = ("raw_imu_hz", "mag_hz", "gps_hz", "system_time_hz")


def truth_summary(result: SimResult) -> dict[str, Any]:
    """The run's parameters and truth constants, JSON-able (lists for arrays).

    Runs that use the newer scenarios or knobs (``config.legacy`` False) also get: ``variation`` (the
    knobs), the effective message rates, ``heading_reference`` and, per compass, ``logged_frame``: the
    true calibration ``L``, ``d_mgauss`` of the LOGGED field (``L logged - d = u + B + D``, body frame) and
    theta in that frame, plus the autopilot's calibration when it applies one. Frames of theta:
    ``theta_mgauss`` is the body (= calibrated) frame the pipeline estimates in after its own (L, d);
    ``theta_logged_mgauss`` = L^-1 theta is the frame of the RAW_IMU/SCALED_IMU values;
    ``theta_raw_mgauss`` = K theta is the sensor's frame before any calibration.
    """
    summary = _truth_summary_base(result)
    if result.config.legacy:
        for key in _NEW_RATE_KEYS:
            summary["rates_hz"].pop(key, None)
        return summary
    cfg = result.config
    summary["variation"] = asdict(cfg.variation)
    summary["rates_hz"]["raw_imu_hz"] = cfg.rates.raw_imu_rate
    summary["rates_hz"]["mag_hz"] = cfg.rates.mag_rate
    summary["gps"] = cfg.gps
    summary["start_unix_s"] = default_start_unix_s(result)
    summary["heading_reference"] = (
        "GPS yaw (truth)"
        if cfg.variation.yaw_source == "truth"
        else f"compass {cfg.variation.primary_compass}"
        + (" with the autopilot's calibration" if result.ap_calibration is not None else "")
    )
    summary["frames"] = (
        "theta_mgauss: body frame (what L logged - d gives); theta_logged_mgauss: frame of the logged "
        "RAW_IMU/SCALED_IMU values; theta_raw_mgauss: raw sensor frame (K theta)"
    )
    for j, entry in enumerate(summary["compasses"]):
        l_matrix, d = result.true_calibration(j)
        frame: dict[str, Any] = {
            "L": l_matrix.tolist(),
            "d_mgauss": d.tolist(),
            "theta_logged_mgauss": result.theta_logged_mgauss(j).tolist(),
            "model": "L logged - d = u + B + drift (body frame, noise aside)",
        }
        if result.ap_calibration is not None:
            cal = result.ap_calibration[j]
            frame["autopilot"] = {
                "A": cal.a_matrix.tolist(),
                "offsets_mgauss": cal.offsets_mgauss.tolist(),
                "residual_hard_iron_mgauss": cal.residual_hard_iron_mgauss.tolist(),
                "soft_iron_error": cal.soft_iron_error.tolist(),
                "model": "logged = A (raw + offsets), rounded to 1 mgauss",
            }
        entry["logged_frame"] = frame
        entry["external"] = bool(j == 0 and cfg.variation.external_compass0)
    return summary


def _truth_summary_base(result: SimResult) -> dict[str, Any]:
    cfg = result.config
    return {
        "generator": "magcomp simulate",
        "scenario": cfg.scenario,
        "vehicle": cfg.vehicle,
        "duration_s": cfg.duration,
        "seed": cfg.seed,
        "t0_s": cfg.t0_s,
        "effects": dict(cfg.effects),
        "effect_params": result.effect_params,
        "location": asdict(cfg.location),
        "rates_hz": asdict(cfg.rates),
        "earth_field_ned_mgauss": result.earth_field_ned_mgauss.tolist(),
        "earth_field_norm_mgauss": float(np.linalg.norm(result.earth_field_ned_mgauss)),
        "declination_deg": result.declination_deg,
        "bias_model": "B = theta * throttle^2 (eq. 11) when no effect is on; theta in the calibrated frame",
        "mag_model": "v = K (u + B + drift) + b + noise (eq. 1); u = R_nb^T m_n",
        "compasses": [
            {
                "index": c.index,
                "message": c.message,
                "K": c.k_matrix.tolist(),
                "b_mgauss": c.b_mgauss.tolist(),
                "theta_mgauss": c.theta_mgauss.tolist(),
                "theta_raw_mgauss": c.theta_raw_mgauss.tolist(),
                "theta_motor_mgauss": c.theta_motor_mgauss.tolist(),
                "distance_m": c.distance_m,
                "noise_mgauss": c.noise_mgauss,
                "lsb_mgauss": c.lsb_mgauss,
                "gyro_bias_rad_s": c.gyro_bias_rad_s.tolist(),
                "gyro_noise_rad_s": c.gyro_noise_rad_s,
                "accel_bias_m_s2": c.accel_bias_m_s2.tolist(),
                "accel_noise_m_s2": c.accel_noise_m_s2,
            }
            for c in result.compasses
        ],
        "segments": list(result.motion.segment_names),
        "npz_arrays_at": "the IMU sample instants (imu_hz), boot clock t_s",
    }


def truth_arrays(result: SimResult) -> dict[str, F64]:
    """Truth at the sample instants (the loop grid, imu_hz): the arrays written to ``FILE.truth.npz``.

    Non-legacy runs add heading_true_deg (true heading, deg from true north), autopilot_yaw_error_deg
    (ATTITUDE yaw - true yaw), mag_logged_mgauss (J, n, 3; what the messages carry at the loop grid),
    mag_sensor_mgauss (raw readings, with the autopilot's calibration on), gps_lat_lon_alt (n, 3)."""
    pick = result.truth_at_samples
    euler = pick(result.euler_rad)
    arrays = {
        "t_s": result.samples.t_s,
        "q_nb": pick(result.motion.q_nb),
        "euler_rad": euler,
        "heading_mag_deg": np.mod(np.degrees(euler[:, 2]) - result.declination_deg, 360.0),
        "omega_b_rad_s": pick(result.motion.omega_b_rad_s),
        "throttle_cmd_01": pick(result.motion.throttle_cmd_01),
        "motors_cmd_01": pick(result.motion.motors_cmd_01),
        "throttle_acting_01": pick(result.power.throttle_acting_01),
        "speed_01": pick(result.power.speed_01),
        "load_01": pick(result.power.load_01),
        "current_a": pick(result.power.current_a),
        "voltage_v": pick(result.power.voltage_v),
        "soc": pick(result.power.soc),
        "temp_powertrain_degc": pick(result.power.temp_powertrain_degc),
        "temp_imu_degc": pick(result.power.temp_imu_degc),
        "bias_mgauss": pick(result.bias_mgauss),
        "drift_mgauss": pick(result.drift_mgauss),
        "field_earth_b_mgauss": pick(result.field_earth_b_mgauss),
        "autopilot_euler_rad": result.samples.attitude_rad,
        "segment": result.motion.segment[result.samples.truth_index].astype(np.float64),
    }
    if result.config.legacy:
        return arrays
    s = result.samples
    yaw_err = np.degrees(s.attitude_rad[:, 2] - euler[:, 2])
    arrays["heading_true_deg"] = np.mod(np.degrees(euler[:, 2]), 360.0)
    arrays["autopilot_yaw_error_deg"] = (yaw_err + 180.0) % 360.0 - 180.0
    arrays["mag_logged_mgauss"] = s.mag_mgauss
    if s.mag_sensor_mgauss is not None:
        arrays["mag_sensor_mgauss"] = s.mag_sensor_mgauss
    if s.gps is not None:
        arrays["gps_lat_lon_alt"] = np.stack([s.gps.lat_deg, s.gps.lon_deg, s.gps.alt_msl_m], axis=1)
    return arrays


def write_truth(
    result: SimResult, out_path: str | os.PathLike[str], single_precision: bool = False
) -> tuple[Path, Path]:
    """Write ``FILE.truth.json`` and ``FILE.truth.npz`` beside ``out_path``; returns both paths.

    single_precision: store every array but ``t_s`` as float32 (half the size; for shipped sample logs).
    """
    json_path, npz_path = truth_paths(out_path)
    arrays = truth_arrays(result)
    if single_precision:
        arrays = {k: (v if k == "t_s" else v.astype(np.float32)) for k, v in arrays.items()}
    try:
        json_path.write_text(json.dumps(truth_summary(result), indent=1) + "\n")
        np.savez_compressed(npz_path, **arrays)  # type: ignore[arg-type]
    except OSError as exc:
        raise InputError(f"cannot write truth beside {out_path}: {exc.strerror or exc}") from exc
    return json_path, npz_path


def _open_link(url: str) -> Any:
    if not url.startswith(("udpout:", "tcpout:", "udpin:", "tcp:", "udp:")):
        raise InputError(f"link {url!r}: expected udpout:HOST:PORT or tcpout:HOST:PORT")
    os.environ.setdefault("MAVLINK20", "1")  # before pymavlink.mavutil is imported (stack-notes §2)
    dialect = "ardupilotmega"
    try:
        from magcomp.adapters.dialect import ensure_dialect

        ensure_dialect()
        dialect = "magcomp"  # a superset of ardupilotmega that also decodes MAGCOMP_HEADING sent back
    except Exception:  # the dialect is optional here: fall back to the shipped one
        dialect = "ardupilotmega"
    from pymavlink import mavutil

    device = "tcp:" + url[len("tcpout:") :] if url.startswith("tcpout:") else url  # mavutil's TCP client
    try:
        return mavutil.mavlink_connection(device, source_system=1, source_component=1, dialect=dialect)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot open link {url}: {exc}") from exc


def stream_to_link(
    result: SimResult,
    url: str,
    speed: float = 1.0,
    stop: Callable[[], bool] | None = None,
    keep_received: int = 50,
    flavour: str = "ardupilot",
) -> LinkReport:
    """Play the stream to a live endpoint in (simulated) real time divided by ``speed`` (<= 0: no pacing),
    acting as the flight controller: whatever the peer sends back is read, counted by type, and the first
    ``keep_received`` messages are kept. ``stop()`` returning True ends the run early."""
    packets = encode_stream(result, flavour=flavour)
    conn = _open_link(url)
    received: dict[str, int] = {}
    first: list[dict[str, Any]] = []
    sent = 0
    completed = True

    def drain() -> None:
        while True:
            try:
                msg = conn.recv_msg()
            except (OSError, ConnectionError):
                return
            if msg is None:
                return
            name = msg.get_type()
            received[name] = received.get(name, 0) + 1
            if len(first) < keep_received:
                try:
                    first.append(msg.to_dict())
                except Exception:  # unknown/bad data may not convert
                    first.append({"mavpackettype": name})

    wall0 = time.monotonic()
    t_first = packets[0][0] if packets else 0.0
    try:
        for t, pkt in packets:
            if stop is not None and stop():
                completed = False
                break
            if speed > 0.0:
                delay = (t - t_first) / speed - (time.monotonic() - wall0)
                if delay > 0.0:
                    drain()
                    time.sleep(max(0.0, (t - t_first) / speed - (time.monotonic() - wall0)))
            try:
                conn.write(pkt)
            except OSError as exc:
                raise InputError(f"link {url}: send failed: {exc}") from exc
            sent += 1
        drain()
    finally:
        conn.close()
    return LinkReport(
        url=url,
        sent=sent,
        received=received,
        first_received=first,
        wall_s=time.monotonic() - wall0,
        completed=completed,
    )
