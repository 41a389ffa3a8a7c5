"""Whole-log loading: what :func:`~magcomp.adapters.mavlink_source.load_log` keeps of a source's records,
in compact columns (:mod:`magcomp.adapters.columns`), and the preferences between origins decided with the
whole log known (RAW_IMU over SCALED_IMU for compass 0, SYS_STATUS/CURR over BATTERY_STATUS for battery 0,
IMU temperature over barometer temperature, the ``auto`` throttle source from the final vehicle type and
parameters)."""

from __future__ import annotations

import math
from array import array
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Protocol

import numpy as np

from magcomp.adapters.columns import PwmRows, Rows, Window
from magcomp.adapters.message_convert import PwmRecord, Record, ThrottleRecord
from magcomp.adapters.param_values import finite_params
from magcomp.adapters.throttle import (
    FIXED_WING_TYPES,
    MULTIROTOR_TYPES,
    ResolvedThrottle,
    ThrottleSpec,
    motor_channels,
    resolve_throttle,
    throttle_from_pwm,
)
from magcomp.adapters.wire_samples import Float3
from magcomp.core.types import (
    AttitudeSample,
    ImuSample,
    LogData,
    MagSample,
    PositionSample,
    PowerSample,
    Series,
    TemperatureSample,
    TimeSample,
)
from magcomp.errors import InputError


class CollectedSource(Protocol):
    """What :func:`collect_log` reads of the source once its records are consumed."""

    target: str
    spec: ThrottleSpec
    params: dict[str, float]
    counts: dict[str, int]

    @property
    def vehicle_type(self) -> int: ...

    @property
    def autopilot(self) -> int: ...


def reporting(
    records: Iterator[tuple[str, Record]], on_progress: Callable[[float], None], every: int = 1024
) -> Iterator[tuple[str, Record]]:
    """``records`` with ``on_progress(t_s)`` every ``every`` of them."""
    for i, item in enumerate(records):
        if i % every == 0:
            t = getattr(item[1], "t_s", None)
            if t is not None:
                on_progress(float(t))
        yield item


# compass 0 in several messages: RAW_IMU, then SCALED_IMU and the rest, then PX4's HIGHRES_IMU (calibrated)
_MAG_ORIGIN_RANK = {"RAW_IMU": 0, "HIGHRES_IMU": 2}


def _xyz(rec: Any, wire: str, arr: str) -> Float3 | list[float]:
    """A sample's vector as three floats: the wire samples' own tuple, else the array's values."""
    v = getattr(rec, wire, None)
    return v if v is not None else getattr(rec, arr).tolist()  # type: ignore[no-any-return]


class _Collector:
    """What :func:`load_log` keeps of a log, in columns (:mod:`magcomp.adapters.columns`), one store per
    (kind, origin); preferences between origins are decided at the end (:meth:`fill`)."""

    def __init__(self, window: Window | None) -> None:
        self.window = window
        self.mag: dict[tuple[str, int], Rows] = {}
        self.imu: dict[str, Rows] = {}  # IMU 0: gyro xyz, accel xyz
        self.att = Rows(3, window)
        self.power: dict[str, Rows] = {}  # battery 0: voltage, current
        self.temp: dict[str, Rows] = {}
        self.pwm = {"servo": PwmRows(window), "rc": PwmRows(window)}
        self.thr = {"vfr_hud": Rows(0, window), "ctun": Rows(0, window)}
        self.gnss = _GnssCollector(window)

    def _store(self, stores: dict[Any, Rows], key: Any, width: int) -> Rows:
        st = stores.get(key)
        if st is None:
            st = stores[key] = Rows(width, self.window)
        return st

    def add(self, origin: str, rec: Record) -> None:
        if isinstance(rec, MagSample):
            key = (origin, rec.mag_index)
            self._store(self.mag, key, 3).append(rec.t_s, _xyz(rec, "field_xyz", "field_b_mgauss"))
        elif isinstance(rec, ImuSample):
            if rec.imu_index == 0:
                gyro, accel = _xyz(rec, "gyro_xyz", "gyro_b_rad_s"), _xyz(rec, "accel_xyz", "accel_b_m_s2")
                self._store(self.imu, origin, 6).append(rec.t_s, (*gyro, *accel))
        elif isinstance(rec, AttitudeSample):
            self.att.append(rec.t_s, (rec.roll_rad, rec.pitch_rad, rec.yaw_rad))
        elif isinstance(rec, PowerSample):
            if rec.battery_index == 0:
                self._store(self.power, origin, 2).append(rec.t_s, (rec.voltage_v, rec.current_a))
        elif isinstance(rec, TemperatureSample):
            self._store(self.temp, rec.sensor, 0).append(rec.t_s, (rec.temperature_degc,))
        elif isinstance(rec, PwmRecord):
            self.pwm[rec.kind].append(rec.t_s, rec.pwm_us)
        elif isinstance(rec, ThrottleRecord):
            self.thr[rec.kind].append(rec.t_s, (rec.throttle_01,))
        elif isinstance(rec, PositionSample | TimeSample):
            self.gnss.add(origin, rec)

    def fill(self, data: LogData, counts: dict[str, int]) -> None:
        # compass 0: RAW_IMU wins over SCALED_IMU (ArduPilot sends the same compass in both)
        by_index: dict[int, Rows] = {}
        ranked = sorted(self.mag.items(), key=lambda kv: _MAG_ORIGIN_RANK.get(kv[0][0], 1))
        for (_origin, index), rows in ranked:
            if index in by_index:
                counts["scaled_imu_shadowed"] += rows.n_seen
                continue
            by_index[index] = rows
        data.mag = {i: rows.series() for i, rows in sorted(by_index.items())}
        imu_origin = next((o for o in ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU", "IMU") if o in self.imu), None)
        if imu_origin is not None:
            imu = self.imu[imu_origin].series()
            data.imu_t_s = imu.t_s
            data.gyro_rad_s = np.ascontiguousarray(imu.values[:, :3])
            data.accel_m_s2 = np.ascontiguousarray(imu.values[:, 3:])
        data.attitude_rad = self.att.series()
        power_origins = ("SYS_STATUS", "CURR", "BAT", "BATTERY_STATUS")
        power_origin = next((o for o in power_origins if o in self.power), None)
        if power_origin is not None:
            pw = self.power[power_origin].series()
            data.voltage_v = Series(pw.t_s, pw.values[:, 0])
            data.current_a = Series(pw.t_s, pw.values[:, 1])
        temp_key = next((k for k in ("imu0", "imu1", "imu2", "baro") if k in self.temp), None)
        if temp_key is not None:
            data.temperature_degc = self.temp[temp_key].series()
        self.gnss.fill(data)


def collect_log(
    source: CollectedSource, records: Iterable[tuple[str, Record]], window: Window | None = None
) -> LogData:
    col = _Collector(window)
    add = col.add
    for origin, rec in records:
        add(origin, rec)
    counts = source.counts
    data = LogData(
        source=source.target,
        params=finite_params(source.params, counts),
        vehicle_type=source.vehicle_type,
        autopilot=source.autopilot,
    )
    col.fill(data, counts)
    _collect_throttle(data, source, col.pwm, col.thr)
    data.counts = dict(counts)
    if not data.mag and not len(data.attitude_rad) and not data.imu_t_s.size:
        raise InputError(f"{source.target}: no magnetometer, IMU or attitude data in the log")
    return data


class _GnssCollector:
    """Positions (3D fixes only) and UTC dates of a whole log, for :class:`LogData`.

    The receiver's own position (GPS_RAW_INT, DataFlash GPS, ULog vehicle_gps_position) is preferred to the
    estimator's (GLOBAL_POSITION_INT, POS, vehicle_global_position); the date is the median of every valid
    one (GPS time, SYSTEM_TIME, ULog time_utc_usec), in the window or not."""

    RECEIVER = frozenset({"GPS_RAW_INT", "GPS", "vehicle_gps_position", "sensor_gps"})

    def __init__(self, window: Window | None = None) -> None:
        self.rows: dict[bool, Rows] = {True: Rows(3, window), False: Rows(3, window)}
        self.velocity: dict[str, Rows] = {}
        self.window = window
        self.years = array("d")

    def add(self, origin: str, rec: PositionSample | TimeSample) -> None:
        year = rec.decimal_year
        if isinstance(rec, PositionSample):
            if not rec.fix_ok:
                return
            self.rows[origin in self.RECEIVER].append(rec.t_s, (rec.lat_deg, rec.lon_deg, rec.alt_m))
            if rec.vel_ned_m_s is not None:
                rows = self.velocity.get(origin)
                if rows is None:
                    rows = self.velocity[origin] = Rows(3, self.window)
                rows.append(rec.t_s, rec.vel_ned_m_s)
        if math.isfinite(year):
            self.years.append(year)

    def fill(self, data: LogData) -> None:
        rows = self.rows[True] if len(self.rows[True]) else self.rows[False]
        data.position = rows.series()
        # the velocity with a vertical component first (GLOBAL_POSITION_INT, DataFlash GPS), then GPS_RAW_INT
        for origin in ("GLOBAL_POSITION_INT", "GPS", "GPS_RAW_INT"):
            if origin in self.velocity and len(self.velocity[origin]):
                data.gps_velocity_ned_m_s = self.velocity[origin].series()
                break
        if self.years:
            data.decimal_year = float(np.median(np.frombuffer(self.years, dtype=np.float64)))


def _throttle_rows(
    resolved: ResolvedThrottle, pwm: PwmRows, which: int, width: int = 0
) -> Series:
    """Throttle (``which`` 0: the 0..1 throttle) or per-channel outputs (1) of every PWM row that gives one
    (:func:`throttle_from_pwm`, row by row: the same numbers as streaming)."""
    out = Rows(width)
    for t_s, row in pwm.rows(resolved.channels):
        got = throttle_from_pwm(resolved, row)
        if got is not None:
            out.append(t_s, (got[0],) if which == 0 else got[1])
    return out.series()


def _collect_throttle(
    data: LogData,
    source: CollectedSource,
    pwm: dict[str, PwmRows],
    thr: dict[str, Rows],
) -> None:
    available = frozenset(k for k, v in (*pwm.items(), *thr.items()) if v.n_seen)
    resolved = resolve_throttle(source.spec, data.vehicle_type, data.params, available)
    multirotor = data.vehicle_type in MULTIROTOR_TYPES or bool(motor_channels(data.params))
    if len(pwm["servo"]) and (multirotor or (resolved is not None and resolved.kind == "motors")):
        motors = resolve_throttle("motors", data.vehicle_type, data.params, available)
        if motors is not None:
            data.motors_01 = _throttle_rows(motors, pwm["servo"], 1, len(motors.channels))
        else:
            data.motors_01 = Series.empty(4)
    if resolved is None:
        return
    data.throttle_source = resolved.label
    if resolved.kind in thr:
        data.throttle_01 = thr[resolved.kind].series()
        return
    data.throttle_01 = _throttle_rows(resolved, pwm["rc" if resolved.kind == "rc" else "servo"], 0)
    if data.vehicle_type in FIXED_WING_TYPES and resolved.kind == "servo":
        data.motors_01 = Series(data.throttle_01.t_s, data.throttle_01.values[:, None])
