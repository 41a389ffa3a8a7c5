"""Does the log's theta hold together? Two checks of eq. (11)'s theta that its 95 % interval cannot make.

The interval of theta (:mod:`magcomp.diagnosis.intervals`) covers noise, white or coloured, but not a model
error that follows the throttle. Two such errors were measured on log171 (docs/measured-data.md):

``segments``  theta fitted once per segment of the flying time (throttle above :data:`FLYING_THROTTLE`),
    with one calibration, Earth field and heading drift for the whole log: the drive column is split into
    throttle^2 x [t in segment k]. Sharing the calibration is what makes a short segment's theta
    observable at all. A difference theta_k - theta_1 outside its own 95 % interval (from the same fit, so
    the two estimates' correlation is accounted for) means something the model misses moves theta
    between segments: on log171 the gyro-integrated heading wanders +-8 deg around its fitted linear drift,
    and a segment's small throttle swing lets that wander pass for theta.
``motors-off anchor``  eq. (11) says the bias is zero at zero throttle, so the motors-off samples (on the
    ground before take-off, often a third of a log) fix the hard iron, and theta is then mostly the
    contrast between them and the flight. An offset column on the motors-off samples, fitted with
    everything else, measures how far they sit from the in-flight model's zero-throttle prediction; when
    that is outside its 95 % interval, theta leans on a contrast the model does not describe (an idle or
    avionics current that starts at arming, a different field on the ground), and theta with the offset
    free is reported beside it.

``model-error bound``  the least-squares theta moves by cov(e, d) / var(d) under an unmodelled error e(t)
    and the drive d = throttle^2 (eq. (11)); by Cauchy-Schwarz at most sd(e) / sd(d) per axis. sd(e) is
    estimated as the residual's structured part, sqrt(rms^2 - white floor^2) (the floor from second
    differences, :func:`magcomp.diagnosis.gate.noise_floor_mgauss`). When that bound exceeds |theta|,
    theta is not identifiable in this log or segment: an error of the residual's own size that happened
    to follow the throttle could have produced it. This is the condition a short segment of a real flight
    fails (log171's thirds: the drive's sd is 0.016-0.048 in a third against 0.11 over the whole log, so
    12 mgauss of residual allow shifts of 250-750 mgauss).

None of the checks refuses the compass (the gate's physical checks do that); they say when theta's interval is
a lower bound. Departure from the paper: the paper has a bench log with known zero-throttle periods and no
such checks.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from magcomp.diagnosis.effects import drive_columns
from magcomp.diagnosis.gate import structured_shift_bound
from magcomp.diagnosis.intervals import column_halfwidth
from magcomp.diagnosis.model import CompassData, ModelFit, fit_model

F64 = NDArray[np.float64]

#: throttle above which the motors turn (the "flying" samples) and below which they are off; a motor
#: at idle (MOT_SPIN_ARM) is at 5-10 %
FLYING_THROTTLE = 0.05
#: each side of a split needs this many samples (a few seconds at 10 Hz) for its own theta
MIN_SEGMENT_SAMPLES = 30
#: evaluations of the nonlinear refit: an extra linear column barely moves the field direction, heading drift
#: and extension values, and the linear part (theta, the columns) is solved exactly at every evaluation
NFEV = 8
#: the motors-off offset needs this share of the samples on each side (motors off / flying)
MIN_ANCHOR_SHARE = 0.05


@dataclass(frozen=True)
class SegmentTheta:
    """theta of one segment (t_from_s..t_to_s) and its 95 % half-width; ``ratio``: largest |theta_k -
    theta_1| / its own 95 % half-width over the axes (0 for the first segment)."""

    t_from_s: float
    t_to_s: float
    theta_mgauss: F64
    halfwidth_mgauss: F64
    ratio: float


@dataclass(frozen=True)
class AnchorCheck:
    """The motors-off samples' offset from the in-flight model (mgauss, compass frame) with its 95 %
    half-width, and theta with that offset free."""

    offset_mgauss: F64
    offset_halfwidth_mgauss: F64
    ratio: float
    theta_free_mgauss: F64
    theta_free_halfwidth_mgauss: F64


def segment_thetas(data: CompassData, fit: ModelFit, k: int) -> list[SegmentTheta] | None:
    """theta per segment of ``k`` equal durations of the flying time, calibration shared (module
    docstring); None when a segment has fewer than :data:`MIN_SEGMENT_SAMPLES` samples."""
    flying = data.t_s[data.throttle_01 > FLYING_THROTTLE]
    if flying.size < k * MIN_SEGMENT_SAMPLES:
        return None
    edges = np.linspace(float(flying[0]), float(flying[-1]), k + 1)
    seg = np.clip(np.searchsorted(edges, data.t_s, side="right") - 1, 0, k - 1)
    fly = data.throttle_01 > FLYING_THROTTLE
    if min(int(np.sum(fly & (seg == j))) for j in range(k)) < MIN_SEGMENT_SAMPLES:
        return None
    col = drive_columns(data.drive, fit.ext)[0][:, 0]
    extra = np.column_stack([col * (seg == j) for j in range(1, k)])
    names = tuple(f"segment{j + 1}" for j in range(1, k))
    d2 = _with_extra(data, extra, names)
    f = fit_model(d2, fit.effects, start=fit, max_nfev=NFEV)
    th1 = f.theta_mgauss
    out = [SegmentTheta(edges[0], edges[1], th1, column_halfwidth(d2, f, {"throttle": 1.0}), 0.0)]
    for j, name in enumerate(names, start=1):
        diff = f.coefs[list(f.columns).index(name)]
        hw_d = column_halfwidth(d2, f, {name: 1.0})
        hw = column_halfwidth(d2, f, {"throttle": 1.0, name: 1.0})
        ratio = float(np.max(np.abs(diff) / np.maximum(hw_d, 1e-9)))
        out.append(SegmentTheta(edges[j], edges[j + 1], th1 + diff, hw, ratio))
    return out


def motors_off_anchor(data: CompassData, fit: ModelFit) -> AnchorCheck | None:
    """The motors-off offset check (module docstring); None when either side has less than
    :data:`MIN_ANCHOR_SHARE` of the samples."""
    off = (data.throttle_01 <= FLYING_THROTTLE).astype(float)
    share = float(np.mean(off))
    if not (MIN_ANCHOR_SHARE <= share <= 1.0 - MIN_ANCHOR_SHARE):
        return None
    d2 = _with_extra(data, off[:, None], ("motors_off",))
    f = fit_model(d2, fit.effects, start=fit, max_nfev=NFEV)
    offset = f.coefs[list(f.columns).index("motors_off")]
    hw = column_halfwidth(d2, f, {"motors_off": 1.0})
    ratio = float(np.max(np.abs(offset) / np.maximum(hw, 1e-9)))
    return AnchorCheck(offset, hw, ratio, f.theta_mgauss, column_halfwidth(d2, f, {"throttle": 1.0}))


def model_error_bound(data: CompassData, fit: ModelFit) -> tuple[float, float, float]:
    """(bound on theta's shift per axis, mgauss; the residual's structured part, mgauss; sd of the drive):
    see the module docstring."""
    d = drive_columns(data.drive, fit.ext)[0][:, 0]
    return structured_shift_bound(fit.residual_mgauss, d)


def _with_extra(data: CompassData, extra: F64, names: tuple[str, ...]) -> CompassData:
    d = data.drive
    if d.extra is not None:  # nuisance columns of the open search stay in
        extra = np.column_stack([d.extra, extra])
        names = d.extra_names + names
    return replace(data, drive=replace(d, extra=extra, extra_names=names))


def _v(x: F64) -> str:
    return "[" + ", ".join(f"{float(v):.0f}" for v in x) + "]"


def consistency_checks(data: CompassData, fit: ModelFit) -> dict[str, object]:
    """The two checks as JSON-ready gate entries: ``theta_halves_ratio``, ``theta_motors_off_offset_mgauss``
    (+ half-width, ratio, theta with it free), ``theta_consistent`` and ``theta_consistency_why``."""
    out: dict[str, object] = {}
    why: list[str] = []
    halves = segment_thetas(data, fit, 2)
    if halves is not None:
        h2 = halves[1]
        out["theta_halves"] = [
            {
                "t_s": [round(float(h.t_from_s), 1), round(float(h.t_to_s), 1)],
                "theta": _r(h.theta_mgauss),
                "ci95_halfwidth": _r(h.halfwidth_mgauss),
            }
            for h in halves
        ]
        # reported, not a flag: on clean simulations it exceeds 1 in most logs (the intervals are lower
        # bounds there too), see benchmarks/diagnosis_flight_pairs.py
        out["theta_halves_ratio"] = round(h2.ratio, 2)
    anchor = motors_off_anchor(data, fit)
    if anchor is not None:
        out["theta_motors_off_offset_mgauss"] = _r(anchor.offset_mgauss)
        out["theta_motors_off_offset_ci95_halfwidth"] = _r(anchor.offset_halfwidth_mgauss)
        out["theta_motors_off_ratio"] = round(anchor.ratio, 2)
        out["theta_motors_off_free"] = _r(anchor.theta_free_mgauss)
        out["theta_motors_off_free_ci95_halfwidth"] = _r(anchor.theta_free_halfwidth_mgauss)
        if anchor.ratio > 1.0:
            why.append(
                f"the motors-off samples sit {_v(anchor.offset_mgauss)} mgauss off the in-flight model "
                f"({anchor.ratio:.2f}x their 95 % interval) and theta leans on them: with that offset free "
                f"theta is {_v(anchor.theta_free_mgauss)} +- {_v(anchor.theta_free_halfwidth_mgauss)}"
            )
    bound, structured, sd_d = model_error_bound(data, fit)
    tn = float(np.linalg.norm(fit.theta_mgauss))
    out["theta_model_error_bound_mgauss"] = round(bound, 1) if np.isfinite(bound) else None
    out["throttle2_sd"] = round(sd_d, 4)
    out["theta_identifiable"] = bound < tn
    if bound >= tn:
        why.append(
            f"theta is not identifiable here: {structured:.1f} mgauss of structured residual over a drive "
            f"(throttle^2) sd of {sd_d:.3f} could move theta by up to {bound:.0f} mgauss, more than |theta| "
            f"{tn:.0f}"
        )
    out["theta_consistent"] = not why
    out["theta_consistency_why"] = "; ".join(why)
    return out


def _r(x: F64) -> list[float]:
    return [round(float(v), 1) for v in x]
