"""Configuration: TOML (``tomllib``) -> frozen dataclasses, every value validated once.

A file only needs the keys it changes; everything else keeps the defaults below, which
``config/default.toml`` mirrors key for key (a test holds them equal). Unknown sections or keys are
rejected with their name, wrong types and out-of-range values with the key, the rule and the value,
always as one-line :class:`~magcomp.errors.InputError` messages such as
``config my.toml: [observer] k1 must be > 0, got -1``.

This is the only module that reads configuration files.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal, get_args

from magcomp.errors import InputError

ATTITUDE_SOURCES = ("auto", "mahony", "autopilot")
CALIBRATION_MODES = ("auto", "learn", "stored", "none")
INFLIGHT_REFERENCES = ("auto", "absolute", "relative")
#: ``[observer] form``: which member of the eq. (20) family runs (magcomp.service.estimators.observer_params)
ObserverForm = Literal["default", "paper", "delta_dot", "regression"]
OBSERVER_FORMS: tuple[str, ...] = get_args(ObserverForm)


class ConfigError(InputError):
    """A configuration file or value that cannot be used."""


@dataclass(frozen=True)
class InputConfig:
    """Which inputs to use and which samples to refuse.

    throttle_source: ``auto``, ``servo:N``, ``motors``, ``rc:N``, ``vfr_hud``, ``ctun``, ``none``.
    compasses: compass indices to correct; empty = every compass the vehicle sends.
    attitude: ``mahony`` (our own filter on gyro + accelerometer, as in the paper, sec. II-A) or
    ``autopilot`` (roll and pitch from ATTITUDE).
    """

    throttle_source: str = "auto"
    compasses: tuple[int, ...] = ()
    attitude: str = "auto"
    saturation_mgauss: float = 8000.0
    # below the largest rate RAW_IMU / SCALED_IMU* can carry (int16 mrad/s: 32.767 rad/s), so a value
    # clipped at the message's integer limit reads as saturated; also below the 2000 deg/s (34.9 rad/s)
    # range of the usual MEMS gyros, where DataFlash IMU values clip
    gyro_saturation_rad_s: float = 32.7
    stale_s: float = 0.5
    time_reset_s: float = 1.0


@dataclass(frozen=True)
class FilterConfig:
    """The 5 Hz low-pass of sec. II-D."""

    corner_hz: float = 5.0
    order: int = 2


@dataclass(frozen=True)
class ObserverConfig:
    """Online theta estimator, eq. (20) family (:mod:`magcomp.core.observer`).

    form: ``default``/``regression`` (recursive least squares on the exact discrete model, the 5 Hz
    filter on the regression: unbiased), ``delta_dot`` (eq. (20) with the throttle-rate term of
    eq. (16)), ``paper`` (eq. (20) as printed). k1 (1/s), k2: gains of eq. (20) (observer forms);
    forget_s: forgetting time constant of the regression form. learn = false: keep the stored theta
    fixed (no online estimation; bias = stored theta * throttle^2). max_throttle_jump_01: a magnetometer
    sample between two throttle samples further apart than this is not used by the observer (the
    instant of the step is unknown, and interpolating across it would feed eq. (16) a wrong delta_dot).
    """

    form: ObserverForm = "default"
    learn: bool = True
    k1: float = 2.0  # = ObserverParams.k1_1_s (tests/unit/test_config.py holds the defaults equal)
    k2: float = 4.0  # = ObserverParams.k2
    forget_s: float = 30.0
    theta_max_mgauss: float = 2000.0
    dt_min_s: float = 0.001
    dt_max_s: float = 0.2
    max_throttle_jump_01: float = 0.15


@dataclass(frozen=True)
class MahonyConfig:
    """Complementary attitude filter of ref. [23] (gains in rad/s per unit error)."""

    kp: float = 1.0
    ki: float = 0.1
    accel_gate_m_s2: float = 2.0


@dataclass(frozen=True)
class CalibrationConfig:
    """DPI calibration, eqs. (1)-(3), from a hand rotation at zero throttle.

    mode: ``auto`` (stored calibration if any, else learn one), ``learn`` (ignore the stored one),
    ``stored`` (only a stored one; uncalibrated otherwise), ``none`` (identity: L = I, d = 0).
    """

    mode: str = "auto"
    max_throttle_01: float = 0.05
    min_samples: int = 500
    max_samples: int = 10000
    check_every: int = 250


@dataclass(frozen=True)
class InflightConfig:
    """In-flight calibration jointly with theta (magcomp/core/inflight.py), for compasses that have no
    hand-rotation (or stored) calibration: real flights.

    reference: ``auto`` (from the autopilot's parameters: absolute where the autopilot's yaw comes from an
    external compass other than this one or from GPS, else relative), ``absolute`` (the autopilot's
    attitude, yaw included, is trusted), ``relative`` (only rotations from the gyro / attitude are used).
    rotation: where the relative form's rotations come from: ``auto`` (the integrated gyro while it is fast,
    unless this compass is the external primary; else the autopilot's attitude), ``gyro`` or ``attitude``.
    per_motor: ``off`` (the paper's eq. (11)) or ``auto`` (per-motor vectors when motor outputs are known).
    max_rate_hz: samples per second and compass fed to the estimator (white noise averages down with
    every sample: at 50 Hz, feeding all instead of 10 Hz halved theta's error on the simulated flight).
    absolute_settle_s: the autopilot's yaw is used only with the motors running and this long after they
    start (before arming its yaw can be tens of degrees off).
    sigma_*: the prior around the autopilot's own calibration (see InflightParams).
    """

    enabled: bool = True
    reference: str = "auto"
    rotation: str = "auto"
    per_motor: str = "off"
    max_rate_hz: float = 100.0
    absolute_settle_s: float = 0.0
    sigma_a_calibrated: float = 0.05
    sigma_a_uncalibrated: float = 0.3
    sigma_d_calibrated_mgauss: float = 50.0
    sigma_d_uncalibrated_mgauss: float = 300.0
    sigma_theta_mgauss: float = 600.0
    heading_ok_deg: float = 2.0
    heading_converged_deg: float = 1.0


@dataclass(frozen=True)
class LocationConfig:
    """Where the vehicle flies, for the WMM Earth field the calibration is scaled to."""

    lat_deg: float = 29.65
    lon_deg: float = -82.35
    alt_m: float = 30.0
    decimal_year: float = 2025.5


@dataclass(frozen=True)
class OutputConfig:
    """What is published. rate_hz = 0: one MAGCOMP_HEADING per magnetometer sample.

    heading_tau_s: time constant of the gyro-aided complementary filter on both headings (0 = the raw
    per-sample tilt-compensated eq. (24)); see :class:`magcomp.service.estimators.HeadingFilter`.

    named_values_hz: NAMED_VALUE_FLOAT values a pilot sees without the dialect (MC_HDG0, MC_THETA0,
    MC_STAT0 ...; docs/pilots.md) at most this often per compass, message time, on live links (0 = none).
    """

    rate_hz: float = 0.0
    heading_tau_s: float = 1.0
    #: publish a correction only where the self-check against the gyro and the autopilot's yaw finds it
    #: better than the autopilot's own heading (docs/real-flights.md); false: as soon as it is learned
    self_check: bool = True
    named_values_hz: float = 2.0
    source_system: int = 0
    source_component: int = 191


@dataclass(frozen=True)
class StateConfig:
    """How often theta is written to the state directory (message time)."""

    save_interval_s: float = 10.0


@dataclass(frozen=True)
class LinkConfig:
    """Live link behaviour."""

    reconnect_s: float = 1.0
    silence_s: float = 5.0
    heartbeat_hz: float = 1.0


@dataclass(frozen=True)
class Config:
    input: InputConfig = field(default_factory=InputConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    observer: ObserverConfig = field(default_factory=ObserverConfig)
    mahony: MahonyConfig = field(default_factory=MahonyConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    inflight: InflightConfig = field(default_factory=InflightConfig)
    location: LocationConfig = field(default_factory=LocationConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    state: StateConfig = field(default_factory=StateConfig)
    link: LinkConfig = field(default_factory=LinkConfig)


# ----------------------------------------------------------------------------------------- validation


def _positive(v: float) -> bool:
    return v > 0.0


def _non_negative(v: float) -> bool:
    return v >= 0.0


#: the calibration buffer holds this many 3-vectors at most (24 MB); more is a typo, not a wish
MAX_CALIBRATION_SAMPLES = 1_000_000
_SAMPLES_RULE = f"be in [20, {MAX_CALIBRATION_SAMPLES}]"

# (section, key) -> (predicate, rule text). Types are checked separately from the dataclass defaults.
_RULES: dict[tuple[str, str], tuple[Any, str]] = {
    ("input", "attitude"): (lambda v: v in ATTITUDE_SOURCES, f"be one of {', '.join(ATTITUDE_SOURCES)}"),
    ("input", "throttle_source"): (
        lambda v: (
            v in ("auto", "motors", "vfr_hud", "ctun", "none")
            or (v.split(":")[0] in ("servo", "rc") and v.split(":")[-1].isdigit() and ":" in v)
        ),
        "be auto, motors, vfr_hud, ctun, none, servo:N or rc:N",
    ),
    ("input", "compasses"): (lambda v: all(0 <= i <= 7 for i in v), "hold compass indices 0..7"),
    ("input", "saturation_mgauss"): (_positive, "be > 0"),
    ("input", "gyro_saturation_rad_s"): (_positive, "be > 0"),
    ("input", "stale_s"): (_positive, "be > 0"),
    ("input", "time_reset_s"): (_positive, "be > 0"),
    ("filter", "corner_hz"): (_positive, "be > 0"),
    ("filter", "order"): (lambda v: v in (1, 2), "be 1 or 2"),
    ("observer", "form"): (lambda v: v in OBSERVER_FORMS, f"be one of {', '.join(OBSERVER_FORMS)}"),
    ("observer", "k1"): (_positive, "be > 0"),
    ("observer", "k2"): (_positive, "be > 0"),
    ("observer", "forget_s"): (_positive, "be > 0"),
    ("observer", "theta_max_mgauss"): (_positive, "be > 0"),
    ("observer", "dt_min_s"): (_positive, "be > 0"),
    ("observer", "dt_max_s"): (lambda v: 0.0 < v <= 5.0, "be in (0, 5] s"),
    ("observer", "max_throttle_jump_01"): (lambda v: 0.0 < v <= 1.0, "be in (0, 1]"),
    ("mahony", "kp"): (_non_negative, "be >= 0"),
    ("mahony", "ki"): (_non_negative, "be >= 0"),
    ("mahony", "accel_gate_m_s2"): (_positive, "be > 0"),
    ("calibration", "mode"): (lambda v: v in CALIBRATION_MODES, f"be one of {', '.join(CALIBRATION_MODES)}"),
    ("calibration", "max_throttle_01"): (lambda v: 0.0 <= v <= 1.0, "be in [0, 1]"),
    ("calibration", "min_samples"): (lambda v: 20 <= v <= MAX_CALIBRATION_SAMPLES, _SAMPLES_RULE),
    ("calibration", "max_samples"): (lambda v: 20 <= v <= MAX_CALIBRATION_SAMPLES, _SAMPLES_RULE),
    ("calibration", "check_every"): (lambda v: v >= 1, "be >= 1"),
    ("inflight", "reference"): (
        lambda v: v in INFLIGHT_REFERENCES,
        f"be one of {', '.join(INFLIGHT_REFERENCES)}",
    ),
    ("inflight", "per_motor"): (lambda v: v in ("auto", "off"), "be auto or off"),
    ("inflight", "rotation"): (lambda v: v in ("auto", "gyro", "attitude"), "be auto, gyro or attitude"),
    ("inflight", "max_rate_hz"): (lambda v: 0.0 < v <= 1000.0, "be in (0, 1000] Hz"),
    ("inflight", "absolute_settle_s"): (_non_negative, "be >= 0"),
    ("inflight", "sigma_a_calibrated"): (lambda v: 0.0 < v <= 1.0, "be in (0, 1]"),
    ("inflight", "sigma_a_uncalibrated"): (lambda v: 0.0 < v <= 1.0, "be in (0, 1]"),
    ("inflight", "sigma_d_calibrated_mgauss"): (_positive, "be > 0"),
    ("inflight", "sigma_d_uncalibrated_mgauss"): (_positive, "be > 0"),
    ("inflight", "sigma_theta_mgauss"): (_positive, "be > 0"),
    ("inflight", "heading_ok_deg"): (lambda v: 0.0 < v <= 90.0, "be in (0, 90] deg"),
    ("inflight", "heading_converged_deg"): (lambda v: 0.0 < v <= 90.0, "be in (0, 90] deg"),
    ("location", "lat_deg"): (lambda v: -90.0 <= v <= 90.0, "be in [-90, 90]"),
    ("location", "lon_deg"): (lambda v: -180.0 <= v <= 360.0, "be in [-180, 360]"),
    ("location", "alt_m"): (lambda v: -1000.0 <= v <= 100000.0, "be in [-1000, 100000] m"),
    ("location", "decimal_year"): (
        lambda v: 2010.0 <= v < 2030.0,
        "be in [2010, 2030) (WMM 2010-2025 validity)",
    ),
    ("output", "rate_hz"): (_non_negative, "be >= 0 (0 = every magnetometer sample)"),
    ("output", "named_values_hz"): (lambda v: 0.0 <= v <= 50.0, "be in [0, 50] Hz (0 = none)"),
    ("output", "heading_tau_s"): (lambda v: 0.0 <= v <= 60.0, "be in [0, 60] s (0 = unfiltered)"),
    ("output", "source_system"): (lambda v: 0 <= v <= 255, "be in 0..255 (0 = the vehicle's own id)"),
    ("output", "source_component"): (lambda v: 1 <= v <= 255, "be in 1..255"),
    ("state", "save_interval_s"): (_positive, "be > 0"),
    ("link", "reconnect_s"): (lambda v: 0.0 < v <= 3600.0, "be in (0, 3600] s"),
    ("link", "silence_s"): (_positive, "be > 0"),
    ("link", "heartbeat_hz"): (lambda v: 0.0 <= v <= 50.0, "be in [0, 50] Hz (0 = no heartbeat)"),
}


def _coerce(origin: str, section: str, key: str, default: Any, value: Any) -> Any:
    """Check ``value`` against the type of ``default``; ints are accepted where floats are expected."""
    where = f"config {origin}: [{section}] {key}"
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{where} must be a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ConfigError(f"{where} must be finite, got {value!r}")
        return float(value)
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return value
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    if isinstance(default, tuple):
        ints = isinstance(value, list) and all(isinstance(i, int) and not isinstance(i, bool) for i in value)
        if not ints:
            raise ConfigError(f"{where} must be a list of integers, got {value!r}")
        return tuple(value)
    raise ConfigError(f"{where}: unsupported value {value!r}")  # pragma: no cover


def config_from_dict(data: dict[str, Any], origin: str = "<dict>", base: Config | None = None) -> Config:
    """Validate a parsed TOML document and lay it over ``base`` (default: the built-in defaults)."""
    cfg = base if base is not None else Config()
    section_names = [f.name for f in fields(Config)]
    for name in data:
        if name not in section_names:
            known = ", ".join(section_names)
            raise ConfigError(f"config {origin}: unknown section [{name}] (known: {known})")
    updates: dict[str, Any] = {}
    for name in section_names:
        if name not in data:
            continue
        raw = data[name]
        if not isinstance(raw, dict):
            raise ConfigError(f"config {origin}: [{name}] must be a table, got {raw!r}")
        current = getattr(cfg, name)
        keys = [f.name for f in fields(current)]
        changes: dict[str, Any] = {}
        for key, value in raw.items():
            if key not in keys:
                known = ", ".join(keys)
                raise ConfigError(f"config {origin}: unknown key '{key}' in [{name}] (known: {known})")
            v = _coerce(origin, name, key, getattr(current, key), value)
            rule = _RULES.get((name, key))
            if rule is not None and not rule[0](v):
                raise ConfigError(f"config {origin}: [{name}] {key} must {rule[1]}, got {value!r}")
            changes[key] = v
        updates[name] = replace(current, **changes)
    out = replace(cfg, **updates)
    _check_cross(out, origin)
    return out


def _check_cross(cfg: Config, origin: str) -> None:
    if cfg.observer.dt_min_s >= cfg.observer.dt_max_s:
        raise ConfigError(
            f"config {origin}: [observer] dt_min_s ({cfg.observer.dt_min_s}) must be below dt_max_s "
            f"({cfg.observer.dt_max_s})"
        )
    if cfg.calibration.min_samples > cfg.calibration.max_samples:
        raise ConfigError(
            f"config {origin}: [calibration] min_samples ({cfg.calibration.min_samples}) must not exceed "
            f"max_samples ({cfg.calibration.max_samples})"
        )


def load_config(path: str | Path | None = None, base: Config | None = None) -> Config:
    """Read a TOML file (``None``: the defaults). Raises :class:`ConfigError` with a one-line message."""
    if path is None:
        return base if base is not None else Config()
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(f"config {p}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"config {p}: is a directory, not a TOML file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config {p}: cannot read ({exc.__class__.__name__}: {exc})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config {p}: not valid TOML ({exc})") from None
    return config_from_dict(data, str(p), base)


def config_to_dict(cfg: Config) -> dict[str, dict[str, Any]]:
    """The configuration as plain values (for summaries and for comparing with default.toml)."""
    out: dict[str, dict[str, Any]] = {}
    for sec in fields(cfg):
        section = getattr(cfg, sec.name)
        out[sec.name] = {
            f.name: list(getattr(section, f.name))
            if isinstance(getattr(section, f.name), tuple)
            else getattr(section, f.name)
            for f in fields(section)
        }
    return out
