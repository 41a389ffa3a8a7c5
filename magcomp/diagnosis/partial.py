"""theta where the calibration is not observable: the autopilot's calibration as the prior.

The validity gate (:mod:`magcomp.diagnosis.gate`) refuses a fit whose calibration the log cannot determine
(the heading covers less than 90 deg, the tilt less than 10 deg, or the free calibration comes out
non-physical). That is a statement about A and the hard iron, not about theta: theta multiplies throttle^2
(eq. (11)), and a hover whose throttle varies at a near-constant attitude carries theta in the field's
changes with throttle while the Earth-field term hardly moves. So theta is estimated separately, with the
calibration A held near the one the autopilot flies with, a *prior*, not a fit:

    v = A h_b(inc, dec) + c + theta D + noise,   A ~ N(A0, sigma_A^2) element-wise (maximum a posteriori)

A0 = F I: a compass the autopilot has calibrated reads the Earth field F (WMM strength at the log's place,
else the measured field's median magnitude clipped to Earth's surface range) along the body axes. sigma_A = s
F / 1.96 with s the gate's scale tolerance (``GateParams.max_scale_error``, 0.35: ArduPilot's own arming
range), so the prior admits any calibration the gate would accept and no more. The hard iron c is free (the
field at a constant attitude fixes it with theta). inc and dec are fitted with A held at the prior (the WMM
inclination when known is the start).

theta's 95 % interval is the posterior one, sigma^2 (X'X + P)^-1 with the residual's variance, inflated by
Bartlett's factor of the residual against the theta column (the effective sample size of
:mod:`magcomp.diagnosis.selection`): it includes what the prior leaves uncertain about A. It is at least the
block jackknife's (:func:`magcomp.diagnosis.intervals.block_jackknife_se`, the prior kept in every
refit; inclination, declination and heading drift linearised and free), as the free fit's interval is: the
Bartlett factor sees only the residual's autocorrelation against the drive, not a model error that moves
theta from one manoeuvre to the next. Measured: on hovers with AR(1) compass noise (5 mgauss, 10 s,
``tests/unit/test_diagnosis_partial.py``, seeds 200-229) the simulated theta was inside on every axis in
22/30 flights with the Bartlett factor alone and 28/30 with the floor; on the varied clean simulations of
``benchmarks/diagnosis_prior_coverage.py`` (seeds 70000-70023) 9/24 and 19/24. theta is reported as
identifiable when its interval is narrower than |theta| (the same rule as
:mod:`magcomp.diagnosis.consistency`). What the data cannot carry is still refused with the gate's reasons:
a throttle that does not vary, a model that leaves more than the gate allows.

Pure, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from magcomp.core.types import EARTH_MAX_MGAUSS, EARTH_MIN_MGAUSS
from magcomp.diagnosis.effects import ExtensionParams, drive_columns
from magcomp.diagnosis.gate import structured_shift_bound
from magcomp.diagnosis.intervals import block_jackknife_se, box_quantile
from magcomp.diagnosis.model import CompassData, earth_dir_body
from magcomp.diagnosis.selection import bartlett_factor

F64 = NDArray[np.float64]

#: 95 % two-sided normal quantile
Z95 = 1.959964


@dataclass(frozen=True)
class PriorTheta:
    """theta (compass frame, mgauss at full throttle) with the calibration held at the prior.

    halfwidth: 95 % per axis; identifiable: |halfwidth| < |theta| (and, where the model leaves more than the
    gate allows, the model-error bound below |theta| too); residual_rms_mgauss: of the prior fit;
    field_mgauss: F of the prior; prior: one sentence on A0 and its width; model_error_bound_mgauss: how far
    an unmodelled error of the residual's structured size could move theta if it followed the throttle
    (:func:`magcomp.diagnosis.consistency.model_error_bound`'s rule); why: why theta is not identifiable
    (empty when it is)."""

    theta_mgauss: F64
    halfwidth_mgauss: F64
    identifiable: bool
    residual_rms_mgauss: float
    field_mgauss: float
    prior: str
    model_error_bound_mgauss: float = math.inf
    why: str = ""
    #: the joint 95 % box of theta (Bonferroni over the three axes, :mod:`magcomp.diagnosis.intervals`)
    joint_halfwidth_mgauss: F64 | None = None


def _map_solve(x: F64, v: F64, prior_rows: int, a0: F64, w: float) -> tuple[F64, F64]:
    """Per axis: minimise |x b - v_i|^2 + w |b[:3] - a0_i|^2; returns (coefficients (k, 3), (X'X + P)^-1)."""
    k = x.shape[1]
    p = np.zeros((k, k))
    p[:prior_rows, :prior_rows] = w * np.eye(prior_rows)
    xtx_p = x.T @ x + p
    inv = np.asarray(np.linalg.inv(xtx_p), dtype=np.float64)
    beta = np.empty((k, 3))
    for i in range(3):
        rhs = x.T @ v[:, i]
        rhs[:prior_rows] += w * a0[i]
        beta[:, i] = inv @ rhs
    return beta, inv


def theta_with_prior(
    data: CompassData,
    drift_rad_s: float,
    dec_rad: float,
    field_strength_mgauss: float | None,
    inclination_rad: float | None,
    max_scale_error: float,
    model_error_decides: bool = False,
) -> PriorTheta | None:
    """theta with A held near the autopilot's calibration (module docstring); None without throttle.

    ``model_error_decides``: the free fit left more residual than the gate allows, so an unmodelled error of
    that size might follow the throttle: theta is identifiable only when the model-error bound (structured
    residual / sd of throttle^2, Cauchy-Schwarz) is below |theta| as well. Where the residual is within the
    gate's limit the bound is reported, not applied: it is a worst case (an error wholly aligned with the
    throttle) that a hover's small throttle swing fails whatever the data say."""
    cols, names = drive_columns(data.drive, ExtensionParams())
    if "throttle" not in names or data.n < 20:
        return None
    d = cols[:, list(names).index("throttle")]
    v = data.field_mgauss
    f = field_strength_mgauss
    if f is None or not math.isfinite(f) or f <= 0.0:
        # no position: the calibrated compass reads the Earth field, so its magnitude, within Earth's range
        f = float(np.clip(np.median(np.linalg.norm(v, axis=1)), EARTH_MIN_MGAUSS, EARTH_MAX_MGAUSS))
    a0 = f * np.eye(3)
    sigma_a = max_scale_error * f / Z95

    def design(inc: float, dec: float) -> F64:
        h = earth_dir_body(data, inc, dec, drift_rad_s)
        return np.column_stack([h, np.ones(data.n), d])

    # noise variance for the prior's weight: first from a fit with A at A0, then from the MAP fit itself
    noise_var = float(np.var(v - v.mean(axis=0)))

    def residual(z: F64) -> F64:
        x = design(float(z[0]), float(z[1]))
        beta, _ = _map_solve(x, v, 3, a0, noise_var / sigma_a**2)
        r = x @ beta - v
        prior = math.sqrt(noise_var) / sigma_a * (beta[:3].T - a0)
        return np.concatenate([r.ravel(), prior.ravel()])

    inc0 = inclination_rad if inclination_rad is not None else 1.0
    z = np.array([inc0, dec_rad])
    for _ in range(2):
        sol = least_squares(
            residual, z, bounds=([-math.pi / 2, -4 * math.pi], [math.pi / 2, 4 * math.pi]), max_nfev=100
        )
        z = sol.x
        x = design(float(z[0]), float(z[1]))
        beta, _ = _map_solve(x, v, 3, a0, noise_var / sigma_a**2)
        noise_var = float(np.mean((x @ beta - v) ** 2))
    x = design(float(z[0]), float(z[1]))
    w = noise_var / sigma_a**2
    beta, inv = _map_solve(x, v, 3, a0, w)
    res = v - x @ beta
    theta = beta[4]
    var_res = np.mean(res**2, axis=0)
    inflate = bartlett_factor(res, np.outer(d - d.mean(), theta))
    sd = np.sqrt(var_res * inv[4, 4] * inflate)
    jk_se, jk_dof = _jackknife_se(data, x, beta, res, w, (float(z[0]), float(z[1]), drift_rad_s))
    hw = np.maximum(Z95 * sd, box_quantile(1, jk_dof) * jk_se)
    hw_joint = np.maximum(box_quantile(3) * sd, box_quantile(3, jk_dof) * jk_se)
    tn = float(np.linalg.norm(theta))
    prior = (
        f"calibration held at the autopilot's (A = {f:.0f} mgauss x identity, each element within "
        f"+-{100 * max_scale_error:.0f} % at 95 %), hard iron fitted"
    )
    bound, why = _not_identifiable(tn, hw, res, d, model_error_decides)
    return PriorTheta(
        theta,
        hw,
        not why,
        float(np.sqrt(np.mean(res**2))),
        f,
        prior,
        bound,
        "; ".join(why),
        hw_joint,
    )


def _jackknife_se(
    data: CompassData, x: F64, beta: F64, res: F64, w: float, z3: tuple[float, float, float]
) -> tuple[F64, int]:
    """Standard error of theta per axis (and its degrees of freedom) from the delete-one-block jackknife of
    the posterior mode (:func:`magcomp.diagnosis.intervals.block_jackknife_se` with the prior kept in every
    refit). The
    Earth field's inclination, declination and the heading drift enter linearised (their derivative columns
    per axis, as the free fit's interval has them), so a block whose removal would move them moves theta as
    it would in a refit."""
    h0 = earth_dir_body(data, *z3)
    dh = []
    for k, eps in enumerate((1e-4, 1e-4, 1e-6)):
        zk = list(z3)
        zk[k] += eps
        dh.append((earth_dir_body(data, zk[0], zk[1], zk[2]) - h0) / eps)
    k_cols = x.shape[1]
    prior = np.zeros((k_cols + 3, k_cols + 3))
    prior[:3, :3] = w * np.eye(3)
    sel = np.zeros(k_cols + 3)
    sel[4] = 1.0
    out = np.zeros(3)
    dof = 1
    for a in range(3):
        xa = np.column_stack([x, np.column_stack([dk @ beta[:3, a] for dk in dh])])
        out[a], dof = block_jackknife_se(data.t_s, xa, res[:, a], sel, prior)
    return out, dof


def _not_identifiable(
    theta_norm: float, hw: F64, residual: F64, drive: F64, model_error_decides: bool
) -> tuple[float, list[str]]:
    """(the model-error bound, mgauss; why theta is not identifiable, empty when it is): see
    :func:`theta_with_prior`."""
    bound, structured, sd_d = structured_shift_bound(residual, drive)
    why = []
    width = float(np.linalg.norm(hw))
    if width >= theta_norm:
        why.append(f"theta's 95 % interval ({width:.0f} mgauss) is wider than |theta| {theta_norm:.0f}")
    if model_error_decides and bound >= theta_norm:
        why.append(
            f"{structured:.1f} mgauss of structured residual over a drive (throttle^2) sd of {sd_d:.3f} "
            f"could move theta by up to {bound:.0f} mgauss, more than |theta| {theta_norm:.0f}"
        )
    return bound, why
