"""Source time: one monotonic clock from the per-stream raw timestamps of a log or link.

A jump back of more than ``RESET_JUMP_S`` is a reboot of the autopilot (an offset keeps ``t_s`` monotonic,
``counts["clock_resets"]``); a jump either way is believed only once the next timestamp confirms it
(``counts["time_jumps"]``); smaller steps back within one stream are dropped (``counts["time_backwards"]``).
Streams stamped ``time_usec`` on a clock of their own are moved onto the ``time_boot_ms`` clock by
:class:`StreamOffsets` (see :mod:`magcomp.adapters.mavlink_source`).
"""

from __future__ import annotations

import logging
import math
from collections import deque

log = logging.getLogger("magcomp.source")

RESET_JUMP_S = 5.0  # a timestamp this far behind the newest one is an autopilot reboot
#: a timestamp this far ahead of the newest one (the streams read come at 1 Hz or faster) is believed only
#: when the next timestamp lies within this of it: one corrupt time cannot make the stream after it look
#: like it went backwards, nor stretch the log
FORWARD_CONFIRM_S = 1.0
U32_WRAP_S = 4294.967296  # SERVO_OUTPUT_RAW.time_usec is uint32

#: MAVLink streams stamped ``time_usec`` (us since boot) and those stamped ``time_boot_ms``. ArduCopter
#: 3.1/3.2 stamps the former on a clock of its own, 2.57-2.87 s behind the latter (issue 23, item 4):
#: :class:`StreamOffsets` measures and removes the difference.
USEC_STREAMS = frozenset({"RAW_IMU", "SERVO_OUTPUT_RAW", "HIGHRES_IMU", "ACTUATOR_OUTPUT_STATUS"})
MS_STREAMS = frozenset({"SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "ATTITUDE", "ATTITUDE_QUATERNION",
                        "RC_CHANNELS", "RC_CHANNELS_RAW", "SCALED_PRESSURE"})  # fmt: skip
#: the side of a pair a stream is on (-1: ``time_usec``, +1: ``time_boot_ms``, 0: neither): a pair is two
#: consecutive messages of opposite sides
_SIDE = dict.fromkeys(USEC_STREAMS, -1) | dict.fromkeys(MS_STREAMS, 1)
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
        self._last: tuple[str, float, float, int, int] | None = None  # stream, raw, rx, sender, side
        self._said: set[str] = set()

    def reset(self) -> None:
        self._pairs.clear()
        self._new.clear()
        self._last = None

    def observe(self, stream: str, raw_s: float, rx_s: float, src: int = -1) -> None:
        """One message's stream, raw stamp (s), receive time (s) and sender (system id)."""
        last = self._last
        side = _SIDE.get(stream, 0)
        self._last = (stream, raw_s, rx_s, src, side)
        if last is None:
            return
        last_stream, last_raw, last_rx, last_src, last_side = last
        if side * last_side != -1 or abs(rx_s - last_rx) > PAIR_RX_S or src != last_src:
            return
        if side < 0:
            key, diff = (stream, last_stream, -1), last_raw - raw_s
        else:
            key, diff = (last_stream, stream, 1), raw_s - last_raw
        pairs = self._pairs.get(key)
        if pairs is None:
            pairs = self._pairs[key] = deque(maxlen=OFFSET_WINDOW)
        pairs.append(diff)
        n_new = self._new.get(key, 0) + 1
        n_pairs = len(pairs)
        if n_pairs >= OFFSET_MIN_PAIRS and (n_new >= OFFSET_EVAL_EVERY or n_pairs == OFFSET_MIN_PAIRS):
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


class SourceClock:
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
