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
# the slots' setters bound once (looked up per sample, ``__set__`` cost a third of a constructor's time)
_set_imu_t, _set_imu_index = _IMU_T.__set__, _IMU_INDEX.__set__
_set_mag_t, _set_mag_index, _set_mag_onboard = _MAG_T.__set__, _MAG_INDEX.__set__, _MAG_ONBOARD.__set__
_set_att_t, _set_att_roll, _set_att_pitch, _set_att_yaw = (
    _ATT_T.__set__, _ATT_ROLL.__set__, _ATT_PITCH.__set__, _ATT_YAW.__set__
)
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
        _set_imu_t(self, t_s)
        _set_imu_index(self, imu_index)
        _set(self, "gyro_xyz", gyro_b_rad_s if type(gyro_b_rad_s) is tuple else _floats(gyro_b_rad_s))
        _set(self, "accel_xyz", accel_b_m_s2 if type(accel_b_m_s2) is tuple else _floats(accel_b_m_s2))

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
        _set_mag_t(self, t_s)
        _set_mag_index(self, mag_index)
        _set_mag_onboard(self, onboard_mgauss)
        _set(self, "field_xyz", field_b_mgauss if type(field_b_mgauss) is tuple else _floats(field_b_mgauss))

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
        _set(self, "rates_xyz", rates_b_rad_s if type(rates_b_rad_s) is tuple else _floats(rates_b_rad_s))
        _set_att_t(self, t_s)
        _set_att_roll(self, roll_rad)
        _set_att_pitch(self, pitch_rad)
        _set_att_yaw(self, yaw_rad)

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
    """Three Python floats from what is not a tuple of them (arrays, e.g. from ``dataclasses.replace``;
    the constructors keep a tuple as given)."""
    return float(v[0]), float(v[1]), float(v[2])


def _lazy_vec(sample: Any, slot: Any, xyz: Float3) -> np.ndarray:
    """The array in ``slot`` of ``sample``, built from ``xyz`` on first use (the same object afterwards)."""
    try:
        return slot.__get__(sample)  # type: ignore[no-any-return]
    except AttributeError:
        arr = np.array(xyz, dtype=np.float64)
        slot.__set__(sample, arr)
        return arr
