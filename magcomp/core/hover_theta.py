"""Theta against the autopilot's calibration: eq. (11) where the flight cannot determine a calibration.

A hover (or any flight with little rotation) does not determine a compass calibration: eq. (2)'s hard iron
d and the Earth field look alike unless the vehicle turns through a large angle. But theta is observable: the
throttle varies at near-constant attitude, and eq. (11)'s bias ``theta * throttle^2`` moves the field with it.
So here the calibration is the autopilot's own (L = I, d = 0 on the field as logged, the prior of issue 23
item 3) and theta is fitted alone, by linear least squares, with the Earth field:

    m_b(t) = R_nb(t)^T e_n + theta * throttle(t)^2 + noise          (eq. (11) with eq. (2) the identity)

R_nb from the autopilot's roll, pitch and yaw; e_n (3) and theta (3) are the six unknowns. Departure from
the paper's eqs. (12)-(15): no DPI calibration first, no observer; one batch solve. Where the autopilot's yaw
is fused from this compass it carries part of the bias; the throttle moves faster (seconds) than the
autopilot pulls its yaw to the compass (a minute or more, docs/real-flights.md), so the fit still sees
theta. Whether the result helps is left to the self-check (core/selfcheck.py), never assumed.

Pure numpy; fields in mgauss, angles in rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import dcms_from_quats, quats_from_euler

F64 = NDArray[np.float64]

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


def body_from_nav(roll_rad: F64, pitch_rad: F64, yaw_rad: F64) -> F64:
    """R_nb^T per sample, (n, 3, 3): NED to body FRD (ZYX Euler), from :mod:`magcomp.core.rotations`."""
    return np.asarray(dcms_from_quats(quats_from_euler(roll_rad, pitch_rad, yaw_rad)).transpose(0, 2, 1))


def fit_hover_theta(
    field_b_mgauss: F64, roll_rad: F64, pitch_rad: F64, yaw_rad: F64, throttle_01: F64
) -> HoverTheta | None:
    """The least-squares theta of the module's model; None where throttle^2 hardly varies (see
    MIN_THROTTLE2_STD) or there are fewer samples than twice the unknowns."""
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
    return HoverTheta(x[3:].copy(), np.sqrt(np.maximum(np.diag(cov)[3:], 0.0)), math.sqrt(s2), n)
