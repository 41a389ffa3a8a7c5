"""Replay equals live: the same simulated flight streamed over loopback UDP to the daemon (at two
speeds) and replayed from its tlog gives bit-identical headings, theta and flags for every sample."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcomp.core.types import HeadingEstimate
from magcomp.service.daemon import Daemon
from magcomp.service.demo import free_udp_port
from magcomp.service.replay import replay_log
from tests.configs import QUICK_CALIBRATION
from tests.waiting import running_daemon, wait_for


def live(result: object, speed: float) -> list[HeadingEstimate]:
    from magcomp.adapters.mavlink_emit import stream_to_link

    port = free_udp_port()
    ests: list[HeadingEstimate] = []
    daemon = Daemon(f"udpin:127.0.0.1:{port}", QUICK_CALIBRATION, on_estimate=ests.append)
    with running_daemon(daemon, join_s=10.0):
        stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=speed)  # type: ignore[arg-type]
        n = result.samples.t_s.shape[0] * result.samples.mag_mgauss.shape[0]  # type: ignore[attr-defined]
        wait_for(lambda: len(ests) >= n, 60.0, "every heading")  # normally < 2 s
    return ests


def key(e: HeadingEstimate) -> tuple[object, ...]:
    return (e.t_s, e.mag_index, e.heading_deg, e.heading_raw_deg, e.flags, e.throttle_01,
            *e.theta_mgauss.tolist(), *e.bias_mgauss.tolist())  # fmt: skip


@pytest.mark.slow
def test_replay_equals_live_at_two_speeds(tmp_path: Path) -> None:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="paper", duration_s=40.0, seed=5))
    path = tmp_path / "flight.tlog"
    write_tlog(result, path)
    replayed = replay_log(path, QUICK_CALIBRATION, keep_estimates=True).estimates
    n = result.samples.t_s.shape[0] * result.samples.mag_mgauss.shape[0]
    assert len(replayed) == n
    theta_last = replayed[-2].theta_mgauss
    assert np.any(theta_last != 0.0)  # the run did learn something, so the comparison means something
    for speed in (25.0, 8.0):
        got = live(result, speed)
        assert len(got) == n, f"live at {speed}x: {len(got)} of {n} estimates (UDP loss on loopback?)"
        assert [key(e) for e in got] == [key(e) for e in replayed], f"live at {speed}x differs from replay"
