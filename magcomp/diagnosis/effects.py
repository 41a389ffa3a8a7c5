"""Library of model extensions: physical causes that the paper's bias model, eq. (11)
``B = theta delta^2``, ignores.

Each extension has the same name as the simulator's hidden effect (:mod:`magcomp.sim.config`) and the same
physics, so a finding names the mechanism and its parameter in the simulator's units:

``throttle_offset`` (offset)      speed = (delta - offset)/(1 - offset), zero below: ESC dead band
                                  (replaces eq. (9))
``throttle_exponent`` (exponent)  B ~ speed^exponent instead of speed^2: C_Q of eq. (8) not constant
``current_lag`` (tau_s)           speed follows the command through a first-order lag (rotor inertia)
``time_skew`` (skew_s)            the field follows the logged throttle skew_s late (clocks/transport)
``voltage_sag`` (sag)             unregulated ESC: speed *= 1 - sag + sag V/V_full
``temperature_drift`` (mgauss_per_degc)  hard iron b + k (T - T0) u along a fixed direction u
``per_motor`` (spread)            B = sum_i theta_i m_i^2 / n, one theta_i per motor output m_i;
                                  spread = mean |theta_i - theta| / |theta|

The "drive" of the bias is the regressor column(s) that multiply the bias vectors. With every extension off
it is exactly ``delta^2`` (eq. (11)), normalised to 1 at full throttle so that theta is "mgauss at full
throttle". The nonlinear extension parameters change the column; ``temperature_drift`` and ``per_motor`` add
or split columns and are linear in their parameters.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class ExtensionParams:
    """Values of every extension; the defaults are "off" (the paper's model): the nonlinear parameters
    (``offset`` to ``sag``, see :func:`set_value`) at the values that leave eq. (11) as it is, and the linear
    effects (``temperature``, ``per_motor``) off."""

    offset: float = 0.0
    exponent: float = 2.0
    tau_s: float = 0.0
    skew_s: float = 0.0
    sag: float = 0.0
    temperature: bool = False
    per_motor: bool = False


@dataclass(frozen=True)
class Effect:
    """One extension.

    name: the simulator's effect name; cause: one sentence of physics; param: field of
    :class:`ExtensionParams` that is fitted nonlinearly (None for the linear effects);
    bounds / grid: search range and starting grid of that parameter; needs: the log signal required.
    """

    name: str
    cause: str
    param: str | None
    bounds: tuple[float, float]
    grid: tuple[float, ...]
    needs: str


EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            "throttle_offset",
            "ESC dead band / motor start-up friction: the motors do not turn (and draw no current) until the "
            "throttle passes an offset, so the bias follows ((throttle - offset)/(1 - offset))^2.",
            "offset",
            # physical ceiling, not the simulator's maximum: a dead band cannot reach the throttle the vehicle
            # flies at (hover 0.3-0.8 on multirotors, cruise on planes), and above the log's highest throttle
            # the bias vanishes; 0.9 keeps any flying vehicle's dead band inside the range, not at its edge
            (0.0, 0.9),
            (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.55, 0.7),
            "throttle",
        ),
        Effect(
            "throttle_exponent",
            "The propeller torque coefficient (eq. (8)) and ESC efficiency vary with speed, "
            "so the current and "
            "its field grow as throttle^exponent rather than throttle^2.",
            "exponent",
            # physical ceiling: the current cannot grow faster than shaft power (speed^3 for a fixed-pitch
            # propeller at fixed voltage), and a duty-to-speed curve steeper than linear or an efficiency that
            # falls with load (I^2 R) adds at most about one power more; beyond throttle^5 the bias is a step
            # near full throttle, which throttle_offset describes. 0.5: a thrust-linearised ESC (current ~
            # throttle) with a soft start
            (0.5, 5.0),
            (1.0, 1.5, 2.5, 3.0, 3.5, 4.5),
            "throttle",
        ),
        Effect(
            "current_lag",
            "Rotor inertia and the ESC's acceleration limit: motor speed, hence current and "
            "field, follows the "
            "throttle command through a first-order lag.",
            "tau_s",
            # physical ceiling: rotor spin-up is 0.02-0.2 s, an ESC / battery-current filter up to ~1 s, the
            # slowest powertrain loop that follows the command (a thermal / current-limit filter) several
            # seconds; 10 s keeps those inside the range. Slower than that, a "lag" is a drift over a 1-2 min
            # flight and the smooth time-drift nuisance is the right description
            (0.0, 10.0),
            (0.05, 0.1, 0.2, 0.4, 0.8, 1.5, 3.0, 6.0),
            "throttle",
        ),
        Effect(
            "time_skew",
            "The throttle and the magnetometer are stamped by different clocks or transport "
            "paths, so the field "
            "follows the logged throttle late (positive skew) or early.",
            "skew_s",
            # physical ceiling: clocks of one autopilot agree within ms; a ground station stamping telemetry
            # on receipt over a radio link with buffering sees up to ~1-3 s (1-2 Hz streams, retries); 3 s
            (-3.0, 3.0),
            (-2.0, -1.0, -0.6, -0.3, -0.15, -0.06, 0.06, 0.15, 0.3, 0.6, 1.0, 2.0),
            "throttle",
        ),
        Effect(
            "voltage_sag",
            "An unregulated ESC sets a duty cycle, so motor speed (and current) scales with "
            "the battery voltage, "
            "which falls with discharge and sags under load.",
            "sag",
            (0.0, 1.5),
            (0.25, 0.5, 0.75, 1.0),
            "voltage",
        ),
        Effect(
            "temperature_drift",
            "Hard iron that changes with the powertrain temperature (magnet remanence, "
            "magnetisation of nearby "
            "steel) adds an offset proportional to the temperature rise.",
            None,
            (0.0, 0.0),
            (),
            "temperature",
        ),
        Effect(
            "per_motor",
            "Each motor's ESC and wiring run along its own arm, so each motor output drives "
            "its own bias vector; "
            "the sum departs from theta * mean(throttle)^2 when the motors differ.",
            None,
            (0.0, 0.0),
            (),
            "motors",
        ),
    )
}


def set_value(p: ExtensionParams, param: str, value: float) -> ExtensionParams:
    """``p`` with the nonlinear extension parameter ``param`` (a field name) set to ``value``."""
    v = float(value)
    if param == "offset":
        return replace(p, offset=v)
    if param == "exponent":
        return replace(p, exponent=v)
    if param == "tau_s":
        return replace(p, tau_s=v)
    if param == "skew_s":
        return replace(p, skew_s=v)
    if param == "sag":
        return replace(p, sag=v)
    raise ValueError(f"unknown extension parameter {param!r}")


def with_effect(p: ExtensionParams, name: str, value: float | None = None) -> ExtensionParams:
    """``p`` with extension ``name`` switched on (nonlinear ones at ``value``)."""
    eff = EFFECTS[name]
    if eff.param is None:
        return replace(p, temperature=True) if name == "temperature_drift" else replace(p, per_motor=True)
    if value is None:
        raise ValueError(f"effect {name} needs a value")
    return set_value(p, eff.param, value)


@dataclass(frozen=True)
class DriveInputs:
    """The log's powertrain signals, ready for :func:`drive_columns`.

    t_s: (n,) compass sample times. grid_t_s: (g,) uniform grid (spacing ``grid_dt_s``) covering the log,
    on which
    throttle_grid (g,) 0..1, motors_grid (g, m) 0..1 or None and voltage_grid (g,) V or None are sampled.
    v_full_v: reference battery voltage of the sag model. temperature_degc: (n,) at the compass times or None.
    throttle_dt_s: median interval of the logged throttle (its time resolution).
    compass_timing_s: the range within which each compass sample's measurement time is not known (s): a held
    compass's message period (its update fell between two messages), an unheld one's largest age
    (:func:`~magcomp.diagnosis.latency.unheld_age_bounds_s`); 0 when the times are exact.
    """

    t_s: F64
    grid_t_s: F64
    grid_dt_s: float
    throttle_grid: F64
    motors_grid: F64 | None
    voltage_grid: F64 | None
    v_full_v: float
    temperature_degc: F64 | None
    throttle_dt_s: float = 0.04
    compass_timing_s: float = 0.0
    # nuisance columns found by the open search (:mod:`magcomp.diagnosis.structure`), e.g. a step: (n, k)
    extra: F64 | None = None
    extra_names: tuple[str, ...] = ()
    # the logged battery current (times, A), a second witness of the load (:mod:`magcomp.diagnosis.current`)
    current_t_s: F64 | None = None
    current_a: F64 | None = None


def _speed(x: F64, d: DriveInputs, p: ExtensionParams) -> F64:
    """Normalised motor speed from a command ``x`` on the grid: eq. (9) with offset, sag and lag."""
    o = min(max(p.offset, 0.0), 0.95)
    s = np.clip((x - o) / (1.0 - o), 0.0, None)  # eq. (9) with a dead band (throttle_offset)
    if p.sag != 0.0 and d.voltage_grid is not None:
        s = s * (1.0 - p.sag + p.sag * d.voltage_grid / d.v_full_v)  # voltage_sag
    if p.tau_s > 0.25 * d.grid_dt_s:
        a = float(np.exp(-d.grid_dt_s / p.tau_s))  # current_lag: exact first-order lag, ZOH input
        s = lfilter([1.0 - a], [1.0, -a], s, zi=[a * float(s[0])])[0]
    return np.asarray(s, dtype=float)


def drive_columns(d: DriveInputs, p: ExtensionParams) -> tuple[F64, tuple[str, ...]]:
    """Regressor columns that multiply the bias vectors, at the compass times, and their names.

    Baseline: one column ``delta^2`` (eq. (11)). per_motor: the mean load and m - 1 load differences.
    temperature_drift: an extra column ``T - mean(T)`` (degC).
    """
    t_eval = d.t_s - p.skew_s  # time_skew: the field at t follows the throttle logged at t - skew
    cols: list[F64] = []
    names: list[str] = []
    if p.per_motor and d.motors_grid is not None:
        # B = sum_i theta_i L_i / m with theta_i = theta + delta_i, sum_i delta_i = 0, written as
        # theta * mean(L) + sum_{i<m} delta_i (L_i - L_m) / m: theta stays well conditioned even when the
        # motors move together, and only the small differential part is spread over the delta_i.
        m = d.motors_grid.shape[1]
        loads = np.column_stack(
            [
                np.interp(t_eval, d.grid_t_s, np.power(_speed(d.motors_grid[:, i], d, p), p.exponent))
                for i in range(m)
            ]
        )
        cols.append(loads.mean(axis=1))
        names.append("throttle")
        for i in range(m - 1):
            cols.append((loads[:, i] - loads[:, m - 1]) / m)
            names.append(f"motor_diff{i + 1}")
    else:
        sp = _speed(d.throttle_grid, d, p)
        cols.append(np.interp(t_eval, d.grid_t_s, np.power(sp, p.exponent)))  # eq. (11) at exponent 2
        names.append("throttle")
    if p.temperature and d.temperature_degc is not None:
        cols.append(d.temperature_degc - float(np.mean(d.temperature_degc)))
        names.append("temperature")
    if d.extra is not None:
        for j, name in enumerate(d.extra_names):
            cols.append(d.extra[:, j])
            names.append(name)
    return np.column_stack(cols), tuple(names)


def effect_available(name: str, d: DriveInputs) -> str | None:
    """None when the log has what ``name`` needs, else a one-line reason."""
    needs = EFFECTS[name].needs
    if float(np.max(d.throttle_grid, initial=0.0)) < 0.05:
        return "the throttle never rises above 5 %: throttle-driven effects are unobservable"
    if needs == "motors" and (d.motors_grid is None or d.motors_grid.shape[1] < 2):
        return "the log has no individual motor outputs"
    if needs == "voltage" and (d.voltage_grid is None or float(np.ptp(d.voltage_grid)) < 0.05):
        return "the log has no battery voltage that varies"
    if needs == "temperature" and (d.temperature_degc is None or float(np.ptp(d.temperature_degc)) < 0.5):
        return "the log has no temperature that varies by 0.5 degC or more"
    return None


def _delay_ms(value: float, d: DriveInputs) -> str:
    ms = d.throttle_dt_s * 1e3
    return f"{abs(value) * 1e3:.0f} ms is below the throttle's sampling interval ({ms:.0f} ms)"


def delay_unresolved(
    name: str, value: float, ci: tuple[float, float] | None, d: DriveInputs, max_age_s: float
) -> str | None:
    """Why a fitted delay (current_lag, time_skew) is not told from the timing of the logged samples, or None.

    Two timings blur a delay shorter than the throttle's sampling interval. Whether the ESC held each logged
    value until the next or ramped (what the forward model's interpolation assumes) moves it by up to half
    that interval, a systematic error the likelihood cannot see; :func:`~.intervals.profile_interval` widens
    a delay's 95 % interval by it (and by half the compass's own timing range). And a compass sample may be
    older than its message, by up to ``max_age_s``
    (autopilots read their compasses at 10 Hz or faster: :data:`~.latency.MAX_HOLD_S`). So a delay shorter
    than the sampling interval is refused when it is also shorter than that age (:func:`negligible`, before
    any held-out test), and otherwise when its widened interval reaches zero. Below a 0.1 s interval (10 Hz
    and faster) this is the former rule, every delay shorter than the interval refused. On telemetry logs
    (throttle at 4 Hz, every 0.26 s) that rule refused a 0.3 s current_lag fitted at 0.18-0.25 s with raw
    delta BIC -66 to -150 (docs/diagnosis.md, 2026-11-28 "telemetry rates")."""
    if name not in ("time_skew", "current_lag") or abs(value) >= d.throttle_dt_s:
        return None
    if abs(value) < max_age_s:
        return _delay_ms(value, d)
    if ci is not None and (ci[0] > 0.0 or ci[1] < 0.0):
        return None
    why = _delay_ms(value, d)
    return why if ci is None else f"{why} and its 95 % interval [{ci[0]:.3g}, {ci[1]:.3g}] s reaches 0"


def negligible(name: str, value: float, d: DriveInputs, max_age_s: float = 0.0) -> str | None:
    """None when a fitted extension value is physically meaningful, else why it is not. A delay shorter than
    both the throttle's sampling interval and ``max_age_s``, the oldest a compass sample can be, is not told
    from the timing of the samples (:func:`delay_unresolved` judges one between the two by its interval)."""
    if name in ("time_skew", "current_lag") and abs(value) < min(d.throttle_dt_s, max_age_s):
        return _delay_ms(value, d)
    if name == "throttle_offset" and value < 0.01:
        return "offset below 1 % of full throttle"
    if name == "throttle_exponent" and abs(value - 2.0) < 0.05:
        return "exponent within 0.05 of eq. (11)'s 2"
    if name == "voltage_sag" and value < 0.05:
        return "sag strength below 0.05"
    return None
