"""Compact columnar storage for whole-log loading (:func:`magcomp.adapters.mavlink_source.load_log`).

A log is read one message at a time; what ``load_log`` keeps of each message goes into typed arrays, one
struct-of-arrays per kind of record, instead of lists of Python objects. A row of three floats kept as a
tuple (or a sample object with a 3-vector array) costs 150-350 bytes; here it costs 8 bytes per value plus
8 for its time. The arrays are :class:`array.array`: appended to in amortised O(1) (grown geometrically),
handed to numpy without a copy at the end.

Precision: times, physical values (field, rates, attitude, power, position) stay float64, the dtype of
:class:`~magcomp.core.types.LogData` (so every number reaching the fit and the diagnosis is bit for bit the
one the message gave). PWM pulse widths are float32: every PWM field read is an integer number of us
(uint16 in SERVO_OUTPUT_RAW, RC_CHANNELS and DataFlash RCOU), exact in float32; PX4's float
ACTUATOR_OUTPUT_STATUS values are kept to 1e-4 us at 2000 us, far below any ESC's resolution (1 us).

Windows (``fit --start/--end``): a :class:`Window` keeps the rows inside ``[lo, hi]`` plus, per store, the
last row before ``lo`` and the first after ``hi``, so that interpolation at the window's edges (throttle at a
magnetometer time) sees the same neighbours as on the whole log.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.core.types import Series

_NAN = math.nan
_BLOCK = 1 << 16  # rows turned back into Python floats at a time


@dataclass(frozen=True, slots=True)
class Window:
    """Rows to keep: ``lo <= t_s <= hi`` (s on the log's clock), plus one neighbour on each side."""

    lo: float = -math.inf
    hi: float = math.inf

    @classmethod
    def around(cls, start_s: float | None, end_s: float | None, pad_s: float) -> Window | None:
        """The window ``[start - pad, end + pad]`` (an open side when not given); None when neither is."""
        if start_s is None and end_s is None:
            return None
        lo = -math.inf if start_s is None else start_s - pad_s
        hi = math.inf if end_s is None else end_s + pad_s
        return cls(lo, hi)


class _Windowed:
    """Window bookkeeping shared by the stores: which offered rows are stored (``_put``), in order."""

    __slots__ = ("_after_taken", "_before", "n_seen", "window")

    def __init__(self, window: Window | None) -> None:
        self.window = window
        self.n_seen = 0  # rows offered, inside the window or not
        self._before: tuple[float, Any] | None = None
        self._after_taken = False

    def _put(self, t_s: float, row: Any) -> None:
        raise NotImplementedError

    def _offer(self, t_s: float, row: Any) -> None:
        """A row of a windowed store: stored when inside the window, or when it is the neighbour of one."""
        w = self.window
        assert w is not None
        if t_s < w.lo:  # NaN times are never offered (the clock drops them)
            self._before = (t_s, row)
            return
        if t_s > w.hi:
            if self._after_taken:
                return
            self._after_taken = True
        self._flush()
        self._put(t_s, row)

    def _flush(self) -> None:
        """Store the last row before the window (at its first row inside or after it, or at the end)."""
        if self._before is not None:
            before, self._before = self._before, None
            self._put(*before)


class Rows(_Windowed):
    """Rows ``(t_s, v_0 .. v_{width-1})`` of one stream, float64, in arrival order.

    ``width`` 0 is a scalar series (``append(t, (v,))``; values shape (n,)); otherwise values are (n, width).
    """

    __slots__ = ("_t", "_v", "width")

    def __init__(self, width: int = 0, window: Window | None = None) -> None:
        super().__init__(window)
        self.width = width
        self._t = array("d")
        self._v = array("d")

    def append(self, t_s: float, values: Sequence[float]) -> None:
        self.n_seen += 1
        if self.window is None:
            self._t.append(t_s)
            self._v.extend(values)
        else:
            self._offer(t_s, values)

    def _put(self, t_s: float, row: Any) -> None:
        self._t.append(t_s)
        self._v.extend(row)

    def __len__(self) -> int:
        return len(self._t) + (self._before is not None)

    def arrays(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(t_s (n,), values (n,) or (n, width)) in arrival order (views of the arrays, no copy); the store
        is complete (nothing is appended after this)."""
        self._flush()
        t = np.frombuffer(self._t, dtype=np.float64) if len(self._t) else np.zeros(0)
        v = np.frombuffer(self._v, dtype=np.float64) if len(self._v) else np.zeros(0)
        return t, (v if self.width == 0 else v.reshape(-1, self.width))

    def series(self) -> Series:
        """The rows sorted by time (stable: equal times keep their arrival order), as a Series."""
        self._flush()
        if not len(self._t):
            return Series.empty(self.width)
        t, v = self.arrays()
        if bool(np.all(t[1:] >= t[:-1])):  # already in order (the usual case): the arrays as they are
            return Series(t, v)
        order = np.argsort(t, kind="stable")
        return Series(t[order], v[order])


class PwmRows(_Windowed):
    """PWM pulse widths (us) by 1-based channel, one row per message, float32 (see the module docstring);
    a channel a message does not carry is NaN (a channel first seen late is NaN in the rows before)."""

    __slots__ = ("_ch", "_t")

    def __init__(self, window: Window | None = None) -> None:
        super().__init__(window)
        self._t = array("d")
        self._ch: dict[int, array[float]] = {}

    def append(self, t_s: float, pwm_us: Mapping[int, float]) -> None:
        self.n_seen += 1
        if self.window is None:
            self._put(t_s, pwm_us)
        else:
            self._offer(t_s, pwm_us)

    def _put(self, t_s: float, pwm_us: Mapping[int, float]) -> None:
        n = len(self._t)
        self._t.append(t_s)
        cols = self._ch
        for ch, col in cols.items():
            col.append(pwm_us.get(ch, _NAN))
        if not pwm_us.keys() <= cols.keys():  # a channel seen for the first time
            for ch, value in pwm_us.items():
                if ch not in cols:
                    col = cols[ch] = array("f", [_NAN]) * n
                    col.append(value)

    def __len__(self) -> int:
        return len(self._t) + (self._before is not None)

    def rows(self, channels: Sequence[int]) -> Iterator[tuple[float, dict[int, float]]]:
        """(t_s, {channel: pwm}) in arrival order for the given channels (those a row carries), as the
        message gave them (Python floats)."""
        self._flush()
        have = [ch for ch in channels if ch in self._ch]
        for a in range(0, len(self._t), _BLOCK):  # a block at a time: the Python floats are transient
            t = self._t[a : a + _BLOCK].tolist()
            cols = [(ch, self._ch[ch][a : a + _BLOCK].tolist()) for ch in have]
            for i, t_s in enumerate(t):
                yield t_s, {ch: col[i] for ch, col in cols if col[i] == col[i]}  # NaN: not carried
