"""`diagnose(log) -> Diagnosis`: simulation vs measurement for every compass of a log.

Steps, per compass:
1. Forward model driven by the log's own inputs (:mod:`magcomp.diagnosis.inputs`,
   :mod:`magcomp.diagnosis.model`): rotation from the gyro with compass-free tilt
   (:mod:`magcomp.diagnosis.attitude`), throttle/motors/battery/temperature through the bias model eq. (11)
   and its extensions (:mod:`magcomp.diagnosis.effects`); compare with the measured field.
2. The paper's model (baseline) and each extension are fitted; an extension is kept when it wins on held-out
   blocks and on BIC (:mod:`magcomp.diagnosis.search`, :mod:`magcomp.diagnosis.selection`); winners are
   combined and refitted.
3. The remaining residual is related to every signal, lagged (:mod:`magcomp.diagnosis.suspects`).
4. The gain: residual RMS of the paper's model vs the extended one, and the heading error of each against a
   reference heading when there is one (simulated truth, or a compass far from the wires;
   :mod:`magcomp.diagnosis.heading`).

This module runs the whole log: each compass, the physical gate, the choice of yaw source, the heading
reference. Everything is pure (no I/O) and the results are frozen (:mod:`magcomp.diagnosis.results`);
:func:`Diagnosis.to_json` (:mod:`magcomp.diagnosis.export`) gives the JSON document; the report writer and
the CLI live in :mod:`magcomp.diagnosis.report` and :mod:`magcomp.commands.diagnose`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cache, partial

import numpy as np
from numpy.typing import NDArray

from magcomp.core.types import LogData
from magcomp.core.yaw_follow import FOLLOW_Z, YawFollow
from magcomp.diagnosis import gate as gate_mod
from magcomp.diagnosis.attitude import AttitudeSource, with_yaw_reference
from magcomp.diagnosis.consistency import consistency_checks
from magcomp.diagnosis.export import MAX_CONDITION_INDEX
from magcomp.diagnosis.gyro_heading import with_gyro_bias_heading
from magcomp.diagnosis.heading import compass_yaw_rad, heading_errors
from magcomp.diagnosis.identity import sensor_identity
from magcomp.diagnosis.inputs import (
    GRID_DT_S,
    IMPACT_M_S2,
    MAX_SAMPLES,
    compass_data,
    crash_mask,
    decimation_step,
    drive_inputs,
    finite_series,
    impact_left_out,
    inlier_mask,
    log_attitude,
    signals_at,
    spans,
    subset,
)
from magcomp.diagnosis.latency import MIN_HELD_FRACTION, compass_latency_s, held_fraction, unheld_age_bounds_s
from magcomp.diagnosis.model import CompassData
from magcomp.diagnosis.partial import theta_with_prior
from magcomp.diagnosis.results import CompassDiagnosis, Diagnosis, Finding, HeadingErrors
from magcomp.diagnosis.search import diagnose_compass, motors_off_step, step_candidate
from magcomp.diagnosis.selection import SelectionParams
from magcomp.diagnosis.siblings import clock_conflicts
from magcomp.diagnosis.slow_gyro import paper_rms_mgauss, prefer_slow_gyro
from magcomp.diagnosis.yaw_follow import yaw_follow_gain
from magcomp.errors import InputError

__all__ = [
    "GRID_DT_S",
    "IMPACT_M_S2",
    "MAX_CONDITION_INDEX",
    "MAX_SAMPLES",
    "YAW_REFERENCE_MAX_REL",
    "CompassDiagnosis",
    "Diagnosis",
    "Finding",
    "HeadingErrors",
    "compass_data",
    "compass_yaw_rad",
    "crash_mask",
    "diagnose",
    "diagnose_compass",
    "drive_inputs",
    "heading_errors",
    "inlier_mask",
    "motors_off_step",
    "signals_at",
    "step_candidate",
    "subset",
    "with_gate",
]

F64 = NDArray[np.float64]
Events = list[tuple[float, str]]

#: A compass can serve as the yaw reference of the others when its own full-throttle bias turns its heading
#: by less than this (rad, |theta| / |field|): 0.05 rad = 2.9 deg, the paper's corrected heading error level.
YAW_REFERENCE_MAX_REL = 0.05


def _rel_theta(c: CompassDiagnosis) -> float:
    return float(np.linalg.norm(c.extended.theta_mgauss)) / max(c.extended.field_strength_mgauss, 1e-9)


def _rate_hz(t_s: F64) -> float:
    return gate_mod.median_rate_hz(t_s)


def with_gate(
    c: CompassDiagnosis,
    log: LogData,
    earth: gate_mod.EarthReference,
    gp: gate_mod.GateParams | None = None,
) -> CompassDiagnosis:
    """``c`` with its gate result from the fit and the log (see :mod:`magcomp.diagnosis.gate`)."""
    fit = c.extended
    result = gate_mod.check(
        stationary=c.data.attitude_source == "stationary",
        r_nb=c.data.r_nb,
        a_mgauss=fit.a_mgauss,
        inc_rad=fit.inc_rad,
        residual_rms_mgauss=fit.rms_mgauss,
        residual_mgauss=fit.residual_mgauss,
        throttle_01=c.data.throttle_01,
        mag_t_s=c.data.t_s,
        gyro_rate_hz=_rate_hz(log.imu_t_s),
        attitude_rate_hz=_rate_hz(log.attitude_rad.t_s),
        earth=earth,
        p=gp,
    )
    if not result.observable and not result.theta_why and c.data.attitude_source != "stationary":
        # theta is not refused with the rest: against the autopilot's calibration as prior (partial.py); where
        # the model leaves more than the gate allows, its model-error bound decides too
        gp = gp or gate_mod.GateParams()
        pt = theta_with_prior(
            c.data,
            c.baseline.drift_rad_s,
            c.baseline.dec_rad,
            earth.strength_mgauss,
            None if earth.inclination_deg is None else math.radians(earth.inclination_deg),
            gp.max_scale_error,
            model_error_decides=result.residual_refused,
        )
        return replace(c, gate=result, prior_theta=pt)
    if result.observable:  # non-blocking: when theta's interval is a lower bound (consistency module)
        result = replace(result, checks={**result.checks, **consistency_checks(c.data, c.extended)})
        if result.checks.get("theta_identifiable") is False and c.autopilot:
            # no compensation parameters for a theta the log cannot pin down (COMPASS_MOT*, CAL_MAGn_*COMP)
            why = str(result.checks.get("theta_consistency_why", "theta is not identifiable in this log"))
            note = (
                "No autopilot compensation parameters: " + why + ". Writing them would set the autopilot's "
                "compensation from a theta the log does not determine."
            )
            return replace(c, gate=result, autopilot={}, linear_note=note)
    return replace(c, gate=result)


def _with_compass_yaw(c: CompassDiagnosis, ref: CompassDiagnosis) -> CompassData:
    """``c``'s data with the autopilot's yaw replaced by the heading of compass ``ref`` (its extended fit)."""
    yaw = np.unwrap(compass_yaw_rad(ref.data, ref.extended))
    yaw_c = np.interp(c.data.t_s, ref.data.t_s, yaw)
    r = with_yaw_reference(c.data.r_nb, yaw_c)
    note = (
        f"roll and pitch from the autopilot, yaw from compass {ref.index} (its full-throttle bias is "
        f"{100 * _rel_theta(ref):.1f} % of the field, < {100 * YAW_REFERENCE_MAX_REL:.0f} %), because "
        + c.data.attitude_note
    )
    return CompassData(
        c.data.mag_index,
        c.data.t_s,
        c.data.field_mgauss,
        r,
        c.data.drive,
        f"autopilot+compass{ref.index}",
        note,
    )


@dataclass(frozen=True)
class _Run:
    """The arguments every compass of one log is diagnosed with."""

    log: LogData
    events: Events | None
    p: SelectionParams | None
    earth: gate_mod.EarthReference
    gate_params: gate_mod.GateParams | None
    #: the data each kept diagnosis was searched with, for a second search (:func:`_shared_clock`)
    given: dict[int, CompassData] = field(default_factory=dict)

    def compass(self, data: CompassData, exclude: dict[str, str] | None = None) -> CompassDiagnosis:
        """One compass searched and gated (``exclude``: causes ruled out before the search, name -> why)."""
        data = with_gyro_bias_heading(data)  # the heading's wander through tilt, removed first
        cd = diagnose_compass(data, self.log.source, self.p, self.log, self.events, exclude=exclude)
        return with_gate(cd, self.log, self.earth, self.gate_params)


def _shared_clock(run: _Run, comps: list[CompassDiagnosis], notes: list[str]) -> list[CompassDiagnosis]:
    """A time_skew that a sibling compass of the log contradicts with stronger evidence is refused and the
    compass searched again without it (:mod:`magcomp.diagnosis.siblings`)."""
    conflicts = clock_conflicts(comps)
    out = list(comps)
    for i, c in enumerate(comps):
        if c.index in conflicts:
            notes.append(f"compass {c.index}: time_skew refused: {conflicts[c.index]}")
            out[i] = run.compass(run.given[c.index], exclude={"time_skew": conflicts[c.index]})
    return out


def _each_compass(run: _Run, notes: list[str]) -> list[CompassDiagnosis]:
    """Every compass with enough samples, its impacts left out (noted)."""
    log = run.log
    comps: list[CompassDiagnosis] = []
    left_out: dict[str, list[int]] = {}  # the stretches left out (as printed) -> the compasses
    first = len(notes)
    attitude = cache(partial(log_attitude, log))  # one rotation for every compass (and latency) of the log
    if len(log.gps_velocity_ned_m_s) and attitude().gnss_note:
        notes.append(attitude().gnss_note)  # the GNSS tilt reference used, or why not
    for idx in sorted(log.mag):
        if idx in log.mag and len(log.mag[idx]) > 0:
            mag = finite_series(log.mag[idx])  # what compass_data decides on, at its decimation
            crash = impact_left_out(log, mag.t_s, decimation_step(len(mag)))
            stretches = [f"{a:.1f}-{b:.1f}" for a, b in spans(mag.t_s, crash)]
            if stretches:
                left_out.setdefault(", ".join(stretches), []).append(idx)
            if not crash.any():
                for a, b in spans(mag.t_s, crash_mask(log, mag.t_s)):
                    notes.append(
                        f"compass {idx}: impact above 2.5 g around t = {a:.1f}-{b:.1f} s kept (too few "
                        "samples without it)"
                    )
        try:
            data = compass_data(log, idx, attitude=attitude)
        except InputError as exc:
            notes.append(f"compass {idx} skipped: {exc}")
            continue
        data = _timed(log, idx, data, attitude, notes)
        comps.append(run.compass(data))
        run.given[idx] = data
    notes[first:first] = [_left_out_note(ts, idxs) for ts, idxs in left_out.items()]
    if not comps:
        raise InputError("no compass has enough samples to diagnose")
    return comps


def _unheld_age(
    log: LogData,
    idx: int,
    data: CompassData,
    logged_t_s: F64,
    attitude: Callable[[], AttitudeSource],
    notes: list[str],
) -> CompassData:
    """An unheld compass's samples re-timed by their fitted age (:func:`latency.unheld_age_bounds_s`): the
    rotation and the drive taken that much before each logged time, when the rotation is the gyro's
    integral (the gyro travels in the compass's own message, so the latency against it is the compass's
    age; the autopilot's attitude would add its filter's delay, which the powertrain does not have); else
    ``data`` as it is."""
    if not data.attitude_source.startswith("gyro"):
        return data
    bounds = unheld_age_bounds_s(logged_t_s)
    age, aged = compass_latency_s(data, partial(_aged_data, log, idx, attitude), bounds)
    # the age is a least-squares nuisance of the paper's model: kept only where that model's residual falls,
    # as the search will see it (after the gyro-bias heading, _Run.compass). The heading's own nonlinear fit
    # may land elsewhere from the re-timed data: on a real log the model hardly describes (peterbarker 1,
    # compass 0) the residual went from 31 to 88 mgauss rms at a fitted 68 ms
    if age <= 0.0:
        return data
    if _paper_rms(aged) >= _paper_rms(data):
        return data
    notes.append(
        f"compass {idx}: its samples do not repeat (no hold to read their age from): the rotation and the "
        f"drive taken {1000 * age:.1f} ms before each logged time, the compass's fitted age (0-"
        f"{1000 * bounds[1]:.0f} ms: one compass period at most, as a compass repeating under "
        f"{MIN_HELD_FRACTION:.0%} of its samples updates at least every 1.25 messages)"
    )
    return aged


def _timed(log: LogData, idx: int, data: CompassData, attitude: Callable[[], AttitudeSource],
           notes: list[str]) -> CompassData:  # fmt: skip
    """Compass ``idx``'s ``data`` re-timed to its samples' measurement times: a compass held in a faster
    message by its hold and its fitted latency (:func:`latency.compass_latency_s`), an unheld one by its age
    fitted against the rotation (:func:`_unheld_age`); the change noted. The engine's first pass and the
    slow gyro's second (slow_gyro.py ``prefer_slow_gyro``) both take it."""
    held = held_fraction(finite_series(log.mag[idx]).values)
    if held < MIN_HELD_FRACTION:
        return _unheld_age(log, idx, data, finite_series(log.mag[idx]).t_s, attitude, notes)
    latency, data = compass_latency_s(data, partial(compass_data, log, idx, attitude=attitude))
    age_ms = 1000.0 * float(np.mean(data.t_s - data.drive.t_s))
    notes.append(
        f"compass {idx}: held in a faster message ({100 * held:.0f} % of its samples repeat the one "
        f"before): attitude re-timed to each sample's measurement time ({age_ms:.1f} ms before its "
        f"logged time on average), then by {-1000 * latency:+.1f} ms, the compass's fitted latency"
    )
    return data


def _slow_gyro_timed(log: LogData) -> Callable[[int, CompassData, AttitudeSource, list[str]], CompassData]:
    """:func:`_timed` for a compass searched again with the slow gyro's integral (slow_gyro.py)."""

    def timed(idx: int, data: CompassData, source: AttitudeSource, notes: list[str]) -> CompassData:
        return _timed(log, idx, data, lambda: source, notes)

    return timed


def _paper_rms(data: CompassData) -> float:
    """The paper model's residual rms (mgauss) on ``data`` with the gyro-bias heading, as searched."""
    return paper_rms_mgauss(with_gyro_bias_heading(data))


def _aged_data(log: LogData, idx: int, attitude: Callable[[], AttitudeSource], age_s: float) -> CompassData:
    """Compass ``idx`` of ``log`` measured ``age_s`` before its logged times (rotation and drive)."""
    return compass_data(log, idx, attitude=attitude, age_s=age_s)


def _left_out_note(stretches: str, compasses: list[int]) -> str:
    """One note for the impacts left out of the compasses that share them (one line per log, not one per
    compass and stretch)."""
    n = stretches.count(",") + 1
    who = f"compass {compasses[0]}" if len(compasses) == 1 else "compasses " + ", ".join(map(str, compasses))
    what = "a stretch" if n == 1 else f"{n} stretches"
    why = "with an impact above 2.5 g (a crash, a drop or a hard landing)"
    return f"{who}: left out {what} {why}: t = {stretches} s"


def _prefer_compass_yaw(run: _Run, comps: list[CompassDiagnosis], notes: list[str]) -> list[CompassDiagnosis]:
    """Attitude from the autopilot (slow or no gyro): a compass far from the wires is the better yaw source
    when it lowers the paper model's residual."""
    refs = [c for c in comps if c.observable and _rel_theta(c) < YAW_REFERENCE_MAX_REL]
    out = list(comps)
    for i, c in enumerate(comps):
        if c.data.attitude_source != "autopilot":
            continue
        others = [o for o in refs if o.index != c.index]
        if not others:
            continue
        ref = min(others, key=_rel_theta)
        alt_data = _with_compass_yaw(c, ref)
        alt = run.compass(alt_data)
        if alt.baseline.rms_mgauss < c.baseline.rms_mgauss:
            run.given[c.index] = alt_data
            notes.append(
                f"compass {c.index}: yaw from compass {ref.index} instead of the autopilot's "
                f"(paper-model residual {c.baseline.rms_mgauss:.1f} -> {alt.baseline.rms_mgauss:.1f} mgauss)"
            )
            out[i] = alt
    return out


def _heading(
    c: CompassDiagnosis, comps: list[CompassDiagnosis], heading_reference: tuple[F64, F64] | None
) -> HeadingErrors | None:
    """Heading errors of ``c`` against the truth, or against the compass with the smallest relative theta
    when that is less than half of ``c``'s; None without a reference."""
    fits = {"uncompensated": c.baseline, "paper": c.baseline, "extended": c.extended}
    if heading_reference is not None:
        return heading_errors(c.data, fits, heading_reference[0], heading_reference[1], "truth")
    others = [o for o in comps if o.index != c.index and o.observable]
    if not others:
        return None
    ref = min(others, key=_rel_theta)
    rel_ref, rel_c = _rel_theta(ref), _rel_theta(c)
    if rel_ref >= 0.5 * rel_c:
        return None
    ref_yaw = compass_yaw_rad(ref.data, ref.extended)
    return heading_errors(
        c.data,
        fits,
        ref.data.t_s,
        ref_yaw,
        f"compass {ref.index} (extended model; |theta|/|field| {rel_ref:.3f} vs {rel_c:.3f})",
    )


def diagnose(
    log: LogData,
    primary: int | None = None,
    heading_reference: tuple[F64, F64] | None = None,
    events: Events | None = None,
    p: SelectionParams | None = None,
    earth: gate_mod.EarthReference | None = None,
    gate_params: gate_mod.GateParams | None = None,
) -> Diagnosis:
    """Diagnose every compass of ``log``.

    heading_reference: (t_s, yaw_rad) of a trusted heading (e.g. simulated truth); without it the compass
    with the smallest fitted |theta| relative to the field serves as the reference for the others.
    events: (t_s, text) logged events, for the residual step report.
    earth: the WMM field at the log's position and date (default: none known, Earth's surface range).
    """
    if not log.mag:
        raise InputError("the log has no magnetometer samples")
    earth = earth or gate_mod.NO_POSITION
    notes: list[str] = [f"Earth field reference: {earth.source}"]
    run = _Run(log, events, p, earth, gate_params)
    comps = prefer_slow_gyro(log, _each_compass(run, notes), run.compass, run.given, notes,
                             _slow_gyro_timed(log))  # fmt: skip
    comps = _shared_clock(run, _prefer_compass_yaw(run, comps, notes), notes)
    prim = primary if primary is not None else comps[0].index
    if prim not in [c.index for c in comps]:
        raise InputError(f"compass {prim} is not in the log or has too few samples")
    comps = [replace(c, heading=_heading(c, comps, heading_reference)) if c.observable else c for c in comps]
    comps = [replace(c, sensor=sensor_identity(log.params, c.index)) for c in comps]
    if heading_reference is None and all(c.heading is None for c in comps):
        notes.append("no heading reference (no truth, no compass far from the wires): heading errors omitted")
    note, fit = _yaw_follow(log, prim)
    if note:
        notes.append(note)
    return Diagnosis(log.source, prim, comps, notes, autopilot=int(log.autopilot), yaw_follow=fit)


def _yaw_follow(log: LogData, compass: int) -> tuple[str | None, YawFollow | None]:
    """How fast the autopilot's yaw follows compass ``compass`` with the motors running (yaw_follow.py), as
    a note and as the fit (None where it cannot be measured): a real EKF's pull is slow (log171:
    0.02 /s), a complementary filter's ~0.5 /s; how long the autopilot keeps a compass error in its yaw, and
    so in its GPS-aided tilt. The check against the gyro (gyro_check.py) decides on the fit, by the
    product's rule (core/selfcheck.py :func:`~magcomp.core.selfcheck.att_is_circular`), whether that yaw is
    a second reference."""
    mag, att, thr = log.mag.get(compass), log.attitude_rad, log.throttle_01
    if mag is None or len(att) < 2 or log.imu_t_s.size < 2 or len(thr) < 2:
        return None, None
    on = thr.t_s[thr.values > 0.1]
    if on.size < 2:
        return None, None
    try:
        fit = yaw_follow_gain(
            att.t_s, att.values, log.imu_t_s, log.gyro_rad_s, mag.t_s, mag.values,
            t_start_s=float(on[0]) + 5.0, t_end_s=float(on[-1]),
        )  # fmt: skip
    except (np.linalg.LinAlgError, ValueError):  # a note, never a reason for diagnose to fail
        return None, None
    if fit is None or not math.isfinite(fit.gain_per_s) or not math.isfinite(fit.gain_sigma_per_s):
        return None, None
    note = (
        f"the autopilot's yaw follows compass {compass}'s heading at {fit.gain_per_s:.3f} +- "
        f"{fit.gain_sigma_per_s:.3f} /s with the motors running ({fit.n_windows} windows of 2 s; the yaw "
        f"minus the gyro's integral against the compass's heading)"
        + yaw_follow_comment(fit.gain_per_s, fit.gain_sigma_per_s)
    )
    return note, fit


def yaw_follow_comment(gain: float, sigma: float) -> str:
    """What a measured follow rate means when it is not a plain pull toward the compass (FOLLOW_Z sigma,
    ~95 %)."""
    if gain < -FOLLOW_Z * sigma:
        return (
            ": negative, so the yaw moves *away* from this compass's heading: the autopilot does not "
            "fuse this compass (it uses another compass, GPS yaw or none), or its yaw error is driven by "
            "something the compass does not see; not a filter gain"
        )
    if abs(gain) <= FOLLOW_Z * sigma:
        return ": not distinguishable from zero, the autopilot's yaw does not measurably follow this compass"
    return ""
