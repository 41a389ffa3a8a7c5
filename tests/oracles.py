"""Vectorised numpy forms of the per-sample core steps, kept as test oracles (two forms tested against
each other; the filterpy habit). The core writes each step once, on Python floats, because that is what
is fast at one call per sample; these forms write the same equations with numpy arrays and numpy's own
linear algebra (``inv``, ``eigvalsh``, ``cross``), so a slip in the hand-written float arithmetic shows.

Not used by the package. Equation numbers as in magcomp/core/observer.py.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from magcomp.core.mahony import MahonyParams
from magcomp.core.observer import NO_THROTTLE_D2, ObserverParams
from magcomp.core.types import (
    FLAG_INPUTS_STALE,
    FLAG_NO_THROTTLE,
    FLAG_OBSERVER_RESET,
    FLAG_SATURATED,
    FLAG_THETA_CONVERGED,
    FLAG_Z_UNOBSERVABLE,
)

F64 = NDArray[np.float64]


# --- rotations -------------------------------------------------------------------------------------------


def skew(w: F64) -> F64:
    x, y, z = w
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(phi: F64) -> F64:
    """Rodrigues with numpy matrices."""
    angle = float(np.linalg.norm(phi))
    k = skew(phi)
    if angle < 1e-8:
        return np.eye(3) + k + 0.5 * k @ k
    return np.eye(3) + (np.sin(angle) / angle) * k + ((1.0 - np.cos(angle)) / angle**2) * (k @ k)


def quat_mul(p: F64, q: F64) -> F64:
    pw, pv = p[0], p[1:]
    qw, qv = q[0], q[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def quat_step(q: F64, omega: F64, dt: float) -> F64:
    """q * exp(omega dt / 2), normalised."""
    phi = np.asarray(omega, dtype=float) * dt
    angle = float(np.linalg.norm(phi))
    if angle < 1e-12:
        dq = np.array([1.0, *(0.5 * phi)])
    else:
        dq = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * phi / angle])
    out = quat_mul(q, dq)
    return out / np.linalg.norm(out)


def dcm(q: F64) -> F64:
    """R_nb from q_nb through R = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]_x."""
    w, v = q[0], q[1:]
    return (w * w - v @ v) * np.eye(3) + 2.0 * np.outer(v, v) + 2.0 * w * skew(v)


# --- Mahony ----------------------------------------------------------------------------------------------


def mahony_update(q: F64, b: F64, gyro: F64, accel: F64, dt: float, p: MahonyParams) -> tuple[F64, F64, bool]:
    norm = float(np.linalg.norm(accel))
    used = bool(np.isfinite(norm) and abs(norm - p.gravity_m_s2) <= p.accel_gate_frac * p.gravity_m_s2)
    q_pred = quat_step(q, gyro - b, dt)
    if used:
        w_mes = np.cross(-accel / norm, dcm(q_pred)[2, :])
        q_new = quat_step(q_pred, p.kp * w_mes, dt)
    else:
        w_mes = np.zeros(3)
        q_new = q_pred
    b_new = np.clip(b - p.ki * w_mes * dt, -p.max_bias_rad_s, p.max_bias_rad_s)
    return q_new, b_new, used


# --- low-pass ------------------------------------------------------------------------------------------


def heading_deg(field_b: F64, roll: F64, pitch: F64) -> F64:
    """Tilt-compensated eq. (24) on arrays, (n, 3) fields and (n,) angles: the field de-rotated by the roll
    and pitch rotation matrices into the level frame, then ``atan2(-y, x)`` in [0, 360) deg."""
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    one, zero = np.ones_like(roll), np.zeros_like(roll)
    rows_x = ((one, zero, zero), (zero, cr, -sr), (zero, sr, cr))
    rows_y = ((cp, zero, sp), (zero, one, zero), (-sp, zero, cp))
    rx = np.stack([np.stack(r, -1) for r in rows_x], -2)
    ry = np.stack([np.stack(r, -1) for r in rows_y], -2)
    level = np.einsum("nij,njk,nk->ni", ry, rx, field_b)
    return np.asarray(np.mod(np.degrees(np.arctan2(-level[:, 1], level[:, 0])), 360.0), dtype=float)


def biquad_ba(corner_hz: float, order: int, dt: float) -> tuple[F64, F64]:
    fs = 1.0 / dt
    fc = min(corner_hz, 0.45 * fs)
    k = np.tan(np.pi * fc / fs)
    if order == 1:
        b0 = k / (1.0 + k)
        return np.array([b0, b0, 0.0]), np.array([1.0, (k - 1.0) / (k + 1.0), 0.0])
    q = 1.0 / np.sqrt(2.0)
    norm = 1.0 / (1.0 + k / q + k * k)
    b0 = k * k * norm
    a = np.array([1.0, 2.0 * (k * k - 1.0) * norm, (1.0 - k / q + k * k) * norm])
    return np.array([b0, 2 * b0, b0]), a


@dataclass(frozen=True)
class Lp:
    z: F64
    initialized: bool = False


def lp_step(st: Lp, x: F64, dt: float, p: ObserverParams) -> tuple[Lp, F64]:
    b, a = biquad_ba(p.lowpass.corner_hz, p.lowpass.order, dt)
    z = st.z if st.initialized else np.vstack([(b[1] + b[2] - a[1] - a[2]) * x, (b[2] - a[2]) * x])
    y = b[0] * x + z[0]
    return Lp(np.vstack([b[1] * x - a[1] * y + z[1], b[2] * x - a[2] * y]), True), y


# --- observer ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class State:
    v_hat: F64
    theta: F64
    info: F64
    gram_sum: F64
    gram_weight: float
    field_prev: F64
    w_prev: F64
    w_prev2: F64
    d2_prev: float
    dt_prev: float
    lp: Lp | None
    resid_var: float
    excited: F64
    converged: tuple[bool, bool, bool]
    initialized: bool = False
    prior: bool = False


@dataclass(frozen=True)
class Info:
    status: str
    flags: int
    residual_norm: float
    excitation_min: float
    observable: tuple[bool, bool, bool]


def init(p: ObserverParams, theta0: F64 | None = None) -> State:
    z = np.zeros(3)
    theta = np.zeros(3) if theta0 is None else np.asarray(theta0, dtype=float)
    return State(z, theta, p.info0 * np.eye(3), np.zeros((3, 3)), 0.0, z, z, z, 0.0, float("nan"), None, 0.0,
                 z, (False, False, False), prior=theta0 is not None)  # fmt: skip


def reset(st: State) -> State:
    return replace(st, initialized=False, lp=None, dt_prev=float("nan"))


def rotation_increment(wpp: F64, wp: F64, wn: F64, h0: float, h1: float, interp: str) -> F64:
    if interp == "hold":
        return wn * h1
    integral = 0.5 * h1 * (wp + wn)
    if interp == "quadratic" and np.isfinite(h0) and h0 > 0.0:
        c = (h0 * (wn - wp) + h1 * (wpp - wp)) / (h0 * h1 * (h0 + h1))
        b = (wn - wp) / h1 - c * h1
        integral = wp * h1 + b * (h1 * h1 / 2.0) + c * (h1**3 / 3.0)
    return integral + (h1 * h1 / 12.0) * np.cross(wp, wn)


def excitation(g: F64, min_info: float) -> tuple[float, tuple[bool, bool, bool]]:
    g = 0.5 * (g + g.T)
    lam = float(np.linalg.eigvalsh(g)[0])
    info = 1.0 / np.diag(np.linalg.inv(g + 1e-9 * max(float(np.trace(g)), 1e-12) * np.eye(3)))
    obs = info >= min_info
    return lam, (bool(obs[0]), bool(obs[1]), bool(obs[2]))


def _info(st: State, p: ObserverParams, status: str, flags: int, resid: float = float("nan")) -> Info:
    g = st.gram_sum / st.gram_weight if st.gram_weight > 0.0 else np.zeros((3, 3))
    lam, obs = excitation(g, p.excitation_min_rad2_s2)
    if not obs[2]:
        flags |= FLAG_Z_UNOBSERVABLE
    if all(st.converged):
        flags |= FLAG_THETA_CONVERGED
    return Info(status, flags, resid, lam, obs)


def _anchor(st: State, v: F64, w: F64, d2: float, p: ObserverParams) -> State:
    lp = None
    if p.prefilter == "field":
        lp = Lp(np.zeros((2, 3)))
    elif p.prefilter == "inputs":
        lp = Lp(np.zeros((2, 7)))
    return replace(st, v_hat=v, field_prev=v, w_prev=w, w_prev2=w, d2_prev=d2, dt_prev=float("nan"), lp=lp,
                   initialized=True)  # fmt: skip


def step(st: State, omega: F64, field: F64, thr: float, dt: float, p: ObserverParams) -> tuple[State, Info]:
    """The observer step of magcomp.core.observer on numpy arrays (one long function, as it was written)."""
    w1, v1 = np.asarray(omega, dtype=float), np.asarray(field, dtype=float)
    if not (np.all(np.isfinite(w1)) and np.all(np.isfinite(v1)) and np.isfinite(thr) and np.isfinite(dt)):
        return st, _info(st, p, "non_finite", FLAG_INPUTS_STALE)
    d2 = min(max(thr, 0.0), 1.0) ** 2
    if not st.initialized or not p.dt_min_s <= dt <= p.dt_max_s:
        new = _anchor(st, v1, w1, d2, p)
        return new, _info(new, p, "dt_out_of_range" if st.initialized else "init", FLAG_OBSERVER_RESET)
    lp = st.lp
    if p.prefilter == "field" and lp is not None:
        lp, v1 = lp_step(lp, v1, dt, p)
    elif p.prefilter == "inputs" and lp is not None:
        lp, out = lp_step(lp, np.concatenate([v1, w1, [d2]]), dt, p)
        v1, w1, d2 = out[:3], out[3:6], float(out[6])
    a_k = so3_exp(-rotation_increment(st.w_prev2, st.w_prev, w1, st.dt_prev, dt, p.rate_interp))
    if p.variant == "delta_dot":
        phi_k = d2 * np.eye(3) - st.d2_prev * a_k
    else:
        phi_k = 0.5 * (st.d2_prev + d2) * (np.eye(3) - a_k)
    y_k = v1 - a_k @ st.field_prev
    lam_e = float(np.exp(-dt / p.excitation_window_s))
    gram_sum = lam_e * st.gram_sum + phi_k.T @ phi_k / dt
    gram_w = lam_e * st.gram_weight + dt
    lam_min, obs = excitation(gram_sum / gram_w, p.excitation_min_rad2_s2)
    held = ~np.array(obs)
    if gram_w < 0.5 * p.excitation_window_s and not st.prior:
        held[:] = False
    y_f, phi_f = y_k, phi_k
    if p.prefilter == "regression":
        regs = np.concatenate([y_k, phi_k.ravel()])
        lp, out = lp_step(Lp(np.zeros((2, 12))) if lp is None else lp, regs, dt, p)
        y_f, phi_f = out[:3], out[3:].reshape(3, 3)
    resid = y_f - phi_f @ st.theta
    lam = float(np.exp(-dt / p.forget_s))
    info = lam * st.info + (1.0 - lam) * p.info0 * np.eye(3) + phi_f.T @ phi_f
    info_inv = np.linalg.inv(info)
    innovation = a_k @ st.v_hat + phi_k @ st.theta - v1
    flags = 0
    if p.scheme == "regression":
        d_theta = info_inv @ (phi_f.T @ resid)
    else:
        k2 = p.k2
        n2 = float(np.linalg.eigvalsh(phi_k.T @ phi_k)[-1])
        if k2 * n2 > 1.0:
            k2, flags = 1.0 / n2, FLAG_SATURATED
        d_theta = -k2 * (phi_k.T @ innovation)
    theta_new = st.theta + np.where(held, 0.0, d_theta)
    clipped = np.clip(theta_new, -p.theta_max_mgauss, p.theta_max_mgauss)
    if np.any(clipped != theta_new):
        flags |= FLAG_SATURATED
    c = float(np.exp(-p.k1_1_s * dt))
    v_hat = v1 + c * (a_k @ st.v_hat + phi_k @ clipped - v1)
    rv = lam_e * st.resid_var + (1.0 - lam_e) * float(resid @ resid) / 3.0
    excited = st.excited + np.where(obs, dt, 0.0)
    std = np.sqrt(np.diag(info_inv) * rv)
    conv = (excited >= p.converge_min_excited_s) & (
        std <= p.converge_std_mgauss + p.converge_rel * float(np.linalg.norm(clipped))
    )
    if d2 < NO_THROTTLE_D2:
        flags |= FLAG_NO_THROTTLE
    new = State(v_hat, clipped, info, gram_sum, gram_w, v1, w1, st.w_prev, d2, dt, lp, rv, excited,
                (bool(conv[0]), bool(conv[1]), bool(conv[2])), True, st.prior)  # fmt: skip
    if not obs[2]:
        flags |= FLAG_Z_UNOBSERVABLE
    if all(new.converged):
        flags |= FLAG_THETA_CONVERGED
    return new, Info("ok", flags, float(np.linalg.norm(resid)), lam_min, obs)


# --- in-flight estimator ----------------------------------------------------------------------------------


def variance_inflation_loop(
    batches: list[tuple[F64, F64, F64, int]], p: F64, c0: float, cov: F64 | None, s2: float
) -> float:
    """The batch-means variance inflation as a loop over the batches (c_b, M_b, g_b, n_b), each batch's
    residual sum and its white expectation in turn (what magcomp.core.inflight.ResidualBatches stacks)."""
    num = den = 0.0
    for c, m, g, n_b in batches:
        e = c - m @ p - g * c0
        num += float(e @ e) / n_b
        fit = 0.0 if cov is None else float(np.einsum("ij,jk,ik->", m, cov, m)) / n_b
        den += 3.0 * s2 - fit
    return max(1.0, num / den) if den > 0.0 else 1.0
