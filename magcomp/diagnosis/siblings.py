"""What the compasses of one log must agree on: one clock.

``time_skew`` names a delay between the logged throttle and the field: the throttle and the compass are
stamped by different clocks or transport paths (:mod:`magcomp.diagnosis.effects`). Every compass of one log
is stamped by the autopilot's one clock (DataFlash ``TimeUS``, ULog timestamps) or by the ground station's
receipt of one link (a tlog), and its throttle is the same signal for all of them, so a clock or transport
skew is one number per log: buses and drivers differ by milliseconds, not tenths of a second. Two compasses
of one log whose named skews have disjoint 95 % intervals cannot both be describing that delay: at most one
of them is, and the one with the weaker evidence is refused (the other keeps it), with the reason. A set of
rivals that holds a skew (the data cannot tell it from a current lag) is held to the same rule: refused, the
skew leaves the set, and what is left is named only where it stands on its own.

Seen on log171 (ArduCopter 3.3, DataFlash; docs/diagnosis.md, 2026-11-28): compass 0 named a skew of
0.337 s [0.311, 0.371] (effective delta BIC -37, residual 8.83 -> 8.76 mgauss) while compass 2 of the same
log named 0.040 s [0.028, 0.052] (delta BIC -821).
"""

from __future__ import annotations

from dataclasses import dataclass

from magcomp.diagnosis.results import CompassDiagnosis


@dataclass(frozen=True)
class _Skew:
    index: int
    skew_s: float
    ci95: tuple[float, float]
    delta_bic: float


def _named_skews(comps: list[CompassDiagnosis]) -> list[_Skew]:
    out = []
    for c in comps:
        if not c.observable:
            continue
        for f in c.findings:
            # a set of rivals ("time_skew or current_lag") names the skew as one of its explanations: that
            # member is held to the one clock too (log171 compass 0's 0.337 s came back that way)
            rivals = len(f.candidates) > 1
            if "time_skew" not in (f.candidates if rivals else [f.effect]):
                continue
            params = f.candidate_params.get("time_skew", {}) if rivals else f.params
            ci = params.get("skew_s_ci95")
            if ci is None or "skew_s" not in params:
                continue
            # the skew's own evidence: a set's is its best member's, the skew's behind it by its delta
            dbic = float(f.evidence.get("delta_bic", 0.0)) + float(params.get("delta_bic_vs_best", 0.0))
            out.append(_Skew(c.index, float(params["skew_s"]), (float(ci[0]), float(ci[1])), dbic))
    return out


def clock_conflicts(comps: list[CompassDiagnosis]) -> dict[int, str]:
    """Compass index -> why its time_skew is refused: a sibling compass of the same log names a skew whose
    95 % interval does not overlap this one's, with stronger evidence (a more negative delta BIC)."""
    skews = _named_skews(comps)
    out: dict[int, str] = {}
    for a in skews:
        for b in skews:
            if a.index == b.index or b.delta_bic >= a.delta_bic:
                continue  # only a stronger sibling refuses
            if a.ci95[1] < b.ci95[0] or b.ci95[1] < a.ci95[0]:
                out[a.index] = (
                    f"compass {b.index} of the same log puts the throttle-to-field skew at {b.skew_s:.3f} s "
                    f"[{b.ci95[0]:.3f}, {b.ci95[1]:.3f}] with stronger evidence (delta BIC {b.delta_bic:.0f} "
                    f"against {a.delta_bic:.0f}), outside this compass's {a.skew_s:.3f} s "
                    f"[{a.ci95[0]:.3f}, {a.ci95[1]:.3f}]: one log's compasses share one clock, so this skew "
                    "is not the delay it names"
                )
                break
    return out
