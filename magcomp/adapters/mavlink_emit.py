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

import datetime as _dt
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.core.types import STANDARD_GRAVITY_M_S2
from magcomp.errors import InputError
from magcomp.sim.simulate import SimResult

F64 = NDArray[np.float64]

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
BATTERY_CAPACITY_MAH = 2200

# ArduPilot SERVOn_FUNCTION values
FN_DISABLED, FN_THROTTLE, FN_ELEVON_LEFT, FN_ELEVON_RIGHT = 0, 70, 77, 78
FN_MOTOR1 = 33


@dataclass(frozen=True)
class LinkReport:
    """What a live run did: packets sent, messages received back (by type) and the first few of them."""

    url: str
    sent: int
    received: dict[str, int] = field(default_factory=dict)
    first_received: list[dict[str, Any]] = field(default_factory=list)
    wall_s: float = 0.0
    completed: bool = True


def default_start_unix_s(result: SimResult) -> float:
    """UNIX time of boot: the config's decimal year (at whole seconds), deterministic."""
    year_f = result.config.location.decimal_year
    year = int(year_f)
    start = _dt.datetime(year, 1, 1, tzinfo=_dt.UTC)
    length = (_dt.datetime(year + 1, 1, 1, tzinfo=_dt.UTC) - start).total_seconds()
    return float(math.floor(start.timestamp() + (year_f - year) * length))


def _rate_indices(n: int, imu_hz: float, rate_hz: float) -> NDArray[np.int64]:
    """Rows of the imu_hz samples that a stream at rate_hz uses (nearest sample to each tick)."""
    ticks = np.arange(0.0, n / imu_hz, 1.0 / rate_hz)
    return np.unique(np.minimum(np.round(ticks * imu_hz).astype(np.int64), n - 1))


def _servo_params(vehicle: str) -> list[tuple[str, float]]:
    if vehicle == "multirotor":
        functions = [FN_MOTOR1, FN_MOTOR1 + 1, FN_MOTOR1 + 2, FN_MOTOR1 + 3] + [FN_DISABLED] * 4
    else:
        functions = [FN_ELEVON_LEFT, FN_ELEVON_RIGHT, FN_THROTTLE] + [FN_DISABLED] * 5
    out: list[tuple[str, float]] = []
    for i, fn in enumerate(functions, start=1):
        out += [(f"SERVO{i}_FUNCTION", float(fn)), (f"SERVO{i}_MIN", 1000.0), (f"SERVO{i}_MAX", 2000.0)]
    out.append(("BATT_CAPACITY", float(BATTERY_CAPACITY_MAH)))
    if vehicle == "multirotor":
        out += [("FRAME_CLASS", 1.0), ("FRAME_TYPE", 1.0)]  # quad, X
    return out


def _pwm(x01: F64) -> NDArray[np.int64]:
    return np.round(1000.0 + 1000.0 * np.clip(x01, 0.0, 1.0)).astype(np.int64)


def build_messages(result: SimResult) -> list[tuple[float, int, Any]]:
    """All messages as (boot time s, priority, unpacked MAVLink message object), in send order."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    cfg = result.config
    s = result.samples
    rates = cfg.rates
    n = s.t_s.size
    t = s.t_s
    multirotor = cfg.vehicle == "multirotor"
    events: list[tuple[float, int, Any]] = []
    t_first = float(t[0])

    params = _servo_params(cfg.vehicle)
    for i, (name, value) in enumerate(params):
        events.append(
            (
                t_first,
                -1,
                apm.MAVLink_param_value_message(name.encode(), value, MAV_PARAM_TYPE_REAL32, len(params), i),
            )
        )
    for i in _rate_indices(n, rates.imu_hz, rates.heartbeat_hz):
        events.append(
            (
                float(t[i]),
                0,
                apm.MAVLink_heartbeat_message(
                    MAV_TYPE_QUADROTOR if multirotor else MAV_TYPE_FIXED_WING,
                    MAV_AUTOPILOT_ARDUPILOTMEGA,
                    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MAV_MODE_FLAG_SAFETY_ARMED,
                    0,
                    MAV_STATE_ACTIVE,
                    3,
                ),
            )
        )

    acc_mg = np.round(s.accel_m_s2 / STANDARD_GRAVITY_M_S2 * 1000.0).astype(np.int64)
    gyro_mrad = np.round(s.gyro_rad_s * 1000.0).astype(np.int64)
    mag = np.round(s.mag_mgauss).astype(np.int64)
    temp_cdeg = np.round(s.imu_temp_degc * 100.0).astype(np.int64)
    t_us = np.round(t * 1e6).astype(np.int64)
    t_ms = np.round(t * 1e3).astype(np.int64)
    for i in range(n):
        a, w, m = acc_mg[0, i], gyro_mrad[0, i], mag[0, i]
        events.append(
            (
                float(t[i]),
                1,
                apm.MAVLink_raw_imu_message(
                    int(t_us[i]),
                    int(a[0]),
                    int(a[1]),
                    int(a[2]),
                    int(w[0]),
                    int(w[1]),
                    int(w[2]),
                    int(m[0]),
                    int(m[1]),
                    int(m[2]),
                    0,
                    int(temp_cdeg[0, i]),
                ),
            )
        )
        for j in range(1, mag.shape[0]):
            cls = apm.MAVLink_scaled_imu2_message if j == 1 else apm.MAVLink_scaled_imu3_message
            a, w, m = acc_mg[j, i], gyro_mrad[j, i], mag[j, i]
            events.append(
                (
                    float(t[i]),
                    1 + j,
                    cls(
                        int(t_ms[i]),
                        int(a[0]),
                        int(a[1]),
                        int(a[2]),
                        int(w[0]),
                        int(w[1]),
                        int(w[2]),
                        int(m[0]),
                        int(m[1]),
                        int(m[2]),
                        int(temp_cdeg[j, i]),
                    ),
                )
            )

    att = s.attitude_rad
    rates_b = s.gyro_rad_s[0] - result.compasses[0].gyro_bias_rad_s
    for i in _rate_indices(n, rates.imu_hz, rates.attitude_hz):
        events.append(
            (
                float(t[i]),
                4,
                apm.MAVLink_attitude_message(
                    int(t_ms[i]),
                    float(att[i, 0]),
                    float(att[i, 1]),
                    float(att[i, 2]),
                    float(rates_b[i, 0]),
                    float(rates_b[i, 1]),
                    float(rates_b[i, 2]),
                ),
            )
        )

    motors_pwm = _pwm(s.motors_01)
    thr_pwm = _pwm(s.throttle_01)
    # fixed wing: elevons mix pitch and roll demands (from body rates), around 1500
    pitch_cmd = np.clip(0.3 * rates_b[:, 1], -0.4, 0.4)
    roll_cmd = np.clip(0.3 * rates_b[:, 0], -0.4, 0.4)
    elevon_l = np.round(1500 + 500 * (pitch_cmd + roll_cmd)).astype(np.int64)
    elevon_r = np.round(1500 + 500 * (pitch_cmd - roll_cmd)).astype(np.int64)
    for i in _rate_indices(n, rates.imu_hz, rates.servo_hz):
        ch = [0] * 16
        if multirotor:
            ch[0:4] = [int(v) for v in motors_pwm[i, :4]]
        else:
            ch[0], ch[1], ch[2] = int(elevon_l[i]), int(elevon_r[i]), int(thr_pwm[i])
        events.append(
            (float(t[i]), 5, apm.MAVLink_servo_output_raw_message(int(t_us[i]) & 0xFFFFFFFF, 0, *ch))
        )
    for i in _rate_indices(n, rates.imu_hz, rates.rc_hz):
        rc = [1500, 1500, int(thr_pwm[i]), 1500, 1000, 1000, 1000, 1000] + [UINT16_UNUSED] * 10
        events.append((float(t[i]), 6, apm.MAVLink_rc_channels_message(int(t_ms[i]), 8, *rc, 255)))
    for i in _rate_indices(n, rates.imu_hz, rates.vfr_hud_hz):
        heading = round(math.degrees(float(att[i, 2]))) % 360
        events.append(
            (
                float(t[i]),
                7,
                apm.MAVLink_vfr_hud_message(
                    float(s.airspeed_m_s[i]),
                    float(s.groundspeed_m_s[i]),
                    heading,
                    round(100.0 * float(s.throttle_01[i])),
                    float(s.alt_m[i]),
                    float(s.climb_m_s[i]),
                ),
            )
        )
    # battery: consumed charge from the reported current
    dt = 1.0 / rates.imu_hz
    consumed_mah = np.cumsum(s.current_a) * dt / 3.6
    energy_hj = np.cumsum(s.current_a * s.voltage_v) * dt / 100.0
    for i in _rate_indices(n, rates.imu_hz, rates.power_hz):
        mv = round(float(s.voltage_v[i]) * 1000.0)
        ca = round(float(s.current_a[i]) * 100.0)
        remaining = int(np.clip(round(100.0 * (1.0 - consumed_mah[i] / BATTERY_CAPACITY_MAH) * 0.95), 0, 100))
        events.append(
            (
                float(t[i]),
                8,
                apm.MAVLink_sys_status_message(
                    SENSORS_PRESENT,
                    SENSORS_PRESENT,
                    SENSORS_PRESENT,
                    300,
                    mv,
                    ca,
                    remaining,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                ),
            )
        )
        events.append(
            (
                float(t[i]),
                9,
                apm.MAVLink_battery_status_message(
                    0,
                    0,
                    MAV_BATTERY_TYPE_LIPO,
                    INT16_UNKNOWN,
                    [mv] + [UINT16_UNUSED] * 9,
                    ca,
                    int(consumed_mah[i]),
                    int(energy_hj[i]),
                    remaining,
                    0,
                    MAV_BATTERY_CHARGE_STATE_OK,
                ),
            )
        )
    events.sort(key=lambda e: (e[0], e[1]))
    return events


def encode_stream(
    result: SimResult, src_system: int = 1, src_component: int = 1
) -> list[tuple[float, bytes]]:
    """Packed MAVLink 2 packets in send order: (boot time s, bytes); sequence numbers run 0..255."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    mav = apm.MAVLink(None, srcSystem=src_system, srcComponent=src_component)
    out = []
    for i, (t, _, msg) in enumerate(build_messages(result)):
        mav.seq = i & 0xFF  # pack() does not advance it (send() would); a receiver counts gaps in it
        out.append((t, bytes(msg.pack(mav))))
    return out


def write_tlog(result: SimResult, path: str | os.PathLike[str], start_unix_s: float | None = None) -> int:
    """Write the stream as a tlog (8-byte big-endian UNIX usec + packet per record). Returns the count."""
    start = default_start_unix_s(result) if start_unix_s is None else float(start_unix_s)
    packets = encode_stream(result)
    chunks = []
    for t, pkt in packets:
        chunks.append(round((start + t) * 1e6).to_bytes(8, "big"))
        chunks.append(pkt)
    try:
        Path(path).write_bytes(b"".join(chunks))
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror or exc}") from exc
    return len(packets)


def truth_paths(out_path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``FILE.tlog`` -> (``FILE.truth.json``, ``FILE.truth.npz``)."""
    p = Path(out_path)
    stem = p.with_suffix("") if p.suffix else p
    return stem.with_name(stem.name + ".truth.json"), stem.with_name(stem.name + ".truth.npz")


def truth_summary(result: SimResult) -> dict[str, Any]:
    """The run's parameters and truth constants, JSON-able (lists for arrays)."""
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
    """Truth at the sample instants: the arrays written to ``FILE.truth.npz``."""
    pick = result.truth_at_samples
    euler = pick(result.euler_rad)
    return {
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
) -> LinkReport:
    """Play the stream to a live endpoint in (simulated) real time divided by ``speed`` (<= 0: no pacing),
    acting as the flight controller: whatever the peer sends back is read, counted by type, and the first
    ``keep_received`` messages are kept. ``stop()`` returning True ends the run early."""
    packets = encode_stream(result)
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
