"""Stateful shells around the per-sample core steps, for the pipeline.

The arithmetic lives in the core (:func:`magcomp.core.mahony.mahony_update`, written on Python floats
because it runs once per IMU sample); this module only keeps the state between samples, as PX4
modules own their library states. The observer's shell is
:class:`magcomp.service.estimators.ThetaEstimator`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from magcomp.core.linalg3 import Vec3, Vec3Like, vec3
from magcomp.core.mahony import MahonyParams, MahonyState, mahony_update

F64 = NDArray[np.float64]


class FastMahony:
    """The Mahony filter (ref. [23], :func:`magcomp.core.mahony.mahony_update`) for one vehicle."""

    __slots__ = ("p", "state")

    def __init__(self, p: MahonyParams, q_nb: Sequence[float] | F64, gyro_bias_b_rad_s: Vec3Like) -> None:
        self.p = p
        q = (float(q_nb[0]), float(q_nb[1]), float(q_nb[2]), float(q_nb[3]))
        self.state = MahonyState(q, vec3(gyro_bias_b_rad_s))

    @property
    def b(self) -> Vec3:
        """Gyro-bias estimate, rad/s, body FRD."""
        return self.state.gyro_bias_b_rad_s

    def down_b(self) -> Vec3:
        """The reference down vector in body axes (sec. II-A)."""
        return self.state.down_b

    def update(self, gx: float, gy: float, gz: float, ax: float, ay: float, az: float, dt: float) -> bool:
        """One step over ``dt`` s; returns whether the accelerometer passed the gate."""
        self.state, used = mahony_update(self.state, (gx, gy, gz), (ax, ay, az), dt, self.p)
        return used
