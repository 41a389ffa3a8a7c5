"""Decoded MAVLink and DataFlash messages turned into records: the typed samples of
:mod:`magcomp.core.types` in the module's fixed units (see :mod:`magcomp.adapters.mavlink_source`), plus raw
PWM and throttle records that the source turns into throttle samples once the throttle source is known.
"""

from __future__ import annotations

import math
import operator
import re
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np

from magcomp.adapters.ardupilot_motcomp import OnboardMotorComp
from magcomp.adapters.dataflash_read import DATAFLASH_MAX_INSTANCES
from magcomp.adapters.gnss_time import decimal_year_from_gps, decimal_year_from_unix
from magcomp.adapters.param_values import param_value
from magcomp.adapters.stream_clock import SourceClock
from magcomp.adapters.wire_samples import Float3, WireAttitudeSample, WireImuSample, WireMagSample
from magcomp.core.autopilot_params import motor_comp_known_off
from magcomp.core.identity import uid_from_autopilot_version, uid_from_board_msg
from magcomp.core.types import (
    AttitudeSample,
    HeartbeatSample,
    IdentitySample,
    ImuSample,
    MagSample,
    ParamSample,
    PositionSample,
    PowerSample,
    Sample,
    TemperatureSample,
    TimeSample,
)

G_M_S2 = 9.80665
_MG_TO_M_S2 = G_M_S2 * 1e-3
MAV_AUTOPILOT_INVALID = 8
MAV_AUTOPILOT_PX4 = 12
HIGHRES_ACCEL_GYRO = 0x3F  # HIGHRES_IMU_UPDATED_FLAGS: X/Y/Z ACC (1, 2, 4), X/Y/Z GYRO (8, 16, 32)
HIGHRES_MAG = 0x1C0  # X/Y/Z MAG (64, 128, 256)
HIGHRES_TEMPERATURE = 0x1000
MAV_TYPE_GCS = 6

WANTED_MAVLINK = (
    "HEARTBEAT",
    "SYS_STATUS",
    "PARAM_VALUE",
    "SCALED_IMU",
    "RAW_IMU",
    "SCALED_PRESSURE",
    "ATTITUDE",
    "SERVO_OUTPUT_RAW",
    "RC_CHANNELS",
    "RC_CHANNELS_RAW",  # only for the clock offsets: ArduPilot sends it right after SERVO_OUTPUT_RAW
    "VFR_HUD",
    "SCALED_IMU2",
    "SCALED_IMU3",
    "BATTERY_STATUS",
    "GPS_RAW_INT",
    "GLOBAL_POSITION_INT",
    "SYSTEM_TIME",
    "HIGHRES_IMU",
    "ATTITUDE_QUATERNION",
    "ACTUATOR_OUTPUT_STATUS",
    "AUTOPILOT_VERSION",
)
_SERVO_FIELDS = tuple(f"servo{i}_raw" for i in range(1, 17))
_IMU_SENSOR_NAMES = tuple(f"imu{i}" for i in range(256))  # RAW_IMU.id is a uint8
_servo_values = operator.attrgetter(*_SERVO_FIELDS)
_RC_FIELDS = tuple(f"chan{i}_raw" for i in range(1, 19))
_PWM_COLUMN = re.compile(r"^(?:C|Ch|Chan)(\d+)$")


@dataclass(frozen=True, slots=True)
class PwmRecord:
    """Raw PWM (us) by 1-based channel: ``kind`` "servo" (outputs) or "rc" (inputs)."""

    t_s: float
    kind: str
    pwm_us: dict[int, float]


@dataclass(frozen=True, slots=True)
class ThrottleRecord:
    """A throttle that is already 0..1: ``kind`` "vfr_hud" or "ctun"."""

    t_s: float
    kind: str
    throttle_01: float


Record = Sample | PwmRecord | ThrottleRecord


class Counts(dict[str, int]):
    """A dict of counters whose missing keys read as 0 (and are created on first increment)."""

    def __missing__(self, key: str) -> int:
        return 0


def _finite(*values: float) -> bool:
    return all(map(math.isfinite, values))


def _vec(x: float, y: float, z: float, scale: float = 1.0) -> np.ndarray:
    return np.array([x * scale, y * scale, z * scale], dtype=np.float64)


class MessageConverter:
    """Turns decoded messages (MAVLink or DataFlash) into records; holds the clock and what is known so
    far."""

    def __init__(
        self,
        counts: dict[str, int],
        *,
        mag_index: int | None,
        undo_motor_comp: bool,
        pipeline_only: bool = False,
        rc_pwm: bool = True,
    ) -> None:
        self.counts = counts
        # pipeline_only: leave out the samples the heading pipeline ignores (temperature, power, IMUs other
        # than IMU 0), counted in ``skipped`` instead: a replay built and dispatched ~96k of them per 10 min
        self.pipeline_only = pipeline_only
        # rc_pwm: RC_CHANNELS become PWM records (False: only their clock is read; for a source whose
        # throttle can never be the RC inputs', i.e. not ``--throttle-source rc``: "auto" never picks them)
        self.rc_pwm = rc_pwm
        self.skipped = 0
        self.clock = SourceClock(counts)
        self.mag_index = mag_index
        self.undo_motor_comp = undo_motor_comp
        # ArduPilot's COMPASS_MOTCT compensation in MAVLink compass fields (see ardupilot_motcomp)
        self.onboard_comp = OnboardMotorComp()
        self.seen_raw_imu = False
        self.seen_highres_imu = False  # PX4: HIGHRES_IMU is IMU 0; SCALED_IMU then adds only its compass
        self.seen_scaled_mag0 = False  # a compass 0 in SCALED_IMU shadows HIGHRES_IMU's
        self.seen_attitude = False  # ATTITUDE shadows ATTITUDE_QUATERNION
        self.seen_servo_output = False  # SERVO_OUTPUT_RAW shadows ACTUATOR_OUTPUT_STATUS
        self.sys_status_current = False
        self.servo_pwm: dict[int, float] = {}
        self.vehicle_type = -1
        self.autopilot = -1
        self.system_id = -1
        self.uid: str | None = None  # the vehicle's unique id (magcomp.core.identity)
        self._pwm_columns: dict[str, list[tuple[str, int]]] = {}
        self._df_converters: dict[int, tuple[Any, list[tuple[str, int, Any, float]]]] = {}

    def _keep(self) -> bool:
        """False (and the sample counted as skipped) for a sample only a pipeline-only source leaves out."""
        if self.pipeline_only:
            self.skipped += 1
            return False
        return True

    # --- MAVLink -----------------------------------------------------------------------------------------
    def mavlink(self, msg: Any) -> list[tuple[str, Record]]:
        """A pymavlink message (a live link's, or the tests' reference decode): its arrival time, when it
        has one, is the receive time of :class:`StreamOffsets`."""
        rx = getattr(msg, "_timestamp", None)
        if rx is not None:
            self.clock.rx_s = float(rx)
            self.clock.rx_src = int(msg.get_srcSystem())
        mtype = msg.get_type()
        handler = getattr(self, f"_m_{mtype}", None)
        return handler(msg) if handler is not None else []

    def _imu_mag(self, origin: str, t_s: float, msg: Any, index: int) -> list[tuple[str, Record]]:
        out: list[tuple[str, Record]] = []
        if index == 0 or self._keep():  # (a left-out IMU's vectors are not even scaled)
            gyro = (msg.xgyro * 1e-3, msg.ygyro * 1e-3, msg.zgyro * 1e-3)  # mrad/s -> rad/s
            accel = (msg.xacc * _MG_TO_M_S2, msg.yacc * _MG_TO_M_S2, msg.zacc * _MG_TO_M_S2)  # mG
            out.append((origin, WireImuSample(t_s, gyro, accel, index)))
        xmag, ymag, zmag = msg.xmag, msg.ymag, msg.zmag
        if not (xmag or ymag or zmag):  # (0, 0, 0): no compass data in this message
            self.counts["mag_zero"] += 1
        elif self.mag_index is None or self.mag_index == index:
            fx, fy, fz = float(xmag), float(ymag), float(zmag)  # mgauss
            onboard: Float3 | None = None
            if self.undo_motor_comp and self.onboard_comp.params and self.autopilot != MAV_AUTOPILOT_PX4:
                o = self.onboard_comp.offset(index, self.counts)
                if o is not None:  # the autopilot added o (COMPASS_MOTCT): the field the motors disturbed
                    fx, fy, fz = fx - o[0], fy - o[1], fz - o[2]
                    onboard = (float(o[0]), float(o[1]), float(o[2]))
                    self.counts["motor_comp_removed"] += 1
            out.append((origin, WireMagSample(t_s, (fx, fy, fz), index, onboard)))
        temp = getattr(msg, "temperature", 0)
        if temp and self._keep():  # 0 = not provided (common.xml)
            out.append((origin, TemperatureSample(t_s, temp * 0.01, _IMU_SENSOR_NAMES[index])))
        return out

    def _m_RAW_IMU(self, msg: Any) -> list[tuple[str, Record]]:
        self.seen_raw_imu = True
        t_s = self.clock.stamp("RAW_IMU", msg.time_usec * 1e-6)
        return [] if t_s is None else self._imu_mag("RAW_IMU", t_s, msg, int(getattr(msg, "id", 0)))

    def _m_SCALED_IMU(self, msg: Any) -> list[tuple[str, Record]]:
        if self.seen_raw_imu:
            self.counts["scaled_imu_shadowed"] += 1
            return []
        t_s = self.clock.stamp("SCALED_IMU", msg.time_boot_ms * 1e-3)
        if t_s is None:
            return []
        out = self._imu_mag("SCALED_IMU", t_s, msg, 0)
        return (
            self._px4_scaled_imu(out) if self.seen_highres_imu or self.autopilot == MAV_AUTOPILOT_PX4 else out
        )

    def _m_SCALED_IMU2(self, msg: Any) -> list[tuple[str, Record]]:
        t_s = self.clock.stamp("SCALED_IMU2", msg.time_boot_ms * 1e-3)
        return [] if t_s is None else self._imu_mag("SCALED_IMU2", t_s, msg, 1)

    def _m_SCALED_IMU3(self, msg: Any) -> list[tuple[str, Record]]:
        t_s = self.clock.stamp("SCALED_IMU3", msg.time_boot_ms * 1e-3)
        return [] if t_s is None else self._imu_mag("SCALED_IMU3", t_s, msg, 2)

    def _m_ATTITUDE(self, msg: Any) -> list[tuple[str, Record]]:
        if not _finite(msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed):
            self.counts["nonfinite"] += 1
            return []
        t_s = self.clock.stamp("ATTITUDE", msg.time_boot_ms * 1e-3)
        if t_s is None:
            return []
        self.seen_attitude = True
        rates = (float(msg.rollspeed), float(msg.pitchspeed), float(msg.yawspeed))
        att = WireAttitudeSample(t_s, float(msg.roll), float(msg.pitch), float(msg.yaw), rates)
        return [("ATTITUDE", att)]

    def _m_SERVO_OUTPUT_RAW(self, msg: Any) -> list[tuple[str, Record]]:
        self.seen_servo_output = True
        t_s = self.clock.stamp("SERVO_OUTPUT_RAW", self.clock.unwrap_u32_us(msg.time_usec))
        if t_s is None:
            return []
        base = 8 * int(msg.port)
        try:
            values = _servo_values(msg)
        except AttributeError:  # a message class without the servo9..16 extension
            values = tuple(getattr(msg, name, 0) for name in _SERVO_FIELDS)
        pwm = self.servo_pwm
        # servo1..8 (a loop: 0.4 us, dict.update of a zip 0.85 us)
        for channel, value in zip(range(base + 1, base + 9), values, strict=False):
            pwm[channel] = float(value)
        if base == 0 and any(values[8:]):  # servo9..16 are an extension: 0 when the sender does not fill them
            pwm.update((channel, float(value)) for channel, value in enumerate(values[8:], start=9) if value)
        return [("SERVO_OUTPUT_RAW", PwmRecord(t_s, "servo", dict(self.servo_pwm)))]

    def _m_RC_CHANNELS(self, msg: Any) -> list[tuple[str, Record]]:
        t_s = self.clock.stamp("RC_CHANNELS", msg.time_boot_ms * 1e-3)
        if t_s is None or not self.rc_pwm:
            return []
        pwm = {}
        for i, name in enumerate(_RC_FIELDS[: min(int(msg.chancount), 18)], start=1):
            value = getattr(msg, name)
            if value != 0xFFFF:
                pwm[i] = float(value)
        return [("RC_CHANNELS", PwmRecord(t_s, "rc", pwm))]

    def _m_RC_CHANNELS_RAW(self, msg: Any) -> list[tuple[str, Record]]:
        self.clock.observe("RC_CHANNELS_RAW", msg.time_boot_ms * 1e-3)  # pairs with SERVO_OUTPUT_RAW
        return []

    def _m_VFR_HUD(self, msg: Any) -> list[tuple[str, Record]]:
        thr = min(1.0, max(0.0, float(msg.throttle) * 0.01))  # percent -> 0..1
        self.onboard_comp.throttle_01 = thr
        return [("VFR_HUD", ThrottleRecord(self.clock.last_t_s, "vfr_hud", thr))]

    def _m_SYS_STATUS(self, msg: Any) -> list[tuple[str, Record]]:
        volt = msg.voltage_battery * 1e-3 if msg.voltage_battery not in (0xFFFF, -1) else math.nan
        curr = msg.current_battery * 0.01 if msg.current_battery >= 0 else math.nan
        if math.isnan(volt) and math.isnan(curr):
            return []
        if not math.isnan(curr):
            self.sys_status_current = True
            self.onboard_comp.current_a = curr
        return [("SYS_STATUS", PowerSample(self.clock.last_t_s, volt, curr, 0))] if self._keep() else []

    def _m_BATTERY_STATUS(self, msg: Any) -> list[tuple[str, Record]]:
        index = int(msg.id)
        if index == 0 and self.sys_status_current:
            return []
        if not self._keep():
            return []
        cells = [v for v in msg.voltages if v != 0xFFFF]
        cells += [v for v in getattr(msg, "voltages_ext", ()) if v not in (0, 0xFFFF)]
        volt = sum(cells) * 1e-3 if cells else math.nan
        curr = msg.current_battery * 0.01 if msg.current_battery >= 0 else math.nan
        return [("BATTERY_STATUS", PowerSample(self.clock.last_t_s, volt, curr, index))]

    def _m_SCALED_PRESSURE(self, msg: Any) -> list[tuple[str, Record]]:
        t_s = self.clock.stamp("SCALED_PRESSURE", msg.time_boot_ms * 1e-3)
        if t_s is None:
            return []
        if not self._keep():
            return []
        return [("SCALED_PRESSURE", TemperatureSample(t_s, msg.temperature * 0.01, "baro"))]

    def _m_HEARTBEAT(self, msg: Any) -> list[tuple[str, Record]]:
        if msg.autopilot == MAV_AUTOPILOT_INVALID or msg.type == MAV_TYPE_GCS:
            return []  # a GCS, companion computer, gimbal... not the vehicle
        self.vehicle_type, self.autopilot = int(msg.type), int(msg.autopilot)
        self.system_id = int(msg.get_srcSystem())
        hb = HeartbeatSample(self.clock.last_t_s, self.vehicle_type, self.autopilot, self.system_id)
        return [("HEARTBEAT", hb)]

    def _m_AUTOPILOT_VERSION(self, msg: Any) -> list[tuple[str, Record]]:
        uid = uid_from_autopilot_version(int(msg.uid), getattr(msg, "uid2", None))
        if uid is None or uid == self.uid:  # (sent again on every request: said once)
            return []
        self.uid = uid
        return [("AUTOPILOT_VERSION", IdentitySample(self.clock.last_t_s, uid, int(msg.get_srcSystem())))]

    def _m_PARAM_VALUE(self, msg: Any) -> list[tuple[str, Record]]:
        name = msg.param_id
        if isinstance(name, bytes):
            name = name.decode("ascii", "replace")
        name = name.rstrip("\x00")
        value = param_value(float(msg.param_value), int(msg.param_type), self.autopilot == MAV_AUTOPILOT_PX4)
        self.onboard_comp.param(name, value)  # (a NaN COMPASS_MOT* is reported there as invalid)
        return [("PARAM_VALUE", ParamSample(self.clock.last_t_s, name, value))]

    # --- PX4 (MAV_AUTOPILOT_PX4): HIGHRES_IMU, ATTITUDE_QUATERNION, ACTUATOR_OUTPUT_STATUS ---------------
    def _px4_scaled_imu(self, out: list[tuple[str, Record]]) -> list[tuple[str, Record]]:
        """SCALED_IMU of a vehicle that also sends HIGHRES_IMU: its compass only (mgauss, as ArduPilot's;
        it then shadows HIGHRES_IMU's compass 0), not a second IMU 0 stream."""
        kept: list[tuple[str, Record]] = []
        for origin, rec in out:
            if isinstance(rec, ImuSample):
                if self.seen_highres_imu:
                    continue
            elif isinstance(rec, MagSample):
                self.seen_scaled_mag0 = True
            kept.append((origin, rec))
        return kept

    def _m_HIGHRES_IMU(self, msg: Any) -> list[tuple[str, Record]]:
        """accel m/s^2, gyro rad/s, mag gauss -> mgauss; only the fields ``fields_updated`` flags as new."""
        self.seen_highres_imu = True
        updated = int(msg.fields_updated)
        t_s = self.clock.stamp("HIGHRES_IMU", msg.time_usec * 1e-6)
        if t_s is None:
            return []
        out: list[tuple[str, Record]] = []
        index = int(getattr(msg, "id", 0))
        if updated & HIGHRES_ACCEL_GYRO == HIGHRES_ACCEL_GYRO:
            gyro = (float(msg.xgyro), float(msg.ygyro), float(msg.zgyro))
            accel = (float(msg.xacc), float(msg.yacc), float(msg.zacc))
            if _finite(*gyro, *accel):
                out.append(("HIGHRES_IMU", WireImuSample(t_s, gyro, accel, index)))
            else:
                self.counts["nonfinite"] += 1
        if updated & HIGHRES_MAG == HIGHRES_MAG:
            mag = (msg.xmag * 1000.0, msg.ymag * 1000.0, msg.zmag * 1000.0)  # gauss -> mgauss
            if self.seen_scaled_mag0:
                self.counts["highres_mag_shadowed"] += 1
            elif not _finite(*mag):
                self.counts["nonfinite"] += 1
            elif not any(mag):
                self.counts["mag_zero"] += 1
            elif self.mag_index is None or self.mag_index == index:
                out.append(("HIGHRES_IMU", WireMagSample(t_s, mag, index)))
        if updated & HIGHRES_TEMPERATURE and math.isfinite(msg.temperature) and self._keep():
            out.append(
                ("HIGHRES_IMU", TemperatureSample(t_s, float(msg.temperature), _IMU_SENSOR_NAMES[index]))
            )
        return out

    def _m_ATTITUDE_QUATERNION(self, msg: Any) -> list[tuple[str, Record]]:
        if self.seen_attitude:
            return []
        q = (msg.q1, msg.q2, msg.q3, msg.q4)  # w, x, y, z
        if not _finite(*q, msg.rollspeed, msg.pitchspeed, msg.yawspeed) or sum(v * v for v in q) < 0.25:
            self.counts["nonfinite"] += 1
            return []
        t_s = self.clock.stamp("ATTITUDE_QUATERNION", msg.time_boot_ms * 1e-3)
        if t_s is None:
            return []
        from magcomp.core.rotations import euler_from_quat

        norm = math.sqrt(sum(v * v for v in q))
        roll, pitch, yaw = euler_from_quat(np.array(q, dtype=np.float64) / norm)
        rates = _vec(msg.rollspeed, msg.pitchspeed, msg.yawspeed)
        return [("ATTITUDE", AttitudeSample(t_s, float(roll), float(pitch), float(yaw), rates))]

    def _m_ACTUATOR_OUTPUT_STATUS(self, msg: Any) -> list[tuple[str, Record]]:
        """PX4's actuator outputs (PWM us on PWM outputs), as servo channels 1..32 while no
        SERVO_OUTPUT_RAW is seen; inactive outputs (``active`` bit clear) are left out."""
        if self.seen_servo_output:
            return []
        t_s = self.clock.stamp("ACTUATOR_OUTPUT_STATUS", msg.time_usec * 1e-6)
        if t_s is None:
            return []
        active = int(msg.active)
        pwm = {
            ch: float(v)
            for ch, v in enumerate(msg.actuator, start=1)
            if active >> (ch - 1) & 1 and math.isfinite(v)
        }
        return [("ACTUATOR_OUTPUT_STATUS", PwmRecord(t_s, "servo", pwm))]

    # --- position and UTC time (for the Earth-field model at the vehicle) ----------------------------------
    # Stamped with the latest source time: GPS_RAW_INT.time_usec may be Unix time or time since boot, and
    # a position needs no sub-second timing.
    def _m_GPS_RAW_INT(self, msg: Any) -> list[tuple[str, Record]]:
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7  # degE7
        fix_ok = int(msg.fix_type) >= 3 and (msg.lat != 0 or msg.lon != 0) and abs(lat) <= 90.0
        year = decimal_year_from_unix(msg.time_usec * 1e-6)  # NaN for time since boot
        vel: tuple[float, float, float] | None = None
        if msg.vel != 65535 and msg.cog != 65535:  # UINT16_MAX: unknown; ground speed cm/s, course cdeg
            course = math.radians(msg.cog * 1e-2)
            ground = msg.vel * 1e-2
            vel = (ground * math.cos(course), ground * math.sin(course), math.nan)
        pos = PositionSample(self.clock.last_t_s, lat, lon, msg.alt * 1e-3, year, fix_ok, vel)  # alt mm MSL
        return [("GPS_RAW_INT", pos)]

    def _m_GLOBAL_POSITION_INT(self, msg: Any) -> list[tuple[str, Record]]:
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
        fix_ok = (msg.lat != 0 or msg.lon != 0) and abs(lat) <= 90.0  # (0, 0) before the EKF has an origin
        vel = (msg.vx * 1e-2, msg.vy * 1e-2, msg.vz * 1e-2)  # cm/s north, east, down
        pos = PositionSample(self.clock.last_t_s, lat, lon, msg.alt * 1e-3, fix_ok=fix_ok, vel_ned_m_s=vel)
        return [("GLOBAL_POSITION_INT", pos)]

    def _m_SYSTEM_TIME(self, msg: Any) -> list[tuple[str, Record]]:
        year = decimal_year_from_unix(msg.time_unix_usec * 1e-6)  # 0 / 1970 / 1980: clock not set
        return [] if math.isnan(year) else [("SYSTEM_TIME", TimeSample(self.clock.last_t_s, year))]

    # --- DataFlash -----------------------------------------------------------------------------------------
    def _df_values(self, msg: Any) -> SimpleNamespace:
        """Field values of a DFReader message, read once through cached converters.

        Same values as ``DFMessage.__getattr__`` (type conversion, then the format's multiplier), about 8x
        cheaper when several fields are read.
        """
        fmt = msg.fmt
        conv = self._df_converters.get(id(fmt))
        if conv is None or conv[0] is not fmt:
            cols = []
            for i, name in enumerate(fmt.columns):
                to_type = fmt.msg_types[i]
                if to_type is str or fmt.format[i] in "aZM" or to_type is bytes:
                    cols.append((name, i, None, 0.0))
                else:
                    cols.append((name, i, to_type, fmt.msg_mults[i] or 0.0))
            conv = (fmt, cols)
            self._df_converters[id(fmt)] = conv
        elements = msg._elements
        values: dict[str, Any] = {"mtype": fmt.name, "fieldnames": fmt.columns}
        for name, i, to_type, mult in conv[1]:
            if to_type is None:
                values[name] = getattr(msg, name)
            elif mult and msg._apply_multiplier:
                values[name] = to_type(elements[i]) * mult
            else:
                values[name] = to_type(elements[i])
        return SimpleNamespace(**values)

    def dataflash(self, msg: Any) -> list[tuple[str, Record]]:
        try:
            v = self._df_values(msg)
        except (ValueError, TypeError, OverflowError, IndexError):
            # a field that is not a number of its type (a text log line with NUL bytes or cut short):
            # the record is dropped and counted, the rest of the log is read
            self.counts["unreadable_records"] += 1
            return []
        mtype = v.mtype
        if mtype == "PARM":
            value = float(v.Value)
            self.onboard_comp.param(str(v.Name), value)  # (a NaN COMPASS_MOT* is reported there as invalid)
            return [("PARM", ParamSample(self.clock.last_t_s, str(v.Name), value))]
        if mtype == "MSG":
            return self._df_msg(str(v.Message))
        if mtype in ("GPS", "GPS2", "POS"):
            return self._df_position(v)
        if hasattr(v, "TimeUS"):
            raw_s = v.TimeUS * 1e-6
        elif hasattr(v, "TimeMS"):
            raw_s = v.TimeMS * 1e-3
        else:
            return []
        base = mtype.rstrip("0123456789")
        suffix = mtype[len(base) :]
        # the instance field: I (MAG, IMU, GPS), Inst (BAT in recent 4.x) or Instance (BAT in early 4.x)
        index = (
            int(getattr(v, "I", getattr(v, "Inst", getattr(v, "Instance", 0))))
            if not suffix
            else int(suffix) - 1
        )
        if base in ("MAG", "IMU") and not 0 <= index < DATAFLASH_MAX_INSTANCES:
            # DataFlash has no checksum: a corrupt instance byte would make a phantom compass or IMU
            self.counts["dataflash_bad_instance"] += 1
            return []
        stream = f"{base}{index}"
        if base == "MAG":
            return self._df_mag(v, stream, raw_s, index)
        if base == "IMU":
            return self._df_imu(v, stream, raw_s, index)
        if base == "ATT":
            if not _finite(v.Roll, v.Pitch, v.Yaw):
                self.counts["nonfinite"] += 1
                return []
            t_s = self.clock.stamp(stream, raw_s)
            if t_s is None:
                return []
            r, p, y = (math.radians(v) for v in (v.Roll, v.Pitch, v.Yaw))
            return [("ATT", AttitudeSample(t_s, r, p, y))]
        if base == "RCOU":
            return self._df_rcou(v, stream, raw_s)
        if base == "CTUN":
            if hasattr(v, "NavRoll"):  # Plane's CTUN: ThO (4.x) / ThrOut (3.x) in percent
                thr = float(getattr(v, "ThO", getattr(v, "ThrOut", math.nan))) * 0.01
            elif hasattr(v, "ThO"):
                thr = float(v.ThO)
            elif hasattr(v, "ThrOut"):
                thr = v.ThrOut * 1e-3 if isinstance(v.ThrOut, int) else float(v.ThrOut)
            else:
                return []
            t_s = self.clock.stamp(stream, raw_s)
            if t_s is None or not math.isfinite(thr):
                return []
            self.onboard_comp.throttle_01 = min(1.0, max(0.0, thr))  # the throttle the compass was given
            return [("CTUN", ThrottleRecord(t_s, "ctun", min(1.0, max(0.0, thr))))]
        if base in ("CURR", "BAT"):
            volt = v.Volt * 0.01 if isinstance(v.Volt, int) else float(v.Volt)  # old logs: cV, cA
            curr = v.Curr * 0.01 if isinstance(v.Curr, int) else float(v.Curr)
            t_s = self.clock.stamp(stream, raw_s)
            if t_s is None:
                return []
            return [(base, PowerSample(t_s, volt, curr, index))] if self._keep() else []
        return []

    def _df_position(self, v: Any) -> list[tuple[str, Record]]:
        """DataFlash GPS/GPS2 (Status >= 3 is a 3D fix; GPS week + ms of week -> UTC) and POS (EKF position).

        Old logs (ArduPilot <= 3.3) have TimeMS = GPS time of week, Week, and T = time since boot (ms);
        newer ones TimeUS, GMS and GWk. Lat/Lng are degrees after DFReader's 1e-7 multiplier; an integer
        column without it (text logs) is degE7. Stamped with the latest source time (see GPS_RAW_INT)."""
        lat, lon = getattr(v, "Lat", math.nan), getattr(v, "Lng", math.nan)
        alt = float(getattr(v, "Alt", math.nan))
        if isinstance(lat, int) and isinstance(lon, int) and (abs(lat) > 180 or abs(lon) > 360):
            lat, lon = lat * 1e-7, lon * 1e-7
        lat, lon = float(lat), float(lon)
        if not _finite(lat, lon):
            self.counts["nonfinite"] += 1
            return []
        known = (lat != 0.0 or lon != 0.0) and abs(lat) <= 90.0 and abs(lon) <= 180.0
        if v.mtype == "POS":
            return [("POS", PositionSample(self.clock.last_t_s, lat, lon, alt, fix_ok=known))]
        if hasattr(v, "GWk"):
            year = decimal_year_from_gps(float(v.GWk), float(v.GMS))
        elif hasattr(v, "Week") and hasattr(v, "TimeMS"):
            year = decimal_year_from_gps(float(v.Week), float(v.TimeMS))
        else:
            year = math.nan
        fix_ok = known and int(getattr(v, "Status", 0)) >= 3
        vel: tuple[float, float, float] | None = None
        spd, crs = float(getattr(v, "Spd", math.nan)), float(getattr(v, "GCrs", math.nan))
        if _finite(spd, crs):  # ground speed m/s, course deg; VZ m/s down (absent in old logs)
            c = math.radians(crs)
            vel = (spd * math.cos(c), spd * math.sin(c), float(getattr(v, "VZ", math.nan)))
        return [("GPS", PositionSample(self.clock.last_t_s, lat, lon, alt, year, fix_ok, vel))]

    def _df_msg(self, text: str) -> list[tuple[str, Record]]:
        uid = uid_from_board_msg(text)
        if uid is not None:
            if uid == self.uid:
                return []
            self.uid = uid
            return [("MSG", IdentitySample(self.clock.last_t_s, uid, 1))]
        lowered = text.lower()
        vtype = -1
        if "copter" in lowered:
            vtype = 2
        elif "plane" in lowered:
            vtype = 1
        elif "rover" in lowered:
            vtype = 10
        elif "sub" in lowered.split():
            vtype = 12
        if vtype < 0 or self.vehicle_type >= 0:
            return []
        self.vehicle_type, self.autopilot = vtype, 3  # MAV_AUTOPILOT_ARDUPILOTMEGA
        return [("MSG", HeartbeatSample(self.clock.last_t_s, vtype, 3, 1))]

    def _df_mag(self, v: Any, stream: str, raw_s: float, index: int) -> list[tuple[str, Record]]:
        if self.mag_index is not None and index != self.mag_index:
            return []
        field = _vec(v.MagX, v.MagY, v.MagZ)
        onboard: Float3 | None = None
        # the applied motor compensation: MOfsX/Y/Z in ArduPilot up to 4.0 (MAG, MAG2, MAG3), MOX/MOY/MOZ
        # since the instance field I (AP_Compass/LogStructure.h)
        mo = ("MOfsX", "MOfsY", "MOfsZ") if hasattr(v, "MOfsX") else ("MOX", "MOY", "MOZ")
        if self.undo_motor_comp and hasattr(v, mo[0]):
            mofs = _vec(*(getattr(v, a) for a in mo))
            if mofs.any() and np.isfinite(mofs).all():
                if self._df_motor_comp_off(index):
                    # the autopilot applied none (COMPASS_MOTCT = 0, no per-motor compensation): a corrupt
                    # record (DataFlash has no checksum), the logged field is the one it used
                    self.counts["motor_comp_ignored"] += 1
                else:
                    field = field - mofs
                    onboard = (float(mofs[0]), float(mofs[1]), float(mofs[2]))
                    self.counts["motor_comp_removed"] += 1
                    self.onboard_comp.record(index, mofs)
        if not np.isfinite(field).all():
            self.counts["nonfinite"] += 1
            return []
        if not field.any():  # (0, 0, 0): compass not read yet
            self.counts["mag_zero"] += 1
            return []
        t_s = self.clock.stamp(stream, raw_s)
        return [] if t_s is None else [("MAG", MagSample(t_s, field, index, onboard))]

    def _df_motor_comp_off(self, index: int) -> bool:
        """True when the logged parameters say the autopilot adds no motor offset to compass ``index``:
        COMPASS_MOTCT = 0 and, for compass 0, no per-motor compensation (COMPASS_PMOT_EN). Unknown parameters
        (none logged yet): False."""
        return motor_comp_known_off(self.onboard_comp.params, index)

    def _df_imu(self, v: Any, stream: str, raw_s: float, index: int) -> list[tuple[str, Record]]:
        gyro = _vec(v.GyrX, v.GyrY, v.GyrZ)
        accel = _vec(v.AccX, v.AccY, v.AccZ)
        if not (np.isfinite(gyro).all() and np.isfinite(accel).all()):
            self.counts["nonfinite"] += 1
            return []
        t_s = self.clock.stamp(stream, raw_s)
        if t_s is None:
            return []
        out: list[tuple[str, Record]] = []
        if index == 0 or self._keep():
            out.append(("IMU", ImuSample(t_s, gyro, accel, index)))
        temp = getattr(v, "T", getattr(v, "Temp", None))
        if temp is not None and temp != 0 and math.isfinite(temp) and self._keep():
            out.append(("IMU", TemperatureSample(t_s, float(temp), f"imu{index}")))
        return out

    def _df_rcou(self, v: Any, stream: str, raw_s: float) -> list[tuple[str, Record]]:
        cols = self._pwm_columns.get(v.mtype)
        if cols is None:
            cols = []
            for name in v.fieldnames:
                m = _PWM_COLUMN.match(name)
                if m:
                    cols.append((name, int(m.group(1))))
            self._pwm_columns[v.mtype] = cols
        t_s = self.clock.stamp(stream, raw_s)
        if t_s is None:
            return []
        return [("RCOU", PwmRecord(t_s, "servo", {ch: float(getattr(v, name)) for name, ch in cols}))]
