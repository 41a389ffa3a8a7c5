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
* excitation (Definition 1, eq. (21)) is monitored online and theta is held on unexcited axes;
* no step across samples missing (:func:`samples_missing`): :func:`observer_skip` re-anchors the next step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, NamedTuple, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.linalg3 import (
    FloatSeq,
    Mat3,
    Sym3,
    Vec3,
    Vec3Like,
    gram,
    matTvec,
    minus_matvec,
    sym3_eigvals,
    sym3_inv,
    vec3,
)
from magcomp.core.lowpass import (
    Biquad,
    LowPassParams,
    LowPassState,
    biquad_step,
    lowpass_coefficients,
    lowpass_init,
)
from magcomp.core.rotations import dcm_from_rotvec, skew
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
StepStatus = Literal["ok", "init", "dt_out_of_range", "non_finite"]
Bool3 = tuple[bool, bool, bool]

NO_THROTTLE_D2 = 1e-4  # delta^2 below this (delta < 1 %): theta has no effect on v
#: an interval longer than this many of the stream's usual intervals has at least one sample missing in it
#: (one missing sample doubles the interval; the margin takes timestamp jitter up to half an interval)
MISSING_SAMPLE_INTERVALS = 1.5
_NAN3: Vec3 = (math.nan, math.nan, math.nan)
_ZERO3: Vec3 = (0.0, 0.0, 0.0)
#: builds a named tuple from its fields in order without the generated Python ``__new__`` (0.2-0.8 us a
#: step less; every field given, so the defaults do not matter)
_new = tuple.__new__


class StepConstants(NamedTuple):
    """What a step needs that depends on the sample interval alone (:meth:`ObserverParams.step_constants`).

    lam_excitation : exp(-dt / excitation_window_s), the window of eq. (21)
    lam_forget : exp(-dt / forget_s), the RLS forgetting factor
    info_regularise : (1 - lam_forget) * info0, the pull of J toward J_0
    damping : exp(-k1 dt), eq. (20a)
    lowpass : the sec. II-D low-pass section at this dt
    """

    lam_excitation: float
    lam_forget: float
    info_regularise: float
    damping: float
    lowpass: Biquad


@dataclass(frozen=True)
class ObserverParams:
    """Configuration of :func:`observer_step` (the ``[observer]`` section maps onto it through
    :func:`magcomp.service.estimators.observer_params`, with the same defaults and bounds).

    k1_1_s : eq. (20a) damping of the field-prediction error, 1/s (applied as exp(-k1 dt)); > 0 (Theorem 1)
    k2 : eq. (20b) adaptation gain (dimensionless: theta_dot [mgauss/s] = k2 * omega [1/s] * v_err [mgauss]);
        > 0 (Theorem 1); the discrete step caps it at 1 / |Phi_k|_2^2 (see module docstring)
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
    k2: float = 4.0
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
    #: memo of :meth:`step_constants` by dt (a steady rate repeats a few dt values); not a parameter
    _memo: dict[float, StepConstants] = field(default_factory=dict, init=False, repr=False, compare=False)

    def step_constants(self, dt_s: float) -> StepConstants:
        """Everything of a step that depends on ``dt_s`` alone: the forgetting factors, the eq. (20a)
        damping and the low-pass of sec. II-D. Memoised: recomputing them (three exponentials and a tangent)
        costs 1.5 us a step."""
        k = self._memo.get(dt_s)
        if k is None:
            lam = math.exp(-dt_s / self.forget_s)
            k = StepConstants(
                lam_excitation=math.exp(-dt_s / self.excitation_window_s),
                lam_forget=lam,
                info_regularise=(1.0 - lam) * self.info0,
                damping=math.exp(-self.k1_1_s * dt_s),
                lowpass=lowpass_coefficients(self.lowpass, dt_s),
            )
            if len(self._memo) >= 64:  # jittery timestamps: keep the memo small
                self._memo.clear()
            self._memo[dt_s] = k
        return k

    def __post_init__(self) -> None:
        for name, kind in (("scheme", Scheme), ("variant", Variant), ("prefilter", Prefilter),
                           ("rate_interp", RateInterp)):  # fmt: skip
            if getattr(self, name) not in get_args(kind):
                raise InputError(f"observer {name} must be one of {', '.join(get_args(kind))}, "
                                 f"got {getattr(self, name)!r}")  # fmt: skip
        if self.prefilter == "regression" and self.scheme != "regression":
            raise InputError("prefilter 'regression' needs scheme 'regression'")
        if not (self.k1_1_s > 0.0 and self.k2 > 0.0):
            raise InputError(f"observer gains need k1 > 0 and k2 > 0, got k1={self.k1_1_s}, k2={self.k2}")
        if not (self.forget_s > 0.0 and self.info0 > 0.0 and self.theta_max_mgauss > 0.0):
            raise InputError("observer forget_s, info0 and theta_max_mgauss must be > 0")
        if not 0.0 < self.dt_min_s < self.dt_max_s:
            raise InputError(f"observer needs 0 < dt_min_s < dt_max_s, got {self.dt_min_s}, {self.dt_max_s}")
        if not self.excitation_window_s > 0.0:
            raise InputError("observer excitation_window_s must be > 0")


class ObserverState(NamedTuple):
    """State of :func:`observer_step`, in Python floats (immutable).

    v_hat_mgauss, theta_hat_mgauss : estimates, body frame
    info : RLS information matrix J (upper triangle a, b, c, e, f, i of the symmetric 3x3), dimensionless
    gram_sum, gram_weight : exponentially weighted sum of Phi^T Phi / dt (upper triangle) and of dt
        (the excitation Gramian of eq. (21) is their ratio)
    field_prev_mgauss, omega_prev_rad_s, omega_prev2_rad_s, d2_prev : last (filtered) inputs
    dt_prev_s : last interval (NaN when the previous-but-one gyro sample is not usable)
    lp : low-pass state (None when ``prefilter == "none"`` or before the first step)
    resid_var : running mean of the squared regression residual per component, mgauss^2
    excited_s : time each axis has been observable since the last full reset, s
    converged : per-axis convergence flags
    initialized : False until the first valid sample anchors the state
    n_steps : updates so far
    theta_prior : theta_hat started from a prior estimate (``observer_init(p, theta0)``), see
        :func:`_excitation_update`
    """

    v_hat_mgauss: Vec3
    theta_hat_mgauss: Vec3
    info: Sym3
    gram_sum: Sym3
    gram_weight: float
    field_prev_mgauss: Vec3
    omega_prev_rad_s: Vec3
    omega_prev2_rad_s: Vec3
    d2_prev: float
    dt_prev_s: float
    lp: LowPassState | None
    resid_var: float
    excited_s: Vec3
    converged: Bool3
    initialized: bool = False
    n_steps: int = 0
    theta_prior: bool = False


class StepInfo(NamedTuple):
    """Diagnostics of one :func:`observer_step`.

    status : "ok", "init" (first sample anchored), "dt_out_of_range" (re-anchored, theta kept),
        "non_finite" (input ignored, state unchanged)
    flags : FLAG_* bits of magcomp.core.types
    innovation_mgauss : field prediction error before the update, v_hat^- - v
    residual_norm_mgauss : |y - Phi theta_hat| of the (filtered) regression before the update
    info_axis_rad2_s2 : per-axis information 1 / [G^-1]_ii (other axes marginalised)
    observable, converged : per-axis flags
    theta_std_mgauss : estimated 1-sigma of theta_hat per axis (from J and the residual variance)
    gramian : the windowed excitation Gramian G of eq. (21) (upper triangle), rad^2/s^2
    """

    status: StepStatus
    flags: int
    innovation_mgauss: Vec3
    residual_norm_mgauss: float
    info_axis_rad2_s2: Vec3
    observable: Bool3
    converged: Bool3
    theta_std_mgauss: Vec3
    gramian: Sym3

    @property
    def excitation_min_rad2_s2(self) -> float:
        """Smallest eigenvalue of the Gramian (Definition 1); solved when read, not in every step."""
        return sym3_eigvals(self.gramian)[0]

    @property
    def excitation(self) -> float:
        """Short name of :attr:`excitation_min_rad2_s2` (the value published with each heading)."""
        return sym3_eigvals(self.gramian)[0]

    @property
    def z_unobservable(self) -> bool:
        """Body z lacks excitation (e.g. pure yaw): theta_z is held and not claimed."""
        return not self.observable[2]

    @property
    def saturated(self) -> bool:
        """theta_hat hit ``theta_max_mgauss`` (or the eq. (20b) gain was capped) in this step."""
        return bool(self.flags & FLAG_SATURATED)


class ObserverStep(NamedTuple):
    """What :func:`observer_step` returns."""

    state: ObserverState
    info: StepInfo


class Excitation(NamedTuple):
    """Observability from the excitation Gramian (Definition 1, eq. (21))."""

    lam_min_rad2_s2: float
    info_axis_rad2_s2: Vec3
    observable: Bool3


# --- continuous-time form (eq. (20)): the reference the discrete step is checked against -------------------


def observer_rhs(t: float, x: F64, u: tuple[ArrayLike, float, float, ArrayLike], p: ObserverParams) -> F64:
    """Right-hand side of the observer eq. (20), SciPy shape (for ``solve_ivp``; not the online path).

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


# --- discrete model -------------------------------------------------------------------------------------


def rotation_increment(
    omega_prev2: Sequence[float], omega_prev: Sequence[float], omega_now: Sequence[float], dt_prev_s: float,
    dt_s: float, interp: RateInterp = "quadratic",
) -> Vec3:
    """Rotation vector phi (rad, body) of the body over the last interval, ``dR = exp([phi]_x)``.

    Integrates a quadratic through omega at t_{k-1}, t_k, t_{k+1} over [t_k, t_{k+1}] (third order; the
    Adams-Moulton weights (-1, 8, 5)/12 for equal steps), plus the two-sample coning correction
    ``dt^2/12 omega_k x omega_{k+1}``. Falls back to the trapezoid when ``dt_prev_s`` is not finite.
    Not in the paper (which integrates eq. (18) in continuous time).
    """
    nx, ny, nz = omega_now
    if interp == "hold":
        return nx * dt_s, ny * dt_s, nz * dt_s
    px, py, pz = omega_prev
    h1 = dt_s
    if interp == "quadratic" and math.isfinite(dt_prev_s) and dt_prev_s > 0.0:
        h0 = dt_prev_s
        qx, qy, qz = omega_prev2
        den = h0 * h1 * (h0 + h1)
        cx = (h0 * (nx - px) + h1 * (qx - px)) / den
        cy = (h0 * (ny - py) + h1 * (qy - py)) / den
        cz = (h0 * (nz - pz) + h1 * (qz - pz)) / den
        hh2, hh3 = h1 * h1 / 2.0, h1**3 / 3.0
        ix = px * h1 + ((nx - px) / h1 - cx * h1) * hh2 + cx * hh3
        iy = py * h1 + ((ny - py) / h1 - cy * h1) * hh2 + cy * hh3
        iz = pz * h1 + ((nz - pz) / h1 - cz * h1) * hh2 + cz * hh3
    else:  # trapezoid
        ix, iy, iz = 0.5 * h1 * (px + nx), 0.5 * h1 * (py + ny), 0.5 * h1 * (pz + nz)
    k = h1 * h1 / 12.0  # two-sample coning term, omega_k x omega_{k+1}
    return ix + k * (py * nz - pz * ny), iy + k * (pz * nx - px * nz), iz + k * (px * ny - py * nx)


def rotation_increments(w0: F64, w1: F64, w2: F64, h0: F64, h1: F64, p: ObserverParams) -> F64:
    """:func:`rotation_increment` over arrays (the batch solver, core/observer_batch.py): rows of
    (omega_{k-1}, omega_k, omega_{k+1}) and the intervals before and of the step; (m, 3) rotation vectors,
    rad."""
    if p.rate_interp == "hold":
        return w2 * h1[:, None]
    quad = np.isfinite(h0) & (h0 > 0.0) if p.rate_interp == "quadratic" else np.zeros(h1.shape, dtype=bool)
    hq = np.where(quad, h0, 1.0)[:, None]
    hn = h1[:, None]
    c = (hq * (w2 - w1) + hn * (w0 - w1)) / (hq * hn * (hq + hn))
    integral_q = w1 * hn + ((w2 - w1) / hn - c * hn) * (hn * hn / 2.0) + c * (hn**3 / 3.0)
    integral_t = 0.5 * hn * (w1 + w2)
    integral = np.where(quad[:, None], integral_q, integral_t)
    return integral + (hn * hn / 12.0) * np.cross(w1, w2)  # two-sample coning term


def regressor(a_k: Sequence[float], d2_prev: float, d2_now: float, variant: Variant) -> Mat3:
    """Phi_k of ``y_k = v_{k+1} - A_k v_k = Phi_k theta`` (exact discrete eq. (16), or eq. (19)),
    row-major."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a_k
    if variant == "delta_dot":  # eq. (16), discrete and exact: d2_{k+1} I - d2_k A_k
        m = d2_prev
        return (d2_now - m * a0, -m * a1, -m * a2, -m * a3, d2_now - m * a4, -m * a5, -m * a6, -m * a7,
                d2_now - m * a8)  # fmt: skip
    m = 0.5 * (d2_prev + d2_now)  # eq. (19): throttle held at its mean over the step, d2 (I - A_k)
    return (m * (1.0 - a0), -m * a1, -m * a2, -m * a3, m * (1.0 - a4), -m * a5, -m * a6, -m * a7,
            m * (1.0 - a8))  # fmt: skip


def _observability(g: Sym3, min_info_rad2_s2: float) -> tuple[Vec3, Bool3]:
    """Per-axis information ``1 / [G^-1]_ii`` (other axes marginalised) and the flags
    ``info_i >= min_info`` of the Gramian ``g`` (eq. (21)); a 1e-9 relative ridge keeps G invertible."""
    a, b, c, e, f, i = g
    tr = a + e + i
    reg = 1e-9 * (1e-12 if tr < 1e-12 else tr)  # max(tr, 1e-12) without the call
    gi = sym3_inv((a + reg, b, c, e + reg, f, i + reg))
    d0, d1, d2 = gi[0], gi[3], gi[5]
    info = (1.0 / d0, 1.0 / d1, 1.0 / d2)
    return info, (info[0] >= min_info_rad2_s2, info[1] >= min_info_rad2_s2, info[2] >= min_info_rad2_s2)


def excitation(gram_rad2_s2: ArrayLike, min_info_rad2_s2: float) -> Excitation:
    """Observability from a windowed excitation Gramian of Definition 1, eq. (21), (3, 3).

    ``gram`` is the time average of ``Phi^T Phi / dt^2 ~ delta^4 [omega]_x^T [omega]_x`` (plus the
    throttle-change term), rad^2/s^2. Under pure yaw G = delta^4 r^2 diag(1, 1, 0): the z information is 0
    and z is unobservable. The same arithmetic as the online step.
    """
    g = np.asarray(gram_rad2_s2, dtype=float)
    s = 0.5 * (g + g.T)
    up: Sym3 = (float(s[0, 0]), float(s[0, 1]), float(s[0, 2]), float(s[1, 1]), float(s[1, 2]),
                float(s[2, 2]))  # fmt: skip
    info, obs = _observability(up, min_info_rad2_s2)
    return Excitation(sym3_eigvals(up)[0], info, obs)


def excitation_from_rates(
    omega_b_rad_s: ArrayLike, throttle_01: ArrayLike | float = 1.0, min_info_rad2_s2: float = 0.05
) -> Excitation:
    """:func:`excitation` for a window of gyro samples (n, 3) and throttle (n,) or scalar (eq. (21)).

    Uses the continuous-time integrand ``W W^T`` with ``W = delta^2 [omega]_x`` averaged over the window.
    """
    w = np.atleast_2d(np.asarray(omega_b_rad_s, dtype=float))
    d2 = np.broadcast_to(np.asarray(throttle_01, dtype=float) ** 2, (w.shape[0],))
    sq = np.einsum("ni,ni->n", w, w)
    g = np.einsum("n,nij->ij", d2**2, sq[:, None, None] * np.eye(3) - w[:, :, None] * w[:, None, :])
    return excitation(g / max(w.shape[0], 1), min_info_rad2_s2)


def samples_missing(dt_s: float, dt_usual_s: float | None) -> bool:
    """True when an interval of ``dt_s`` (s) skips at least one sample of a stream whose usual interval,
    measured from its own timestamps, is ``dt_usual_s`` (s; None: not measured yet).

    Not in the paper. The step's rotation ``dR_k`` (:func:`rotation_increment`) interpolates the gyro
    samples at the two ends of the step (and the one before); over an interval with samples missing in
    it the rotation is not known to the accuracy the regression differences (an error ``e`` rad on the
    ~500 mgauss Earth field is ``500 e`` mgauss of ``y_k``, against a theta signal of
    ``delta^2 |omega| dt |theta|``, a few mgauss a step in a spin), and that step weighs ``~n^2`` times
    a regular one in the regression. The observer re-anchors after such an interval instead
    (:func:`observer_skip`): no step is formed across missing samples.
    """
    return dt_usual_s is not None and dt_s > MISSING_SAMPLE_INTERVALS * dt_usual_s


# --- discrete step: named pieces ------------------------------------------------------------------------


def observer_init(p: ObserverParams, theta0_mgauss: ArrayLike | None = None) -> ObserverState:
    """A state waiting for its first sample; theta_hat starts at ``theta0_mgauss`` (default 0).

    A given ``theta0_mgauss`` is a prior estimate (a stored theta): axes the young excitation window does
    not see keep it from the first step (see :func:`_excitation_update`)."""
    theta = _ZERO3 if theta0_mgauss is None else vec3(np.asarray(theta0_mgauss, dtype=np.float64).reshape(3))
    j0 = p.info0
    return ObserverState(
        v_hat_mgauss=_ZERO3, theta_hat_mgauss=theta, info=(j0, 0.0, 0.0, j0, 0.0, j0),
        gram_sum=(0.0,) * 6, gram_weight=0.0, field_prev_mgauss=_ZERO3, omega_prev_rad_s=_ZERO3,  # type: ignore[arg-type]
        omega_prev2_rad_s=_ZERO3, d2_prev=0.0, dt_prev_s=math.nan, lp=None, resid_var=0.0, excited_s=_ZERO3,
        converged=(False, False, False), initialized=False, n_steps=0,
        theta_prior=theta0_mgauss is not None,
    )  # fmt: skip


def observer_reset(state: ObserverState, p: ObserverParams, keep_theta: bool = True) -> ObserverState:
    """Reset after a gap, a time jump or a configuration change.

    ``keep_theta=True`` (soft reset): keeps theta_hat, its information and convergence; drops the
    anchors (previous sample, filters), so the next sample re-initialises them. This is what
    :func:`observer_step` does by itself when dt is outside [dt_min_s, dt_max_s].
    ``keep_theta=False``: back to :func:`observer_init` with theta_hat = 0.
    """
    if not keep_theta:
        return observer_init(p)
    return state._replace(initialized=False, lp=None, dt_prev_s=math.nan)


def observer_skip(state: ObserverState) -> ObserverState:
    """Samples missing before the next one (:func:`samples_missing`): the next sample re-anchors the step
    (no regression sample across the interval), theta, J and the excitation kept as by
    :func:`observer_reset`, and the sec. II-D low-pass on the regression keeps its memory.

    Not in the paper. That low-pass filters ``y`` and every column of ``Phi`` alike, so ``y_f = Phi_f theta``
    holds for any sequence of regression samples, one left out included; restarting it instead starts it
    at steady state on the first sample after the interval, which then weighs like several (in a spin at
    full throttle, where one sample's noise is tens of mgauss of theta while J is still small, that moved
    theta by up to 14 mgauss in the hostile corpus). The prefilters on the inputs ("field", "inputs")
    filter signals in time and restart as after a reset.
    """
    return state._replace(initialized=False, dt_prev_s=math.nan)


def _anchor(
    state: ObserverState, field_b: Vec3, omega_b: Vec3, d2: float, p: ObserverParams
) -> ObserverState:
    """First sample after init, a reset or a skip: the model's previous sample; theta and J kept, and the
    regression low-pass's state as it is (None after init and a reset; kept by :func:`observer_skip`)."""
    lp = state.lp if p.prefilter == "regression" else None
    if p.prefilter == "field":
        lp = lowpass_init(field_b)
    elif p.prefilter == "inputs":
        lp = lowpass_init((*field_b, *omega_b, d2))
    return state._replace(
        v_hat_mgauss=field_b, field_prev_mgauss=field_b, omega_prev_rad_s=omega_b, omega_prev2_rad_s=omega_b,
        d2_prev=d2, dt_prev_s=math.nan, lp=lp, initialized=True,
    )


def _make_info(
    status: StepStatus, flags: int, innovation: Vec3, residual: float, g: Sym3, obs: tuple[Vec3, Bool3],
    converged: Bool3, std: Vec3,
) -> StepInfo:
    info_axis, observable = obs
    if not observable[2]:
        flags |= FLAG_Z_UNOBSERVABLE
    if converged[0] and converged[1] and converged[2]:
        flags |= FLAG_THETA_CONVERGED
    return _new(StepInfo, (status, flags, innovation, residual, info_axis, observable, converged, std, g))


def _held_info(state: ObserverState, p: ObserverParams, status: StepStatus, flags: int) -> StepInfo:
    """Info of a step that did not update theta (from the state's own Gramian and information)."""
    gw = state.gram_weight
    g: Sym3 = tuple(x / gw for x in state.gram_sum) if gw > 0.0 else (0.0,) * 6  # type: ignore[assignment]
    ji = sym3_inv(state.info)
    rv = state.resid_var
    std = (math.sqrt(ji[0] * rv), math.sqrt(ji[3] * rv), math.sqrt(ji[5] * rv))
    obs = _observability(g, p.excitation_min_rad2_s2)
    return _make_info(status, flags, _NAN3, math.nan, g, obs, state.converged, std)


def _prefilter_inputs(
    lp: LowPassState | None, v: Vec3, w: Vec3, d2: float, c: Biquad, p: ObserverParams
) -> tuple[LowPassState | None, Vec3, Vec3, float]:
    """Sec. II-D low-pass on the raw inputs: "field" alone (the paper; delays v but not omega: biased)
    or "inputs" (field, rate and throttle^2 alike). Other prefilters pass the inputs through."""
    if lp is None or p.prefilter not in ("field", "inputs"):
        return lp, v, w, d2
    if p.prefilter == "field":
        lp, y = biquad_step(c, lp, v)
        return lp, (y[0], y[1], y[2]), w, d2
    lp, y = biquad_step(c, lp, (*v, *w, d2))
    return lp, (y[0], y[1], y[2]), (y[3], y[4], y[5]), y[6]


def _prefilter_regression(
    lp: LowPassState | None, y: Vec3, phi: Mat3, c: Biquad, p: ObserverParams
) -> tuple[LowPassState | None, FloatSeq]:
    """The same LTI low-pass on y and on every column of Phi keeps ``y_f = Phi_f theta`` exact (sec. II-D,
    moved from the field to the regression: not in the paper). Returns the state and (y_f, Phi_f) as
    twelve numbers."""
    regs = (*y, *phi)
    if p.prefilter != "regression":
        return lp, regs
    return biquad_step(c, lowpass_init(regs) if lp is None else lp, regs)


def _excitation_update(
    state: ObserverState, phi_k: Mat3, dt_s: float, k: StepConstants, p: ObserverParams
) -> tuple[Sym3, float, Sym3, tuple[Vec3, Bool3], Bool3]:
    """Eq. (21): the exponentially windowed time average G of ``Phi^T Phi / dt^2`` (its sum and weight),
    the per-axis observability from it, and the axes on which theta is held for lack of excitation.

    The hold is not in the paper. On a truly unexcited axis the column of Phi is zero, so the update there
    is zero anyway; the hold guards against noise-driven drift. While the window holds less than half its
    length the Gramian is young (one sample of it is rank 2), so the hold waits for it, except when
    theta_hat started from a prior estimate (a stored theta): then an axis the young window does not see
    keeps that value rather than following a regression with almost no information (restart in flight).
    """
    q0, q1, q2, q3, q4, q5 = gram(phi_k)
    g0, g1, g2, g3, g4, g5 = state.gram_sum
    lam, r = k.lam_excitation, 1.0 / dt_s
    gs = (lam * g0 + q0 * r, lam * g1 + q1 * r, lam * g2 + q2 * r, lam * g3 + q3 * r, lam * g4 + q4 * r,
          lam * g5 + q5 * r)  # fmt: skip
    gw = lam * state.gram_weight + dt_s
    iw = 1.0 / gw
    g = (gs[0] * iw, gs[1] * iw, gs[2] * iw, gs[3] * iw, gs[4] * iw, gs[5] * iw)
    info_obs = _observability(g, p.excitation_min_rad2_s2)
    obs = info_obs[1]
    if gw < 0.5 * p.excitation_window_s and not state.theta_prior:
        return gs, gw, g, info_obs, (False, False, False)
    return gs, gw, g, info_obs, (not obs[0], not obs[1], not obs[2])


def _eq20b_increment(phi_k: Mat3, innovation: Vec3, p: ObserverParams) -> tuple[Vec3, int]:
    """Eq. (20b) discretised, ``-k2 Phi^T eps`` (-Phi^T ~ delta^2 [omega]_x dt), with k2 capped so that
    ``k2 |Phi_k|_2^2 <= 1`` (the discrete decrease of eq. (23); flagged as saturation)."""
    phi_norm2 = sym3_eigvals(gram(phi_k))[2]  # |Phi_k|_2^2
    k2, flags = p.k2, 0
    if k2 * phi_norm2 > 1.0:
        k2, flags = 1.0 / phi_norm2, FLAG_SATURATED
    gx, gy, gz = matTvec(phi_k, innovation)
    return (-k2 * gx, -k2 * gy, -k2 * gz), flags


def _estimate_update(
    state: ObserverState, a_k: Mat3, phi_k: Mat3, regs_f: FloatSeq, v1: Vec3, held: Bool3, k: StepConstants,
    p: ObserverParams,
) -> tuple[Vec3, Sym3, Sym3, float, Vec3, Vec3, int]:
    """theta_hat and v_hat over one step from the (filtered) regression ``regs_f = (y_f, Phi_f)``; returns
    (theta+, J+, J+^-1, |r|^2, innovation, v_hat+, flags).

    * RLS with regularised forgetting on ``y_f = Phi_f theta`` (scheme "regression"; not in the paper):
      ``J+ = lam J + (1 - lam) J_0 + Phi_f^T Phi_f``, ``theta+ = theta + J+^-1 Phi_f^T r`` with
      ``r = y_f - Phi_f theta``; or eq. (20b) discretised (scheme "observer", :func:`_eq20b_increment`).
      J is kept in both schemes.
    * theta held on the ``held`` axes and clipped to +-theta_max_mgauss (not in the paper).
    * eq. (20a), exact over the step: ``v_hat+ = v + exp(-k1 dt) (A_k v_hat + Phi_k theta+ - v)``; the
      innovation is the prediction error before the update, ``A_k v_hat + Phi_k theta - v``.
    Written out (no helper calls for the 3-vector algebra): this runs once per magnetometer sample.
    """
    t0, t1, t2 = state.theta_hat_mgauss
    y0, y1, y2, f0, f1, f2, f3, f4, f5, f6, f7, f8 = regs_f
    r0 = y0 - (f0 * t0 + f1 * t1 + f2 * t2)
    r1 = y1 - (f3 * t0 + f4 * t1 + f5 * t2)
    r2 = y2 - (f6 * t0 + f7 * t1 + f8 * t2)
    j, lam, j0 = state.info, k.lam_forget, k.info_regularise
    q = gram((f0, f1, f2, f3, f4, f5, f6, f7, f8))
    info = (lam * j[0] + q[0] + j0, lam * j[1] + q[1], lam * j[2] + q[2], lam * j[3] + q[3] + j0,
            lam * j[4] + q[4], lam * j[5] + q[5] + j0)  # fmt: skip
    ji = sym3_inv(info)
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a_k
    p0, p1, p2, p3, p4, p5, p6, p7, p8 = phi_k
    x, y, z = state.v_hat_mgauss
    av0, av1, av2 = a0 * x + a1 * y + a2 * z, a3 * x + a4 * y + a5 * z, a6 * x + a7 * y + a8 * z
    innovation = (av0 + p0 * t0 + p1 * t1 + p2 * t2 - v1[0], av1 + p3 * t0 + p4 * t1 + p5 * t2 - v1[1],
                  av2 + p6 * t0 + p7 * t1 + p8 * t2 - v1[2])  # fmt: skip
    flags = 0
    if p.scheme == "regression":
        g0, g1, g2 = f0 * r0 + f3 * r1 + f6 * r2, f1 * r0 + f4 * r1 + f7 * r2, f2 * r0 + f5 * r1 + f8 * r2
        d0 = ji[0] * g0 + ji[1] * g1 + ji[2] * g2
        d1 = ji[1] * g0 + ji[3] * g1 + ji[4] * g2
        d2 = ji[2] * g0 + ji[4] * g1 + ji[5] * g2
    else:
        (d0, d1, d2), flags = _eq20b_increment(phi_k, innovation, p)
    x0 = t0 if held[0] else t0 + d0
    x1 = t1 if held[1] else t1 + d1
    x2 = t2 if held[2] else t2 + d2
    m = p.theta_max_mgauss  # clip to +-m; NaN passes
    n0 = m if x0 > m else -m if x0 < -m else x0
    n1 = m if x1 > m else -m if x1 < -m else x1
    n2 = m if x2 > m else -m if x2 < -m else x2
    if n0 != x0 or n1 != x1 or n2 != x2:
        flags |= FLAG_SATURATED
    c = k.damping
    u0, u1, u2 = v1
    v_hat = (u0 + c * (av0 + p0 * n0 + p1 * n1 + p2 * n2 - u0),
             u1 + c * (av1 + p3 * n0 + p4 * n1 + p5 * n2 - u1),
             u2 + c * (av2 + p6 * n0 + p7 * n1 + p8 * n2 - u2))  # fmt: skip
    return (n0, n1, n2), info, ji, r0 * r0 + r1 * r1 + r2 * r2, innovation, v_hat, flags


def _convergence(
    state: ObserverState, obs: Bool3, resid_sq: float, info_inv: Sym3, theta: Vec3, dt_s: float, lam_e: float,
    p: ObserverParams,
) -> tuple[float, Vec3, Bool3, Vec3]:
    """Residual variance, excited time, per-axis convergence and 1-sigma of theta_hat (not in the paper)."""
    rv = lam_e * state.resid_var + (1.0 - lam_e) * resid_sq / 3.0
    e0, e1, e2 = state.excited_s
    ex = (e0 + (dt_s if obs[0] else 0.0), e1 + (dt_s if obs[1] else 0.0), e2 + (dt_s if obs[2] else 0.0))
    std = (math.sqrt(info_inv[0] * rv), math.sqrt(info_inv[3] * rv), math.sqrt(info_inv[5] * rv))
    tol = p.converge_std_mgauss + p.converge_rel * math.sqrt(theta[0] ** 2 + theta[1] ** 2 + theta[2] ** 2)
    need = p.converge_min_excited_s
    conv = (ex[0] >= need and std[0] <= tol, ex[1] >= need and std[1] <= tol, ex[2] >= need and std[2] <= tol)
    return rv, ex, conv, std


# --- discrete step --------------------------------------------------------------------------------------


def observer_step(
    state: ObserverState, omega_b_rad_s: Vec3Like, field_b_mgauss: Vec3Like, throttle_01: float,
    dt_s: float, p: ObserverParams,
) -> ObserverStep:
    """One step of the online theta estimator for a gyro + magnetometer + throttle sample.

    Parameters
    ----------
    state : from :func:`observer_init` or a previous step
    omega_b_rad_s : body rate at the sample time (3 numbers), rad/s, body FRD
    field_b_mgauss : calibrated (eq. (2)) field at the same time (3 numbers), mgauss, body
    throttle_01 : throttle command delta_t, 0..1, at the same time
    dt_s : time since the previous sample, s, from the source's timestamps
    p : parameters

    Guards: a non-finite input returns the state unchanged (status "non_finite", FLAG_INPUTS_STALE);
    dt outside [dt_min_s, dt_max_s] re-anchors on this sample and keeps theta (status
    "dt_out_of_range", FLAG_OBSERVER_RESET); theta_hat is clipped to +-theta_max_mgauss (FLAG_SATURATED).
    """
    o, f = omega_b_rad_s, field_b_mgauss  # the pipeline passes tuples of floats: no copy (0.3 us a step)
    w1: Vec3 = o if type(o) is tuple else (float(o[0]), float(o[1]), float(o[2]))  # type: ignore[assignment]
    v1: Vec3 = f if type(f) is tuple else (float(f[0]), float(f[1]), float(f[2]))  # type: ignore[assignment]
    delta, dt = float(throttle_01), float(dt_s)
    fin = math.isfinite
    if not (fin(w1[0]) and fin(w1[1]) and fin(w1[2]) and fin(v1[0]) and fin(v1[1]) and fin(v1[2])
            and fin(delta) and fin(dt)):  # fmt: skip
        return ObserverStep(state, _held_info(state, p, "non_finite", FLAG_INPUTS_STALE))
    d2 = (0.0 if delta < 0.0 else 1.0 if delta > 1.0 else delta) ** 2  # min(max(delta, 0), 1)^2
    if not (state.initialized and p.dt_min_s <= dt <= p.dt_max_s):
        # an interval out of range restarts the filters (the state after a skip or a reset is not initialised)
        new = _anchor(state._replace(lp=None) if state.initialized else state, v1, w1, d2, p)
        status: StepStatus = "dt_out_of_range" if state.initialized else "init"
        return ObserverStep(new, _held_info(new, p, status, FLAG_OBSERVER_RESET))
    k = p.step_constants(dt)
    lp = state.lp
    if lp is not None and p.prefilter != "regression":
        lp, v1, w1, d2 = _prefilter_inputs(lp, v1, w1, d2, k.lowpass, p)

    # exact discrete model, eqs. (13), (16), (18): v_{k+1} - d2_{k+1} theta = A_k (v_k - d2_k theta)
    ph = rotation_increment(state.omega_prev2_rad_s, state.omega_prev_rad_s, w1, state.dt_prev_s, dt,
                            p.rate_interp)  # fmt: skip
    a_k = dcm_from_rotvec((-ph[0], -ph[1], -ph[2]))  # A_k = dR_k^T
    phi_k = regressor(a_k, state.d2_prev, d2, p.variant)
    y_k = minus_matvec(v1, a_k, state.field_prev_mgauss)  # y_k = v_{k+1} - A_k v_k = Phi_k theta

    # excitation (eq. (21)) and the axes held for lack of it (not in the paper)
    gram_sum, gram_w, g, info_obs, held = _excitation_update(state, phi_k, dt, k, p)

    lp, regs_f = _prefilter_regression(lp, y_k, phi_k, k.lowpass, p)
    theta_new, info_new, info_inv, resid_sq, innovation, v_hat, flags = _estimate_update(
        state, a_k, phi_k, regs_f, v1, held, k, p
    )
    rv, excited, conv, std = _convergence(state, info_obs[1], resid_sq, info_inv, theta_new, dt,
                                          k.lam_excitation, p)
    if d2 < NO_THROTTLE_D2:
        flags |= FLAG_NO_THROTTLE
    fields = (v_hat, theta_new, info_new, gram_sum, gram_w, v1, w1, state.omega_prev_rad_s, d2, dt, lp, rv,
              excited, conv, True, state.n_steps + 1, state.theta_prior)  # ObserverState order; fmt: skip
    new = _new(ObserverState, fields)
    info = _make_info("ok", flags, innovation, math.sqrt(resid_sq), g, info_obs, conv, std)
    return _new(ObserverStep, (new, info))
