"""Log and link sources turned into the typed samples of :mod:`magcomp.core.types`.

Inputs: MAVLink ``.tlog`` and raw MAVLink streams, ArduPilot DataFlash ``.bin`` / text ``.log``, PX4 ``.ulg``
(:mod:`magcomp.adapters.ulog_source`) and live ``udp``/``tcp``/``serial`` links.

Units at this boundary (everything downstream uses them):
- RAW_IMU / SCALED_IMU*: accel mG -> m/s^2 (x 9.80665e-3), gyro mrad/s -> rad/s, mag mgauss (ArduPilot
  units); temperature cdegC -> degC (0 means "not provided"). RAW_IMU and SCALED_IMU both carry compass 0
  in ArduPilot: once RAW_IMU has been seen, SCALED_IMU is ignored (``counts["scaled_imu_shadowed"]``).
  SCALED_IMU2/3 are compasses (and IMUs) 1 and 2. A (0, 0, 0) field is "no data" (``mag_zero``).
- PX4 (HEARTBEAT autopilot 12): HIGHRES_IMU accel m/s^2, gyro rad/s, mag gauss -> mgauss, each only when its
  ``fields_updated`` bits are set; its IMU 0 replaces SCALED_IMU's, and a compass in SCALED_IMU shadows
  HIGHRES_IMU's (``highres_mag_shadowed``). ATTITUDE_QUATERNION (w, x, y, z) while no ATTITUDE is seen;
  ACTUATOR_OUTPUT_STATUS (PWM us of the ``active`` outputs) while no SERVO_OUTPUT_RAW is seen; throttle
  channels and ranges from PWM_MAIN_FUNCn / PWM_MAIN_MINn (see :mod:`magcomp.adapters.throttle`).
- Position: GPS_RAW_INT (fix_type >= 3 is ``fix_ok``) and GLOBAL_POSITION_INT (lat/lon degE7, alt mm MSL),
  DataFlash GPS/GPS2 (Status >= 3, GPS week + ms -> UTC) and POS become PositionSample; SYSTEM_TIME
  (time_unix_usec, unset clocks ignored) a TimeSample. Stamped with the latest source time.
- SYS_STATUS: voltage_battery mV, current_battery cA (-1 / UINT16_MAX = unknown -> NaN), battery 0.
  BATTERY_STATUS (cell voltages mV summed, current cA) is used for battery 0 only while SYS_STATUS has not
  reported a current.
- DataFlash: MAG/MAG2/MAG3 (or MAG with instance field I) in mgauss, IMU GyrX.. rad/s and AccX.. m/s^2,
  ATT deg, RCOU C1.. / Ch1.. / Chan1.. us, CTUN ThO (0..1) or ThrOut (0..1000) (Plane's CTUN, the one with
  NavRoll: ThO / ThrOut in percent), CURR/BAT Volt and Curr
  (integer columns of old logs are cV / cA), PARM. When MAG records the motor compensation the autopilot
  applied (MOfsX.. / MOX..), it is subtracted by default (``undo_motor_comp``) so that the field is the one
  the motors actually disturbed; not when the logged parameters say the autopilot applies none
  (COMPASS_MOTCT = 0 and no per-motor compensation): a non-zero offset is then a corrupt record
  (``motor_comp_ignored``). MAVLink compass fields carry no such record: with COMPASS_MOTCT = 1 / 2 the
  compensation is rebuilt from COMPASS_MOT*/MOT2*/MOT3* and VFR_HUD.throttle / SYS_STATUS current and
  subtracted from when they are known (:mod:`magcomp.adapters.ardupilot_motcomp`).
- Time: the message's own timestamp (time_boot_ms, time_usec, DataFlash TimeUS / TimeMS) in s. Messages
  without one (VFR_HUD, SYS_STATUS, BATTERY_STATUS, HEARTBEAT, PARAM_VALUE) get the latest time seen. A
  jump back of more than ``RESET_JUMP_S`` is a reboot of the autopilot: an offset keeps ``t_s`` monotonic,
  ``counts["clock_resets"]`` counts them and ``samples()`` yields a ClockResetSample (the pipeline ends its
  calibration window and filters there). A jump either way is believed only once the next timestamp
  confirms it; a lone corrupt timestamp is dropped (``counts["time_jumps"]``). Smaller steps back within
  one message stream are dropped (``counts["time_backwards"]``). Streams stamped ``time_usec`` on a clock
  of their own (ArduCopter 3.1/3.2's RAW_IMU and SERVO_OUTPUT_RAW, 2.57-2.87 s behind ``time_boot_ms``)
  are moved onto the ``time_boot_ms`` clock by an offset measured from messages sent together, by the
  tlog's receive stamps or a link's arrival times (:class:`StreamOffsets`; ``counts["clock_aligned"]``,
  said once per stream).
- Bad input is skipped and counted, never fatal: ``bad_crc``, ``garbage_bytes``, ``truncated``,
  ``nonfinite``. A file with no usable message at all is an :class:`~magcomp.errors.InputError`.

The tlog / raw-stream reader walks the framing (8-byte big-endian timestamp + MAVLink 1/2 packet) itself and
decodes only the message ids it needs, without pymavlink's ``MAVLink.decode``: X.25 CRC with the message's
crc_extra (the dialect module's CRC function, i.e. fastcrc when pymavlink uses it), then the dialect class's
precompiled ``Struct`` (zero-truncated MAVLink 2 payloads padded with zeros) into a named-tuple view in wire
order with pymavlink's field values (arrays as lists, char[N] as str); other ids are skipped unread. Same
messages, values and counts as ``MAVLink.decode`` (tests/unit/test_sources_fastpath.py); on a 600 s simulated
tlog the whole source (decode + conversion + throttle) takes ~0.3x the wall time of ``mavlink_connection`` +
``recv_msg`` merely parsing it (benchmarks/source_speed.py). Signatures of signed frames are not checked.
The file is read ``READ_CHUNK_BYTES`` at a time: memory does not grow with the log's length (a frame cut by a
chunk's end is completed from the next chunk; same messages and counts as reading it whole).

:func:`load_log` keeps what it needs of each record in compact columns (:mod:`magcomp.adapters.columns`),
not as sample objects: ~8 bytes per value instead of ~150-350 bytes per row.
"""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import math
import mmap
import operator
import os
import re
import stat
import struct
import sys
from array import array
from collections import deque
from collections.abc import Callable, Generator, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, BinaryIO, NamedTuple

import numpy as np

from magcomp.adapters.ardupilot_motcomp import OnboardMotorComp
from magcomp.adapters.columns import PwmRows, Rows, Window
from magcomp.adapters.gnss_time import decimal_year_from_gps, decimal_year_from_unix
from magcomp.adapters.throttle import (
    FIXED_WING_TYPES,
    MULTIROTOR_TYPES,
    ResolvedThrottle,
    ThrottleSpec,
    motor_channels,
    parse_throttle_source,
    resolve_throttle,
    throttle_from_pwm,
)
from magcomp.core.autopilot_params import motor_comp_known_off
from magcomp.core.identity import uid_from_autopilot_version, uid_from_board_msg
from magcomp.core.types import (
    AttitudeSample,
    ClockResetSample,
    HeartbeatSample,
    IdentitySample,
    ImuSample,
    LogData,
    MagSample,
    ParamSample,
    PositionSample,
    PowerSample,
    Sample,
    Series,
    TemperatureSample,
    ThrottleSample,
    TimeSample,
    Vec3,
)
from magcomp.errors import InputError

if TYPE_CHECKING:
    from magcomp.adapters.ulog_source import UlogSource

log = logging.getLogger("magcomp.source")

G_M_S2 = 9.80665
_MG_TO_M_S2 = G_M_S2 * 1e-3
RESET_JUMP_S = 5.0  # a timestamp this far behind the newest one is an autopilot reboot
#: a timestamp this far ahead of the newest one (the streams read come at 1 Hz or faster) is believed only
#: when the next timestamp lies within this of it: one corrupt time cannot make the stream after it look
#: like it went backwards, nor stretch the log
FORWARD_CONFIRM_S = 1.0
U32_WRAP_S = 4294.967296  # SERVO_OUTPUT_RAW.time_usec is uint32
MAV_AUTOPILOT_INVALID = 8
MAV_AUTOPILOT_PX4 = 12
HIGHRES_ACCEL_GYRO = 0x3F  # HIGHRES_IMU_UPDATED_FLAGS: X/Y/Z ACC (1, 2, 4), X/Y/Z GYRO (8, 16, 32)
HIGHRES_MAG = 0x1C0  # X/Y/Z MAG (64, 128, 256)
HIGHRES_TEMPERATURE = 0x1000
MAV_TYPE_GCS = 6
MAGIC_V1 = 0xFE
MAGIC_V2 = 0xFD
LIVE_PREFIXES = ("udp:", "udpin:", "udpout:", "udpbcast:", "tcp:", "tcpin:", "serial:")

log = logging.getLogger("magcomp.source")

WANTED_MAVLINK = (
    "HEARTBEAT",
    "SYS_STATUS",
    "PARAM_VALUE",
    "SCALED_IMU",
    "RAW_IMU",
    "SCALED_PRESSURE",
    "ATTITUDE",
    "SERVO_OUTPUT_RAW",
    "RC_CHANNELS",
    "RC_CHANNELS_RAW",  # only for the clock offsets: ArduPilot sends it right after SERVO_OUTPUT_RAW
    "VFR_HUD",
    "SCALED_IMU2",
    "SCALED_IMU3",
    "BATTERY_STATUS",
    "GPS_RAW_INT",
    "GLOBAL_POSITION_INT",
    "SYSTEM_TIME",
    "HIGHRES_IMU",
    "ATTITUDE_QUATERNION",
    "ACTUATOR_OUTPUT_STATUS",
    "AUTOPILOT_VERSION",
)
WANTED_DATAFLASH = (
    "MAG",
    "MAG2",
    "MAG3",
    "IMU",
    "IMU2",
    "IMU3",
    "ATT",
    "RCOU",
    "CTUN",
    "CURR",
    "CURR2",
    "BAT",
    "BAT2",
    "PARM",
    "MSG",
    "GPS",
    "GPS2",
    "POS",
)
_SERVO_FIELDS = tuple(f"servo{i}_raw" for i in range(1, 17))
_IMU_SENSOR_NAMES = tuple(f"imu{i}" for i in range(256))  # RAW_IMU.id is a uint8
_servo_values = operator.attrgetter(*_SERVO_FIELDS)
_RC_FIELDS = tuple(f"chan{i}_raw" for i in range(1, 19))
_PWM_COLUMN = re.compile(r"^(?:C|Ch|Chan)(\d+)$")


@dataclass(frozen=True, slots=True)
class PwmRecord:
    """Raw PWM (us) by 1-based channel: ``kind`` "servo" (outputs) or "rc" (inputs)."""

    t_s: float
    kind: str
    pwm_us: dict[int, float]


@dataclass(frozen=True, slots=True)
class ThrottleRecord:
    """A throttle that is already 0..1: ``kind`` "vfr_hud" or "ctun"."""

    t_s: float
    kind: str
    throttle_01: float


Record = Sample | PwmRecord | ThrottleRecord


#: MAVLink streams stamped ``time_usec`` (us since boot) and those stamped ``time_boot_ms``. ArduCopter
#: 3.1/3.2 stamps the former on a clock of its own, 2.57-2.87 s behind the latter (issue 23, item 4):
#: :class:`StreamOffsets` measures and removes the difference.
USEC_STREAMS = frozenset({"RAW_IMU", "SERVO_OUTPUT_RAW", "HIGHRES_IMU", "ACTUATOR_OUTPUT_STATUS"})
MS_STREAMS = frozenset({"SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "ATTITUDE", "ATTITUDE_QUATERNION",
                        "RC_CHANNELS", "RC_CHANNELS_RAW", "SCALED_PRESSURE"})  # fmt: skip
#: two messages received this close together (s) were sent together, in one burst: at 57600 baud one
#: 40-byte message takes 7 ms on the wire, so 20 ms is two or three messages apart (measured on the squilter
#: tlogs: 91-98 % of the RAW_IMU -> SCALED_IMU2 pairs arrive within it)
PAIR_RX_S = 0.02
#: the last pairs of one kind kept (the estimate follows a drift or a new boot, outliers outvoted)
OFFSET_WINDOW = 31
#: pairs of one kind needed before their median is believed (at 2 Hz telemetry: 4.5 s)
OFFSET_MIN_PAIRS = 9
#: a kind of pair is "sent together" only when its stamp differences agree this well (s): messages stamped
#: in one send call differ by the call's duration (measured IQR 0.2-1.4 ms on the squilter tlogs), messages
#: from different scheduler slots by whole loop periods (10-20 ms at 50-100 Hz; measured IQR 36-260 ms)
OFFSET_MAX_IQR_S = 0.005
#: an offset is applied only when larger than this (s): one period of a 20 Hz stream, the fastest telemetry
#: rate ArduPilot streams these at, below which pairing by receive time cannot tell it from the send slots
OFFSET_MIN_S = 0.05
#: re-evaluate a kind of pair every this many new pairs (a median of OFFSET_WINDOW values each time)
OFFSET_EVAL_EVERY = 8


class StreamOffsets:
    """Per-stream clock offsets of ``time_usec`` streams to the ``time_boot_ms`` clock, from messages sent
    together (issue 23, item 4).

    Consecutive messages of one sender (system id) received within :data:`PAIR_RX_S` of each other (the
    tlog's receive stamp, or a live link's arrival time) were sent in one burst; each such pair of a
    ``time_usec`` stream and a ``time_boot_ms`` one gives one difference of their stamps. Pairs are kept
    per kind (stream, partner, which came first); of the kinds whose differences agree (IQR at most
    :data:`OFFSET_MAX_IQR_S`) :meth:`estimate` takes the one stamped at the same instant, and its median
    is the offset. It is applied (``offset_s``, added to the stream's raw time) when larger than
    :data:`OFFSET_MIN_S`; said once per stream and counted in ``counts["clock_aligned"]``. A reboot
    (:meth:`reset`) starts the pairs again and keeps the offsets until the new boot's pairs say otherwise.
    """

    def __init__(self, counts: dict[str, int]) -> None:
        self.counts = counts
        self.offset_s: dict[str, float] = {}
        self._pairs: dict[tuple[str, str, int], deque[float]] = {}
        self._new: dict[tuple[str, str, int], int] = {}
        self._last: tuple[str, float, float, int] | None = None
        self._said: set[str] = set()

    def reset(self) -> None:
        self._pairs.clear()
        self._new.clear()
        self._last = None

    def observe(self, stream: str, raw_s: float, rx_s: float, src: int = -1) -> None:
        """One message's stream, raw stamp (s), receive time (s) and sender (system id)."""
        last = self._last
        self._last = (stream, raw_s, rx_s, src)
        if last is None or abs(rx_s - last[2]) > PAIR_RX_S or src != last[3]:
            return
        if stream in USEC_STREAMS:
            if last[0] not in MS_STREAMS:
                return
            key, diff = (stream, last[0], -1), last[1] - raw_s
        elif stream in MS_STREAMS and last[0] in USEC_STREAMS:
            key, diff = (last[0], stream, 1), raw_s - last[1]
        else:
            return
        pairs = self._pairs.get(key)
        if pairs is None:
            pairs = self._pairs[key] = deque(maxlen=OFFSET_WINDOW)
        pairs.append(diff)
        n_new = self._new.get(key, 0) + 1
        if len(pairs) >= OFFSET_MIN_PAIRS and (n_new >= OFFSET_EVAL_EVERY or len(pairs) == OFFSET_MIN_PAIRS):
            n_new = 0
            self._evaluate(key[0])
        self._new[key] = n_new

    def estimate(self, stream: str) -> tuple[float, float, int] | None:
        """(offset, IQR, pairs) of ``stream`` from its kinds of pair that agree (IQR at most
        :data:`OFFSET_MAX_IQR_S`); None while none does.

        A partner sent after the stream's message was stamped no earlier than it, so each consistent kind
        with the partner after gives an upper bound of the offset and each with the partner before a lower
        bound (the tail of the previous burst on a link that runs bursts together: on the squilter tlogs
        20 ms and 180 ms below, one and nine 50 Hz scheduler slots). The offset is the tightest upper
        bound, the message sent right after in the same call; a lower bound alone only once its kind has
        a whole window of pairs and still no partner after agrees."""
        upper: tuple[float, float, int] | None = None
        lower: tuple[float, float, int] | None = None
        for key, pairs in self._pairs.items():
            n = len(pairs)
            if key[0] != stream or n < OFFSET_MIN_PAIRS:
                continue
            v = sorted(pairs)
            iqr = v[(3 * n) // 4] - v[n // 4]
            if iqr > OFFSET_MAX_IQR_S:
                continue
            med = v[n // 2]
            if key[2] > 0:
                if upper is None or med < upper[0]:
                    upper = (med, iqr, n)
            elif n == OFFSET_WINDOW and (lower is None or med > lower[0]):
                lower = (med, iqr, n)
        return upper if upper is not None else lower

    def _evaluate(self, stream: str) -> None:
        est = self.estimate(stream)
        if est is None:
            return  # no kind of pair stamped at one instant (yet): the offset stays as it is
        med = est[0]
        if abs(med) <= OFFSET_MIN_S:
            self.offset_s.pop(stream, None)
            return
        self.offset_s[stream] = med
        if stream not in self._said:
            self._said.add(stream)
            self.counts["clock_aligned"] += 1
            how = "behind" if med > 0 else "ahead of"
            log.info("%s time_usec %.2f s %s time_boot_ms: aligned", stream, abs(med), how)


class _Clock:
    """Monotonic source time from per-stream raw timestamps, with reboot detection (see module docstring)."""

    def __init__(self, counts: dict[str, int]) -> None:
        self.counts = counts
        self.offset_s = 0.0
        self.max_raw_s: float | None = None
        self.last_by_stream: dict[str, float] = {}
        self.last_t_s = 0.0
        self.pending_s: float | None = None  # a jumped timestamp waiting for a second one to confirm it
        self.reboot_pending = False  # a reboot was detected; MavSource.samples() yields the event
        #: the receive time (s) of the message being converted: the tlog's stamp or a link's arrival time;
        #: None where there is none (DataFlash, a raw MAVLink file)
        self.rx_s: float | None = None
        self.rx_src = -1  # the sender's system id (only consecutive messages of one sender pair)
        self.offsets = StreamOffsets(counts)

    def observe(self, stream: str, raw_s: float) -> None:
        """A message that is not stamped (nothing of it is kept) but pairs with its neighbours."""
        rx = self.rx_s
        if rx is not None and math.isfinite(raw_s):
            self.offsets.observe(stream, raw_s, rx, self.rx_src)

    def stamp(self, stream: str, raw_s: float) -> float | None:
        if not math.isfinite(raw_s):
            self.counts["nonfinite"] += 1
            return None
        rx = self.rx_s
        if rx is not None:  # streams on a clock of their own moved onto the time_boot_ms clock
            offsets = self.offsets
            offsets.observe(stream, raw_s, rx, self.rx_src)
            if offsets.offset_s:
                raw_s += offsets.offset_s.get(stream, 0.0)
        top = self.max_raw_s
        if top is None:
            self.max_raw_s = raw_s
        elif raw_s < top - RESET_JUMP_S or raw_s > top + FORWARD_CONFIRM_S:
            # a jump of the clock: believed only when the next timestamp (of any message) agrees with
            # it, so that one corrupt timestamp cannot shift or stretch everything after it
            pend = self.pending_s
            if pend is None or abs(raw_s - pend) > FORWARD_CONFIRM_S:
                self.pending_s = raw_s
                self.counts["time_jumps"] += 1
                return None
            self.pending_s = None
            self.counts["time_jumps"] -= 1  # confirmed: not a glitch
            if raw_s < top:  # a reboot of the autopilot: an event for the pipeline (reboot_pending)
                self.offset_s += top - raw_s
                self.counts["clock_resets"] += 1
                self.reboot_pending = True
                self.offsets.reset()
            self.max_raw_s = raw_s
            self.last_by_stream = {}
        else:
            self.pending_s = None  # this timestamp agrees with the clock: a pending jump was a glitch
            prev = self.last_by_stream.get(stream)
            if prev is not None and raw_s < prev:
                self.counts["time_backwards"] += 1
                return None
            if raw_s > top:
                self.max_raw_s = raw_s
        self.last_by_stream[stream] = raw_s
        t_s = raw_s + self.offset_s
        if t_s > self.last_t_s:
            self.last_t_s = t_s
        return t_s

    def unwrap_u32_us(self, usec: int) -> float:
        """uint32 microseconds -> seconds, unwrapped to the turn nearest the newest raw time."""
        raw_s = usec * 1e-6
        if self.max_raw_s is not None and self.max_raw_s > U32_WRAP_S / 2:
            turns = round((self.max_raw_s - raw_s) / U32_WRAP_S)
            raw_s += max(turns, 0) * U32_WRAP_S
        return raw_s


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


#: MAV_PARAM_TYPE's integer types (UINT8 .. INT64) as their struct codes, the value in the float's low bytes
_PARAM_INT_CODES = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i", 7: "<I", 8: "<i"}


def param_value(value: float, param_type: int, bytewise: bool) -> float:
    """A PARAM_VALUE's value. ArduPilot casts every parameter to the float field (C cast); PX4 copies an
    integer parameter's bytes into it (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE: EKF2_GPS_CTRL = 15
    reads 2.1e-44 as a float, PWM_MAIN_MIN1 = 1000 reads 1.4e-42). Integer types are decoded from their bytes
    for a PX4 vehicle (``bytewise``), and whenever the float is no integer at all (the HEARTBEAT not seen
    yet: a C-cast integer is always a whole float, a byte copy of a nonzero integer below 2^30 never is)."""
    code = _PARAM_INT_CODES.get(param_type)
    if code is None or not (bytewise or not math.isfinite(value) or value != math.floor(value)):
        return value
    raw = struct.pack("<f", value)
    return float(struct.unpack_from(code, raw)[0])


def _vec(x: float, y: float, z: float, scale: float = 1.0) -> np.ndarray:
    return np.array([x * scale, y * scale, z * scale], dtype=np.float64)


#: the dataclass slots behind the public vector fields (set directly: the classes are frozen)
_IMU_T, _IMU_GYRO, _IMU_ACCEL, _IMU_INDEX = (
    ImuSample.__dict__[name] for name in ("t_s", "gyro_b_rad_s", "accel_b_m_s2", "imu_index")
)
_MAG_T, _MAG_FIELD, _MAG_INDEX, _MAG_ONBOARD = (
    MagSample.__dict__[name] for name in ("t_s", "field_b_mgauss", "mag_index", "onboard_mgauss")
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
        return ImuSample, (self.t_s, self.gyro_b_rad_s, self.accel_b_m_s2, self.imu_index)


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
        return MagSample, (self.t_s, self.field_b_mgauss, self.mag_index, self.onboard_mgauss)


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


class _Converter:
    """Turns decoded messages (MAVLink or DataFlash) into records; holds the clock and what is known so
    far."""

    def __init__(
        self,
        counts: dict[str, int],
        *,
        mag_index: int | None,
        undo_motor_comp: bool,
        pipeline_only: bool = False,
    ) -> None:
        self.counts = counts
        # pipeline_only: leave out the samples the heading pipeline ignores (temperature, power, IMUs other
        # than IMU 0), counted in ``skipped`` instead: a replay built and dispatched ~96k of them per 10 min
        self.pipeline_only = pipeline_only
        self.skipped = 0
        self.clock = _Clock(counts)
        self.mag_index = mag_index
        self.undo_motor_comp = undo_motor_comp
        # ArduPilot's COMPASS_MOTCT compensation in MAVLink compass fields (see ardupilot_motcomp)
        self.onboard_comp = OnboardMotorComp()
        self.seen_raw_imu = False
        self.seen_highres_imu = False  # PX4: HIGHRES_IMU is IMU 0; SCALED_IMU then adds only its compass
        self.seen_scaled_mag0 = False  # a compass 0 in SCALED_IMU shadows HIGHRES_IMU's
        self.seen_attitude = False  # ATTITUDE shadows ATTITUDE_QUATERNION
        self.seen_servo_output = False  # SERVO_OUTPUT_RAW shadows ACTUATOR_OUTPUT_STATUS
        self.sys_status_current = False
        self.servo_pwm: dict[int, float] = {}
        self.vehicle_type = -1
        self.autopilot = -1
        self.system_id = -1
        self.uid: str | None = None  # the vehicle's unique id (magcomp.core.identity)
        self._pwm_columns: dict[str, list[tuple[str, int]]] = {}
        self._df_converters: dict[int, tuple[Any, list[tuple[str, int, Any, float]]]] = {}

    def _keep(self) -> bool:
        """False (and the sample counted as skipped) for a sample only a pipeline-only source leaves out."""
        if self.pipeline_only:
            self.skipped += 1
            return False
        return True

    # --- MAVLink -----------------------------------------------------------------------------------------
    def mavlink(self, msg: Any) -> list[tuple[str, Record]]:
        """A pymavlink message (a live link's, or the tests' reference decode): its arrival time, when it
        has one, is the receive time of :class:`StreamOffsets`."""
        rx = getattr(msg, "_timestamp", None)
        if rx is not None:
            self.clock.rx_s = float(rx)
            self.clock.rx_src = int(msg.get_srcSystem())
        mtype = msg.get_type()
        handler = getattr(self, f"_m_{mtype}", None)
        return handler(msg) if handler is not None else []

    def _imu_mag(self, origin: str, t_s: float, msg: Any, index: int) -> list[tuple[str, Record]]:
        gyro = (msg.xgyro * 1e-3, msg.ygyro * 1e-3, msg.zgyro * 1e-3)  # mrad/s -> rad/s
        accel = (msg.xacc * _MG_TO_M_S2, msg.yacc * _MG_TO_M_S2, msg.zacc * _MG_TO_M_S2)  # mG
        out: list[tuple[str, Record]] = []
        if index == 0 or self._keep():
            out.append((origin, WireImuSample(t_s, gyro, accel, index)))
        xmag, ymag, zmag = msg.xmag, msg.ymag, msg.zmag
        if not (xmag or ymag or zmag):  # (0, 0, 0): no compass data in this message
            self.counts["mag_zero"] += 1
        elif self.mag_index is None or self.mag_index == index:
            fx, fy, fz = float(xmag), float(ymag), float(zmag)  # mgauss
            onboard: Float3 | None = None
            if self.undo_motor_comp and self.onboard_comp.params and self.autopilot != MAV_AUTOPILOT_PX4:
                o = self.onboard_comp.offset(index, self.counts)
                if o is not None:  # the autopilot added o (COMPASS_MOTCT): the field the motors disturbed
                    fx, fy, fz = fx - o[0], fy - o[1], fz - o[2]
                    onboard = (float(o[0]), float(o[1]), float(o[2]))
                    self.counts["motor_comp_removed"] += 1
            out.append((origin, WireMagSample(t_s, (fx, fy, fz), index, onboard)))
        temp = getattr(msg, "temperature", 0)
        if temp and self._keep():  # 0 = not provided (common.xml)
            out.append((origin, TemperatureSample(t_s, temp * 0.01, _IMU_SENSOR_NAMES[index])))
        return out

    def _m_RAW_IMU(self, msg: Any) -> list[tuple[str, Record]]:
        self.seen_raw_imu = True
        t_s = self.clock.stamp("RAW_IMU", msg.time_usec * 1e-6)
        return [] if t_s is None else self._imu_mag("RAW_IMU", t_s, msg, int(getattr(msg, "id", 0)))

    def _m_SCALED_IMU(self, msg: Any) -> list[tuple[str, Record]]:
        if self.seen_raw_imu:
            self.counts["scaled_imu_shadowed"] += 1
            return []
        t_s = self.clock.stamp("SCALED_IMU", msg.time_boot_ms * 1e-3)
        if t_s is None:
            return []
        out = self._imu_mag("SCALED_IMU", t_s, msg, 0)
        return (
            self._px4_scaled_imu(out) if self.seen_highres_imu or self.autopilot == MAV_AUTOPILOT_PX4 else out
        )

    def _m_SCALED_IMU2(self, msg: Any) -> list[tuple[str, Record]]:
        t_s = self.clock.stamp("SCALED_IMU2", msg.time_boot_ms * 1e-3)
        return [] if t_s is None else self._imu_mag("SCALED_IMU2", t_s, msg, 1)

    def _m_SCALED_IMU3(self, msg: Any) -> list[tuple[str, Record]]:
        t_s = self.clock.stamp("SCALED_IMU3", msg.time_boot_ms * 1e-3)
        return [] if t_s is None else self._imu_mag("SCALED_IMU3", t_s, msg, 2)

    def _m_ATTITUDE(self, msg: Any) -> list[tuple[str, Record]]:
        if not _finite(msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed):
            self.counts["nonfinite"] += 1
            return []
        t_s = self.clock.stamp("ATTITUDE", msg.time_boot_ms * 1e-3)
        if t_s is None:
            return []
        self.seen_attitude = True
        rates = _vec(msg.rollspeed, msg.pitchspeed, msg.yawspeed)
        return [("ATTITUDE", AttitudeSample(t_s, float(msg.roll), float(msg.pitch), float(msg.yaw), rates))]

    def _m_SERVO_OUTPUT_RAW(self, msg: Any) -> list[tuple[str, Record]]:
        self.seen_servo_output = True
        t_s = self.clock.stamp("SERVO_OUTPUT_RAW", self.clock.unwrap_u32_us(msg.time_usec))
        if t_s is None:
            return []
        base = 8 * int(msg.port)
        try:
            values = _servo_values(msg)
        except AttributeError:  # a message class without the servo9..16 extension
            values = tuple(getattr(msg, name, 0) for name in _SERVO_FIELDS)
        pwm = self.servo_pwm
        for channel, value in enumerate(values[:8], start=base + 1):
            pwm[channel] = float(value)
        if base == 0:
            for channel, value in enumerate(values[8:], start=9):
                if value:  # servo9..16 are an extension: 0 when the sender does not fill them
                    pwm[channel] = float(value)
        return [("SERVO_OUTPUT_RAW", PwmRecord(t_s, "servo", dict(self.servo_pwm)))]

    def _m_RC_CHANNELS(self, msg: Any) -> list[tuple[str, Record]]:
        t_s = self.clock.stamp("RC_CHANNELS", msg.time_boot_ms * 1e-3)
        if t_s is None:
            return []
        pwm = {}
        for i, name in enumerate(_RC_FIELDS[: min(int(msg.chancount), 18)], start=1):
            value = getattr(msg, name)
            if value != 0xFFFF:
                pwm[i] = float(value)
        return [("RC_CHANNELS", PwmRecord(t_s, "rc", pwm))]

    def _m_RC_CHANNELS_RAW(self, msg: Any) -> list[tuple[str, Record]]:
        self.clock.observe("RC_CHANNELS_RAW", msg.time_boot_ms * 1e-3)  # pairs with SERVO_OUTPUT_RAW
        return []

    def _m_VFR_HUD(self, msg: Any) -> list[tuple[str, Record]]:
        thr = min(1.0, max(0.0, float(msg.throttle) * 0.01))  # percent -> 0..1
        self.onboard_comp.throttle_01 = thr
        return [("VFR_HUD", ThrottleRecord(self.clock.last_t_s, "vfr_hud", thr))]

    def _m_SYS_STATUS(self, msg: Any) -> list[tuple[str, Record]]:
        volt = msg.voltage_battery * 1e-3 if msg.voltage_battery not in (0xFFFF, -1) else math.nan
        curr = msg.current_battery * 0.01 if msg.current_battery >= 0 else math.nan
        if math.isnan(volt) and math.isnan(curr):
            return []
        if not math.isnan(curr):
            self.sys_status_current = True
            self.onboard_comp.current_a = curr
        return [("SYS_STATUS", PowerSample(self.clock.last_t_s, volt, curr, 0))] if self._keep() else []

    def _m_BATTERY_STATUS(self, msg: Any) -> list[tuple[str, Record]]:
        index = int(msg.id)
        if index == 0 and self.sys_status_current:
            return []
        cells = [v for v in msg.voltages if v != 0xFFFF]
        cells += [v for v in getattr(msg, "voltages_ext", ()) if v not in (0, 0xFFFF)]
        volt = sum(cells) * 1e-3 if cells else math.nan
        curr = msg.current_battery * 0.01 if msg.current_battery >= 0 else math.nan
        if not self._keep():
            return []
        return [("BATTERY_STATUS", PowerSample(self.clock.last_t_s, volt, curr, index))]

    def _m_SCALED_PRESSURE(self, msg: Any) -> list[tuple[str, Record]]:
        t_s = self.clock.stamp("SCALED_PRESSURE", msg.time_boot_ms * 1e-3)
        if t_s is None:
            return []
        if not self._keep():
            return []
        return [("SCALED_PRESSURE", TemperatureSample(t_s, msg.temperature * 0.01, "baro"))]

    def _m_HEARTBEAT(self, msg: Any) -> list[tuple[str, Record]]:
        if msg.autopilot == MAV_AUTOPILOT_INVALID or msg.type == MAV_TYPE_GCS:
            return []  # a GCS, companion computer, gimbal... not the vehicle
        self.vehicle_type, self.autopilot = int(msg.type), int(msg.autopilot)
        self.system_id = int(msg.get_srcSystem())
        hb = HeartbeatSample(self.clock.last_t_s, self.vehicle_type, self.autopilot, self.system_id)
        return [("HEARTBEAT", hb)]

    def _m_AUTOPILOT_VERSION(self, msg: Any) -> list[tuple[str, Record]]:
        uid = uid_from_autopilot_version(int(msg.uid), getattr(msg, "uid2", None))
        if uid is None or uid == self.uid:  # (sent again on every request: said once)
            return []
        self.uid = uid
        return [("AUTOPILOT_VERSION", IdentitySample(self.clock.last_t_s, uid, int(msg.get_srcSystem())))]

    def _m_PARAM_VALUE(self, msg: Any) -> list[tuple[str, Record]]:
        name = msg.param_id
        if isinstance(name, bytes):
            name = name.decode("ascii", "replace")
        name = name.rstrip("\x00")
        value = param_value(float(msg.param_value), int(msg.param_type), self.autopilot == MAV_AUTOPILOT_PX4)
        self.onboard_comp.param(name, value)  # (a NaN COMPASS_MOT* is reported there as invalid)
        return [("PARAM_VALUE", ParamSample(self.clock.last_t_s, name, value))]

    # --- PX4 (MAV_AUTOPILOT_PX4): HIGHRES_IMU, ATTITUDE_QUATERNION, ACTUATOR_OUTPUT_STATUS ---------------
    def _px4_scaled_imu(self, out: list[tuple[str, Record]]) -> list[tuple[str, Record]]:
        """SCALED_IMU of a vehicle that also sends HIGHRES_IMU: its compass only (mgauss, as ArduPilot's;
        it then shadows HIGHRES_IMU's compass 0), not a second IMU 0 stream."""
        kept: list[tuple[str, Record]] = []
        for origin, rec in out:
            if isinstance(rec, ImuSample):
                if self.seen_highres_imu:
                    continue
            elif isinstance(rec, MagSample):
                self.seen_scaled_mag0 = True
            kept.append((origin, rec))
        return kept

    def _m_HIGHRES_IMU(self, msg: Any) -> list[tuple[str, Record]]:
        """accel m/s^2, gyro rad/s, mag gauss -> mgauss; only the fields ``fields_updated`` flags as new."""
        self.seen_highres_imu = True
        updated = int(msg.fields_updated)
        t_s = self.clock.stamp("HIGHRES_IMU", msg.time_usec * 1e-6)
        if t_s is None:
            return []
        out: list[tuple[str, Record]] = []
        index = int(getattr(msg, "id", 0))
        if updated & HIGHRES_ACCEL_GYRO == HIGHRES_ACCEL_GYRO:
            gyro = (float(msg.xgyro), float(msg.ygyro), float(msg.zgyro))
            accel = (float(msg.xacc), float(msg.yacc), float(msg.zacc))
            if _finite(*gyro, *accel):
                out.append(("HIGHRES_IMU", WireImuSample(t_s, gyro, accel, index)))
            else:
                self.counts["nonfinite"] += 1
        if updated & HIGHRES_MAG == HIGHRES_MAG:
            mag = (msg.xmag * 1000.0, msg.ymag * 1000.0, msg.zmag * 1000.0)  # gauss -> mgauss
            if self.seen_scaled_mag0:
                self.counts["highres_mag_shadowed"] += 1
            elif not _finite(*mag):
                self.counts["nonfinite"] += 1
            elif not any(mag):
                self.counts["mag_zero"] += 1
            elif self.mag_index is None or self.mag_index == index:
                out.append(("HIGHRES_IMU", WireMagSample(t_s, mag, index)))
        if updated & HIGHRES_TEMPERATURE and math.isfinite(msg.temperature) and self._keep():
            out.append(
                ("HIGHRES_IMU", TemperatureSample(t_s, float(msg.temperature), _IMU_SENSOR_NAMES[index]))
            )
        return out

    def _m_ATTITUDE_QUATERNION(self, msg: Any) -> list[tuple[str, Record]]:
        if self.seen_attitude:
            return []
        q = (msg.q1, msg.q2, msg.q3, msg.q4)  # w, x, y, z
        if not _finite(*q, msg.rollspeed, msg.pitchspeed, msg.yawspeed) or sum(v * v for v in q) < 0.25:
            self.counts["nonfinite"] += 1
            return []
        t_s = self.clock.stamp("ATTITUDE_QUATERNION", msg.time_boot_ms * 1e-3)
        if t_s is None:
            return []
        from magcomp.core.rotations import euler_from_quat

        norm = math.sqrt(sum(v * v for v in q))
        roll, pitch, yaw = euler_from_quat(np.array(q, dtype=np.float64) / norm)
        rates = _vec(msg.rollspeed, msg.pitchspeed, msg.yawspeed)
        return [("ATTITUDE", AttitudeSample(t_s, float(roll), float(pitch), float(yaw), rates))]

    def _m_ACTUATOR_OUTPUT_STATUS(self, msg: Any) -> list[tuple[str, Record]]:
        """PX4's actuator outputs (PWM us on PWM outputs), as servo channels 1..32 while no
        SERVO_OUTPUT_RAW is seen; inactive outputs (``active`` bit clear) are left out."""
        if self.seen_servo_output:
            return []
        t_s = self.clock.stamp("ACTUATOR_OUTPUT_STATUS", msg.time_usec * 1e-6)
        if t_s is None:
            return []
        active = int(msg.active)
        pwm = {
            ch: float(v)
            for ch, v in enumerate(msg.actuator, start=1)
            if active >> (ch - 1) & 1 and math.isfinite(v)
        }
        return [("ACTUATOR_OUTPUT_STATUS", PwmRecord(t_s, "servo", pwm))]

    # --- position and UTC time (for the Earth-field model at the vehicle) ----------------------------------
    # Stamped with the latest source time: GPS_RAW_INT.time_usec may be Unix time or time since boot, and
    # a position needs no sub-second timing.
    def _m_GPS_RAW_INT(self, msg: Any) -> list[tuple[str, Record]]:
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7  # degE7
        fix_ok = int(msg.fix_type) >= 3 and (msg.lat != 0 or msg.lon != 0) and abs(lat) <= 90.0
        year = decimal_year_from_unix(msg.time_usec * 1e-6)  # NaN for time since boot
        pos = PositionSample(self.clock.last_t_s, lat, lon, msg.alt * 1e-3, year, fix_ok)  # alt mm MSL
        return [("GPS_RAW_INT", pos)]

    def _m_GLOBAL_POSITION_INT(self, msg: Any) -> list[tuple[str, Record]]:
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
        fix_ok = (msg.lat != 0 or msg.lon != 0) and abs(lat) <= 90.0  # (0, 0) before the EKF has an origin
        pos = PositionSample(self.clock.last_t_s, lat, lon, msg.alt * 1e-3, fix_ok=fix_ok)  # alt mm MSL
        return [("GLOBAL_POSITION_INT", pos)]

    def _m_SYSTEM_TIME(self, msg: Any) -> list[tuple[str, Record]]:
        year = decimal_year_from_unix(msg.time_unix_usec * 1e-6)  # 0 / 1970 / 1980: clock not set
        return [] if math.isnan(year) else [("SYSTEM_TIME", TimeSample(self.clock.last_t_s, year))]

    # --- DataFlash -----------------------------------------------------------------------------------------
    def _df_values(self, msg: Any) -> SimpleNamespace:
        """Field values of a DFReader message, read once through cached converters.

        Same values as ``DFMessage.__getattr__`` (type conversion, then the format's multiplier), about 8x
        cheaper when several fields are read.
        """
        fmt = msg.fmt
        conv = self._df_converters.get(id(fmt))
        if conv is None or conv[0] is not fmt:
            cols = []
            for i, name in enumerate(fmt.columns):
                to_type = fmt.msg_types[i]
                if to_type is str or fmt.format[i] in "aZM" or to_type is bytes:
                    cols.append((name, i, None, 0.0))
                else:
                    cols.append((name, i, to_type, fmt.msg_mults[i] or 0.0))
            conv = (fmt, cols)
            self._df_converters[id(fmt)] = conv
        elements = msg._elements
        values: dict[str, Any] = {"mtype": fmt.name, "fieldnames": fmt.columns}
        for name, i, to_type, mult in conv[1]:
            if to_type is None:
                values[name] = getattr(msg, name)
            elif mult and msg._apply_multiplier:
                values[name] = to_type(elements[i]) * mult
            else:
                values[name] = to_type(elements[i])
        return SimpleNamespace(**values)

    def dataflash(self, msg: Any) -> list[tuple[str, Record]]:
        try:
            v = self._df_values(msg)
        except (ValueError, TypeError, OverflowError, IndexError):
            # a field that is not a number of its type (a text log line with NUL bytes or cut short):
            # the record is dropped and counted, the rest of the log is read
            self.counts["unreadable_records"] += 1
            return []
        mtype = v.mtype
        if mtype == "PARM":
            value = float(v.Value)
            self.onboard_comp.param(str(v.Name), value)  # (a NaN COMPASS_MOT* is reported there as invalid)
            return [("PARM", ParamSample(self.clock.last_t_s, str(v.Name), value))]
        if mtype == "MSG":
            return self._df_msg(str(v.Message))
        if mtype in ("GPS", "GPS2", "POS"):
            return self._df_position(v)
        if hasattr(v, "TimeUS"):
            raw_s = v.TimeUS * 1e-6
        elif hasattr(v, "TimeMS"):
            raw_s = v.TimeMS * 1e-3
        else:
            return []
        base = mtype.rstrip("0123456789")
        suffix = mtype[len(base) :]
        # the instance field: I (MAG, IMU, GPS), Inst (BAT in recent 4.x) or Instance (BAT in early 4.x)
        index = (
            int(getattr(v, "I", getattr(v, "Inst", getattr(v, "Instance", 0))))
            if not suffix
            else int(suffix) - 1
        )
        if base in ("MAG", "IMU") and not 0 <= index < DATAFLASH_MAX_INSTANCES:
            # DataFlash has no checksum: a corrupt instance byte would make a phantom compass or IMU
            self.counts["dataflash_bad_instance"] += 1
            return []
        stream = f"{base}{index}"
        if base == "MAG":
            return self._df_mag(v, stream, raw_s, index)
        if base == "IMU":
            return self._df_imu(v, stream, raw_s, index)
        if base == "ATT":
            if not _finite(v.Roll, v.Pitch, v.Yaw):
                self.counts["nonfinite"] += 1
                return []
            t_s = self.clock.stamp(stream, raw_s)
            if t_s is None:
                return []
            r, p, y = (math.radians(v) for v in (v.Roll, v.Pitch, v.Yaw))
            return [("ATT", AttitudeSample(t_s, r, p, y))]
        if base == "RCOU":
            return self._df_rcou(v, stream, raw_s)
        if base == "CTUN":
            if hasattr(v, "NavRoll"):  # Plane's CTUN: ThO (4.x) / ThrOut (3.x) in percent
                thr = float(getattr(v, "ThO", getattr(v, "ThrOut", math.nan))) * 0.01
            elif hasattr(v, "ThO"):
                thr = float(v.ThO)
            elif hasattr(v, "ThrOut"):
                thr = v.ThrOut * 1e-3 if isinstance(v.ThrOut, int) else float(v.ThrOut)
            else:
                return []
            t_s = self.clock.stamp(stream, raw_s)
            if t_s is None or not math.isfinite(thr):
                return []
            self.onboard_comp.throttle_01 = min(1.0, max(0.0, thr))  # the throttle the compass was given
            return [("CTUN", ThrottleRecord(t_s, "ctun", min(1.0, max(0.0, thr))))]
        if base in ("CURR", "BAT"):
            volt = v.Volt * 0.01 if isinstance(v.Volt, int) else float(v.Volt)  # old logs: cV, cA
            curr = v.Curr * 0.01 if isinstance(v.Curr, int) else float(v.Curr)
            t_s = self.clock.stamp(stream, raw_s)
            if t_s is None:
                return []
            return [(base, PowerSample(t_s, volt, curr, index))] if self._keep() else []
        return []

    def _df_position(self, v: Any) -> list[tuple[str, Record]]:
        """DataFlash GPS/GPS2 (Status >= 3 is a 3D fix; GPS week + ms of week -> UTC) and POS (EKF position).

        Old logs (ArduPilot <= 3.3) have TimeMS = GPS time of week, Week, and T = time since boot (ms);
        newer ones TimeUS, GMS and GWk. Lat/Lng are degrees after DFReader's 1e-7 multiplier; an integer
        column without it (text logs) is degE7. Stamped with the latest source time (see GPS_RAW_INT)."""
        lat, lon = getattr(v, "Lat", math.nan), getattr(v, "Lng", math.nan)
        alt = float(getattr(v, "Alt", math.nan))
        if isinstance(lat, int) and isinstance(lon, int) and (abs(lat) > 180 or abs(lon) > 360):
            lat, lon = lat * 1e-7, lon * 1e-7
        lat, lon = float(lat), float(lon)
        if not _finite(lat, lon):
            self.counts["nonfinite"] += 1
            return []
        known = (lat != 0.0 or lon != 0.0) and abs(lat) <= 90.0 and abs(lon) <= 180.0
        if v.mtype == "POS":
            return [("POS", PositionSample(self.clock.last_t_s, lat, lon, alt, fix_ok=known))]
        if hasattr(v, "GWk"):
            year = decimal_year_from_gps(float(v.GWk), float(v.GMS))
        elif hasattr(v, "Week") and hasattr(v, "TimeMS"):
            year = decimal_year_from_gps(float(v.Week), float(v.TimeMS))
        else:
            year = math.nan
        fix_ok = known and int(getattr(v, "Status", 0)) >= 3
        return [("GPS", PositionSample(self.clock.last_t_s, lat, lon, alt, year, fix_ok))]

    def _df_msg(self, text: str) -> list[tuple[str, Record]]:
        uid = uid_from_board_msg(text)
        if uid is not None:
            if uid == self.uid:
                return []
            self.uid = uid
            return [("MSG", IdentitySample(self.clock.last_t_s, uid, 1))]
        lowered = text.lower()
        vtype = -1
        if "copter" in lowered:
            vtype = 2
        elif "plane" in lowered:
            vtype = 1
        elif "rover" in lowered:
            vtype = 10
        elif "sub" in lowered.split():
            vtype = 12
        if vtype < 0 or self.vehicle_type >= 0:
            return []
        self.vehicle_type, self.autopilot = vtype, 3  # MAV_AUTOPILOT_ARDUPILOTMEGA
        return [("MSG", HeartbeatSample(self.clock.last_t_s, vtype, 3, 1))]

    def _df_mag(self, v: Any, stream: str, raw_s: float, index: int) -> list[tuple[str, Record]]:
        if self.mag_index is not None and index != self.mag_index:
            return []
        field = _vec(v.MagX, v.MagY, v.MagZ)
        onboard: Float3 | None = None
        # the applied motor compensation: MOfsX/Y/Z in ArduPilot up to 4.0 (MAG, MAG2, MAG3), MOX/MOY/MOZ
        # since the instance field I (AP_Compass/LogStructure.h)
        mo = ("MOfsX", "MOfsY", "MOfsZ") if hasattr(v, "MOfsX") else ("MOX", "MOY", "MOZ")
        if self.undo_motor_comp and hasattr(v, mo[0]):
            mofs = _vec(*(getattr(v, a) for a in mo))
            if mofs.any() and np.isfinite(mofs).all():
                if self._df_motor_comp_off(index):
                    # the autopilot applied none (COMPASS_MOTCT = 0, no per-motor compensation): a corrupt
                    # record (DataFlash has no checksum), the logged field is the one it used
                    self.counts["motor_comp_ignored"] += 1
                else:
                    field = field - mofs
                    onboard = (float(mofs[0]), float(mofs[1]), float(mofs[2]))
                    self.counts["motor_comp_removed"] += 1
                    self.onboard_comp.record(index, mofs)
        if not np.isfinite(field).all():
            self.counts["nonfinite"] += 1
            return []
        if not field.any():  # (0, 0, 0): compass not read yet
            self.counts["mag_zero"] += 1
            return []
        t_s = self.clock.stamp(stream, raw_s)
        return [] if t_s is None else [("MAG", MagSample(t_s, field, index, onboard))]

    def _df_motor_comp_off(self, index: int) -> bool:
        """True when the logged parameters say the autopilot adds no motor offset to compass ``index``:
        COMPASS_MOTCT = 0 and, for compass 0, no per-motor compensation (COMPASS_PMOT_EN). Unknown parameters
        (none logged yet): False."""
        return motor_comp_known_off(self.onboard_comp.params, index)

    def _df_imu(self, v: Any, stream: str, raw_s: float, index: int) -> list[tuple[str, Record]]:
        gyro = _vec(v.GyrX, v.GyrY, v.GyrZ)
        accel = _vec(v.AccX, v.AccY, v.AccZ)
        if not (np.isfinite(gyro).all() and np.isfinite(accel).all()):
            self.counts["nonfinite"] += 1
            return []
        t_s = self.clock.stamp(stream, raw_s)
        if t_s is None:
            return []
        out: list[tuple[str, Record]] = []
        if index == 0 or self._keep():
            out.append(("IMU", ImuSample(t_s, gyro, accel, index)))
        temp = getattr(v, "T", getattr(v, "Temp", None))
        if temp is not None and temp != 0 and math.isfinite(temp) and self._keep():
            out.append(("IMU", TemperatureSample(t_s, float(temp), f"imu{index}")))
        return out

    def _df_rcou(self, v: Any, stream: str, raw_s: float) -> list[tuple[str, Record]]:
        cols = self._pwm_columns.get(v.mtype)
        if cols is None:
            cols = []
            for name in v.fieldnames:
                m = _PWM_COLUMN.match(name)
                if m:
                    cols.append((name, int(m.group(1))))
            self._pwm_columns[v.mtype] = cols
        t_s = self.clock.stamp(stream, raw_s)
        if t_s is None:
            return []
        return [("RCOU", PwmRecord(t_s, "servo", {ch: float(getattr(v, name)) for name, ch in cols}))]


# --- readers: each yields decoded messages ---------------------------------------------------------------


def _mavlink_module() -> Any:
    from magcomp.adapters.dialect import ensure_dialect

    return ensure_dialect()


def _next_magic(data: bytes, start: int) -> int:
    a = data.find(b"\xfd", start)
    b = data.find(b"\xfe", start)
    if a < 0:
        return b
    if b < 0:
        return a
    return min(a, b)


class _ViewBase(tuple):
    """Base of the decoded-message views: a named tuple of the payload fields in wire order + srcSystem."""

    __slots__ = ()
    msgname = ""

    def get_type(self) -> str:
        return self.msgname

    def get_srcSystem(self) -> int:  # pymavlink's spelling
        return int(self[-1])


# (payload Struct, its size, crc_extra as 1 byte, view builder (fields tuple, srcSystem) -> view, handler)
FrameDecoder = tuple[Any, int, bytes, Callable[[tuple[Any, ...], int], Any], Callable[[Any], Any]]


def _view_builder(msgtype: Any) -> Callable[[tuple[Any, ...], int], Any]:
    """A builder of the message's view from ``Struct.unpack`` output, with pymavlink's field values.

    Fields are in wire order (``ordered_fieldnames``), which is the order of the unpacked tuple, so a
    message without arrays or strings needs no reordering at all. Arrays become lists and ``char[N]``
    fields strings cut at the first NUL (ASCII, errors replaced), as pymavlink's generated classes do.
    """
    names = list(msgtype.ordered_fieldnames)
    from collections import namedtuple

    base = namedtuple(f"{msgtype.msgname}_view", [*names, "srcSystem"])  # type: ignore[misc]
    cls = type(base.__name__, (base, _ViewBase), {"__slots__": (), "msgname": msgtype.msgname})
    new = tuple.__new__
    fmt = msgtype.unpacker.format
    has_str = "s" in (fmt.decode() if isinstance(fmt, bytes) else fmt)
    lengths = list(msgtype.lengths)
    if not has_str and sum(lengths) == len(lengths):

        def build(t: tuple[Any, ...], src: int) -> Any:
            return new(cls, (*t, src))

        return build
    # a layout of (first element, count, kind): kind 0 scalar, 1 array, 2 string
    layout: list[tuple[int, int, int]] = []
    i = 0
    for n_el, array_len in zip(lengths, msgtype.array_lengths, strict=True):
        is_str = array_len > 0 and n_el == 1  # char[N]: one "Ns" element
        layout.append((i, n_el, 2 if is_str else (1 if n_el > 1 else 0)))
        i += n_el

    def build_slow(t: tuple[Any, ...], src: int) -> Any:
        values: list[Any] = []
        for first, count, kind in layout:
            if kind == 0:
                values.append(t[first])
            elif kind == 1:
                values.append(list(t[first : first + count]))
            else:
                raw = t[first]
                values.append(raw.split(b"\x00", 1)[0].decode("ascii", errors="replace"))
        values.append(src)
        return new(cls, values)

    return build_slow


def frame_decoders(mod: Any, handlers: dict[str, Callable[[Any], Any]]) -> dict[int, FrameDecoder]:
    """Precompiled decoders by message id, from the dialect's message classes, for the ids in ``handlers``."""
    out: dict[int, FrameDecoder] = {}
    for name, handler in handlers.items():
        msgtype = mod.mavlink_map[getattr(mod, f"MAVLINK_MSG_ID_{name}")]
        st = msgtype.unpacker
        out[msgtype.id] = (st, st.size, bytes([msgtype.crc_extra]), _view_builder(msgtype), handler)
    return out


def _crc_function(mod: Any) -> Callable[[Any, int], int]:
    """The CRC-16/MCRF4XX (X.25) function of the dialect module: fastcrc's when pymavlink uses it."""
    fast = getattr(mod, "mcrf4xx", None)
    if fast is not None:
        return fast
    x25 = mod.x25crc

    def slow(buf: Any, crc: int) -> int:
        acc = x25()
        acc.crc = crc
        acc.accumulate(bytes(buf))
        return int(acc.crc)

    return slow


_TLOG_STAMP = struct.Struct(">Q")  # a tlog record's receive time, us since 1970

#: bytes read from a log file at a time (the tlog / raw MAVLink reader keeps at most this plus one frame)
READ_CHUNK_BYTES = 1 << 20
#: the longest MAVLink frame (MAVLink 2: 10-byte header, 255-byte payload, CRC, 13-byte signature)
_MAX_FRAME = 280


def iter_mavlink_frames(
    data: bytes,
    decoders: dict[int, FrameDecoder],
    counts: dict[str, int],
    ts_len: int,
    *,
    crc16: Callable[[Any, int], int],
    ignore_crc: bool = False,
    reference_mav: Any = None,
    final: bool = True,
    rx_into: Any = None,
) -> Generator[tuple[Callable[[Any], Any], Any], None, int]:
    """Walk tlog framing (``ts_len`` = 8) or a raw MAVLink stream (0); yield (handler, message) for the ids
    in ``decoders`` only, CRC-checked (X.25 with the message's crc_extra) and unpacked with a precompiled
    Struct (MAVLink 2 payloads cut by zero-truncation are padded with zeros). Other ids are skipped unread.

    ``data`` is the whole input (``final``) or one chunk of it: then the walk stops where a frame (and the
    byte after it, which checks its framing) might not be whole yet, and returns the offset to resume from,
    with the next chunk appended; the messages and counts are the same as for the whole input at once.
    ``reference_mav`` (tests): decode the same frames with pymavlink's ``MAVLink.decode`` instead.
    ``rx_into``: an object whose ``rx_s`` and ``rx_src`` are set to each yielded message's tlog receive
    stamp (s) and sender's system id before it is yielded (for :class:`StreamOffsets`); raw streams
    (``ts_len`` 0) have no receive stamp.
    """
    mav_error = sys.modules[type(reference_mav).__module__].MAVError if reference_mav is not None else None
    view = memoryview(data)
    n = len(data)
    p = 0
    magics = (MAGIC_V1, MAGIC_V2)
    get = decoders.get
    # a chunk: stop while a whole frame, its timestamp and the next frame's magic may still be missing
    limit = n - ts_len - 8 if final else n - 2 * ts_len - _MAX_FRAME - 1
    while p <= limit:
        h = p + ts_len
        magic = data[h]
        if magic == MAGIC_V2:
            if h + 10 > n:
                counts["truncated"] += 1
                break
            mlen = data[h + 1]
            start = h + 10
            crc_at = start + mlen
            end = crc_at + (15 if data[h + 2] & 1 else 2)
            msgid = data[h + 7] | (data[h + 8] << 8) | (data[h + 9] << 16)
        elif magic == MAGIC_V1:
            mlen = data[h + 1]
            start = h + 6
            crc_at = start + mlen
            end = crc_at + 2
            msgid = data[h + 5]
        else:
            q = _next_magic(data, h + 1)
            # no magic in the rest of a chunk: skip up to where the next chunk's first timestamp may begin
            q = (n if final else n - ts_len) if q < 0 else q - ts_len
            q = max(q, p + 1)
            counts["garbage_bytes"] += q - p
            p = q
            continue
        if end > n:
            counts["truncated"] += 1
            break
        next_ok = end + ts_len >= n or data[end + ts_len] in magics
        dec = get(msgid)
        if dec is not None:
            st, size, extra, build, handler = dec
            if mav_error is not None:
                try:
                    msg = reference_mav.decode(bytearray(data[h:end]))
                except mav_error:
                    msg = None
            elif ignore_crc or crc16(extra, crc16(view[h + 1 : crc_at], 0xFFFF)) == (
                data[crc_at] | (data[crc_at + 1] << 8)
            ):
                if mlen >= size:
                    fields = st.unpack_from(data, start)
                else:  # MAVLink 2 zero-truncation: the missing tail is zeros
                    fields = st.unpack(data[start:crc_at] + bytes(size - mlen))
                msg = build(fields, data[start - 5] if magic == MAGIC_V2 else data[h + 3])
            else:
                msg = None
            if msg is None:
                if next_ok:
                    counts["bad_crc"] += 1
                    p = end
                else:
                    counts["garbage_bytes"] += 1
                    p += 1
                continue
            counts["messages"] += 1
            if rx_into is not None and ts_len == 8:
                rx_into.rx_s = _TLOG_STAMP.unpack_from(data, p)[0] * 1e-6
                rx_into.rx_src = data[h + 5] if magic == MAGIC_V2 else data[h + 3]
            yield handler, msg
        elif not next_ok:  # framing of an unchecked packet is doubtful: resynchronise byte by byte
            counts["garbage_bytes"] += 1
            p += 1
            continue
        p = end
    return p


def iter_mavlink_file(
    f: BinaryIO,
    head: bytes,
    decoders: dict[int, FrameDecoder],
    counts: dict[str, int],
    ts_len: int,
    **kw: Any,
) -> Iterator[tuple[Callable[[Any], Any], Any]]:
    """:func:`iter_mavlink_frames` over an open file read ``READ_CHUNK_BYTES`` at a time, ``head`` being what
    was already read from it: memory stays at a chunk, whatever the file's length."""
    buf = head
    while True:
        more = f.read(READ_CHUNK_BYTES)
        if not more:
            yield from iter_mavlink_frames(buf, decoders, counts, ts_len, final=True, **kw)
            return
        buf += more
        p = yield from iter_mavlink_frames(buf, decoders, counts, ts_len, final=False, **kw)
        buf = buf[p:]


def _sniff_mavlink_stream(data: bytes) -> int | None:
    """8 for tlog framing, 0 for a raw MAVLink stream, None when neither starts the data."""
    if len(data) >= 16 and data[8] in (MAGIC_V1, MAGIC_V2):
        return 8
    if len(data) >= 8 and data[0] in (MAGIC_V1, MAGIC_V2):
        return 0
    return None


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """pymavlink's DFReader prints warnings ("bad header ...") to stdout/stderr; the library must not
    print."""
    sink = io.StringIO()
    with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
        yield


@contextlib.contextmanager
def _quiet_c_streams() -> Iterator[None]:
    """Silence file descriptors 1 and 2 for the block: pymavlink's Cython indexer (``dfindexer``, run when a
    DFReader_binary is built) writes "bad header ..." for every byte it cannot frame straight to the C
    streams, out of :func:`_quiet`'s reach (122815 lines for 200 kB of random bytes). Used only around that
    constructor (a file replay, not the live daemon); a no-op when the descriptors cannot be duplicated."""
    import ctypes
    import os

    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved: list[tuple[int, int]] = []
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
    except OSError:
        yield
        return
    try:
        for fd in (1, 2):
            with contextlib.suppress(OSError):
                saved.append((fd, os.dup(fd)))
                os.dup2(devnull, fd)
        yield
    finally:
        with contextlib.suppress(Exception):
            ctypes.CDLL(None).fflush(None)  # what C stdio still buffers goes to /dev/null too
        for fd, old in saved:
            os.dup2(old, fd)
            os.close(old)
        os.close(devnull)


#: ArduPilot logs at most this many compasses (MAG instance I) and IMUs (IMU I): COMPASS_MAX_INSTANCES and
#: INS_MAX_INSTANCES are 3; a larger instance in a DataFlash log is a corrupt byte, not a sensor
DATAFLASH_MAX_INSTANCES = 3

_DF_HEAD = b"\xa3\x95"
_DF_FMT_TYPE = 0x80
_DF_FMT_LEN = 89


# Bytes around each point of damage that are not believed. DataFlash has no checksum: a corrupt byte is
# seen only when it breaks the framing (a header, a type or a length: ~3 of a message's bytes), while every
# other corrupt byte silently changes a value that may stay plausible. Damage at a rate p per byte is seen
# about every 1/(3p) messages and leaves ~L/3 (10-30) unseen corrupt messages per point seen, spread at the
# same density. A margin wider than the spacing of the points seen drops the whole damaged region: 8 KiB
# (0.05-0.5 s of a log at 16-160 KiB/s) covers points seen every ~5 KiB, i.e. damage rates down to ~0.03 %
# of bytes, for at most 16 KiB of lost data per isolated point.
DAMAGE_MARGIN_BYTES = 8192
#: bytes of each DataFlash format character (ArduPilot's AP_Logger; what DFReader unpacks)
_DF_CHAR_BYTES = {
    "a": 64, "b": 1, "B": 1, "g": 2, "h": 2, "H": 2, "i": 4, "I": 4, "f": 4, "n": 4, "N": 16, "Z": 64, "c": 2,
    "C": 2, "e": 4, "E": 4, "L": 4, "d": 8, "M": 1, "q": 8, "Q": 8,
}  # fmt: skip


def _df_fmt_valid(data: Any, p: int) -> bool:
    """An FMT message at ``p`` whose definition holds together: known format characters whose sizes add up to
    its length, a name and one column per character. DataFlash has no checksum: a byte hit in a format string
    would otherwise define a message wrongly (or make pymavlink's reader raise)."""
    body = bytes(data[p + 3 : p + _DF_FMT_LEN])
    length = body[1]
    fmt = body[6:22].split(b"\0", 1)[0]
    cols = body[22:86].split(b"\0", 1)[0]
    name = body[2:6].split(b"\0", 1)[0]
    try:
        fmt_s, cols_s, name_s = fmt.decode("ascii"), cols.decode("ascii"), name.decode("ascii")
    except UnicodeDecodeError:
        return False
    if not name_s.isprintable() or not name_s or not cols_s.isprintable():
        return False
    if any(c not in _DF_CHAR_BYTES for c in fmt_s):
        return False
    if body[0] == _DF_FMT_TYPE:
        return length == _DF_FMT_LEN
    n_cols = len(cols_s.split(",")) if cols_s else 0  # old logs define empty messages (STRT: no fields)
    return 3 + sum(_DF_CHAR_BYTES[c] for c in fmt_s) == length and n_cols == len(fmt_s)


class IntactSpans(NamedTuple):
    """What :func:`dataflash_intact_spans` believes of a binary DataFlash log."""

    spans: list[tuple[int, int]]  # [start, end) byte ranges of believed messages, in file order
    damaged_bytes: int  # bytes that are no message (corrupt framing, or garbage)
    dropped_bytes: int  # whole messages not believed: within the margin of damage
    resyncs: int  # points of damage resynchronised past


def _df_framed_next(data: Any, q: int, lengths: dict[int, int], n: int) -> bool:
    """A message of a known type starts at ``q`` and ends where the next header (or the file) starts."""
    if q < 0 or q + 3 > n:
        return False
    mlen = lengths.get(data[q + 2])
    end = q + mlen if mlen else -1
    return bool(mlen) and (end == n or (end + 2 <= n and data[end] == 0xA3 and data[end + 1] == 0x95))


def dataflash_intact_spans(
    data: bytes | memoryview | mmap.mmap, margin_bytes: int = DAMAGE_MARGIN_BYTES
) -> IntactSpans:
    """The byte ranges of a binary DataFlash log that hold whole messages, and how many bytes lie between
    them (damage). A message is believed when its type is known (from the FMT messages before it), the next
    message header (or the end of the file) follows it exactly, and it lies more than ``margin_bytes`` from
    any damage (FMT messages excepted: the formats are kept so that later messages stay readable, also those
    within the margin before it); anything else is skipped up to the next header. An FMT whose definition
    does not hold together (format characters, length, columns: a byte hit inside it) is not believed, and
    messages of a type whose FMT was seen but not believed are skipped, not taken for damage, when a whole
    message of a known type follows them (else one lost FMT quarantined the whole log). pymavlink's reader
    stops indexing at the first unknown message type, dropping the rest of a damaged log, and prints about
    every bad byte: it gets the believed messages only."""
    n = len(data)
    lengths: dict[int, int] = {_DF_FMT_TYPE: _DF_FMT_LEN}
    lost: set[int] = set()  # types whose FMT was seen but not believed
    spans: list[tuple[int, int]] = []
    skipped = 0
    find = bytes(data).find if isinstance(data, memoryview) else data.find
    p = find(_DF_HEAD)
    if p < 0:
        return IntactSpans([], n, 0, 0)
    skipped += p
    start = p
    resyncs = 0
    quarantine_end = -1  # messages starting before this offset follow damage too closely to be believed
    recent: deque[int] = deque(maxlen=4096)  # starts of the latest believed messages (each >= 3 bytes)
    while p + 3 <= n:
        mtype = data[p + 2]
        mlen = lengths.get(mtype)
        end = p + mlen if mlen else -1
        framed = mlen and (end == n or (end + 2 <= n and data[end] == 0xA3 and data[end + 1] == 0x95))
        if framed and mtype == _DF_FMT_TYPE and not _df_fmt_valid(data, p):
            # a whole FMT whose definition does not hold together (a byte hit inside it): skipped alone, its
            # type's messages then skipped as types without an FMT, the rest believed
            if p > start and p >= quarantine_end:
                spans.append((start, p))
            lost.add(data[p + 3])
            skipped += end - p
            p = start = end
            continue
        if framed:
            if mtype == _DF_FMT_TYPE and data[p + 4] >= 3:
                lengths[data[p + 3]] = data[p + 4]
            if p < quarantine_end:
                if mtype == _DF_FMT_TYPE:
                    spans.append((p, end))
                start = end
            else:
                recent.append(p)
            p = end
            continue
        if mlen and end > n:  # a message cut by the end of the file
            break
        q = find(_DF_HEAD, p + 1) if mtype in lost else -1
        hops = 0
        while q >= 0 and q + 3 <= n and data[q + 2] in lost and hops < 8:
            q, hops = find(_DF_HEAD, q + 1), hops + 1  # more messages of types whose FMT was lost
        if mtype in lost and _df_framed_next(data, q, lengths, n):
            # types whose FMT was seen but not believed, before a whole message: those messages only are
            # skipped, not damage (counting each of them as damage quarantined the whole log); any other
            # unknown type is damage (a hit type byte)
            if p > start and p >= quarantine_end:
                spans.append((start, p))
            skipped += q - p
            p = start = q
            continue
        # damage: close the intact span short of the margin and resynchronise on the next header (no header
        # after it: the log's unfinished last write, nothing to distrust)
        if mtype == _DF_FMT_TYPE and p + 4 <= n and data[p + 3] not in lengths:
            lost.add(data[p + 3])  # an FMT not believed (its framing hit): its type's messages have no format
        q = find(_DF_HEAD, p + 1)
        q = n if q < 0 else q
        cut = p
        formats: list[int] = []  # FMT messages within the margin before the damage: kept all the same
        while q < n and recent and recent[-1] > p - margin_bytes and recent[-1] >= start:
            cut = recent.pop()
            if data[cut + 2] == _DF_FMT_TYPE:
                formats.append(cut)
        if cut > start:
            spans.append((start, cut))
        spans.extend((f, f + _DF_FMT_LEN) for f in reversed(formats))
        recent.clear()
        skipped += q - p
        resyncs += q < n
        p = start = q
        quarantine_end = q + margin_bytes
    if p > start:
        spans.append((start, min(p, n)))
    skipped += max(0, n - max(p, spans[-1][1] if spans else 0))
    kept = sum(b - a for a, b in spans)
    return IntactSpans(spans, skipped, max(0, n - kept - skipped), resyncs)


def _dataflash_repaired(path: Path, counts: dict[str, int]) -> Path | None:
    """A temporary copy of a damaged binary DataFlash log holding its intact messages only (None when the
    log is intact, or cannot be read). The log is mapped, not read into memory."""
    import tempfile

    name = ""
    try:
        with path.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            spans, skipped, dropped, resyncs = dataflash_intact_spans(data)
            tail = len(data) - (spans[-1][1] if spans else 0)
            if not spans or (len(spans) == 1 and spans[0][0] == 0 and tail < 528):
                return None  # intact (a short tail of garbage is normal at the end of a log)
            counts["garbage_bytes"] += skipped
            counts["dataflash_resyncs"] += resyncs
            counts["dataflash_dropped_bytes"] += dropped
            fd, name = tempfile.mkstemp(prefix="magcomp-", suffix=".bin")
            with os.fdopen(fd, "wb") as out:
                for a, b in spans:
                    for c in range(a, b, READ_CHUNK_BYTES):
                        out.write(data[c : min(b, c + READ_CHUNK_BYTES)])
    except (OSError, ValueError):  # unreadable, empty (nothing to map), or no room for the copy
        if name:
            with contextlib.suppress(OSError):
                os.unlink(name)
        return None
    return Path(name)


def _iter_dataflash(path: Path, counts: dict[str, int], text: bool) -> Iterator[Any]:
    repaired = None if text else _dataflash_repaired(path, counts)
    try:
        yield from _iter_dataflash_file(repaired or path, path, counts, text)
    finally:
        if repaired is not None:
            with contextlib.suppress(OSError):
                repaired.unlink()


def _iter_dataflash_file(path: Path, shown: Path, counts: dict[str, int], text: bool) -> Iterator[Any]:
    from pymavlink import DFReader

    try:
        with _quiet(), _quiet_c_streams():
            reader: Any = (
                DFReader.DFReader_text(str(path), zero_time_base=False)
                if text
                else DFReader.DFReader_binary(str(path), zero_time_base=False)
            )
    except (UnicodeDecodeError, ValueError, IndexError, KeyError, OSError) as exc:
        raise InputError(f"{shown}: not a readable DataFlash log ({type(exc).__name__})") from None
    wanted = list(WANTED_DATAFLASH)
    try:
        while True:
            batch: list[Any] = []
            with _quiet():
                for _ in range(2000):
                    m = reader.recv_match(type=wanted)
                    if m is None:
                        break
                    batch.append(m)
            for m in batch:
                counts["messages"] += 1
                yield m
            if len(batch) < 2000:
                break
    except (UnicodeDecodeError, ValueError, IndexError, KeyError) as exc:
        counts["dataflash_errors"] += 1
        if counts["messages"] == 0:
            raise InputError(f"{shown}: not a readable DataFlash log ({type(exc).__name__})") from None
    finally:
        with contextlib.suppress(Exception):
            reader.close()


# --- the source --------------------------------------------------------------------------------------------


def _is_live(target: str) -> bool:
    if target.startswith(LIVE_PREFIXES):
        return True
    dev = target.rsplit(":", 1)[0] if re.search(r":\d+$", target) else target
    try:
        return stat.S_ISCHR(os.stat(dev).st_mode)
    except OSError:
        return False


def _is_ulog(target: str) -> bool:
    """A ULog file: ``.ulg`` or the ULog magic, read from a regular file only (never from a link)."""
    if _is_live(target):
        return False
    path = Path(target)
    if path.suffix.lower() == ".ulg":
        return path.is_file()
    try:
        with path.open("rb") as f:
            return f.read(4) == b"ULog"
    except OSError:
        return False


#: a locked UDP peer silent this long may be replaced by another sender of vehicle data (a flight
#: controller that restarted on a new port); until then, datagrams from anyone else are dropped
PEER_RELOCK_S = 5.0
#: foreign senders named in a warning; the rest are counted only
FOREIGN_NAMED = 5
_MAV_TYPE_GCS = 6


class UdpPeerLock:
    """The trust boundary of a UDP link (``udpin:``, ``udp:``, ``udpout:``): the link follows one peer.

    ``udpin``: the first address whose datagram carries vehicle data (a sensor, attitude, output or
    parameter message, or a HEARTBEAT that is not a ground station's) becomes the flight controller;
    datagrams from any other address are dropped before the MAVLink parser sees them (counted as
    ``foreign_datagrams``, the first senders named in a warning), and what the link sends goes to that
    address only (pymavlink would send to every address that ever sent a datagram). A peer silent for
    ``relock_s`` may be replaced by the next sender of vehicle data (logged). ``udpout``: only the
    destination's replies are read. Installed by replacing the connection's ``recv``."""

    def __init__(
        self,
        conn: Any,
        counts: dict[str, int],
        relock_s: float = PEER_RELOCK_S,
        signing_key: bytes | None = None,
    ) -> None:
        import socket

        self.conn = conn
        self.counts = counts
        self.relock_s = relock_s
        self.peer: tuple[Any, ...] | None = None
        self.vehicle: tuple[int, int] | None = None
        self._last_from_peer = -math.inf
        self._foreign: set[tuple[Any, ...]] = set()
        self._probe = _mavlink_module().MAVLink(None)
        self._probe.robust_parsing = True
        if signing_key is not None:  # a signed link locks onto signed vehicle data only
            from magcomp.adapters.signing import require_signed

            require_signed(self._probe, signing_key)
        self._wanted = frozenset(WANTED_MAVLINK)
        self._socket_error = socket.error
        self._relockable = bool(conn.udp_server or conn.broadcast)  # (udpbcast: the first replier)
        if not self._relockable:  # udpout: the destination is the peer, by construction
            with contextlib.suppress(OSError):
                host, port = conn.destination_addr
                self.peer = (socket.gethostbyname(host), int(port))
        conn.clients.clear()
        conn.recv = self.recv

    def recv(self, n: int | None = None) -> bytes:
        import time

        conn = self.conn
        try:
            data, addr = conn.port.recvfrom(65535)
        except self._socket_error as exc:
            if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                return b""
            raise
        now = time.monotonic()
        if addr == self.peer:
            self._last_from_peer = now
            return bytes(data)
        if self.peer is not None and (not self._relockable or now - self._last_from_peer < self.relock_s):
            self._refuse(addr)
            return b""
        vehicle = self._vehicle_in(data)
        if vehicle is None:
            self._refuse(addr)
            return b""
        if self.peer is not None:
            log.warning("the flight controller at %s:%s was silent for %.0f s; now following %s:%s "
                        "(system %d component %d)", *self.peer[:2], now - self._last_from_peer, *addr[:2],
                        *vehicle)  # fmt: skip
        else:
            log.info("following the flight controller at %s:%s (system %d component %d); vehicle data "
                     "from other addresses is ignored", *addr[:2], *vehicle)  # fmt: skip
        self.peer, self.vehicle, self._last_from_peer = addr, vehicle, now
        self._foreign.discard(addr)
        conn.clients.clear()
        conn.clients.add(addr)
        conn.clients_last_alive[addr] = time.time()
        if conn.broadcast:
            conn.last_address = addr
        return bytes(data)

    def _vehicle_in(self, data: bytes) -> tuple[int, int] | None:
        """(system, component) of the first vehicle message in a datagram, None when it has none."""
        try:
            msgs = self._probe.parse_buffer(bytearray(data)) or []
        except Exception:  # whatever the parser makes of hostile bytes: not vehicle data
            return None
        finally:
            self._probe.buf = bytearray()  # each datagram on its own: nothing carried to the next
            self._probe.buf_index = 0
        for m in msgs:
            mtype = m.get_type()
            if mtype not in self._wanted:
                continue
            if mtype == "HEARTBEAT" and getattr(m, "type", None) == _MAV_TYPE_GCS:
                continue
            return int(m.get_srcSystem()), int(m.get_srcComponent())
        return None

    def _refuse(self, addr: tuple[Any, ...]) -> None:
        self.counts["foreign_datagrams"] += 1
        if addr in self._foreign or len(self._foreign) >= FOREIGN_NAMED:
            return
        self._foreign.add(addr)
        follows = f"{self.peer[0]}:{self.peer[1]}" if self.peer is not None else "no flight controller yet"
        more = " (further senders are counted only)" if len(self._foreign) == FOREIGN_NAMED else ""
        log.warning("ignoring datagrams from %s:%s, not the flight controller (following %s)%s",
                    *addr[:2], follows, more)  # fmt: skip


def _raise_dropped(reason: str) -> Callable[[], None]:
    """A replacement for pymavlink's TCP ``handle_eof`` / ``handle_disconnect`` (which reconnect in place,
    printing on stdout): the drop becomes an error of the reading (or writing) call."""

    def dropped() -> None:
        raise ConnectionResetError(reason)

    return dropped


class MavSource:
    """One source of typed samples. Use :func:`open_source`.

    ``samples()`` streams :data:`~magcomp.core.types.Sample` objects in arrival order (throttle already
    converted
    with the configured source); ``counts`` holds what was skipped and why, plus ``messages`` and
    ``clock_resets``. ``connection`` is the mavutil connection of a live link (None for files), e.g. to send
    MAGCOMP_HEADING back on it.
    """

    def __init__(
        self,
        target: str,
        *,
        throttle_source: str | ThrottleSpec = "auto",
        mag_index: int | None = None,
        undo_motor_comp: bool = True,
        baud: int = 57600,
        live_timeout_s: float = 0.5,
        pipeline_only: bool = False,
        signing_key: bytes | None = None,
    ) -> None:
        self.target = target
        self._signing_key = signing_key
        self.spec = parse_throttle_source(throttle_source)
        self.mag_index = mag_index
        self.counts: dict[str, int] = _Counts()
        self.params: dict[str, float] = {}
        self.connection: Any = None
        self._conv = _Converter(
            self.counts, mag_index=mag_index, undo_motor_comp=undo_motor_comp, pipeline_only=pipeline_only
        )
        self._closed = False
        self._live_timeout_s = live_timeout_s
        self._baud = baud
        self._kind = self._classify(target)
        self._reference_decode = False  # tests: decode tlog frames with pymavlink's MAVLink.decode
        #: live links: polled while the link is quiet or carries only unwanted messages; True ends the
        #: stream (the daemon's stop request, seen by the reading thread itself)
        self.interrupt: Callable[[], bool] | None = None
        self._own_reconnect = False  # a drop ends the source (TCP client links): see _open_live
        self.peer_lock: UdpPeerLock | None = None  # UDP links: the one peer followed
        if self._kind == "live":
            self._open_live()

    @property
    def vehicle_type(self) -> int:
        return self._conv.vehicle_type

    @property
    def skipped_samples(self) -> int:
        """Samples a ``pipeline_only`` source left out so far (0 otherwise)."""
        return self._conv.skipped

    def onboard_motor_comp(self) -> dict[int, dict[str, Any]]:
        """ArduPilot's COMPASS_MOTCT compensation undone per compass (see
        :mod:`magcomp.adapters.ardupilot_motcomp`); empty when there was none."""
        return self._conv.onboard_comp.report()

    @property
    def autopilot(self) -> int:
        return self._conv.autopilot

    def clock_offsets(self) -> dict[str, float]:
        """Streams moved onto the ``time_boot_ms`` clock and the offset added to their times (s)
        (:class:`StreamOffsets`); empty when all streams share one clock."""
        return dict(self._conv.clock.offsets.offset_s)

    def _classify(self, target: str) -> str:
        if _is_live(target):
            return "live"
        path = Path(target)
        if not path.exists():
            raise InputError(f"{target}: no such file (and not a link URL such as udpin:0.0.0.0:14550)")
        if not path.is_file():
            raise InputError(f"{target}: not a file")
        try:
            size = path.stat().st_size
            with path.open("rb") as f:
                head = f.read(64)
        except OSError as exc:
            raise InputError(f"{target}: cannot read ({exc.strerror})") from None
        if size == 0:
            raise InputError(f"{target}: empty file")
        suffix = path.suffix.lower()
        if suffix == ".ulg" or head.startswith(b"ULog"):
            return "ulog"
        if suffix == ".bin" or head[:2] == b"\xa3\x95":
            return "dataflash_bin"
        if suffix == ".log" or head.startswith(b"FMT,") or b"\nFMT," in head:
            return "dataflash_text"
        return "mavlink_file"

    def _open_live(self) -> None:
        _mavlink_module()  # registers the dialect and sets MAVLINK20 before mavutil is imported
        from pymavlink import mavutil

        url = self.target.removeprefix("serial:")
        baud = self._baud
        match = re.match(r"^(/dev/\S+?|COM\d+):(\d+)$", url)
        if match:
            url, baud = match.group(1), int(match.group(2))
        tcp_client = url.startswith("tcp:")
        try:
            # a TCP client link is not reconnected by pymavlink (its reconnect, run by whichever thread
            # reads or writes first, races between the reader and the heartbeat writer and can leave the
            # reader on a dead socket): a drop ends this source, the daemon opens a new one; one connect
            # attempt (retries=0), no sleeping retries inside the open
            self.connection = mavutil.mavlink_connection(
                url, baud=baud, dialect="magcomp", source_system=255, source_component=191,
                autoreconnect=not tcp_client, retries=0,
            )  # fmt: skip
        except Exception as exc:
            raise InputError(f"cannot open link {self.target}: {exc}") from None
        if self._signing_key is not None:  # only signed frames are read from this link
            from magcomp.adapters.signing import require_signed

            require_signed(self.connection.mav, self._signing_key)
        if isinstance(self.connection, mavutil.mavudp):
            self.peer_lock = UdpPeerLock(self.connection, self.counts, signing_key=self._signing_key)
        if tcp_client:
            self._own_reconnect = True
            self.connection.handle_eof = _raise_dropped("connection closed by the other end")
            self.connection.handle_disconnect = _raise_dropped("connection reset by the other end")

    def close(self) -> None:
        """Stop streaming and release the link (idempotent)."""
        self._closed = True
        if self.connection is not None:
            with contextlib.suppress(Exception):
                self.connection.close()
            self.connection = None

    def __enter__(self) -> MavSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- raw message streams --
    def _messages(self) -> Iterator[tuple[Callable[[Any], list[tuple[str, Record]]], Any]]:
        conv = self._conv
        if self._kind == "ulog":
            raise AssertionError("ulog is read by load_log only")  # pragma: no cover
        if self._kind in ("dataflash_bin", "dataflash_text"):
            for m in _iter_dataflash(Path(self.target), self.counts, self._kind == "dataflash_text"):
                yield conv.dataflash, m
            if self.counts["messages"] == 0:
                raise InputError(f"{self.target}: no DataFlash messages found (not an ArduPilot log?)")
            return
        if self._kind == "mavlink_file":
            if self._reference_decode:  # tests: pymavlink's decode, dispatched by type name
                yield from ((conv.mavlink, m) for _, m in self._file_messages())
            else:
                yield from self._file_messages()
            return
        yield from ((conv.mavlink, m) for m in self._live_messages())

    def _file_messages(self) -> Iterator[tuple[Callable[[Any], list[tuple[str, Record]]], Any]]:
        path = Path(self.target)
        try:
            f = path.open("rb")
        except OSError as exc:
            raise InputError(f"{path}: cannot read ({exc.strerror})") from None
        with f:
            head = f.read(READ_CHUNK_BYTES)
            ts_len = _sniff_mavlink_stream(head)
            mod = _mavlink_module()
            if ts_len is None:
                if head[:256].isascii():
                    raise InputError(f"{path}: a text file, not a MAVLink log")
                ts_len = 8 if path.suffix.lower() == ".tlog" else 0
            conv = self._conv
            decoders = frame_decoders(mod, {name: getattr(conv, f"_m_{name}") for name in WANTED_MAVLINK})
            yield from iter_mavlink_file(
                f,
                head,
                decoders,
                self.counts,
                ts_len,
                crc16=_crc_function(mod),
                ignore_crc=bool(mod.MAVLINK_IGNORE_CRC),
                reference_mav=mod.MAVLink(None) if self._reference_decode else None,
                rx_into=conv.clock,
            )
        if self.counts["messages"] == 0:
            raise InputError(f"{path}: no valid MAVLink messages found")

    def _live_messages(self) -> Iterator[Any]:
        wanted = set(WANTED_MAVLINK)
        while not self._closed and self.connection is not None:
            interrupt = self.interrupt
            if interrupt is not None and interrupt():
                return
            try:
                m = self.connection.recv_match(blocking=True, timeout=self._live_timeout_s)
            except (OSError, ValueError, AttributeError) as exc:
                # (AttributeError: pymavlink's link object after its socket was closed under it)
                if self._own_reconnect:
                    self.close()  # the socket is dead: the daemon reconnects with a new source
                raise InputError(f"link {self.target} failed: {exc}") from None
            if m is None:
                continue
            mtype = m.get_type()
            if mtype == "BAD_DATA":
                reason = str(getattr(m, "reason", ""))
                if "signature" in reason:
                    self.counts["bad_signature"] += 1  # unsigned or signed with another key
                else:
                    self.counts["bad_crc" if "CRC" in reason else "garbage_bytes"] += 1
                continue
            if mtype in wanted:
                self.counts["messages"] += 1
                yield m

    def records(self) -> Iterator[tuple[str, Record]]:
        """(origin, record) pairs: samples plus raw PWM / throttle records, before throttle selection."""
        for handler, msg in self._messages():
            for origin, rec in handler(msg):
                if isinstance(rec, ParamSample):
                    self.params[rec.name] = rec.value
                yield origin, rec

    def samples(self) -> Iterator[Sample]:
        """Stream typed samples; throttle records become ThrottleSample per the configured source."""
        # records() inlined (the hot loop of a replay): parameters are stored before the sample is yielded
        available: set[str] = set()
        resolved: ResolvedThrottle | None = None
        stale = True
        params = self.params
        clock = self._conv.clock
        for handler, msg in self._messages():
            recs = handler(msg)
            if clock.reboot_pending:
                clock.reboot_pending = False
                yield ClockResetSample(clock.last_t_s, clock.offset_s)
            for _, rec in recs:
                cls = type(rec)
                if cls is PwmRecord or cls is ThrottleRecord:
                    assert isinstance(rec, PwmRecord | ThrottleRecord)  # for mypy (cheap: few per message)
                    if rec.kind not in available:
                        available.add(rec.kind)
                        stale = True
                    if stale:
                        resolved = resolve_throttle(
                            self.spec, self.vehicle_type, params, frozenset(available)
                        )
                        stale = False
                    thr = _throttle_sample(resolved, rec)
                    if thr is not None:
                        yield thr
                    continue
                if cls is ParamSample:
                    assert isinstance(rec, ParamSample)
                    params[rec.name] = rec.value
                    stale = True
                elif cls is HeartbeatSample:
                    stale = True
                yield rec  # type: ignore[misc]

    def vehicle_samples(self) -> Iterator[tuple[tuple[int, int], Sample]]:
        """Live links: ((system id, component id), sample) for every sender on the link, each with its
        own clock (reboots, jumps), parameters and throttle selection: a link carrying several vehicles
        (or components) never mixes their samples. Same samples per sender as :meth:`samples`."""
        if self._kind != "live":
            raise AssertionError("vehicle_samples() is for live links")  # pragma: no cover
        streams: dict[tuple[int, int], _SenderStream] = {}
        undo = self._conv.undo_motor_comp
        for msg in self._live_messages():
            key = (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
            st = streams.get(key)
            if st is None:
                conv = self._conv if not streams else _Converter(self.counts, mag_index=self.mag_index,
                                                                 undo_motor_comp=undo)  # fmt: skip
                st = streams[key] = _SenderStream(self.spec, conv, self.params if not streams else {})
            for sample in st.push(msg):
                yield key, sample


class _SenderStream:
    """The samples of one sender on a shared link (the loop of :meth:`MavSource.samples`, one message at
    a time)."""

    def __init__(self, spec: ThrottleSpec, conv: _Converter, params: dict[str, float]) -> None:
        self.spec = spec
        self.conv = conv
        self.params = params
        self.available: set[str] = set()
        self.resolved: ResolvedThrottle | None = None
        self.stale = True

    def push(self, msg: Any) -> list[Sample]:
        conv = self.conv
        recs = conv.mavlink(msg)
        out: list[Sample] = []
        if conv.clock.reboot_pending:
            conv.clock.reboot_pending = False
            out.append(ClockResetSample(conv.clock.last_t_s, conv.clock.offset_s))
        for _, rec in recs:
            if isinstance(rec, PwmRecord | ThrottleRecord):
                if rec.kind not in self.available:
                    self.available.add(rec.kind)
                    self.stale = True
                if self.stale:
                    self.resolved = resolve_throttle(self.spec, conv.vehicle_type, self.params,
                                                     frozenset(self.available))  # fmt: skip
                    self.stale = False
                thr = _throttle_sample(self.resolved, rec)
                if thr is not None:
                    out.append(thr)
                continue
            if isinstance(rec, ParamSample):
                self.params[rec.name] = rec.value
                self.stale = True
            elif isinstance(rec, HeartbeatSample):
                self.stale = True
            out.append(rec)
        return out


def sender_stream(spec: str | ThrottleSpec, counts: dict[str, int] | None = None) -> _SenderStream:
    """A converter for the messages of one sender handed over one at a time (a host that owns the link:
    :mod:`magcomp.service.companion`); ``push(msg)`` returns that message's samples."""
    counts = counts if counts is not None else _Counts()
    conv = _Converter(counts, mag_index=None, undo_motor_comp=True)
    return _SenderStream(parse_throttle_source(spec), conv, {})


def finite_params(params: Mapping[str, float], counts: dict[str, int]) -> dict[str, float]:
    """``params`` without the non-finite values (a damaged PARAM_VALUE / PARM / ULog parameter), each
    counted in ``non_finite_params``: the parameters decide compass forms, channels and rotations, and
    ``int(nan)`` raised in each of those places."""
    out = {}
    for name, value in params.items():
        if math.isfinite(value):
            out[name] = value
        else:
            counts["non_finite_params"] = counts.get("non_finite_params", 0) + 1
    return out


def _throttle_sample(
    resolved: ResolvedThrottle | None, rec: PwmRecord | ThrottleRecord
) -> ThrottleSample | None:
    if resolved is None:
        return None
    if isinstance(rec, ThrottleRecord):
        if rec.kind != resolved.kind:
            return None
        return ThrottleSample(rec.t_s, rec.throttle_01, resolved.label)
    if (rec.kind == "rc") != (resolved.kind == "rc") or resolved.kind in ("vfr_hud", "ctun"):
        return None
    out = throttle_from_pwm(resolved, rec.pwm_us)
    if out is None:
        return None
    return ThrottleSample(rec.t_s, out[0], resolved.label, out[1] if resolved.kind == "motors" else ())


class _Counts(dict[str, int]):
    """A dict of counters whose missing keys read as 0 (and are created on first increment)."""

    def __missing__(self, key: str) -> int:
        return 0


def open_source(
    url_or_path: str | os.PathLike[str],
    *,
    throttle_source: str | ThrottleSpec = "auto",
    mag_index: int | None = None,
    undo_motor_comp: bool = True,
    baud: int = 57600,
    live_timeout_s: float = 0.5,
    pipeline_only: bool = False,
    signing_key: bytes | None = None,
) -> MavSource | UlogSource:
    """Open a log file (.tlog, raw MAVLink, DataFlash .bin/.log, PX4 .ulg) or a live link URL.

    Links: ``udpin:0.0.0.0:14550``, ``udpout:host:port``, ``tcp:host:port``, ``tcpin:0.0.0.0:5760``,
    ``/dev/ttyACM0:115200`` or ``serial:/dev/ttyUSB0:57600``. Raises InputError for a missing, empty or
    unrecognisable file. ``mag_index`` restricts MagSamples to one compass. A ``.ulg`` gives a
    :class:`~magcomp.adapters.ulog_source.UlogSource` (same interface, no link).
    ``pipeline_only``: leave out what :class:`~magcomp.service.pipeline.Pipeline` ignores (temperature and
    power samples, IMUs other than IMU 0; MAVLink and DataFlash), counted in ``skipped_samples``.
    """
    target = os.fspath(url_or_path)
    if _is_ulog(target):
        from magcomp.adapters.ulog_source import UlogSource

        return UlogSource(target, throttle_source=throttle_source, mag_index=mag_index)
    source = MavSource(
        target,
        throttle_source=throttle_source,
        mag_index=mag_index,
        undo_motor_comp=undo_motor_comp,
        baud=baud,
        live_timeout_s=live_timeout_s,
        pipeline_only=pipeline_only,
        signing_key=signing_key,
    )
    return source


# --- whole-log loading ---


def load_log(
    path: str | os.PathLike[str],
    throttle_source: str | ThrottleSpec = "auto",
    mag_index: int | None = None,
    *,
    undo_motor_comp: bool = True,
    window: Window | None = None,
    on_progress: Callable[[float], None] | None = None,
) -> LogData:
    """Read a whole log into columns (:class:`~magcomp.core.types.LogData`), in the module's fixed units.

    Unlike streaming, preferences are decided with the whole log known: RAW_IMU over SCALED_IMU for compass 0,
    SYS_STATUS/CURR over BATTERY_STATUS for battery 0, IMU temperature over barometer temperature, and the
    ``auto`` throttle source from the final vehicle type and parameters.

    Memory: the file is read a chunk at a time and each message's values go straight into compact columns
    (:mod:`magcomp.adapters.columns`), ~8 bytes per value kept. ``window`` keeps only the rows in a time
    window (and one neighbour each side), cut while reading; the whole file is still read (parameters and
    the vehicle type can come at any time). PX4 ULog (:func:`~magcomp.adapters.ulog_source.load_ulog`)
    ignores it. ``on_progress``: called every thousand messages or so with the message time reached (s; a
    progress bar), not for ULog (read whole by pyulog).
    """
    target = os.fspath(path)
    if _is_ulog(target):
        from magcomp.adapters.ulog_source import load_ulog

        return load_ulog(target, throttle_source, mag_index)
    source = MavSource(
        target, throttle_source=throttle_source, mag_index=mag_index, undo_motor_comp=undo_motor_comp
    )
    if source._kind == "live":
        raise InputError(f"{target}: load_log reads files; use open_source for live links")
    records = source.records()
    if on_progress is not None:
        records = _reporting(records, on_progress)
    try:
        return _collect(source, records, window)
    finally:
        source.close()


def _reporting(
    records: Iterator[tuple[str, Record]], on_progress: Callable[[float], None], every: int = 1024
) -> Iterator[tuple[str, Record]]:
    """``records`` with ``on_progress(t_s)`` every ``every`` of them."""
    for i, item in enumerate(records):
        if i % every == 0:
            t = getattr(item[1], "t_s", None)
            if t is not None:
                on_progress(float(t))
        yield item


# compass 0 in several messages: RAW_IMU, then SCALED_IMU and the rest, then PX4's HIGHRES_IMU (calibrated)
_MAG_ORIGIN_RANK = {"RAW_IMU": 0, "HIGHRES_IMU": 2}


def _xyz(rec: Any, wire: str, arr: str) -> Float3 | list[float]:
    """A sample's vector as three floats: the wire samples' own tuple, else the array's values."""
    v = getattr(rec, wire, None)
    return v if v is not None else getattr(rec, arr).tolist()  # type: ignore[no-any-return]


class _Collector:
    """What :func:`load_log` keeps of a log, in columns (:mod:`magcomp.adapters.columns`), one store per
    (kind, origin); preferences between origins are decided at the end (:meth:`fill`)."""

    def __init__(self, window: Window | None) -> None:
        self.window = window
        self.mag: dict[tuple[str, int], Rows] = {}
        self.imu: dict[str, Rows] = {}  # IMU 0: gyro xyz, accel xyz
        self.att = Rows(3, window)
        self.power: dict[str, Rows] = {}  # battery 0: voltage, current
        self.temp: dict[str, Rows] = {}
        self.pwm = {"servo": PwmRows(window), "rc": PwmRows(window)}
        self.thr = {"vfr_hud": Rows(0, window), "ctun": Rows(0, window)}
        self.gnss = _GnssCollector(window)

    def _store(self, stores: dict[Any, Rows], key: Any, width: int) -> Rows:
        st = stores.get(key)
        if st is None:
            st = stores[key] = Rows(width, self.window)
        return st

    def add(self, origin: str, rec: Record) -> None:
        if isinstance(rec, MagSample):
            key = (origin, rec.mag_index)
            self._store(self.mag, key, 3).append(rec.t_s, _xyz(rec, "field_xyz", "field_b_mgauss"))
        elif isinstance(rec, ImuSample):
            if rec.imu_index == 0:
                gyro, accel = _xyz(rec, "gyro_xyz", "gyro_b_rad_s"), _xyz(rec, "accel_xyz", "accel_b_m_s2")
                self._store(self.imu, origin, 6).append(rec.t_s, (*gyro, *accel))
        elif isinstance(rec, AttitudeSample):
            self.att.append(rec.t_s, (rec.roll_rad, rec.pitch_rad, rec.yaw_rad))
        elif isinstance(rec, PowerSample):
            if rec.battery_index == 0:
                self._store(self.power, origin, 2).append(rec.t_s, (rec.voltage_v, rec.current_a))
        elif isinstance(rec, TemperatureSample):
            self._store(self.temp, rec.sensor, 0).append(rec.t_s, (rec.temperature_degc,))
        elif isinstance(rec, PwmRecord):
            self.pwm[rec.kind].append(rec.t_s, rec.pwm_us)
        elif isinstance(rec, ThrottleRecord):
            self.thr[rec.kind].append(rec.t_s, (rec.throttle_01,))
        elif isinstance(rec, PositionSample | TimeSample):
            self.gnss.add(origin, rec)

    def fill(self, data: LogData, counts: dict[str, int]) -> None:
        # compass 0: RAW_IMU wins over SCALED_IMU (ArduPilot sends the same compass in both)
        by_index: dict[int, Rows] = {}
        ranked = sorted(self.mag.items(), key=lambda kv: _MAG_ORIGIN_RANK.get(kv[0][0], 1))
        for (_origin, index), rows in ranked:
            if index in by_index:
                counts["scaled_imu_shadowed"] += rows.n_seen
                continue
            by_index[index] = rows
        data.mag = {i: rows.series() for i, rows in sorted(by_index.items())}
        imu_origin = next((o for o in ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU", "IMU") if o in self.imu), None)
        if imu_origin is not None:
            imu = self.imu[imu_origin].series()
            data.imu_t_s = imu.t_s
            data.gyro_rad_s = np.ascontiguousarray(imu.values[:, :3])
            data.accel_m_s2 = np.ascontiguousarray(imu.values[:, 3:])
        data.attitude_rad = self.att.series()
        power_origins = ("SYS_STATUS", "CURR", "BAT", "BATTERY_STATUS")
        power_origin = next((o for o in power_origins if o in self.power), None)
        if power_origin is not None:
            pw = self.power[power_origin].series()
            data.voltage_v = Series(pw.t_s, pw.values[:, 0])
            data.current_a = Series(pw.t_s, pw.values[:, 1])
        temp_key = next((k for k in ("imu0", "imu1", "imu2", "baro") if k in self.temp), None)
        if temp_key is not None:
            data.temperature_degc = self.temp[temp_key].series()
        self.gnss.fill(data)


def _collect(
    source: MavSource, records: Iterable[tuple[str, Record]], window: Window | None = None
) -> LogData:
    col = _Collector(window)
    add = col.add
    for origin, rec in records:
        add(origin, rec)
    counts = source.counts
    data = LogData(
        source=source.target,
        params=finite_params(source.params, counts),
        vehicle_type=source.vehicle_type,
        autopilot=source.autopilot,
    )
    col.fill(data, counts)
    _collect_throttle(data, source, col.pwm, col.thr)
    data.counts = dict(counts)
    if not data.mag and not len(data.attitude_rad) and not data.imu_t_s.size:
        raise InputError(f"{source.target}: no magnetometer, IMU or attitude data in the log")
    return data


class _GnssCollector:
    """Positions (3D fixes only) and UTC dates of a whole log, for :class:`LogData`.

    The receiver's own position (GPS_RAW_INT, DataFlash GPS, ULog vehicle_gps_position) is preferred to the
    estimator's (GLOBAL_POSITION_INT, POS, vehicle_global_position); the date is the median of every valid
    one (GPS time, SYSTEM_TIME, ULog time_utc_usec), in the window or not."""

    RECEIVER = frozenset({"GPS_RAW_INT", "GPS", "vehicle_gps_position", "sensor_gps"})

    def __init__(self, window: Window | None = None) -> None:
        self.rows: dict[bool, Rows] = {True: Rows(3, window), False: Rows(3, window)}
        self.years = array("d")

    def add(self, origin: str, rec: PositionSample | TimeSample) -> None:
        year = rec.decimal_year
        if isinstance(rec, PositionSample):
            if not rec.fix_ok:
                return
            self.rows[origin in self.RECEIVER].append(rec.t_s, (rec.lat_deg, rec.lon_deg, rec.alt_m))
        if math.isfinite(year):
            self.years.append(year)

    def fill(self, data: LogData) -> None:
        rows = self.rows[True] if len(self.rows[True]) else self.rows[False]
        data.position = rows.series()
        if self.years:
            data.decimal_year = float(np.median(np.frombuffer(self.years, dtype=np.float64)))


def _throttle_rows(
    resolved: ResolvedThrottle, pwm: PwmRows, which: int, width: int = 0
) -> Series:
    """Throttle (``which`` 0: the 0..1 throttle) or per-channel outputs (1) of every PWM row that gives one
    (:func:`throttle_from_pwm`, row by row: the same numbers as streaming)."""
    out = Rows(width)
    for t_s, row in pwm.rows(resolved.channels):
        got = throttle_from_pwm(resolved, row)
        if got is not None:
            out.append(t_s, (got[0],) if which == 0 else got[1])
    return out.series()


def _collect_throttle(
    data: LogData,
    source: MavSource,
    pwm: dict[str, PwmRows],
    thr: dict[str, Rows],
) -> None:
    available = frozenset(k for k, v in (*pwm.items(), *thr.items()) if v.n_seen)
    resolved = resolve_throttle(source.spec, data.vehicle_type, data.params, available)
    multirotor = data.vehicle_type in MULTIROTOR_TYPES or bool(motor_channels(data.params))
    if len(pwm["servo"]) and (multirotor or (resolved is not None and resolved.kind == "motors")):
        motors = resolve_throttle("motors", data.vehicle_type, data.params, available)
        if motors is not None:
            data.motors_01 = _throttle_rows(motors, pwm["servo"], 1, len(motors.channels))
        else:
            data.motors_01 = Series.empty(4)
    if resolved is None:
        return
    data.throttle_source = resolved.label
    if resolved.kind in thr:
        data.throttle_01 = thr[resolved.kind].series()
        return
    data.throttle_01 = _throttle_rows(resolved, pwm["rc" if resolved.kind == "rc" else "servo"], 0)
    if data.vehicle_type in FIXED_WING_TYPES and resolved.kind == "servo":
        data.motors_01 = Series(data.throttle_01.t_s, data.throttle_01.values[:, None])
