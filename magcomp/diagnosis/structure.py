"""Open search: structure in the final residual that none of the seven named causes explains.

The named extensions are a library; a real vehicle can have other things (a payload or servo switched on
mid-flight: a step in the field; heading-dependent soft iron that a linear calibration cannot absorb: the
second harmonic of the heading; a second current loop: a signal other than the throttle). Each is tried as
a few extra linear columns on the extended model's residual, and reported as *unexplained structure* (with
its time, size and best correlates) when it passes the same tests that admit a named extension:

- an information criterion with the effective sample size: Delta BIC = n_eff ln(RSS_1/RSS_0)
  + k ln(n_eff) <= -``min_delta_bic``, n_eff = 3 n / Bartlett's factor of the candidate against the residual
  (:func:`magcomp.diagnosis.selection.bartlett_factor`): a coloured residual must not pass for structure;
- a relative rms reduction of at least ``min_gain`` (the 1 % held-out gain the named extensions need).

Candidates (k = parameters, counting the searched step time / lag as one):
``step``              a Heaviside column at the largest mean shift of the residual (k = 4)
``heading harmonic``  cos 2psi, sin 2psi of the heading (k = 6)
``follows <signal>``  the signal that explains most of the residual at its best lag (k = 4)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import euler_from_dcms
from magcomp.diagnosis.selection import bartlett_factor
from magcomp.diagnosis.suspects import SignalRelation, find_step

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class StructureParams:
    min_delta_bic: float = 50.0
    min_gain: float = 0.01


def _gain(res: F64, cols: F64) -> tuple[float, F64, F64]:
    """(RSS after / RSS before, coefficients (k, 3), fitted part (n, 3)) of res on [cols, 1]."""
    x = np.column_stack([cols, np.ones(res.shape[0])])
    beta, *_ = np.linalg.lstsq(x, res, rcond=None)
    fitted = x @ beta
    rss0 = float(np.sum((res - res.mean(axis=0)) ** 2))
    rss1 = float(np.sum((res - fitted) ** 2))
    return (rss1 / rss0 if rss0 > 0 else 1.0), np.asarray(beta[:-1]), fitted


def search(
    t_s: F64,
    residual_mgauss: F64,
    r_nb: F64,
    signals: dict[str, tuple[F64, F64]],
    suspects: list[SignalRelation],
    events: list[tuple[float, str]] | None = None,
    p: StructureParams | None = None,
) -> list[dict[str, Any]]:
    """Candidates that pass (see the module docstring), strongest first, as JSON-ready dicts."""
    p = p or StructureParams()
    n = t_s.shape[0]
    if n < 50:
        return []
    res = residual_mgauss - residual_mgauss.mean(axis=0)
    rms0 = float(np.sqrt(np.mean(res**2)))
    found: list[dict[str, Any]] = []

    def passes(ratio: float, k: int, fitted: F64) -> tuple[bool, float]:
        n_eff = 3.0 * n / bartlett_factor(res - fitted, fitted - fitted.mean(axis=0))
        dbic = n_eff * math.log(max(ratio, 1e-12)) + k * math.log(n_eff)
        return dbic <= -p.min_delta_bic and (1.0 - math.sqrt(ratio)) >= p.min_gain, dbic

    top = [{"signal": s.signal, "lag_s": s.lag_s, "r2": round(s.r2, 3)} for s in suspects[:3] if s.r2 > 0.0]
    st = find_step(t_s, res, signals, events)
    if st is not None:
        col = (t_s >= st.t_s).astype(float)
        ratio, beta, fitted = _gain(res, col[:, None])
        ok, dbic = passes(ratio, 4, fitted)
        if ok:
            found.append(
                {
                    "kind": "step",
                    "t_s": round(st.t_s, 2),
                    "size_mgauss": [round(float(v), 2) for v in beta[0]],
                    "rms_reduction_pct": round(100.0 * (1.0 - math.sqrt(ratio)), 2),
                    "delta_bic": round(dbic, 1),
                    "co_stepping_signals": dict(list(st.co_stepping.items())[:5]),
                    "events": [{"t_s": round(te, 2), "event": e} for te, e in st.events],
                    "best_correlates": top,
                }
            )
    yaw = euler_from_dcms(r_nb)[:, 2]
    ratio, beta, fitted = _gain(res, np.column_stack([np.cos(2 * yaw), np.sin(2 * yaw)]))
    ok, dbic = passes(ratio, 6, fitted)
    if ok:
        found.append(
            {
                "kind": "heading harmonic",
                "size_mgauss": [round(float(np.linalg.norm(beta[:, i])), 2) for i in range(3)],
                "rms_reduction_pct": round(100.0 * (1.0 - math.sqrt(ratio)), 2),
                "delta_bic": round(dbic, 1),
                "note": "a field error that repeats twice per turn: heading-dependent soft iron the linear "
                "calibration (eq. (1)) cannot absorb",
                "best_correlates": top,
            }
        )
    if suspects and suspects[0].signal in signals and suspects[0].r2 > 0.0:
        s = suspects[0]
        ts, vs = signals[s.signal]
        col = np.interp(t_s - s.lag_s, ts, vs)
        ratio, beta, fitted = _gain(res, col[:, None])
        ok, dbic = passes(ratio, 4, fitted)
        if ok:
            sd = float(np.std(col))
            found.append(
                {
                    "kind": f"follows {s.signal}",
                    "lag_s": s.lag_s,
                    "size_mgauss": [round(float(v) * 2.0 * sd, 2) for v in beta[0]],
                    "size_is": "per axis, over +-1 standard deviation of the signal",
                    "rms_reduction_pct": round(100.0 * (1.0 - math.sqrt(ratio)), 2),
                    "delta_bic": round(dbic, 1),
                    "best_correlates": top,
                }
            )
    found.sort(key=lambda d: -float(d["rms_reduction_pct"]))
    for d in found:
        d["residual_rms_mgauss"] = round(rms0, 3)
    return found
