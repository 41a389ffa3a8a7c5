"""The autopilot's attitude at each magnetometer sample's time, where its ATTITUDE stream is slow.

Eq. (24) tilt-compensates a magnetometer sample with the roll and pitch at its time. The pipeline takes
them from the latest ATTITUDE. At 1-4 Hz telemetry that is up to an interval old (0.25-1 s): a banked turn
or a roll back to level in between tilts the heading by the roll changed times tan(inclination) (2-3
degrees of heading per degree of roll at 60-70 deg of inclination). On a real telemetry log (ArduCopter
3.5.7, ATTITUDE at 2.2 Hz, the field at 1.25 Hz) the autopilot's own field so compensated was 10.4 deg rms
from the autopilot's yaw, interpolated between the two ATTITUDE messages around each sample 7.0: magcomp's
fallback to "the autopilot's own heading" was worse than that heading (docs/real-flights.md, eleventh
stop). Extrapolating the latest attitude with the gyro or the attitude's own change did worse than holding
it (the gyro of telemetry is one instantaneous sample per interval).

So in a two-pass replay (the default ``magcomp replay``: the whole log is known), where the ATTITUDE stream
is slower than MAX_GYRO_DT_S (the cut between an IMU-rate stream and telemetry, the self-check's), a
magnetometer sample, and every sample after it in the stream, waits for the next ATTITUDE; the roll, pitch
and yaw interpolated at the magnetometer sample's time then go to the pipeline as an ATTITUDE at that time,
just before it. The order of the stream is kept; what changes is what the pipeline knows of the attitude at
each magnetometer sample (its heading, its in-flight rows, the self-check's references). Where the stream is
fast nothing waits.

Not live (the daemon, ``--causal``): there a sample would wait up to one ATTITUDE interval before it is
published, and measured that way (the same class before the daemon's pipeline) it changed which corrections
the running self-check switched on: a live correction switches on with its own constant, a step att counts,
and two absolute-form compasses switched on where they had not (the development corpus's ``--causal`` median
att ratio 0.60 -> 0.67 from squilter kresge_02 compass 1 alone; a held-out tlog's compass 1 worse than the
autopilot's own); docs/real-flights.md, eighth stop.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator

from magcomp.core.selfcheck import MAX_GYRO_DT_S
from magcomp.core.types import AttitudeSample, ClockResetSample, MagSample, Sample

#: the longest ATTITUDE gap interpolated across (s): a 1 Hz stream with one message lost; over a longer gap
#: the samples held go on with the latest attitude as before
MAX_BRACKET_S = 2.0


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def interpolated(a: AttitudeSample, b: AttitudeSample, t_s: float) -> AttitudeSample:
    """Roll, pitch and yaw (the shorter way round) linearly between ``a`` and ``b`` at ``t_s``."""
    span = b.t_s - a.t_s
    f = 0.0 if span <= 0.0 else min(1.0, max(0.0, (t_s - a.t_s) / span))
    yaw = _wrap_pi(a.yaw_rad + f * _wrap_pi(b.yaw_rad - a.yaw_rad))
    return AttitudeSample(
        t_s, a.roll_rad + f * (b.roll_rad - a.roll_rad), a.pitch_rad + f * (b.pitch_rad - a.pitch_rad), yaw
    )


class AttitudeAtMag:
    """One sender's stream: :meth:`push` a sample, get the samples to process now (in stream order, with an
    interpolated ATTITUDE before each magnetometer sample that waited); :meth:`flush` at the end."""

    __slots__ = ("_held", "_last", "_slow", "inserted")

    def __init__(self) -> None:
        #: the interpolated ATTITUDEs passed on (not the log's: a count of the log's samples leaves them out)
        self.inserted = 0
        self._held: list[Sample] = []
        self._last: AttitudeSample | None = None  # the latest ATTITUDE passed on
        self._slow = False  # its stream's latest interval is longer than MAX_GYRO_DT_S

    def push(self, s: Sample) -> list[Sample]:
        held = self._held
        cls = type(s)
        if cls is AttitudeSample or isinstance(s, AttitudeSample):
            return self._on_attitude(s)  # type: ignore[arg-type]
        if cls is ClockResetSample:  # a reboot: the attitude before it says nothing of the samples after
            out = self.flush()
            out.append(s)
            self._last = None
            return out
        if held:
            if s.t_s - held[0].t_s > MAX_BRACKET_S:  # no ATTITUDE came: on with the latest one
                out = self.flush()
                return [*out, *self.push(s)]
            held.append(s)
            return []
        last = self._last
        if self._slow and isinstance(s, MagSample) and last is not None and s.t_s > last.t_s:
            held.append(s)
            return []
        return [s]

    def _on_attitude(self, a: AttitudeSample) -> list[Sample]:
        last, held = self._last, self._held
        self._slow = last is not None and a.t_s - last.t_s > MAX_GYRO_DT_S
        self._last = a
        if not held:
            return [a]
        out: list[Sample] = []
        keep: list[Sample] = []
        t_prev = -math.inf if last is None else last.t_s
        for s in held:
            if keep:
                keep.append(s)
            elif isinstance(s, MagSample) and s.t_s > a.t_s:
                keep.append(s)  # still ahead of this ATTITUDE: waits for the next one
            else:
                if isinstance(s, MagSample) and last is not None and a.t_s - last.t_s <= MAX_BRACKET_S:
                    # the angles at the sample's time; stamped no earlier than the ATTITUDE before it (the
                    # compasses' streams are re-timed apart by tens of ms: a stamp going back is dropped)
                    att = interpolated(last, a, s.t_s)
                    t_prev = max(t_prev, s.t_s)
                    out.append(att if att.t_s == t_prev else AttitudeSample(
                        t_prev, att.roll_rad, att.pitch_rad, att.yaw_rad))
                    self.inserted += 1
                out.append(s)
        if keep:  # this ATTITUDE goes before the samples still waiting, as the stream had it
            out.append(a)
            self._held = keep
            return out
        self._held = []
        out.append(a)
        return out

    def flush(self) -> list[Sample]:
        """The samples still held, as they came (no ATTITUDE after them)."""
        out, self._held = self._held, []
        return out


    def stream(self, samples: Iterable[Sample]) -> Iterator[Sample]:
        """:meth:`push` over a whole stream of one sender, then :meth:`flush`."""
        push = self.push
        for s in samples:
            yield from push(s)
        yield from self.flush()
