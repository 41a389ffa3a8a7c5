"""Synthetic vehicle: scenarios, powertrain with hidden effects, sensors and a simulated autopilot.

Public API: ``simulate(SimConfig(...), rng) -> SimResult``; the MAVLink/tlog/live-link output is in
:mod:`magcomp.adapters.mavlink_emit` (``write_tlog``, ``stream_to_link``, ``write_truth``). Variation knobs:
``apply_settings(config, ["KEY=VALUE", ...])``, ``sample_variation(rng)``; quick reference at the top of
:mod:`magcomp.sim.config`.
"""

from magcomp.sim.config import (
    EFFECTS,
    SCENARIO_ALIASES,
    SCENARIOS,
    Location,
    Rates,
    SimConfig,
    Variation,
    apply_settings,
    parse_effect,
    sample_variation,
)
from magcomp.sim.simulate import SimResult, SimSamples, simulate

__all__ = [
    "EFFECTS",
    "SCENARIOS",
    "SCENARIO_ALIASES",
    "Location",
    "Rates",
    "SimConfig",
    "SimResult",
    "SimSamples",
    "Variation",
    "apply_settings",
    "parse_effect",
    "sample_variation",
    "simulate",
]
