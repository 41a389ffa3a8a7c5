"""The logged battery current: a second witness of the powertrain's load shape.

The bias the compass sees is the field of the motor currents (eqs. (5a), (11): B = theta I / I_max with
I / I_max = delta^2), and the autopilot logs the battery current beside the compass. The throttle-shape
effects (``throttle_offset``, ``throttle_exponent``, ``voltage_sag``) each change how the load follows the
logged throttle, so each must change the logged current the same way: I(t) = i0 + i1 D(t; value), D the
effect's drive column (:func:`magcomp.diagnosis.effects.drive_columns`), i0 the avionics' draw and the
sensor's zero offset, i1 the current at full load. Pure, no I/O.

Why a second witness: on a 60 s flight what tells a sag from a rescaled throttle^2 in the field is ~2 % of
the load, ~4 mgauss on a 200 mgauss theta, against 3 mgauss of slow AR(1) compass noise; the compass's
generalised-least-squares evidence then straddles the -30 margin (measured on held-out logs: -14 to -30 on
the five of 40 fresh logs, seeds 5100-5139, at sag 1.0 that named nothing). The current carries the same
2 % against a sensor noise of tens of mA on tens of A: the same sag gives delta BIC about -1600 on the
current (exponent about -115, offset none), and on clean logs no shape improves it (+6, the BIC's penalty).
So a throttle-shape effect that the compass's own evidence prefers but leaves short of the margin is named
when the current record independently shows that same effect (:func:`corroborates`): both witnesses agree
on the cause and the current's value lies inside the compass's own 95 % interval. The interval reported
stays the compass's: the current's model (the throttle interpolated between its samples, the total of the
motors' currents taken as the mean throttle's load) has errors of its own that are not the field's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from magcomp.diagnosis.effects import EFFECTS, DriveInputs, ExtensionParams, drive_columns, with_effect
from magcomp.diagnosis.rivals import GROUPS, RIVAL_DELTA_BIC
from magcomp.diagnosis.selection import bartlett_factor

F64 = NDArray[np.float64]

#: the current must vary by this much (A) to witness a load shape: a few times a hobby sensor's resolution
MIN_CURRENT_SPAN_A = 2.0
#: trial values per effect on its range before the bounded refinement
_GRID_POINTS = 151


@dataclass(frozen=True)
class CurrentFit:
    """One throttle-shape effect fitted to the logged current: its value and its effective delta BIC against
    the paper's throttle^2 (negative: the effect's shape explains the current better)."""

    effect: str
    value: float
    delta_bic: float


def _rss(d: DriveInputs, t_s: F64, amps: F64, p: ExtensionParams) -> tuple[float, F64, F64]:
    """Residual sum of squares, residual and fitted values of I = i0 + i1 D(t; p) at the current's times."""
    col = drive_columns(replace(d, t_s=t_s, extra=None, extra_names=()), p)[0][:, 0]
    x = np.column_stack([np.ones_like(col), col])
    beta, *_ = np.linalg.lstsq(x, amps, rcond=None)
    fitted = x @ beta
    r = amps - fitted
    return float(r @ r), r, fitted


def _best_value(d: DriveInputs, t_s: F64, amps: F64, name: str) -> float:
    """The effect's value minimising the current's residual: a grid over its range, then a bounded search
    between the grid neighbours of the best point."""
    from scipy.optimize import minimize_scalar

    lo, hi = EFFECTS[name].bounds
    base = ExtensionParams()
    grid = np.linspace(lo, hi, _GRID_POINTS)
    rss = [_rss(d, t_s, amps, with_effect(base, name, float(v)))[0] for v in grid]
    k = int(np.argmin(rss))
    a, b = float(grid[max(k - 1, 0)]), float(grid[min(k + 1, grid.size - 1)])
    res = minimize_scalar(
        lambda v: _rss(d, t_s, amps, with_effect(base, name, float(v)))[0],
        bounds=(a, b),
        method="bounded",
        options={"xatol": 1e-5 * (hi - lo)},
    )
    return float(res.x) if float(res.fun) <= rss[k] else float(grid[k])


def current_fits(d: DriveInputs) -> dict[str, CurrentFit]:
    """Each throttle-shape effect fitted to the logged current (empty when the log has no current that
    varies by MIN_CURRENT_SPAN_A). The delta BIC uses the effective sample size n / Bartlett's factor of
    the residual against what the effect explains (``selection.bartlett_factor``), so a current sensor's
    filtering or a slow model error is not counted once per sample."""
    if d.current_t_s is None or d.current_a is None:
        return {}
    inside = (d.current_t_s >= d.grid_t_s[0]) & (d.current_t_s <= d.grid_t_s[-1])
    t_s, amps = d.current_t_s[inside], d.current_a[inside]
    if amps.size < 20 or float(np.ptp(amps)) < MIN_CURRENT_SPAN_A:
        return {}
    rss0, _, fit0 = _rss(d, t_s, amps, ExtensionParams())
    out: dict[str, CurrentFit] = {}
    for name in GROUPS["throttle_shape"]:
        if name == "voltage_sag" and d.voltage_grid is None:
            continue
        v = _best_value(d, t_s, amps, name)
        rss, r, fitted = _rss(d, t_s, amps, with_effect(ExtensionParams(), name, v))
        explained = (fitted - fit0)[:, None]
        n_eff = amps.size / bartlett_factor(r[:, None], explained)
        ratio = rss / rss0 if rss0 > 0.0 else 1.0
        out[name] = CurrentFit(name, v, n_eff * math.log(max(ratio, 1e-300)) + math.log(n_eff))
    return out


def corroborates(
    name: str, fits: dict[str, CurrentFit], interval: tuple[float, float] | None, margin: float
) -> CurrentFit | None:
    """The current's fit of ``name`` when it witnesses the compass's finding, else None: the current's
    evidence for ``name`` passes the ``margin`` on its own, ``name`` is the throttle shape the current
    prefers (or within RIVAL_DELTA_BIC of it: a shape the current tells apart from a better one is not
    witnessed), and the current's value lies inside the compass's 95 % ``interval`` for it."""
    f = fits.get(name)
    if f is None or interval is None or not f.delta_bic <= -margin:
        return None
    best = min(c.delta_bic for c in fits.values())
    if f.delta_bic - best >= RIVAL_DELTA_BIC:
        return None
    return f if interval[0] <= f.value <= interval[1] else None
