"""One correction value: what a compass's samples get, written once for a float sample and for arrays.

Reference: M. Silic and K. Mohseni, "Correcting Current-Induced Magnetometer Errors on UAVs: An Online
Model-Based Approach", IEEE Sensors J. 20(2), 2020; equation numbers as in that article.

A :class:`Correction` holds L and d of eq. (2) (the hand rotation's, eqs. (1)-(3), or the in-flight
calibration's), theta of eq. (11), the per-motor terms when the in-flight fit has them, whether theta counts
as converged, and where the correction came from. :meth:`Correction.apply` is eq. (2) then eq. (11)'s bias
removed, ``u = L v - d``, ``m = u - theta delta^2 (- sum_j theta_j (m_j^2 - delta^2))``; the same arithmetic
on Python floats (one sample) and on numpy arrays (a whole log), so both give the same numbers.
:func:`headings_deg` is eq. (24) of the calibrated and of the corrected field
(:func:`magcomp.core.heading.heading_from_trig_deg`, the one place it is written).

Symbols: v -> the raw field (mgauss, compass frame); u -> calibrated field; m -> bias-corrected field;
delta -> throttle_01 (0..1); theta -> theta_mgauss (mgauss per unit throttle squared).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Generic, NamedTuple, TypeVar

import numpy as np
from numpy.typing import NDArray

from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.types import FLAG_CALIBRATED, FLAG_THETA_CONVERGED

F64 = NDArray[np.float64]
Float3 = tuple[float, float, float]

#: eq. (2) as the identity (L = I, d = 0): the field as the autopilot calibrated it
IDENTITY_COEFFS = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)

#: where a correction came from: nothing; a hand rotation's calibration learned in this run (eqs. (1)-(3)),
#: one stored by an earlier run, the identity (configured); the in-flight calibration; theta fitted against
#: the autopilot's own calibration over the motors-on samples (core/hover_theta.py)
SOURCES = ("none", "hand rotation", "stored", "identity", "in flight", "hover")

_T = TypeVar("_T", float, F64)


class Applied(NamedTuple, Generic[_T]):
    """One :meth:`Correction.apply`: the calibrated field (eq. (2)), the bias (eq. (11)) and the field with
    the bias removed, each as three components (floats for one sample, arrays (n,) for many)."""

    field_cal: tuple[_T, _T, _T]
    bias: tuple[_T, _T, _T]
    corrected: tuple[_T, _T, _T]


def converged(heading_sigma_deg: float, limit_deg: float) -> bool:
    """Theta counts as converged (FLAG_THETA_CONVERGED) when the estimate's own heading uncertainty (deg, 1
    sigma) is below ``limit_deg`` (``[inflight] heading_converged_deg``)."""
    return heading_sigma_deg < limit_deg


@dataclass(frozen=True)
class Correction:
    """A compass's correction, held fixed while it is applied.

    ``coeffs``: L (row-major) and d of eq. (2) as 12 floats; None: no calibration (the field as logged).
    ``theta_mgauss``: theta of eq. (11). ``motor_theta_mgauss``: one vector per motor output, the bias's
    part ``theta_j (m_j^2 - delta^2)`` beyond the collective throttle (the in-flight fit's, when it has motor
    outputs; empty otherwise). ``converged``: FLAG_THETA_CONVERGED on its samples. ``source``: one of
    SOURCES. ``needs_throttle``: applied only to samples whose throttle is known (the in-flight calibration
    replaces the autopilot's own, and only where its bias can be removed)."""

    coeffs: tuple[float, ...] | None = None
    theta_mgauss: Float3 = (0.0, 0.0, 0.0)
    motor_theta_mgauss: tuple[Float3, ...] = ()
    converged: bool = False
    source: str = "none"
    needs_throttle: bool = False

    def __post_init__(self) -> None:
        if self.coeffs is not None and len(self.coeffs) != 12:
            raise ValueError(f"eq. (2) takes 12 coefficients (L row-major, d), got {len(self.coeffs)}")
        if self.source not in SOURCES:
            raise ValueError(f"unknown correction source {self.source!r} (one of {', '.join(SOURCES)})")

    @classmethod
    def from_solution(cls, calib_l: F64, calib_d: F64, theta_mgauss: F64, motor_theta_mgauss: F64 | None,
                      heading_sigma_deg: float, converged_deg: float) -> Correction:  # fmt: skip
        """The in-flight calibration's solution (L (3, 3), d (3,), theta (3,), per-motor (m, 3)) as a
        correction applied where the throttle is known."""
        coeffs = (*np.ravel(calib_l).tolist(), *np.ravel(calib_d).tolist())
        th = np.asarray(theta_mgauss, dtype=float).tolist()
        motors: tuple[Float3, ...] = ()
        if motor_theta_mgauss is not None and np.size(motor_theta_mgauss):
            motors = tuple((r[0], r[1], r[2]) for r in np.reshape(motor_theta_mgauss, (-1, 3)).tolist())
        return cls(coeffs, (th[0], th[1], th[2]), motors, converged(heading_sigma_deg, converged_deg),
                   "in flight", needs_throttle=True)  # fmt: skip

    @property
    def calibrated(self) -> bool:
        return self.coeffs is not None

    @property
    def flags(self) -> int:
        """The MAGCOMP_HEADING flags its samples carry: FLAG_CALIBRATED, FLAG_THETA_CONVERGED."""
        if self.coeffs is None:
            return 0
        return FLAG_CALIBRATED | FLAG_THETA_CONVERGED if self.converged else FLAG_CALIBRATED

    def calibrate(self, vx: _T, vy: _T, vz: _T) -> tuple[_T, _T, _T]:
        """Eq. (2), ``u = L v - d``, on one sample's floats or on arrays (n,); uncalibrated: ``v``."""
        k = self.coeffs
        if k is None:
            return vx, vy, vz
        return (
            k[0] * vx + k[1] * vy + k[2] * vz - k[9],
            k[3] * vx + k[4] * vy + k[5] * vz - k[10],
            k[6] * vx + k[7] * vy + k[8] * vz - k[11],
        )

    def bias(self, throttle_01: _T, motors_01: Any = None) -> tuple[_T, _T, _T]:
        """Eq. (11), ``theta delta^2``, plus the per-motor terms ``theta_j (m_j^2 - delta^2)`` where the
        motor outputs are given (a sequence of one value or array per motor, as many as the terms)."""
        d2 = throttle_01 * throttle_01
        t0, t1, t2 = self.theta_mgauss
        b0, b1, b2 = t0 * d2, t1 * d2, t2 * d2
        if self.motor_theta_mgauss and motors_01 is not None:
            if len(motors_01) != len(self.motor_theta_mgauss):
                raise ValueError(f"{len(motors_01)} motor outputs for {len(self.motor_theta_mgauss)} terms")
            for (m0, m1, m2), mj in zip(self.motor_theta_mgauss, motors_01, strict=True):
                x = mj * mj - d2
                b0, b1, b2 = b0 + m0 * x, b1 + m1 * x, b2 + m2 * x
        return b0, b1, b2

    def apply(self, vx: _T, vy: _T, vz: _T, throttle_01: _T, motors_01: Any = None) -> Applied[_T]:
        """Eq. (2) then eq. (11)'s bias removed, on one sample (floats) or many (arrays (n,)). A sample
        whose throttle is unknown takes ``throttle_01`` 0 (no bias)."""
        u = self.calibrate(vx, vy, vz)
        b = self.bias(throttle_01, motors_01)
        return Applied(u, b, (u[0] - b[0], u[1] - b[1], u[2] - b[2]))


def headings_deg(applied: Applied[_T], cos_roll: _T, sin_roll: _T, cos_pitch: _T,
                 sin_pitch: _T) -> tuple[_T, _T]:  # fmt: skip
    """Eq. (24), tilt-compensated, of the corrected and of the calibrated field: (corrected, uncorrected)
    heading, deg in [0, 360)."""
    trig = (cos_roll, sin_roll, cos_pitch, sin_pitch)
    psi = heading_from_trig_deg(*applied.corrected, *trig)
    psi_raw = heading_from_trig_deg(*applied.field_cal, *trig)
    return psi, psi_raw
