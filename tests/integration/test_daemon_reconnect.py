"""Link loss: the flight controller's TCP link drops in the middle of a flight and comes back; the
daemon logs it, keeps its calibration and theta, and headings flow again. Silence is logged once."""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import pytest

from magcomp.core.types import HeadingEstimate
from magcomp.service.daemon import Daemon
from tests.configs import QUICK_CALIBRATION


@pytest.mark.slow
def test_tcp_link_loss_reconnects_and_keeps_state(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, split_tlog: Callable[[bytes], list[bytes]]
) -> None:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="paper", duration_s=34.0, seed=4, n_compasses=1))
    write_tlog(result, tmp_path / "f.tlog")
    pkts = [r[8:] for r in split_tlog((tmp_path / "f.tlog").read_bytes())]
    half = len(pkts) // 2
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))
    server.listen(2)
    port = server.getsockname()[1]

    def flight_controller() -> None:
        try:
            for part in (pkts[:half], pkts[half:]):
                conn, _ = server.accept()
                for i in range(0, len(part), 40):
                    conn.sendall(b"".join(part[i : i + 40]))
                    time.sleep(0.004)
                # silence until the daemon has noticed it (a condition, bounded), then the link drops
                t_quiet = time.monotonic()
                while not daemon._silent and time.monotonic() - t_quiet < 30.0:
                    time.sleep(0.02)
                conn.close()
        finally:
            server.close()

    fc = threading.Thread(target=flight_controller)
    fc.start()
    c = replace(QUICK_CALIBRATION, link=replace(QUICK_CALIBRATION.link, silence_s=0.4, reconnect_s=0.2))
    ests: list[HeadingEstimate] = []
    daemon = Daemon(f"tcp:127.0.0.1:{port}", c, on_estimate=ests.append)
    with caplog.at_level(logging.INFO, logger="magcomp"):
        worker = threading.Thread(target=daemon.run)
        worker.start()
        fc.join(timeout=60)
        t0 = time.monotonic()
        while len(ests) < result.samples.t_s.shape[0] and time.monotonic() - t0 < 30:
            time.sleep(0.05)
        daemon.stop()
        worker.join(timeout=15)
    assert not worker.is_alive()
    n = result.samples.t_s.shape[0]
    assert len(ests) >= 0.98 * n, (len(ests), n)  # both halves came through
    t = [e.t_s for e in ests]
    assert t == sorted(t)
    # calibration learned in the first half was kept across the reconnect
    second = [e for e in ests if e.t_s > result.samples.t_s[half // 2 + 50]]
    assert second and all(e.flags & 1 for e in second[-100:])
    text = caplog.text
    assert "no data from" in text
    assert "link reset" in text or "link lost" in text
    assert daemon.link_losses >= 1
