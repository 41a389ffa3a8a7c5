"""The model search for one compass: the paper's model (baseline), each extension on its own, rivals the data
cannot tell apart, the greedy combination, and the open search for a step of the field.

:func:`diagnose_compass` runs these steps in order and returns a complete, frozen
:class:`~magcomp.diagnosis.results.CompassDiagnosis`. Pure, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcomp.core.types import LogData
from magcomp.diagnosis.current import CurrentFit, corroborates, current_fits
from magcomp.diagnosis.effects import EFFECTS, delay_unresolved, effect_available, negligible
from magcomp.diagnosis.export import autopilot_export, evidence_json, params_json, r4
from magcomp.diagnosis.inputs import inlier_mask, signals_at, spans, subset
from magcomp.diagnosis.intervals import profile_interval
from magcomp.diagnosis.latency import MAX_HOLD_S, unheld_age_bounds_s
from magcomp.diagnosis.model import CompassData, ModelFit, design, fit_model, initial_fit
from magcomp.diagnosis.results import CompassDiagnosis, Finding
from magcomp.diagnosis.rivals import (
    GROUPS,
    RIVAL_DELTA_BIC,
    group_of,
    rival_gap,
    rival_set,
    temperature_beats_time,
    time_shapes,
)
from magcomp.diagnosis.selection import (
    Comparison,
    CVScore,
    Folds,
    SelectionParams,
    compare,
    cv_score,
    effective_delta_bic,
    folds_for,
    repeat_in_halves,
)
from magcomp.diagnosis.structure import search as structure_search
from magcomp.diagnosis.suspects import find_step, relate, step_at

F64 = NDArray[np.float64]
Signals = dict[str, tuple[F64, F64]]
Events = list[tuple[float, str]]


class Baseline(NamedTuple):
    """The paper's model fitted on the data left after outlier spans are excluded."""

    data: CompassData
    fit: ModelFit
    excluded: list[tuple[float, float]]


@dataclass
class _Search:
    """What the search has decided so far (internal; the order of ``rejected`` is the JSON's order)."""

    unavailable: dict[str, str] = field(default_factory=dict)
    rejected: dict[str, dict[str, Any]] = field(default_factory=dict)
    singles: list[Comparison] = field(default_factory=list)
    temp_vs_time: dict[str, dict[str, float]] = field(default_factory=dict)
    cv_base: CVScore | None = None
    folds: Folds | None = None
    candidates: dict[str, list[str]] = field(default_factory=dict)
    candidate_params: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: per effect, its single fit and that fit's profile interval (the report asks for it again)
    intervals: dict[str, tuple[ModelFit, tuple[float, float] | None]] = field(default_factory=dict)
    #: fits of group members refused by the margin or the held-out test alone (:func:`group_rivals`)
    near: dict[str, ModelFit] = field(default_factory=dict)
    #: the throttle shapes fitted to the logged current (None: not yet computed) and the effects it witnessed
    current: dict[str, CurrentFit] | None = None
    witnessed: dict[str, CurrentFit] = field(default_factory=dict)

    def interval(self, name: str, fit: ModelFit) -> tuple[float, float] | None:
        """The profile interval of ``name`` already computed for this very ``fit``, or None."""
        known = self.intervals.get(name)
        return known[1] if known is not None and known[0] is fit else None

    def base_cv(self, data: CompassData, base: ModelFit, p: SelectionParams) -> Callable[[], CVScore]:
        """The baseline's held-out score, computed at the first call (a comparison that fails the BIC test
        never asks for it) and kept."""

        def get() -> CVScore:
            if self.cv_base is None:
                self.cv_base = cv_score(data, base, p, self.folds)
            return self.cv_base

        return get


class Combined(NamedTuple):
    """The greedy combination: the final fit, its held-out rms and each kept effect with its comparison."""

    fit: ModelFit
    cv: CVScore | None
    kept: list[tuple[str, Comparison]]


class StepCandidate(NamedTuple):
    """A step of the field that passed: the data with its column, the refit, and the report entry."""

    data: CompassData
    fit: ModelFit
    info: dict[str, Any]


def fit_baseline(data: CompassData, p: SelectionParams) -> Baseline:
    """The paper's model eq. (11), refitted (up to twice) without the outlier spans of its residual."""
    base = fit_model(data, (), start=initial_fit(data), max_nfev=p.max_nfev)
    excluded: list[tuple[float, float]] = []
    for _ in range(2):
        keep = inlier_mask(data.t_s, base.residual_mgauss)
        if keep is None:
            break
        excluded += spans(data.t_s, ~keep)
        data = subset(data, keep)
        base = fit_model(data, (), start=initial_fit(data), max_nfev=p.max_nfev)
    return Baseline(data, base, excluded)


def _cheap_rejection(
    name: str, f: ModelFit, dbic: float, data: CompassData, p: SelectionParams
) -> str | None:
    """Why extension ``name`` fails before any held-out test (BIC, negligible, pinned), or None."""
    param = EFFECTS[name].param
    small = negligible(name, float(getattr(f.ext, param)), data.drive, MAX_HOLD_S) if param else None
    if dbic > -p.min_delta_bic:  # cheap test first: CV only for candidates that pass BIC
        return "BIC"
    if small is not None:
        return small
    if param is not None:
        lo_b, hi_b = EFFECTS[name].bounds
        v = float(getattr(f.ext, param))
        # (a lower bound of 0 is the effect switched off, which ``negligible`` judges)
        near_lo = lo_b != 0.0 and v - lo_b < 0.01 * (hi_b - lo_b)
        if near_lo or hi_b - v < 0.01 * (hi_b - lo_b):
            # a parameter pinned at the end of its physical range: the data want something the cause
            # cannot be (e.g. a 5 s "spin-up lag" that is really a slow drift), so it is not the cause
            return f"{param} = {v:.3g} at the edge of its range [{lo_b}, {hi_b}]"
    return None


def interval_at_edge(
    name: str, data: CompassData, f: ModelFit, ci: tuple[float, float] | None = None
) -> str | None:
    """Why a significant nonlinear extension is not identified, or None: its 95 % profile interval reaches the
    end of its physical range (a lower end of 0 is the effect switched off, judged by the BIC instead).

    The rule of :func:`_cheap_rejection` for the point estimate, applied to what the data cannot exclude: a
    parameter that may as well sit at its physical ceiling (a 9 s "lag" on a 1-2 min hover, interval to the
    10 s ceiling) is a slow drift of the log, not the cause. Measured: the one false alarm on fresh clean
    seeds 10600-10659 (``benchmarks/diagnosis_false_alarm.py``) was such a lag, 9.1 s [5.6, 10.0].
    ``ci``: that interval when the caller has it (:func:`~magcomp.diagnosis.intervals.profile_interval`)."""
    param = EFFECTS[name].param
    ci = ci if ci is not None else profile_interval(data, f, name)
    if param is None or ci is None:
        return None
    lo_b, hi_b = EFFECTS[name].bounds
    tol = 1e-3 * (hi_b - lo_b)
    if ci[1] >= hi_b - tol or (lo_b != 0.0 and ci[0] <= lo_b + tol):
        rng = f"[{lo_b}, {hi_b}]"
        return f"{param}'s 95 % interval [{ci[0]:.3g}, {ci[1]:.3g}] reaches the end of its range {rng}"
    return None


def within_compass_age(name: str, data: CompassData, ci: tuple[float, float] | None) -> str | None:
    """Why a timing effect cannot be told from the age of the compass's own samples, or None.

    A compass sample is older than its logged time by 0 to one compass period, and the field then follows
    the logged throttle by that much: a delay a skew or a lag would fit. Where the ages were read from a
    hold or fitted against the rotation (``engine._unheld_age``), the drive is taken at the measurement
    times (``data.drive.t_s`` differs from ``data.t_s``); where the rotation is the gyro's integral the age
    was fitted against it (kept where it helped the paper model, else found not to: a fast or a slow gyro,
    engine._unheld_age); otherwise (an unheld compass on a vehicle that does not rotate, or against the
    autopilot's attitude) the age is unknown within
    :func:`~magcomp.diagnosis.latency.unheld_age_bounds_s`, and a skew or lag whose 95 % interval reaches into
    that range is not identified. Measured on clean held-out logs at drawn rates (``diagnosis_heldout.py
    --clean --rates``, seeds 6000-6019, the bench cases): a lag of 43 ms [5, 89] and 63 ms [15, 127], a
    skew of 41 ms [1, 65], on compasses at 24.7 and 16.9 Hz in 25 and 20 Hz messages (ages 30-40 ms)."""
    if name not in ("time_skew", "current_lag") or ci is None or data.n < 2:
        return None
    if not np.array_equal(data.drive.t_s, data.t_s) or data.attitude_source.startswith("gyro"):
        return None  # re-timed by a hold or a fitted age, or the age fitted against the gyro's rotation
    _, max_age = unheld_age_bounds_s(data.t_s)
    if ci[0] > max_age or ci[1] < 0.0:  # above any age, or the field leading the throttle (no age does that)
        return None
    return (
        f"{EFFECTS[name].param}'s 95 % interval [{ci[0]:.3g}, {ci[1]:.3g}] s reaches into the age of the "
        f"compass's own samples (0-{max_age:.3f} s: one compass period; not read from a hold nor fitted "
        "against a rotation)"
    )


def not_identified(name: str, data: CompassData, f: ModelFit, ci: tuple[float, float] | None) -> str | None:
    """Why a significant extension with the 95 % profile interval ``ci`` is not named, or None: the interval
    reaches the end of its range (:func:`interval_at_edge`), or a delay shorter than the throttle's
    sampling interval is not told from the samples' timing
    (:func:`~magcomp.diagnosis.effects.delay_unresolved`; MAX_HOLD_S: the oldest a compass sample can be)."""
    edge = interval_at_edge(name, data, f, ci)
    param = EFFECTS[name].param
    if edge is not None or param is None:
        return edge
    return delay_unresolved(name, float(getattr(f.ext, param)), ci, data.drive, MAX_HOLD_S)


def _test_single(name: str, data: CompassData, base: ModelFit, p: SelectionParams, s: _Search) -> None:
    """Fit extension ``name`` alone against the baseline; record it in ``s`` as a single or a rejection."""
    f = fit_model(data, (name,), start=base, max_nfev=p.max_nfev)
    dbic = f.bic - base.bic
    why = _cheap_rejection(name, f, dbic, data, p)
    if why == "BIC" and dbic < 0.0 and _current_shows(name, data, p, s):
        why = _cheap_rejection(name, f, -math.inf, data, p)  # the current may witness it; the rest holds
    if why is not None:
        s.rejected[name] = {"delta_bic": r4(dbic), "rms_with": r4(f.rms_mgauss), "why": why}
        return
    if s.folds is None:
        s.folds = folds_for(data, base, p)
    c = compare(data, base, f, s.base_cv(data, base, p), p, s.folds)
    short = not c.significant and c.cv_extended is None and c.delta_bic < 0.0
    if short and group_of(name) == "throttle_shape":
        c = _witnessed(name, data, base, f, c, p, s)
    if c.significant and name == "temperature_drift":
        wins, shape, vs_time = temperature_beats_time(data, base, f, RIVAL_DELTA_BIC, p.max_nfev)
        if not wins:
            s.rejected[name] = {
                "delta_bic": r4(dbic),
                "cv_gain_pct": r4(100 * c.cv_gain),
                "delta_bic_vs_time_shapes": vs_time,
                "why": f"no better than a smooth drift {shape} with as many parameters",
            }
            return
        s.temp_vs_time[name] = vs_time
    if c.significant and EFFECTS[name].param is not None:
        ci = s.interval(name, f)  # a witnessed shape's was profiled already (_witnessed)
        if ci is None:
            ci = profile_interval(data, f, name)
        s.intervals[name] = (f, ci)
        why_edge = not_identified(name, data, f, ci) or within_compass_age(name, data, ci)
        if why_edge is not None:
            s.rejected[name] = {"delta_bic": r4(dbic), "cv_gain_pct": r4(100 * c.cv_gain), "why": why_edge}
            return
    if c.significant:
        s.singles.append(c)
    else:
        held_out_ok = c.cv_gain > 0.0 and c.cv_t >= c.cv_t_critical
        if c.cv_extended is None:  # the BIC test failed first: the held-out test was not run
            why = f"effective BIC {c.delta_bic:.0f} > -{p.min_delta_bic:.0f} (held-out test not run)"
        elif held_out_ok:
            why = f"effective BIC {c.delta_bic:.0f}"
        else:
            why = f"held-out (Diebold-Mariano {c.cv_t:.1f} < {c.cv_t_critical:.2f})"
        if group_of(name) is not None:
            s.near[name] = f
        s.rejected[name] = {
            "delta_bic": r4(dbic),
            "effective_delta_bic": r4(c.delta_bic),
            "cv_gain_pct": r4(100 * c.cv_gain),
            "cv_t": r4(c.cv_t) if math.isfinite(c.cv_t) else None,
            "why": why,
        }


def _current_shows(name: str, data: CompassData, p: SelectionParams, s: _Search) -> bool:
    """Does the logged current show throttle shape ``name`` on its own (:func:`~.current.corroborates` before
    the compass's interval is asked)? The current's fits are made once per compass."""
    if group_of(name) != "throttle_shape":
        return False
    if s.current is None:
        s.current = current_fits(data.drive)
    return corroborates(name, s.current, (-math.inf, math.inf), p.min_delta_bic) is not None


def _witnessed(
    name: str, data: CompassData, base: ModelFit, f: ModelFit, c: Comparison, p: SelectionParams, s: _Search
) -> Comparison:
    """``c`` again with the held-out test run, when the logged current witnesses throttle shape ``name``
    that the compass prefers (its delta BIC below 0, raw and generalised) but leaves short of the margin
    (:mod:`magcomp.diagnosis.current`): the current's own evidence passes the margin, it prefers ``name``
    among the throttle shapes and its value lies inside the compass's 95 % interval. The compass must still
    pass its held-out test. Otherwise ``c`` unchanged."""
    if not _current_shows(name, data, p, s):
        return c
    ci = profile_interval(data, f, name)
    s.intervals[name] = (f, ci)
    w = corroborates(name, s.current or {}, ci, p.min_delta_bic)
    if w is None:
        return c
    cw = compare(data, base, f, s.base_cv(data, base, p), replace(p, min_delta_bic=0.0), s.folds)
    if cw.significant:
        s.witnessed[name] = w
    return cw


def screen_effects(
    data: CompassData, base: ModelFit, p: SelectionParams, exclude: Mapping[str, str] | None = None
) -> _Search:
    """Every available extension on its own; the significant ones sorted by held-out gain. ``exclude``: causes
    ruled out before the search (name -> why, e.g. by a sibling compass: :mod:`magcomp.diagnosis.siblings`),
    recorded as rejected with that reason."""
    s = _Search()
    for name in EFFECTS:
        why = effect_available(name, data.drive)
        if why is not None:
            s.unavailable[name] = why
            continue
        if exclude and name in exclude:
            s.rejected[name] = {"why": exclude[name]}
            continue
        _test_single(name, data, base, p, s)
    s.singles.sort(key=lambda c: -c.cv_gain)
    return s


def group_rivals(data: CompassData, s: _Search) -> None:
    """Singles of one group the data cannot tell apart (BIC within RIVAL_DELTA_BIC) become one candidate set:
    the best stays, the others are rejected and reported with it.

    A member refused on its own only by the margin or the held-out test (``s.near``) joins the set of a
    member that passed when the two fits are within RIVAL_DELTA_BIC of each other, compared directly: the
    data do not tell it from the cause that is named, so naming that cause alone would claim a distinction
    the log does not carry (measured: a sag of 0.8 at effective delta BIC -25 beside an exponent at -56
    whose fit is 7.7 better, docs/diagnosis.md 2026-11-28 "sag"). A set needs a member that passed, so
    this adds no finding to a log that has none."""
    for group in GROUPS:
        members = {c.fit.effects[0]: c for c in s.singles if group_of(c.fit.effects[0]) == group}
        if not members:
            continue
        same, gap = rival_set({k: c.fit for k, c in members.items()}, RIVAL_DELTA_BIC)
        best = same[0]
        for k, f in s.near.items():
            if group_of(k) != group:
                continue
            g = rival_gap(f, members[best].fit)
            if not (math.isfinite(g) and g < RIVAL_DELTA_BIC):
                continue
            ci = profile_interval(data, f, k)
            if not_identified(k, data, f, ci) is None and within_compass_age(k, data, ci) is None:
                s.intervals[k] = (f, ci)
                same.append(k)
                gap[k] = g
        if len(same) < 2:
            continue
        s.candidates[best] = same
        fits = {k: members[k].fit if k in members else s.near[k] for k in same}
        s.candidate_params[best] = {
            k: params_json(fits[k], k, data, s.interval(k, fits[k])) | {"delta_bic_vs_best": r4(gap[k])}
            for k in same
        }
        for k in same[1:]:
            why = f"cannot be told from {best} (BIC within {RIVAL_DELTA_BIC:.0f}): reported as a set"
            if k not in members:
                s.rejected[k]["why"] = f"{s.rejected[k]['why']}; {why}"
                continue
            s.singles.remove(members[k])
            s.rejected[k] = {
                "delta_bic": r4(members[k].delta_bic),
                "cv_gain_pct": r4(100 * members[k].cv_gain),
                "why": why,
            }


def combine(data: CompassData, base: ModelFit, p: SelectionParams, s: _Search) -> Combined:
    """Greedy combination: each single, best first, joins when it still wins against what is kept."""
    current, cv_current = base, s.cv_base
    kept: list[tuple[str, Comparison]] = []
    for c in s.singles:
        name = c.fit.effects[0]
        if not kept:
            current, cv_current = c.fit, c.cv_extended
            kept.append((name, c))
            continue
        param = EFFECTS[name].param
        init = {name: float(getattr(c.fit.ext, param))} if param is not None else None
        trial = fit_model(data, (*current.effects, name), start=current, init=init, max_nfev=p.max_nfev)
        cv_ref = cv_current or partial(cv_score, data, current, p, s.folds)
        ct = compare(data, current, trial, cv_ref, p, s.folds)  # the current testified to this shape alone
        if ct.significant:
            current, cv_current = trial, ct.cv_extended
            kept.append((name, ct))
        else:
            s.rejected[name] = {
                "delta_bic": r4(ct.delta_bic),
                "cv_gain_pct": r4(100 * ct.cv_gain),
                "why": f"explained by {', '.join(current.effects)}",
            }
    return Combined(current, cv_current, kept)


def reduced_fit(data: CompassData, current: ModelFit, name: str, max_nfev: int) -> ModelFit:
    """``current`` refitted without the extension ``name`` (warm-started from ``current``). The start must not
    list ``name``: :func:`fit_model` carries every nonlinear value of its start's effects over and holds the
    ones it does not fit fixed (what a profile needs), so a start that still lists a nonlinear ``name`` would
    keep it, at its fitted value, in the model meant to be without it."""
    others = tuple(e for e in current.effects if e != name)
    return fit_model(data, others, start=replace(current, effects=others), max_nfev=max_nfev)


def keep_repeatable(
    data: CompassData, base: ModelFit, comb: Combined, p: SelectionParams, s: _Search
) -> tuple[Combined, list[dict[str, Any]]]:
    """Each kept cause must hold on each half of the log (:func:`repeat_in_halves`); one that does not is no
    finding: it is removed from the model and reported as unexplained structure that does not repeat."""
    if not comb.kept:
        return comb, []
    current = comb.fit
    kept = list(comb.kept)
    demoted: list[dict[str, Any]] = []
    for name, c in list(comb.kept):
        others = tuple(e for e in current.effects if e != name)
        reduced = base if not others else reduced_fit(data, current, name, p.max_nfev)
        rep = repeat_in_halves(data, reduced, current, name, p)
        if rep.repeats:
            continue
        explained = reduced.residual_mgauss - current.residual_mgauss
        param = EFFECTS[name].param
        each = "" if rep.halves is None else f"{param} {rep.halves[0]:.3g} vs {rep.halves[1]:.3g}; "
        halves = (
            f"{each}one value for both halves costs chi-square {rep.statistic:.1f} on {rep.dof} dof "
            f"> {rep.critical:.1f}, {100 * rep.share:.0f} % of what it explains"
        )
        s.rejected[name] = {
            "delta_bic": r4(c.delta_bic),
            "cv_gain_pct": r4(100 * c.cv_gain),
            "halves_chi2": r4(rep.statistic),
            "why": f"does not repeat: the two halves of the log want different values ({halves})",
        }
        demoted.append(
            {
                "kind": f"unexplained, not repeatable (looked like {name})",
                "size_mgauss": [round(float(v), 2) for v in np.sqrt(np.mean(explained**2, axis=0))],
                "rms_reduction_pct": round(100.0 * (1.0 - current.rms_mgauss / reduced.rms_mgauss), 2),
                "effect": name,
                "params": params_json(current, name, data, s.interval(name, current)),
                "halves_chi2": r4(rep.statistic),
                "note": f"{name} fits the whole log but not each half ({halves}): a structure of one stretch "
                "of the log, not a constant cause; not named as a finding",
            }
        )
        kept = [(k, ck) for k, ck in kept if k != name]
        current = reduced
    if not demoted:
        return comb, []
    return Combined(current, None, kept), demoted


def open_step(
    data: CompassData,
    base: ModelFit,
    comb: Combined,
    p: SelectionParams,
    s: _Search,
    log: LogData | None,
    events: Events | None,
) -> StepCandidate | None:
    """A step of the field the named causes were soaking up, or one in what they leave, or None."""
    sig0 = signals_at(data, log)
    # a step on its own (against the paper's model) that fits better than every named cause on its own:
    # the named ones were soaking it up
    folds = s.folds or folds_for(data, base, p)
    cv_base = s.cv_base or (lambda: cv_score(data, base, p, folds))  # held-out scores only when a step passes
    st = step_candidate(data, base, p, cv_base, sig0, events, folds)
    best_named = min((c.fit.bic for c in s.singles), default=math.inf)
    if st is None or st.fit.bic >= best_named:
        # or a step in what the named causes leave
        cv_comb = comb.cv or (lambda: cv_score(data, comb.fit, p, folds))
        st = step_candidate(data, comb.fit, p, cv_comb, sig0, events, folds)
    return st


def _witness_json(w: CurrentFit, fits: dict[str, CurrentFit] | None) -> dict[str, Any]:
    """The current's testimony for a cause the compass alone left short of the margin."""
    return {
        "witnessed_by_current": {
            "value": r4(w.value),
            "delta_bic": r4(w.delta_bic),
            "delta_bic_per_shape": {k: r4(v.delta_bic) for k, v in (fits or {}).items()},
            "note": "the compass's evidence is short of the margin; the logged battery current shows the "
            "same load shape on its own, with its value inside the compass's 95 % interval",
        }
    }


def _findings(data: CompassData, comb: Combined, s: _Search, margin: float) -> list[Finding]:
    """The kept causes as findings; the current's testimony is attached where the compass's own evidence
    kept for a cause is short of the BIC ``margin`` (the one case it named the cause)."""
    return [
        Finding(
            name,
            EFFECTS[name].cause,
            params_json(comb.fit, name, data, s.interval(name, comb.fit)),
            evidence_json(c, data)
            | ({"delta_bic_vs_time_shapes": s.temp_vs_time[name]} if name in s.temp_vs_time else {})
            | (_witness_json(s.witnessed[name], s.current)
               if name in s.witnessed and c.delta_bic > -margin else {}),
            c.fit.rms_mgauss,
            s.candidates.get(name, []),
            s.candidate_params.get(name, {}),
        )
        for name, c in comb.kept
    ]


def _result(
    bl: Baseline,
    comb: Combined,
    s: _Search,
    source: str,
    log: LogData | None,
    events: Events | None,
    opened: list[dict[str, Any]] | None,
    margin: float,
) -> CompassDiagnosis:
    """The complete diagnosis of one compass from the search's outcome (``margin``: the BIC margin)."""
    data, extended = bl.data, comb.fit
    findings = _findings(data, comb, s, margin)
    sig = signals_at(data, log)
    suspects = relate(data.t_s, extended.residual_mgauss, sig)
    step = find_step(data.t_s, extended.residual_mgauss, sig, events)
    field_step = motors_off_step(data, extended, sig, events)
    structure = list(opened or []) + structure_search(
        data.t_s, extended.residual_mgauss, data.r_nb, sig, suspects, events
    )
    ap = autopilot_export(data.mag_index, data, extended, log)
    return CompassDiagnosis(
        data.mag_index,
        source,
        data,
        bl.fit,
        extended,
        findings,
        s.rejected,
        s.unavailable,
        suspects,
        step,
        autopilot=ap.params,
        linear_note=ap.note,
        excluded=bl.excluded,
        field_step=field_step,
        structure=structure,
    )


def diagnose_compass(
    data: CompassData,
    source: str,
    p: SelectionParams | None = None,
    log: LogData | None = None,
    events: Events | None = None,
    open_search: bool = True,
    opened: list[dict[str, Any]] | None = None,
    exclude: Mapping[str, str] | None = None,
) -> CompassDiagnosis:
    """Baseline, every available extension, greedy combination; suspects on the final residual.

    open_search: after the selection, look for a step of the field in the residual; when one passes, it
    joins the nuisance model and the selection is run again, so a named cause that only soaked up the
    step is dropped (named causes get the first shot, so a fast warm-up is not mistaken for a step).
    exclude: causes ruled out before the search (:func:`screen_effects`).
    """
    p = p or SelectionParams()
    bl = fit_baseline(data, p)
    s = screen_effects(bl.data, bl.fit, p, exclude)
    group_rivals(bl.data, s)
    comb = combine(bl.data, bl.fit, p, s)
    comb, demoted = keep_repeatable(bl.data, bl.fit, comb, p, s)
    if open_search:
        st = open_step(bl.data, bl.fit, comb, p, s, log, events)
        if st is not None:
            return diagnose_compass(
                st.data, source, p, log, events, open_search=False, opened=[st.info], exclude=exclude
            )
    return _result(bl, comb, s, source, log, events, [*(opened or []), *demoted], p.min_delta_bic)


def step_gain(data: CompassData, base: ModelFit) -> F64:
    """RSS reduction (summed over axes) of adding a step after sample k (k = 1..n-1) to ``base``'s linear
    model, its nonlinear parameters held: the profile likelihood of the step time.

    Not the mean shift of the residual: the baseline fit has already absorbed part of the step into theta
    (when the throttle changes near the switch), the hard iron and the calibration, so the residual's own
    change point is pulled toward the throttle change (measured: 0.4-0.8 s on the paper runs with the
    payload 2-5 s after the motors start). With X the baseline design and r its residual (r orthogonal to X),
    the step column s_k projected off X gives gain_k = |s_k' r|^2 / (|s_k|^2 - q_k' (X'X)^-1 q_k) with
    q_k = X' s_k: suffix sums, so every k costs O(columns^2)."""
    x, _ = design(data, base.inc_rad, base.dec_rad, base.drift_rad_s, base.ext)
    r = base.residual_mgauss
    n = data.n
    # suffix sums over i >= k, k = 1..n-1
    sr = np.cumsum(r[::-1], axis=0)[::-1][1:]  # (n-1, 3)
    q = np.cumsum(x[::-1], axis=0)[::-1][1:]  # (n-1, p)
    g = np.linalg.pinv(x.T @ x)
    denom = (n - np.arange(1, n)) - np.einsum("kp,pq,kq->k", q, g, q)
    denom = np.maximum(denom, 1e-9 * n)
    return np.asarray(np.sum(sr**2, axis=1) / denom)


def step_candidate(
    data: CompassData,
    base: ModelFit,
    p: SelectionParams,
    cv_base: CVScore | Callable[[], CVScore],
    sig: Signals,
    events: Events | None,
    folds: Folds | None = None,
) -> StepCandidate | None:
    """The best single step of the field (change point of the baseline residual's mean, least squares), as a
    model column; kept when it passes the extensions' own tests (held-out gain, BIC with one more
    ln(3n) for the searched time). Returns the data with the column, the refit and the report entry."""
    n = data.n
    if n < 100:
        return None
    gain = step_gain(data, base)
    lo, hi = int(0.05 * n), int(0.95 * n)  # a step at the very ends is the calibration's business
    i = lo + int(np.argmax(gain[lo:hi]))
    t_step = float(0.5 * (data.t_s[i] + data.t_s[i + 1]))
    col = (data.t_s >= t_step).astype(float)[:, None]
    d = data.drive
    drive = replace(d, extra=col, extra_names=("step",))
    data_s = replace(data, drive=drive)
    fs = fit_model(data_s, base.effects, start=base, max_nfev=p.max_nfev)
    extra_penalty = math.log(3 * n)
    in_sample = 1.0 - fs.rms_mgauss / base.rms_mgauss
    # the in-sample tests first: a step that fails them is not kept whatever it gains held out, so the
    # held-out refits are run only for one that passes (compare's effective BIC is the same number)
    if not (
        in_sample >= p.min_cv_gain
        and effective_delta_bic(base, fs) <= -p.min_delta_bic_structure - extra_penalty
    ):
        return None
    cmp = compare(data_s, base, fs, cv_base, p, folds, gls=False)
    if not (
        cmp.cv_gain >= p.min_cv_gain
        and in_sample >= p.min_cv_gain
        and cmp.delta_bic <= -p.min_delta_bic_structure - extra_penalty
    ):
        return None
    # a slow drift (temperature, a settling hard iron) is not a step: the step must beat every smooth time
    # column with as many parameters, by the same margin
    for shape in time_shapes(data.t_s).values():
        smooth = replace(data, drive=replace(d, extra=shape[:, None], extra_names=("step",)))
        fsm = fit_model(smooth, base.effects, start=base, max_nfev=p.max_nfev)
        if effective_delta_bic(fsm, fs) > -RIVAL_DELTA_BIC:
            return None
    size = fs.coefs[list(fs.columns).index("step")]
    co: dict[str, float] = {}
    for name, (ts, vs) in sig.items():
        before = (ts >= t_step - 2.0) & (ts < t_step)
        after = (ts >= t_step) & (ts < t_step + 2.0)
        sd = float(np.std(vs))
        if np.count_nonzero(before) >= 2 and np.count_nonzero(after) >= 2 and sd > 0:
            co[name] = round(float(np.mean(vs[after]) - np.mean(vs[before])) / sd, 3)
    co = dict(sorted(co.items(), key=lambda kv: -abs(kv[1]))[:5])
    info = {
        "kind": "step",
        "t_s": round(t_step, 2),
        "size_mgauss": [round(float(v), 2) for v in size],
        "rms_reduction_pct": round(100.0 * (1.0 - fs.rms_mgauss / base.rms_mgauss), 2),
        "cv_gain_pct": round(100.0 * cmp.cv_gain, 2),
        "delta_bic": round(cmp.delta_bic, 1),
        "co_stepping_signals": co,
        "events": [{"t_s": round(te, 2), "event": e} for te, e in (events or []) if abs(te - t_step) <= 2.0],
        "note": "a step of the field that no named cause explains (a payload, servo or light switched on?); "
        "kept in the model as a nuisance so the named causes are tested on what is left",
    }
    return StepCandidate(data_s, fs, info)


def motors_off_step(
    data: CompassData, fit: ModelFit, sig: dict[str, tuple[F64, F64]], events: list[tuple[float, str]] | None
) -> dict[str, Any] | None:
    """The largest step of the *measured* field while the motors are off, and what explains it.

    With the throttle at zero eq. (11) predicts no bias change, so a step there is either a rotation
    (which the forward model predicts from the gyro), or something outside the powertrain. Reported: its
    time and size, the step the model predicts and the step left in the residual at that time, the
    signals that step with it and the logged events nearby.
    """
    thr = data.throttle_01
    off = thr < 0.02
    if np.count_nonzero(off) < 40:
        return None
    st = find_step(data.t_s[off], data.field_mgauss[off], sig, events)
    if st is None:
        return None
    predicted = data.field_mgauss - fit.residual_mgauss
    pred = step_at(data.t_s, predicted, st.t_s)
    res = step_at(data.t_s, fit.residual_mgauss, st.t_s)
    explained = None
    if pred is not None and res is not None:
        size = float(np.linalg.norm(st.size_mgauss))
        explained = round(1.0 - float(np.linalg.norm(res)) / size, 3) if size > 0 else None
    return {
        "t_s": r4(st.t_s),
        "size_mgauss": r4(np.array(st.size_mgauss)),
        "size_sigma": r4(st.size_sigma),
        "predicted_step_mgauss": None if pred is None else r4(pred),
        "residual_step_mgauss": None if res is None else r4(res),
        "fraction_explained_by_model": explained,
        "co_stepping_signals": dict(list(st.co_stepping.items())[:8]),
        "events": [{"t_s": r4(t), "event": e} for t, e in st.events],
    }
