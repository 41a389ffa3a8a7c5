"""The one-clock rule (magcomp.diagnosis.siblings) holds a set of rivals that names a time skew too.

log171 (ArduCopter 3.3): compass 0's 0.337 s skew, refused against compass 2's 0.040 s, came back as one
member of the set "time_skew or current_lag" once near-miss rivals joined a passing member's set; the rule
skipped sets. The same numbers here: the set's skew is refused, a set without one is left alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

from magcomp.diagnosis.results import CompassDiagnosis, Finding
from magcomp.diagnosis.siblings import clock_conflicts


@dataclass
class _Compass:  # the three fields the rule reads of a CompassDiagnosis
    index: int
    observable: bool
    findings: list[Finding]


def _skew(skew_s: float, ci: tuple[float, float]) -> dict[str, Any]:
    return {"skew_s": skew_s, "skew_s_ci95": list(ci)}


def test_a_set_holding_a_skew_that_a_sibling_contradicts_is_refused() -> None:
    strong = Finding("time_skew", "", _skew(0.040, (0.028, 0.052)), {"delta_bic": -821.0}, 13.1)
    lag = {"tau_s": 1.82, "tau_s_ci95": [0.17, 5.59]}
    pair = Finding("time_skew", "", _skew(0.337, (0.311, 0.371)), {"delta_bic": -37.0}, 8.76,
                   ["time_skew", "current_lag"],
                   {"time_skew": _skew(0.337, (0.311, 0.371)), "current_lag": lag})  # fmt: skip
    no_skew = Finding("current_lag", "", lag, {"delta_bic": -37.0}, 8.76, ["current_lag", "voltage_sag"],
                      {"current_lag": lag, "voltage_sag": {"sag": 0.5}})  # fmt: skip
    comps = [_Compass(0, True, [pair]), _Compass(1, True, [no_skew]), _Compass(2, True, [strong])]
    out = clock_conflicts(cast(list[CompassDiagnosis], comps))
    assert set(out) == {0}, out
    assert "share one clock" in out[0] and "0.040 s" in out[0]
