"""Configuration of the synthetic vehicle: scenario, hidden effects, location, rates, sensor errors.

Everything here is a frozen dataclass validated once in ``__post_init__``; bad values raise
:class:`magcomp.errors.InputError` with a one-line message (the CLI prints it as is).

Hidden effects (all off by default; ``SimConfig.effects`` maps a name to its VALUE). Each is a physical
mechanism that the paper's model, eq. (11) ``B = theta * delta_t^2``, ignores:

``throttle_offset`` (VALUE: offset, 0..0.5 of full throttle)
    ESC dead band and motor start-up current: the motor does not turn until the command passes the
    offset (friction to overcome; the ESC cannot sense back-EMF at low speed, sec. IV of the paper,
    Fig. 6). Motor speed = (delta - offset) / (1 - offset), zero below; replaces eq. (9).
``throttle_exponent`` (VALUE: exponent p, 0.5..4)
    The torque coefficient C_Q of eq. (8) is not constant (Reynolds number, advance ratio, ESC
    efficiency vary with speed), so current and bias go as speed^p instead of speed^2.
``current_lag`` (VALUE: tau_s, 0..5 s)
    Rotor inertia and the ESC's acceleration limit: motor speed (hence torque and current) follows the
    command through a first-order lag with time constant tau_s; eq. (9) assumes it is instantaneous.
``time_skew`` (VALUE: skew_s, -1..1 s)
    The logged throttle and the field are stamped by different clocks / transport paths: the field
    responds to the throttle logged ``skew_s`` earlier (positive: the field follows the logged throttle
    late).
``voltage_sag`` (VALUE: strength s, 0..1)
    Unregulated ESC (no RPM governor): the motor speed scales with the battery voltage,
    speed = speed_cmd * (1 - s + s * V_batt / V_full). s = 1 is a fully unregulated ESC; the battery
    voltage falls with discharge and sags under load through the internal resistance.
``temperature_drift`` (VALUE: mgauss per degC, -5..5)
    Hard iron that changes with the powertrain temperature (magnet remanence of the motor and the
    magnetisation of nearby steel change with temperature): b(T) = b + k (T - T_ambient) u along a fixed
    unit direction u per compass.
``per_motor`` (VALUE: spread s, 0..2; multirotor only)
    Each motor's ESC and wires take their own route past the compass, so motor i adds its own
    theta_i = theta + s |theta| e_i (e_i: a fixed random direction per motor, re-centred so that
    sum of e_i = 0) driven by its own output: B = sum_i theta_i m_i^2 / n. When the motors differ
    (attitude control: roll, pitch and above all yaw demands), the bias departs from theta * mean(m)^2.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from magcomp.errors import InputError

#: name -> (value that means "off", lowest allowed, highest allowed, one-line meaning of VALUE)
EFFECTS: Mapping[str, tuple[float, float, float, str]] = MappingProxyType(
    {
        "throttle_offset": (0.0, 0.0, 0.5, "ESC dead band, fraction of full throttle"),
        "throttle_exponent": (2.0, 0.5, 4.0, "bias ~ speed^VALUE instead of ^2"),
        "current_lag": (0.0, 0.0, 5.0, "motor/ESC spin-up time constant tau_s, s"),
        "time_skew": (0.0, -1.0, 1.0, "field follows the logged throttle VALUE s late"),
        "voltage_sag": (0.0, 0.0, 1.0, "unregulated-ESC strength 0..1 (speed ~ battery voltage)"),
        "temperature_drift": (0.0, -5.0, 5.0, "hard-iron drift, mgauss per degC of powertrain temperature"),
        "per_motor": (0.0, 0.0, 2.0, "spread of per-motor theta_i, fraction of |theta| (multirotor)"),
    }
)

#: Scenario name -> default duration (s). ``flight_fixedwing`` / ``flight_multirotor`` are aliases.
SCENARIOS: Mapping[str, float] = MappingProxyType(
    {
        "tumble": 60.0,
        "spin": 60.0,
        "pan": 30.0,
        "ramp": 20.0,
        "step": 10.0,
        "bench": 60.0,
        "flight": 120.0,
        "paper": 133.0,
    }
)
SCENARIO_ALIASES: Mapping[str, tuple[str, str]] = MappingProxyType(
    {"flight_fixedwing": ("flight", "fixedwing"), "flight_multirotor": ("flight", "multirotor")}
)
VEHICLES = ("fixedwing", "multirotor")


@dataclass(frozen=True)
class Location:
    """Where and when: geodetic latitude/longitude (deg), altitude above the ellipsoid (m), decimal year.

    The default is the paper's lab (Gainesville, FL) in mid-2025 (inside WMM-2025's lifespan).
    """

    lat_deg: float = 29.65
    lon_deg: float = -82.35
    alt_m: float = 30.0
    decimal_year: float = 2025.5

    def __post_init__(self) -> None:
        if not (-90.0 <= self.lat_deg <= 90.0 and -180.0 <= self.lon_deg <= 180.0):
            raise InputError(f"location out of range: lat {self.lat_deg} deg, lon {self.lon_deg} deg")
        if not (2025.0 <= self.decimal_year < 2030.0):
            raise InputError(f"date {self.decimal_year} outside WMM-2025's lifespan 2025.0-2030.0")


@dataclass(frozen=True)
class Rates:
    """Sample rates (Hz). Truth is integrated at ``truth_hz``; the autopilot samples its sensors at
    ``imu_hz`` (a divisor of ``truth_hz``); message rates must not exceed ``imu_hz``."""

    truth_hz: float = 200.0
    imu_hz: float = 50.0
    attitude_hz: float = 25.0
    servo_hz: float = 25.0
    rc_hz: float = 10.0
    vfr_hud_hz: float = 10.0
    power_hz: float = 10.0
    heartbeat_hz: float = 1.0

    def __post_init__(self) -> None:
        if self.truth_hz < 200.0:
            raise InputError(f"truth rate {self.truth_hz} Hz: must be at least 200 Hz")
        ratio = self.truth_hz / self.imu_hz if self.imu_hz > 0 else 0.0
        if self.imu_hz <= 0 or abs(ratio - round(ratio)) > 1e-9:
            raise InputError(f"IMU rate {self.imu_hz} Hz must divide the truth rate {self.truth_hz} Hz")
        for name in ("attitude_hz", "servo_hz", "rc_hz", "vfr_hud_hz", "power_hz", "heartbeat_hz"):
            value = getattr(self, name)
            if not (0.0 < value <= self.imu_hz):
                raise InputError(f"rate {name}={value} Hz must be in (0, imu_hz={self.imu_hz}]")


@dataclass(frozen=True)
class SimConfig:
    """One simulation run.

    scenario: one of :data:`SCENARIOS` (or an alias in :data:`SCENARIO_ALIASES`, which also sets vehicle)
    duration_s: None -> the scenario's default; for ``paper`` the segments scale with it
    seed: seeds the sensor errors and the hand-rotation profile (``simulate`` also takes an rng)
    effects: hidden effects, name -> VALUE (see the module docstring); omitted -> off
    vehicle: ``fixedwing`` (throttle on SERVO3) or ``multirotor`` (quad X, motors on SERVO1-4)
    n_compasses: 1..3 (RAW_IMU, SCALED_IMU2, SCALED_IMU3)
    t0_s: boot-clock time at which the scenario starts (time_boot_ms of the first sample / 1000)
    theta_mgauss: eq. (11) theta of compass 0 at full throttle (default: Table II, 1.5 mG/LSB)
    earth_field_ned_mgauss: None -> WMM-2025 at ``location``; or an explicit (N, E, D) mgauss
    """

    scenario: str = "paper"
    duration_s: float | None = None
    seed: int = 0
    effects: Mapping[str, float] = field(default_factory=dict)
    vehicle: str = "fixedwing"
    location: Location = field(default_factory=Location)
    rates: Rates = field(default_factory=Rates)
    n_compasses: int = 2
    t0_s: float = 5.0
    theta_mgauss: tuple[float, float, float] = (-61.0, 26.4, -1.2)
    earth_field_ned_mgauss: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.scenario in SCENARIO_ALIASES:
            base, vehicle = SCENARIO_ALIASES[self.scenario]
            object.__setattr__(self, "scenario", base)
            object.__setattr__(self, "vehicle", vehicle)
        if self.scenario not in SCENARIOS:
            names = ", ".join([*SCENARIOS, *SCENARIO_ALIASES])
            raise InputError(f"unknown scenario {self.scenario!r} (choose from {names})")
        if self.vehicle not in VEHICLES:
            raise InputError(f"unknown vehicle {self.vehicle!r} (choose from {', '.join(VEHICLES)})")
        if self.duration_s is not None and not (1.0 <= self.duration_s <= 3600.0):
            raise InputError(f"duration {self.duration_s} s must be between 1 and 3600 s")
        if not 1 <= self.n_compasses <= 3:
            raise InputError(f"n_compasses={self.n_compasses}: must be 1, 2 or 3")
        if not (0.0 <= self.t0_s <= 3.0e6):
            raise InputError(f"t0_s={self.t0_s}: must be a boot time between 0 and 3e6 s")
        if len(self.theta_mgauss) != 3 or not all(math.isfinite(v) for v in self.theta_mgauss):
            raise InputError("theta_mgauss must be three finite numbers")
        effects = {}
        for name, value in dict(self.effects).items():
            if name not in EFFECTS:
                raise InputError(f"unknown effect {name!r} (choose from {', '.join(EFFECTS)})")
            _, lo, hi, meaning = EFFECTS[name]
            v = float(value)
            if not (math.isfinite(v) and lo <= v <= hi):
                raise InputError(f"effect {name}={value}: VALUE ({meaning}) must be in [{lo}, {hi}]")
            effects[name] = v
        if effects.get("per_motor", 0.0) != 0.0 and self.vehicle != "multirotor":
            raise InputError("effect per_motor needs --vehicle multirotor")
        if effects.get("throttle_offset", 0.0) >= 0.5:
            raise InputError("effect throttle_offset must be below 0.5")
        object.__setattr__(self, "effects", MappingProxyType(effects))

    @property
    def duration(self) -> float:
        """The run's length in seconds (the scenario default when ``duration_s`` is None)."""
        return float(self.duration_s) if self.duration_s is not None else SCENARIOS[self.scenario]

    def effect(self, name: str) -> float:
        """VALUE of an effect, or its "off" value."""
        return float(self.effects.get(name, EFFECTS[name][0]))

    def effect_on(self, name: str) -> bool:
        return self.effect(name) != EFFECTS[name][0]


def parse_effect(text: str) -> tuple[str, float]:
    """``"NAME=VALUE"`` -> (name, value); raises InputError with a one-line message."""
    name, sep, value = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise InputError(f"--effect {text!r}: expected NAME=VALUE, e.g. current_lag=0.3")
    if name not in EFFECTS:
        raise InputError(f"unknown effect {name!r} (choose from {', '.join(EFFECTS)})")
    try:
        v = float(value)
    except ValueError:
        raise InputError(f"--effect {text!r}: VALUE must be a number") from None
    return name, v
