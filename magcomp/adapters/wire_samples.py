"""IMU, compass and attitude samples decoded from a message, whose vectors stay three floats until first read.

Used by every source (:mod:`magcomp.adapters.mavlink_source`, :mod:`magcomp.adapters.ulog_source`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magcomp.core.types import AttitudeSample, ImuSample, MagSample, Vec3

#: the dataclass slots behind the public vector fields (set directly: the classes are frozen)
_IMU_T, _IMU_GYRO, _IMU_ACCEL, _IMU_INDEX = (
    ImuSample.__dict__[name] for name in ("t_s", "gyro_b_rad_s", "accel_b_m_s2", "imu_index")
)
_MAG_T, _MAG_FIELD, _MAG_INDEX, _MAG_ONBOARD = (
    MagSample.__dict__[name] for name in ("t_s", "field_b_mgauss", "mag_index", "onboard_mgauss")
)
_ATT_T, _ATT_ROLL, _ATT_PITCH, _ATT_YAW, _ATT_RATES = (
    AttitudeSample.__dict__[name] for name in ("t_s", "roll_rad", "pitch_rad", "yaw_rad", "rates_b_rad_s")
)
_set = object.__setattr__  # the frozen dataclasses' __setattr__ refuses every attribute
Float3 = tuple[float, float, float]


class WireImuSample(ImuSample):
    """An :class:`ImuSample` decoded from a message, whose vectors stay three floats (``gyro_xyz``,
    ``accel_xyz``) until the array fields are first read (then built once, with the same values).

    Most samples of a replay only ever reach the pipeline, which works on floats: building two numpy
    arrays per message that nobody reads was ~10 % of a replay. Everything else sees an ImuSample
    (isinstance, fields, ``dataclasses.replace``, pickling and copying as a plain ImuSample). The
    constructor takes the public field names; vectors given as arrays are read as floats."""

    __slots__ = ("accel_xyz", "gyro_xyz")
    gyro_xyz: Float3
    accel_xyz: Float3

    def __init__(
        self, t_s: float, gyro_b_rad_s: Float3 | Vec3, accel_b_m_s2: Float3 | Vec3, imu_index: int = 0
    ) -> None:
        _IMU_T.__set__(self, t_s)
        _IMU_INDEX.__set__(self, imu_index)
        _set(self, "gyro_xyz", _floats(gyro_b_rad_s))
        _set(self, "accel_xyz", _floats(accel_b_m_s2))

    @property  # type: ignore[override]
    def gyro_b_rad_s(self) -> np.ndarray:
        return _lazy_vec(self, _IMU_GYRO, self.gyro_xyz)

    @property  # type: ignore[override]
    def accel_b_m_s2(self) -> np.ndarray:
        return _lazy_vec(self, _IMU_ACCEL, self.accel_xyz)

    def floats(self) -> tuple[float, float, float, float, float, float]:
        return (*self.gyro_xyz, *self.accel_xyz)

    def __reduce__(self) -> tuple[Any, ...]:
        return _as_plain(self, ImuSample)


class WireMagSample(MagSample):
    """A :class:`MagSample` decoded from a message, whose field stays three floats (``field_xyz``) until
    ``field_b_mgauss`` is first read (see :class:`WireImuSample`)."""

    __slots__ = ("field_xyz",)
    field_xyz: Float3

    def __init__(
        self,
        t_s: float,
        field_b_mgauss: Float3 | Vec3,
        mag_index: int = 0,
        onboard_mgauss: Float3 | None = None,
    ) -> None:
        _MAG_T.__set__(self, t_s)
        _MAG_INDEX.__set__(self, mag_index)
        _MAG_ONBOARD.__set__(self, onboard_mgauss)
        _set(self, "field_xyz", _floats(field_b_mgauss))

    @property  # type: ignore[override]
    def field_b_mgauss(self) -> np.ndarray:
        return _lazy_vec(self, _MAG_FIELD, self.field_xyz)

    def floats(self) -> Float3:
        return self.field_xyz

    def __reduce__(self) -> tuple[Any, ...]:
        return _as_plain(self, MagSample)


class WireAttitudeSample(AttitudeSample):
    """An :class:`AttitudeSample` decoded from a message, whose body rates stay three floats (``rates_xyz``)
    until ``rates_b_rad_s`` is first read (see :class:`WireImuSample`; the pipeline reads only the angles)."""

    __slots__ = ("rates_xyz",)
    rates_xyz: Float3

    def __init__(
        self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float, rates_b_rad_s: Float3 | Vec3
    ) -> None:
        _set(self, "rates_xyz", _floats(rates_b_rad_s))
        _ATT_T.__set__(self, t_s)
        _ATT_ROLL.__set__(self, roll_rad)
        _ATT_PITCH.__set__(self, pitch_rad)
        _ATT_YAW.__set__(self, yaw_rad)

    @property  # type: ignore[override]
    def rates_b_rad_s(self) -> np.ndarray:
        return _lazy_vec(self, _ATT_RATES, self.rates_xyz)

    def __reduce__(self) -> tuple[Any, ...]:
        return _as_plain(self, AttitudeSample)


def _as_plain(sample: Any, cls: Any) -> tuple[Any, ...]:
    """A wire sample's ``__reduce__``: it pickles and copies as the public dataclass ``cls`` with the same
    field values (arrays built)."""
    return cls, tuple(getattr(sample, name) for name in cls.__dataclass_fields__)


def _floats(v: Float3 | Vec3) -> Float3:
    """Three Python floats (as given when they are; arrays, e.g. from ``dataclasses.replace``, converted)."""
    if type(v) is tuple:
        return v
    return float(v[0]), float(v[1]), float(v[2])


def _lazy_vec(sample: Any, slot: Any, xyz: Float3) -> np.ndarray:
    """The array in ``slot`` of ``sample``, built from ``xyz`` on first use (the same object afterwards)."""
    try:
        return slot.__get__(sample)  # type: ignore[no-any-return]
    except AttributeError:
        arr = np.array(xyz, dtype=np.float64)
        slot.__set__(sample, arr)
        return arr
