"""What every part of the in-flight estimator shares: the forms, the settings of the model, the prior's
standard deviations, the published solution and the lazily imported LAPACK (no I/O)."""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Literal

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

InflightMode = Literal["absolute", "relative"]

#: chi-square quantile, 3 degrees of freedom, p = 1e-6: the innovation gate (a false rejection once per
#: million clean samples)
GATE_CHI2_3DOF = 30.66
#: the smallest residual scale the gate assumes (mgauss): unmodelled effects of 10-20 mgauss are common on
#: real vehicles (docs/measured-data.md), and a glitch worth rejecting is larger than that
GATE_SIGMA_FLOOR_MGAUSS = 20.0
#: prior standard deviation of the relative form's rotation-rate nuisance (rad/s): the gyro-bias clamp of an
#: attitude filter (MahonyParams.max_bias_rad_s); only keeps a window without rotation solvable
NUISANCE_PRIOR_RAD_S = 0.2
#: a stored estimate's standard deviation is widened by this factor when a new run starts from it
WARM_INFLATE = 2.0
#: residual batches for the variance inflation (see InflightEstimator.variance_inflation): a batch lasts
#: about this long (s; longer than the slow errors the rows carry: the autopilot's yaw loop, 2-5 s, and a
#: manoeuvre's tilt error, 5-30 s), and at least this many batches come in before it is used
VIF_BATCH_S = 30.0
VIF_MIN_BATCHES = 4
#: a solution conditioned on another estimator's theta (``InflightEstimator``'s ``theta_from``) counts
#: the two thetas' difference as a model uncertainty of the one it takes (its covariance plus the
#: difference's outer product)
THETA_MODEL_SPREAD = True
#: ... and the heading the two models' whole calibrations (L, d, theta) give apart, rms over the heading grid
#: of ``uncertainty.heading_sd_deg``, as a model uncertainty of the published heading sigma (in quadrature;
#: it is always reported as ``InflightSolution.heading_model_deg``)
HEADING_MODEL_SPREAD = True
#: the published heading sigma also counts the spread of the estimate over time (``uncertainty.SplitHalves``):
#: the closed nuisance windows are dealt alternately, VIF_BATCH_S at a time, to two halves, each solved on
#: its own, and the heading their calibrations give apart (rms over the heading grid, halved: the sd of the
#: whole-data estimate when the halves are independent) is added in quadrature. It sees what biases the
#: parameters without leaving a residual (the autopilot's tilt error that the hard iron absorbs in turns,
#: docs/inflight.md "Short flights"), which the variance inflation cannot. Both forms report it; only the
#: relative form's apply decision uses it (``apply.apply_decision``: on log171's absolute-form compasses it
#: delayed the causal correction by 30 s)
SPLIT_CHECK = True


_LAPACK: ModuleType | None = None


def lapack() -> ModuleType:
    """scipy's LAPACK wrappers (Cholesky solves: ``dposv``, ``dpotrs``), imported at the first solve: a run
    whose compasses never learn in flight need not pay for them (the live daemon imports them before its
    sample loop: cli.py). The wrappers are scipy's compiled ``scipy.linalg._flapack`` module, the very
    functions ``scipy.linalg.lapack`` re-exports; loaded on its own, without the ``scipy.linalg`` package
    around it, it costs ~15 ms of CPU where importing ``scipy.linalg`` costs ~120 ms (its Python layers,
    which the solver never calls). Where scipy's layout differs, the package is imported after all."""
    global _LAPACK
    if _LAPACK is None:
        _LAPACK = _flapack_alone()
    return _LAPACK


def _flapack_alone() -> ModuleType:
    """``scipy.linalg._flapack`` loaded without importing ``scipy.linalg`` (see :func:`lapack`); registered
    under its own name, so that a later ``import scipy.linalg`` takes this module, not a second copy."""
    import importlib.machinery
    import importlib.util
    import os
    import sys

    import scipy

    name = "scipy.linalg._flapack"
    mod = sys.modules.get(name)
    if mod is not None:
        return mod
    where = os.path.join(os.path.dirname(scipy.__file__), "linalg")
    spec = importlib.machinery.PathFinder.find_spec(name, [where])
    if spec is None or spec.loader is None:
        from scipy.linalg import lapack as scipy_lapack

        return scipy_lapack
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


@dataclass(frozen=True, slots=True)
class InflightParams:
    """Prior standard deviations (the autopilot's calibration is the prior mean) and noise floor.

    sigma_a: soft-iron/scale entries of A, dimensionless (a compass calibrated by the autopilot is within a
    few %; an uncalibrated one within ~30 %). sigma_d_mgauss: hard iron left after the autopilot's
    offsets (a vehicle's hard iron is at most a few hundred mgauss). sigma_theta_mgauss: theta of eq. (11)
    (the paper's Table II: up to ~200 mgauss; measured vehicles up to ~600). sigma_motor_mgauss: each
    per-motor deviation. sigma_rot_rad: the compass's misalignment to the IMU (relative form; a board or
    mast is mounted within a few degrees). noise_floor_mgauss: lower bound on the residual standard
    deviation (quantisation of 1-3 mgauss and the field's local disturbances). heading_ok_deg: the heading
    uncertainty (1 sigma, from the covariance) below which the estimate is used for correction;
    heading_converged_deg: below which theta is flagged converged.
    """

    sigma_a: float = 0.3
    sigma_d_mgauss: float = 300.0
    sigma_theta_mgauss: float = 600.0
    sigma_motor_mgauss: float = 150.0
    sigma_rot_rad: float = 0.05
    noise_floor_mgauss: float = 3.0
    heading_ok_deg: float = 2.0
    heading_converged_deg: float = 1.0


@dataclass(frozen=True, slots=True)
class InflightSolution:
    """The estimate: ``calib_l`` = A^-1 and ``calib_d`` = A^-1 d (the L and d of eq. (2): u = L y - d),
    ``theta_mgauss`` in the calibrated frame (A^-1 theta_0), ``motor_theta_mgauss`` (m, 3) likewise,
    ``theta_sigma_mgauss`` its 1-sigma per axis, ``heading_sigma_deg`` the heading uncertainty the
    parameters' covariance implies at the throttle seen so far, ``residual_rms_mgauss`` the fit's residual.
    Both sigmas include ``variance_inflation`` (>= 1: the residual's correlation in time, see
    :meth:`InflightEstimator.variance_inflation`)."""

    calib_l: F64
    calib_d: F64
    theta_mgauss: F64
    motor_theta_mgauss: F64
    theta_sigma_mgauss: F64
    heading_sigma_deg: float
    residual_rms_mgauss: float
    n: int
    variance_inflation: float = 1.0
    #: heading (deg) the two models' calibrations give apart (0 without a second model; see
    #: HEADING_MODEL_SPREAD): included in ``heading_sigma_deg`` when that flag is on
    heading_model_deg: float = 0.0
    #: heading (deg) the two alternate-batch halves' estimates give apart, halved (SPLIT_CHECK): included in
    #: ``heading_sigma_deg`` when that flag is on
    heading_split_deg: float = 0.0


_IDENTITY: dict[int, F64] = {}


def identity(n: int) -> F64:
    """The n x n identity, built once per size (read only: LAPACK's dpotrs copies its right-hand side)."""
    eye = _IDENTITY.get(n)
    if eye is None:
        eye = _IDENTITY[n] = np.eye(n)
        eye.flags.writeable = False
    return eye
