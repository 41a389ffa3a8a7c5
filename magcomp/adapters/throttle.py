"""Throttle source selection and PWM -> 0..1 conversion (pure; no pymavlink).

Sources (the ``--throttle`` option): ``servo:N`` (servo output channel N, 1-based), ``motors`` (mean of the
motor
outputs), ``rc:N`` (RC input channel N), ``vfr_hud`` (VFR_HUD.throttle, %), ``ctun`` (DataFlash CTUN
ThO/ThrOut)
and ``auto``, resolved from the vehicle type (HEARTBEAT MAV_TYPE, or the firmware name of a DataFlash log):

- multirotor (MAV_TYPE 2, 3, 4, 13, 14, 15): ``motors``, on the channels whose SERVOn_FUNCTION is 33-40
  (Motor1-8) when those parameters are known, else channels 1-4;
- fixed wing (MAV_TYPE 1): the servo channel with SERVOn_FUNCTION 70 (throttle), else channel 3;
- anything else, or no servo outputs: ``vfr_hud``, then ``ctun``.

PWM ranges: motors use MOT_PWM_MIN/MAX when both are set, else SERVOn_MIN/MAX of the channel, else PX4's
PWM_MAIN_MINn/MAXn, PWM_MAIN_MIN/MAX or PWM_MIN/MAX, else 1000-2000 us (PX4 motors: PWM_MAIN_FUNCn 101-112);
servo channels use SERVOn_MIN/MAX, RC channels RCn_MIN/MAX, both defaulting to 1000-2000 us. Results are
clipped
to 0..1. Older ArduPilot firmware without SERVOn_* parameters therefore uses 1000-2000 us for motors (its RC3
range is the pilot's stick range, not the ESC range).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass, field

from magcomp.errors import InputError

MULTIROTOR_TYPES = frozenset({2, 3, 4, 13, 14, 15})
FIXED_WING_TYPES = frozenset({1})
MOTOR_FUNCTIONS = range(33, 41)  # SERVOn_FUNCTION Motor1..Motor8
THROTTLE_FUNCTION = 70
DEFAULT_PWM_MIN = 1000.0
DEFAULT_PWM_MAX = 2000.0
KINDS = ("auto", "servo", "motors", "rc", "vfr_hud", "ctun")


@dataclass(frozen=True, slots=True)
class ThrottleSpec:
    """A parsed throttle-source option. ``channel`` is 1-based, for ``servo`` and ``rc`` only."""

    kind: str
    channel: int = 0

    def __str__(self) -> str:
        return f"{self.kind}:{self.channel}" if self.kind in ("servo", "rc") else self.kind


@dataclass(frozen=True, slots=True)
class ResolvedThrottle:
    """What to read: ``kind`` in servo/motors/rc/vfr_hud/ctun, the 1-based channels, and each channel's PWM
    range."""

    kind: str
    channels: tuple[int, ...] = ()
    pwm_min: tuple[float, ...] = ()
    pwm_max: tuple[float, ...] = ()
    #: what the throttle samples say they came from, made once (every throttle sample carries it)
    label: str = field(init=False, compare=False, repr=False, default="")
    #: (channel, pwm_min, pwm_max) of each channel, made once (:func:`throttle_from_pwm`, per PWM message)
    ranges: tuple[tuple[int, float, float], ...] = field(init=False, compare=False, repr=False, default=())

    def __post_init__(self) -> None:
        ranges = tuple(zip(self.channels, self.pwm_min, self.pwm_max, strict=True))
        object.__setattr__(self, "ranges", ranges)
        if self.kind in ("servo", "rc"):
            label = f"{self.kind}:{self.channels[0]}"
        elif self.kind == "motors":
            label = "motors:" + ",".join(str(c) for c in self.channels)
        else:
            label = self.kind
        object.__setattr__(self, "label", label)


def parse_throttle_source(text: str | ThrottleSpec) -> ThrottleSpec:
    """Parse ``auto``, ``motors``, ``vfr_hud``, ``ctun``, ``servo:N`` or ``rc:N`` (InputError otherwise)."""
    if isinstance(text, ThrottleSpec):
        return text
    raw = text.strip().lower()
    kind, _, arg = raw.partition(":")
    if kind in ("servo", "rc"):
        try:
            channel = int(arg)
        except ValueError:
            raise InputError(f"throttle source {text!r}: expected {kind}:N with a channel number N") from None
        if not 1 <= channel <= 32:
            raise InputError(f"throttle source {text!r}: channel must be 1..32")
        return ThrottleSpec(kind, channel)
    if kind in KINDS and not arg:
        return ThrottleSpec(kind)
    raise InputError(f"unknown throttle source {text!r} (use auto, motors, servo:N, rc:N, vfr_hud or ctun)")


def motor_channels(params: Mapping[str, float]) -> tuple[int, ...]:
    """Channels whose SERVOn_FUNCTION is a motor (33-40), ordered by motor number; () when unknown."""
    return _motors_by_function(params, "SERVO{}_FUNCTION", 32, MOTOR_FUNCTIONS)


def _motors_by_function(
    params: Mapping[str, float], name: str, n_outputs: int, motor_functions: Collection[int]
) -> tuple[int, ...]:
    """Outputs 1..``n_outputs`` whose function parameter (``name`` with the output number) is one of
    ``motor_functions``, ordered by function (motor number)."""
    found: list[tuple[float, int]] = []
    for n in range(1, n_outputs + 1):
        fn = params.get(name.format(n))
        if fn is not None and int(fn) in motor_functions:
            found.append((fn, n))
    return tuple(n for _, n in sorted(found))


def _servo_range(params: Mapping[str, float], prefix: str, channel: int) -> tuple[float, float]:
    lo = params.get(f"{prefix}{channel}_MIN")
    hi = params.get(f"{prefix}{channel}_MAX")
    if lo is not None and hi is not None and hi > lo > 0:
        return float(lo), float(hi)
    if prefix == "SERVO":  # a PX4 vehicle has no SERVOn_*: its PWM_MAIN_* (defaults when absent too)
        return px4_pwm_range(params, channel)
    return DEFAULT_PWM_MIN, DEFAULT_PWM_MAX


def _motor_range(params: Mapping[str, float], channel: int) -> tuple[float, float]:
    lo = params.get("MOT_PWM_MIN", 0.0)
    hi = params.get("MOT_PWM_MAX", 0.0)
    if hi > lo > 0:
        return float(lo), float(hi)
    return _servo_range(params, "SERVO", channel)


def _with_ranges(kind: str, channels: tuple[int, ...], params: Mapping[str, float]) -> ResolvedThrottle:
    if kind == "motors":
        ranges = [_motor_range(params, c) for c in channels]
    else:
        ranges = [_servo_range(params, "RC" if kind == "rc" else "SERVO", c) for c in channels]
    return ResolvedThrottle(kind, channels, tuple(r[0] for r in ranges), tuple(r[1] for r in ranges))


def resolve_throttle(
    spec: ThrottleSpec | str,
    vehicle_type: int,
    params: Mapping[str, float],
    available: frozenset[str] | set[str],
) -> ResolvedThrottle | None:
    """Decide what to read for ``spec`` given what is known; ``None`` when nothing suitable is available yet.

    ``vehicle_type`` is MAV_TYPE or -1; ``available`` holds the kinds of throttle data seen so far, among
    ``servo``, ``rc``, ``vfr_hud``, ``ctun``. An explicit spec is returned as asked, whatever is available.
    """
    spec = parse_throttle_source(spec)
    if spec.kind in ("servo", "rc"):
        return _with_ranges(spec.kind, (spec.channel,), params)
    if spec.kind == "motors":
        return _with_ranges("motors", _any_motor_channels(params), params)
    if spec.kind in ("vfr_hud", "ctun"):
        return ResolvedThrottle(spec.kind)
    # auto
    if "servo" in available:
        if vehicle_type in MULTIROTOR_TYPES:
            return _with_ranges("motors", _any_motor_channels(params), params)
        if vehicle_type in FIXED_WING_TYPES:
            thr = [n for n in range(1, 33) if params.get(f"SERVO{n}_FUNCTION") == THROTTLE_FUNCTION]
            thr += px4_motor_channels(params)[:1]  # PX4: the fixed wing's throttle is its Motor 1 output
            return _with_ranges("servo", (thr[0] if thr else 3,), params)
    if "vfr_hud" in available:
        return ResolvedThrottle("vfr_hud")
    if "ctun" in available:
        return ResolvedThrottle("ctun")
    return None


def _any_motor_channels(params: Mapping[str, float]) -> tuple[int, ...]:
    """ArduPilot's SERVOn_FUNCTION motors, else PX4's PWM_MAIN_FUNCn motors, else channels 1-4."""
    return motor_channels(params) or px4_motor_channels(params) or (1, 2, 3, 4)


def pwm_to_01(pwm_us: float, pwm_min: float, pwm_max: float) -> float:
    """Map a PWM pulse (us) linearly from [pwm_min, pwm_max] to [0, 1], clipped."""
    x = (float(pwm_us) - pwm_min) / (pwm_max - pwm_min)
    return x if 0.0 < x < 1.0 else (1.0 if x >= 1.0 else 0.0)  # min(1, max(0, x)) without the calls


#: pulse widths an ESC or servo can be driven with (RC PWM is 800-2200 us); MAVLink reports 0 for a
#: disabled output and UINT16_MAX for an unused RC channel
PWM_PLAUSIBLE_US = (500.0, 2500.0)


def throttle_from_pwm(
    resolved: ResolvedThrottle, pwm_by_channel: Mapping[int, float]
) -> tuple[float, tuple[float, ...]] | None:
    """Throttle 0..1 and each selected channel's 0..1 from PWM values keyed by 1-based channel.

    ``None`` when a selected channel is missing or carries no pulse width (0, or UINT16_MAX for RC
    inputs: "output disabled / channel unused", anything outside PWM_PLAUSIBLE_US): that is no
    throttle information, not throttle 0. For ``motors`` the throttle is the mean of the motors.
    """
    outs: list[float] = []
    lo_ok, hi_ok = PWM_PLAUSIBLE_US
    get = pwm_by_channel.get
    for ch, lo, hi in resolved.ranges:
        pwm = get(ch)
        if pwm is None or not lo_ok <= pwm <= hi_ok:
            return None
        outs.append(pwm_to_01(pwm, lo, hi))
    if not outs:
        return None
    return sum(outs) / len(outs), tuple(outs)


# --- PX4 (ULog actuator_outputs, MAVLink SERVO_OUTPUT_RAW of a PX4 vehicle) ---------------------------------
PX4_MOTOR_FUNCTIONS = range(101, 113)  # PWM_MAIN_FUNCn / PWM_AUX_FUNCn Motor1..Motor12 (PX4 >= 1.13)


def px4_motor_channels(params: Mapping[str, float]) -> tuple[int, ...]:
    """Main outputs whose PWM_MAIN_FUNCn is a motor (101-112), ordered by motor number; () when unknown
    (PX4 before 1.13 has no output functions: its mixers put the motors of a multirotor on outputs 1..n)."""
    return _motors_by_function(params, "PWM_MAIN_FUNC{}", 16, PX4_MOTOR_FUNCTIONS)


def px4_pwm_range(params: Mapping[str, float], channel: int) -> tuple[float, float]:
    """PWM range (us) of PX4 main output ``channel`` (1-based): PWM_MAIN_MINn/MAXn (PX4 >= 1.13, and the
    per-channel overrides of older versions, -1 = unset), else PWM_MAIN_MIN/MAX (1.11-1.12), else PWM_MIN/MAX
    (before 1.11), else 1000-2000 us."""
    for lo_name, hi_name in (
        (f"PWM_MAIN_MIN{channel}", f"PWM_MAIN_MAX{channel}"),
        ("PWM_MAIN_MIN", "PWM_MAIN_MAX"),
        ("PWM_MIN", "PWM_MAX"),
    ):
        lo, hi = params.get(lo_name), params.get(hi_name)
        if lo is not None and hi is not None and hi > lo > 0:
            return float(lo), float(hi)
    return DEFAULT_PWM_MIN, DEFAULT_PWM_MAX
