"""Validity gate per compass: is the fitted forward model physical, and is theta observable in this log?

A fit is only a result when the model it assumes can be checked against physics. The forward model
(:mod:`magcomp.diagnosis.model`) sees the Earth field through ``A = K |u|`` (eq. (1)) along a direction
(inclination, declination) in NED. Each check below compares what the fit found with what the Earth and the
sensor can physically produce; a compass that fails any of them gets no theta, no findings and no autopilot
parameters, only the reason (``unobservable_why``).

Thresholds and where they come from:

``max_scale_error`` = 0.35
    A = K |u|; for a magnetometer whose gain and soft-iron errors are within +-s of unity, |A|'s singular
    values lie in [(1 - s), (1 + s)] |u|. s = 0.35 is the tolerance ArduPilot's own arming check allows
    (COMPASS field 185-875 mgauss around an expected 530, i.e. about +-35 % of a typical field) and covers the
    +-15 % gain tolerance of common MEMS magnetometers plus vehicle soft iron. So: fitted field strength
    within [1 - s, 1 + s] of the WMM's, and cond(A) <= (1 + s)/(1 - s).
``max_inclination_error_deg`` (derived, about 20.5 deg)
    The largest angle by which a positive-definite distortion with condition number r = (1 + s)/(1 - s) can
    turn a vector is atan((r - 1) / (2 sqrt(r))). A fitted inclination further from the WMM's than that
    cannot be explained by a calibration within tolerance: the fit is using A's freedom to absorb
    something else (a rotation it cannot see, a bias).
Earth's surface field range 220-670 mgauss
    WMM: the total intensity at the surface spans about 22,000 nT (South Atlantic anomaly) to 67,000 nT
    (near the magnetic poles). Without a position the strength must lie in that range widened by
    ``max_scale_error``.
``max_residual_fraction`` = 0.05
    A field residual of a fraction e of the Earth field can turn the heading by up to e rad; 0.05 rad is
    2.9 deg, the size of the paper's corrected heading errors (Table III: 1.3-3.7 deg). A model that leaves
    more than that cannot resolve a bias at the level the paper's correction works at.
``min_yaw_span_deg`` = 90, ``min_tilt_span_deg`` = 10 (down direction's spread: twice its 95th-percentile
angle from the mean)
    A and the hard iron c are separable only when the field sweeps an arc in body axes: the centre of a
    circle fitted to an arc of width w has an error of about noise / (1 - cos(w / 2)); at w = 90 deg that is
    3.4x the noise, at 30 deg already 30x. The inclination (the vertical part of the field against c's third
    component) needs the down vector to move; with roll and pitch spanning less than 10 deg a 1 deg attitude
    error already moves the fitted inclination by several degrees.
``min_throttle_span`` = 0.1
    theta multiplies throttle^2 (eq. (11)); it is only separable from the hard iron c when throttle^2 varies.
    A span of 0.1 in throttle at hover (0.5) changes throttle^2 by 0.1, i.e. a 10 % sweep of the full-throttle
    bias.

A stationary log (no rotation, :mod:`magcomp.diagnosis.attitude`) is the paper's offline bench fit (eqs.
(14a), (15)): the calibration is neither needed nor checked there, only the throttle span and the residual.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import euler_from_dcms
from magcomp.core.types import EARTH_MAX_MGAUSS, EARTH_MIN_MGAUSS

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GateParams:
    """Thresholds of :func:`check`; the module docstring says where each one comes from. ``max_condition``
    and ``max_inclination_error_deg`` are not set: they follow from ``max_scale_error``."""

    max_scale_error: float = 0.35
    max_residual_fraction: float = 0.05
    min_yaw_span_deg: float = 90.0
    min_tilt_span_deg: float = 10.0
    min_throttle_span: float = 0.1

    @property
    def max_condition(self) -> float:
        return (1.0 + self.max_scale_error) / (1.0 - self.max_scale_error)

    @property
    def max_inclination_error_deg(self) -> float:
        r = self.max_condition
        return math.degrees(math.atan((r - 1.0) / (2.0 * math.sqrt(r))))


@dataclass(frozen=True)
class EarthReference:
    """The Earth field the fit is checked against: WMM (N, E, D) mgauss at the log's position and date, or
    None when the position is unknown (then only Earth's surface range is checked). ``source`` says which."""

    field_ned_mgauss: F64 | None
    source: str

    @property
    def strength_mgauss(self) -> float | None:
        return None if self.field_ned_mgauss is None else float(np.linalg.norm(self.field_ned_mgauss))

    @property
    def inclination_deg(self) -> float | None:
        if self.field_ned_mgauss is None:
            return None
        n, e, d = (float(x) for x in self.field_ned_mgauss)
        return math.degrees(math.atan2(d, math.hypot(n, e)))


NO_POSITION = EarthReference(None, "no GPS position in the log: checked against Earth's surface range only")


@dataclass(frozen=True)
class GateResult:
    """observable: every check passed; why: the failed checks; theta_why: the failed checks that concern theta
    itself (a throttle that does not vary; on a stationary bench log also a model that leaves too much),
    empty when the rest is refused: then theta is still estimated with the autopilot's calibration as prior
    (:mod:`magcomp.diagnosis.partial`), which tells by itself whether the residual leaves theta determined."""

    observable: bool
    why: str
    checks: dict[str, Any] = field(default_factory=dict)
    theta_why: str = ""
    #: the forward model leaves more than ``max_residual_fraction`` of the field
    residual_refused: bool = False


def yaw_span_deg(r_nb: F64) -> float:
    """Arc of headings covered (deg): 360 minus the largest gap between the sorted headings."""
    yaw = np.sort(np.degrees(euler_from_dcms(r_nb)[:, 2]) % 360.0)
    if yaw.size < 2:
        return 0.0
    gaps = np.diff(np.concatenate([yaw, [yaw[0] + 360.0]]))
    return float(360.0 - np.max(gaps))


def tilt_span_deg(r_nb: F64) -> float:
    """Spread of the down direction in body axes (deg): twice the 95th percentile of its angle from the
    mean down direction (free of the Euler angles' wrap at +-180 deg)."""
    down = r_nb[:, 2, :]
    m = down.mean(axis=0)
    norm = float(np.linalg.norm(m))
    if norm < 1e-9:
        return 180.0
    ang = np.degrees(np.arccos(np.clip(down @ (m / norm), -1.0, 1.0)))
    return float(2.0 * np.percentile(ang, 95.0))


def median_rate_hz(t_s: F64) -> float:
    if t_s.shape[0] < 2:
        return 0.0
    dt = float(np.median(np.diff(t_s)))
    return 1.0 / dt if dt > 0 else 0.0


def noise_floor_mgauss(residual_mgauss: F64) -> float:
    """White-noise level of a residual (rms over axes): robust sd of second differences / sqrt(6)."""
    if residual_mgauss.shape[0] < 5:
        return float("nan")
    d2 = residual_mgauss[2:] - 2.0 * residual_mgauss[1:-1] + residual_mgauss[:-2]
    sd = 1.4826 * np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / math.sqrt(6.0)
    return float(np.sqrt(np.mean(sd**2)))


def _rotation_reasons(
    strength: float, cond: float, inc: float, checks: dict[str, Any], earth: EarthReference, p: GateParams
) -> list[str]:
    """Why a rotating log's fit is not physical (spans, field strength, calibration, inclination)."""
    reasons: list[str] = []
    ref = earth.strength_mgauss
    if checks["yaw_span_deg"] < p.min_yaw_span_deg:
        reasons.append(
            f"the heading covers only {checks['yaw_span_deg']:.0f} deg (< {p.min_yaw_span_deg:.0f}): "
            "calibration and hard iron are not separable"
        )
    if checks["tilt_span_deg"] < p.min_tilt_span_deg:
        reasons.append(
            f"tilt span only {checks['tilt_span_deg']:.0f} deg (< {p.min_tilt_span_deg:.0f}): the "
            "field's vertical part is not separable from the hard iron"
        )
    lo, hi = 1.0 - p.max_scale_error, 1.0 + p.max_scale_error
    if ref is not None:
        if not (lo * ref <= strength <= hi * ref):
            reasons.append(
                f"fitted Earth field {strength:.0f} mgauss vs WMM {ref:.0f} "
                f"(outside x{lo:.2f}-x{hi:.2f}): not physical"
            )
    elif not (lo * EARTH_MIN_MGAUSS <= strength <= hi * EARTH_MAX_MGAUSS):
        reasons.append(
            f"fitted Earth field {strength:.0f} mgauss is outside Earth's {EARTH_MIN_MGAUSS:.0f}-"
            f"{EARTH_MAX_MGAUSS:.0f} mgauss widened by +-{100 * p.max_scale_error:.0f} %: not physical"
        )
    if cond > p.max_condition:
        reasons.append(
            f"fitted calibration has condition number {cond:.1f} (> {p.max_condition:.2f} for scale "
            f"errors within +-{100 * p.max_scale_error:.0f} %): not physical"
        )
    wmm_inc = earth.inclination_deg
    if wmm_inc is not None and abs(inc - wmm_inc) > p.max_inclination_error_deg:
        reasons.append(
            f"fitted inclination {inc:.0f} deg vs WMM {wmm_inc:.0f} (more than "
            f"{p.max_inclination_error_deg:.1f} deg apart): not physical"
        )
    return reasons


def check(
    *,
    stationary: bool,
    r_nb: F64,
    a_mgauss: F64,
    inc_rad: float,
    residual_rms_mgauss: float,
    residual_mgauss: F64,
    throttle_01: F64,
    mag_t_s: F64,
    gyro_rate_hz: float,
    attitude_rate_hz: float,
    earth: EarthReference,
    p: GateParams | None = None,
) -> GateResult:
    """Run every check (see the module docstring); the first failure in this order is the reason given."""
    p = p or GateParams()
    sv = np.linalg.svd(a_mgauss, compute_uv=False)
    strength = float(np.prod(np.abs(sv)) ** (1.0 / 3.0))
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    inc = math.degrees(inc_rad)
    thr_span = float(np.ptp(np.percentile(throttle_01, [2.5, 97.5]))) if throttle_01.size else 0.0
    checks: dict[str, Any] = {
        "earth_reference": earth.source,
        "wmm_strength_mgauss": _r(earth.strength_mgauss),
        "wmm_inclination_deg": _r(earth.inclination_deg),
        "fitted_strength_mgauss": _r(strength),
        "fitted_inclination_deg": _r(inc),
        "calibration_condition": _r(cond),
        "yaw_span_deg": _r(yaw_span_deg(r_nb)),
        "tilt_span_deg": _r(tilt_span_deg(r_nb)),
        "throttle_span": _r(thr_span),
        "residual_rms_mgauss": _r(residual_rms_mgauss),
        "noise_floor_mgauss": _r(noise_floor_mgauss(residual_mgauss)),
        "magnetometer_hz": _r(median_rate_hz(mag_t_s)),
        "gyro_hz": _r(gyro_rate_hz),
        "attitude_hz": _r(attitude_rate_hz),
        "thresholds": {
            "max_scale_error": p.max_scale_error,
            "max_calibration_condition": _r(p.max_condition),
            "max_inclination_error_deg": _r(p.max_inclination_error_deg),
            "max_residual_fraction_of_field": p.max_residual_fraction,
            "min_yaw_span_deg": p.min_yaw_span_deg,
            "min_tilt_span_deg": p.min_tilt_span_deg,
            "min_throttle_span": p.min_throttle_span,
        },
    }
    reasons: list[str] = []
    theta_reasons: list[str] = []
    if thr_span < p.min_throttle_span:
        theta_reasons.append(
            f"the throttle spans only {thr_span:.2f} (< {p.min_throttle_span}): theta * throttle^2 cannot be "
            "told from the hard iron"
        )
    reasons += theta_reasons
    ref = earth.strength_mgauss
    if not stationary:
        reasons += _rotation_reasons(strength, cond, inc, checks, earth, p)
    scale = ref if ref is not None else (strength if not stationary else EARTH_MIN_MGAUSS)
    residual_refused = residual_rms_mgauss > p.max_residual_fraction * scale
    if residual_refused:
        r = (
            f"the forward model leaves {residual_rms_mgauss:.0f} mgauss rms "
            f"(> {100 * p.max_residual_fraction:.0f} % of the {scale:.0f} mgauss field, i.e. > "
            f"{math.degrees(p.max_residual_fraction):.1f} deg of heading): the model does not describe "
            "this compass"
        )
        reasons.append(r)
        if stationary:  # the bench fit has no prior to fall back on: the model is all there is
            theta_reasons.append(r)
    return GateResult(not reasons, "; ".join(reasons), checks, "; ".join(theta_reasons), residual_refused)


def _r(x: float | None) -> float | None:
    if x is None or not math.isfinite(x):
        return None
    return round(float(x), 3)


def structured_shift_bound(residual_mgauss: F64, drive: F64) -> tuple[float, float, float]:
    """(bound on theta's shift, mgauss; the residual's structured part, mgauss; sd of the drive): a least-
    squares coefficient moves by cov(e, d) / var(d) under an unmodelled error e, at most sd(e) / sd(d)
    (Cauchy-Schwarz); sd(e) is the residual's rms above its white floor (second differences)."""
    sd_d = float(np.std(drive))
    rms = float(np.sqrt(np.mean(residual_mgauss**2)))
    floor = noise_floor_mgauss(residual_mgauss)
    floor = floor if np.isfinite(floor) else 0.0
    structured = float(np.sqrt(max(rms**2 - floor**2, 0.0)))
    return (structured / sd_d if sd_d > 0 else math.inf), structured, sd_d
