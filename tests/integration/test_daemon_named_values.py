"""Live loopback: the simulator as the flight controller -> the daemon -> a listener on --out that knows only
the common MAVLink dialect (as Mission Planner or Cockpit without magcomp's) sees the documented
NAMED_VALUE_FLOAT names for every compass, decimated, carrying the daemon's corrected heading."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from magcomp.adapters.state_store import StateStore
from magcomp.core.types import HeadingEstimate, PowerSample
from magcomp.service.daemon import Daemon
from magcomp.service.demo import free_udp_port
from magcomp.service.publish import named_value_names
from tests.configs import QUICK_CALIBRATION
from tests.waiting import receiving_mavlink, running_daemon, wait_for


@pytest.mark.slow
def test_named_value_float_listener_sees_the_documented_names(tmp_path: Path) -> None:
    from pymavlink.dialects.v20 import common

    from magcomp.adapters.mavlink_emit import stream_to_link
    from magcomp.sim import SimConfig, simulate

    mav = common.MAVLink(None)
    mav.robust_parsing = True  # MAGCOMP_HEADING is unknown to this dialect: skipped as bad data
    result = simulate(SimConfig(scenario="paper", duration_s=30.0, seed=3))
    n_mag = result.samples.t_s.shape[0] * result.samples.mag_mgauss.shape[0]
    port = free_udp_port()
    ests: list[HeadingEstimate] = []
    powers: list[PowerSample] = []
    with receiving_mavlink(("NAMED_VALUE_FLOAT",), mav) as (out_port, got):
        daemon = Daemon(f"udpin:127.0.0.1:{port}", QUICK_CALIBRATION, outs=[f"udpout:127.0.0.1:{out_port}"],
                        store=StateStore(tmp_path), on_estimate=ests.append,
                        on_power=powers.append)  # fmt: skip
        with running_daemon(daemon):
            link = stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=20.0)
            wait_for(lambda: len(ests) >= n_mag, 60.0, "every estimate")
            last_ms = round(ests[-1].t_boot_s * 1000)
            wait_for(lambda: any(m.time_boot_ms >= last_ms - 600 for m in list(got)), 60.0, "the last values")
    # the battery samples reach the viewer's hook (run's current and voltage plots)
    assert len(powers) > 10 and all(8.0 < p.voltage_v < 30.0 for p in powers if p.voltage_v == p.voltage_v)
    # the daemon asked the flight controller for its unique id (AUTOPILOT_VERSION: the key of its state)
    assert link.received.get("COMMAND_LONG", 0) >= 1
    names = {m.name for m in got}
    assert names == {*named_value_names(0), *named_value_names(1)}
    # decimated to 2 Hz per compass on message time, not one per sample (~100 Hz)
    span_s = ests[-1].t_s - ests[0].t_s
    per_name = {n: [m for m in got if m.name == n] for n in names}
    for n, msgs in per_name.items():
        assert 1.8 * span_s <= len(msgs) <= 2.0 * span_s + 2, (n, len(msgs), span_s)
        stamps = [m.time_boot_ms for m in msgs]
        assert min(b - a for a, b in itertools.pairwise(stamps)) >= 500
    # the value is the corrected heading the daemon published for that compass at that time
    heading_at = {(e.mag_index, round(e.t_boot_s * 1000)): e.heading_deg for e in ests}
    for idx in (0, 1):
        for m in per_name[f"MC_HDG{idx}"]:
            assert m.value == pytest.approx(heading_at[(idx, m.time_boot_ms)] % 360.0, abs=1e-3)
        assert {m.value for m in per_name[f"MC_STAT{idx}"]} <= {0.0, 1.0, 2.0, 3.0}
        assert per_name[f"MC_STAT{idx}"][-1].value in (1.0, 2.0)  # compensating by the end
        assert per_name[f"MC_THETA{idx}"][-1].value > 0.0
