"""Neutral, typed samples exchanged between the shell and the core.

Every sample carries ``t_s``: seconds on the *source's* clock (the message's own timestamp,
e.g. ``time_boot_ms * 1e-3``), never arrival time. Vectors are numpy arrays of shape (3,).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Vec3 = NDArray[np.float64]
Mat3 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class ImuSample:
    """Gyro (rad/s) and accelerometer (specific force, m/s^2), both body FRD."""

    t_s: float
    gyro_b_rad_s: Vec3
    accel_b_m_s2: Vec3
    imu_index: int = 0


@dataclass(frozen=True, slots=True)
class MagSample:
    """Magnetometer. field_b_mgauss: mgauss in the compass's own (uncalibrated) frame."""

    t_s: float
    field_b_mgauss: Vec3
    mag_index: int = 0


@dataclass(frozen=True, slots=True)
class AttitudeSample:
    """Autopilot attitude estimate: Euler ZYX angles (rad) and body rates (rad/s)."""

    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rates_b_rad_s: Vec3 = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True, slots=True)
class ThrottleSample:
    """Throttle command 0..1 from the configured source; motors_01 holds each motor output when known."""

    t_s: float
    throttle_01: float
    source: str = ""
    motors_01: tuple[float, ...] = ()


@dataclass(frozen=True, slots=True)
class PowerSample:
    """Battery voltage (V) and current (A); NaN when the message does not carry one."""

    t_s: float
    voltage_v: float
    current_a: float
    battery_index: int = 0


@dataclass(frozen=True, slots=True)
class TemperatureSample:
    """A temperature (degC), e.g. the IMU's, the nearest proxy a log has for the powertrain's."""

    t_s: float
    temperature_degc: float
    sensor: str = "imu"


@dataclass(frozen=True, slots=True)
class HeartbeatSample:
    """HEARTBEAT: MAV_TYPE and MAV_AUTOPILOT of the vehicle; ``t_s`` is the last known source time."""

    t_s: float
    vehicle_type: int
    autopilot: int
    system_id: int = 1


@dataclass(frozen=True, slots=True)
class ParamSample:
    """One parameter value (PARAM_VALUE or DataFlash PARM)."""

    t_s: float
    name: str
    value: float


Sample = (
    ImuSample
    | MagSample
    | AttitudeSample
    | ThrottleSample
    | PowerSample
    | TemperatureSample
    | HeartbeatSample
    | ParamSample
)
