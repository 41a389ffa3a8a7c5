"""Theta against the autopilot's calibration: eq. (11) where the flight cannot determine a calibration.

A hover (or any flight with little rotation) does not determine a compass calibration: eq. (2)'s hard iron
d and the Earth field look alike unless the vehicle turns through a large angle. But theta is observable: the
throttle varies at near-constant attitude, and eq. (11)'s bias ``theta * throttle^2`` moves the field with it.
So here the calibration is the autopilot's own (L = I, d = 0 on the field as logged, the prior of issue 23
item 3) and theta is fitted alone, by linear least squares, with the Earth field:

    m_b(t) = R_nb(t)^T e_n + theta * throttle(t)^2 + noise          (eq. (11) with eq. (2) the identity)

R_nb from the autopilot's roll, pitch and yaw; e_n (3) and theta (3) are the six unknowns. A second form
adds a change d (3) of the autopilot's hard-iron offsets (``m_b - d``, eq. (2) with L = I), under a prior of
OFFSET_PRIOR_SD_MGAUSS: where the autopilot's calibration is off (a battery or payload moved since, a
calibration accepted at its fit limit), theta alone cannot take the heading error that turns with the yaw.
Either form moves the heading's constant part by what the flight cannot tell from the Earth field (a hover
hardly turns): :func:`anchored` gives the heading offset that keeps the mean heading the autopilot's own, as
the live path anchors its constant part (service/heading.py; a rotation of the field about the body z axis
would not do: with the vehicle tilted it mixes the vertical field into the heading). Departure from
the paper's eqs. (12)-(15): no DPI calibration first, no observer; one batch solve. Where the autopilot's yaw
is fused from this compass it carries part of the bias; the throttle moves faster (seconds) than the
autopilot pulls its yaw to the compass (a minute or more, docs/real-flights.md), so the fit still sees
theta. Whether the result helps is left to the self-check (core/selfcheck.py), never assumed.

Pure numpy; fields in mgauss, angles in rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import dcms_from_quats, quats_from_euler

F64 = NDArray[np.float64]

#: prior sd (mgauss, per axis) of a change of the autopilot's hard-iron offsets since its calibration:
#: ArduPilot accepts a calibration whose sphere fit leaves up to COMPASS_CAL_FIT (16 mgauss by default) rms,
#: so its offsets are uncertain by a few times that, and a battery or payload moved since adds tens of mgauss.
#: 60 is 12 % of a 500 mgauss field; the development logs' result is the same for 40 and 100
#: (docs/real-flights.md)
OFFSET_PRIOR_SD_MGAUSS = 60.0
#: below this standard deviation of throttle^2 the bias hardly changes (a 0.05 swing around hover at 0.5 is
#: 0.05 of throttle^2): theta is not separable from the Earth field's constant part
MIN_THROTTLE2_STD = 0.01


@dataclass(frozen=True)
class HoverTheta:
    """theta (mgauss, compass frame), its 1-sigma (mgauss) and the residual rms (mgauss)."""

    theta_mgauss: F64
    theta_sigma_mgauss: F64
    residual_rms_mgauss: float
    n: int
    #: the change of the autopilot's hard-iron offsets (zeros in the theta-only form), mgauss
    offset_mgauss: F64 = field(default_factory=lambda: np.zeros(3))
    #: subtracted from the heading of the corrected field (rad): the mean heading stays the autopilot's own
    #: (:func:`anchored`)
    anchor_rad: float = 0.0

    def corrected_mgauss(self, field_b_mgauss: F64, throttle_01: F64) -> F64:
        """Eq. (11) with this fit: ``m_b - d - theta throttle^2``, (n, 3) mgauss."""
        d2 = np.asarray(throttle_01, dtype=float) ** 2
        u = np.asarray(field_b_mgauss, dtype=float) - self.offset_mgauss - d2[:, None] * self.theta_mgauss
        return np.asarray(u)

    def coeffs(self) -> tuple[tuple[float, ...], tuple[float, float, float]]:
        """(L and d of eq. (2) as 12 floats, theta) that give :meth:`corrected_mgauss` as
        ``L m - d - theta t^2``: L = I, d the offsets' change."""
        th = self.theta_mgauss.tolist()
        identity = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
        return (*identity, *self.offset_mgauss.tolist()), (th[0], th[1], th[2])


def anchored(fit: HoverTheta, baseline_heading_rad: F64, candidate_heading_rad: F64) -> HoverTheta:
    """``fit`` with the anchor that removes the circular mean of ``candidate - baseline`` (the headings of
    the same samples, the candidate without anchor): the flight cannot tell the heading's constant part."""
    d = np.asarray(candidate_heading_rad, dtype=float) - np.asarray(baseline_heading_rad, dtype=float)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return fit
    return replace(fit, anchor_rad=math.atan2(float(np.mean(np.sin(d))), float(np.mean(np.cos(d)))))


def body_from_nav(roll_rad: F64, pitch_rad: F64, yaw_rad: F64) -> F64:
    """R_nb^T per sample, (n, 3, 3): NED to body FRD (ZYX Euler), from :mod:`magcomp.core.rotations`."""
    return np.asarray(dcms_from_quats(quats_from_euler(roll_rad, pitch_rad, yaw_rad)).transpose(0, 2, 1))


def fit_hover_theta(
    field_b_mgauss: F64,
    roll_rad: F64,
    pitch_rad: F64,
    yaw_rad: F64,
    throttle_01: F64,
    offset_sd_mgauss: float | None = None,
) -> HoverTheta | None:
    """The least-squares theta of the module's model; None where throttle^2 hardly varies (see
    MIN_THROTTLE2_STD) or there are fewer samples than twice the unknowns. With ``offset_sd_mgauss`` the
    second form: a change of the hard-iron offsets too, under that prior (three pseudo-rows weighed by the
    residual's scale of the theta-only fit)."""
    m = np.asarray(field_b_mgauss, dtype=float)
    d2 = np.asarray(throttle_01, dtype=float) ** 2
    ok = np.isfinite(m).all(axis=1) & np.isfinite(d2) & np.isfinite(roll_rad) & np.isfinite(pitch_rad)
    ok &= np.isfinite(yaw_rad)
    n = int(ok.sum())
    if n < 12 or float(np.std(d2[ok])) < MIN_THROTTLE2_STD:
        return None
    r = body_from_nav(roll_rad[ok], pitch_rad[ok], yaw_rad[ok])  # (n, 3, 3)
    a = np.zeros((3 * n, 6))
    a[:, :3] = r.reshape(3 * n, 3)  # rows of R^T: body axis k of sample i is row 3 i + k
    eye = np.tile(np.eye(3), (n, 1))
    a[:, 3:] = eye * np.repeat(d2[ok], 3)[:, None]
    y = m[ok].reshape(3 * n)
    x, *_ = np.linalg.lstsq(a, y, rcond=None)
    res = y - a @ x
    dof = max(3 * n - 6, 1)
    s2 = float(res @ res) / dof
    cov = s2 * np.linalg.pinv(a.T @ a)
    if offset_sd_mgauss is None:
        return HoverTheta(x[3:].copy(), np.sqrt(np.maximum(np.diag(cov)[3:], 0.0)), math.sqrt(s2), n)
    w = math.sqrt(s2) / offset_sd_mgauss  # a prior row's weight relative to a data row's
    a9 = np.vstack((np.hstack((a, eye)), np.hstack((np.zeros((3, 6)), w * np.eye(3)))))
    y9 = np.concatenate((y, np.zeros(3)))
    x9, *_ = np.linalg.lstsq(a9, y9, rcond=None)
    res9 = (y9 - a9 @ x9)[: 3 * n]
    s29 = float(res9 @ res9) / max(3 * n - 9, 1)
    cov9 = s29 * np.linalg.pinv(a9.T @ a9)
    sd9 = np.sqrt(np.maximum(np.diag(cov9)[3:6], 0.0))
    return HoverTheta(x9[3:6].copy(), sd9, math.sqrt(s29), n, x9[6:9].copy())
