"""Late matching: a magnetometer sample whose attitude or throttle arrives after it waits until both have
passed its time, and then gets both interpolated to it (on a telemetry link ATTITUDE and the throttle of an
instant often arrive after the RAW_IMU of that instant, so the latest ones are a whole message interval old:
1 s at 1 Hz; docs/inflight.md). No I/O."""

from __future__ import annotations

import itertools
from collections import deque
from typing import Generic, TypeVar

import numpy as np

from magcomp.core.inflight.base import F64
from magcomp.core.rotations import so3_exp, so3_log

#: the longest interval (s) between the attitude (or throttle) samples a sample is interpolated between,
#: and the longest a sample waits for them: the rotation between two samples comes from integrated gyro or
#: the autopilot's attitude, whose yaw drift over this time is well under 1 deg
MAX_PAIR_S = 2.5

P = TypeVar("P")


def interpolate_rotation(att: deque[tuple[float, F64]], t_s: float) -> F64 | None:
    """R_nb at ``t_s`` on the geodesic between the source samples around it (None: outside them, or they
    are more than MAX_PAIR_S apart)."""
    if att and att[-1][0] == t_s:
        return att[-1][1]
    for (t1, r1), (t0, r0) in itertools.pairwise(reversed(att)):  # newest first: the match is near the end
        if t0 <= t_s <= t1:
            if t1 - t0 > MAX_PAIR_S:
                return None
            if t1 == t0:
                return r1
            step = so3_log(r0.T @ r1) * ((t_s - t0) / (t1 - t0))
            return np.asarray(r0 @ so3_exp(step), dtype=np.float64)
    return None


def interpolate_scalar(hist: deque[tuple[float, float]], t_s: float) -> float | None:
    """The value at ``t_s``, linear between the samples around it (None: outside them, or they are more
    than MAX_PAIR_S apart)."""
    if hist and hist[-1][0] == t_s:
        return hist[-1][1]
    for (t1, v1), (t0, v0) in itertools.pairwise(reversed(hist)):
        if t0 <= t_s <= t1:
            if t1 - t0 > MAX_PAIR_S:
                return None
            return v1 if t1 == t0 else v0 + (v1 - v0) * (t_s - t0) / (t1 - t0)
    return None


class LateMatcher(Generic[P]):
    """Samples (a time and a payload) waiting for the attitude and the throttle to pass their time, and the
    recent (time, R_nb) and (time, throttle) samples they are interpolated between."""

    def __init__(self) -> None:
        self._pending: deque[tuple[float, P]] = deque()
        self._att: deque[tuple[float, F64]] = deque()
        self._thr: deque[tuple[float, float]] = deque()

    @property
    def waiting(self) -> bool:
        """Some sample waits (a later one must wait behind it, whatever its own sources' times)."""
        return bool(self._pending)

    def clear(self) -> None:
        """A gap, a clock reset or a change of rotation source: nothing waits, nothing to interpolate."""
        self._pending.clear()
        self._att.clear()
        self._thr.clear()

    def push(
        self, t_s: float, payload: P, r_nb: F64, r_t_s: float, throttle_01: float, throttle_t_s: float
    ) -> list[tuple[float, P, F64, float]]:
        """A sample at ``t_s`` with the latest attitude ``r_nb`` (of time ``r_t_s``) and throttle (of time
        ``throttle_t_s``); returns the waiting samples now matched, oldest first, as (time, payload, R_nb
        and throttle at that time). A sample whose sources stopped more than MAX_PAIR_S before it is
        dropped."""
        att, thr = self._att, self._thr
        if not att or r_t_s > att[-1][0]:
            att.append((r_t_s, r_nb))
        if not thr or throttle_t_s > thr[-1][0]:
            thr.append((throttle_t_s, throttle_01))
        for h in (att, thr):
            while len(h) > 2 and h[1][0] < t_s - 2.0 * MAX_PAIR_S:
                h.popleft()  # type: ignore[union-attr]
        self._pending.append((t_s, payload))
        out = []
        while self._pending:
            tp, pay = self._pending[0]
            reached = min(att[-1][0], thr[-1][0])
            if tp > reached and tp - reached <= MAX_PAIR_S:
                break  # wait for the next ones
            self._pending.popleft()
            if tp > reached:
                continue  # a source stopped: this one will not be matched
            r_at = interpolate_rotation(att, tp)
            thr_at = interpolate_scalar(thr, tp)
            if r_at is not None and thr_at is not None:
                out.append((tp, pay, r_at, thr_at))
        return out
