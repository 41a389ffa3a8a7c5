"""End to end over real UDP sockets on loopback: the simulator as the flight controller -> the daemon ->
MAGCOMP_HEADING decoded by the flight controller (udpin: master, sent back to the sender) and by a
second receiver on --out. (`magcomp run` as a process stopped by signals: tests/integration/test_signals.py.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.state_store import StateStore
from magcomp.core.identity import SIM_UID
from magcomp.service.daemon import Daemon
from magcomp.service.demo import free_udp_port, run_demo
from tests.configs import QUICK_CALIBRATION
from tests.waiting import receiving_mavlink, running_daemon, wait_for


@pytest.mark.slow
def test_sim_to_daemon_to_receivers_over_loopback_udp(tmp_path: Path) -> None:
    with receiving_mavlink() as (out_port, got):
        # --out is wired through the Daemon; run_demo builds the same daemon with outs=() so build one here
        from magcomp.adapters.mavlink_emit import stream_to_link
        from magcomp.sim import SimConfig, simulate

        result = simulate(SimConfig(scenario="paper", duration_s=40.0, seed=3))
        port = free_udp_port()
        ests: list[object] = []
        daemon = Daemon(f"udpin:127.0.0.1:{port}", QUICK_CALIBRATION, outs=[f"udpout:127.0.0.1:{out_port}"],
                        store=StateStore(tmp_path), on_estimate=ests.append)  # fmt: skip
        with running_daemon(daemon, join_s=10.0) as worker:
            link = stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=20.0)
            n_mag = result.samples.t_s.shape[0] * result.samples.mag_mgauss.shape[0]
            wait_for(lambda: len(ests) >= n_mag, 60.0, "every heading")
            # and every one of them through the receiver's thread before it stops (on a loaded machine it
            # can still be reading the last datagrams when the daemon has counted its last estimate)
            wait_for(lambda: sum(m.get_type() == "MAGCOMP_HEADING" for m in got) >= n_mag, 30.0,
                     "every heading at the receiver")  # fmt: skip
    assert not worker.is_alive()
    # one MAGCOMP_HEADING per magnetometer sample (both compasses), nothing lost on loopback
    assert len(ests) == n_mag
    headings = [m for m in got if m.get_type() == "MAGCOMP_HEADING"]  # type: ignore[attr-defined]
    assert len(headings) == n_mag
    # the flight controller (the udpin: sender) got them back too (it stops reading when its stream
    # ends, so the daemon's last few are not counted there)
    assert link.received.get("MAGCOMP_HEADING", 0) >= 0.5 * n_mag
    # decoded fields: the time of the magnetometer sample, both compasses, MAVLink 2, a heading in range
    t_mag_ms = set(np.round(result.samples.t_s * 1000).astype(int).tolist())
    assert {h.time_boot_ms for h in headings} <= t_mag_ms  # type: ignore[attr-defined]
    assert {h.mag_index for h in headings} == {0, 1}  # type: ignore[attr-defined]
    assert all(0.0 <= h.heading < 360.0 for h in headings)  # type: ignore[attr-defined]
    assert all(h.get_msgbuf()[0] == 0xFD for h in headings)  # type: ignore[attr-defined]
    assert all(h.get_srcSystem() == 1 for h in headings)  # type: ignore[attr-defined]
    last0 = [h for h in headings if h.mag_index == 0][-1]  # type: ignore[attr-defined]
    truth = np.array(result.compasses[0].theta_mgauss)
    # a 10 s spin: theta is rough but learned (accuracy is measured in benchmarks/accuracy.py)
    assert np.linalg.norm(np.array(last0.theta) - truth) < 0.5 * np.linalg.norm(truth)  # type: ignore[attr-defined]
    # state was written for both compasses of vehicle 1
    store = StateStore(tmp_path)
    assert store.load(1, 0, SIM_UID) is not None and store.load(1, 1, SIM_UID) is not None


@pytest.mark.slow
def test_demo_reduces_heading_error_against_truth(tmp_path: Path) -> None:
    report, _result, ests = run_demo(duration_s=60.0, speed=15.0, seed=1, store=StateStore(tmp_path))
    assert report.estimates == len(ests) > 0
    by_name = {s.name: s for s in report.segments}
    assert set(by_name) == {"pan", "ramp", "step"}
    for s in report.segments:
        assert s.max_corrected_deg * 3.0 < s.max_raw_deg, s
