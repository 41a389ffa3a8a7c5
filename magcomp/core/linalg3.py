"""3-vectors and 3x3 matrices on plain Python floats, for the per-sample steps of the core.

Why hand-written: the observer, the Mahony filter and the low-pass run once per sample on 3-vectors
and 3x3 matrices, where numpy's per-call overhead is far larger than the arithmetic. Measured on this
machine (python 3.11, numpy 2, wall time per call under load): ``np.linalg.inv`` 8.7 us vs
:func:`sym3_inv` 0.3 us; ``np.linalg.eigvalsh`` 10 us vs :func:`sym3_eigvals` 1.5 us; ``np.cross``
38 us vs :func:`cross` 0.3 us. The observer step written on numpy arrays took ~450 us, on floats it takes
~10 us CPU (benchmarks/replay_speed.py runs ~59000 of them per 600 s of log). Batch (vectorised) work
stays in numpy/scipy. tests/unit/test_oracles.py checks these functions against numpy.

Matrices are row-major tuples of nine floats: ``m = (m00, m01, m02, m10, ..., m22)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

Vec3 = tuple[float, float, float]
Mat3 = tuple[float, float, float, float, float, float, float, float, float]
#: the upper triangle (a, b, c, e, f, i) of the symmetric [[a, b, c], [b, e, f], [c, f, i]]
Sym3 = tuple[float, float, float, float, float, float]

#: numbers as a caller may hold them (list, tuple, numpy array)
FloatSeq = Sequence[float] | NDArray[np.floating[Any]]
Vec3Like = FloatSeq

def vec3(x: Vec3Like) -> Vec3:
    """Three Python floats from any sequence of three numbers (lists, tuples, numpy arrays)."""
    return float(x[0]), float(x[1]), float(x[2])


def cross(u: FloatSeq, v: FloatSeq) -> Vec3:
    """``u x v``."""
    return u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]


def minus_matvec(v: FloatSeq, m: FloatSeq, u: FloatSeq) -> Vec3:
    """``v - M u``."""
    x, y, z = u
    return (v[0] - (m[0] * x + m[1] * y + m[2] * z), v[1] - (m[3] * x + m[4] * y + m[5] * z),
            v[2] - (m[6] * x + m[7] * y + m[8] * z))  # fmt: skip


def matTvec(m: FloatSeq, v: FloatSeq) -> Vec3:
    """``M^T v``."""
    x, y, z = v
    return (m[0] * x + m[3] * y + m[6] * z, m[1] * x + m[4] * y + m[7] * z, m[2] * x + m[5] * y + m[8] * z)


def gram(m: FloatSeq) -> Sym3:
    """``M^T M`` as its upper triangle."""
    p0, p1, p2, p3, p4, p5, p6, p7, p8 = m
    return (
        p0 * p0 + p3 * p3 + p6 * p6, p0 * p1 + p3 * p4 + p6 * p7, p0 * p2 + p3 * p5 + p6 * p8,
        p1 * p1 + p4 * p4 + p7 * p7, p1 * p2 + p4 * p5 + p7 * p8, p2 * p2 + p5 * p5 + p8 * p8,
    )  # fmt: skip


def sym3_eigvals(s: Sym3) -> Vec3:
    """Eigenvalues (ascending) of a symmetric 3x3 from its upper triangle (closed form, trigonometric)."""
    a, b, c, e, f, i = s
    p1 = b * b + c * c + f * f
    q = (a + e + i) / 3.0
    p2 = (a - q) ** 2 + (e - q) ** 2 + (i - q) ** 2 + 2.0 * p1
    if p1 == 0.0 or p2 == 0.0:
        lo, mid, hi = sorted((a, e, i))
        return lo, mid, hi
    p = math.sqrt(p2 / 6.0)
    b00, b11, b22 = (a - q) / p, (e - q) / p, (i - q) / p
    b01, b02, b12 = b / p, c / p, f / p
    det_b = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    phi = math.acos(min(max(det_b / 2.0, -1.0), 1.0)) / 3.0
    hi = q + 2.0 * p * math.cos(phi)
    lo = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    return lo, 3.0 * q - lo - hi, hi


def sym3_inv(s: Sym3) -> Sym3:
    """Inverse of a regular symmetric 3x3 given by its upper triangle, as its upper triangle (cofactors)."""
    a, b, c, e, f, i = s
    c00, c01, c02 = e * i - f * f, c * f - b * i, b * f - c * e
    r = 1.0 / (a * c00 + b * c01 + c * c02)
    return c00 * r, c01 * r, c02 * r, (a * i - c * c) * r, (b * c - a * f) * r, (a * e - b * b) * r


