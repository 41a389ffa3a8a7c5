"""A simulated flight as ArduPilot 4.x logs it on board: a binary DataFlash ``.bin``.

Layout: every message is ``0xA3 0x95`` + a one-byte type + the packed fields (little endian, no padding).
Type 128 (FMT) defines each message: type, length (header included), a 4-char name, the format characters
and the comma-separated field names. The format characters are ArduPilot's: ``Q`` uint64, ``B`` uint8,
``h``/``H`` int16/uint16, ``i``/``I`` int32/uint32, ``f`` float, ``N`` char[16], ``Z`` char[64],
``c``/``C`` int16/uint16 x 0.01, ``e`` int32 x 0.01, ``L`` int32 x 1e-7 (latitude/longitude); the reader
(pymavlink's DFReader) applies the multipliers. As ArduPilot 4.x writes it, each FMT comes just before the
first message of its type, and UNIT / MULT / FMTU messages give every field's unit and multiplier (``#``
marks the instance field; the FMTU multipliers describe, DFReader does not apply them).

Messages and field lists (ArduPilot 4.x ``LogStructure.h``):
    PARM  TimeUS,Name,Value,Default               once at the start (the autopilot's parameters)
    MSG   TimeUS,Message                          "ArduCopter V4.5.7" / "ArduPlane V4.5.7"
    IMU   TimeUS,I,GyrX..AccZ,EG,EA,T,GH,AH,GHz,AHz  imu_hz, one per IMU instance (rad/s, m/s^2, degC)
    MAG   TimeUS,I,MagX..MagZ,OfsX..,MOX..,Health,S  per compass (mgauss after offsets and motor comp.)
    ATT   TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF   attitude_hz, degrees
    RCOU  TimeUS,C1..C14                          servo_hz, PWM us
    CTUN  Copter: TimeUS,ThI,ABst,ThO,... (ThO 0..1); Plane: TimeUS,NavRoll,...,ThO (percent)  servo_hz
    BAT   TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res   power_hz (V, A, mAh, Wh)
    GPS   TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U   gps_hz (GPS week / ms of week)

The samples are the simulator's at the tlog twin's quantisation (:func:`~magcomp.adapters.mavlink_emit.
write_tlog`: gyro 1 mrad/s, accel 1 mG, compass 1 mgauss, PWM 1 us, 1 mV, 10 mA) and the same parameters
(SERVOn_*, COMPASS_*), so a replay of both gives the same headings. ``motor_comp``: ArduPilot's own
throttle-based motor compensation (COMPASS_MOTCT = 1): per compass COMPASS_MOT*_X/Y/Z (mgauss per unit
throttle); the logged field then has ``MOX.. = mot * throttle`` added, as the autopilot does.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.files import write_file
from magcomp.adapters.sim_log_rows import (
    F64,
    compass_params,
    default_start_unix_s,
    elevons_pwm,
    pwm_us,
    quantised_imu,
    rate_indices,
    raw_imu_rows,
    servo_params,
    true_yaw_deg,
)
from magcomp.core.identity import board_msg

if TYPE_CHECKING:
    from magcomp.sim.simulate import SimResult

HEAD = b"\xa3\x95"
FMT_TYPE = 128
FIRMWARE_VERSION = "V4.5.7"
GPS_EPOCH_UNIX_S = 315_964_800  # 1980-01-06 00:00:00 UTC
GPS_LEAP_S = 18  # GPS - UTC since 2017
_STRUCT = {
    "b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d", "q": "q", "Q": "Q",
    "n": "4s", "N": "16s", "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I", "L": "i", "M": "B",
}  # fmt: skip

# CTUN of Copter and of Plane: (format characters, field names); ArduPilot 4.x
_COPTER_CTUN = ("Qffffffefffhh", "TimeUS,ThI,ABst,ThO,ThH,DAlt,Alt,BAlt,DSAlt,SAlt,TAlt,DCRt,CRt")
_PLANE_CTUN = ("QccccffffBffi", "TimeUS,NavRoll,Roll,NavPitch,Pitch,ThO,RdO,ThD,As,AsT,SAs,E2T,GU")
#: name -> (format characters, field names, units, multipliers) of the messages written; ArduPilot 4.x. The
#: units and multipliers are the FMTU's (``#`` the instance field), their ids' meanings in _UNITS / _MULTS
MESSAGES: dict[str, tuple[str, str, str, str]] = {
    "PARM": ("QNff", "TimeUS,Name,Value,Default", "s---", "F---"),
    "MSG": ("QZ", "TimeUS,Message", "s-", "F-"),
    "IMU": ("QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
            "s#EEEooo--O--zz", "F-000000-----00"),
    "MAG": ("QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S",
            "s#GGGGGGGGG-s", "F-CCCCCCCCC-F"),
    "ATT": ("QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF",
            "sddddhhdh-", "FBBBBBBBB-"),
    "RCOU": ("QHHHHHHHHHHHHHH", "TimeUS,C1,C2,C3,C4,C5,C6,C7,C8,C9,C10,C11,C12,C13,C14",
             "sYYYYYYYYYYYYYY", "F--------------"),
    "BAT": ("QBfffffcf", "TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res", "s#vvAaXOw", "F-000C0?0"),
    "GPS": ("QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U",
            "s#-s-S-DUmnhnh-", "F--C-0BGGB000--"),
}  # fmt: skip
#: name -> (format characters, field names)
FORMATS: dict[str, tuple[str, str]] = {name: (m[0], m[1]) for name, m in MESSAGES.items()}
_UNITS = {
    "-": "", "#": "instance", "s": "s", "E": "rad/s", "o": "m/s/s", "O": "degC", "z": "Hz", "G": "Gauss",
    "d": "deg", "h": "degheading", "Y": "us", "v": "V", "A": "A", "a": "Ah", "X": "Wh", "w": "Ohm",
    "S": "satellites", "D": "deglatitude", "U": "deglongitude", "m": "m", "n": "m/s",
}  # fmt: skip
_MULTS = {"-": 0.0, "?": 1.0, "0": 1.0, "B": 1e-2, "C": 1e-3, "F": 1e-6, "G": 1e-7}


class DataflashWriter:
    """Build a DataFlash log in memory: :meth:`define` each message (its FMT), then :meth:`add` messages in
    time order, then :meth:`write`. Values are given in the stored units (``c`` centi-units, ``L`` 1e-7).

    ``lazy_formats``: each FMT is written just before the first message of its type, as ArduPilot 4.x writes
    them (else all at the start). ``units``: UNIT and MULT tables and an FMTU (units and multipliers of
    every field, ``#`` the instance field) after each FMT defined with ``units`` / ``mults``, as 4.x logs
    have them (the multipliers there describe the fields; DFReader applies only the format characters')."""

    def __init__(self, *, lazy_formats: bool = False, units: bool = False) -> None:
        self._fmts: list[bytes] = []
        self._data: list[bytes] = []
        self._types: dict[str, tuple[int, struct.Struct]] = {}
        self._pending: dict[str, bytes] = {}
        self.lazy = lazy_formats
        self.units = units
        if units:
            self.define("UNIT", "QbZ", "TimeUS,Id,Label")
            self.define("MULT", "Qbd", "TimeUS,Id,Mult")
            self.define("FMTU", "QBNN", "TimeUS,FmtType,UnitIds,MultIds")
            if self.lazy:  # FMTU's own FMT first: an FMTU follows each later FMT
                self._data.append(self._pending.pop("FMTU"))
            for uid, label in _UNITS.items():
                self.add("UNIT", [0, ord(uid), label.encode()])
            for mid, mult in _MULTS.items():
                self.add("MULT", [0, ord(mid), mult])

    def define(self, name: str, fmt: str, columns: str, units: str = "", mults: str = "") -> None:
        if len(name) > 4 or len(fmt) > 16 or len(columns) > 64 or len(fmt) != len(columns.split(",")):
            raise ValueError(f"DataFlash format {name}: name <= 4, format <= 16, columns <= 64 chars")
        st = struct.Struct("<" + "".join(_STRUCT[c] for c in fmt))
        mtype = 129 + len(self._types)
        if mtype > 255:
            raise ValueError("too many DataFlash formats")
        self._types[name] = (mtype, st)
        body = struct.pack("<BB4s16s64s", mtype, 3 + st.size, name.encode(), fmt.encode(), columns.encode())
        out = HEAD + bytes([FMT_TYPE]) + body
        if self.units and units and mults:
            fmtu_type, fmtu = self._types["FMTU"]
            out += HEAD + bytes([fmtu_type]) + fmtu.pack(0, mtype, units.encode(), mults.encode())

        if self.lazy:
            self._pending[name] = out
        else:
            self._fmts.append(out)

    def add(self, name: str, values: Sequence[Any]) -> None:
        mtype, st = self._types[name]
        pending = self._pending.pop(name, None) if self.lazy else None
        if pending is not None:
            self._data.append(pending)
        self._data.append(HEAD + bytes([mtype]) + st.pack(*values))

    def to_bytes(self) -> bytes:
        cols = b"Type,Length,Name,Format,Columns"
        fmt_fmt = struct.pack("<BB4s16s64s", FMT_TYPE, 89, b"FMT", b"BBnNZ", cols)
        return HEAD + bytes([FMT_TYPE]) + fmt_fmt + b"".join(self._fmts) + b"".join(self._data)

    def write(self, path: str | os.PathLike[str]) -> int:
        write_file(path, self.to_bytes())
        return len(self._data)


def gps_week_ms(unix_s: float) -> tuple[int, int]:
    """GPS week and milliseconds of week of a UTC time (GPS time = UTC + 18 leap seconds)."""
    gps_ms = round((unix_s - GPS_EPOCH_UNIX_S + GPS_LEAP_S) * 1000.0)
    week, ms = divmod(gps_ms, 7 * 86_400_000)
    return int(week), int(ms)


def sim_parameters(result: SimResult, motor_comp: np.ndarray | None = None) -> list[tuple[str, float]]:
    """The parameters the simulated autopilot logs: the tlog twin's PARAM_VALUEs (SERVOn_*, COMPASS_*) plus
    COMPASS_USEn, MOT_PWM_MIN/MAX (multirotor), AHRS_EKF_TYPE, EK3_SRC1_YAW and, with ``motor_comp``,
    COMPASS_MOTCT = 1 and COMPASS_MOT*_X/Y/Z."""
    cfg = result.config
    params = dict(servo_params(cfg.vehicle))
    if not cfg.legacy:
        params.update(compass_params(result))
        use = 1.0 if cfg.variation.yaw_source == "compass" else 0.0
        for j in range(1, len(result.compasses)):
            params[f"COMPASS_USE{j + 1}"] = use
        params["AHRS_EKF_TYPE"] = 3.0
        params["EK3_SRC1_YAW"] = 1.0 if cfg.variation.yaw_source == "compass" else 2.0  # compass / GPS
        if motor_comp is not None:
            params["COMPASS_MOTCT"] = 1.0
            for j, mot in enumerate(motor_comp):
                prefix = "COMPASS_MOT_" if j == 0 else f"COMPASS_MOT{j + 1}_"
                for ax, val in zip("XYZ", mot, strict=True):
                    params[prefix + ax] = float(val)
    if cfg.vehicle == "multirotor":
        params["MOT_PWM_MIN"], params["MOT_PWM_MAX"] = 1000.0, 2000.0
    return sorted(params.items())


DfEvent = tuple[int, int, str, list[Any]]


def write_sim_dataflash(
    result: SimResult,
    path: str | os.PathLike[str],
    *,
    start_unix_s: float | None = None,
    motor_comp: Sequence[Sequence[float]] | np.ndarray | None = None,
    units: bool = True,
    lazy_formats: bool = True,
) -> int:
    """Write ``result`` as an ArduPilot 4.x DataFlash log (see the module docstring); returns the number of
    data messages. ``motor_comp``: (J, 3) COMPASS_MOT*_X/Y/Z, mgauss per unit throttle (COMPASS_MOTCT = 1),
    or None (COMPASS_MOTCT = 0). ``units`` (UNIT, MULT, FMTU messages) and ``lazy_formats`` (each FMT just
    before its first message) as ArduPilot 4.x writes them (:class:`DataflashWriter`); off: all FMT first,
    no units, as older logs."""
    s = result.samples
    n_mag = s.mag_mgauss.shape[0]
    mot = None
    if motor_comp is not None:
        mot = np.asarray(motor_comp, dtype=np.float64).reshape(-1, 3)
        if mot.shape[0] != n_mag or not np.isfinite(mot).all():
            raise ValueError(f"motor_comp: {n_mag} finite rows of COMPASS_MOT*_X/Y/Z expected")
    start_unix = default_start_unix_s(result) if start_unix_s is None else float(start_unix_s)
    w = DataflashWriter(units=units, lazy_formats=lazy_formats)
    for mname, (fmt, cols, field_units, mults) in MESSAGES.items():
        w.define(mname, fmt, cols, field_units, mults)
    w.define("CTUN", *(_COPTER_CTUN if result.config.vehicle == "multirotor" else _PLANE_CTUN))
    params = sim_parameters(result, mot)
    events = _df_start_events(result, params)
    events += _df_imu_events(result)
    events += _df_mag_events(result, params, mot)
    events += _df_att_events(result)
    events += _df_output_events(result)
    events += _df_bat_events(result)
    if s.gps is not None:
        events += _df_gps_events(result, start_unix)
    events.sort(key=lambda e: (e[0], e[1]))
    for _, _, name, values in events:
        w.add(name, values)
    return w.write(path)


def _t_us(result: SimResult) -> NDArray[np.int64]:
    return np.round(result.samples.t_s * 1e6).astype(np.int64)


def _throttle_given_01(result: SimResult) -> F64:
    """The throttle the compass was given, at the PWM's resolution (the tlog twin's 1 us)."""
    return (pwm_us(result.samples.throttle_01) - 1000) / 1000.0  # type: ignore[no-any-return]


def _df_start_events(result: SimResult, params: list[tuple[str, float]]) -> list[DfEvent]:
    """The firmware and board MSG lines and every PARM, at the first sample's time."""
    t0 = int(_t_us(result)[0])
    vehicle = "ArduCopter" if result.config.vehicle == "multirotor" else "ArduPlane"
    events: list[DfEvent] = [
        (t0, -2, "MSG", [t0, f"{vehicle} {FIRMWARE_VERSION}".encode()]),
        (t0, -2, "MSG", [t0, board_msg(result.config.uid).encode()]),  # the board's unique id
    ]
    for pname, value in params:
        events.append((t0, -1, "PARM", [t0, pname.encode(), float(value), float(value)]))
    return events


def _df_imu_events(result: SimResult) -> list[DfEvent]:
    s = result.samples
    imu_hz = int(result.config.rates.imu_hz)
    t_us = _t_us(result)
    gyro, acc = quantised_imu(result)
    events: list[DfEvent] = []
    for i in range(s.t_s.size):
        ti = int(t_us[i])
        for k in range(gyro.shape[0]):
            temp = round(float(s.imu_temp_degc[k, i]) * 100.0) / 100.0
            events.append((ti, 1, "IMU", [ti, k, *gyro[k, i], *acc[k, i], 0, 0, temp, 1, 1, imu_hz, imu_hz]))
    return events


def _df_mag_events(result: SimResult, params: list[tuple[str, float]], mot: F64 | None) -> list[DfEvent]:
    """MAG per compass: the field plus the autopilot's motor compensation ``MOX.. = mot * throttle`` (the
    throttle last sent with the outputs), and the logged COMPASS_OFS offsets."""
    s = result.samples
    rates = result.config.rates
    n = s.t_s.size
    n_mag = s.mag_mgauss.shape[0]
    t_us = _t_us(result)
    mag = np.round(s.mag_mgauss).astype(np.int64)
    thr_01 = _throttle_given_01(result)
    pdict = dict(params)
    ofs = {}
    for j in range(n_mag):
        sfx = "" if j == 0 else str(j + 1)
        ofs[j] = np.array([pdict.get(f"COMPASS_OFS{sfx}_{a}", 0.0) for a in "XYZ"])
    mag_rows = raw_imu_rows(result) if rates.mag_hz is None else rate_indices(n, rates.imu_hz, rates.mag_hz)
    last_thr = 0.0
    thr_rows = set(rate_indices(n, rates.imu_hz, rates.servo_hz).tolist())
    events: list[DfEvent] = []
    for i in mag_rows:
        ti = int(t_us[i])
        if i in thr_rows or last_thr == 0.0:
            last_thr = float(thr_01[i])
        for j in range(n_mag):
            mo = np.zeros(3, dtype=np.int64) if mot is None else np.round(mot[j] * last_thr).astype(np.int64)
            field = mag[j, i] + mo
            ofs_j = [round(float(v)) for v in ofs[j]]
            values = [ti, j, *(int(v) for v in field), *ofs_j, *(int(v) for v in mo), 1, ti & 0xFFFFFFFF]
            events.append((ti, 2 + j, "MAG", values))
    return events


def _df_att_events(result: SimResult) -> list[DfEvent]:
    t_us = _t_us(result)
    att_deg = np.degrees(result.samples.attitude_rad)
    events: list[DfEvent] = []
    for i in rate_indices(t_us.size, result.config.rates.imu_hz, result.config.rates.attitude_hz):
        ti = int(t_us[i])
        r, p, y = (float(v) for v in att_deg[i])
        r_c, p_c, y_c = round(r * 100.0), round(p * 100.0), round(y * 100.0) % 36000
        events.append((ti, 6, "ATT", [ti, r_c, r_c, p_c, p_c, y_c, y_c, 2, 5, 3]))
    return events


def _df_output_events(result: SimResult) -> list[DfEvent]:
    """RCOU (motors 1-4, or elevons 1/2 and throttle 3) and CTUN (Copter: ThO 0..1; Plane: percent)."""
    s = result.samples
    multirotor = result.config.vehicle == "multirotor"
    t_us = _t_us(result)
    att_deg = np.degrees(s.attitude_rad)
    pwm_motor = pwm_us(s.motors_01)
    pwm_thr = pwm_us(s.throttle_01)
    thr_01 = _throttle_given_01(result)
    elevon_l, elevon_r = elevons_pwm(result)
    events: list[DfEvent] = []
    for i in rate_indices(t_us.size, result.config.rates.imu_hz, result.config.rates.servo_hz):
        ti = int(t_us[i])
        ch = [0] * 14
        if multirotor:
            ch[0:4] = [int(v) for v in pwm_motor[i, :4]]
        else:
            ch[0], ch[1], ch[2] = int(elevon_l[i]), int(elevon_r[i]), int(pwm_thr[i])
        events.append((ti, 7, "RCOU", [ti, *ch]))
        alt = float(s.alt_m[i])
        if multirotor:
            tho = float(thr_01[i])
            climb_cm = round(float(s.climb_m_s[i]) * 100.0)
            ctun = [ti, tho, 0.0, tho, 0.35, alt, alt, round(alt * 100.0), 0.0, alt, alt, 0, climb_cm]
        else:
            r_c, p_c = round(float(att_deg[i, 0]) * 100.0), round(float(att_deg[i, 1]) * 100.0)
            tho = float(thr_01[i]) * 100.0  # Plane logs its throttle in percent
            asp = float(s.airspeed_m_s[i])
            ctun = [ti, r_c, r_c, p_c, p_c, tho, 0.0, tho, asp, 1, asp, 1.0, 0]
        events.append((ti, 8, "CTUN", ctun))
    return events


def _df_bat_events(result: SimResult) -> list[DfEvent]:
    s = result.samples
    rates = result.config.rates
    t_us = _t_us(result)
    dt = 1.0 / rates.imu_hz
    consumed_mah = np.cumsum(s.current_a) * dt / 3.6
    energy_wh = np.cumsum(s.current_a * s.voltage_v) * dt / 3600.0
    events: list[DfEvent] = []
    for i in rate_indices(t_us.size, rates.imu_hz, rates.power_hz):
        ti = int(t_us[i])
        volt = round(float(s.voltage_v[i]) * 1000.0) / 1000.0
        curr = round(float(s.current_a[i]) * 100.0) / 100.0
        bat = [ti, 0, volt, volt + 0.02 * curr, curr, float(consumed_mah[i]), float(energy_wh[i]), 2500, 0.02]
        events.append((ti, 9, "BAT", bat))
    return events


def _df_gps_events(result: SimResult, start_unix: float) -> list[DfEvent]:
    """GPS at gps_hz: GPS week and ms of week, a 3D fix, course over ground and (yaw_source = truth) yaw."""
    s = result.samples
    rates = result.config.rates
    track = s.gps
    assert track is not None
    t_us = _t_us(result)
    yaw_true = true_yaw_deg(result)
    events: list[DfEvent] = []
    for i in rate_indices(t_us.size, rates.imu_hz, min(rates.gps_hz, rates.imu_hz)):
        ti = int(t_us[i])
        week, ms = gps_week_ms(start_unix + float(s.t_s[i]))
        v = track.vel_n_m_s[i]
        ground = math.hypot(float(v[0]), float(v[1]))
        cog = math.degrees(math.atan2(float(v[1]), float(v[0]))) % 360.0 if ground > 0.5 else 0.0
        gps_yaw = float(yaw_true[i]) % 360.0 if result.config.variation.yaw_source == "truth" else 0.0
        lat, lon = track.lat_lon_e7(i)
        alt_cm = round(float(track.alt_msl_m[i]) * 100.0)
        gps = [ti, 0, 3, ms, week, 14, 80, lat, lon, alt_cm, ground, cog, float(v[2]), gps_yaw, 1]
        events.append((ti, 10, "GPS", gps))
    return events
