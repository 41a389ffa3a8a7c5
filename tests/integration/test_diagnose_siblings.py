"""Compasses of one log share one clock (magcomp.diagnosis.siblings).

A seeded two-compass flight with a throttle-to-field skew of 0.15 s on the log's clock: both compasses name
time_skew, with overlapping intervals. Then compass 1 is given a second delay of its own (its bias follows the
throttle 0.4 s later still, as if its field followed something else than the clock): before the rule it named
a skew of 0.55 s [0.52, 0.57] beside compass 0's 0.17 s [0.15, 0.20], two delays for one clock; now the weaker
of the two is refused with the reason and compass 1 is searched again without it.
"""

from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.adapters.mavlink_source import load_log
from magcomp.core.types import LogData, Series
from magcomp.diagnosis.engine import diagnose
from magcomp.diagnosis.gate import EarthReference
from magcomp.sim import SimConfig, simulate

SKEW_S = 0.15


@pytest.fixture(scope="module")
def flight() -> tuple[LogData, Any]:
    cfg = SimConfig(
        scenario="paper", duration_s=60.0, seed=7, effects={"time_skew": SKEW_S}, vehicle="fixedwing",
        n_compasses=2,
    )  # fmt: skip
    res = simulate(cfg)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "two.tlog"
        write_tlog(res, path)
        return load_log(path), res


def _skews(log: LogData, res: Any) -> tuple[dict[int, Any], list[str], dict[int, dict[str, Any]]]:
    dg = diagnose(log, earth=EarthReference(res.earth_field_ned_mgauss, "simulated place"))
    named = {
        c.index: next((f.params for f in c.findings if f.effect == "time_skew"), None) for c in dg.compasses
    }
    return named, dg.notes, {c.index: c.rejected for c in dg.compasses}


@pytest.mark.slow
def test_one_clock_two_compasses_agree(flight: tuple[LogData, Any]) -> None:
    named, notes, _ = _skews(*flight)
    assert named[0] is not None and named[1] is not None  # both see the log's one skew
    (a0, b0), (a1, b1) = named[0]["skew_s_ci95"], named[1]["skew_s_ci95"]
    assert a0 <= b1 and a1 <= b0  # the intervals overlap: nothing refused
    assert not any("time_skew refused" in n for n in notes)


@pytest.mark.slow
def test_a_second_delay_on_one_compass_is_not_the_clock(flight: tuple[LogData, Any]) -> None:
    log, res = flight
    thr = log.throttle_01
    mag = log.mag[1]
    theta = res.theta_logged_mgauss(1)

    def load(t: np.ndarray) -> np.ndarray:
        return np.asarray(np.interp(t, thr.t_s, thr.values) ** 2)

    # compass 1's bias follows the throttle 0.4 s later than the clock's skew: theta load(t - 0.55)
    moved = (load(mag.t_s - SKEW_S - 0.4) - load(mag.t_s - SKEW_S))[:, None] * theta[None]
    log = replace(log, mag={**log.mag, 1: Series(mag.t_s, mag.values + moved)})
    named, notes, rejected = _skews(log, res)
    assert named[0] is not None and abs(named[0]["skew_s"] - SKEW_S) < 0.05  # the stronger one stands
    assert named[1] is None  # two disjoint skews on one clock: the weaker one is refused
    assert "share one clock" in rejected[1]["time_skew"]["why"]
    assert any(n.startswith("compass 1: time_skew refused") for n in notes)
