"""What the writers of simulated logs share (tlog :mod:`magcomp.adapters.mavlink_emit`, DataFlash
:mod:`magcomp.adapters.dataflash_writer`, ULog :mod:`magcomp.adapters.ulog_writer`): the clock of boot,
which loop rows a stream at a given rate carries, PWM of a 0..1 demand, and ArduPilot's servo and compass
parameters of the simulated vehicle."""

from __future__ import annotations

import datetime as _dt
import math

import numpy as np
from numpy.typing import NDArray

from magcomp.core.types import STANDARD_GRAVITY_M_S2
from magcomp.sim.simulate import SimResult

F64 = NDArray[np.float64]

BATTERY_CAPACITY_MAH = 2200
# ArduPilot SERVOn_FUNCTION values
FN_DISABLED, FN_THROTTLE, FN_ELEVON_LEFT, FN_ELEVON_RIGHT = 0, 70, 77, 78
FN_MOTOR1 = 33


def default_start_unix_s(result: SimResult) -> float:
    """UNIX time of boot: the config's decimal year (at whole seconds), deterministic."""
    year_f = result.config.location.decimal_year
    year = int(year_f)
    start = _dt.datetime(year, 1, 1, tzinfo=_dt.UTC)
    length = (_dt.datetime(year + 1, 1, 1, tzinfo=_dt.UTC) - start).total_seconds()
    return float(math.floor(start.timestamp() + (year_f - year) * length))


def rate_indices(n: int, imu_hz: float, rate_hz: float) -> NDArray[np.int64]:
    """Rows of the imu_hz samples that a stream at rate_hz uses (nearest sample to each tick)."""
    ticks = np.arange(0.0, n / imu_hz, 1.0 / rate_hz)
    return np.unique(np.minimum(np.round(ticks * imu_hz).astype(np.int64), n - 1))


def raw_imu_rows(result: SimResult) -> range | NDArray[np.int64]:
    """Loop rows that carry a RAW_IMU / HIGHRES_IMU / SCALED_IMU message (every row unless raw_imu_hz)."""
    rates = result.config.rates
    n = result.samples.t_s.size
    return range(n) if rates.raw_imu_hz is None else rate_indices(n, rates.imu_hz, rates.raw_imu_hz)


def pwm_us(x01: F64) -> NDArray[np.int64]:
    """PWM (us, 1000..2000) of a 0..1 demand."""
    return np.round(1000.0 + 1000.0 * np.clip(x01, 0.0, 1.0)).astype(np.int64)


def servo_params(vehicle: str) -> list[tuple[str, float]]:
    """ArduPilot's SERVOn_FUNCTION/MIN/MAX, BATT_CAPACITY and (multirotor) FRAME_CLASS/TYPE."""
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


def compass_params(result: SimResult) -> list[tuple[str, float]]:
    """ArduPilot's compass parameters for the autopilot's own calibration (logged = A (raw + OFS), A the
    symmetric matrix of DIA/ODI), the primary compass, which compasses are external, and COMPASS_MOTCT = 0
    (no onboard motor compensation)."""
    out: list[tuple[str, float]] = []
    var = result.config.variation
    if result.ap_calibration is not None:
        for j, cal in enumerate(result.ap_calibration):
            k = "" if j == 0 else str(j + 1)
            ofs, a = cal.offsets_mgauss, cal.a_matrix
            out += [(f"COMPASS_OFS{k}_{ax}", float(ofs[i])) for i, ax in enumerate("XYZ")]
            out += [(f"COMPASS_DIA{k}_{ax}", float(a[i, i])) for i, ax in enumerate("XYZ")]
            out += [(f"COMPASS_ODI{k}_X", float(a[0, 1])), (f"COMPASS_ODI{k}_Y", float(a[0, 2]))]
            out += [(f"COMPASS_ODI{k}_Z", float(a[1, 2]))]
    for j in range(len(result.compasses)):
        name = "COMPASS_EXTERNAL" if j == 0 else f"COMPASS_EXTERN{j + 1}"
        out.append((name, 1.0 if (j == 0 and var.external_compass0) else 0.0))
    out += [
        ("COMPASS_PRIMARY", float(var.primary_compass)),
        ("COMPASS_USE", 1.0 if var.yaw_source == "compass" else 0.0),
        ("COMPASS_MOTCT", 0.0),
    ]
    return out


def quantised_imu(result: SimResult) -> tuple[F64, F64]:
    """(gyro rad/s, accel m/s^2) of every IMU at the tlog twin's quantisation: 1 mrad/s, 1 mG."""
    s = result.samples
    g = STANDARD_GRAVITY_M_S2
    gyro = np.round(s.gyro_rad_s * 1000.0) / 1000.0
    acc = np.round(s.accel_m_s2 / g * 1000.0) * g / 1000.0
    return gyro, acc


def body_rates(result: SimResult) -> F64:
    """The autopilot's body rates (rad/s): IMU 0's gyro without its bias."""
    return result.samples.gyro_rad_s[0] - result.compasses[0].gyro_bias_rad_s  # type: ignore[no-any-return]


def elevons_pwm(result: SimResult) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """A fixed wing's left and right elevon PWM (us): pitch and roll demands from the body rates, mixed
    around 1500."""
    rates_b = body_rates(result)
    pitch_cmd = np.clip(0.3 * rates_b[:, 1], -0.4, 0.4)
    roll_cmd = np.clip(0.3 * rates_b[:, 0], -0.4, 0.4)
    left = np.round(1500 + 500 * (pitch_cmd + roll_cmd)).astype(np.int64)
    right = np.round(1500 + 500 * (pitch_cmd - roll_cmd)).astype(np.int64)
    return left, right


def px4_outputs(result: SimResult, i: int, n_out: int) -> list[float]:
    """PX4's actuator outputs (PWM us) at loop row ``i``: motors 1-4 (quad) or the throttle on output 3,
    unused outputs 900."""
    s = result.samples
    out = [900.0] * n_out
    if result.config.vehicle == "multirotor":
        out[0:4] = [float(v) for v in pwm_us(s.motors_01[i, :4])]
    else:
        out[2] = float(pwm_us(s.throttle_01[i : i + 1])[0])
    return out


def px4_motor_outputs(vehicle: str) -> tuple[int, ...]:
    """The PWM outputs (1-based) PX4 drives the simulated motors on: 1-4 (quad) or 3 (the throttle)."""
    return (1, 2, 3, 4) if vehicle == "multirotor" else (3,)


def true_yaw_deg(result: SimResult) -> F64:
    """The yaw (deg) a GPS yaw reports: the autopilot's attitude yaw, or the truth with yaw_source = truth."""
    s = result.samples
    if result.config.variation.yaw_source == "truth":
        from magcomp.core.rotations import euler_from_quats

        return np.degrees(euler_from_quats(result.motion.q_nb[s.truth_index])[:, 2])  # type: ignore[no-any-return]
    return np.degrees(s.attitude_rad[:, 2])  # type: ignore[no-any-return]
