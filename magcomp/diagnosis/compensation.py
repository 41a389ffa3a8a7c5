"""The fitted bias as autopilot parameters (ArduPilot COMPASS_MOT_*, PX4 CAL_MAGn_*COMP).

Both autopilots compensate *linearly*: ArduPilot adds ``COMPASS_MOT * thr`` (COMPASS_MOTCT=1, thr 0..1, or
``* current_A`` with COMPASS_MOTCT=2) to the field in milligauss, after its offsets and soft-iron matrix, in
the body frame (AP_Compass_Backend::correct_field). PX4 adds ``power * CAL_MAGn_[XYZ]COMP`` to the raw field
in gauss before its offsets, scale and rotation (CAL_MAG_COMP_TYP=1 throttle 0..1 [G], 2 current [G/kA]).
The physics (eq. (11)) is quadratic, ``B = theta delta^2``, so the best linear term depends on the throttle
range flown; we give the least-squares slope through the origin over the log's own samples (both autopilots
have no intercept: an intercept would belong in the offsets, which are calibrated at zero throttle) and the
largest error that linearisation leaves in the log's range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class LinearTerms:
    """Best linear approximation of the fitted bias over the log.

    per_throttle_mgauss: (3,) compass frame, bias per unit throttle; per_amp_mgauss: (3,) or None.
    max_error_mgauss: largest |bias - linear| over the log's samples (throttle version).
    throttle_range: (min, max) throttle in the log.
    """

    per_throttle_mgauss: F64
    per_amp_mgauss: F64 | None
    max_error_mgauss: float
    max_error_amp_mgauss: float | None
    throttle_range: tuple[float, float]


def linearise(throttle_01: F64, bias_mgauss: F64, current_a: F64 | None) -> LinearTerms:
    """Slopes through the origin minimising the squared error of ``k x`` against ``bias`` (n, 3)."""
    x = np.clip(throttle_01, 0.0, 1.0)
    den = float(x @ x)
    k = (x @ bias_mgauss) / den if den > 0 else np.zeros(3)
    err = float(np.max(np.linalg.norm(bias_mgauss - np.outer(x, k), axis=1))) if x.size else 0.0
    ka = None
    erra = None
    if current_a is not None and current_a.size == x.size and float(np.ptp(current_a)) > 0.5:
        den_a = float(current_a @ current_a)
        ka = (current_a @ bias_mgauss) / den_a
        erra = float(np.max(np.linalg.norm(bias_mgauss - np.outer(current_a, ka), axis=1)))
    rng = (float(np.min(x)), float(np.max(x))) if x.size else (0.0, 0.0)
    return LinearTerms(k, ka, err, erra, rng)


def ardupilot_params(
    terms: LinearTerms, a_mgauss: F64, field_strength_mgauss: float, instance: int
) -> dict[str, float]:
    """COMPASS_MOT* for compass ``instance`` (0 -> COMPASS_MOT_, 1 -> COMPASS_MOT2_, ...).

    The bias is mapped from the compass frame through the fitted calibration into the calibrated frame
    ArduPilot applies COMPASS_MOT in (F A^-1, F the field strength), and negated (ArduPilot adds it).
    """
    suffix = "" if instance == 0 else str(instance + 1)
    # without rotation no calibration is observable: then assume ArduPilot's matrix is near identity
    ok = np.linalg.cond(a_mgauss) < 20.0
    m = field_strength_mgauss * np.linalg.inv(a_mgauss) if ok else np.eye(3)
    out: dict[str, float] = {}
    if terms.per_amp_mgauss is not None:
        k = -(m @ terms.per_amp_mgauss)
        out["COMPASS_MOTCT"] = 2.0
    else:
        k = -(m @ terms.per_throttle_mgauss)
        out["COMPASS_MOTCT"] = 1.0
    for axis, value in zip("XYZ", k, strict=True):
        out[f"COMPASS_MOT{suffix}_{axis}"] = round(float(value), 2)
    k_thr = -(m @ terms.per_throttle_mgauss)
    for axis, value in zip("XYZ", k_thr, strict=True):
        out[f"COMPASS_MOT{suffix}_{axis}_if_MOTCT_1"] = round(float(value), 2)
    return out


def px4_params(terms: LinearTerms, instance: int, calibration: F64 | None = None) -> dict[str, float]:
    """CAL_MAGn_[XYZ]COMP in the sensor (compass) frame, negated (PX4 adds it to the raw field).

    ``calibration``: PX4's ``R S`` for this compass (:func:`magcomp.core.px4.px4_calibration_matrix`): the
    fitted bias is in the body frame PX4's calibration puts the field in (vehicle_magnetometer, or sensor_mag
    calibrated as PX4 does), and PX4 adds COMP before ``R S``, so the bias goes back through its inverse
    (None: the identity, a compass PX4 neither rotates nor scales).
    Throttle type (CAL_MAG_COMP_TYP=1): gauss per unit throttle = mgauss / 1000.
    Current type (2): gauss per kA, numerically equal to mgauss per A.
    """
    back = np.eye(3) if calibration is None else np.linalg.inv(calibration)
    out: dict[str, float] = {}
    if terms.per_amp_mgauss is not None:
        out["CAL_MAG_COMP_TYP"] = 2.0
        k = -(back @ terms.per_amp_mgauss)
    else:
        out["CAL_MAG_COMP_TYP"] = 1.0
        k = -(back @ terms.per_throttle_mgauss) / 1000.0
    for axis, value in zip("XYZ", k, strict=True):
        out[f"CAL_MAG{instance}_{axis}COMP"] = round(float(value), 5)
    return out
