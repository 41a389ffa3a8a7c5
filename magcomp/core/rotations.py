"""Rotations with one convention: scalar-first quaternions ``(w, x, y, z)``, ``q_nb`` body FRD -> NED.

``dcm_from_quat(q_nb)`` returns ``R_nb`` with ``v_n = R_nb @ v_b``. In the paper's notation this is
``R = R_b^e`` of eq. (13); the earth-to-body matrix ``R_e^b`` of section II-A is ``R_nb.T`` and its third
column, the reference "down" vector of the DPI calibration, is ``down_b = R_nb.T @ [0, 0, 1]``.

Euler angles are the aerospace ZYX sequence (yaw, pitch, roll) used by MAVLink ATTITUDE.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.linalg3 import FloatSeq, Mat3, Vec3

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation as RotationT

F64 = NDArray[np.float64]


def _rotation() -> type[RotationT]:
    """scipy's Rotation, imported on first use: ``scipy.spatial`` costs 0.17 s of start-up, and the
    per-sample path (which every command runs) does not need it."""
    from scipy.spatial.transform import Rotation

    return Rotation


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
    """Hamilton product ``p * q`` (scalar first): :func:`quats_multiply` of one pair."""
    return quats_multiply(np.asarray(p, dtype=float)[None, :], np.asarray(q, dtype=float)[None, :])[0]


def quats_multiply(p: ArrayLike, q: ArrayLike) -> F64:
    """Row-wise Hamilton products ``p[k] * q[k]`` of (n, 4) unit quaternions (scipy's Rotation; the sign is
    the Hamilton product's, not canonicalised)."""
    rp = _rotation().from_quat(np.asarray(p, dtype=float), scalar_first=True)
    rq = _rotation().from_quat(np.asarray(q, dtype=float), scalar_first=True)
    return np.asarray((rp * rq).as_quat(scalar_first=True), dtype=float)


def quat_conj(q: ArrayLike) -> F64:
    w, x, y, z = np.asarray(q, dtype=float)
    return np.array([w, -x, -y, -z])


def dcm_from_quat(q_nb: ArrayLike) -> F64:
    """``R_nb`` (3x3) from a unit quaternion ``q_nb`` (w, x, y, z). Written out because the pipeline calls it
    per magnetometer sample (in-flight relative mode): 5.7 us vs 27 us through scipy's Rotation."""
    if type(q_nb) is tuple:  # four numbers: the pipeline's gyro integral, once per IMU sample
        w, x, y, z = float(q_nb[0]), float(q_nb[1]), float(q_nb[2]), float(q_nb[3])
    else:
        w, x, y, z = np.asarray(q_nb, dtype=float).reshape(4).tolist()
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            down_b_from_quat((w, x, y, z)),
        ]
    )


def dcms_from_quats(q_nb: ArrayLike) -> F64:
    """``R_nb`` for each row of ``q_nb`` (n, 4) -> (n, 3, 3); each row is normalised first (a zero or
    non-finite norm raises ValueError).

    The arithmetic of scipy's ``Rotation.from_quat(q, scalar_first=True).as_matrix()`` (1.17), in the same
    order, so the same bits (checked on 200k random quaternions, tests/test_rotations.py), without importing
    ``scipy.spatial`` (~0.05 s of a replay's start-up)."""
    q = np.asarray(q_nb, dtype=float)
    if q.shape[0] == 0:
        return np.empty((0, 3, 3))
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    n = np.sqrt(x * x + y * y + z * z + w * w)
    if not np.all(n > 0.0):
        raise ValueError("Found zero norm quaternions in `quat`.")
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    m = np.empty((q.shape[0], 3, 3))
    m[:, 0, 0] = x2 - y2 - z2 + w2
    m[:, 1, 0] = 2.0 * (xy + zw)
    m[:, 2, 0] = 2.0 * (xz - yw)
    m[:, 0, 1] = 2.0 * (xy - zw)
    m[:, 1, 1] = -x2 + y2 - z2 + w2
    m[:, 2, 1] = 2.0 * (yz + xw)
    m[:, 0, 2] = 2.0 * (xz + yw)
    m[:, 1, 2] = 2.0 * (yz - xw)
    m[:, 2, 2] = -x2 - y2 + z2 + w2
    return m


def quat_from_dcm(r_nb: ArrayLike) -> F64:
    """Unit quaternion ``q_nb`` (w >= 0) from ``R_nb`` (scipy's Rotation)."""
    return quat_normalize(_rotation().from_matrix(np.asarray(r_nb, dtype=float)).as_quat(scalar_first=True))


def dcm_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> F64:
    """``R_nb`` from ZYX Euler angles: ``R_nb = Rz(yaw) @ Ry(pitch) @ Rx(roll)``. Written out because the
    pipeline calls it per magnetometer sample (in-flight absolute mode): 4.2 us vs 26 us through scipy."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def euler_from_dcm(r_nb: ArrayLike) -> tuple[float, float, float]:
    """ZYX Euler angles (roll, pitch, yaw) in rad from ``R_nb``; yaw in (-pi, pi]: :func:`euler_from_dcms`."""
    roll, pitch, yaw = euler_from_dcms(np.asarray(r_nb, dtype=float)[None])[0]
    return float(roll), float(pitch), float(yaw)


def quat_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> F64:
    """``q_nb`` (w >= 0) from ZYX Euler angles: :func:`quats_from_euler` of one attitude."""
    return quat_normalize(quats_from_euler([roll_rad], [pitch_rad], [yaw_rad])[0])


def euler_from_quat(q_nb: ArrayLike) -> tuple[float, float, float]:
    return euler_from_dcm(dcm_from_quat(q_nb))


def euler_from_dcms(r_nb: ArrayLike) -> F64:
    """ZYX Euler angles (roll, pitch, yaw) rad for each ``R_nb`` of (n, 3, 3) -> (n, 3); yaw in (-pi, pi].

    Written out rather than scipy's ``as_euler``: that one re-orthonormalises the matrices and warns at
    gimbal lock (pitch +-90 deg, which hand-held logs reach); this reads the angles off the matrix as is.
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
    """``q_nb`` (n, 4) from ZYX Euler angle arrays (n,), in closed form (half angles). The sign is not
    normalised to ``w >= 0``, so a smooth angle path gives a smooth quaternion path.

    Written out rather than scipy's ``_rotation().from_euler`` (which gives the same quaternions to 2e-16):
    :func:`magcomp.core.mahony.mahony_init` needs it in every replay and live session, and importing
    ``scipy.spatial`` adds 0.17 s to every command's start-up (python -X importtime, this machine).
    """
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
        axis=-1,
    )


def so3_exp(phi: ArrayLike) -> F64:
    """Exponential map so(3) -> SO(3) (Rodrigues) as a (3, 3) array: :func:`dcm_from_rotvec`."""
    v = np.asarray(phi, dtype=float).reshape(3)
    return np.array(dcm_from_rotvec((float(v[0]), float(v[1]), float(v[2])))).reshape(3, 3)


def dcm_from_rotvec(phi: FloatSeq) -> Mat3:
    """Rotation by angle |phi| about phi/|phi| (Rodrigues, ``I + sin(a)/a K + (1-cos(a))/a^2 K^2`` with
    ``K = [phi]_x``), row-major floats: the per-sample form (the observer's A_k; 13 us as numpy arrays,
    1 us on floats)."""
    kx, ky, kz = phi
    ang = math.sqrt(kx * kx + ky * ky + kz * kz)
    if ang < 1e-8:
        s1, s2 = 1.0, 0.5
    else:
        s1, s2 = math.sin(ang) / ang, (1.0 - math.cos(ang)) / (ang * ang)
    kxx, kyy, kzz, kxy, kxz, kyz = kx * kx, ky * ky, kz * kz, kx * ky, kx * kz, ky * kz
    return (
        1.0 - s2 * (kyy + kzz), -s1 * kz + s2 * kxy, s1 * ky + s2 * kxz,
        s1 * kz + s2 * kxy, 1.0 - s2 * (kxx + kzz), -s1 * kx + s2 * kyz,
        -s1 * ky + s2 * kxz, s1 * kx + s2 * kyz, 1.0 - s2 * (kxx + kyy),
    )  # fmt: skip


def dcms_from_rotvecs(phi: F64) -> F64:
    """:func:`dcm_from_rotvec` over rows (the batch solver): (m, 3) -> (m, 3, 3)."""
    ang = np.sqrt(np.einsum("ij,ij->i", phi, phi))
    small = ang < 1e-8
    a = np.where(small, 1.0, ang)
    s1 = np.where(small, 1.0, np.sin(a) / a)
    s2 = np.where(small, 0.5, (1.0 - np.cos(a)) / (a * a))
    k = np.zeros((phi.shape[0], 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = phi[:, 2], -phi[:, 1], phi[:, 0]
    return np.eye(3) + s1[:, None, None] * k + s2[:, None, None] * (k @ k)


def so3_log(r: ArrayLike) -> F64:
    """Logarithm SO(3) -> so(3) as a rotation vector (inverse of :func:`so3_exp`; scipy's Rotation)."""
    return np.asarray(_rotation().from_matrix(np.asarray(r, dtype=float)).as_rotvec(), dtype=float)


def quat_exp(phi: ArrayLike) -> F64:
    """Quaternion (w >= 0) of the rotation vector ``phi`` (rad; scipy's Rotation)."""
    q = _rotation().from_rotvec(np.asarray(phi, dtype=float)).as_quat(scalar_first=True)
    return np.asarray(q, dtype=float)


def quat_integrate_body_rate(q_nb: ArrayLike, omega_b_rad_s: ArrayLike, dt_s: float) -> F64:
    """Exact attitude update for a body rate held constant over ``dt_s``: ``q <- q * exp(omega dt)``, as an
    array (:func:`quat_step_body_rate`)."""
    q = np.asarray(q_nb, dtype=float).reshape(4)
    w = np.asarray(omega_b_rad_s, dtype=float).reshape(3)
    return np.array(quat_step_body_rate(q.tolist(), w.tolist(), dt_s))


def down_b_from_quat(q_nb: FloatSeq) -> Vec3:
    """Unit 'down' vector in body axes: third row of ``R_nb`` = third column of ``R_e^b`` (section II-A
    reference vector of the DPI calibration, eq. (3)); plain floats (per IMU sample). The one place the
    formula is written; :func:`dcm_from_quat` uses it for its third row."""
    w, x, y, z = q_nb[0], q_nb[1], q_nb[2], q_nb[3]
    return 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)



def roll_pitch_from_down(d: FloatSeq) -> tuple[float, float]:
    """ZYX roll and pitch (rad) of a unit down vector in body axes (:func:`down_b_from_quat`'s output):
    ``roll = atan2(d_y, d_z)``, ``pitch = -asin(d_x)`` (clipped); plain floats (per sample)."""
    return math.atan2(d[1], d[2]), -math.asin(max(-1.0, min(1.0, d[0])))

def euler_yaw_rate_coefs(roll_rad: float, pitch_rad: float) -> tuple[float, float]:
    """``(sin roll, cos roll) / cos pitch``: the ZYX Euler yaw rate is ``q c0 + r c1`` for the body rates
    (p, q, r) (plain floats; the pipeline's gyro yaw and the diagnosis's yaw-follow fit). cos(pitch) is
    floored at 0.1: near 84 deg of pitch the yaw is undefined."""
    cp = max(math.cos(pitch_rad), 0.1)
    return (math.sin(roll_rad) / cp, math.cos(roll_rad) / cp)


def euler_tilt_step(
    roll_rad: float, pitch_rad: float, p_rad_s: float, q_rad_s: float, r_rad_s: float, dt_s: float
) -> tuple[float, float]:
    """ZYX Euler roll and pitch advanced over ``dt_s`` by the body rates (p, q, r) (plain floats, one Euler
    step): roll rate ``p + (q sin roll + r cos roll) tan pitch``, pitch rate ``q cos roll - r sin roll``.
    Carries an attitude reported every few tens of ms across the IMU samples between (cos pitch floored at
    0.1, as in :func:`euler_yaw_rate_coefs`)."""
    sr, cr = math.sin(roll_rad), math.cos(roll_rad)
    cp = max(math.cos(pitch_rad), 0.1)
    tp = math.sin(pitch_rad) / cp
    return (
        roll_rad + (p_rad_s + (q_rad_s * sr + r_rad_s * cr) * tp) * dt_s,
        pitch_rad + (q_rad_s * cr - r_rad_s * sr) * dt_s,
    )


def quat_step_body_rate(
    q_nb: FloatSeq, omega_b_rad_s: FloatSeq, dt_s: float
) -> tuple[float, float, float, float]:
    """One step of ``q_dot = q (x) (0, omega / 2)`` on plain floats, normalised: the exact rotation for a
    body rate constant over ``dt_s`` (eq. (18); the per-sample path of the Mahony filter and the pipeline's
    gyro integral, the simulator's strap-down); :func:`quat_integrate_body_rate` wraps it for arrays.
    Measured: 3.6 us vs 16 us for the same step on numpy arrays (quat_exp + quat_multiply)."""
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
