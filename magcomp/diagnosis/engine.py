"""`diagnose(log) -> Diagnosis`: simulation vs measurement for every compass of a log.

Steps, per compass:
1. Forward model driven by the log's own inputs (:mod:`magcomp.diagnosis.model`): rotation from the gyro with
   compass-free tilt (:mod:`magcomp.diagnosis.attitude`), throttle/motors/battery/temperature through the
   bias model eq. (11) and its extensions (:mod:`magcomp.diagnosis.effects`); compare with the measured field.
2. The paper's model (baseline) and each extension are fitted; an extension is kept when it wins on held-out
   blocks and on BIC (:mod:`magcomp.diagnosis.selection`); winners are combined and refitted.
3. The remaining residual is related to every signal, lagged (:mod:`magcomp.diagnosis.suspects`).
4. The gain: residual RMS of the paper's model vs the extended one, and the heading error of each against a
   reference heading when there is one (simulated truth, or a compass far from the wires).

Everything here is pure (no I/O): :func:`Diagnosis.to_json` gives the JSON document; the report writer and
the CLI live in :mod:`magcomp.diagnosis.report` and :mod:`magcomp.commands.diagnose`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import euler_from_dcms
from magcomp.core.types import STANDARD_GRAVITY_M_S2, LogData, Series
from magcomp.diagnosis import gate as gate_mod
from magcomp.diagnosis.attitude import attitude_track, with_yaw_reference
from magcomp.diagnosis.compensation import ardupilot_params, linearise, px4_params
from magcomp.diagnosis.effects import EFFECTS, DriveInputs, drive_columns, effect_available, negligible
from magcomp.diagnosis.intervals import column_halfwidth, profile_interval, theta_halfwidth
from magcomp.diagnosis.model import CompassData, ModelFit, fit_model, initial_fit
from magcomp.diagnosis.rivals import (
    GROUPS,
    RIVAL_DELTA_BIC,
    group_of,
    motors_identified,
    rival_set,
    temperature_beats_time,
    time_shapes,
)
from magcomp.diagnosis.selection import Comparison, SelectionParams, compare, cv_rms, effective_delta_bic
from magcomp.diagnosis.structure import search as structure_search
from magcomp.diagnosis.suspects import SignalRelation, StepEvent, find_step, relate, step_at
from magcomp.errors import InputError

F64 = NDArray[np.float64]

GRID_DT_S = 0.01
#: Belsley's condition index above which regressors are strongly collinear (Belsley, Kuh & Welsch 1980):
#: per-motor vectors are then not reported one by one.
MAX_CONDITION_INDEX = 30.0
MAX_SAMPLES = 5000


@dataclass(frozen=True)
class Finding:
    effect: str
    cause: str
    params: dict[str, Any]
    evidence: dict[str, Any]
    residual_rms_after: float
    candidates: list[str] = field(default_factory=list)
    candidate_params: dict[str, Any] = field(default_factory=dict)

    @property
    def label(self) -> str:
        """The effect's name, or "a or b" when the data cannot tell the candidates apart."""
        return " or ".join(self.candidates) if len(self.candidates) > 1 else self.effect


@dataclass(frozen=True)
class HeadingErrors:
    """Heading error (deg) against a reference, constant offset removed: rms and max |.|."""

    reference: str
    rms_deg: dict[str, float]
    max_deg: dict[str, float]


@dataclass
class CompassDiagnosis:
    index: int
    source: str
    data: CompassData
    baseline: ModelFit
    extended: ModelFit
    findings: list[Finding]
    rejected: dict[str, dict[str, Any]]
    unavailable: dict[str, str]
    suspects: list[SignalRelation]
    step: StepEvent | None
    heading: HeadingErrors | None = None
    autopilot: dict[str, dict[str, float]] = field(default_factory=dict)
    linear_note: str = ""
    excluded: list[tuple[float, float]] = field(default_factory=list)
    field_step: dict[str, Any] | None = None
    gate: gate_mod.GateResult | None = None
    structure: list[dict[str, Any]] = field(default_factory=list)

    @property
    def observable(self) -> bool:
        return self.gate is None or self.gate.observable

    def bias_mgauss(self, fit: ModelFit) -> F64:
        cols, _ = drive_columns(self.data.drive, fit.ext)
        rows = [i for i, c in enumerate(fit.columns) if c != "temperature" and not c.startswith("step")]
        return cols[:, rows] @ fit.coefs[rows]

    def to_json(self) -> dict[str, Any]:
        out = self._result_json()
        out["observable"] = self.observable
        out["unobservable_why"] = "" if self.gate is None else self.gate.why
        out["gate"] = {} if self.gate is None else self.gate.checks
        if not self.observable:
            # no theta, no findings, no autopilot parameters: a non-physical fit is not a result
            for k in (
                "theta",
                "theta_baseline",
                "theta_ci95_halfwidth",
                "theta_baseline_ci95_halfwidth",
                "heading_error",
                "residual_step",
                "field_step_motors_off",
            ):
                out[k] = None
            for k in ("findings", "suspects", "unexplained_structure"):
                out[k] = []
            for k in ("rejected", "autopilot"):
                out[k] = {}
            out["linearisation"] = ""
            out["heading_drift_deg_per_min"] = None
        return out

    def _result_json(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "source": self.source,
            "n_samples": self.data.n,
            "excluded_spans_s": [[_r(a), _r(b)] for a, b in self.excluded],
            "theta": _r(self.extended.theta_mgauss),
            "theta_ci95_halfwidth": _r(theta_halfwidth(self.data, self.extended)),
            "theta_baseline": _r(self.baseline.theta_mgauss),
            "theta_baseline_ci95_halfwidth": _r(theta_halfwidth(self.data, self.baseline)),
            "residual_rms_baseline": _r(self.baseline.rms_mgauss),
            "residual_rms_extended": _r(self.extended.rms_mgauss),
            "findings": [_finding_json(f) for f in self.findings],
            "rejected": self.rejected,
            "unavailable": self.unavailable,
            "attitude": {"source": self.data.attitude_source, "why": self.data.attitude_note},
            "field_strength_mgauss": _r(self.extended.field_strength_mgauss),
            "inclination_deg": _r(math.degrees(self.extended.inc_rad)),
            "heading_drift_deg_per_min": _r(math.degrees(self.extended.drift_rad_s) * 60.0),
            "suspects": [
                {
                    "signal": s.signal,
                    "lag_s": s.lag_s,
                    "r2": _r(s.r2),
                    "slope_mgauss_per_unit": _r(np.array(s.slope_mgauss_per_unit)),
                }
                for s in self.suspects[:8]
            ],
            "residual_step": None
            if self.step is None
            else {
                "t_s": _r(self.step.t_s),
                "size_mgauss": _r(np.array(self.step.size_mgauss)),
                "size_sigma": _r(self.step.size_sigma),
                "co_stepping_signals": dict(list(self.step.co_stepping.items())[:8]),
                "events": [{"t_s": _r(t), "event": e} for t, e in self.step.events],
            },
            "field_step_motors_off": self.field_step,
            "unexplained_structure": self.structure,
            "heading_error": None
            if self.heading is None
            else {
                "reference": self.heading.reference,
                "rms_deg": self.heading.rms_deg,
                "max_deg": self.heading.max_deg,
            },
            "autopilot": self.autopilot,
            "linearisation": self.linear_note,
        }


@dataclass
class Diagnosis:
    log_source: str
    primary: int
    compasses: list[CompassDiagnosis]
    notes: list[str]

    def compass(self, index: int) -> CompassDiagnosis:
        for c in self.compasses:
            if c.index == index:
                return c
        raise KeyError(index)

    def to_json(self) -> dict[str, Any]:
        p = self.compass(self.primary)
        base, ext = p.baseline.rms_mgauss, p.extended.rms_mgauss
        if not p.observable:
            return {
                "log": self.log_source,
                "primary_compass": self.primary,
                "observable": False,
                "unobservable_why": p.gate.why if p.gate is not None else "",
                "findings": [],
                "residual_rms_baseline": _r(base),
                "residual_rms_extended": _r(ext),
                "gain": {},
                "compasses": [c.to_json() for c in self.compasses],
                "notes": self.notes,
            }
        gain: dict[str, Any] = {
            "residual_rms_ratio": _r(base / ext) if ext > 0 else None,
            "residual_rms_reduction_pct": _r(100.0 * (1.0 - ext / base)) if base > 0 else None,
        }
        if p.heading is not None:
            gain["heading_reference"] = p.heading.reference
            gain["heading_error_rms_deg"] = p.heading.rms_deg
            gain["heading_error_max_deg"] = p.heading.max_deg
        return {
            "log": self.log_source,
            "primary_compass": self.primary,
            "observable": True,
            "unobservable_why": "",
            "findings": [_finding_json(f) for f in p.findings],
            "residual_rms_baseline": _r(base),
            "residual_rms_extended": _r(ext),
            "gain": gain,
            "compasses": [c.to_json() for c in self.compasses],
            "notes": self.notes,
        }


def _r(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return [round(float(v), 4) for v in x.ravel()]
    if isinstance(x, float | np.floating):
        return round(float(x), 4) if math.isfinite(float(x)) else None
    return x


def _finding_json(f: Finding) -> dict[str, Any]:
    out: dict[str, Any] = {
        "effect": f.label,
        "cause": f.cause,
        "params": f.params,
        "evidence": f.evidence,
        "residual_rms_after": _r(f.residual_rms_after),
    }
    if len(f.candidates) > 1:
        out["candidates"] = f.candidates
        out["candidate_params"] = f.candidate_params
        out["cause"] = (
            "The data cannot tell these causes apart (their fits differ by less than the BIC margin): "
            + f.cause
        )
    return out


# ----------------------------------------------------------------------------------------------------------
# inputs


def _finite_series(s: Series) -> Series:
    if len(s) == 0:
        return s
    v = s.values
    ok = np.isfinite(v) if v.ndim == 1 else np.all(np.isfinite(v), axis=1)
    ok &= np.isfinite(s.t_s)
    t, v = s.t_s[ok], v[ok]
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if t.size else np.zeros(0, dtype=bool)
    return Series(t[keep], v[keep])


def drive_inputs(log: LogData, t_s: F64) -> DriveInputs:
    """The powertrain signals of ``log`` on a uniform grid around the compass times ``t_s``."""
    t0, t1 = float(t_s[0]) - 2.0, float(t_s[-1]) + 2.0
    grid = np.arange(t0, t1 + GRID_DT_S, GRID_DT_S)
    thr = _finite_series(log.throttle_01)
    thr_g = np.interp(grid, thr.t_s, np.clip(thr.values, 0.0, 1.0)) if len(thr) else np.zeros_like(grid)
    mot = _finite_series(log.motors_01)
    mot_g = None
    if len(mot) >= 2 and mot.values.ndim == 2 and mot.values.shape[1] >= 2:
        mv = np.clip(mot.values, 0.0, 1.0)
        active = [j for j in range(mv.shape[1]) if float(np.ptp(mv[:, j])) > 0.0]
        if len(active) >= 2:
            mot_g = np.column_stack([np.interp(grid, mot.t_s, mv[:, j]) for j in active])
    volt = _finite_series(log.voltage_v)
    volt = Series(volt.t_s[volt.values > 0.5], volt.values[volt.values > 0.5]) if len(volt) else volt
    v_g = np.interp(grid, volt.t_s, volt.values) if len(volt) >= 2 else None
    # reference of the sag model: a full LiPo pack, 4.2 V per cell, cells counted from the highest voltage
    v_full = 4.2 * max(1.0, math.ceil(float(np.max(volt.values)) / 4.2 - 0.02)) if len(volt) >= 2 else 1.0
    temp = _finite_series(log.temperature_degc)
    temp_m = np.interp(t_s, temp.t_s, temp.values) if len(temp) >= 2 else None
    thr_dt = float(np.median(np.diff(thr.t_s))) if len(thr) >= 2 else GRID_DT_S
    return DriveInputs(t_s, grid, GRID_DT_S, thr_g, mot_g, v_g, v_full, temp_m, thr_dt)


IMPACT_M_S2 = 2.5 * STANDARD_GRAVITY_M_S2


def crash_mask(log: LogData, t_s: F64, before_s: float = 2.0, after_s: float = 3.0) -> NDArray[np.bool_]:
    """True for samples to leave out because of an impact (|specific force| above 2.5 g).

    The forward model holds for a vehicle handled or flown, not for one tumbling after a crash (the attitude
    estimate and the wiring may both be disturbed). When the vehicle ends the log tilted beyond 60 deg
    after an impact (a crash), everything from ``before_s`` before the first impact on is left out;
    otherwise only ``before_s``/``after_s`` around each impact.
    """
    out = np.zeros(t_s.shape[0], dtype=bool)
    if log.imu_t_s.shape[0] < 10:
        return out
    hits = log.imu_t_s[np.linalg.norm(log.accel_m_s2, axis=1) > IMPACT_M_S2]
    if hits.size == 0:
        return out
    att = _finite_series(log.attitude_rad)
    ends_tilted = False
    if len(att) >= 2:
        tail = att.t_s > hits[0] + after_s
        if np.any(tail):
            cos_tilt = np.cos(att.values[tail, 0]) * np.cos(att.values[tail, 1])
            ends_tilted = bool(np.mean(cos_tilt < 0.5) > 0.5)
    if ends_tilted:
        return np.asarray(t_s >= hits[0] - before_s)
    for h in hits:
        out |= (t_s >= h - before_s) & (t_s <= h + after_s)
    return out


def compass_data(log: LogData, index: int) -> CompassData:
    """Align compass ``index`` of ``log`` with rotation and drive signals (decimated to MAX_SAMPLES)."""
    if index not in log.mag:
        raise InputError(f"the log has no compass {index} (compasses: {sorted(log.mag)})")
    mag = _finite_series(log.mag[index])
    if len(mag) < 50:
        raise InputError(f"compass {index} has only {len(mag)} usable samples (need 50)")
    step = max(1, math.ceil(len(mag) / MAX_SAMPLES))
    t = mag.t_s[::step]
    v = mag.values[::step].astype(float)
    keep = ~crash_mask(log, t)
    if np.count_nonzero(keep) >= 50:
        t, v = t[keep], v[keep]
    att = _finite_series(log.attitude_rad)
    imu_ok = log.imu_t_s.shape[0] >= 10
    track = attitude_track(
        t,
        log.imu_t_s if imu_ok else np.zeros(0),
        log.gyro_rad_s if imu_ok else np.zeros((0, 3)),
        log.accel_m_s2 if imu_ok else np.zeros((0, 3)),
        att.t_s,
        att.values if len(att) else np.zeros((0, 3)),
    )
    return CompassData(index, t, v, track.r_nb, drive_inputs(log, t), track.source, track.note)


# ----------------------------------------------------------------------------------------------------------
# fitting and selection


def inlier_mask(
    t_s: F64, residual_mgauss: F64, k_sigma: float = 10.0, pad_s: float = 0.5, max_fraction: float = 0.05
) -> NDArray[np.bool_] | None:
    """Samples to keep, or None when nothing is an outlier.

    A sample is an outlier when any axis of its residual lies more than ``k_sigma`` robust standard
    deviations (1.4826 MAD) from the median; outliers are padded by ``pad_s`` on both sides, because a crash
    or a sensor glitch corrupts its neighbourhood too. When more than ``max_fraction`` of the log would go,
    the model is wrong rather than the data, and nothing is excluded.
    """
    med = np.median(residual_mgauss, axis=0)
    sig = 1.4826 * np.median(np.abs(residual_mgauss - med), axis=0)
    bad = np.any(np.abs(residual_mgauss - med) > k_sigma * np.maximum(sig, 1e-9), axis=1)
    if not np.any(bad):
        return None
    tb = t_s[bad]
    idx = np.searchsorted(tb, t_s)
    near = np.zeros(t_s.shape[0], dtype=bool)
    for off in (-1, 0):
        j = np.clip(idx + off, 0, tb.size - 1)
        near |= np.abs(t_s - tb[j]) <= pad_s
    if np.mean(near) > max_fraction:
        return None
    return ~near


def _spans(t_s: F64, mask: NDArray[np.bool_]) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    start = None
    for i, m in enumerate(mask):
        if m and start is None:
            start = float(t_s[i])
        if not m and start is not None:
            out.append((start, float(t_s[i - 1])))
            start = None
    if start is not None:
        out.append((start, float(t_s[-1])))
    return out


def subset(data: CompassData, keep: NDArray[np.bool_]) -> CompassData:
    """``data`` restricted to the samples ``keep`` (the drive grid is kept whole: lags need the history)."""
    d = data.drive
    temp = d.temperature_degc[keep] if d.temperature_degc is not None else None
    drive = DriveInputs(
        d.t_s[keep],
        d.grid_t_s,
        d.grid_dt_s,
        d.throttle_grid,
        d.motors_grid,
        d.voltage_grid,
        d.v_full_v,
        temp,
        d.throttle_dt_s,
        d.extra[keep] if d.extra is not None else None,
        d.extra_names,
    )
    return CompassData(
        data.mag_index,
        data.t_s[keep],
        data.field_mgauss[keep],
        data.r_nb[keep],
        drive,
        data.attitude_source,
        data.attitude_note,
    )


def _params_json(fit: ModelFit, effect: str, data: CompassData) -> dict[str, Any]:
    e = EFFECTS[effect]
    if e.param is not None:
        out: dict[str, Any] = {e.param: _r(float(getattr(fit.ext, e.param)))}
        ci = profile_interval(data, fit, effect)
        if ci is not None:
            out[f"{e.param}_ci95"] = [_r(ci[0]), _r(ci[1])]
        if effect == "voltage_sag":
            out["v_full_v"] = _r(data.drive.v_full_v)
        return out
    if effect == "temperature_drift":
        k = fit.coefs[list(fit.columns).index("temperature")]
        mag = float(np.linalg.norm(k))
        hw = column_halfwidth(data, fit, {"temperature": 1.0})
        return {
            "mgauss_per_degc": _r(mag),
            "mgauss_per_degc_ci95_halfwidth_per_axis": _r(hw),
            "direction": _r(k / mag if mag > 0 else k),
        }
    theta = fit.theta_mgauss
    names = [c for c in fit.columns if c.startswith("motor_diff")]
    rows = [list(fit.columns).index(c) for c in names]
    delta = np.vstack([fit.coefs[rows], -np.sum(fit.coefs[rows], axis=0, keepdims=True)])
    theta_i = theta + delta
    hws = [column_halfwidth(data, fit, {"throttle": 1.0, c: 1.0}) for c in names]
    hws.append(column_halfwidth(data, fit, {"throttle": 1.0, **{c: -1.0 for c in names}}))
    hw = np.vstack(hws)
    tn = float(np.linalg.norm(theta))
    spread = float(np.mean(np.linalg.norm(theta_i - theta, axis=1))) / tn if tn > 0 else float("nan")
    cols, _ = drive_columns(data.drive, fit.ext)
    sel = cols[:, [list(fit.columns).index(c) for c in ("throttle", *names)]]
    sel = sel - sel.mean(axis=0)
    sel = sel / np.maximum(np.linalg.norm(sel, axis=0), 1e-12)
    sv = np.linalg.svd(sel, compute_uv=False)
    cond = float(sv[0] / max(sv[-1], 1e-12))
    out = {"spread": _r(spread), "condition_index": _r(cond)}
    # the same vectors from each half of the log must agree within their intervals (a half has twice the
    # variance, a difference of two halves four times: 2 x the whole log's half-width)
    halves = []
    for keep in (data.t_s < np.median(data.t_s), data.t_s >= np.median(data.t_s)):
        fh = fit_model(data, fit.effects, start=fit, train=keep, max_nfev=50)
        dh = np.vstack([fh.coefs[rows], -np.sum(fh.coefs[rows], axis=0, keepdims=True)])
        halves.append(fh.theta_mgauss + dh)
    half_gap = float(np.max(np.abs(halves[0] - halves[1]) / np.maximum(2.0 * hw, 1e-9)))
    out["halves_disagreement"] = _r(half_gap)
    stable = half_gap <= 1.0
    if cond <= MAX_CONDITION_INDEX and stable and motors_identified(theta_i, hw, theta):
        out["theta_per_motor_mgauss"] = [_r(row) for row in theta_i]
        out["theta_per_motor_ci95_halfwidth"] = [_r(row) for row in hw]
    else:
        why = []
        if cond > MAX_CONDITION_INDEX:
            why.append(
                f"condition index {cond:.0f} of the motor columns (collinear above {MAX_CONDITION_INDEX:.0f})"
            )
        if not stable:
            why.append(f"the two halves of the log disagree by {half_gap:.1f}x their interval (must be <= 1)")
        why.append(f"95 % intervals up to {float(np.max(hw)):.0f} mgauss against |theta| {tn:.0f}")
        out["theta_per_motor_mgauss"] = (
            "not identifiable: " + "; ".join(why) + ": only the spread and the mean theta are meaningful"
        )
    return out


def _evidence(c: Comparison, data: CompassData) -> dict[str, Any]:
    return {
        "cv_rms_without": _r(c.cv_rms_reference),
        "cv_rms_with": _r(c.cv_rms_extended),
        "cv_gain_pct": _r(100.0 * c.cv_gain),
        "delta_bic": _r(c.delta_bic),
        "rms_without": _r(c.reference.rms_mgauss),
        "rms_with": _r(c.fit.rms_mgauss),
        "compared_with": list(c.reference.effects) or "paper model eq. (11)",
        "residual": "3-axis field residual (compass frame, mgauss) against a forward model whose rotation is "
        + data.attitude_note,
    }


def diagnose_compass(
    data: CompassData,
    source: str,
    p: SelectionParams | None = None,
    log: LogData | None = None,
    events: list[tuple[float, str]] | None = None,
    open_search: bool = True,
    opened: list[dict[str, Any]] | None = None,
) -> CompassDiagnosis:
    """Baseline, every available extension, greedy combination; suspects on the final residual.

    open_search: after the selection, look for a step of the field in the residual; when one passes, it
    joins the nuisance model and the selection is run again, so a named cause that only soaked up the
    step is dropped (named causes get the first shot, so a fast warm-up is not mistaken for a step).
    """
    p = p or SelectionParams()
    base = fit_model(data, (), start=initial_fit(data), max_nfev=p.max_nfev)
    excluded: list[tuple[float, float]] = []
    for _ in range(2):
        keep = inlier_mask(data.t_s, base.residual_mgauss)
        if keep is None:
            break
        excluded += _spans(data.t_s, ~keep)
        data = subset(data, keep)
        base = fit_model(data, (), start=initial_fit(data), max_nfev=p.max_nfev)
    unavailable: dict[str, str] = {}
    singles: list[Comparison] = []
    rejected: dict[str, dict[str, Any]] = {}
    temp_vs_time: dict[str, dict[str, float]] = {}
    cv_base: float | None = None
    for name in EFFECTS:
        why = effect_available(name, data.drive)
        if why is not None:
            unavailable[name] = why
            continue
        f = fit_model(data, (name,), start=base, max_nfev=p.max_nfev)
        dbic = f.bic - base.bic
        param = EFFECTS[name].param
        small = negligible(name, float(getattr(f.ext, param)), data.drive) if param else None
        if dbic > -p.min_delta_bic:  # cheap test first: CV only for candidates that pass BIC
            rejected[name] = {"delta_bic": _r(dbic), "rms_with": _r(f.rms_mgauss), "why": "BIC"}
            continue
        if small is not None:
            rejected[name] = {"delta_bic": _r(dbic), "rms_with": _r(f.rms_mgauss), "why": small}
            continue
        if param is not None:
            lo_b, hi_b = EFFECTS[name].bounds
            v = float(getattr(f.ext, param))
            # (a lower bound of 0 is the effect switched off, which ``negligible`` judges)
            near_lo = lo_b != 0.0 and v - lo_b < 0.01 * (hi_b - lo_b)
            if near_lo or hi_b - v < 0.01 * (hi_b - lo_b):
                # a parameter pinned at the end of its physical range: the data want something the cause
                # cannot be (e.g. a 5 s "spin-up lag" that is really a slow drift), so it is not the cause
                rejected[name] = {
                    "delta_bic": _r(dbic),
                    "rms_with": _r(f.rms_mgauss),
                    "why": f"{param} = {v:.3g} at the edge of its range [{lo_b}, {hi_b}]",
                }
                continue
        if cv_base is None:
            cv_base = cv_rms(data, base, p)
        c = compare(data, base, f, cv_base, p)
        if c.significant and name == "temperature_drift":
            wins, shape, vs_time = temperature_beats_time(data, base, f, RIVAL_DELTA_BIC, p.max_nfev)
            if not wins:
                rejected[name] = {
                    "delta_bic": _r(dbic),
                    "cv_gain_pct": _r(100 * c.cv_gain),
                    "delta_bic_vs_time_shapes": vs_time,
                    "why": f"no better than a smooth drift {shape} with as many parameters",
                }
                continue
            temp_vs_time[name] = vs_time
        if c.significant:
            singles.append(c)
        else:
            rejected[name] = {
                "delta_bic": _r(dbic),
                "cv_gain_pct": _r(100 * c.cv_gain),
                "why": "held-out" if c.cv_gain < p.min_cv_gain else f"effective BIC {c.delta_bic:.0f}",
            }
    singles.sort(key=lambda c: -c.cv_gain)
    candidates: dict[str, list[str]] = {}
    candidate_params: dict[str, dict[str, Any]] = {}
    for group in GROUPS:
        members = {c.fit.effects[0]: c for c in singles if group_of(c.fit.effects[0]) == group}
        if len(members) < 2:
            continue
        same, gap = rival_set({k: c.fit for k, c in members.items()}, RIVAL_DELTA_BIC)
        if len(same) < 2:
            continue
        best = same[0]
        candidates[best] = same
        candidate_params[best] = {
            k: _params_json(members[k].fit, k, data) | {"delta_bic_vs_best": _r(gap[k])} for k in same
        }
        for k in same[1:]:
            singles.remove(members[k])
            rejected[k] = {
                "delta_bic": _r(members[k].delta_bic),
                "cv_gain_pct": _r(100 * members[k].cv_gain),
                "why": f"cannot be told from {best} (BIC within {RIVAL_DELTA_BIC:.0f}): reported as a set",
            }
    current, cv_current = base, (cv_base if cv_base is not None else 0.0)
    kept: list[tuple[str, Comparison]] = []
    for c in singles:
        name = c.fit.effects[0]
        if not kept:
            current, cv_current = c.fit, c.cv_rms_extended
            kept.append((name, c))
            continue
        param = EFFECTS[name].param
        init = {name: float(getattr(c.fit.ext, param))} if param is not None else None
        trial = fit_model(data, (*current.effects, name), start=current, init=init, max_nfev=p.max_nfev)
        ct = compare(data, current, trial, cv_current, p)
        if ct.significant:
            current, cv_current = trial, ct.cv_rms_extended
            kept.append((name, ct))
        else:
            rejected[name] = {
                "delta_bic": _r(ct.delta_bic),
                "cv_gain_pct": _r(100 * ct.cv_gain),
                "why": f"explained by {', '.join(current.effects)}",
            }
    extended = current
    if open_search:
        sig0 = signals_at(data, log)
        # a step on its own (against the paper's model) that fits better than every named cause on its own:
        # the named ones were soaking it up
        st = step_candidate(data, base, p, cv_base or cv_rms(data, base, p), sig0, events)
        best_named = min((c.fit.bic for c in singles), default=math.inf)
        if st is None or st[1].bic >= best_named:
            # or a step in what the named causes leave
            st = step_candidate(data, extended, p, cv_current or cv_rms(data, extended, p), sig0, events)
        if st is not None:
            return diagnose_compass(st[0], source, p, log, events, open_search=False, opened=[st[2]])
    findings = [
        Finding(
            name,
            EFFECTS[name].cause,
            _params_json(extended, name, data),
            _evidence(c, data)
            | ({"delta_bic_vs_time_shapes": temp_vs_time[name]} if name in temp_vs_time else {}),
            c.fit.rms_mgauss,
            candidates.get(name, []),
            candidate_params.get(name, {}),
        )
        for name, c in kept
    ]
    sig = signals_at(data, log)
    suspects = relate(data.t_s, extended.residual_mgauss, sig)
    step = find_step(data.t_s, extended.residual_mgauss, sig, events)
    cd = CompassDiagnosis(
        data.mag_index,
        source,
        data,
        base,
        extended,
        findings,
        rejected,
        unavailable,
        suspects,
        step,
        excluded=excluded,
    )
    cd.field_step = motors_off_step(data, extended, sig, events)
    cd.structure = list(opened or []) + structure_search(
        data.t_s, extended.residual_mgauss, data.r_nb, sig, suspects, events
    )
    _autopilot_terms(cd, log)
    return cd


def step_candidate(
    data: CompassData,
    base: ModelFit,
    p: SelectionParams,
    cv_base: float,
    sig: dict[str, tuple[F64, F64]],
    events: list[tuple[float, str]] | None,
) -> tuple[CompassData, ModelFit, dict[str, Any]] | None:
    """The best single step of the field (change point of the baseline residual's mean, least squares), as a
    model column; kept when it passes the extensions' own tests (held-out gain, BIC with one more
    ln(3n) for the searched time). Returns the data with the column, the refit and the report entry."""
    r = base.residual_mgauss - base.residual_mgauss.mean(axis=0)
    n = data.n
    if n < 100:
        return None
    c = np.cumsum(r, axis=0)
    k = np.arange(1, n)
    # RSS reduction of a mean shift after sample k (exact for a step on a constant): |S_k|^2 n / (k (n - k))
    gain = np.sum(c[:-1] ** 2, axis=1) * n / (k * (n - k))
    lo, hi = int(0.05 * n), int(0.95 * n)  # a step at the very ends is the calibration's business
    i = lo + int(np.argmax(gain[lo:hi]))
    t_step = float(0.5 * (data.t_s[i] + data.t_s[i + 1]))
    col = (data.t_s >= t_step).astype(float)[:, None]
    d = data.drive
    drive = replace(d, extra=col, extra_names=("step",))
    data_s = replace(data, drive=drive)
    fs = fit_model(data_s, base.effects, start=base, max_nfev=p.max_nfev)
    cmp = compare(data_s, base, fs, cv_base, p)
    extra_penalty = math.log(3 * n)
    in_sample = 1.0 - fs.rms_mgauss / base.rms_mgauss
    if not (
        cmp.cv_gain >= p.min_cv_gain
        and in_sample >= p.min_cv_gain
        and cmp.delta_bic <= -p.min_delta_bic_structure - extra_penalty
    ):
        return None
    # a slow drift (temperature, a settling hard iron) is not a step: the step must beat every smooth time
    # column with as many parameters, by the same margin
    for shape in time_shapes(data.t_s).values():
        smooth = replace(data, drive=replace(d, extra=shape[:, None], extra_names=("step",)))
        fsm = fit_model(smooth, base.effects, start=base, max_nfev=p.max_nfev)
        if effective_delta_bic(fsm, fs) > -RIVAL_DELTA_BIC:
            return None
    size = fs.coefs[list(fs.columns).index("step")]
    co: dict[str, float] = {}
    for name, (ts, vs) in sig.items():
        before = (ts >= t_step - 2.0) & (ts < t_step)
        after = (ts >= t_step) & (ts < t_step + 2.0)
        sd = float(np.std(vs))
        if np.count_nonzero(before) >= 2 and np.count_nonzero(after) >= 2 and sd > 0:
            co[name] = round(float(np.mean(vs[after]) - np.mean(vs[before])) / sd, 3)
    co = dict(sorted(co.items(), key=lambda kv: -abs(kv[1]))[:5])
    info = {
        "kind": "step",
        "t_s": round(t_step, 2),
        "size_mgauss": [round(float(v), 2) for v in size],
        "rms_reduction_pct": round(100.0 * (1.0 - fs.rms_mgauss / base.rms_mgauss), 2),
        "cv_gain_pct": round(100.0 * cmp.cv_gain, 2),
        "delta_bic": round(cmp.delta_bic, 1),
        "co_stepping_signals": co,
        "events": [{"t_s": round(te, 2), "event": e} for te, e in (events or []) if abs(te - t_step) <= 2.0],
        "note": "a step of the field that no named cause explains (a payload, servo or light switched on?); "
        "kept in the model as a nuisance so the named causes are tested on what is left",
    }
    return data_s, fs, info


def motors_off_step(
    data: CompassData, fit: ModelFit, sig: dict[str, tuple[F64, F64]], events: list[tuple[float, str]] | None
) -> dict[str, Any] | None:
    """The largest step of the *measured* field while the motors are off, and what explains it.

    With the throttle at zero eq. (11) predicts no bias change, so a step there is either a rotation
    (which the forward model predicts from the gyro), or something outside the powertrain. Reported: its
    time and size, the step the model predicts and the step left in the residual at that time, the
    signals that step with it and the logged events nearby.
    """
    thr = data.throttle_01
    off = thr < 0.02
    if np.count_nonzero(off) < 40:
        return None
    st = find_step(data.t_s[off], data.field_mgauss[off], sig, events)
    if st is None:
        return None
    predicted = data.field_mgauss - fit.residual_mgauss
    pred = step_at(data.t_s, predicted, st.t_s)
    res = step_at(data.t_s, fit.residual_mgauss, st.t_s)
    explained = None
    if pred is not None and res is not None:
        size = float(np.linalg.norm(st.size_mgauss))
        explained = round(1.0 - float(np.linalg.norm(res)) / size, 3) if size > 0 else None
    return {
        "t_s": _r(st.t_s),
        "size_mgauss": _r(np.array(st.size_mgauss)),
        "size_sigma": _r(st.size_sigma),
        "predicted_step_mgauss": None if pred is None else _r(pred),
        "residual_step_mgauss": None if res is None else _r(res),
        "fraction_explained_by_model": explained,
        "co_stepping_signals": dict(list(st.co_stepping.items())[:8]),
        "events": [{"t_s": _r(t), "event": e} for t, e in st.events],
    }


def signals_at(data: CompassData, log: LogData | None) -> dict[str, tuple[F64, F64]]:
    """Every signal the residual may follow, as (t_s, values)."""
    d = data.drive
    g = d.grid_t_s
    out: dict[str, tuple[F64, F64]] = {
        "throttle": (g, d.throttle_grid),
        "throttle^2": (g, d.throttle_grid**2),
        "throttle_rate": (g, np.gradient(_smooth(d.throttle_grid, 10), d.grid_dt_s)),
        "time": (data.t_s, data.t_s - data.t_s[0]),
    }
    roll, pitch, yaw = euler_from_dcms(data.r_nb).T
    out["roll"] = (data.t_s, roll)
    out["pitch"] = (data.t_s, pitch)
    out["yaw_deg"] = (data.t_s, np.degrees(np.unwrap(yaw)))
    out["cos_yaw"] = (data.t_s, np.cos(yaw))
    out["sin_yaw"] = (data.t_s, np.sin(yaw))
    if d.motors_grid is not None:
        for j in range(d.motors_grid.shape[1]):
            out[f"motor{j + 1}"] = (g, d.motors_grid[:, j])
    if d.voltage_grid is not None:
        out["voltage"] = (g, d.voltage_grid)
    if d.temperature_degc is not None:
        out["temperature"] = (data.t_s, d.temperature_degc)
    if log is not None:
        cur = _finite_series(log.current_a)
        if len(cur) >= 2:
            out["current"] = (cur.t_s, cur.values)
        if log.imu_t_s.shape[0] >= 10:
            out["body_rate"] = (log.imu_t_s, np.linalg.norm(log.gyro_rad_s, axis=1))
        att = _finite_series(log.attitude_rad)
        if len(att) >= 2:
            out["autopilot_yaw_rate"] = (att.t_s, np.gradient(np.unwrap(att.values[:, 2]), att.t_s))
        for k, s in log.mag.items():
            if k != data.mag_index and len(s) >= 2:
                fs = _finite_series(s)
                out[f"compass{k}_norm"] = (fs.t_s, np.linalg.norm(fs.values, axis=1))
    return out


def _smooth(x: F64, w: int) -> F64:
    if w <= 1:
        return x
    k = np.ones(w) / w
    return np.convolve(x, k, mode="same")


def _autopilot_terms(cd: CompassDiagnosis, log: LogData | None) -> None:
    fit = cd.extended
    bias = cd.bias_mgauss(fit)
    thr = cd.data.throttle_01
    cur = None
    if log is not None:
        c = _finite_series(log.current_a)
        if len(c) >= 2 and float(np.ptp(c.values)) > 0.5:
            cur = np.interp(cd.data.t_s, c.t_s, c.values)
    terms = linearise(thr, bias, cur)
    thr_only = linearise(thr, bias, None)
    use_current = (
        terms.per_amp_mgauss is not None and (terms.max_error_amp_mgauss or 0.0) < thr_only.max_error_mgauss
    )
    best = terms if use_current else thr_only
    cd.autopilot = {
        "ardupilot": ardupilot_params(best, fit.a_mgauss, fit.field_strength_mgauss, cd.index),
        "px4": px4_params(best, cd.index),
        "px4_throttle": px4_params(thr_only, cd.index),
    }
    if terms.per_amp_mgauss is not None:
        cd.autopilot["px4_current"] = px4_params(terms, cd.index)
    lo, hi = terms.throttle_range
    note = (
        "Both autopilots compensate linearly (k * throttle or k * current); eq. (11) is quadratic in "
        f"throttle. Over this log's throttle range {lo:.2f}-{hi:.2f} the best slope through the origin is "
        f"{_fmt(terms.per_throttle_mgauss)} mgauss per unit throttle, leaving up to "
        f"{thr_only.max_error_mgauss:.1f} mgauss of error."
    )
    if terms.per_amp_mgauss is not None:
        note += (
            f" Against battery current (COMPASS_MOTCT=2, CAL_MAG_COMP_TYP=2): {_fmt(terms.per_amp_mgauss)} "
            f"mgauss/A, leaving up to {terms.max_error_amp_mgauss:.1f} mgauss. The parameters given use the "
            f"{'current' if use_current else 'throttle'}, the smaller error here (eqs. (5a), (8) make "
            "current ~ throttle^2, but a real current sensor also lags and carries other loads)."
        )
    cd.linear_note = note


def _fmt(v: F64) -> str:
    return "[" + ", ".join(f"{float(x):.1f}" for x in v) + "]"


# ----------------------------------------------------------------------------------------------------------
# heading


def compass_yaw_rad(data: CompassData, fit: ModelFit, remove_bias: bool = True) -> F64:
    """Heading (rad) implied by the field after the fitted calibration (and bias removal), tilt-compensated
    with the forward model's compass-free roll and pitch; magnetic, up to a constant."""
    v = data.field_mgauss - fit.c_mgauss
    cols, _ = drive_columns(data.drive, fit.ext)
    if remove_bias:
        v = v - cols @ fit.coefs
    elif "temperature" in fit.columns:
        i = list(fit.columns).index("temperature")
        v = v - np.outer(cols[:, i], fit.coefs[i])
    if data.attitude_source == "stationary" or np.linalg.cond(fit.a_mgauss) > 20.0:
        # no rotation, no calibration: the raw field (hard iron and all) still shows heading *changes*
        h_b = np.asarray(v + fit.c_mgauss, dtype=float)
    else:
        h_b = np.asarray(np.linalg.solve(fit.a_mgauss, v.T).T, dtype=float)
    r = data.r_nb
    yaw = euler_from_dcms(r)[:, 2]
    cy, sy = np.cos(yaw), np.sin(yaw)
    # level frame: R_tilt = Rz(-yaw) R_nb
    h_n = np.einsum("nij,nj->ni", r, h_b)
    hx = cy * h_n[:, 0] + sy * h_n[:, 1]
    hy = -sy * h_n[:, 0] + cy * h_n[:, 1]
    return np.asarray(-np.arctan2(hy, hx))


def heading_errors(
    data: CompassData, fits: dict[str, ModelFit], ref_t_s: F64, ref_yaw_rad: F64, reference: str
) -> HeadingErrors:
    """rms / max heading error (deg) of each fit against a reference heading, constant offset removed."""
    ref = np.interp(data.t_s, ref_t_s, np.unwrap(ref_yaw_rad))
    r = data.r_nb
    level = r[:, 2, 2] > math.cos(math.radians(45.0))  # heading is defined (tilt below 45 deg)
    if np.count_nonzero(level) < 10:
        level = np.ones(data.n, dtype=bool)
    rms: dict[str, float] = {}
    mx: dict[str, float] = {}
    for name, fit in fits.items():
        yaw = compass_yaw_rad(data, fit, remove_bias=name != "uncompensated")[level]
        e = np.angle(np.exp(1j * (yaw - ref[level])))
        e = np.angle(np.exp(1j * (e - np.angle(np.mean(np.exp(1j * e))))))
        rms[name] = round(math.degrees(float(np.sqrt(np.mean(e**2)))), 3)
        mx[name] = round(math.degrees(float(np.max(np.abs(e)))), 3)
    return HeadingErrors(reference, rms, mx)


# ----------------------------------------------------------------------------------------------------------
# whole log


#: A compass can serve as the yaw reference of the others when its own full-throttle bias turns its heading
#: by less than this (rad, |theta| / |field|): 0.05 rad = 2.9 deg, the paper's corrected heading error level.
YAW_REFERENCE_MAX_REL = 0.05


def _rel_theta(c: CompassDiagnosis) -> float:
    return float(np.linalg.norm(c.extended.theta_mgauss)) / max(c.extended.field_strength_mgauss, 1e-9)


def _rate_hz(t_s: F64) -> float:
    return gate_mod.median_rate_hz(t_s)


def apply_gate(
    c: CompassDiagnosis,
    log: LogData,
    earth: gate_mod.EarthReference,
    gp: gate_mod.GateParams | None = None,
) -> None:
    """Set ``c.gate`` from the fit and the log (see :mod:`magcomp.diagnosis.gate`)."""
    fit = c.extended
    c.gate = gate_mod.check(
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


def diagnose(
    log: LogData,
    primary: int | None = None,
    heading_reference: tuple[F64, F64] | None = None,
    events: list[tuple[float, str]] | None = None,
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
    comps: list[CompassDiagnosis] = []
    for idx in sorted(log.mag):
        if idx in log.mag and len(log.mag[idx]) > 0:
            crash = crash_mask(log, log.mag[idx].t_s)
            for a, b in _spans(log.mag[idx].t_s, crash):
                notes.append(
                    f"compass {idx}: left out t = {a:.1f}-{b:.1f} s (impact above 2.5 g: a crash or a drop)"
                )
        try:
            data = compass_data(log, idx)
        except InputError as exc:
            notes.append(f"compass {idx} skipped: {exc}")
            continue
        cd = diagnose_compass(data, log.source, p, log, events)
        apply_gate(cd, log, earth, gate_params)
        comps.append(cd)
    if not comps:
        raise InputError("no compass has enough samples to diagnose")
    # attitude from the autopilot (slow or no gyro): a compass far from the wires is the better yaw source
    refs = [c for c in comps if c.observable and _rel_theta(c) < YAW_REFERENCE_MAX_REL]
    for i, c in enumerate(comps):
        if c.data.attitude_source != "autopilot":
            continue
        others = [o for o in refs if o.index != c.index]
        if not others:
            continue
        ref = min(others, key=_rel_theta)
        alt = diagnose_compass(_with_compass_yaw(c, ref), log.source, p, log, events)
        apply_gate(alt, log, earth, gate_params)
        if alt.baseline.rms_mgauss < c.baseline.rms_mgauss:
            notes.append(
                f"compass {c.index}: yaw from compass {ref.index} instead of the autopilot's "
                f"(paper-model residual {c.baseline.rms_mgauss:.1f} -> {alt.baseline.rms_mgauss:.1f} mgauss)"
            )
            comps[i] = alt
    prim = primary if primary is not None else comps[0].index
    if prim not in [c.index for c in comps]:
        raise InputError(f"compass {prim} is not in the log or has too few samples")
    for c in comps:
        if not c.observable:
            continue
        fits = {"uncompensated": c.baseline, "paper": c.baseline, "extended": c.extended}
        if heading_reference is not None:
            c.heading = heading_errors(c.data, fits, heading_reference[0], heading_reference[1], "truth")
        else:
            others = [o for o in comps if o.index != c.index and o.observable]
            if not others:
                continue
            ref = min(others, key=_rel_theta)
            rel_ref, rel_c = _rel_theta(ref), _rel_theta(c)
            if rel_ref < 0.5 * rel_c:
                ref_yaw = compass_yaw_rad(ref.data, ref.extended)
                c.heading = heading_errors(
                    c.data,
                    fits,
                    ref.data.t_s,
                    ref_yaw,
                    f"compass {ref.index} (extended model; |theta|/|field| {rel_ref:.3f} vs {rel_c:.3f})",
                )
    if heading_reference is None and all(c.heading is None for c in comps):
        notes.append("no heading reference (no truth, no compass far from the wires): heading errors omitted")
    return Diagnosis(log.source, prim, comps, notes)
