"""Two vehicles on one UDP link (issue 12, item 11): one pipeline per sender, each vehicle's headings go
out as that vehicle with its own clock, nothing is dropped as "time going backwards"."""

from __future__ import annotations

import numpy as np
import pytest

from magcomp.service.daemon import Daemon
from magcomp.service.demo import free_udp_port
from tests.configs import QUICK_CALIBRATION
from tests.waiting import receiving_mavlink, running_daemon, send_paced, wait_for


@pytest.mark.slow
def test_two_vehicles_on_one_link_are_kept_apart() -> None:
    from magcomp.adapters.mavlink_emit import encode_stream
    from magcomp.sim import SimConfig, simulate

    # vehicle 2 booted 300 s before vehicle 1: two clocks far apart on one link
    sims = {1: simulate(SimConfig(scenario="paper", duration_s=40.0, seed=1, n_compasses=1)),
            2: simulate(SimConfig(scenario="paper", duration_s=40.0, seed=2, n_compasses=1, t0_s=300.0))}
    streams = {k: encode_stream(r, src_system=k) for k, r in sims.items()}
    merged = sorted(((t - streams[k][0][0], k, pkt) for k in streams for t, pkt in streams[k]),
                    key=lambda x: (x[0], x[1]))  # fmt: skip
    port = free_udp_port()
    n_mag = {k: r.samples.t_s.shape[0] for k, r in sims.items()}
    with receiving_mavlink(("MAGCOMP_HEADING",)) as (out_port, got):
        daemon = Daemon(f"udpin:127.0.0.1:{port}", QUICK_CALIBRATION, outs=[f"udpout:127.0.0.1:{out_port}"])
        with running_daemon(daemon):
            send_paced([pkt for _, _, pkt in merged], port)
            wait_for(lambda: len(got) >= sum(n_mag.values()), 60.0, "every heading")
    report = daemon.report().to_json()
    by_sys = {k: [m for m in got if m.get_srcSystem() == k] for k in sims}
    for k, r in sims.items():
        assert len(by_sys[k]) == n_mag[k]  # none dropped as time going backwards
        # each vehicle's headings carry that vehicle's own clock
        t_ms = set(np.round(r.samples.t_s * 1000).astype(int).tolist())
        assert {m.time_boot_ms for m in by_sys[k]} <= t_ms
    vehicles = {v["system_id"]: v for v in report["vehicles"]}
    assert set(vehicles) == {1, 2}
    for k, r in sims.items():
        v = vehicles[k]
        assert v["counts"]["time_backwards"] == 0 and v["counts"]["reboots"] == 0
        theta = np.asarray(v["compasses"][0]["theta_mgauss"])
        truth = np.asarray(r.compasses[0].theta_mgauss)
        assert np.linalg.norm(theta - truth) < 0.5 * np.linalg.norm(truth)
    assert report["source_counts"].get("clock_resets", 0) == 0
