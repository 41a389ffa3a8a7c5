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
from collections.abc import Callable
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


# ----------------------------------------------------------------------------------------- rules
# Each checked key's default carries its rule (``_ruled``): the check a configured value must pass and the
# rule's text in the error. Types are checked separately, from the defaults.


def _ruled(default: Any, check: Callable[[Any], bool], rule: str) -> Any:
    """A field with ``default`` whose configured values must pass ``check`` ("... must {rule}")."""
    return field(default=default, metadata={"rule": (check, rule)})


def _one_of(default: str, choices: tuple[str, ...]) -> Any:
    """A field whose configured value must be one of ``choices``."""
    return _ruled(default, lambda v: v in choices, f"be one of {', '.join(choices)}")


def _positive(v: float) -> bool:
    return v > 0.0


def _non_negative(v: float) -> bool:
    return v >= 0.0


def _up_to(default: float, high: float, unit: str = "") -> Any:
    """A field whose configured values must lie in (0, ``high``] (``unit`` in the rule's text)."""
    return _ruled(default, lambda v: 0.0 < v <= high, f"be in (0, {high:g}]" + (f" {unit}" if unit else ""))


def _positive_field(default: float) -> Any:
    return _ruled(default, _positive, "be > 0")


def _non_negative_field(default: float) -> Any:
    return _ruled(default, _non_negative, "be >= 0")


def _throttle_source_ok(v: str) -> bool:
    return v in ("auto", "motors", "vfr_hud", "ctun", "none") or (
        v.split(":")[0] in ("servo", "rc") and v.split(":")[-1].isdigit() and ":" in v
    )


def _compass_indices_ok(v: tuple[int, ...]) -> bool:
    return all(0 <= i <= 7 for i in v)


#: the calibration buffer holds this many 3-vectors at most (24 MB); more is a typo, not a wish
MAX_CALIBRATION_SAMPLES = 1_000_000
_SAMPLES_RULE = f"be in [20, {MAX_CALIBRATION_SAMPLES}]"


@dataclass(frozen=True)
class InputConfig:
    """Which inputs to use and which samples to refuse.

    throttle_source: ``auto``, ``servo:N``, ``motors``, ``rc:N``, ``vfr_hud``, ``ctun``, ``none``.
    compasses: compass indices to correct; empty = every compass the vehicle sends.
    attitude: ``mahony`` (our own filter on gyro + accelerometer, as in the paper, sec. II-A) or
    ``autopilot`` (roll and pitch from ATTITUDE).
    """

    throttle_source: str = _ruled(
        "auto", _throttle_source_ok, "be auto, motors, vfr_hud, ctun, none, servo:N or rc:N"
    )
    compasses: tuple[int, ...] = _ruled((), _compass_indices_ok, "hold compass indices 0..7")
    attitude: str = _one_of("auto", ATTITUDE_SOURCES)
    saturation_mgauss: float = _positive_field(8000.0)
    # below the largest rate RAW_IMU / SCALED_IMU* can carry (int16 mrad/s: 32.767 rad/s), so a value
    # clipped at the message's integer limit reads as saturated; also below the 2000 deg/s (34.9 rad/s)
    # range of the usual MEMS gyros, where DataFlash IMU values clip
    gyro_saturation_rad_s: float = _positive_field(32.7)
    stale_s: float = _positive_field(0.5)
    time_reset_s: float = _positive_field(1.0)


@dataclass(frozen=True)
class FilterConfig:
    """The 5 Hz low-pass of sec. II-D."""

    corner_hz: float = _positive_field(5.0)
    order: int = _ruled(2, lambda v: v in (1, 2), "be 1 or 2")


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

    form: ObserverForm = _one_of("default", OBSERVER_FORMS)  # noqa: RUF009 (a field, as every _ruled)
    learn: bool = True
    # k1, k2 = ObserverParams.k1_1_s, ObserverParams.k2 (tests/unit/test_config.py holds the defaults equal)
    k1: float = _positive_field(2.0)
    k2: float = _positive_field(4.0)
    forget_s: float = _positive_field(30.0)
    theta_max_mgauss: float = _positive_field(2000.0)
    dt_min_s: float = _positive_field(0.001)
    dt_max_s: float = _up_to(0.2, 5.0, "s")
    max_throttle_jump_01: float = _up_to(0.15, 1.0)


@dataclass(frozen=True)
class MahonyConfig:
    """Complementary attitude filter of ref. [23] (gains in rad/s per unit error)."""

    kp: float = _non_negative_field(1.0)
    ki: float = _non_negative_field(0.1)
    accel_gate_m_s2: float = _positive_field(2.0)


@dataclass(frozen=True)
class CalibrationConfig:
    """DPI calibration, eqs. (1)-(3), from a hand rotation at zero throttle.

    mode: ``auto`` (stored calibration if any, else learn one), ``learn`` (ignore the stored one),
    ``stored`` (only a stored one; uncalibrated otherwise), ``none`` (identity: L = I, d = 0).
    """

    mode: str = _one_of("auto", CALIBRATION_MODES)
    max_throttle_01: float = _ruled(0.05, lambda v: 0.0 <= v <= 1.0, "be in [0, 1]")
    min_samples: int = _ruled(500, lambda v: 20 <= v <= MAX_CALIBRATION_SAMPLES, _SAMPLES_RULE)
    max_samples: int = _ruled(10000, lambda v: 20 <= v <= MAX_CALIBRATION_SAMPLES, _SAMPLES_RULE)
    check_every: int = _ruled(250, lambda v: v >= 1, "be >= 1")


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
    solve_period_s: the estimate is re-solved at most this often (s of message time): how often the live
    correction is refreshed (the first pass of a two-pass replay re-solves less often,
    ``service/inflight_stage.py`` LEARN_SOLVE_PERIOD_S: only its final estimate is published). 0.5 s: the
    calibration and theta are constants of the vehicle, and re-solving every 0.1 s instead cost 1.7 s more
    CPU on a 10 min `--causal` replay (6.1 -> 4.4 s) for the same headings (ordinary flight within 1 %,
    log171 8.20 / 8.90 -> 8.16 / 8.91 deg, the corpus's causal verdicts unchanged; docs/benchmarks.md).
    tilt_solve_period_s: the relative form's tilt model (whose theta is the one published) is re-solved at
    most this often, at whole multiples of solve_period_s; every 5 s instead of 1 s took the simulated
    10 Hz internal-primary flights' theta error from 6.6 to 7.1 % of |theta| (mean of 4 seeds).
    """

    enabled: bool = True
    reference: str = _one_of("auto", INFLIGHT_REFERENCES)
    rotation: str = _ruled("auto", lambda v: v in ("auto", "gyro", "attitude"), "be auto, gyro or attitude")
    per_motor: str = _ruled("off", lambda v: v in ("auto", "off"), "be auto or off")
    max_rate_hz: float = _up_to(100.0, 1000.0, "Hz")
    absolute_settle_s: float = _non_negative_field(0.0)
    sigma_a_calibrated: float = _up_to(0.05, 1.0)
    sigma_a_uncalibrated: float = _up_to(0.3, 1.0)
    sigma_d_calibrated_mgauss: float = _positive_field(50.0)
    sigma_d_uncalibrated_mgauss: float = _positive_field(300.0)
    sigma_theta_mgauss: float = _positive_field(600.0)
    heading_ok_deg: float = _up_to(2.0, 90.0, "deg")
    heading_converged_deg: float = _up_to(1.0, 90.0, "deg")
    solve_period_s: float = _up_to(0.5, 10.0, "s")
    tilt_solve_period_s: float = _up_to(1.0, 60.0, "s")


@dataclass(frozen=True)
class LocationConfig:
    """Where the vehicle flies, for the WMM Earth field the calibration is scaled to."""

    lat_deg: float = _ruled(29.65, lambda v: -90.0 <= v <= 90.0, "be in [-90, 90]")
    lon_deg: float = _ruled(-82.35, lambda v: -180.0 <= v <= 360.0, "be in [-180, 360]")
    alt_m: float = _ruled(30.0, lambda v: -1000.0 <= v <= 100000.0, "be in [-1000, 100000] m")
    decimal_year: float = _ruled(
        2025.5, lambda v: 2010.0 <= v < 2030.0, "be in [2010, 2030) (WMM 2010-2025 validity)"
    )


@dataclass(frozen=True)
class OutputConfig:
    """What is published. rate_hz = 0: one MAGCOMP_HEADING per magnetometer sample.

    heading_tau_s: time constant of the gyro-aided complementary filter on both headings (0 = the raw
    per-sample tilt-compensated eq. (24)); see :class:`magcomp.core.heading_filter.HeadingFilter`.

    named_values_hz: NAMED_VALUE_FLOAT values a pilot sees without the dialect (MC_HDG0, MC_THETA0,
    MC_STAT0 ...; docs/pilots.md) at most this often per compass, message time, on live links (0 = none).
    """

    rate_hz: float = _ruled(0.0, _non_negative, "be >= 0 (0 = every magnetometer sample)")
    heading_tau_s: float = _ruled(4.0, lambda v: 0.0 <= v <= 60.0, "be in [0, 60] s (0 = unfiltered)")
    #: publish a correction only where the self-check against the gyro and the autopilot's yaw finds it
    #: better than the autopilot's own heading (docs/real-flights.md); false: as soon as it is learned
    self_check: bool = True
    named_values_hz: float = _ruled(2.0, lambda v: 0.0 <= v <= 50.0, "be in [0, 50] Hz (0 = none)")
    source_system: int = _ruled(0, lambda v: 0 <= v <= 255, "be in 0..255 (0 = the vehicle's own id)")
    source_component: int = _ruled(191, lambda v: 1 <= v <= 255, "be in 1..255")


@dataclass(frozen=True)
class StateConfig:
    """How often theta is written to the state directory (message time)."""

    save_interval_s: float = _positive_field(10.0)


@dataclass(frozen=True)
class LinkConfig:
    """Live link behaviour."""

    reconnect_s: float = _up_to(1.0, 3600.0, "s")
    silence_s: float = _positive_field(5.0)
    heartbeat_hz: float = _ruled(1.0, lambda v: 0.0 <= v <= 50.0, "be in [0, 50] Hz (0 = no heartbeat)")


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
        specs = {f.name: f for f in fields(current)}
        changes: dict[str, Any] = {}
        for key, value in raw.items():
            if key not in specs:
                known = ", ".join(specs)
                raise ConfigError(f"config {origin}: unknown key '{key}' in [{name}] (known: {known})")
            v = _coerce(origin, name, key, getattr(current, key), value)
            rule = specs[key].metadata.get("rule")
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
