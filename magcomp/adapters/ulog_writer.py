"""A minimal PX4 ULog writer (for the simulator and the tests): header, flag bits, formats, info, initial
parameters, add-logged-message and data messages, per the ULog file format (version 1).

Layout: 16-byte header ("ULog" 0x01 0x12 0x35, version 1, uint64 start time us), then messages of a 3-byte
header (uint16 payload size, uint8 type) + payload. Definitions section: 'B' flag bits, 'F' formats
("name:type field;..."), 'I' info and 'P' parameters (key "type name" + value). Data section: 'A'
subscriptions (multi_id, msg_id, name), 'D' data (msg_id + the packed struct, little endian, no padding),
'P' parameter changes.

:func:`write_sim_ulog` writes a :class:`~magcomp.sim.SimResult` as PX4 1.13-1.14 would log it: ``sensor_mag``
(or ``vehicle_magnetometer``) per compass with CAL_MAGn_ID device ids, ``sensor_combined``,
``vehicle_attitude``, ``actuator_outputs`` (PWM us) with PWM_MAIN_FUNCn / PWM_MAIN_MINn / MAXn,
``battery_status``, ``vehicle_gps_position`` (lat/lon 1e-7 deg, alt mm, time_utc_usec), ``vehicle_status``.
The values are the simulator's samples at the units of the tlog twin (same quantisation), so a replay of
both gives the same headings.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.files import write_file
from magcomp.adapters.sim_log_rows import (
    default_start_unix_s,
    px4_motor_outputs,
    px4_outputs,
    quantised_imu,
    rate_indices,
)

if TYPE_CHECKING:
    from magcomp.sim.simulate import SimResult

MAGIC = b"ULog\x01\x12\x35"
_TYPES = {
    "int8_t": "b",
    "uint8_t": "B",
    "int16_t": "h",
    "uint16_t": "H",
    "int32_t": "i",
    "uint32_t": "I",
    "int64_t": "q",
    "uint64_t": "Q",
    "float": "f",
    "double": "d",
    "bool": "?",
    "char": "c",
}


def _msg(kind: str, payload: bytes) -> bytes:
    if len(payload) > 0xFFFF:
        raise ValueError("ULog message too long")
    return struct.pack("<HB", len(payload), ord(kind)) + payload


@dataclass
class _Topic:
    name: str
    fields: list[tuple[str, str, int]]  # (type, name, array length or 0)
    struct: struct.Struct
    msg_ids: dict[int, int] = field(default_factory=dict)  # multi_id -> msg_id


class UlogWriter:
    """Build a ULog in memory: :meth:`topic` (format), :meth:`info`, :meth:`param`, then :meth:`data` and
    :meth:`param_change` in time order, then :meth:`write`. The first field of every topic is
    ``uint64_t timestamp`` (added when missing)."""

    def __init__(self, start_us: int = 0) -> None:
        self.start_us = int(start_us)
        self._definitions: list[bytes] = []
        self._data: list[bytes] = []
        self._topics: dict[str, _Topic] = {}
        self._next_id = 0

    def topic(self, name: str, fields: Sequence[tuple[str, str]]) -> None:
        """Define a topic: ``fields`` as (type, name) with "float[3]"-style arrays, e.g. ("float[3]", "x")."""
        parsed: list[tuple[str, str, int]] = []
        if not fields or fields[0] != ("uint64_t", "timestamp"):
            fields = [("uint64_t", "timestamp"), *fields]
        fmt = "<"
        for ftype, fname in fields:
            base, _, rest = ftype.partition("[")
            count = int(rest.rstrip("]")) if rest else 0
            code = _TYPES[base]
            fmt += f"{count}{code}" if count else code
            parsed.append((base, fname, count))
        text = name + ":" + "".join(f"{t}[{c}] {n};" if c else f"{t} {n};" for t, n, c in parsed)
        self._definitions.append(_msg("F", text.encode()))
        self._topics[name] = _Topic(name, parsed, struct.Struct(fmt))

    def info(self, key: str, value: str) -> None:
        raw = value.encode()
        k = f"char[{len(raw)}] {key}".encode()
        self._definitions.append(_msg("I", bytes([len(k)]) + k + raw))

    @staticmethod
    def _param_payload(name: str, value: float, is_int: bool) -> bytes:
        key = f"{'int32_t' if is_int else 'float'} {name}".encode()
        raw = struct.pack("<i", int(value)) if is_int else struct.pack("<f", float(value))
        return bytes([len(key)]) + key + raw

    def param(self, name: str, value: float, *, is_int: bool = False) -> None:
        self._definitions.append(_msg("P", self._param_payload(name, value, is_int)))

    def param_change(self, name: str, value: float, *, is_int: bool = False) -> None:
        """A parameter change in the data section (pyulog stamps it with the last data timestamp)."""
        self._data.append(_msg("P", self._param_payload(name, value, is_int)))

    def data(self, name: str, multi_id: int, values: Sequence[Any]) -> None:
        """One message of ``name`` instance ``multi_id``: ``values`` in field order (timestamp us first,
        arrays flattened in place)."""
        topic = self._topics[name]
        msg_id = topic.msg_ids.get(multi_id)
        if msg_id is None:
            msg_id = self._next_id
            self._next_id += 1
            topic.msg_ids[multi_id] = msg_id
            self._data.append(_msg("A", struct.pack("<BH", multi_id, msg_id) + name.encode()))
        self._data.append(_msg("D", struct.pack("<H", msg_id) + topic.struct.pack(*values)))

    def to_bytes(self) -> bytes:
        header = MAGIC + b"\x01" + struct.pack("<Q", self.start_us)
        flags = _msg("B", bytes(8) + bytes(8) + bytes(24))  # compat, incompat flags, appended offsets
        return header + flags + b"".join(self._definitions) + b"".join(self._data)

    def write(self, path: str | os.PathLike[str]) -> int:
        write_file(path, self.to_bytes())
        return len(self._data)


# --- the simulator's vehicle as PX4 logs it ----------------------------------------------------------------

MAG_DEVICE_IDS = (396825, 396809, 263178)  # device ids of the form PX4 drivers give (bus type/address/dev)
PX4_FN_MOTOR1 = 101


def _sensor_frames(w: UlogWriter, n_mag: int) -> list[tuple[Any, Any]]:
    """Per compass (R^T, offset gauss): a body-frame field ``m`` as its driver publishes it, ``R^T m +
    offset``, with the parameters PX4's calibration undoes it with (``write_sim_ulog``'s ``sensor_frame``)."""
    from magcomp.core.rotations import dcm_from_euler

    w.param("SENS_BOARD_ROT", 2, is_int=True)  # yaw 90 (PX4's rotation enum)
    out = []
    for j in range(n_mag):
        internal = j == 0
        w.param(f"CAL_MAG{j}_ROT", -1 if internal else 8, is_int=True)  # 8: roll 180
        r = dcm_from_euler(0.0, 0.0, math.pi / 2) if internal else dcm_from_euler(math.pi, 0.0, 0.0)
        off = np.array([0.08, -0.05, 0.12]) * (1 + j)
        for a, v in zip("XYZ", off, strict=True):
            w.param(f"CAL_MAG{j}_{a}OFF", float(v))
        out.append((r.T, off))
    return out


UlogEvent = tuple[int, int, str, int, list[Any]]


def write_sim_ulog(
    result: SimResult,
    path: str | os.PathLike[str],
    *,
    mag_topic: str = "sensor_mag",
    start_unix_s: float | None = None,
    sensor_frame: bool = False,
) -> int:
    """Write ``result`` as a PX4 ULog (see the module docstring); returns the number of data messages.

    ``mag_topic``: ``sensor_mag`` (x, y, z gauss), ``vehicle_magnetometer`` (magnetometer_ga[3]) or
    ``both`` (as PX4's default logging profile has them); the compasses are logged at the simulator's IMU
    rate, the attitude and outputs at their configured rates. ``sensor_frame``: ``sensor_mag`` as a PX4
    driver publishes it, before PX4's calibration: compass 0 internal on a board mounted yawed 90 deg
    (SENS_BOARD_ROT 2, CAL_MAG0_ROT -1), the others external and rolled 180 deg (CAL_MAGn_ROT 8), each with
    its CAL_MAGn_OFF offsets added (``vehicle_magnetometer`` stays in the body frame, calibrated).
    """
    if mag_topic not in ("sensor_mag", "vehicle_magnetometer", "both"):
        raise ValueError(f"mag_topic {mag_topic!r}: sensor_mag, vehicle_magnetometer or both")
    t_us = np.round(result.samples.t_s * 1e6).astype(np.int64)
    start_unix = default_start_unix_s(result) if start_unix_s is None else float(start_unix_s)
    n_mag = result.samples.mag_mgauss.shape[0]
    w = UlogWriter(start_us=int(t_us[0]))
    mag_topics = ("sensor_mag", "vehicle_magnetometer") if mag_topic == "both" else (mag_topic,)
    _define_topics(w, mag_topics)
    w.info("sys_name", "PX4")
    w.info("ver_hw", "MAGCOMP_SIM")
    w.info("sys_uuid", result.config.uid)
    for j in range(n_mag):
        w.param(f"CAL_MAG{j}_ID", MAG_DEVICE_IDS[j], is_int=True)
    raw_frame = _sensor_frames(w, n_mag) if sensor_frame else None
    motor_channels = px4_motor_outputs(result.config.vehicle)
    for ch in range(1, 9):
        w.param(f"PWM_MAIN_FUNC{ch}", PX4_FN_MOTOR1 + motor_channels.index(ch) if ch in motor_channels else 0,
                is_int=True)  # fmt: skip
        w.param(f"PWM_MAIN_MIN{ch}", 1000, is_int=True)
        w.param(f"PWM_MAIN_MAX{ch}", 2000, is_int=True)
    w.param("CA_ROTOR_COUNT", len(motor_channels), is_int=True)
    # every message with its time and a tie order like the tlog twin's (compass 0 with the IMU first)
    vtype = 1 if result.config.vehicle == "multirotor" else 2
    events: list[UlogEvent] = [(int(t_us[0]), -1, "vehicle_status", 0, [int(t_us[0]), vtype, 2])]
    events += _sensor_events(result, t_us, mag_topics, raw_frame)
    events += _attitude_output_events(result, t_us)
    events += _power_gps_events(result, t_us, start_unix)
    events.sort(key=lambda e: (e[0], e[1]))
    for _, _, name, multi, values in events:
        w.data(name, multi, values)
    return w.write(path)


def _define_topics(w: UlogWriter, mag_topics: tuple[str, ...]) -> None:
    if "sensor_mag" in mag_topics:
        w.topic("sensor_mag", [("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"), ("float", "x"),
                               ("float", "y"), ("float", "z"), ("float", "temperature"),
                               ("uint32_t", "error_count")])  # fmt: skip
    if "vehicle_magnetometer" in mag_topics:
        vm_fields = [
            ("uint64_t", "timestamp_sample"),
            ("uint32_t", "device_id"),
            ("float[3]", "magnetometer_ga"),
        ]
        w.topic("vehicle_magnetometer", [*vm_fields, ("uint8_t", "calibration_count")])
    sc_gyro = [("float[3]", "gyro_rad"), ("uint32_t", "gyro_integral_dt")]
    sc_acc = [("int32_t", "accelerometer_timestamp_relative"), ("float[3]", "accelerometer_m_s2")]
    w.topic("sensor_combined", [*sc_gyro, *sc_acc, ("uint32_t", "accelerometer_integral_dt")])
    w.topic("vehicle_attitude", [("uint64_t", "timestamp_sample"), ("float[4]", "q")])
    w.topic("actuator_outputs", [("uint32_t", "noutputs"), ("float[16]", "output")])
    w.topic("battery_status", [("float", "voltage_v"), ("float", "current_a"), ("bool", "connected")])
    w.topic("vehicle_gps_position", [("uint64_t", "time_utc_usec"), ("int32_t", "lat"), ("int32_t", "lon"),
                                     ("int32_t", "alt"), ("uint8_t", "fix_type")])  # fmt: skip
    w.topic("vehicle_status", [("uint8_t", "vehicle_type"), ("uint8_t", "arming_state")])


def _sensor_events(
    result: SimResult, t_us: NDArray[np.int64], mag_topics: tuple[str, ...], raw_frame: Any
) -> list[UlogEvent]:
    """sensor_combined (IMU 0) and the compasses at the loop rate, at the tlog twin's quantisation (gyro
    1 mrad/s, accel 1 mG, mag 1 mgauss)."""
    s = result.samples
    gyro, acc = (v[0] for v in quantised_imu(result))
    mag_ga = np.round(s.mag_mgauss) / 1000.0
    events: list[UlogEvent] = []
    for i in range(s.t_s.size):
        ti = int(t_us[i])
        events.append((ti, 1, "sensor_combined", 0, [ti, *gyro[i], 0, 0, *acc[i], 0]))
        for j in range(mag_ga.shape[0]):
            m = mag_ga[j, i]
            if "sensor_mag" in mag_topics:
                r = m if raw_frame is None else raw_frame[j][0] @ m + raw_frame[j][1]
                values = [ti, ti, MAG_DEVICE_IDS[j], r[0], r[1], r[2], float(s.imu_temp_degc[j, i]), 0]
                events.append((ti, 1 + j, "sensor_mag", j, values))
            if "vehicle_magnetometer" in mag_topics:
                values = [ti, ti, MAG_DEVICE_IDS[j], m[0], m[1], m[2], 0]
                events.append((ti, 1 + j, "vehicle_magnetometer", j, values))
    return events


def _attitude_output_events(result: SimResult, t_us: NDArray[np.int64]) -> list[UlogEvent]:
    from magcomp.core.rotations import quats_from_euler

    rates = result.config.rates
    att = result.samples.attitude_rad
    q = quats_from_euler(att[:, 0], att[:, 1], att[:, 2])
    events: list[UlogEvent] = []
    for i in rate_indices(t_us.size, rates.imu_hz, rates.attitude_hz):
        ti = int(t_us[i])
        events.append((ti, 4, "vehicle_attitude", 0, [ti, ti, *q[i]]))
    for i in rate_indices(t_us.size, rates.imu_hz, rates.servo_hz):
        out = px4_outputs(result, int(i), 16)
        events.append((int(t_us[i]), 5, "actuator_outputs", 0, [int(t_us[i]), 8, *out]))
    return events


def _power_gps_events(result: SimResult, t_us: NDArray[np.int64], start_unix: float) -> list[UlogEvent]:
    """battery_status and vehicle_gps_position (the home location, a 3D fix) at power_hz."""
    s = result.samples
    rates, loc = result.config.rates, result.config.location
    events: list[UlogEvent] = []
    for i in rate_indices(t_us.size, rates.imu_hz, rates.power_hz):
        ti = int(t_us[i])
        volt = round(float(s.voltage_v[i]) * 1000.0) / 1000.0
        curr = round(float(s.current_a[i]) * 100.0) / 100.0
        events.append((ti, 8, "battery_status", 0, [ti, volt, curr, True]))
        utc_us = round((start_unix + s.t_s[i]) * 1e6)
        gps = [
            ti,
            utc_us,
            round(loc.lat_deg * 1e7),
            round(loc.lon_deg * 1e7),
            round(float(s.alt_m[i]) * 1e3),
            3,
        ]
        events.append((ti, 9, "vehicle_gps_position", 0, gps))
    return events
