"""Scalar twins of the per-sample core steps, for the pipeline's hot path.

The core steps (:func:`magcomp.core.mahony.mahony_update`, :func:`magcomp.core.observer.observer_step`)
work on small numpy arrays; at one call per sample numpy's per-call overhead dominates (about 450 us per
observer step on this machine). These classes run the *same arithmetic* on Python floats, in the same
order where it matters, so their results agree with the core to rounding (tests/unit/test_fastpath.py
runs both side by side on the same streams). They are mutable shells: the pipeline owns one per
compass (observer) and one per vehicle (attitude), as PX4 modules own their library states.

Only the default observer configuration has a twin (scheme "regression", variant "delta_dot",
prefilter "regression", rate interpolation "quadratic"); any other ``[observer] form`` runs the core
step itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from magcomp.core.mahony import MahonyParams
from magcomp.core.observer import NO_THROTTLE_D2, ObserverParams, ObserverState
from magcomp.core.rotations import quat_step_body_rate
from magcomp.core.types import (
    FLAG_INPUTS_STALE,
    FLAG_NO_THROTTLE,
    FLAG_OBSERVER_RESET,
    FLAG_SATURATED,
    FLAG_THETA_CONVERGED,
    FLAG_Z_UNOBSERVABLE,
)

F64 = NDArray[np.float64]
Vec = list[float]


def supports(p: ObserverParams) -> bool:
    """True when :class:`FastObserver` reproduces ``observer_step`` for these parameters."""
    return (
        p.scheme == "regression"
        and p.variant == "delta_dot"
        and p.prefilter == "regression"
        and p.rate_interp == "quadratic"
    )


# ------------------------------------------------------------------------------------------ attitude


class FastMahony:
    """Twin of :func:`magcomp.core.mahony.mahony_update` (Mahony explicit complementary filter, ref. [23])."""

    __slots__ = ("b", "gate", "gravity", "ki", "kp", "max_b", "q")

    def __init__(self, p: MahonyParams, q_nb: F64, gyro_bias_b_rad_s: F64) -> None:
        self.kp, self.ki = p.kp, p.ki
        self.gravity = p.gravity_m_s2
        self.gate = p.accel_gate_frac * p.gravity_m_s2
        self.max_b = p.max_bias_rad_s
        self.q = [float(x) for x in q_nb]
        self.b = [float(x) for x in gyro_bias_b_rad_s]

    def down_b(self) -> Vec:
        """Third row of R_nb: the reference down vector in body axes (sec. II-A)."""
        w, x, y, z = self.q
        return [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)]

    def update(self, gx: float, gy: float, gz: float, ax: float, ay: float, az: float, dt: float) -> bool:
        """One step over ``dt`` s; returns whether the accelerometer passed the gate."""
        an = math.sqrt(ax * ax + ay * ay + az * az)
        used = math.isfinite(an) and abs(an - self.gravity) <= self.gate
        b0, b1, b2 = self.b
        q = quat_step_body_rate(self.q, (gx - b0, gy - b1, gz - b2), dt)  # predict, eq. (18)
        if used:
            w, x, y, z = q
            vx, vy, vz = -ax / an, -ay / an, -az / an  # measured down
            hx, hy, hz = 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)
            ex, ey, ez = vy * hz - vz * hy, vz * hx - vx * hz, vx * hy - vy * hx  # [23] v x v_hat
            kp = self.kp
            q = quat_step_body_rate(q, (kp * ex, kp * ey, kp * ez), dt)  # [23] correction
        else:
            ex = ey = ez = 0.0
        self.q = list(q)
        kd = self.ki * dt
        m = self.max_b
        b0, b1, b2 = b0 - kd * ex, b1 - kd * ey, b2 - kd * ez
        # clip to +-m (as min(max(b, -m), m))
        self.b = [
            m if b0 > m else -m if b0 < -m else b0,
            m if b1 > m else -m if b1 < -m else b1,
            m if b2 > m else -m if b2 < -m else b2,
        ]
        return used


# ------------------------------------------------------------------------------------- small algebra


def _inv3(m: Vec) -> Vec:
    """Inverse of a row-major 3x3 (9 floats) by cofactors."""
    a, b, c, d, e, f, g, h, i = m
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * c00 + b * c01 + c * c02
    r = 1.0 / det
    return [
        c00 * r, (c * h - b * i) * r, (b * f - c * e) * r,
        c01 * r, (a * i - c * g) * r, (c * d - a * f) * r,
        c02 * r, (b * g - a * h) * r, (a * e - b * d) * r,
    ]  # fmt: skip


def _sym_eig_min(a: float, b: float, c: float, e: float, f: float, i: float) -> float:
    """Smallest eigenvalue of the symmetric 3x3 [[a, b, c], [b, e, f], [c, f, i]] (closed form,
    trigonometric)."""
    p1 = b * b + c * c + f * f
    q = (a + e + i) / 3.0
    if p1 == 0.0:
        return min(a, e, i)
    p2 = (a - q) ** 2 + (e - q) ** 2 + (i - q) ** 2 + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    b00, b11, b22 = (a - q) / p, (e - q) / p, (i - q) / p
    b01, b02, b12 = b / p, c / p, f / p
    det_b = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    r = min(max(det_b / 2.0, -1.0), 1.0)
    phi = math.acos(r) / 3.0
    return q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)


def _excitation(gram: Vec, min_info: float) -> tuple[float, tuple[bool, bool, bool]]:
    """Twin of :func:`magcomp.core.observer.excitation` (smallest eigenvalue, per-axis observability)."""
    g = [
        gram[0], 0.5 * (gram[1] + gram[3]), 0.5 * (gram[2] + gram[6]),
        0.5 * (gram[3] + gram[1]), gram[4], 0.5 * (gram[5] + gram[7]),
        0.5 * (gram[6] + gram[2]), 0.5 * (gram[7] + gram[5]), gram[8],
    ]  # fmt: skip
    return _sym_eig_min(g[0], g[1], g[2], g[4], g[5], g[8]), _observable(
        g[0], g[1], g[2], g[4], g[5], g[8], min_info
    )


def _observable(
    a: float, b: float, c: float, e: float, f: float, i: float, min_info: float
) -> tuple[bool, bool, bool]:
    """Per-axis observability of :func:`_excitation` for the symmetric Gramian [[a, b, c], [b, e, f],
    [c, f, i]] given by its upper triangle: the same arithmetic as the cofactor inverse of :func:`_inv3`,
    diagonal only."""
    reg = 1e-9 * max(a + e + i, 1e-12)
    a, e, i = a + reg, e + reg, i + reg
    c00 = e * i - f * f
    r = 1.0 / (a * c00 + b * (f * c - b * i) + c * (b * f - e * c))
    gi0, gi4, gi8 = c00 * r, (a * i - c * c) * r, (a * e - b * b) * r
    return 1.0 / gi0 >= min_info, 1.0 / gi4 >= min_info, 1.0 / gi8 >= min_info


def _lowpass_coefficients(corner_hz: float, order: int, dt: float) -> tuple[float, ...]:
    """(b0, b1, b2, a1, a2) of :func:`magcomp.core.lowpass._coefficients`."""
    fs = 1.0 / dt
    fc = min(corner_hz, 0.45 * fs)
    k = math.tan(math.pi * fc / fs)
    if order == 1:
        b0 = k / (1.0 + k)
        return b0, b0, 0.0, (k - 1.0) / (k + 1.0), 0.0
    qf = 1.0 / math.sqrt(2.0)
    norm = 1.0 / (1.0 + k / qf + k * k)
    b0 = k * k * norm
    return b0, 2.0 * b0, b0, 2.0 * (k * k - 1.0) * norm, (1.0 - k / qf + k * k) * norm


# -------------------------------------------------------------------------------------------- observer


class FastStepInfo:
    """What one step reports. ``excitation`` (smallest eigenvalue of the normalised Gramian) is only
    output, so a step may leave it as the Gramian's upper triangle, solved on first read."""

    __slots__ = ("_exc", "_gram", "converged", "flags", "residual_norm_mgauss", "status", "z_unobservable")

    def __init__(
        self,
        status: str,
        flags: int,
        converged: bool,
        z_unobs: bool,
        resid: float,
        exc: float,
        gram_upper: tuple[float, float, float, float, float, float] | None = None,
    ) -> None:
        self.status = status
        self.flags = flags
        self.converged = converged
        self.z_unobservable = z_unobs
        self.residual_norm_mgauss = resid
        self._exc = exc
        self._gram = gram_upper

    @property
    def excitation(self) -> float:
        if self._gram is not None:
            self._exc = _sym_eig_min(*self._gram)
            self._gram = None
        return self._exc

    @property
    def saturated(self) -> bool:
        """theta-hat hit ``theta_max_mgauss`` on some axis in this step."""
        return bool(self.flags & FLAG_SATURATED)


class FastObserver:
    """Twin of :func:`magcomp.core.observer.observer_step` for the default parameters (see :func:`supports`).

    Holds the same state as :class:`~magcomp.core.observer.ObserverState` in Python floats;
    :meth:`to_state` / :meth:`from_state` convert, so a run can switch between the two at any sample.
    """

    def __init__(self, p: ObserverParams, state: ObserverState) -> None:
        if not supports(p):
            raise ValueError("FastObserver only covers the default observer configuration")
        self.p = p
        self._consts: dict[float, tuple[float, ...]] = {}
        self.from_state(state)

    # -- conversion --------------------------------------------------------------------------------
    def from_state(self, s: ObserverState) -> None:
        def v(a: F64) -> Vec:
            return [float(x) for x in np.asarray(a, dtype=float).ravel()]

        self.v_hat = v(s.v_hat_mgauss)
        self.theta = v(s.theta_hat_mgauss)
        self.info = v(s.info)
        self.gram = v(s.gram_sum)
        self.gram_w = float(s.gram_weight)
        self.field_prev = v(s.field_prev_mgauss)
        self.w_prev = v(s.omega_prev_rad_s)
        self.w_prev2 = v(s.omega_prev2_rad_s)
        self.d2_prev = float(s.d2_prev)
        self.dt_prev = float(s.dt_prev_s)
        if s.lp is None:
            self.lp_z: Vec | None = None
            self.lp_init = False
        else:
            self.lp_z = v(s.lp.z)  # (2, 12) row-major: z1[0..11], z2[0..11]
            self.lp_init = bool(s.lp.initialized)
        self.resid_var = float(s.resid_var)
        self.excited = v(s.excited_s)
        self.converged = tuple(bool(c) for c in s.converged)
        self.initialized = bool(s.initialized)
        self.n_steps = int(s.n_steps)

    def to_state(self) -> ObserverState:
        from magcomp.core.lowpass import LowPassState

        lp = None
        if self.lp_z is not None:
            lp = LowPassState(z=np.array(self.lp_z).reshape(2, 12), initialized=self.lp_init)
        c = self.converged
        return ObserverState(
            v_hat_mgauss=np.array(self.v_hat), theta_hat_mgauss=np.array(self.theta),
            info=np.array(self.info).reshape(3, 3), gram_sum=np.array(self.gram).reshape(3, 3),
            gram_weight=self.gram_w, field_prev_mgauss=np.array(self.field_prev),
            omega_prev_rad_s=np.array(self.w_prev), omega_prev2_rad_s=np.array(self.w_prev2),
            d2_prev=self.d2_prev, dt_prev_s=self.dt_prev, lp=lp, resid_var=self.resid_var,
            excited_s=np.array(self.excited), converged=(c[0], c[1], c[2]), initialized=self.initialized,
            n_steps=self.n_steps,
        )  # fmt: skip

    def reset(self) -> None:
        """Twin of ``observer_reset(state, p, keep_theta=True)``."""
        self.initialized = False
        self.lp_z = None
        self.lp_init = False
        self.dt_prev = float("nan")

    # -- info ----------------------------------------------------------------------------------------
    def _info(
        self, status: str, flags: int, resid: float, exc: tuple[float, tuple[bool, bool, bool]] | None = None
    ) -> FastStepInfo:
        if exc is not None:  # the step's own excitation: the same Gramian
            lam_min, obs = exc
        elif self.gram_w > 0.0:
            gw = self.gram_w
            lam_min, obs = _excitation([x / gw for x in self.gram], self.p.excitation_min_rad2_s2)
        else:
            lam_min, obs = _excitation([0.0] * 9, self.p.excitation_min_rad2_s2)
        if not obs[2]:
            flags |= 32  # FLAG_Z_UNOBSERVABLE
        conv = all(self.converged)
        if conv:
            flags |= 2  # FLAG_THETA_CONVERGED
        return FastStepInfo(status, flags, conv, not obs[2], resid, lam_min)

    def _anchor(self, field: Sequence[float], omega: Sequence[float], d2: float) -> None:
        self.v_hat = list(field)
        self.field_prev = list(field)
        self.w_prev = list(omega)
        self.w_prev2 = list(omega)
        self.d2_prev = d2
        self.dt_prev = float("nan")
        self.lp_z = None
        self.lp_init = False
        self.initialized = True

    def _step_constants(self, dt: float) -> tuple[float, ...]:
        """Everything of a step that depends on ``dt`` alone (exponentials, the low-pass coefficients).
        A steady sample rate repeats a few ``dt`` values, so they are cached by ``dt``."""
        k = self._consts.get(dt)
        if k is None:
            p = self.p
            lam = math.exp(-dt / p.forget_s)
            k = (
                dt * dt / 12.0,  # coning term
                math.exp(-dt / p.excitation_window_s),
                lam,
                (1.0 - lam) * p.info0,
                math.exp(-p.k1_1_s * dt),
                *_lowpass_coefficients(p.lowpass.corner_hz, p.lowpass.order, dt),
            )
            if len(self._consts) >= 64:  # jittery timestamps: keep the cache small
                self._consts.clear()
            self._consts[dt] = k
        return k

    # -- the step ----------------------------------------------------------------------------------
    def step(
        self, omega: Sequence[float], field: Sequence[float], throttle_01: float, dt: float
    ) -> FastStepInfo:
        p = self.p
        w1x, w1y, w1z = omega
        v1x, v1y, v1z = field
        fin = math.isfinite
        if not (fin(w1x) and fin(w1y) and fin(w1z) and fin(v1x) and fin(v1y) and fin(v1z)
                and fin(throttle_01) and fin(dt)):  # fmt: skip
            return self._info("non_finite", FLAG_INPUTS_STALE, float("nan"))
        d2 = min(max(throttle_01, 0.0), 1.0) ** 2
        if not self.initialized:
            self._anchor(field, omega, d2)
            return self._info("init", FLAG_OBSERVER_RESET, float("nan"))
        if not p.dt_min_s <= dt <= p.dt_max_s:
            self._anchor(field, omega, d2)
            return self._info("dt_out_of_range", FLAG_OBSERVER_RESET, float("nan"))
        k12, lam_e, lam, j0, c, b0, b1, b2, fa1, fa2 = self._step_constants(dt)

        v0x, v0y, v0z = self.field_prev
        d2_0 = self.d2_prev
        wpx, wpy, wpz = self.w_prev
        # rotation over the step: quadratic through three gyro samples + coning (rotation_increment)
        h0 = self.dt_prev
        if math.isfinite(h0) and h0 > 0.0:
            h1 = dt
            w2x, w2y, w2z = self.w_prev2
            den = h0 * h1 * (h0 + h1)
            cx = (h0 * (w1x - wpx) + h1 * (w2x - wpx)) / den
            cy = (h0 * (w1y - wpy) + h1 * (w2y - wpy)) / den
            cz = (h0 * (w1z - wpz) + h1 * (w2z - wpz)) / den
            bx, by, bz = (w1x - wpx) / h1 - cx * h1, (w1y - wpy) / h1 - cy * h1, (w1z - wpz) / h1 - cz * h1
            hh2, hh3 = h1 * h1 / 2.0, h1**3 / 3.0
            ix = wpx * h1 + bx * hh2 + cx * hh3
            iy = wpy * h1 + by * hh2 + cy * hh3
            iz = wpz * h1 + bz * hh2 + cz * hh3
        else:  # trapezoid
            ix, iy, iz = 0.5 * dt * (wpx + w1x), 0.5 * dt * (wpy + w1y), 0.5 * dt * (wpz + w1z)
        px = ix + k12 * (wpy * w1z - wpz * w1y)
        py = iy + k12 * (wpz * w1x - wpx * w1z)
        pz = iz + k12 * (wpx * w1y - wpy * w1x)
        # A_k = so3_exp(-phi) (Rodrigues, as magcomp.core.rotations.so3_exp)
        kx, ky, kz = -px, -py, -pz
        ang = math.sqrt(kx * kx + ky * ky + kz * kz)
        if ang < 1e-8:
            s1, s2 = 1.0, 0.5
        else:
            s1, s2 = math.sin(ang) / ang, (1.0 - math.cos(ang)) / ang**2
        kxx, kyy, kzz = kx * kx, ky * ky, kz * kz
        kxy, kxz, kyz = kx * ky, kx * kz, ky * kz
        a00, a01, a02 = 1.0 + s2 * (-kyy - kzz), -s1 * kz + s2 * kxy, s1 * ky + s2 * kxz
        a10, a11, a12 = s1 * kz + s2 * kxy, 1.0 + s2 * (-kxx - kzz), -s1 * kx + s2 * kyz
        a20, a21, a22 = -s1 * ky + s2 * kxz, s1 * kx + s2 * kyz, 1.0 + s2 * (-kxx - kyy)
        # Phi_k = d2_1 I - d2_0 A_k (exact discrete eq. (16)); y_k = v1 - A_k v0
        ph = [
            d2 - d2_0 * a00, -d2_0 * a01, -d2_0 * a02,
            -d2_0 * a10, d2 - d2_0 * a11, -d2_0 * a12,
            -d2_0 * a20, -d2_0 * a21, d2 - d2_0 * a22,
        ]  # fmt: skip
        yx = v1x - (a00 * v0x + a01 * v0y + a02 * v0z)
        yy = v1y - (a10 * v0x + a11 * v0y + a12 * v0z)
        yz = v1z - (a20 * v0x + a21 * v0y + a22 * v0z)
        # excitation Gramian, eq. (21) (written out: comprehensions and helper calls cost more than the
        # arithmetic here); Phi^T Phi is symmetric: six products
        p0, p1, p2, p3, p4, p5, p6, p7, p8 = ph
        q0 = p0 * p0 + p3 * p3 + p6 * p6
        q1 = p0 * p1 + p3 * p4 + p6 * p7
        q2 = p0 * p2 + p3 * p5 + p6 * p8
        q4 = p1 * p1 + p4 * p4 + p7 * p7
        q5 = p1 * p2 + p4 * p5 + p7 * p8
        q8 = p2 * p2 + p5 * p5 + p8 * p8
        g0, g1, g2, g3, g4, g5, g6, g7, g8 = self.gram
        g0, g1, g2 = lam_e * g0 + q0 / dt, lam_e * g1 + q1 / dt, lam_e * g2 + q2 / dt
        g3, g4, g5 = lam_e * g3 + q1 / dt, lam_e * g4 + q4 / dt, lam_e * g5 + q5 / dt
        g6, g7, g8 = lam_e * g6 + q2 / dt, lam_e * g7 + q5 / dt, lam_e * g8 + q8 / dt
        self.gram = [g0, g1, g2, g3, g4, g5, g6, g7, g8]
        gw = lam_e * self.gram_w + dt
        self.gram_w = gw
        g_upper = (
            g0 / gw, 0.5 * (g1 / gw + g3 / gw), 0.5 * (g2 / gw + g6 / gw),
            g4 / gw, 0.5 * (g5 / gw + g7 / gw), g8 / gw,
        )  # fmt: skip
        obs0, obs1, obs2 = _observable(*g_upper, p.excitation_min_rad2_s2)
        # 5 Hz low-pass on y and on every column of Phi alike (regression prefilter): biquad, direct form II
        # transposed, 12 channels; lp_z holds z1 (12) then z2 (12). Written out channel by channel: a loop
        # or comprehensions take twice as long as this arithmetic.
        z = self.lp_z
        if z is None or not self.lp_init:
            regs = [yx, yy, yz, *ph]
            c1, c2 = b1 + b2 - fa1 - fa2, b2 - fa2
            z = [c1 * x for x in regs] + [c2 * x for x in regs]
        yfx, yfy, yfz = b0 * yx + z[0], b0 * yy + z[1], b0 * yz + z[2]
        f0, f1, f2 = b0 * p0 + z[3], b0 * p1 + z[4], b0 * p2 + z[5]
        f3, f4, f5 = b0 * p3 + z[6], b0 * p4 + z[7], b0 * p5 + z[8]
        f6, f7, f8 = b0 * p6 + z[9], b0 * p7 + z[10], b0 * p8 + z[11]
        self.lp_z = [
            b1 * yx - fa1 * yfx + z[12], b1 * yy - fa1 * yfy + z[13], b1 * yz - fa1 * yfz + z[14],
            b1 * p0 - fa1 * f0 + z[15], b1 * p1 - fa1 * f1 + z[16], b1 * p2 - fa1 * f2 + z[17],
            b1 * p3 - fa1 * f3 + z[18], b1 * p4 - fa1 * f4 + z[19], b1 * p5 - fa1 * f5 + z[20],
            b1 * p6 - fa1 * f6 + z[21], b1 * p7 - fa1 * f7 + z[22], b1 * p8 - fa1 * f8 + z[23],
            b2 * yx - fa2 * yfx, b2 * yy - fa2 * yfy, b2 * yz - fa2 * yfz,
            b2 * p0 - fa2 * f0, b2 * p1 - fa2 * f1, b2 * p2 - fa2 * f2,
            b2 * p3 - fa2 * f3, b2 * p4 - fa2 * f4, b2 * p5 - fa2 * f5,
            b2 * p6 - fa2 * f6, b2 * p7 - fa2 * f7, b2 * p8 - fa2 * f8,
        ]  # fmt: skip
        self.lp_init = True
        th0, th1, th2 = self.theta
        rx = yfx - (f0 * th0 + f1 * th1 + f2 * th2)
        ry = yfy - (f3 * th0 + f4 * th1 + f5 * th2)
        rz = yfz - (f6 * th0 + f7 * th1 + f8 * th2)
        j_0, j_1, j_2, j_3, j_4, j_5, j_6, j_7, j_8 = self.info
        # J = lam J + Phi_f^T Phi_f + (1 - lam) J0 I
        q0 = f0 * f0 + f3 * f3 + f6 * f6
        q1 = f0 * f1 + f3 * f4 + f6 * f7
        q2 = f0 * f2 + f3 * f5 + f6 * f8
        q4 = f1 * f1 + f4 * f4 + f7 * f7
        q5 = f1 * f2 + f4 * f5 + f7 * f8
        q8 = f2 * f2 + f5 * f5 + f8 * f8
        info_new = [
            lam * j_0 + q0 + j0, lam * j_1 + q1, lam * j_2 + q2,
            lam * j_3 + q1, lam * j_4 + q4 + j0, lam * j_5 + q5,
            lam * j_6 + q2, lam * j_7 + q5, lam * j_8 + q8 + j0,
        ]  # fmt: skip
        # RLS with regularised forgetting: d_theta = J^-1 Phi_f^T r
        gx = f0 * rx + f3 * ry + f6 * rz
        gy = f1 * rx + f4 * ry + f7 * rz
        gz = f2 * rx + f5 * ry + f8 * rz
        ji = _inv3(info_new)
        flags = 0
        tmax = p.theta_max_mgauss
        # hold unexcited axes
        t0 = th0 + (ji[0] * gx + ji[1] * gy + ji[2] * gz if obs0 else 0.0)
        t1 = th1 + (ji[3] * gx + ji[4] * gy + ji[5] * gz if obs1 else 0.0)
        t2 = th2 + (ji[6] * gx + ji[7] * gy + ji[8] * gz if obs2 else 0.0)
        # clip to +-tmax (as min(max(x, -tmax), tmax), NaN passing through)
        t0n = tmax if t0 > tmax else -tmax if t0 < -tmax else t0
        t1n = tmax if t1 > tmax else -tmax if t1 < -tmax else t1
        t2n = tmax if t2 > tmax else -tmax if t2 < -tmax else t2
        if t0n != t0 or t1n != t1 or t2n != t2:
            flags |= FLAG_SATURATED
        vh0, vh1, vh2 = self.v_hat
        pv0 = a00 * vh0 + a01 * vh1 + a02 * vh2 + p0 * t0n + p1 * t1n + p2 * t2n
        pv1 = a10 * vh0 + a11 * vh1 + a12 * vh2 + p3 * t0n + p4 * t1n + p5 * t2n
        pv2 = a20 * vh0 + a21 * vh1 + a22 * vh2 + p6 * t0n + p7 * t1n + p8 * t2n
        self.v_hat = [v1x + c * (pv0 - v1x), v1y + c * (pv1 - v1y), v1z + c * (pv2 - v1z)]
        rr = rx * rx + ry * ry + rz * rz
        rv = lam_e * self.resid_var + (1.0 - lam_e) * rr / 3.0
        self.resid_var = rv
        e0, e1, e2 = self.excited
        e0, e1, e2 = e0 + (dt if obs0 else 0.0), e1 + (dt if obs1 else 0.0), e2 + (dt if obs2 else 0.0)
        self.excited = [e0, e1, e2]
        tol = p.converge_std_mgauss + p.converge_rel * math.sqrt(t0n * t0n + t1n * t1n + t2n * t2n)
        need_s = p.converge_min_excited_s
        conv = (
            e0 >= need_s and math.sqrt(ji[0] * rv) <= tol,
            e1 >= need_s and math.sqrt(ji[4] * rv) <= tol,
            e2 >= need_s and math.sqrt(ji[8] * rv) <= tol,
        )
        self.converged = conv
        if d2 < NO_THROTTLE_D2:
            flags |= FLAG_NO_THROTTLE
        self.theta = [t0n, t1n, t2n]
        self.info = info_new
        self.field_prev = [v1x, v1y, v1z]
        self.w_prev2 = self.w_prev
        self.w_prev = [w1x, w1y, w1z]
        self.d2_prev = d2
        self.dt_prev = dt
        self.n_steps += 1
        # the step's info (as _info, with the step's own excitation)
        if not obs2:
            flags |= FLAG_Z_UNOBSERVABLE
        all_conv = conv[0] and conv[1] and conv[2]
        if all_conv:
            flags |= FLAG_THETA_CONVERGED
        return FastStepInfo("ok", flags, all_conv, not obs2, math.sqrt(rr), math.nan, g_upper)
