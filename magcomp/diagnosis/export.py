"""Export of a diagnosis: JSON (rounded to 4 decimals), the findings' parameters and evidence, and the
compensation parameters for the autopilots (linearised, with the prose on what the linearisation costs).

Pure, no I/O: the CLI writes what these functions return.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcomp.core.px4 import px4_calibration_matrix
from magcomp.core.rotations import euler_from_dcms
from magcomp.core.selfcheck import judged
from magcomp.core.types import LogData
from magcomp.core.yaw_follow import YawFollow
from magcomp.diagnosis import gate as gate_mod
from magcomp.diagnosis.compensation import ardupilot_params, linearise, px4_params
from magcomp.diagnosis.effects import EFFECTS, drive_columns
from magcomp.diagnosis.identity import SensorIdentity
from magcomp.diagnosis.inputs import finite_series
from magcomp.diagnosis.intervals import column_halfwidths, profile_interval
from magcomp.diagnosis.model import CompassData, ModelFit, fit_model
from magcomp.diagnosis.partial import PriorTheta
from magcomp.diagnosis.rivals import motors_identified
from magcomp.diagnosis.selection import Comparison
from magcomp.diagnosis.spread import spread_estimate
from magcomp.diagnosis.suspects import SignalRelation, StepEvent

F64 = NDArray[np.float64]

#: Belsley's condition index above which regressors are strongly collinear (Belsley, Kuh & Welsch 1980):
#: per-motor vectors are then not reported one by one.
MAX_CONDITION_INDEX = 30.0


def r4(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return [round(float(v), 4) for v in x.ravel()]
    if isinstance(x, float | np.floating):
        return round(float(x), 4) if math.isfinite(float(x)) else None
    return x


def finding_json(f: Finding) -> dict[str, Any]:
    out: dict[str, Any] = {
        "effect": f.label,
        "cause": f.cause,
        "params": f.params,
        "evidence": f.evidence,
        "residual_rms_after": r4(f.residual_rms_after),
    }
    if len(f.candidates) > 1:
        out["candidates"] = f.candidates
        out["candidate_params"] = f.candidate_params
        out["cause"] = (
            "The data cannot tell these causes apart (their fits differ by less than the BIC margin): "
            + f.cause
        )
    return out


def compass_json(cd: CompassDiagnosis) -> dict[str, Any]:
    """The JSON entry of one compass (nulls and empties in place of results when it is not observable)."""
    out = _result_json(cd)
    out["observable"] = cd.observable
    out["unobservable_why"] = "" if cd.gate is None else cd.gate.why
    out["gate"] = {} if cd.gate is None else cd.gate.checks
    if not cd.observable:
        # no theta, no findings, no autopilot parameters: a non-physical fit is not a result
        for k in (
            "theta",
            "theta_baseline",
            "theta_ci95_halfwidth",
            "theta_ci95_joint_halfwidth",
            "theta_baseline_ci95_halfwidth",
            "theta_baseline_ci95_joint_halfwidth",
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
    out["theta_given_prior"] = prior_theta_json(cd)
    out["throttle2_flown"] = throttle2_flown(cd.data.throttle_01, cd.data.r_nb)
    out["sensor"] = sensor_json(cd.sensor)
    return out


def throttle2_flown(throttle_01: F64, r_nb: F64) -> float | None:
    """The mean throttle^2 over the samples the self-check would judge (core/selfcheck.py
    :func:`~magcomp.core.selfcheck.judged`: the motors running, roll and pitch within bounds; None: none), as
    replay counts it: theta times it is eq. (11)'s bias at the throttle flown, what the compass saw (the
    console prints it beside theta)."""
    thr = np.asarray(throttle_01, dtype=float)
    roll, pitch = euler_from_dcms(r_nb)[:, :2].T
    run = thr[np.isfinite(thr) & np.asarray(judged(thr, np.cos(roll), np.cos(pitch)), dtype=bool)]
    return r4(float(np.mean(run * run))) if run.size else None


def sensor_json(s: SensorIdentity | None) -> dict[str, Any] | None:
    """The physical sensor of a compass slot (None: not looked up)."""
    if s is None:
        return None
    return {"device_id": s.device_id, "external": s.external, "from": s.source, "text": s.describe()}


def prior_theta_json(cd: CompassDiagnosis) -> dict[str, Any] | None:
    """theta with the autopilot's calibration as prior, when the gate refused the calibration only."""
    pt = cd.prior_theta
    if pt is None:
        return None
    why = "" if cd.gate is None else cd.gate.why
    return {
        "theta": r4(pt.theta_mgauss),
        "theta_ci95_halfwidth": r4(pt.halfwidth_mgauss),
        "theta_ci95_joint_halfwidth": r4(pt.joint_halfwidth_mgauss),
        "identifiable": pt.identifiable,
        "residual_rms_mgauss": r4(pt.residual_rms_mgauss),
        "model_error_bound_mgauss": r4(pt.model_error_bound_mgauss)
        if math.isfinite(pt.model_error_bound_mgauss)
        else None,
        "prior": pt.prior,
        "calibration": f"not observable in this log ({why}); theta does not need it: the throttle varies",
        "note": (
            "theta is determined by the field's change with throttle at a near-constant attitude"
            if pt.identifiable
            else f"the log does not determine theta: {pt.why}"
        ),
    }


#: the model's heading-drift bound (rad/s), :func:`magcomp.diagnosis.model._bounds`
MAX_DRIFT_RAD_S = 0.05


def nuisances_at_bound(cd: CompassDiagnosis) -> list[str]:
    """One sentence per nuisance parameter that ended on its bound (attitude's, then heading drift)."""
    out = list(cd.data.nuisance_flags)
    drift = cd.extended.drift_rad_s
    if cd.data.attitude_source != "stationary" and abs(drift) >= MAX_DRIFT_RAD_S * (1.0 - 1e-3):
        out.append(
            f"the heading drift sits on its +-{1e3 * MAX_DRIFT_RAD_S:.0f} mrad/s bound "
            f"({math.degrees(drift) * 60.0:+.0f} deg/min): the fit wants a faster drift than a gyro bias, so "
            "the heading model is wrong over this log and theta and the findings absorb part of that"
        )
    return out


def vector_halfwidths(
    data: CompassData,
    fit: ModelFit,
    weights: dict[str, float],
    blocks: bool,
    coordinates: int = 3,
    walk: bool = False,
) -> tuple[F64, F64]:
    """(per-axis 95 % half-widths, the joint 95 % box's over ``coordinates``) of a vector parameter: the
    per-axis ones are each 95 %, the box holds the whole vector with 95 % (Bonferroni,
    :mod:`magcomp.diagnosis.intervals`); ``walk``: at least the random-walk model's
    (:func:`magcomp.diagnosis.intervals.walk_variance`)."""
    per_axis, joint = column_halfwidths(data, fit, weights, blocks, (1, coordinates), walk)
    return per_axis, joint


def _result_json(cd: CompassDiagnosis) -> dict[str, Any]:
    hw, hw_joint = vector_halfwidths(cd.data, cd.extended, {"throttle": 1.0}, blocks=True)
    hw0, hw0_joint = vector_halfwidths(cd.data, cd.baseline, {"throttle": 1.0}, blocks=True)
    return {
        "index": cd.index,
        "source": cd.source,
        "n_samples": cd.data.n,
        "excluded_spans_s": [[r4(a), r4(b)] for a, b in cd.excluded],
        "theta": r4(cd.extended.theta_mgauss),
        "theta_ci95_halfwidth": r4(hw),
        "theta_ci95_joint_halfwidth": r4(hw_joint),
        "theta_baseline": r4(cd.baseline.theta_mgauss),
        "theta_baseline_ci95_halfwidth": r4(hw0),
        "theta_baseline_ci95_joint_halfwidth": r4(hw0_joint),
        "residual_rms_baseline": r4(cd.baseline.rms_mgauss),
        "residual_rms_extended": r4(cd.extended.rms_mgauss),
        "findings": [finding_json(f) for f in cd.findings],
        "rejected": cd.rejected,
        "unavailable": cd.unavailable,
        "attitude": {"source": cd.data.attitude_source, "why": cd.data.attitude_note},
        "field_strength_mgauss": r4(cd.extended.field_strength_mgauss),
        "inclination_deg": r4(math.degrees(cd.extended.inc_rad)),
        "heading_drift_deg_per_min": r4(math.degrees(cd.extended.drift_rad_s) * 60.0),
        "nuisances_at_bound": nuisances_at_bound(cd),
        "suspects": [
            {
                "signal": s.signal,
                "lag_s": s.lag_s,
                "r2": r4(s.r2),
                "slope_mgauss_per_unit": r4(np.array(s.slope_mgauss_per_unit)),
            }
            for s in cd.suspects[:8]
        ],
        "residual_step": None
        if cd.step is None
        else {
            "t_s": r4(cd.step.t_s),
            "size_mgauss": r4(np.array(cd.step.size_mgauss)),
            "size_sigma": r4(cd.step.size_sigma),
            "co_stepping_signals": dict(list(cd.step.co_stepping.items())[:8]),
            "events": [{"t_s": r4(t), "event": e} for t, e in cd.step.events],
        },
        "field_step_motors_off": cd.field_step,
        "unexplained_structure": cd.structure,
        "heading_error": None
        if cd.heading is None
        else {
            "reference": cd.heading.reference,
            "rms_deg": cd.heading.rms_deg,
            "max_deg": cd.heading.max_deg,
        },
        "autopilot": cd.autopilot,
        "linearisation": cd.linear_note,
    }


def diagnosis_json(d: Diagnosis) -> dict[str, Any]:
    """The JSON document of a diagnosis: the primary compass's findings and gain, then every compass."""
    p = d.compass(d.primary)
    base, ext = p.baseline.rms_mgauss, p.extended.rms_mgauss
    if not p.observable:
        return {
            "log": d.log_source,
            "primary_compass": d.primary,
            "observable": False,
            "unobservable_why": p.gate.why if p.gate is not None else "",
            "findings": [],
            "residual_rms_baseline": r4(base),
            "residual_rms_extended": r4(ext),
            "gain": {},
            "compasses": [compass_json(c) for c in d.compasses],
            "notes": d.notes,
        }
    gain: dict[str, Any] = {
        "residual_rms_ratio": r4(base / ext) if ext > 0 else None,
        "residual_rms_reduction_pct": r4(100.0 * (1.0 - ext / base)) if base > 0 else None,
    }
    if p.heading is not None:
        gain["heading_reference"] = p.heading.reference
        gain["heading_error_rms_deg"] = p.heading.rms_deg
        gain["heading_error_max_deg"] = p.heading.max_deg
    return {
        "log": d.log_source,
        "primary_compass": d.primary,
        "observable": True,
        "unobservable_why": "",
        "findings": [finding_json(f) for f in p.findings],
        "residual_rms_baseline": r4(base),
        "residual_rms_extended": r4(ext),
        "gain": gain,
        "compasses": [compass_json(c) for c in d.compasses],
        "notes": d.notes,
    }


def params_json(
    fit: ModelFit, effect: str, data: CompassData, ci: tuple[float, float] | None = None
) -> dict[str, Any]:
    """The fitted parameter of ``effect`` with its 95 % interval (per-motor vectors when identifiable);
    ``ci``: that interval when the caller has it already (:func:`profile_interval` of this fit)."""
    e = EFFECTS[effect]
    if e.param is not None:
        out: dict[str, Any] = {e.param: r4(float(getattr(fit.ext, e.param)))}
        ci = ci if ci is not None else profile_interval(data, fit, effect)
        if ci is not None:
            out[f"{e.param}_ci95"] = [r4(ci[0]), r4(ci[1])]
        if effect == "voltage_sag":
            out["v_full_v"] = r4(data.drive.v_full_v)
        return out
    if effect == "temperature_drift":
        return _temperature_json(fit, data)
    return _per_motor_json(fit, data)


def _temperature_json(fit: ModelFit, data: CompassData) -> dict[str, Any]:
    """temperature_drift's coefficient vector with its per-axis and joint 95 % half-widths."""
    k = fit.coefs[list(fit.columns).index("temperature")]
    mag = float(np.linalg.norm(k))
    # at least the block jackknife's, as theta's: a slow column absorbs slow model error the HAC variance
    # cannot see (measured coverage: magcomp.diagnosis.intervals); and at least the variance under a random
    # walk fitted to the residual: the temperature rises through the whole log, so it takes up the wander of
    # the compass and of the gyro-integrated heading beyond the HAC's lags (intervals.walk_variance)
    hw, hw_joint = vector_halfwidths(data, fit, {"temperature": 1.0}, blocks=True, walk=True)
    return {
        "mgauss_per_degc": r4(mag),
        "mgauss_per_degc_ci95_halfwidth_per_axis": r4(hw),
        # the box that holds the whole coefficient vector with 95 %: "every axis inside" is a joint claim
        "mgauss_per_degc_ci95_joint_halfwidth": r4(hw_joint),
        "direction": r4(k / mag if mag > 0 else k),
    }


def _per_motor_json(fit: ModelFit, data: CompassData) -> dict[str, Any]:
    """per_motor: the spread (median-unbiased, 95 % interval), the motor columns' condition index, the two
    halves' agreement, and each motor's theta with its intervals where identifiable."""
    theta = fit.theta_mgauss
    names = [c for c in fit.columns if c.startswith("motor_diff")]
    rows = [list(fit.columns).index(c) for c in names]
    delta = np.vstack([fit.coefs[rows], -np.sum(fit.coefs[rows], axis=0, keepdims=True)])
    theta_i = theta + delta
    # per axis, and the joint box over all m x 3 coordinates of the motors' vectors (intervals module)
    coords = 3 * (len(names) + 1)
    pairs = [vector_halfwidths(data, fit, {"throttle": 1.0, c: 1.0}, False, coords) for c in names]
    pairs.append(vector_halfwidths(data, fit, {"throttle": 1.0, **{c: -1.0 for c in names}}, False, coords))
    hw = np.vstack([p[0] for p in pairs])
    hw_joint = np.vstack([p[1] for p in pairs])
    tn = float(np.linalg.norm(theta))
    # the spread is a mean of norms of noisy vectors: biased up by the noise; median-unbiased, with its 95 %
    # interval (magcomp.diagnosis.spread)
    sp = spread_estimate(data, fit)
    cols, _ = drive_columns(data.drive, fit.ext)
    sel = cols[:, [list(fit.columns).index(c) for c in ("throttle", *names)]]
    sel = sel - sel.mean(axis=0)
    sel = sel / np.maximum(np.linalg.norm(sel, axis=0), 1e-12)
    sv = np.linalg.svd(sel, compute_uv=False)
    cond = float(sv[0] / max(sv[-1], 1e-12))
    out = {
        "spread": r4(sp.spread),
        "spread_ci95": [r4(sp.ci95[0]), r4(sp.ci95[1])],
        "spread_raw": r4(sp.raw),
        "condition_index": r4(cond),
    }
    # the same vectors from each half of the log must agree within their intervals (a half has twice the
    # variance, a difference of two halves four times: 2 x the whole log's half-width)
    halves = []
    for keep in (data.t_s < np.median(data.t_s), data.t_s >= np.median(data.t_s)):
        fh = fit_model(data, fit.effects, start=fit, train=keep, max_nfev=50)
        dh = np.vstack([fh.coefs[rows], -np.sum(fh.coefs[rows], axis=0, keepdims=True)])
        halves.append(fh.theta_mgauss + dh)
    half_gap = float(np.max(np.abs(halves[0] - halves[1]) / np.maximum(2.0 * hw, 1e-9)))
    out["halves_disagreement"] = r4(half_gap)
    stable = half_gap <= 1.0
    if cond <= MAX_CONDITION_INDEX and stable and motors_identified(theta_i, hw, theta):
        out["theta_per_motor_mgauss"] = [r4(row) for row in theta_i]
        out["theta_per_motor_ci95_halfwidth"] = [r4(row) for row in hw]
        out["theta_per_motor_ci95_joint_halfwidth"] = [r4(row) for row in hw_joint]
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


def evidence_json(c: Comparison, data: CompassData) -> dict[str, Any]:
    return {
        "cv_rms_without": r4(c.cv_rms_reference),
        "cv_rms_with": r4(c.cv_rms_extended),
        "cv_gain_pct": r4(100.0 * c.cv_gain),
        "cv_t": r4(c.cv_t) if math.isfinite(c.cv_t) else None,
        "cv_t_critical": r4(c.cv_t_critical) if math.isfinite(c.cv_t_critical) else None,
        "delta_bic": r4(c.delta_bic),
        "rms_without": r4(c.reference.rms_mgauss),
        "rms_with": r4(c.fit.rms_mgauss),
        "compared_with": list(c.reference.effects) or "paper model eq. (11)",
        "residual": "3-axis field residual (compass frame, mgauss) against a forward model whose rotation is "
        + data.attitude_note,
    }


class AutopilotExport(NamedTuple):
    """The compensation parameters for each autopilot and the prose on what linearising eq. (11) costs."""

    params: dict[str, dict[str, float]]
    note: str


def bias_mgauss(data: CompassData, fit: ModelFit) -> F64:
    """The fitted powertrain bias (n, 3) of ``fit`` on ``data``: every column but temperature and steps."""
    cols, _ = drive_columns(data.drive, fit.ext)
    rows = [i for i, c in enumerate(fit.columns) if c != "temperature" and not c.startswith("step")]
    return cols[:, rows] @ fit.coefs[rows]


def autopilot_export(index: int, data: CompassData, fit: ModelFit, log: LogData | None) -> AutopilotExport:
    """Linear (throttle or current) compensation parameters from the bias of ``fit`` for compass ``index``."""
    bias = bias_mgauss(data, fit)
    thr = data.throttle_01
    cur = None
    if log is not None:
        c = finite_series(log.current_a)
        if len(c) >= 2 and float(np.ptp(c.values)) > 0.5:
            cur = np.interp(data.t_s, c.t_s, c.values)
    terms = linearise(thr, bias, cur)
    thr_only = linearise(thr, bias, None)
    use_current = (
        terms.per_amp_mgauss is not None and (terms.max_error_amp_mgauss or 0.0) < thr_only.max_error_mgauss
    )
    best = terms if use_current else thr_only
    cal = _px4_calibration(log.params, index) if log is not None else None
    params = {
        "ardupilot": ardupilot_params(best, fit.a_mgauss, fit.field_strength_mgauss, index),
        "px4": px4_params(best, index, cal),
        "px4_throttle": px4_params(thr_only, index, cal),
    }
    if terms.per_amp_mgauss is not None:
        params["px4_current"] = px4_params(terms, index, cal)
    lo, hi = terms.throttle_range
    ap = log.autopilot if log is not None else -1
    who = {3: "ArduPilot compensates", 12: "PX4 compensates"}.get(ap, "Both autopilots compensate")
    both = "COMPASS_MOTCT=2, CAL_MAG_COMP_TYP=2"
    current_params = {3: "COMPASS_MOTCT=2", 12: "CAL_MAG_COMP_TYP=2"}.get(ap, both)
    note = (
        f"{who} linearly (k * throttle or k * current); eq. (11) is quadratic in "
        f"throttle. Over this log's throttle range {lo:.2f}-{hi:.2f} the best slope through the origin is "
        f"{_fmt(terms.per_throttle_mgauss)} mgauss per unit throttle, leaving up to "
        f"{thr_only.max_error_mgauss:.1f} mgauss of error."
    )
    if terms.per_amp_mgauss is not None:
        note += (
            f" Against battery current ({current_params}): {_fmt(terms.per_amp_mgauss)} "
            f"mgauss/A, leaving up to {terms.max_error_amp_mgauss:.1f} mgauss. The parameters given use the "
            f"{'current' if use_current else 'throttle'}, the smaller error here (eqs. (5a), (8) make "
            "current ~ throttle^2, but a real current sensor also lags and carries other loads)."
        )
    return AutopilotExport(params, note)


def _px4_calibration(params: dict[str, float], index: int) -> F64 | None:
    """PX4's ``R S`` for compass ``index`` when the log's parameters describe it (its CAL_MAGn_ID is set: the
    sources give a PX4 compass the index n of its CAL_MAGn_ID), else None."""
    if not params.get(f"CAL_MAG{index}_ID"):
        return None
    m = px4_calibration_matrix(params, index)
    return m if np.linalg.cond(m) < 1e6 else None


def _fmt(v: F64) -> str:
    return "[" + ", ".join(f"{float(x):.1f}" for x in v) + "]"


# the results, frozen and built complete by diagnosis.search and diagnosis.engine (re-exported by
# diagnosis.results); their JSON and bias are the functions above


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
    #: the reference heading at the compass's sample times (rad; the report's heading plot), if kept
    reference_yaw_rad: Any = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
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
    #: theta with the autopilot's calibration as prior, when the gate refuses the calibration only
    prior_theta: PriorTheta | None = None
    #: which physical sensor this compass slot is, from the log's parameters (identity.py)
    sensor: SensorIdentity | None = None

    @property
    def observable(self) -> bool:
        return self.gate is None or self.gate.observable

    def bias_mgauss(self, fit: ModelFit) -> F64:
        return bias_mgauss(self.data, fit)

    def to_json(self) -> dict[str, Any]:
        return compass_json(self)


@dataclass(frozen=True)
class Diagnosis:
    log_source: str
    primary: int
    compasses: list[CompassDiagnosis]
    notes: list[str]
    #: MAV_AUTOPILOT of the log (3 ArduPilot, 12 PX4, -1 unknown): whose parameters the report prints
    autopilot: int = -1
    #: how fast the autopilot's yaw follows the primary compass with the motors running (core/yaw_follow.py;
    #: None: not measured), as the yaw-follow note says
    yaw_follow: YawFollow | None = None

    @property
    def yaw_follow_per_s(self) -> float:
        """The follow gain (1/s; NaN: not measured)."""
        return math.nan if self.yaw_follow is None else self.yaw_follow.gain_per_s

    def compass(self, index: int) -> CompassDiagnosis:
        for c in self.compasses:
            if c.index == index:
                return c
        raise KeyError(index)

    def to_json(self) -> dict[str, Any]:
        return diagnosis_json(self)


def finding_text(f: dict[str, Any]) -> str:
    """``effect name=value [lo, hi]`` (95 %), or the set the data cannot tell apart, each with its own."""
    cands = f.get("candidates") or [f.get("effect")]
    if len(cands) > 1:
        per = f.get("candidate_params") or {}
        inner = ", ".join(_one(str(e), per.get(e) or {}) for e in cands)
        return f"one of {{{inner}}}"
    return _one(str(f.get("effect")), f.get("params") or {})


def _one(effect: str, params: dict[str, Any]) -> str:
    parts = []
    for k, v in params.items():
        if k.endswith("_ci95") or not isinstance(v, int | float) or isinstance(v, bool):
            continue
        ci = params.get(f"{k}_ci95")
        txt = f"{k}={v:.3g}"
        if isinstance(ci, list | tuple) and len(ci) == 2 and all(isinstance(x, int | float) for x in ci):
            txt += f" [{ci[0]:.3g}, {ci[1]:.3g}]"
        parts.append(txt)
    return effect + (" " + " ".join(parts) if parts else "")
