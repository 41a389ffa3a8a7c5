"""In-flight calibration jointly with theta: no motors-off hand rotation needed.

The paper calibrates soft and hard iron (eqs. (1)-(3)) with the motors off and only then learns theta
(eqs. (16)-(20)). Real flights have no motors-off rotation, so here the calibration and theta are one
linear least-squares problem on ordinary flight data, in one of two forms chosen per compass by what the
attitude reference can be trusted for:

``absolute`` (the vehicle's yaw comes from something this compass does not disturb: an external primary
compass, GPS yaw, or truth). The measurement model of eqs. (1)-(2) and (11) with the earth-frame field
``h_n`` of eq. (13) from the WMM at the vehicle's position::

    y = A R_nb^T h_n + d + sum_r theta_r x_r                                   (eqs. (1), (11), (13))

``y`` the field as received (mgauss, compass frame), ``A`` = L^-1 of eq. (2) (soft iron, scale,
misalignment; 9 unknowns), ``d`` the hard iron (3), ``x_r`` the current regressors: ``x_0 = delta^2`` is the
paper's eq. (11); with motor outputs known, ``x_j = m_j^2 - delta^2`` add one vector per motor (the per-motor
extension; their prior mean is 0, so with no evidence the model is the paper's). Linear in every unknown.

``relative`` (the vehicle's yaw is fused from this very compass, so an absolute yaw would hide the bias).
Only the body rotation between two samples is used, from the gyro (or the autopilot's attitude when the
gyro is too slow to integrate). With an earth-fixed field, ``u_k = L (y_k - d - theta x_k)`` obeys
``u_{k+1} = Q_k u_k``, ``Q_k = R_{nb,k+1}^T R_{nb,k}``; with ``L = I + E`` (the autopilot's calibration
plus a small symmetric, traceless correction E, linearised)::

    y_{k+1} - Q_k y_k = (I - Q_k) d + sum_r (x_{r,k+1} I - x_{r,k} Q_k) theta_r - (E v_{k+1} - Q_k E v_k)
                                                                                  (eq. (13) differenced)

the exact discrete form of the paper's eq. (16) with the hard iron added. It needs rotation (yaw turns)
*and* throttle changes; it does not need the yaw itself, so a compass cannot fool it through the
autopilot's yaw.

Departures from the paper: the calibration is not a separate motors-off step, theta may be accompanied by
per-motor vectors, and both are recursive least squares in information form with a prior (the autopilot's
own calibration: A = I, d = 0, theta = 0, with the standard deviations of :class:`InflightParams`), so
the estimate is defined from the first sample and its covariance says how far to trust it.

Units: mgauss, throttle 0..1; frames: body FRD, earth NED. No I/O.

The parts: :mod:`.rows` (the measurement rows and nuisance columns), :mod:`.window` (the open nuisance
window and its Schur complement), :mod:`.solve` (normal equations, prior, MAP solution, conditioning),
:mod:`.uncertainty` (variance inflation, split check, heading sigma), :mod:`.gate` (the innovation gate),
:mod:`.accumulate` (where the rows go), :mod:`.estimator` (the recursive solver's facade), :mod:`.batch`
(the batch solver of the same rows), :mod:`.feed` (what a sample becomes: absolute rows, window-field rows,
the tilt model's estimator, relinearisation; the switches), :mod:`.yawframe` (the gyro's yaw frame and
the tilt-from-yaw line fit), :mod:`.matching` (late attitude and throttle matched to a sample's time) and
:mod:`.apply` (the apply decision and the correction value). Which form a compass gets from the
autopilot's parameters: :mod:`magcomp.core.autopilot_params`.
"""

from magcomp.core.inflight.apply import InflightOutput
from magcomp.core.inflight.base import (
    F64,
    GATE_CHI2_3DOF,
    GATE_SIGMA_FLOOR_MGAUSS,
    HEADING_MODEL_SPREAD,
    NUISANCE_PRIOR_RAD_S,
    SPLIT_CHECK,
    THETA_MODEL_SPREAD,
    VIF_BATCH_S,
    VIF_MIN_BATCHES,
    WARM_INFLATE,
    InflightMode,
    InflightParams,
    InflightSolution,
)
from magcomp.core.inflight.estimator import InflightEstimator
from magcomp.core.inflight.rows import (
    N_SOFT,
    N_SYM,
    ROW_ENTRY_MAX,
    WindowFieldRows,
    absolute_rows,
    n_params,
    reference_yaw_error_rows,
    regressor_values,
    regressors,
    relative_rows,
    rotation_error_rows,
    soft_iron_matrix,
    window_field_rows,
    window_nuisance_cols,
)
from magcomp.core.inflight.uncertainty import ResidualBatches
from magcomp.core.inflight.yawframe import GyroYaw

__all__ = [
    "F64",
    "GATE_CHI2_3DOF",
    "GATE_SIGMA_FLOOR_MGAUSS",
    "HEADING_MODEL_SPREAD",
    "NUISANCE_PRIOR_RAD_S",
    "N_SOFT",
    "N_SYM",
    "ROW_ENTRY_MAX",
    "SPLIT_CHECK",
    "THETA_MODEL_SPREAD",
    "VIF_BATCH_S",
    "VIF_MIN_BATCHES",
    "WARM_INFLATE",
    "GyroYaw",
    "InflightEstimator",
    "InflightMode",
    "InflightOutput",
    "InflightParams",
    "InflightSolution",
    "ResidualBatches",
    "WindowFieldRows",
    "absolute_rows",
    "n_params",
    "reference_yaw_error_rows",
    "regressor_values",
    "regressors",
    "relative_rows",
    "rotation_error_rows",
    "soft_iron_matrix",
    "window_field_rows",
    "window_nuisance_cols",
]
