"""Rotations with one convention: scalar-first quaternions ``(w, x, y, z)``, ``q_nb`` body FRD -> NED.

``dcm_from_quat(q_nb)`` returns ``R_nb`` with ``v_n = R_nb @ v_b``. In the paper's notation this is
``R = R_b^e`` of eq. (13); the earth-to-body matrix ``R_e^b`` of section II-A is ``R_nb.T`` and its third
column, the reference "down" vector of the DPI calibration, is ``down_b = R_nb.T @ [0, 0, 1]``.

Euler angles are the aerospace ZYX sequence (yaw, pitch, roll) used by MAVLink ATTITUDE.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


def skew(w: ArrayLike) -> F64:
    """Cross-product matrix ``[w]_x`` of eq. (17): ``skew(w) @ v == np.cross(w, v)``."""
    x, y, z = np.asarray(w, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def quat_normalize(q: ArrayLike) -> F64:
    q = np.asarray(q, dtype=float)
    n = float(np.linalg.norm(q))
    if n == 0.0:
        raise ValueError("zero quaternion")
    out = q / n
    return out if out[0] >= 0.0 else -out


def quat_multiply(p: ArrayLike, q: ArrayLike) -> F64:
    """Hamilton product ``p * q`` (scalar first)."""
    pw, px, py, pz = np.asarray(p, dtype=float)
    qw, qx, qy, qz = np.asarray(q, dtype=float)
    return np.array(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def quats_multiply(p: ArrayLike, q: ArrayLike) -> F64:
    """Row-wise Hamilton products ``p[k] * q[k]`` of (n, 4) arrays: the vectorised :func:`quat_multiply`."""
    pa = np.asarray(p, dtype=float)
    qa = np.asarray(q, dtype=float)
    pw, px, py, pz = pa[:, 0], pa[:, 1], pa[:, 2], pa[:, 3]
    qw, qx, qy, qz = qa[:, 0], qa[:, 1], qa[:, 2], qa[:, 3]
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=1,
    )


def quat_conj(q: ArrayLike) -> F64:
    w, x, y, z = np.asarray(q, dtype=float)
    return np.array([w, -x, -y, -z])


def dcm_from_quat(q_nb: ArrayLike) -> F64:
    """``R_nb`` (3x3) from a unit quaternion ``q_nb`` (w, x, y, z)."""
    w, x, y, z = np.asarray(q_nb, dtype=float)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def dcms_from_quats(q_nb: ArrayLike) -> F64:
    """``R_nb`` for each row of ``q_nb`` (n, 4) -> (n, 3, 3): the vectorised :func:`dcm_from_quat`."""
    q = np.asarray(q_nb, dtype=float)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((q.shape[0], 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def quat_from_dcm(r_nb: ArrayLike) -> F64:
    """Unit quaternion ``q_nb`` from ``R_nb`` (Shepperd's method, numerically safe)."""
    m = np.asarray(r_nb, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    return quat_normalize(q)


def dcm_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> F64:
    """``R_nb`` from ZYX Euler angles: ``R_nb = Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def euler_from_dcm(r_nb: ArrayLike) -> tuple[float, float, float]:
    """ZYX Euler angles (roll, pitch, yaw) in rad from ``R_nb``; yaw in (-pi, pi]."""
    m = np.asarray(r_nb, dtype=float)
    pitch = float(-np.arcsin(np.clip(m[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(m[2, 1], m[2, 2]))
    yaw = float(np.arctan2(m[1, 0], m[0, 0]))
    return roll, pitch, yaw


def quat_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> F64:
    return quat_from_dcm(dcm_from_euler(roll_rad, pitch_rad, yaw_rad))


def euler_from_quat(q_nb: ArrayLike) -> tuple[float, float, float]:
    return euler_from_dcm(dcm_from_quat(q_nb))


def euler_from_dcms(r_nb: ArrayLike) -> F64:
    """ZYX Euler angles (roll, pitch, yaw) rad for each ``R_nb`` of (n, 3, 3) -> (n, 3); yaw in (-pi, pi].

    The vectorised :func:`euler_from_dcm`.
    """
    r = np.asarray(r_nb, dtype=float)
    roll = np.arctan2(r[:, 2, 1], r[:, 2, 2])
    pitch = -np.arcsin(np.clip(r[:, 2, 0], -1.0, 1.0))
    yaw = np.arctan2(r[:, 1, 0], r[:, 0, 0])
    return np.stack([roll, pitch, yaw], axis=1)


def euler_from_quats(q_nb: ArrayLike) -> F64:
    """ZYX Euler angles (roll, pitch, yaw) rad for each row of ``q_nb`` (n, 4) -> (n, 3): the vectorised
    :func:`euler_from_quat`."""
    return euler_from_dcms(dcms_from_quats(q_nb))


def quats_from_euler(roll_rad: ArrayLike, pitch_rad: ArrayLike, yaw_rad: ArrayLike) -> F64:
    """``q_nb`` (n, 4) from ZYX Euler angle arrays (n,): the same rotations as :func:`quat_from_euler`, in
    closed form. Unlike the scalar function the sign is not normalised to ``w >= 0``, so a smooth angle path
    gives a smooth quaternion path."""
    roll = np.asarray(roll_rad, dtype=float)
    pitch = np.asarray(pitch_rad, dtype=float)
    yaw = np.asarray(yaw_rad, dtype=float)
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=1,
    )


def so3_exp(phi: ArrayLike) -> F64:
    """Exponential map so(3) -> SO(3) (Rodrigues): the rotation by angle |phi| about phi/|phi|."""
    phi = np.asarray(phi, dtype=float)
    angle = float(np.linalg.norm(phi))
    k = skew(phi)
    if angle < 1e-8:
        return np.eye(3) + k + 0.5 * k @ k
    return np.eye(3) + (np.sin(angle) / angle) * k + ((1.0 - np.cos(angle)) / angle**2) * (k @ k)


def so3_log(r: ArrayLike) -> F64:
    """Logarithm SO(3) -> so(3) as a rotation vector (inverse of :func:`so3_exp` for angles < pi)."""
    m = np.asarray(r, dtype=float)
    cos_a = np.clip((np.trace(m) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.arccos(cos_a))
    vee = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    if angle < 1e-8:
        return 0.5 * vee
    if np.pi - angle < 1e-6:
        # near pi: axis from the symmetric part
        b = (m + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diag(b), 0.0, None))
        i = int(np.argmax(axis))
        axis = b[:, i] / np.sqrt(b[i, i])
        return angle * axis / np.linalg.norm(axis)
    return angle / (2.0 * np.sin(angle)) * vee


def quat_exp(phi: ArrayLike) -> F64:
    """Quaternion of the rotation vector ``phi`` (rad)."""
    phi = np.asarray(phi, dtype=float)
    angle = float(np.linalg.norm(phi))
    if angle < 1e-12:
        return quat_normalize(np.array([1.0, 0.5 * phi[0], 0.5 * phi[1], 0.5 * phi[2]]))
    axis = phi / angle
    return np.concatenate([[np.cos(angle / 2.0)], np.sin(angle / 2.0) * axis])


def quat_integrate_body_rate(q_nb: ArrayLike, omega_b_rad_s: ArrayLike, dt_s: float) -> F64:
    """Exact attitude update for a body rate held constant over ``dt_s``: ``q <- q * exp(omega dt)``.

    Implements the strap-down equation (18), ``R_dot = R [omega]_x``, in closed form.
    """
    dq = quat_exp(np.asarray(omega_b_rad_s, dtype=float) * dt_s)
    out = quat_multiply(q_nb, dq)
    return out / np.linalg.norm(out)


def down_b_from_quat(q_nb: ArrayLike) -> F64:
    """Unit 'down' vector in body axes: third column of ``R_e^b`` (section II-A reference vector)."""
    return dcm_from_quat(q_nb)[2, :].copy()


def quat_step_body_rate(
    q_nb: Sequence[float], omega_b_rad_s: Sequence[float], dt_s: float
) -> tuple[float, float, float, float]:
    """One step of ``q_dot = q (x) (0, omega / 2)`` on plain floats, normalised: the exact rotation for a
    body rate constant over ``dt_s`` (eq. (18); the per-sample path of the Mahony filter and the pipeline's
    gyro integral; the vectorised :func:`quat_integrate_body_rate` is its test oracle)."""
    wx, wy, wz = omega_b_rad_s[0], omega_b_rad_s[1], omega_b_rad_s[2]
    rate = math.sqrt(wx * wx + wy * wy + wz * wz)
    half = 0.5 * rate * dt_s
    if rate > 1e-12:
        s_ = math.sin(half) / rate
        dw, dx, dy, dz = math.cos(half), wx * s_, wy * s_, wz * s_
    else:
        dw, dx, dy, dz = 1.0, 0.5 * wx * dt_s, 0.5 * wy * dt_s, 0.5 * wz * dt_s
    w, x, y, z = q_nb[0], q_nb[1], q_nb[2], q_nb[3]
    qw = w * dw - x * dx - y * dy - z * dz
    qx = w * dx + x * dw + y * dz - z * dy
    qy = w * dy - x * dz + y * dw + z * dx
    qz = w * dz + x * dy - y * dx + z * dw
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return (qw / n, qx / n, qy / n, qz / n)
