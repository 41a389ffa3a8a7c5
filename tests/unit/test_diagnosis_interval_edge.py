"""A significant delay or shape parameter whose 95 % interval reaches the end of its physical range is not
named (magcomp/diagnosis/search.py, interval_at_edge); an identified one near the ceiling still is. Seeded.

Oracle: the synthetic log's own hidden lag (throttle steps every 4 s identify it) and the rule's definition.
"""

from __future__ import annotations

import pytest

from magcomp.diagnosis import search
from magcomp.diagnosis.engine import compass_data, diagnose_compass
from tests.unit.test_diagnosis_model import synth_log


def test_identified_slow_lag_is_still_named_with_its_interval_inside() -> None:
    """An 8 s lag (ceiling 10 s) on a log whose throttle steps every 4 s: named, interval inside the range."""
    log, _, _ = synth_log(3, effects={"current_lag": 8.0})
    cd = diagnose_compass(compass_data(log, 0), "synthetic", log=log)
    assert cd.findings and cd.findings[0].effect == "current_lag"
    lo, hi = cd.findings[0].params["tau_s_ci95"]
    assert lo <= 8.0 <= hi + 0.3, (lo, hi)
    assert hi < 10.0 - 0.5, hi


@pytest.mark.parametrize(
    ("effect", "ci", "rejected"),
    [
        ("current_lag", (5.6, 10.0), True),  # reaches the 10 s ceiling: a slow drift, not a lag
        ("current_lag", (0.0, 0.3), False),  # a lower end of 0 is "off": the BIC judges that
        ("current_lag", (5.9, 6.3), False),
        ("time_skew", (-3.0, -2.4), True),  # the -3 s end of the skew range
        ("throttle_exponent", (4.2, 5.0), True),
        ("throttle_exponent", (0.5, 1.2), True),  # 0.5 is a physical end, not "off"
    ],
)
def test_interval_at_the_end_of_the_range(
    monkeypatch: pytest.MonkeyPatch, effect: str, ci: tuple[float, float], rejected: bool
) -> None:
    monkeypatch.setattr(search, "profile_interval", lambda data, fit, name: ci)
    why = search.interval_at_edge(effect, None, None)  # type: ignore[arg-type]
    assert (why is not None) == rejected, why
    if rejected:
        assert "reaches the end of its range" in str(why)
