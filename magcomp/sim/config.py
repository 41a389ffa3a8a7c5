"""Configuration of the synthetic vehicle: scenario, hidden effects, location, rates, sensor errors.

Quick reference (ordinary flight and variation knobs; issues 9 and 10)
----------------------------------------------------------------------
CLI::

    magcomp simulate --scenario ordinary --out f.tlog                 # 300 s multirotor flight, 50 Hz
    magcomp simulate --scenario ordinary_plane --out f.tlog           # the same for a fixed wing
    magcomp simulate --scenario ordinary --set telemetry_hz=2 --out f.tlog  # RAW_IMU, ATTITUDE at 2 Hz
    magcomp simulate --scenario ordinary --set mag_hz=10 --set raw_imu_hz=50 --set attitude_hz=10 ...
    --set yaw_source=truth            # ATTITUDE yaw steered by GPS yaw (not the disturbed compass)
    --set external_compass0=on        # compass 0 external (theta ~ 0, the autopilot's primary), compass 1
                                      # internal with the configured theta (like log171)
    --set ap_cal_hard_iron_mgauss=30 --set ap_cal_soft_iron=0.04   # the autopilot's calibration error
    --set ap_calibration=off          # log the raw readings (what the paper scenarios do)
    --set lat_deg=46.05 --set lon_deg=14.5 --set alt_m=300 --set decimal_year=2026.4   # WMM place/date
    --set mag_ar1_sigma_mgauss=3 --set mag_ar1_tau_s=5 --set mag_rw_mgauss_per_sqrt_s=0.2
    --set mag_lsb_mgauss=3 --set mag_noise_scale=0.5 --set att_roll_bias_deg=1.5 --set att_yaw_bias_deg=2
    --set seed=7 --set vehicle=multirotor --set n_compasses=3 --set gps=on --set theta_mgauss=-40,20,5
    --set theta_scale=0.5 --set hover_throttle=0.4 --set current_max_a=60 --set link_loss=0.05
    --set ap_kp_yaw=0.2 --set ap_kp_tilt=2 --set gyro_noise_scale=3 --set gyro_bias_scale=0

API::

    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings
    cfg = apply_settings(SimConfig(scenario="ordinary", duration_s=120.0), ["telemetry_hz=10"])
    r = simulate(cfg)
    L, d = r.true_calibration(j)    # L logged - d = true body field (Earth + bias), compass j
    r.compasses[j].theta_mgauss     # theta, body frame (after L, d: what the pipeline should find)
    r.theta_logged_mgauss(j)        # theta in the frame of the logged RAW_IMU/SCALED_IMU values
    r.earth_field_ned_mgauss        # the WMM field at cfg.location (unless earth_field_ned_mgauss given)

Rates: ``imu_hz`` is the autopilot's loop (sensor sampling, attitude filter); ``raw_imu_hz`` the
RAW_IMU/SCALED_IMU2/3 message rate (SR*_RAW_SENS; IMU and compass travel together); ``mag_hz`` the
compass's own update rate (values held in between); ``attitude_hz`` ATTITUDE. A rate above the loop
raises the loop (``apply_settings``) but leaves the other message rates as they were (so ``mag_hz=100``
alone gives 100 Hz compass updates inside 50 Hz RAW_IMU; add ``raw_imu_hz=100``).

Truth files (``--out f.tlog`` -> f.truth.json / f.truth.npz): per compass ``logged_frame`` {L, d_mgauss,
theta_logged_mgauss, autopilot {A, offsets_mgauss, residual_hard_iron_mgauss, ...}}, and
``earth_field_ned_mgauss``, ``location``, ``start_unix_s``; npz ``heading_true_deg``, ``heading_mag_deg``,
``autopilot_yaw_error_deg``, ``gps_lat_lon_alt``, ``mag_sensor_mgauss`` at the loop instants.

The ``ordinary`` / ``ordinary_plane`` scenarios: GPS_RAW_INT + GLOBAL_POSITION_INT (5 Hz) and SYSTEM_TIME
(1 Hz, UTC of the WMM date), the autopilot's calibration (10 mgauss residual hard iron, 2 % soft iron) and
COMPASS_OFS/DIA/ODI/EXTERNAL/PRIMARY/MOTCT parameters. Pre-knob scenarios with default knobs are
byte-identical to their output before the knobs existed.

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

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from magcomp.core.identity import SIM_UID, normal_uid
from magcomp.errors import InputError

#: name -> (value that means "off", lowest allowed, highest allowed, one-line meaning of VALUE)
EFFECTS: Mapping[str, tuple[float, float, float, str]] = MappingProxyType(
    {
        "throttle_offset": (0.0, 0.0, 0.5, "ESC dead band, fraction of full throttle"),
        # exponent, lag and skew reach the physical ceilings of magcomp.diagnosis.effects (issue 10: a hidden
        # effect at the diagnosis's search limit cannot be found beyond it)
        "throttle_exponent": (2.0, 0.5, 5.0, "bias ~ speed^VALUE instead of ^2"),
        "current_lag": (0.0, 0.0, 10.0, "motor/ESC spin-up time constant tau_s, s"),
        "time_skew": (0.0, -3.0, 3.0, "field follows the logged throttle VALUE s late"),
        "voltage_sag": (0.0, 0.0, 1.0, "unregulated-ESC strength 0..1 (speed ~ battery voltage)"),
        # +-10 per degC of the powertrain: past the ~4 that a hard iron the autopilot accepts can drift (1800
        # mgauss, ArduPilot's COMPASS_OFFS_MAX, at a ferrite magnet's -0.2 %/degC)
        "temperature_drift": (0.0, -10.0, 10.0, "hard-iron drift, mgauss per degC of powertrain temperature"),
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
        "ordinary": 300.0,
        "ordinary_plane": 300.0,
    }
)
SCENARIO_ALIASES: Mapping[str, tuple[str, str]] = MappingProxyType(
    {"flight_fixedwing": ("flight", "fixedwing"), "flight_multirotor": ("flight", "multirotor")}
)
VEHICLES = ("fixedwing", "multirotor")
#: Scenarios added with the variation knobs; everything else keeps its pre-knob output byte for byte.
EXTENDED_SCENARIOS = frozenset({"ordinary", "ordinary_plane"})
#: scenarios that fix the airframe
SCENARIO_VEHICLE: Mapping[str, str] = MappingProxyType(
    {"ordinary": "multirotor", "ordinary_plane": "fixedwing"}
)
YAW_SOURCES = ("compass", "truth")
#: The autopilot's own compass calibration error when it is on and not set: a typical onboard calibration
#: leaves ~5-30 mgauss of offset error and a few % of scale error (10 mgauss: ~2.3 deg of heading at
#: a 250 mgauss horizontal field).
DEFAULT_AP_CAL_HARD_IRON_MGAUSS = 10.0
DEFAULT_AP_CAL_SOFT_IRON = 0.02


def _loop_rate(default: float | None) -> Any:
    """A :class:`Rates` field for a message the autopilot's loop sends: in (0, imu_hz] (None: imu_hz)."""
    return field(default=default, metadata={"max_hz": "imu_hz"})


def _slow_rate(default: float) -> Any:
    """A :class:`Rates` field for a slow stream (GPS, SYSTEM_TIME): in (0, 50] Hz."""
    return field(default=default, metadata={"max_hz": 50.0})


def _bounded(default: float | None, lo: float, hi: float, *, open_below: bool = False) -> Any:
    """A :class:`Variation` knob whose value (unless None) must be finite and in [lo, hi] ((lo, hi] when
    ``open_below``); :meth:`Variation.__post_init__` checks every such field."""
    return field(default=default, metadata={"range": (lo, hi, open_below)})


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
    attitude_hz: float = _loop_rate(25.0)
    servo_hz: float = _loop_rate(25.0)
    rc_hz: float = _loop_rate(10.0)
    vfr_hud_hz: float = _loop_rate(10.0)
    power_hz: float = _loop_rate(10.0)
    heartbeat_hz: float = _loop_rate(1.0)
    raw_imu_hz: float | None = _loop_rate(None)
    mag_hz: float | None = _loop_rate(None)
    gps_hz: float = _slow_rate(5.0)
    system_time_hz: float = _slow_rate(1.0)

    def __post_init__(self) -> None:
        if self.truth_hz < 200.0:
            raise InputError(f"truth rate {self.truth_hz} Hz: must be at least 200 Hz")
        ratio = self.truth_hz / self.imu_hz if self.imu_hz > 0 else 0.0
        if self.imu_hz <= 0 or abs(ratio - round(ratio)) > 1e-9:
            raise InputError(f"IMU rate {self.imu_hz} Hz must divide the truth rate {self.truth_hz} Hz")
        for f in dataclasses.fields(self):
            cap = f.metadata.get("max_hz")
            value = getattr(self, f.name)
            if cap is None or value is None:
                continue
            top = self.imu_hz if cap == "imu_hz" else cap
            if not (0.0 < value <= top):
                limit = f"loop rate imu_hz={self.imu_hz}" if cap == "imu_hz" else f"{cap:g}"
                raise InputError(f"rate {f.name}={value} Hz must be in (0, {limit}]")

    @property
    def raw_imu_rate(self) -> float:
        """RAW_IMU / SCALED_IMU2/3 message rate (ArduPilot's SR*_RAW_SENS), Hz."""
        return float(self.imu_hz if self.raw_imu_hz is None else self.raw_imu_hz)

    @property
    def mag_rate(self) -> float:
        """Compass update rate, Hz (each value held until the next update)."""
        return float(self.imu_hz if self.mag_hz is None else self.mag_hz)


@dataclass(frozen=True)
class Variation:
    """Knobs that vary what the simulator assumed (issue 10's false-alarm study, issue 9's ordinary flight).

    Every default reproduces the pre-knob output exactly, except that ``None`` means "the scenario's
    default" (the ``ordinary`` scenario turns the autopilot calibration and GPS on).

    mag_ar1_sigma_mgauss, mag_ar1_tau_s: AR(1) (first-order Gauss-Markov) compass noise, stationary sigma
        and correlation time, raw sensor frame, on top of the white noise
    mag_rw_mgauss_per_sqrt_s: random-walk compass noise (sigma grows as VALUE * sqrt(t))
    mag_noise_scale: multiplies each compass's white-noise sigma (1 = 8 / 3 / 5 mgauss)
    mag_lsb_mgauss: sensor quantisation step for every compass (None: 1.5 / 1.0 / 1.0 mgauss)
    ap_calibration: the autopilot applies its own calibration before logging (ArduPilot RAW_IMU / MAG)
    ap_cal_hard_iron_mgauss: residual hard iron left by that calibration, |h| in the logged frame
    ap_cal_soft_iron: rms of the symmetric soft-iron/scale error E of that calibration (fraction)
    yaw_source: ``compass`` (the autopilot fuses its primary compass, uncompensated) or ``truth`` (GPS yaw)
    primary_compass: the compass the autopilot fuses (index)
    external_compass0: compass 0 is an external (GPS-mast) compass far from the wires, theta ~ 0, and
        compass 1 is the internal one with the configured theta
    att_roll_bias_deg, att_pitch_bias_deg, att_yaw_bias_deg: constant errors of the reported ATTITUDE
    att_noise_deg: white noise on each reported ATTITUDE angle
    gps: emit GPS_RAW_INT, GLOBAL_POSITION_INT and SYSTEM_TIME
    ap_kp_yaw, ap_kp_tilt: the autopilot's complementary-filter gains (1/s; 0.5 and 1.0): how fast its
        yaw follows the compass (or GPS yaw) and its tilt the accelerometer. A real EKF pulls its yaw to the
        compass far slower: 0.01-0.02 /s on log171 (benchmarks/autopilot_yaw_follow.py); 0.5 is the stress
        case for a yaw that follows the disturbed compass
    gyro_noise_scale, gyro_bias_scale: multiply each IMU's gyro noise sigma (3 mrad/s) and bias draw
    hover_throttle: the multirotor's hover collective in ``ordinary`` (None: 0.5)
    current_max_a: battery current at full throttle (None: 40 A multirotor, 20 A fixed wing); the bias
        follows theta * throttle^2 whatever the current scale
    theta_scale: multiplies theta of every compass (theta's size; ``theta_mgauss`` sets compass 0's)
    link_loss: fraction of messages lost on the link (each dropped independently, seeded; parameters are
        never dropped), as in a telemetry tlog
    """

    mag_ar1_sigma_mgauss: float = _bounded(0.0, 0.0, 100.0)
    mag_ar1_tau_s: float = _bounded(2.0, 0.01, 1000.0)
    mag_rw_mgauss_per_sqrt_s: float = _bounded(0.0, 0.0, 10.0)
    mag_noise_scale: float = _bounded(1.0, 0.0, 10.0)
    mag_lsb_mgauss: float | None = _bounded(None, 0.0, 50.0, open_below=True)
    ap_calibration: bool | None = None
    ap_cal_hard_iron_mgauss: float | None = _bounded(None, 0.0, 200.0)
    ap_cal_soft_iron: float | None = _bounded(None, 0.0, 0.2)
    yaw_source: str = "compass"
    primary_compass: int = 0
    external_compass0: bool = False
    att_roll_bias_deg: float = _bounded(0.0, -10.0, 10.0)
    att_pitch_bias_deg: float = _bounded(0.0, -10.0, 10.0)
    att_yaw_bias_deg: float = _bounded(0.0, -30.0, 30.0)
    att_noise_deg: float = _bounded(0.0, 0.0, 10.0)
    gps: bool | None = None
    ap_kp_yaw: float = _bounded(0.5, 0.01, 10.0)
    ap_kp_tilt: float = _bounded(1.0, 0.01, 10.0)
    gyro_noise_scale: float = _bounded(1.0, 0.0, 20.0)
    gyro_bias_scale: float = _bounded(1.0, 0.0, 20.0)
    hover_throttle: float | None = _bounded(None, 0.2, 0.7)
    current_max_a: float | None = _bounded(None, 1.0, 500.0)
    theta_scale: float = _bounded(1.0, 0.0, 10.0)
    link_loss: float = _bounded(0.0, 0.0, 0.5)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            limits = f.metadata.get("range")
            v = getattr(self, f.name)
            if limits is None or v is None:
                continue
            lo, hi, open_below = limits
            if not (math.isfinite(v) and (lo < v if open_below else lo <= v) and v <= hi):
                raise InputError(f"{f.name}={v}: must be in {'(' if open_below else '['}{lo:g}, {hi:g}]")
        if self.yaw_source not in YAW_SOURCES:
            raise InputError(f"yaw_source={self.yaw_source!r}: choose from {', '.join(YAW_SOURCES)}")
        if not 0 <= self.primary_compass <= 2:
            raise InputError(f"primary_compass={self.primary_compass}: must be 0, 1 or 2")


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
    variation: Variation = field(default_factory=Variation)
    #: the simulated board's unique id (hex; AUTOPILOT_VERSION, the DataFlash boot MSG, ULog sys_uuid):
    #: its saved state is its own, never a real vehicle's with the same system id
    uid: str = SIM_UID

    def __post_init__(self) -> None:
        uid = normal_uid(self.uid)
        if uid is None or len(uid) > 24:
            raise InputError(f"uid={self.uid!r}: must be 1 to 12 bytes of hex, not all zeros")
        object.__setattr__(self, "uid", uid)
        if self.scenario in SCENARIO_ALIASES:
            base, vehicle = SCENARIO_ALIASES[self.scenario]
            object.__setattr__(self, "scenario", base)
            object.__setattr__(self, "vehicle", vehicle)
        if self.scenario in SCENARIO_VEHICLE:  # ordinary: a multirotor; ordinary_plane: a fixed wing
            object.__setattr__(self, "vehicle", SCENARIO_VEHICLE[self.scenario])
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
        var = self.variation
        if var.primary_compass >= self.n_compasses:
            need = var.primary_compass + 1
            raise InputError(f"primary_compass={var.primary_compass} needs at least {need} compasses")
        if var.external_compass0 and self.n_compasses < 2:
            raise InputError("external_compass0 needs at least 2 compasses (compass 1 is the internal one)")

    @property
    def legacy(self) -> bool:
        """True when the run is one of the pre-knob scenarios with every knob at its default: its output
        (tlog, truth files) is then byte-identical to what the simulator wrote before the knobs existed."""
        return (
            self.scenario not in EXTENDED_SCENARIOS
            and self.variation == Variation()
            and self.rates.raw_imu_hz is None
            and self.rates.mag_hz is None
        )

    def _extended_default(self, switch: bool | None) -> bool:
        """A Variation switch left at None: on for the extended scenarios (``ordinary``), off otherwise."""
        return self.scenario in EXTENDED_SCENARIOS if switch is None else bool(switch)

    @property
    def ap_calibration(self) -> bool:
        """The autopilot calibrates the compasses before logging them (default: on for ``ordinary``)."""
        return self._extended_default(self.variation.ap_calibration)

    @property
    def ap_cal_errors(self) -> tuple[float, float]:
        """The errors that calibration leaves: residual hard iron |h| (mgauss) and soft-iron rms (fraction),
        :data:`DEFAULT_AP_CAL_HARD_IRON_MGAUSS` / :data:`DEFAULT_AP_CAL_SOFT_IRON` where not set."""
        hard, soft = self.variation.ap_cal_hard_iron_mgauss, self.variation.ap_cal_soft_iron
        return (
            DEFAULT_AP_CAL_HARD_IRON_MGAUSS if hard is None else float(hard),
            DEFAULT_AP_CAL_SOFT_IRON if soft is None else float(soft),
        )

    @property
    def gps(self) -> bool:
        """GPS_RAW_INT / GLOBAL_POSITION_INT / SYSTEM_TIME in the output (default: on for ``ordinary``)."""
        return self._extended_default(self.variation.gps)

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


#: ``--set`` keys that are not Variation fields: rates (Hz) and run-level settings
RATE_KEYS = ("mag_hz", "raw_imu_hz", "attitude_hz", "gps_hz", "loop_hz", "telemetry_hz")
RUN_KEYS = (
    "seed",
    "vehicle",
    "n_compasses",
    "duration_s",
    "theta_mgauss",
    "lat_deg",
    "lon_deg",
    "alt_m",
    "decimal_year",
)


def setting_keys() -> tuple[str, ...]:
    """Every key :func:`apply_settings` accepts."""
    return (*RATE_KEYS, *RUN_KEYS, *(f.name for f in dataclasses.fields(Variation)))


def _parse_value(key: str, text: str, kind: object) -> object:
    text = text.strip()
    lowered = text.lower()
    if "None" in str(kind) and lowered in ("none", "default", ""):
        return None
    if "bool" in str(kind):
        if lowered in ("1", "true", "yes", "on"):
            return True
        if lowered in ("0", "false", "no", "off"):
            return False
        raise InputError(f"--set {key}={text}: expected on/off (1/0, true/false)")
    if "str" in str(kind):
        return text
    try:
        number = float(text)
    except ValueError:
        raise InputError(f"--set {key}={text}: VALUE must be a number") from None
    if not math.isfinite(number):
        raise InputError(f"--set {key}={text}: VALUE must be finite")
    if "int" in str(kind) and "float" not in str(kind):
        if number != int(number):
            raise InputError(f"--set {key}={text}: VALUE must be a whole number")
        return int(number)
    return number


def _loop_rate_for(truth_hz: float, needed_hz: float) -> float:
    """The slowest autopilot loop rate that divides truth_hz and is at least needed_hz."""
    for k in range(int(truth_hz), 0, -1):
        rate = truth_hz / k
        if rate >= needed_hz - 1e-9:
            return rate
    raise InputError(f"rate {needed_hz} Hz above the truth rate {truth_hz} Hz")


def apply_settings(config: SimConfig, settings: Mapping[str, object] | list[str]) -> SimConfig:
    """A copy of ``config`` with ``KEY=VALUE`` settings (``--set``) applied; see the module docstring.

    Rates: a rate above the autopilot loop (``imu_hz``, default 50 Hz) raises the loop to the slowest rate
    that divides the truth rate and carries it (e.g. mag_hz=100 -> a 100 Hz loop). ``telemetry_hz=R`` sets
    RAW_IMU, ATTITUDE and SERVO_OUTPUT_RAW to R Hz, RC/VFR_HUD/power to min(R, 10) Hz and GPS to min(R, 5)
    Hz, like a telemetry link's SR*_ stream rates."""
    pairs: dict[str, str] = {}
    items: list[tuple[str, str]] = (
        [(k, v if isinstance(v, str) else str(v)) for k, v in settings.items()]
        if isinstance(settings, Mapping)
        else [_split(text) for text in settings]
    )
    for key, value in items:
        pairs[key.strip()] = value
    kinds = {f.name: f.type for f in dataclasses.fields(Variation)}
    var_changes: dict[str, Any] = {}
    rate_changes: dict[str, float] = {}
    run_changes: dict[str, Any] = {}
    loc_changes: dict[str, float] = {}
    for key, text in pairs.items():
        if key in kinds:
            var_changes[key] = _parse_value(key, text, kinds[key])
        elif key in RATE_KEYS:
            rate = _parse_value(key, text, "float")
            assert isinstance(rate, float)
            if not 0.0 < rate <= 200.0:
                raise InputError(f"--set {key}={text}: rate must be in (0, 200] Hz")
            rate_changes[key] = rate
        elif key in ("lat_deg", "lon_deg", "alt_m", "decimal_year"):
            number = _parse_value(key, text, "float")
            assert isinstance(number, float)
            loc_changes[key] = number
        else:
            run_changes[key] = _run_setting(config, key, text)
    if run_changes.get("seed", 0) < 0:
        raise InputError("--set seed: must be >= 0")
    rates = _with_rates(config.rates, rate_changes) if rate_changes else config.rates
    location = dataclasses.replace(config.location, **loc_changes) if loc_changes else config.location
    variation = dataclasses.replace(config.variation, **var_changes) if var_changes else config.variation
    return dataclasses.replace(
        config,
        rates=rates,
        location=location,
        variation=variation,
        **run_changes,  # type: ignore[arg-type]
    )


def _run_setting(config: SimConfig, key: str, text: str) -> Any:
    """The value of a setting of the run itself (vehicle, seed, n_compasses, theta_mgauss, duration_s)."""
    if key == "vehicle":
        vehicle = text.strip()
        fixed = SCENARIO_VEHICLE.get(config.scenario)
        if fixed is not None and vehicle != fixed:
            raise InputError(f"scenario {config.scenario} is a {fixed} flight; choose the scenario instead")
        return vehicle
    if key in ("seed", "n_compasses"):
        return _parse_value(key, text, "int")
    if key == "theta_mgauss":
        parts = text.replace(";", ",").split(",")
        values = [_parse_value(key, part, "float") for part in parts]
        if len(values) != 3:
            raise InputError(f"--set theta_mgauss={text}: expected three numbers X,Y,Z (mgauss)")
        return tuple(values)
    if key == "duration_s":
        return _parse_value(key, text, "float")
    raise InputError(f"unknown setting {key!r} (choose from {', '.join(setting_keys())})")


def _with_rates(rates: Rates, rate_changes: dict[str, float]) -> Rates:
    """``rates`` with the rate settings applied (``telemetry_hz`` expanded, the loop raised where needed)."""
    rate_changes = dict(rate_changes)
    kw: dict[str, float | None] = {}
    tele = rate_changes.pop("telemetry_hz", None)
    if tele is not None:
        kw.update(
            raw_imu_hz=tele, attitude_hz=tele, servo_hz=tele, rc_hz=min(tele, 10.0),
            vfr_hud_hz=min(tele, 10.0), power_hz=min(tele, 10.0), heartbeat_hz=min(tele, 1.0),
            gps_hz=min(tele, 5.0),
        )  # fmt: skip
    loop = rate_changes.pop("loop_hz", None)
    kw.update(rate_changes)
    current = dataclasses.asdict(rates)
    current.update(kw)
    carried = [f.name for f in dataclasses.fields(Rates) if f.metadata.get("max_hz") == "imu_hz"]
    needed = max(float(current[k]) for k in carried if current[k] is not None)
    loop_hz = float(loop) if loop is not None else max(rates.imu_hz, _loop_rate_for(rates.truth_hz, needed))
    current["imu_hz"] = loop_hz
    if loop is None and loop_hz != rates.imu_hz and rates.raw_imu_hz is None and "raw_imu_hz" not in kw:
        current["raw_imu_hz"] = rates.imu_hz  # raising the loop leaves the RAW_IMU rate where it was
    if loop is None and loop_hz != rates.imu_hz and rates.mag_hz is None and "mag_hz" not in kw:
        current["mag_hz"] = rates.imu_hz
    return Rates(**current)  # type: ignore[arg-type]


def _split(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise InputError(f"--set {text!r}: expected KEY=VALUE, e.g. mag_hz=10")
    return key, value


def sample_variation(rng: np.random.Generator) -> dict[str, str]:
    """One random draw of the knobs over plausible ranges (issue 10's "deliberately varied" clean logs);
    feed it to :func:`apply_settings`. Ranges (each independent):

    rates: 40 % telemetry-like (RAW_IMU = ATTITUDE = 1, 2, 4 or 10 Hz, link loss 0-5 %), else an onboard
    rate (RAW_IMU 10-100 Hz, compass updates 10 Hz .. the RAW_IMU rate, ATTITUDE 1-50 Hz); compass LSB
    0.15 / 0.92 / 1.5 / 3 mgauss, white noise x0.3-2, AR(1) 0-5 mgauss with tau 0.5-10 s, random walk
    0-0.3 mgauss/sqrt(s); autopilot yaw: 60 % its internal compass, 20 % an external compass 0, 20 % GPS
    yaw; autopilot calibration on 80 % (residual hard iron 0-40 mgauss, soft iron 0-5 %); ATTITUDE biases
    roll/pitch +-2 deg, yaw +-3 deg, noise 0-0.5 deg; filter gains kp_yaw 0.02-1 (log-uniform), kp_tilt
    0.5-2; gyro noise x0.5-3, bias x0-2; hover throttle 0.35-0.6; theta x0.3-2; place: latitude +-60 deg,
    any longitude, date 2025.0-2029.9; seed 0-2^31. The scenario (``ordinary`` multirotor or
    ``ordinary_plane``) is the caller's choice."""
    out: dict[str, float | str] = {}
    if rng.random() < 0.4:
        out["telemetry_hz"] = float(rng.choice([1.0, 2.0, 4.0, 10.0]))
        out["link_loss"] = round(float(rng.uniform(0.0, 0.05)), 4)
    else:
        raw = float(rng.choice([10.0, 20.0, 25.0, 50.0, 100.0]))
        out["raw_imu_hz"] = raw
        out["mag_hz"] = round(float(np.exp(rng.uniform(math.log(10.0), math.log(raw)))), 2)
        out["attitude_hz"] = float(rng.choice([1.0, 2.0, 4.0, 10.0, 25.0, 50.0]))
    out["mag_lsb_mgauss"] = float(rng.choice([0.15, 0.92, 1.5, 3.0]))
    out["mag_noise_scale"] = round(float(rng.uniform(0.3, 2.0)), 3)
    out["mag_ar1_sigma_mgauss"] = round(float(rng.uniform(0.0, 5.0)), 3)
    out["mag_ar1_tau_s"] = round(float(np.exp(rng.uniform(math.log(0.5), math.log(10.0)))), 3)
    out["mag_rw_mgauss_per_sqrt_s"] = round(float(rng.uniform(0.0, 0.3)), 4)
    yaw = rng.random()
    out["yaw_source"] = "truth" if yaw < 0.2 else "compass"
    out["external_compass0"] = "on" if 0.2 <= yaw < 0.4 else "off"
    out["n_compasses"] = 2 if out["external_compass0"] == "on" else int(rng.choice([1, 2, 3]))
    out["ap_calibration"] = "on" if rng.random() < 0.8 else "off"
    out["ap_cal_hard_iron_mgauss"] = round(float(rng.uniform(0.0, 40.0)), 2)
    out["ap_cal_soft_iron"] = round(float(rng.uniform(0.0, 0.05)), 4)
    out["att_roll_bias_deg"] = round(float(rng.uniform(-2.0, 2.0)), 3)
    out["att_pitch_bias_deg"] = round(float(rng.uniform(-2.0, 2.0)), 3)
    out["att_yaw_bias_deg"] = round(float(rng.uniform(-3.0, 3.0)), 3)
    out["att_noise_deg"] = round(float(rng.uniform(0.0, 0.5)), 3)
    # log-uniform from a real EKF's slow compass pull (log171: 0.01-0.02 /s, a 50-100 s time constant;
    # benchmarks/autopilot_yaw_follow.py) to a complementary filter's 1 /s
    out["ap_kp_yaw"] = round(float(np.exp(rng.uniform(math.log(0.02), math.log(1.0)))), 4)
    out["ap_kp_tilt"] = round(float(rng.uniform(0.5, 2.0)), 3)
    out["gyro_noise_scale"] = round(float(rng.uniform(0.5, 3.0)), 3)
    out["gyro_bias_scale"] = round(float(rng.uniform(0.0, 2.0)), 3)
    out["hover_throttle"] = round(float(rng.uniform(0.35, 0.6)), 3)
    out["theta_scale"] = round(float(rng.uniform(0.3, 2.0)), 3)
    out["lat_deg"] = round(float(rng.uniform(-60.0, 60.0)), 4)
    out["lon_deg"] = round(float(rng.uniform(-180.0, 180.0)), 4)
    out["decimal_year"] = round(float(rng.uniform(2025.0, 2029.9)), 3)
    out["seed"] = int(rng.integers(0, 2**31))
    return {k: str(v) for k, v in out.items()}
