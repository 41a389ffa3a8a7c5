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

STANDARD_GRAVITY_M_S2 = 9.80665  # standard gravity g_n (exact, by definition)
#: Earth's total field at the surface (WMM: about 22,000 nT in the South Atlantic anomaly to 67,000 nT near
#: the magnetic poles), mgauss
EARTH_MIN_MGAUSS = 220.0
EARTH_MAX_MGAUSS = 670.0


@dataclass(frozen=True, slots=True)
class ImuSample:
    """Gyro (rad/s) and accelerometer (specific force, m/s^2), both body FRD."""

    t_s: float
    gyro_b_rad_s: Vec3
    accel_b_m_s2: Vec3
    imu_index: int = 0

    def floats(self) -> tuple[float, float, float, float, float, float]:
        """Gyro then accelerometer as six Python floats (the per-sample path reads no arrays; a source
        that decodes floats overrides this without building the arrays)."""
        g, a = self.gyro_b_rad_s, self.accel_b_m_s2
        return float(g[0]), float(g[1]), float(g[2]), float(a[0]), float(a[1]), float(a[2])


@dataclass(frozen=True, slots=True)
class MagSample:
    """Magnetometer. field_b_mgauss: mgauss in the compass's own (uncalibrated) frame."""

    t_s: float
    field_b_mgauss: Vec3
    mag_index: int = 0
    #: the motor compensation the autopilot had added to this field and the source removed (ArduPilot's
    #: COMPASS_MOT / MAG.MOX..), mgauss; None: none. field + onboard is the field as the autopilot had it
    onboard_mgauss: tuple[float, float, float] | None = None

    def floats(self) -> tuple[float, float, float]:
        """The field as three Python floats (see :meth:`ImuSample.floats`)."""
        v = self.field_b_mgauss
        return float(v[0]), float(v[1]), float(v[2])


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
class IdentitySample:
    """The vehicle's unique hardware id (AUTOPILOT_VERSION uid2/uid, a DataFlash log's board-id MSG, a ULog's
    sys_uuid) as lower-case hex: the key of its saved state together with the system id."""

    t_s: float
    uid: str
    system_id: int = 1


@dataclass(frozen=True, slots=True)
class ParamSample:
    """One parameter value (PARAM_VALUE or DataFlash PARM)."""

    t_s: float
    name: str
    value: float


@dataclass(frozen=True, slots=True)
class PositionSample:
    """Vehicle position from GNSS (WGS-84 degrees, altitude above mean sea level in m) and, when the
    source carries it, the UTC date as a decimal year (for the WMM epoch); NaN when unknown.
    ``fix_ok``: a 3D fix (or better) that the position can be trusted for the Earth-field model."""

    t_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    decimal_year: float = float("nan")
    fix_ok: bool = True
    #: velocity north, east, down in m/s when the source carries it (down NaN when it does not), else None
    vel_ned_m_s: tuple[float, float, float] | None = None


@dataclass(frozen=True, slots=True)
class TimeSample:
    """UTC wall-clock time of the vehicle (SYSTEM_TIME, GPS week/ms) as a decimal year."""

    t_s: float
    decimal_year: float


@dataclass(frozen=True, slots=True)
class ClockResetSample:
    """The autopilot's boot clock restarted (a reboot) just before ``t_s``. Sources keep ``t_s`` monotonic
    across reboots by adding ``offset_s`` to the autopilot's own timestamps from here on, so the
    autopilot's clock of a later sample is ``t_s - offset_s``."""

    t_s: float
    offset_s: float


Sample = (
    ImuSample
    | MagSample
    | AttitudeSample
    | ThrottleSample
    | PowerSample
    | TemperatureSample
    | HeartbeatSample
    | IdentitySample
    | ParamSample
    | PositionSample
    | TimeSample
    | ClockResetSample
)


@dataclass
class Series:
    """A time series: ``t_s`` (n,) seconds on the source clock, sorted; ``values`` (n,) or (n, k)."""

    t_s: NDArray[np.float64]
    values: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @classmethod
    def empty(cls, width: int = 0) -> Series:
        shape: tuple[int, ...] = (0,) if width == 0 else (0, width)
        return cls(np.zeros(0), np.zeros(shape))


@dataclass
class LogData:
    """A whole log as columns, in the fixed units of this module (see :mod:`magcomp.core`).

    mag: per compass index, field in mgauss, compass frame, shape (n, 3)
    gyro_rad_s / accel_m_s2: body FRD, shape (n, 3) (same time base: ``imu_t_s``)
    attitude_rad: autopilot roll, pitch, yaw (n, 3)
    throttle_01: (n,) from the selected throttle source; motors_01: (n, m) each motor output 0..1
    voltage_v, current_a: battery 0 (n,) each; temperature_degc: (n,)
    params: parameter name -> value; vehicle_type/autopilot from HEARTBEAT (MAV_TYPE/MAV_AUTOPILOT) or -1
    """

    source: str
    mag: dict[int, Series] = field(default_factory=dict)
    imu_t_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    gyro_rad_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    accel_m_s2: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    attitude_rad: Series = field(default_factory=lambda: Series.empty(3))
    throttle_01: Series = field(default_factory=Series.empty)
    throttle_source: str = ""
    motors_01: Series = field(default_factory=lambda: Series.empty(4))
    voltage_v: Series = field(default_factory=Series.empty)
    current_a: Series = field(default_factory=Series.empty)
    temperature_degc: Series = field(default_factory=Series.empty)
    params: dict[str, float] = field(default_factory=dict)
    vehicle_type: int = -1
    autopilot: int = -1
    counts: dict[str, int] = field(default_factory=dict)
    # GNSS position: lat_deg, lon_deg, alt_m (n, 3); decimal_year of the log (NaN when unknown)
    position: Series = field(default_factory=lambda: Series.empty(3))
    decimal_year: float = float("nan")
    # GNSS velocity north, east, down in m/s (n, 3), 3D fixes only; down NaN where the source has none
    gps_velocity_ned_m_s: Series = field(default_factory=lambda: Series.empty(3))


# Bits of HeadingEstimate.flags and of MAGCOMP_HEADING.flags
FLAG_CALIBRATED = 1
FLAG_THETA_CONVERGED = 2
FLAG_INPUTS_STALE = 4
FLAG_NO_THROTTLE = 8
FLAG_OBSERVER_RESET = 16
FLAG_Z_UNOBSERVABLE = 32
FLAG_SATURATED = 64

FLAG_NAMES: tuple[tuple[int, str], ...] = (
    (FLAG_CALIBRATED, "CALIBRATED"),
    (FLAG_THETA_CONVERGED, "THETA_CONVERGED"),
    (FLAG_INPUTS_STALE, "INPUTS_STALE"),
    (FLAG_NO_THROTTLE, "NO_THROTTLE"),
    (FLAG_OBSERVER_RESET, "OBSERVER_RESET"),
    (FLAG_Z_UNOBSERVABLE, "Z_UNOBSERVABLE"),
    (FLAG_SATURATED, "SATURATED"),
)


def flags_text(flags: int) -> str:
    """``FLAG_*`` bits as ``"CALIBRATED|THETA_CONVERGED"`` (``"none"`` for 0; unknown bits as hex)."""
    names = [name for bit, name in FLAG_NAMES if flags & bit]
    known = 0
    for bit, _ in FLAG_NAMES:
        known |= bit
    if flags & ~known:
        names.append(f"0x{flags & ~known:x}")
    return "|".join(names) if names else "none"


@dataclass(frozen=True, slots=True)
class HeadingEstimate:
    """One output of the pipeline, for one magnetometer sample (what MAGCOMP_HEADING carries and more).

    heading_deg / heading_raw_deg: magnetic heading 0..360 with / without current compensation.
    theta_mgauss: theta-hat of eq. (11), compass frame after calibration; bias_mgauss = theta * throttle^2.
    field_raw_mgauss: the sample as received; field_cal_mgauss: after eq. (2) and bias removal.
    excitation: smallest eigenvalue of the recent rotation-excitation Gramian (eq. (21)), rad^2/s^2.
    """

    t_s: float
    mag_index: int
    heading_deg: float
    heading_raw_deg: float
    theta_mgauss: Vec3
    bias_mgauss: Vec3
    throttle_01: float
    flags: int
    field_raw_mgauss: Vec3
    field_cal_mgauss: Vec3
    residual_norm_mgauss: float = float("nan")
    excitation: float = float("nan")
    #: the sample's time on the autopilot's own boot clock (what MAGCOMP_HEADING.time_boot_ms carries);
    #: differs from ``t_s`` after a reboot (see ClockResetSample); NaN: the same as ``t_s``
    t_boot_s: float = float("nan")
    #: 1-sigma of theta_mgauss per axis (mgauss), the observer's own estimate (the viewer's band); NaN where
    #: not known (theta from the in-flight calibration, or no observer step yet)
    theta_sigma_mgauss: tuple[float, float, float] = (float("nan"), float("nan"), float("nan"))
