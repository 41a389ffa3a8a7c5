"""Causal, stateful low-pass filter of section II-D ("5 Hz corner on the magnetometer readings").

The paper gives only the corner frequency. We use a second-order Butterworth section discretised with
the bilinear transform, pre-warped so the -3 dB point sits at ``corner_hz`` at any sample rate, and
recomputed when the sample interval changes (irregular logs). A first-order section is available for
the lowest phase lag. Departure from the paper: the filter order and design are our choice.

The filter is used on *every* signal that enters one equation together (field, rate, throttle^2), so
that the group delay is the same on both sides of eq. (19); see :mod:`magcomp.core.observer`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class LowPassParams:
    corner_hz: float = 5.0
    order: int = 2  # 1 or 2

    def __post_init__(self) -> None:
        if not self.corner_hz > 0.0:
            raise ValueError(f"low-pass corner must be > 0 Hz, got {self.corner_hz}")
        if self.order not in (1, 2):
            raise ValueError(f"low-pass order must be 1 or 2, got {self.order}")


@dataclass(frozen=True)
class LowPassState:
    """Direct-form-II-transposed state, one row per channel: shape (2, k)."""

    z: F64
    initialized: bool = False


def _coefficients(p: LowPassParams, dt_s: float) -> tuple[F64, F64]:
    """(b, a) of the digital filter for sample interval ``dt_s`` (bilinear, pre-warped)."""
    fs = 1.0 / dt_s
    fc = min(p.corner_hz, 0.45 * fs)  # above Nyquist the filter degenerates to a pass-through
    k = np.tan(np.pi * fc / fs)
    if p.order == 1:
        b0 = k / (1.0 + k)
        return np.array([b0, b0, 0.0]), np.array([1.0, (k - 1.0) / (k + 1.0), 0.0])
    q = 1.0 / np.sqrt(2.0)
    norm = 1.0 / (1.0 + k / q + k * k)
    b0 = k * k * norm
    return (
        np.array([b0, 2.0 * b0, b0]),
        np.array([1.0, 2.0 * (k * k - 1.0) * norm, (1.0 - k / q + k * k) * norm]),
    )


def lowpass_init(x0: ArrayLike) -> LowPassState:
    """State for a filter that starts at rest on ``x0`` (no start-up transient)."""
    x = np.atleast_1d(np.asarray(x0, dtype=float))
    return LowPassState(z=np.zeros((2, x.shape[0])), initialized=False)


def lowpass_step(
    state: LowPassState, x: ArrayLike, dt_s: float, p: LowPassParams
) -> tuple[LowPassState, F64]:
    """Filter one sample ``x`` (shape (k,)) taken ``dt_s`` after the previous one. Returns (state, y)."""
    xv = np.atleast_1d(np.asarray(x, dtype=float))
    if not dt_s > 0.0:
        raise ValueError(f"dt must be > 0, got {dt_s}")
    b, a = _coefficients(p, dt_s)
    if not state.initialized:
        # steady state for a constant input x: y = x
        z1 = (b[1] + b[2] - a[1] - a[2]) * xv
        z2 = (b[2] - a[2]) * xv
        z = np.vstack([z1, z2])
    else:
        z = state.z
    y = b[0] * xv + z[0]
    z1 = b[1] * xv - a[1] * y + z[1]
    z2 = b[2] * xv - a[2] * y
    return LowPassState(z=np.vstack([z1, z2]), initialized=True), y


def lowpass_filter(t_s: ArrayLike, x: ArrayLike, p: LowPassParams) -> F64:
    """Run the causal filter over a whole series (same result as repeated :func:`lowpass_step`)."""
    t = np.asarray(t_s, dtype=float)
    xs = np.asarray(x, dtype=float)
    squeeze = xs.ndim == 1
    x2 = xs[:, None] if squeeze else xs
    out = np.empty_like(x2)
    if len(t) == 0:
        return out[:, 0] if squeeze else out
    st = lowpass_init(x2[0])
    dt_prev = float(np.median(np.diff(t))) if len(t) > 1 else 0.02
    for i in range(len(t)):
        dt = t[i] - t[i - 1] if i > 0 else dt_prev
        if not dt > 0.0:
            dt = dt_prev
        st, out[i] = lowpass_step(st, x2[i], dt, p)
        dt_prev = dt
    return out[:, 0] if squeeze else out


def group_delay_s(p: LowPassParams, dt_s: float, freq_hz: float = 0.0) -> float:
    """Group delay (s) of the discrete filter at ``freq_hz`` for sample interval ``dt_s``."""
    b, a = _coefficients(p, dt_s)
    w = 2.0 * np.pi * max(freq_hz, 1e-6) * dt_s
    dw = 1e-6
    def phase(om: float) -> float:
        zi = np.exp(-1j * om * np.arange(3))
        return float(np.angle(np.dot(b, zi) / np.dot(a, zi)))
    return -(phase(w + dw) - phase(w - dw)) / (2 * dw) * dt_s
