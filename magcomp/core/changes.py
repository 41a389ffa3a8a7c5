"""Persistent changes in a series of per-flight estimates with intervals (a vehicle's theta, flight after
flight): where successive flights disagree beyond their intervals *and stay changed*.

Pure statistics: arrays in, results out (no I/O, no clock).

Each flight i has an estimate ``x[i]`` (a vector, e.g. theta in mgauss) and a standard deviation ``s[i]`` per
component; its interval is ``x +- k s`` (k = 2: ~95 %). Two estimates *disagree* when, on some component,
their intervals do not overlap: ``|a - b| > k (s_a + s_b)``.

A change is flagged at flight i when

1. flight i disagrees with flight i-1, and
2. it stays changed: flight i and the ``confirm - 1`` flights after it each disagree with the level of the
   flights since the last change (their inverse-variance weighted mean, its standard deviation widened by
   the Birge ratio ``sqrt(chi2 / dof)`` when they scatter more than their intervals say).

A lone outlier (the flight after it returns to the old level) is not a change. A disagreement among the last
flights that too few flights have confirmed yet is reported as *pending*, not as a change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: interval half-width in standard deviations (~95 % for a normal estimate)
K_INTERVAL = 2.0
#: flights (the first changed one included) that must each disagree with the old level
CONFIRM = 2


@dataclass(frozen=True)
class Level:
    """The weighted level of a run of flights: mean and standard deviation per component."""

    mean: NDArray[np.float64]
    std: NDArray[np.float64]
    n: int


@dataclass(frozen=True)
class Change:
    """A persistent change at flight ``index`` (0-based, in the series given)."""

    index: int
    before: Level
    after: Level
    #: |after - before| (the vector's length)
    size: float
    #: the largest |after - before| / sqrt(std_before^2 + std_after^2) over the components
    z: float
    confirmed: bool


def weighted_level(x: ArrayLike, s: ArrayLike) -> Level:
    """Inverse-variance weighted mean of the rows of ``x`` (n, m) with standard deviations ``s`` (n, m); the
    mean's standard deviation is widened by the Birge ratio when the rows scatter more than ``s`` says."""
    xa = np.atleast_2d(np.asarray(x, dtype=float))
    sa = np.atleast_2d(np.asarray(s, dtype=float))
    w = 1.0 / np.maximum(sa, 1e-12) ** 2
    wsum = w.sum(axis=0)
    mean = (w * xa).sum(axis=0) / wsum
    std = 1.0 / np.sqrt(wsum)
    n = xa.shape[0]
    if n > 1:
        chi2 = (w * (xa - mean) ** 2).sum(axis=0)
        std = std * np.sqrt(np.maximum(1.0, chi2 / (n - 1)))
    return Level(mean, std, n)


def disagree(a: ArrayLike, sa: ArrayLike, b: ArrayLike, sb: ArrayLike, k: float = K_INTERVAL) -> bool:
    """The intervals ``a +- k sa`` and ``b +- k sb`` miss each other on some component."""
    d = np.abs(np.asarray(a, dtype=float) - np.asarray(b, dtype=float))
    return bool(np.any(d > k * (np.asarray(sa, dtype=float) + np.asarray(sb, dtype=float))))


def usable(x: ArrayLike, s: ArrayLike) -> NDArray[np.bool_]:
    """Flights with a finite estimate and a finite, positive standard deviation on every component."""
    xa = np.atleast_2d(np.asarray(x, dtype=float))
    sa = np.atleast_2d(np.asarray(s, dtype=float))
    return np.all(np.isfinite(xa), axis=1) & np.all(np.isfinite(sa), axis=1) & np.all(sa > 0, axis=1)


def find_changes(x: ArrayLike, s: ArrayLike, k: float = K_INTERVAL, confirm: int = CONFIRM) -> list[Change]:
    """The persistent changes of the series (rows in flight order; see the module's doc). The last element
    may be unconfirmed (``confirmed`` False): the series ends before ``confirm`` flights could confirm it."""
    xa = np.atleast_2d(np.asarray(x, dtype=float))
    sa = np.atleast_2d(np.asarray(s, dtype=float))
    if xa.shape != sa.shape:
        raise ValueError(f"estimates {xa.shape} and standard deviations {sa.shape} differ in shape")
    n = xa.shape[0]
    if n and not bool(np.all(usable(xa, sa))):
        raise ValueError("every flight needs finite estimates and positive standard deviations")
    if confirm < 1:
        raise ValueError("confirm must be at least 1")
    out: list[Change] = []
    start = 0
    i = 1
    while i < n:
        if not disagree(xa[i - 1], sa[i - 1], xa[i], sa[i], k):
            i += 1
            continue
        before = weighted_level(xa[start:i], sa[start:i])
        end = min(n, i + confirm)
        stays = all(disagree(before.mean, before.std, xa[j], sa[j], k) for j in range(i, end))
        if not stays:
            i += 1
            continue
        confirmed = end - i >= confirm
        after = weighted_level(xa[i:end], sa[i:end])
        diff = after.mean - before.mean
        z = float(np.max(np.abs(diff) / np.sqrt(before.std**2 + after.std**2)))
        out.append(Change(i, before, after, float(np.linalg.norm(diff)), z, confirmed))
        if not confirmed:
            break
        start = i
        i += 1
    return out


def level_after(x: ArrayLike, s: ArrayLike, changes: list[Change]) -> Level | None:
    """The level since the last confirmed change (or of the whole series)."""
    xa = np.atleast_2d(np.asarray(x, dtype=float))
    sa = np.atleast_2d(np.asarray(s, dtype=float))
    if xa.shape[0] == 0 or xa.size == 0:
        return None
    start = max((c.index for c in changes if c.confirmed), default=0)
    return weighted_level(xa[start:], sa[start:])
