"""Stateful shells around the per-sample core steps, for the pipeline.

The arithmetic lives in the core (:func:`magcomp.core.mahony.mahony_floats`, written on Python floats
because it runs once per IMU sample); this module only keeps the state between samples, as PX4
modules own their library states. The observer's shell is
:class:`magcomp.service.estimators.ThetaEstimator`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from magcomp.core.linalg3 import Vec3, Vec3Like, vec3
from magcomp.core.mahony import MahonyParams, MahonyState, Quat, mahony_floats
from magcomp.core.rotations import down_b_from_quat

F64 = NDArray[np.float64]


class FastMahony:
    """The Mahony filter (ref. [23], :func:`magcomp.core.mahony.mahony_floats`) for one vehicle: its
    attitude and gyro bias kept as plain floats between samples."""

    __slots__ = ("b", "p", "q")

    def __init__(self, p: MahonyParams, q_nb: Sequence[float] | F64, gyro_bias_b_rad_s: Vec3Like) -> None:
        self.p = p
        #: attitude (w, x, y, z), body FRD -> NED
        self.q: Quat = (float(q_nb[0]), float(q_nb[1]), float(q_nb[2]), float(q_nb[3]))
        #: gyro-bias estimate, rad/s, body FRD
        self.b: Vec3 = vec3(gyro_bias_b_rad_s)

    @property
    def state(self) -> MahonyState:
        return MahonyState(self.q, self.b)

    def down_b(self) -> Vec3:
        """The reference down vector in body axes (sec. II-A)."""
        return down_b_from_quat(self.q)

    def update(self, gx: float, gy: float, gz: float, ax: float, ay: float, az: float, dt: float) -> bool:
        """One step over ``dt`` > 0 s; returns whether the accelerometer passed the gate."""
        self.q, self.b, used = mahony_floats(self.q, self.b, gx, gy, gz, ax, ay, az, dt, self.p)
        return used
