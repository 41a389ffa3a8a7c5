"""PX4 ULog (``.ulg``) as a source of typed samples, streamed in message-time order, and as whole columns.

Topics read (every multi-instance where it applies), with the field names of PX4 1.6 to 1.15:

- magnetometers: ``vehicle_magnetometer`` (magnetometer_ga[3], body frame, calibrated by PX4: its CAL_MAGn
  offsets, scales and rotation removed) when logged and PX4 subtracts no power compensation of its own
  (CAL_MAG_COMP_TYP = 0), else ``sensor_mag`` (x, y, z, gauss, the sensor's frame before PX4's
  calibration), calibrated here as PX4 would (offsets, scales, CAL_MAGn_ROT / SENS_BOARD_ROT;
  :func:`px4_calibrated_mag`), else the ``magnetometer_ga`` of old logs' ``sensor_combined`` (compass 0).
  gauss -> mgauss. A topic instance's compass index is the n of the CAL_MAGn_ID parameter equal to its
  ``device_id``, else its multi-instance number.
- IMU: ``sensor_combined`` (gyro_rad, accelerometer_m_s2), else ``vehicle_imu`` (delta_angle /
  delta_angle_dt, delta_velocity / delta_velocity_dt).
- attitude: ``vehicle_attitude`` q[4] (scalar first, body FRD -> NED) -> roll, pitch, yaw; the body rates
  of old logs (rollspeed, ...) when present.
- throttle: ``actuator_motors`` control[] (0..1 already, NaN = stopped -> 0; PX4 >= 1.13) on
  CA_ROTOR_COUNT motors, else ``actuator_outputs`` instance 0 (PWM us) on the PWM_MAIN_FUNCn motor outputs
  (outputs 1-4 before output functions existed) with their PWM range (:func:`~magcomp.adapters.throttle.
  px4_pwm_range`), else ``actuator_controls_0`` control[3] (the thrust command 0..1 of older PX4).
  ``servo:N`` reads actuator_outputs output N-1.
- power: ``battery_status`` voltage_v, current_a (negative = unknown -> NaN), per instance.
- position: ``vehicle_gps_position`` / ``sensor_gps`` (lat/lon int 1e-7 deg and alt mm before PX4 1.14,
  latitude_deg/longitude_deg/altitude_msl_m after; fix_type >= 3; time_utc_usec -> decimal year), and
  ``vehicle_global_position`` (lat, lon deg, alt m) as the estimator's fallback.
- parameters: the initial ones at the log's start, then ``changed_parameters`` at their time; the vehicle
  type from ``vehicle_status`` (system_type = MAV_TYPE in old logs, vehicle_type later).

Time: the topics' ``timestamp`` (microseconds since boot) -> seconds; every topic shares one clock.

Memory: pyulog parses a whole file into per-topic numpy arrays; only the topics above are kept
(``message_name_filter_list``), then samples are generated lazily from those arrays and merged with
:func:`heapq.merge`, so the per-sample objects of a long log never exist at once. The arrays themselves
(about 100 bytes per logged message of the kept topics) cannot be avoided with pyulog.
"""

from __future__ import annotations

import contextlib
import heapq
import os
from collections import Counter
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.gnss_time import decimal_year_from_unix
from magcomp.adapters.param_values import finite_params
from magcomp.adapters.quiet import quiet
from magcomp.adapters.throttle import (
    ThrottleSpec,
    parse_throttle_source,
    px4_motor_channels,
    px4_pwm_range,
)
from magcomp.adapters.wire_samples import WireImuSample, WireMagSample
from magcomp.core.identity import normal_uid
from magcomp.core.px4 import px4_calibrated_mag
from magcomp.core.types import (
    AttitudeSample,
    HeartbeatSample,
    IdentitySample,
    LogData,
    ParamSample,
    PositionSample,
    PowerSample,
    Sample,
    Series,
    ThrottleSample,
)
from magcomp.errors import InputError

F64 = NDArray[np.float64]
MAV_AUTOPILOT_PX4 = 12
GAUSS_TO_MGAUSS = 1000.0
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF  # sensor_combined *_timestamp_relative: no sample
TOPICS = (
    "sensor_mag",
    "vehicle_magnetometer",
    "sensor_combined",
    "vehicle_imu",
    "vehicle_attitude",
    "actuator_motors",
    "actuator_outputs",
    "actuator_controls_0",
    "battery_status",
    "vehicle_gps_position",
    "sensor_gps",
    "vehicle_global_position",
    "vehicle_status",
)
# PX4 vehicle_status.vehicle_type (1.10+) -> MAV_TYPE
_PX4_VEHICLE_TYPE = {1: 2, 2: 1, 3: 10, 4: 7}


@dataclass
class UlogTables:
    """The columns read from one ULog, in magcomp units (see the module docstring)."""

    path: str
    params: dict[str, float]
    param_changes: list[tuple[float, str, float]]
    t0_s: float
    vehicle_type: int = -1
    uid: str | None = None  # info sys_uuid, lower-case hex
    mag: dict[int, tuple[F64, F64]] = field(default_factory=dict)  # index -> (t, field mgauss (n, 3))
    mag_topic: str = ""
    imu: tuple[F64, F64, F64] | None = None  # t, gyro rad/s, accel m/s^2
    attitude: tuple[F64, F64, F64 | None] | None = None  # t, euler (n, 3), rates (n, 3) or None
    throttle: tuple[F64, F64, F64] | None = None  # t, throttle 0..1, motors 0..1 (n, m)
    throttle_label: str = ""
    power: dict[int, tuple[F64, F64, F64]] = field(default_factory=dict)  # index -> t, volt, current
    # origin -> t, lat, lon, alt, decimal year, fix ok
    position: dict[str, tuple[F64, F64, F64, F64, F64, NDArray[np.bool_]]] = field(default_factory=dict)
    # receiver velocity: t, north/east/down m/s (n, 3), 3D fixes only (vehicle_gps_position / sensor_gps)
    gps_velocity: tuple[F64, F64] | None = None
    counts: Counter[str] = field(default_factory=Counter)


def _open_ulog(path: Path, counts: Counter[str] | None = None) -> Any:
    """The ULog at ``path`` read by pyulog. The file is first walked message by message
    (:mod:`magcomp.adapters.ulog_repair`, a few per cent of pyulog's own time): a damaged one is read from
    a copy of its intact messages, what was dropped counted in ``counts`` (``ulog_resyncs``,
    ``ulog_dropped_bytes``). pyulog alone would lose what follows the damage, and walks a long tail of
    zeros one Python step per byte."""
    from magcomp.adapters.ulog_repair import ulog_intact_copy

    repair = ulog_intact_copy(path)
    if repair is None:
        return _parse_ulog(path)
    try:
        repaired = _parse_ulog(repair.path, shown=path)
    except InputError:  # the copy is no better: pyulog's own reading of the file stands
        return _parse_ulog(path)
    finally:
        with contextlib.suppress(OSError):
            repair.path.unlink()
    if counts is not None:
        counts["ulog_resyncs"] += repair.resyncs
        counts["ulog_dropped_bytes"] += repair.dropped_bytes
    return repaired


def _parse_ulog(path: Path, shown: Path | None = None) -> Any:
    try:
        from pyulog import ULog
    except ImportError:  # pragma: no cover - a core dependency
        raise InputError("reading .ulg needs pyulog (pip install pyulog)") from None
    shown = shown or path
    try:
        if path.stat().st_size == 0:
            raise InputError(f"{shown}: empty file")
        with quiet(), path.open("rb") as f:  # our handle: closed even when pyulog raises
            return ULog(f, message_name_filter_list=list(TOPICS))
    except OSError as exc:
        raise InputError(f"{shown}: cannot read ({exc.strerror or exc})") from None
    except InputError:
        raise
    except Exception as exc:  # pyulog raises anything from struct.error to IndexError on a damaged file
        why = (str(exc).splitlines() or [""])[0][:100]
        raise InputError(f"{shown}: not a readable ULog file ({type(exc).__name__}: {why})") from None


#: a timestamp further than this (s, and this many median steps) from the median of its neighbours is
#: a glitch
GLITCH_S = 1.0
GLITCH_STEPS = 100.0
GLITCH_HALF_WINDOW = 3


def lone_time_glitches(t: F64) -> NDArray[np.bool_]:
    """The samples of one topic (timestamps in file order) whose timestamp is a glitch: further than
    GLITCH_S and GLITCH_STEPS median steps from the median of the GLITCH_HALF_WINDOW samples either side
    (a flipped bit sends one far forward or back; up to GLITCH_HALF_WINDOW - 1 of them in a row are
    caught). A real clock event, a jump that the following samples confirm, is not: the neighbours'
    median follows it."""
    n = t.size
    k = GLITCH_HALF_WINDOW
    if n < 2 * k + 1:
        return np.zeros(n, dtype=bool)
    from numpy.lib.stride_tricks import sliding_window_view

    med = np.median(sliding_window_view(np.pad(t, k, mode="reflect"), 2 * k + 1), axis=1)
    steps = np.diff(t)
    ok = steps[(steps > 0) & np.isfinite(steps)]
    step = float(np.median(ok)) if ok.size else 0.0
    limit = max(GLITCH_S, GLITCH_STEPS * step)
    return np.asarray(~(np.abs(t - med) <= limit))


def _cols(data: Mapping[str, Any], name: str, n: int) -> F64 | None:
    keys = [f"{name}[{i}]" for i in range(n)]
    if not all(k in data for k in keys):
        return None
    with np.errstate(invalid="ignore", over="ignore"):  # a damaged value becomes NaN / inf, counted later
        return np.column_stack([np.asarray(data[k], dtype=np.float64) for k in keys])


def _topic_cols(
    topics: dict[str, dict[int, dict[str, Any]]], topic: str, name: str, n: int
) -> tuple[dict[str, Any], F64] | None:
    """The first instance of ``topic`` and its array field ``name[0..n-1]`` as columns; None when the log
    has neither."""
    data = topics.get(topic, {}).get(0)
    if data is None:
        return None
    cols = _cols(data, name, n)
    return None if cols is None else (data, cols)


def _t(data: Mapping[str, Any]) -> F64:
    with np.errstate(invalid="ignore", over="ignore"):
        return np.asarray(data["timestamp"], dtype=np.float64) * 1e-6


def _sorted(t: F64, *cols: Any) -> tuple[Any, ...]:
    order = np.argsort(t, kind="stable")
    return (t[order], *(c[order] if c is not None else None for c in cols))


def read_ulog_tables(
    path: str | os.PathLike[str], throttle_source: str | ThrottleSpec = "auto"
) -> UlogTables:
    """Read the ULog at ``path`` into :class:`UlogTables` (InputError for an unreadable file)."""
    spec = parse_throttle_source(throttle_source)
    p = Path(path)
    counts: Counter[str] = Counter()
    ulog = _open_ulog(p, counts)
    params = finite_params({str(k): float(v) for k, v in ulog.initial_parameters.items()}, counts)
    changes = [(float(t) * 1e-6, str(k), float(v)) for t, k, v in ulog.changed_parameters]
    n_changes = len(changes)
    changes = [c for c in changes if np.isfinite(c[0]) and np.isfinite(c[2])]
    counts["non_finite_params"] += n_changes - len(changes)
    topics: dict[str, dict[int, dict[str, Any]]] = {}
    for d in ulog.data_list:
        if len(d.data.get("timestamp", ())):
            data = d.data
            bad = np.zeros(len(data["timestamp"]), dtype=bool)
            for key in ("timestamp", "timestamp_sample"):  # (the topic's time is either)
                if key in data:
                    bad |= lone_time_glitches(np.asarray(data[key], dtype=np.float64) * 1e-6)
            if bad.any():  # a flipped bit in a timestamp: the sample is dropped, not sorted to the end
                counts["time_jumps"] += int(bad.sum())
                data = {k: np.asarray(v)[~bad] for k, v in data.items()}
            topics.setdefault(d.name, {})[int(d.multi_id)] = data
    tables = UlogTables(str(p), params, changes, float(ulog.start_timestamp) * 1e-6)
    tables.uid = normal_uid(str(ulog.msg_info_dict.get("sys_uuid", "")))
    tables.counts.update(+counts)
    for name, inst in topics.items():
        for multi, data in inst.items():
            tables.counts[f"ulog_{name}" + (f"_{multi}" if multi else "")] = len(data["timestamp"])
    _read_vehicle_type(tables, topics)
    _read_mag(tables, topics)
    _read_imu(tables, topics)
    _read_attitude(tables, topics)
    _read_throttle(tables, topics, spec)
    _read_power(tables, topics)
    _read_position(tables, topics)
    return tables


def _read_vehicle_type(tables: UlogTables, topics: dict[str, dict[int, dict[str, Any]]]) -> None:
    vs = topics.get("vehicle_status", {}).get(0)
    if vs is None:
        return
    if "system_type" in vs:  # MAV_TYPE (PX4 before 1.10)
        tables.vehicle_type = int(vs["system_type"][-1])
    elif "vehicle_type" in vs:
        tables.vehicle_type = _PX4_VEHICLE_TYPE.get(int(vs["vehicle_type"][-1]), -1)
    elif "is_rotary_wing" in vs:
        tables.vehicle_type = 2 if bool(vs["is_rotary_wing"][-1]) else 1


def _compass_indices(params: Mapping[str, float], instances: list[tuple[int, int]]) -> dict[int, int]:
    """multi-instance -> compass index: the n of CAL_MAGn_ID == device_id first, then the others keep their
    multi-instance number when free (else the next free one). ``instances``: (multi_id, device_id)."""
    cal = {int(params[f"CAL_MAG{n}_ID"]): n for n in range(8) if int(params.get(f"CAL_MAG{n}_ID", 0)) != 0}
    out: dict[int, int] = {}
    for multi, device_id in instances:
        n = cal.get(device_id) if device_id else None
        if n is not None and n not in out.values():
            out[multi] = n
    for multi, _ in instances:
        if multi not in out:
            index = multi
            while index in out.values():
                index += 1
            out[multi] = index
    return out


def _read_mag(tables: UlogTables, topics: dict[str, dict[int, dict[str, Any]]]) -> None:
    # vehicle_magnetometer first: PX4's calibration applied, body frame, 2 Hz in the default logging profile;
    # sensor_mag (1 Hz there, in the sensor's frame, before calibration) only without it, calibrated here,
    # or when PX4 subtracts its own power compensation (linear in throttle or current) from the other
    comp = tables.params.get("CAL_MAG_COMP_TYP", 0.0)
    own_comp = bool(np.isfinite(comp) and int(comp) != 0)
    order = ("sensor_mag", "vehicle_magnetometer") if own_comp else ("vehicle_magnetometer", "sensor_mag")
    for name in order:
        found: list[tuple[int, int, F64, F64]] = []  # multi, device id, t, xyz gauss
        for multi, data in sorted(topics.get(name, {}).items()):
            xyz = (
                np.column_stack([np.asarray(data[k], dtype=np.float64) for k in ("x", "y", "z")])
                if "x" in data
                else _cols(data, "magnetometer_ga", 3)
            )
            if xyz is None:
                continue
            ids = np.asarray(data.get("device_id", np.zeros(1)), dtype=np.int64)
            nonzero = ids[ids != 0]
            t = np.asarray(data.get("timestamp_sample", data["timestamp"]), dtype=np.float64) * 1e-6
            found.append((multi, int(nonzero[0]) if nonzero.size else 0, t, xyz))
        indices = _compass_indices(tables.params, [(m, d) for m, d, _, _ in found])
        for multi, device_id, t, xyz in found:
            if name == "sensor_mag":
                n = indices[multi]
                known = device_id != 0 and int(tables.params.get(f"CAL_MAG{n}_ID", 0)) == device_id
                xyz = px4_calibrated_mag(tables.params, n if known else None, xyz)
            _add_mag(tables, indices[multi], t, xyz)
        if tables.mag:
            tables.mag_topic = name
            if name == "vehicle_magnetometer" and own_comp:
                # PX4 already subtracted its own power compensation from this topic (not undone here)
                tables.counts["px4_mag_comp_applied"] = 1
            return
    combined = _topic_cols(topics, "sensor_combined", "magnetometer_ga", 3)
    if combined is None:
        return
    sc, xyz = combined
    rel = np.asarray(sc.get("magnetometer_timestamp_relative", np.zeros(len(xyz))), dtype=np.int64)
    t = (np.asarray(sc["timestamp"], dtype=np.float64) + rel) * 1e-6
    keep = rel != RELATIVE_TIMESTAMP_INVALID
    _add_mag(tables, 0, t[keep], xyz[keep])
    tables.mag_topic = "sensor_combined"


def _add_mag(tables: UlogTables, index: int, t: F64, xyz_gauss: F64) -> None:
    t, xyz = _sorted(t, xyz_gauss * GAUSS_TO_MGAUSS)
    finite = np.isfinite(xyz).all(axis=1) & xyz.any(axis=1)
    tables.counts["nonfinite"] += int((~np.isfinite(xyz).all(axis=1)).sum())
    new = np.diff(t, prepend=-np.inf) > 0  # one sample repeated in several messages (sensor_combined)
    keep = finite & new
    if keep.any():
        tables.mag[index] = (t[keep], xyz[keep])


def _read_imu(tables: UlogTables, topics: dict[str, dict[int, dict[str, Any]]]) -> None:
    sc = topics.get("sensor_combined", {}).get(0)
    if sc is not None:
        gyro = _cols(sc, "gyro_rad", 3)
        acc = _cols(sc, "accelerometer_m_s2", 3)
        if gyro is not None and acc is not None:
            tables.imu = _sorted(_t(sc), gyro, acc)  # type: ignore[assignment]
            return
    vi = topics.get("vehicle_imu", {}).get(0)
    if vi is not None:
        dang, dvel = _cols(vi, "delta_angle", 3), _cols(vi, "delta_velocity", 3)
        if dang is not None and dvel is not None and "delta_angle_dt" in vi and "delta_velocity_dt" in vi:
            da_dt = np.asarray(vi["delta_angle_dt"], dtype=np.float64)[:, None] * 1e-6
            dv_dt = np.asarray(vi["delta_velocity_dt"], dtype=np.float64)[:, None] * 1e-6
            ok = (da_dt[:, 0] > 0) & (dv_dt[:, 0] > 0)
            t = _t(vi)[ok]
            tables.imu = _sorted(t, dang[ok] / da_dt[ok], dvel[ok] / dv_dt[ok])  # type: ignore[assignment]


def _read_attitude(tables: UlogTables, topics: dict[str, dict[int, dict[str, Any]]]) -> None:
    found = _topic_cols(topics, "vehicle_attitude", "q", 4)
    if found is None:
        return
    att, q = found
    from magcomp.core.rotations import euler_from_quats

    norm = np.linalg.norm(q, axis=1)
    ok = np.isfinite(q).all(axis=1) & (norm > 0.5)
    tables.counts["nonfinite"] += int((~ok).sum())
    eul = euler_from_quats(q[ok] / norm[ok, None])
    rates = None
    if all(k in att for k in ("rollspeed", "pitchspeed", "yawspeed")):
        rates = np.column_stack(
            [np.asarray(att[k], dtype=np.float64) for k in ("rollspeed", "pitchspeed", "yawspeed")]
        )[ok]
    tables.attitude = _sorted(_t(att)[ok], eul, rates)  # type: ignore[assignment]


def _read_throttle(
    tables: UlogTables, topics: dict[str, dict[int, dict[str, Any]]], spec: ThrottleSpec
) -> None:
    params = tables.params
    outputs = topics.get("actuator_outputs", {}).get(0)
    if spec.kind == "servo":
        if outputs is None or f"output[{spec.channel - 1}]" not in outputs:
            return
        lo, hi = px4_pwm_range(params, spec.channel)
        pwm = np.asarray(outputs[f"output[{spec.channel - 1}]"], dtype=np.float64)
        thr = np.clip((pwm - lo) / (hi - lo), 0.0, 1.0)
        tables.throttle = _sorted(_t(outputs), thr, thr[:, None])  # type: ignore[assignment]
        tables.throttle_label = f"servo:{spec.channel}"
        return
    if spec.kind not in ("auto", "motors"):
        raise InputError(
            f"throttle source {spec} is not in a PX4 ULog (use auto, motors or servo:N for actuator_outputs)"
        )
    motors_topic = topics.get("actuator_motors", {}).get(0)
    if motors_topic is not None:
        ctrl = _cols(motors_topic, "control", 12)
        if ctrl is None:
            ctrl = _cols(motors_topic, "control", 8)
        if ctrl is not None:
            n = int(params.get("CA_ROTOR_COUNT", 0)) or int(np.isfinite(ctrl).any(axis=0).sum()) or 4
            motors = np.clip(np.nan_to_num(ctrl[:, :n], nan=0.0), 0.0, 1.0)
            tables.throttle = _sorted(_t(motors_topic), motors.mean(axis=1), motors)  # type: ignore[assignment]
            tables.throttle_label = "actuator_motors"
            return
    if outputs is not None:
        channels = px4_motor_channels(params)
        if not channels and tables.vehicle_type not in (1,):  # no output functions: mixer outputs 1..4
            n_out = int(np.max(outputs["noutputs"])) if "noutputs" in outputs else 4
            channels = tuple(range(1, min(4, n_out) + 1))
        cols = [f"output[{c - 1}]" for c in channels]
        if channels and all(c in outputs for c in cols):
            pwm = np.column_stack([np.asarray(outputs[c], dtype=np.float64) for c in cols])
            ranges = np.array([px4_pwm_range(params, c) for c in channels])
            motors = np.clip((pwm - ranges[:, 0]) / (ranges[:, 1] - ranges[:, 0]), 0.0, 1.0)
            tables.throttle = _sorted(_t(outputs), motors.mean(axis=1), motors)  # type: ignore[assignment]
            tables.throttle_label = "actuator_outputs:" + ",".join(str(c) for c in channels)
            return
    ac = topics.get("actuator_controls_0", {}).get(0)
    if ac is not None and "control[3]" in ac:
        thr = np.clip(np.nan_to_num(np.asarray(ac["control[3]"], dtype=np.float64)), 0.0, 1.0)
        tables.throttle = _sorted(_t(ac), thr, thr[:, None])  # type: ignore[assignment]
        tables.throttle_label = "actuator_controls_0[3]"


def _read_power(tables: UlogTables, topics: dict[str, dict[int, dict[str, Any]]]) -> None:
    for multi, data in sorted(topics.get("battery_status", {}).items()):
        if "voltage_v" not in data or "current_a" not in data:
            continue
        volt = np.asarray(data["voltage_v"], dtype=np.float64)
        curr = np.asarray(data["current_a"], dtype=np.float64)
        volt = np.where(volt > 0, volt, np.nan)
        curr = np.where(curr >= 0, curr, np.nan)  # -1: no current sensor
        tables.power[multi] = _sorted(_t(data), volt, curr)  # type: ignore[assignment]


def _read_position(tables: UlogTables, topics: dict[str, dict[int, dict[str, Any]]]) -> None:
    for name in ("vehicle_gps_position", "sensor_gps"):
        data = topics.get(name, {}).get(0)
        if data is None:
            continue
        if "latitude_deg" in data:
            lat = np.asarray(data["latitude_deg"], dtype=np.float64)
            lon = np.asarray(data["longitude_deg"], dtype=np.float64)
            alt = np.asarray(data.get("altitude_msl_m", np.full(len(lat), np.nan)), dtype=np.float64)
        elif "lat" in data:
            lat = np.asarray(data["lat"], dtype=np.float64) * 1e-7
            lon = np.asarray(data["lon"], dtype=np.float64) * 1e-7
            alt = np.asarray(data.get("alt", np.full(len(lat), np.nan)), dtype=np.float64) * 1e-3
        else:
            continue
        fix = np.asarray(data.get("fix_type", np.zeros(len(lat))), dtype=np.int64) >= 3
        utc = np.asarray(data.get("time_utc_usec", np.zeros(len(lat))), dtype=np.float64) * 1e-6
        year = np.array([decimal_year_from_unix(u) for u in utc])
        ok = fix & (np.abs(lat) <= 90) & (np.abs(lon) <= 180) & ((lat != 0) | (lon != 0))
        tables.position[name] = _sorted(_t(data), lat, lon, alt, year, ok)  # type: ignore[assignment]
        if all(k in data for k in ("vel_n_m_s", "vel_e_m_s", "vel_d_m_s")):
            vel = np.column_stack(
                [np.asarray(data[k], dtype=np.float64) for k in ("vel_n_m_s", "vel_e_m_s", "vel_d_m_s")]
            )
            keep = fix & np.all(np.isfinite(vel), axis=1)
            if "vel_ned_valid" in data:
                keep &= np.asarray(data["vel_ned_valid"]) != 0
            t_v, vel_v = _sorted(_t(data)[keep], vel[keep])
            tables.gps_velocity = (t_v, vel_v)
        break
    gp = topics.get("vehicle_global_position", {}).get(0)
    if gp is not None and "lat" in gp and "lon" in gp:
        lat = np.asarray(gp["lat"], dtype=np.float64)
        lon = np.asarray(gp["lon"], dtype=np.float64)
        if np.nanmax(np.abs(lat), initial=0.0) > 90.0:  # int 1e-7 deg in some versions
            lat, lon = lat * 1e-7, lon * 1e-7
        alt = np.asarray(gp.get("alt", np.full(len(lat), np.nan)), dtype=np.float64)
        ok = np.isfinite(lat) & np.isfinite(lon) & ((lat != 0) | (lon != 0)) & (np.abs(lat) <= 90)
        nan = np.full(len(lat), np.nan)
        tables.position["vehicle_global_position"] = _sorted(_t(gp), lat, lon, alt, nan, ok)  # type: ignore[assignment]


# --- streaming -------------------------------------------------------------------------------------------


class UlogSource:
    """A ULog file as a source with :class:`~magcomp.adapters.mavlink_source.MavSource`'s interface:
    ``samples()`` (typed samples in message-time order), ``records()`` ((topic, sample) pairs), ``counts``,
    ``params`` (updated as ParamSamples stream), ``vehicle_type``, ``autopilot`` (PX4), ``close()``.
    Leaves nothing out (``skipped_samples`` is 0: ``pipeline_only`` applies to MAVLink and DataFlash)."""

    skipped_samples = 0

    def __init__(
        self,
        target: str,
        *,
        throttle_source: str | ThrottleSpec = "auto",
        mag_index: int | None = None,
    ) -> None:
        self.target = target
        self.spec = parse_throttle_source(throttle_source)
        self.mag_index = mag_index
        self.connection: Any = None
        self.tables = read_ulog_tables(target, self.spec)
        self.counts: dict[str, int] = Counter(self.tables.counts)
        self.params: dict[str, float] = {}
        self.vehicle_type = self.tables.vehicle_type
        self.autopilot = MAV_AUTOPILOT_PX4
        self._closed = False

    def close(self) -> None:
        self._closed = True

    def __enter__(self) -> UlogSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def records(self) -> Iterator[tuple[str, Sample]]:
        """(topic, sample) pairs in time order; at equal times: parameters, IMU, magnetometers, attitude,
        throttle, power, position (the order of an ArduPilot stream, whose RAW_IMU carries compass 0, so
        that a ULog and a tlog of the same flight replay alike)."""
        streams = [self._head(), *self._streams()]
        merged = heapq.merge(*streams, key=lambda rec: rec[1].t_s)
        for origin, sample in merged:
            if self._closed:
                return
            if isinstance(sample, ParamSample):
                self.params[sample.name] = sample.value
            self.counts["messages"] += 1
            yield origin, sample

    def samples(self) -> Iterator[Sample]:
        for _, sample in self.records():
            yield sample

    def _head(self) -> Iterator[tuple[str, Sample]]:
        tb = self.tables
        t0 = tb.t0_s
        yield "vehicle_status", HeartbeatSample(t0, tb.vehicle_type, MAV_AUTOPILOT_PX4, 1)
        if tb.uid is not None:
            yield "info", IdentitySample(t0, tb.uid, 1)
        for name in sorted(tb.params):
            yield "parameters", ParamSample(t0, name, tb.params[name])
        for t, name, value in sorted(tb.param_changes, key=lambda c: c[0]):
            yield "changed_parameters", ParamSample(max(t, t0), name, value)

    def _streams(self) -> list[Iterator[tuple[str, Sample]]]:
        tb = self.tables
        out: list[Iterator[tuple[str, Sample]]] = []
        if tb.imu is not None:
            out.append(_imu_stream(*tb.imu))
        for index, (t, xyz) in sorted(tb.mag.items()):
            if self.mag_index is None or index == self.mag_index:
                out.append(_mag_stream(tb.mag_topic, t, xyz, index))
        if tb.attitude is not None:
            out.append(_attitude_stream(*tb.attitude))
        if tb.throttle is not None:
            out.append(_throttle_stream(*tb.throttle, tb.throttle_label))
        for index, (t, volt, curr) in sorted(tb.power.items()):
            out.append(_power_stream(t, volt, curr, index))
        for origin, columns in tb.position.items():
            out.append(_position_stream(origin, *columns))
        return out


# Each stream is its own generator function, so that its arguments are bound when it is created.


def _imu_stream(t: F64, gyro: F64, acc: F64) -> Iterator[tuple[str, Sample]]:
    for ti, gi, ai in zip(t.tolist(), gyro.tolist(), acc.tolist(), strict=True):
        yield "imu", WireImuSample(ti, (gi[0], gi[1], gi[2]), (ai[0], ai[1], ai[2]), 0)


def _attitude_stream(t: F64, euler: F64, rates: F64 | None) -> Iterator[tuple[str, Sample]]:
    r = rates if rates is not None else np.zeros_like(euler)
    for ti, ei, ri in zip(t.tolist(), euler.tolist(), r, strict=True):
        yield "vehicle_attitude", AttitudeSample(ti, ei[0], ei[1], ei[2], np.asarray(ri, dtype=np.float64))


def _throttle_stream(t: F64, thr: F64, motors: F64, label: str) -> Iterator[tuple[str, Sample]]:
    for ti, hi, mi in zip(t.tolist(), thr.tolist(), motors.tolist(), strict=True):
        yield "throttle", ThrottleSample(ti, hi, label, tuple(mi))


def _power_stream(t: F64, volt: F64, curr: F64, index: int) -> Iterator[tuple[str, Sample]]:
    for ti, vi, ci in zip(t.tolist(), volt.tolist(), curr.tolist(), strict=True):
        yield "battery_status", PowerSample(ti, vi, ci, index)


def _position_stream(
    origin: str, t: F64, lat: F64, lon: F64, alt: F64, year: F64, ok: NDArray[np.bool_]
) -> Iterator[tuple[str, Sample]]:
    rows = zip(t.tolist(), lat.tolist(), lon.tolist(), alt.tolist(), year.tolist(), ok.tolist(), strict=True)
    for ti, la, lo, al, yi, oi in rows:
        yield origin, PositionSample(ti, la, lo, al, yi, bool(oi))


def _mag_stream(topic: str, t: F64, xyz: F64, index: int) -> Iterator[tuple[str, Sample]]:
    for ti, xi in zip(t.tolist(), xyz.tolist(), strict=True):
        yield topic, WireMagSample(ti, (xi[0], xi[1], xi[2]), index)


# --- whole-log columns -------------------------------------------------------------------------------------


def load_ulog(
    path: str | os.PathLike[str], throttle_source: str | ThrottleSpec = "auto", mag_index: int | None = None
) -> LogData:
    """The ULog at ``path`` as :class:`~magcomp.core.types.LogData` (the same values the stream carries)."""
    tb = read_ulog_tables(path, throttle_source)
    params = dict(tb.params)
    for _, name, value in sorted(tb.param_changes, key=lambda c: c[0]):
        params[name] = value
    data = LogData(
        source=os.fspath(path), params=params, vehicle_type=tb.vehicle_type, autopilot=MAV_AUTOPILOT_PX4
    )
    data.mag = {
        i: Series(t, xyz) for i, (t, xyz) in sorted(tb.mag.items()) if mag_index is None or i == mag_index
    }
    if tb.imu is not None:
        data.imu_t_s, data.gyro_rad_s, data.accel_m_s2 = tb.imu
    if tb.attitude is not None:
        data.attitude_rad = Series(tb.attitude[0], tb.attitude[1])
    if tb.throttle is not None:
        t, thr, motors = tb.throttle
        data.throttle_01 = Series(t, thr)
        data.motors_01 = Series(t, motors)
        data.throttle_source = tb.throttle_label
    if tb.power:
        t, volt, curr = tb.power[min(tb.power)]
        data.voltage_v = Series(t, volt)
        data.current_a = Series(t, curr)
    receiver = [o for o in ("vehicle_gps_position", "sensor_gps") if o in tb.position]
    origin = (
        receiver[0]
        if receiver
        else ("vehicle_global_position" if "vehicle_global_position" in tb.position else None)
    )
    years: list[float] = []
    if origin is not None:
        t, lat, lon, alt, year, ok = tb.position[origin]
        if ok.any():
            data.position = Series(t[ok], np.column_stack([lat[ok], lon[ok], alt[ok]]))
    if tb.gps_velocity is not None:
        data.gps_velocity_ned_m_s = Series(*tb.gps_velocity)
    for _, (_, _, _, _, year, ok) in tb.position.items():
        years.extend(year[ok & np.isfinite(year)].tolist())
    if years:
        data.decimal_year = float(np.median(years))
    data.counts = dict(tb.counts)
    if not data.mag and not data.imu_t_s.size and not len(data.attitude_rad):
        raise InputError(f"{path}: no magnetometer, IMU or attitude topic in the ULog file")
    return data
