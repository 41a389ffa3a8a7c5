"""Synthetic vehicle: scenarios, powertrain with hidden effects, sensors and a simulated autopilot.

Public API: ``simulate(SimConfig(...), rng) -> SimResult``; the MAVLink/tlog/live-link output is in
:mod:`magcomp.adapters.mavlink_emit` (``write_tlog``, ``stream_to_link``, ``write_truth``).
"""

from magcomp.sim.config import EFFECTS, SCENARIO_ALIASES, SCENARIOS, Location, Rates, SimConfig, parse_effect
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
    "parse_effect",
    "simulate",
]
