"""Online estimation of the throttle-bias parameters theta (section II-C.2, eqs. (16)-(23)).

Reference: M. Silic and K. Mohseni, "Correcting Current-Induced Magnetometer Errors on UAVs: An Online
Model-Based Approach", IEEE Sensors Journal, 2019 (equation numbers as in
``/work/shared/paper/silic-mohseni-2019.md``).

Symbol table (paper -> code, unit, frame):

=====================  =============================  ================  ===========
paper                  code                           unit              frame
=====================  =============================  ================  ===========
v (bar v)              field_b_mgauss, v              mgauss            compass/body
v hat                  v_hat_mgauss                   mgauss            body
theta, theta hat       theta_hat_mgauss               mgauss            body
delta_t                throttle_01, delta             0..1              -
delta_t^2              d2                             -                 -
omega, omega_x         omega_b_rad_s, skew(omega)     rad/s             body FRD
k1, k2                 ObserverParams.k1_1_s, .k2     1/s, -            -
V                      lyapunov_v()                   mgauss^2          -
=====================  =============================  ================  ===========

Two discrete schemes share one exact discrete model of eq. (19) / (16). With the body rotation over
one sample interval ``dR_k = exp([phi_k]_x)`` (``phi_k`` = integral of omega, see :func:`rotation_increment`)
and ``A_k = dR_k^T``, the Earth field being constant in NED gives, exactly,

    v_{k+1} - d2_{k+1} theta = A_k (v_k - d2_k theta)                       (discrete eqs. (13), (16))
    y_k := v_{k+1} - A_k v_k = (d2_{k+1} I - d2_k A_k) theta = Phi_k theta  (linear in theta)

``variant="delta_dot"`` uses this Phi_k (it keeps the throttle-rate term of eq. (16) exactly);
``variant="paper"`` uses the constant-throttle form of eq. (19), ``Phi_k = d2_mid (I - A_k)``.

* ``scheme="observer"``: the paper's observer eq. (20) with gains k1, k2, discretised so that the
  Lyapunov function eq. (23) cannot increase: predict ``v_hat`` with the exact model, update
  ``theta_hat <- theta_hat - k2 Phi^T eps`` (discrete eq. (20b); ``-Phi^T ~ delta^2 [omega]_x dt``),
  damp the prediction error by ``exp(-k1 dt)`` (eq. (20a)). Noise-free and with an exact model,
  ``V_{k+1} - V_k = -1/2 |s|^2 + 1/2 (1-P)(c^2(1-P) - 1) <= 0`` per eigen-direction of
  ``P = k2 Phi Phi^T`` as long as ``k2 |Phi_k|_2^2 <= 1`` (see docs/observer.md); the step caps the
  effective k2 to keep that true and flags it.
* ``scheme="regression"`` (default): recursive least squares on ``y_k = Phi_k theta`` with regularised
  exponential forgetting (information ``J_{k+1} = lam J_k + (1-lam) J_0 + Phi^T Phi``); noise-free,
  ``theta_err^T J theta_err`` is non-increasing for any rate and excitation, and ``J >= J_0`` bounds
  the error without wind-up. A low-pass applied identically to ``y`` and to every column of ``Phi``
  keeps ``y_f = Phi_f theta`` exact, so the paper's 5 Hz filter (section II-D) adds no bias here.

Departures from the paper (all deliberate, all measured in tests/unit/test_observer.py):

* eq. (16) as printed has ``+ 2 delta delta_dot theta``; differentiating eq. (13) gives
  ``v_dot = -omega_x (v - delta^2 theta) + 2 delta delta_dot theta``; we use that sign;
* discrete-time design above instead of integrating eq. (20) with Euler (the Euler/zero-order-hold
  rotation errors, ``O(|omega|^2 dt^2 |u|)`` and ``O(|omega_dot| dt^2 |u|)`` on the ~500 mgauss Earth
  field per step, are as large as the theta signal ``delta^2 |omega| dt |theta|`` and bias the result);
* the rotation over a step integrates a quadratic through the last three gyro samples plus the
  two-sample coning term, not the gyro sample held constant;
* excitation (Definition 1, eq. (21)) is monitored online and theta is held on unexcited axes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.lowpass import LowPassParams, LowPassState, lowpass_init, lowpass_step
from magcomp.core.rotations import skew, so3_exp
from magcomp.core.types import (
    FLAG_INPUTS_STALE,
    FLAG_NO_THROTTLE,
    FLAG_OBSERVER_RESET,
    FLAG_SATURATED,
    FLAG_THETA_CONVERGED,
    FLAG_Z_UNOBSERVABLE,
)
from magcomp.errors import InputError

F64 = NDArray[np.float64]
Scheme = Literal["regression", "observer"]
Variant = Literal["paper", "delta_dot"]
Prefilter = Literal["none", "field", "inputs", "regression"]
RateInterp = Literal["quadratic", "trapezoid", "hold"]

NO_THROTTLE_D2 = 1e-4  # delta^2 below this (delta < 1 %): theta has no effect on v


@dataclass(frozen=True)
class ObserverParams:
    """Configuration of :func:`observer_step`.

    k1_1_s : eq. (20a) damping of the field-prediction error, 1/s (applied as exp(-k1 dt))
    k2 : eq. (20b) adaptation gain (dimensionless: theta_dot [mgauss/s] = k2 * omega [1/s] * v_err [mgauss])
    scheme : "regression" (RLS on the exact discrete model, default) or "observer" (discretised eq. (20))
    variant : "delta_dot" (exact throttle-change term of eq. (16)) or "paper" (eq. (19), constant throttle)
    prefilter : where the low-pass goes: "none"; "field" (paper, field only; biased, kept to show it);
        "inputs" (field, omega and delta^2 alike); "regression" (y and Phi alike; exact; regression only)
    lowpass : the low-pass used by ``prefilter``
    forget_s : RLS forgetting time constant, s (lam = exp(-dt / forget_s))
    info0 : regularising information J_0 = info0 * I (prior weight toward the current estimate)
    theta_max_mgauss : per-component bound on theta_hat (clipped and flagged)
    dt_min_s, dt_max_s : accepted sample interval; outside it the step re-anchors and keeps theta
    excitation_window_s : window of the excitation Gramian (eq. (21))
    excitation_min_rad2_s2 : per-axis information below which an axis is unobservable (theta held)
    converge_min_excited_s : excited time an axis needs before it may be called converged
    converge_std_mgauss, converge_rel : converged when the estimated 1-sigma of theta_i is below
        converge_std_mgauss + converge_rel * |theta_hat|
    rate_interp : rotation over a step from a "quadratic" through three gyro samples (default),
        "trapezoid" (two samples) or "hold" (omega_{k+1} held; the naive form, kept for comparison)
    """

    k1_1_s: float = 2.0
    k2: float = 1.0
    scheme: Scheme = "regression"
    variant: Variant = "delta_dot"
    prefilter: Prefilter = "regression"
    lowpass: LowPassParams = field(default_factory=LowPassParams)
    forget_s: float = 30.0
    info0: float = 1e-4
    theta_max_mgauss: float = 2000.0
    dt_min_s: float = 1e-3
    dt_max_s: float = 0.2
    excitation_window_s: float = 5.0
    excitation_min_rad2_s2: float = 0.05
    converge_min_excited_s: float = 5.0
    converge_std_mgauss: float = 3.0
    converge_rel: float = 0.02
    rate_interp: RateInterp = "quadratic"

    def __post_init__(self) -> None:
        if self.scheme not in ("regression", "observer"):
            raise InputError(f"observer scheme must be 'regression' or 'observer', got {self.scheme!r}")
        if self.variant not in ("paper", "delta_dot"):
            raise InputError(f"observer variant must be 'paper' or 'delta_dot', got {self.variant!r}")
        if self.prefilter not in ("none", "field", "inputs", "regression"):
            raise InputError(f"unknown observer prefilter {self.prefilter!r}")
        if self.prefilter == "regression" and self.scheme != "regression":
            raise InputError("prefilter 'regression' needs scheme 'regression'")
        if self.rate_interp not in ("quadratic", "trapezoid", "hold"):
            raise InputError(f"unknown rate interpolation {self.rate_interp!r}")
        if not (self.k1_1_s >= 0.0 and self.k2 > 0.0):
            raise InputError(f"observer gains need k1 >= 0 and k2 > 0, got k1={self.k1_1_s}, k2={self.k2}")
        if not (self.forget_s > 0.0 and self.info0 > 0.0 and self.theta_max_mgauss > 0.0):
            raise InputError("observer forget_s, info0 and theta_max_mgauss must be > 0")
        if not 0.0 < self.dt_min_s < self.dt_max_s:
            raise InputError(f"observer needs 0 < dt_min_s < dt_max_s, got {self.dt_min_s}, {self.dt_max_s}")
        if not self.excitation_window_s > 0.0:
            raise InputError("observer excitation_window_s must be > 0")


@dataclass(frozen=True)
class ObserverState:
    """State of :func:`observer_step`. Arrays are never modified in place.

    v_hat_mgauss, theta_hat_mgauss : estimates (3,), body frame
    info : RLS information matrix J (3, 3), dimensionless
    gram_sum, gram_weight : exponentially weighted sum of Phi^T Phi / dt and of dt (excitation Gramian)
    field_prev_mgauss, omega_prev_rad_s, omega_prev2_rad_s, d2_prev : last (filtered) inputs
    dt_prev_s : last interval (NaN when the previous-but-one gyro sample is not usable)
    lp : low-pass state (None when ``prefilter == "none"``)
    resid_var : running mean of the squared regression residual per component, mgauss^2
    excited_s : time each axis has been observable since the last full reset, s
    converged : per-axis convergence flags
    initialized : False until the first valid sample anchors the state
    """

    v_hat_mgauss: F64
    theta_hat_mgauss: F64
    info: F64
    gram_sum: F64
    gram_weight: float
    field_prev_mgauss: F64
    omega_prev_rad_s: F64
    omega_prev2_rad_s: F64
    d2_prev: float
    dt_prev_s: float
    lp: LowPassState | None
    resid_var: float
    excited_s: F64
    converged: tuple[bool, bool, bool]
    initialized: bool = False
    n_steps: int = 0


@dataclass(frozen=True)
class StepInfo:
    """Diagnostics of one :func:`observer_step`.

    status : "ok", "init" (first sample anchored), "dt_out_of_range" (re-anchored, theta kept),
        "non_finite" (input ignored, state unchanged)
    innovation_mgauss : field prediction error before the update, v_hat^- - v (3,)
    residual_norm_mgauss : |y - Phi theta_hat| of the (filtered) regression before the update
    excitation_min_rad2_s2 : smallest eigenvalue of the windowed Gramian of eq. (21)
    info_axis_rad2_s2 : per-axis information 1 / [G^-1]_ii (other axes marginalised)
    observable, converged : per-axis flags
    z_unobservable : body z lacks excitation (e.g. pure yaw): theta_z is held and not claimed
    theta_std_mgauss : estimated 1-sigma of theta_hat per axis (from J and the residual variance)
    flags : FLAG_* bits of magcomp.core.types
    """

    status: str
    innovation_mgauss: F64
    residual_norm_mgauss: float
    excitation_min_rad2_s2: float
    info_axis_rad2_s2: F64
    observable: tuple[bool, bool, bool]
    converged: tuple[bool, bool, bool]
    z_unobservable: bool
    theta_std_mgauss: F64
    flags: int


# --- continuous-time form (eq. (20)) ------------------------------------------------------------------


def observer_rhs(t: float, x: F64, u: tuple[ArrayLike, float, float, ArrayLike], p: ObserverParams) -> F64:
    """Right-hand side of the observer eq. (20), SciPy shape.

    Parameters
    ----------
    t : time, s (unused; the system is time-varying only through ``u``)
    x : [v_hat (3), theta_hat (3)], mgauss, body
    u : (omega_b_rad_s (3,), delta (0..1), delta_dot (1/s), v_meas (3,) mgauss)
    p : gains ``k1_1_s``, ``k2`` and ``variant``

    ``variant="paper"`` is eq. (20) as printed. ``variant="delta_dot"`` adds the throttle-rate term of
    eq. (16) (with the sign from differentiating eq. (13), see module docstring) to the prediction and
    the matching term to the adaptation, so that eq. (23) still gives V_dot = -k1 |v_err|^2.
    """
    omega = np.asarray(u[0], dtype=float)
    delta = float(u[1])
    delta_dot = float(u[2])
    v_meas = np.asarray(u[3], dtype=float)
    v_hat = x[:3]
    theta_hat = x[3:]
    d2 = delta * delta
    w_x = skew(omega)
    v_err = v_hat - v_meas
    v_dot = -w_x @ (v_hat - d2 * theta_hat) - p.k1_1_s * v_err  # eq. (20a)
    theta_dot = p.k2 * d2 * (w_x @ v_err)  # eq. (20b)
    if p.variant == "delta_dot":
        v_dot = v_dot + 2.0 * delta * delta_dot * theta_hat  # eq. (16), throttle-rate term
        theta_dot = theta_dot - p.k2 * 2.0 * delta * delta_dot * v_err  # keeps V_dot = -k1|v_err|^2
    return np.concatenate([v_dot, theta_dot])


def lyapunov_v(
    v_hat_mgauss: ArrayLike, theta_hat_mgauss: ArrayLike, v_true_mgauss: ArrayLike,
    theta_true_mgauss: ArrayLike, k2: float,
) -> float:
    """Lyapunov function eq. (23): ``V = 1/2 |v_err|^2 + 1/(2 k2) |theta_err|^2`` (mgauss^2)."""
    v_err = np.asarray(v_hat_mgauss, dtype=float) - np.asarray(v_true_mgauss, dtype=float)
    th_err = np.asarray(theta_hat_mgauss, dtype=float) - np.asarray(theta_true_mgauss, dtype=float)
    return float(0.5 * v_err @ v_err + 0.5 / k2 * th_err @ th_err)


# --- discrete model ------------------------------------------------------------------------------------


def rotation_increment(
    omega_prev2: F64, omega_prev: F64, omega_now: F64, dt_prev_s: float, dt_s: float,
    interp: RateInterp = "quadratic",
) -> F64:
    """Rotation vector phi (rad, body) of the body over the last interval, ``dR = exp([phi]_x)``.

    Integrates a quadratic through omega at t_{k-1}, t_k, t_{k+1} over [t_k, t_{k+1}] (third order; the
    Adams-Moulton weights (-1, 8, 5)/12 for equal steps), plus the two-sample coning correction
    ``dt^2/12 omega_k x omega_{k+1}``. Falls back to the trapezoid when ``dt_prev_s`` is not finite.
    Not in the paper (which integrates eq. (18) in continuous time).
    """
    if interp == "hold":
        return omega_now * dt_s
    integral = 0.5 * dt_s * (omega_prev + omega_now)
    if interp == "quadratic" and np.isfinite(dt_prev_s) and dt_prev_s > 0.0:
        h0, h1 = dt_prev_s, dt_s
        c = (h0 * (omega_now - omega_prev) + h1 * (omega_prev2 - omega_prev)) / (h0 * h1 * (h0 + h1))
        b = (omega_now - omega_prev) / h1 - c * h1
        integral = omega_prev * h1 + b * (h1 * h1 / 2.0) + c * (h1**3 / 3.0)
    a, b2 = omega_prev, omega_now
    coning = np.array([a[1] * b2[2] - a[2] * b2[1], a[2] * b2[0] - a[0] * b2[2], a[0] * b2[1] - a[1] * b2[0]])
    return integral + (dt_s * dt_s / 12.0) * coning  # two-sample coning term, omega_k x omega_{k+1}


def regressor(a_k: F64, d2_prev: float, d2_now: float, variant: Variant) -> F64:
    """Phi_k of ``y_k = v_{k+1} - A_k v_k = Phi_k theta`` (exact discrete eq. (16), or eq. (19))."""
    eye = np.eye(3)
    if variant == "delta_dot":
        return d2_now * eye - d2_prev * a_k  # eq. (16), discrete and exact
    return 0.5 * (d2_prev + d2_now) * (eye - a_k)  # eq. (19): throttle held at its mean over the step


def _inv3(m: F64) -> F64:
    """Inverse of a 3x3 matrix by the adjugate (avoids numpy.linalg call overhead in the 100 Hz loop)."""
    c0 = np.array([m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1], m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2],
                   m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]])
    det = float(m[0] @ c0)
    adj = np.array([
        [c0[0], m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2], m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]],
        [c0[1], m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0], m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]],
        [c0[2], m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1], m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]],
    ])
    return adj / det


def excitation(gram: F64, min_info_rad2_s2: float) -> tuple[float, F64, tuple[bool, bool, bool]]:
    """Observability from the windowed excitation Gramian of Definition 1, eq. (21).

    ``gram`` is the time average of ``Phi^T Phi / dt^2 ~ delta^4 [omega]_x^T [omega]_x`` (plus the
    throttle-change term), rad^2/s^2. Returns (smallest eigenvalue, per-axis information
    ``1 / [G^-1]_ii`` with the other axes marginalised, per-axis flag ``info_i >= min_info_rad2_s2``).
    Under pure yaw G = delta^4 r^2 diag(1, 1, 0): the z information is 0 and z is unobservable.
    """
    g = 0.5 * (gram + gram.T)
    lam_min = float(np.linalg.eigvalsh(g)[0])
    reg = 1e-9 * max(float(np.trace(g)), 1e-12)
    ginv = _inv3(g + reg * np.eye(3))
    info = 1.0 / np.diag(ginv)
    obs = info >= min_info_rad2_s2
    return lam_min, info, (bool(obs[0]), bool(obs[1]), bool(obs[2]))


def excitation_from_rates(
    omega_b_rad_s: ArrayLike, throttle_01: ArrayLike | float = 1.0, min_info_rad2_s2: float = 0.05
) -> tuple[float, F64, tuple[bool, bool, bool]]:
    """:func:`excitation` for a window of gyro samples (n, 3) and throttle (n,) or scalar (eq. (21)).

    Uses the continuous-time integrand ``W W^T`` with ``W = delta^2 [omega]_x`` averaged over the window.
    """
    w = np.atleast_2d(np.asarray(omega_b_rad_s, dtype=float))
    d2 = np.broadcast_to(np.asarray(throttle_01, dtype=float) ** 2, (w.shape[0],))
    sq = np.einsum("ni,ni->n", w, w)
    g = np.einsum("n,nij->ij", d2**2, sq[:, None, None] * np.eye(3) - w[:, :, None] * w[:, None, :])
    return excitation(g / max(w.shape[0], 1), min_info_rad2_s2)


# --- discrete step -------------------------------------------------------------------------------------


def observer_init(p: ObserverParams, theta0_mgauss: ArrayLike | None = None) -> ObserverState:
    """A state waiting for its first sample; theta_hat starts at ``theta0_mgauss`` (default 0)."""
    theta = np.zeros(3) if theta0_mgauss is None else np.asarray(theta0_mgauss, dtype=float).copy()
    z3 = np.zeros(3)
    return ObserverState(
        v_hat_mgauss=z3, theta_hat_mgauss=theta, info=p.info0 * np.eye(3), gram_sum=np.zeros((3, 3)),
        gram_weight=0.0, field_prev_mgauss=z3, omega_prev_rad_s=z3, omega_prev2_rad_s=z3, d2_prev=0.0,
        dt_prev_s=float("nan"), lp=None, resid_var=0.0, excited_s=z3, converged=(False, False, False),
        initialized=False, n_steps=0,
    )


def observer_reset(state: ObserverState, p: ObserverParams, keep_theta: bool = True) -> ObserverState:
    """Reset after a gap, a time jump or a configuration change.

    ``keep_theta=True`` (soft reset): keeps theta_hat, its information and convergence; drops the
    anchors (previous sample, filters), so the next sample re-initialises them. This is what
    :func:`observer_step` does by itself when dt is outside [dt_min_s, dt_max_s].
    ``keep_theta=False``: back to :func:`observer_init` with theta_hat = 0.
    """
    if not keep_theta:
        return observer_init(p)
    return replace(state, initialized=False, lp=None, dt_prev_s=float("nan"))


def _info(
    state: ObserverState, p: ObserverParams, status: str, flags: int, innovation: F64 | None = None,
    residual: float = float("nan"),
    exc: tuple[float, F64, tuple[bool, bool, bool]] | None = None, std: F64 | None = None,
) -> StepInfo:
    if exc is None:
        gram = state.gram_sum / state.gram_weight if state.gram_weight > 0.0 else np.zeros((3, 3))
        exc = excitation(gram, p.excitation_min_rad2_s2)
    lam_min, info_axis, obs = exc
    if std is None:
        std = np.sqrt(np.diag(_inv3(state.info)) * state.resid_var)
    if not obs[2]:
        flags |= FLAG_Z_UNOBSERVABLE
    if all(state.converged):
        flags |= FLAG_THETA_CONVERGED
    return StepInfo(
        status=status,
        innovation_mgauss=np.full(3, np.nan) if innovation is None else innovation,
        residual_norm_mgauss=residual,
        excitation_min_rad2_s2=lam_min,
        info_axis_rad2_s2=info_axis,
        observable=obs,
        converged=state.converged,
        z_unobservable=not obs[2],
        theta_std_mgauss=std,
        flags=flags,
    )


def _anchor(state: ObserverState, field_b: F64, omega_b: F64, d2: float, p: ObserverParams) -> ObserverState:
    lp = None
    if p.prefilter == "field":
        lp = lowpass_init(field_b)
    elif p.prefilter == "inputs":
        lp = lowpass_init(np.concatenate([field_b, omega_b, [d2]]))
    return replace(
        state, v_hat_mgauss=field_b, field_prev_mgauss=field_b, omega_prev_rad_s=omega_b,
        omega_prev2_rad_s=omega_b, d2_prev=d2, dt_prev_s=float("nan"), lp=lp, initialized=True,
    )


def observer_step(
    state: ObserverState, omega_b_rad_s: ArrayLike, field_b_mgauss: ArrayLike, throttle_01: float,
    dt_s: float, p: ObserverParams,
) -> tuple[ObserverState, StepInfo]:
    """One step of the online theta estimator for a gyro + magnetometer + throttle sample.

    Parameters
    ----------
    state : from :func:`observer_init` or a previous step
    omega_b_rad_s : body rate at the sample time (3,), rad/s, body FRD
    field_b_mgauss : calibrated (eq. (2)) field at the same time (3,), mgauss, body
    throttle_01 : throttle command delta_t, 0..1, at the same time
    dt_s : time since the previous sample, s, from the source's timestamps
    p : parameters

    Guards: a non-finite input returns the state unchanged (status "non_finite", FLAG_INPUTS_STALE);
    dt outside [dt_min_s, dt_max_s] re-anchors on this sample and keeps theta (status
    "dt_out_of_range", FLAG_OBSERVER_RESET); theta_hat is clipped to +-theta_max_mgauss (FLAG_SATURATED).
    """
    omega = np.asarray(omega_b_rad_s, dtype=float).reshape(3)
    field_b = np.asarray(field_b_mgauss, dtype=float).reshape(3)
    delta = float(throttle_01)
    if not (np.all(np.isfinite(omega)) and np.all(np.isfinite(field_b)) and np.isfinite(delta)
            and np.isfinite(dt_s)):
        return state, _info(state, p, "non_finite", FLAG_INPUTS_STALE)
    d2 = min(max(delta, 0.0), 1.0) ** 2
    if not state.initialized:
        new = _anchor(state, field_b, omega, d2, p)
        return new, _info(new, p, "init", FLAG_OBSERVER_RESET)
    if not p.dt_min_s <= dt_s <= p.dt_max_s:
        new = _anchor(state, field_b, omega, d2, p)
        return new, _info(new, p, "dt_out_of_range", FLAG_OBSERVER_RESET)

    # prefilter of the raw inputs (section II-D); "field" alone delays v but not omega (biased)
    lp = state.lp
    v1, w1, d2_1 = field_b, omega, d2
    if p.prefilter == "field" and lp is not None:
        lp, v1 = lowpass_step(lp, field_b, dt_s, p.lowpass)
    elif p.prefilter == "inputs" and lp is not None:
        lp, out = lowpass_step(lp, np.concatenate([field_b, omega, [d2]]), dt_s, p.lowpass)
        v1, w1, d2_1 = out[:3], out[3:6], float(out[6])
    v0, d2_0 = state.field_prev_mgauss, state.d2_prev

    # exact discrete model: v_{k+1} - d2_{k+1} theta = A_k (v_k - d2_k theta)
    phi = rotation_increment(state.omega_prev2_rad_s, state.omega_prev_rad_s, w1, state.dt_prev_s, dt_s,
                             p.rate_interp)
    a_k = so3_exp(-phi)  # dR_k^T, eqs. (18)-(19) over one step
    phi_k = regressor(a_k, d2_0, d2_1, p.variant)
    y_k = v1 - a_k @ v0

    # excitation Gramian (eq. (21)), exponentially windowed time average of Phi^T Phi / dt^2
    lam_e = float(np.exp(-dt_s / p.excitation_window_s))
    gram_sum = lam_e * state.gram_sum + (phi_k.T @ phi_k) / dt_s
    gram_weight = lam_e * state.gram_weight + dt_s
    exc = excitation(gram_sum / gram_weight, p.excitation_min_rad2_s2)
    obs = exc[2]
    # hold theta on axes without excitation once the window has filled (not in the paper); before that
    # a one-sample Gramian is rank 2 and would freeze every axis. On a truly unexcited axis the column of
    # Phi is zero, so the update there is zero anyway; the hold guards against noise-driven drift.
    warm = gram_weight >= 0.5 * p.excitation_window_s
    held = ~np.array(obs) & warm

    # regression prefilter: the same LTI filter on y and on each column of Phi keeps y_f = Phi_f theta
    if p.prefilter == "regression":
        regs = np.concatenate([y_k, phi_k.ravel()])
        lp_r = lowpass_init(regs) if lp is None else lp
        lp, regs_f = lowpass_step(lp_r, regs, dt_s, p.lowpass)
        y_f, phi_f = regs_f[:3], regs_f[3:].reshape(3, 3)
    else:
        y_f, phi_f = y_k, phi_k

    theta = state.theta_hat_mgauss
    resid = y_f - phi_f @ theta
    lam = float(np.exp(-dt_s / p.forget_s))
    info_new = lam * state.info + (1.0 - lam) * p.info0 * np.eye(3) + phi_f.T @ phi_f
    info_inv = _inv3(info_new)
    v_pred = a_k @ state.v_hat_mgauss + phi_k @ theta  # eq. (20a) prediction, exact over dt
    innovation = v_pred - v1
    flags = 0
    if p.scheme == "regression":
        d_theta = info_inv @ (phi_f.T @ resid)  # RLS with regularised forgetting
    else:
        # eq. (20b), discrete: -Phi^T ~ delta^2 [omega]_x dt; keep k2 |Phi|_2^2 <= 1 (discrete V decrease)
        phi_norm2 = float(np.linalg.eigvalsh(phi_k.T @ phi_k)[-1])  # |Phi_k|_2^2
        k2_eff = p.k2
        if k2_eff * phi_norm2 > 1.0:
            k2_eff = 1.0 / phi_norm2
            flags |= FLAG_SATURATED
        d_theta = -k2_eff * (phi_k.T @ innovation)  # eq. (20b)
    d_theta = np.where(held, 0.0, d_theta)  # hold theta on axes without excitation (not in the paper)
    theta_new = theta + d_theta
    clipped = np.clip(theta_new, -p.theta_max_mgauss, p.theta_max_mgauss)
    if np.any(clipped != theta_new):
        flags |= FLAG_SATURATED
    theta_new = clipped
    c = float(np.exp(-p.k1_1_s * dt_s))
    v_hat_new = v1 + c * (a_k @ state.v_hat_mgauss + phi_k @ theta_new - v1)  # eq. (20a): exp(-k1 dt) damping

    resid_var = lam_e * state.resid_var + (1.0 - lam_e) * float(resid @ resid) / 3.0
    excited = state.excited_s + np.where(np.array(obs), dt_s, 0.0)
    std = np.sqrt(np.diag(info_inv) * resid_var)
    tol = p.converge_std_mgauss + p.converge_rel * float(np.linalg.norm(theta_new))
    conv = (excited >= p.converge_min_excited_s) & (std <= tol)
    if d2_1 < NO_THROTTLE_D2:
        flags |= FLAG_NO_THROTTLE

    new = ObserverState(
        v_hat_mgauss=v_hat_new, theta_hat_mgauss=theta_new, info=info_new, gram_sum=gram_sum,
        gram_weight=gram_weight, field_prev_mgauss=v1, omega_prev_rad_s=w1,
        omega_prev2_rad_s=state.omega_prev_rad_s, d2_prev=d2_1, dt_prev_s=dt_s, lp=lp, resid_var=resid_var,
        excited_s=excited, converged=(bool(conv[0]), bool(conv[1]), bool(conv[2])), initialized=True,
        n_steps=state.n_steps + 1,
    )
    return new, _info(new, p, "ok", flags, innovation, float(np.linalg.norm(resid)), exc, std)
