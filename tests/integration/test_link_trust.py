"""Issue 25 (2): the trust boundary of a UDP link. The daemon follows the flight controller it locked
onto; RAW_IMU forged from another socket to the `udpin` port changes no heading, theta or state, and the
forger receives nothing (no heading, no heartbeat)."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.core.types import HeadingEstimate
from magcomp.service.daemon import Daemon
from magcomp.service.demo import free_udp_port
from magcomp.service.replay import replay_log
from tests.faultgen import rewrite
from tests.waiting import wait_for


def _cfg() -> Config:
    c = Config()
    return replace(c, calibration=replace(c.calibration, min_samples=200, check_every=100),
                   link=replace(c.link, heartbeat_hz=20.0))  # fmt: skip


def _key(e: HeadingEstimate) -> tuple[object, ...]:
    return (e.t_s, e.mag_index, e.heading_deg, e.flags, *e.theta_mgauss.tolist(), *e.bias_mgauss.tolist())


class Forger:
    """A second socket on the network: sends forged packets to the daemon's port until stopped and
    counts every byte the daemon sends back to it."""

    def __init__(self, port: int, packets: list[bytes]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.005)
        self.port, self.packets = port, packets
        self.sent = 0
        self.received = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        i = 0
        while not self.stop.is_set():
            self.sock.sendto(self.packets[i % len(self.packets)], ("127.0.0.1", self.port))
            self.sent += 1
            i += 1
            with contextlib.suppress(TimeoutError):
                self.received += len(self.sock.recv(65536))
        self.sock.close()


@pytest.mark.slow
def test_forged_vehicle_data_from_another_socket_changes_nothing(
    tmp_path: Path, split_tlog: Callable[[bytes], list[bytes]]
) -> None:
    from magcomp.adapters.mavlink_emit import stream_to_link, write_tlog
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="paper", duration_s=40.0, seed=5, n_compasses=1))
    path = tmp_path / "flight.tlog"
    write_tlog(result, path)
    clean = replay_log(path, _cfg(), keep_estimates=True).estimates
    assert np.any(clean[-1].theta_mgauss != 0.0)  # something was learned: the comparison means something
    # the forger replays the vehicle's own RAW_IMU (same system, component and clock) with a field
    # that would move theta by hundreds of mgauss
    records = split_tlog(path.read_bytes())
    forged = [r[8:] for r in rewrite(records, "RAW_IMU", xmag=900, ymag=-900, zmag=900)
              if r[8 + 7 : 8 + 10] == b"\x1b\x00\x00"]  # fmt: skip  # (message id 27: RAW_IMU)
    assert len(forged) > 100

    port = free_udp_port()
    ests: list[HeadingEstimate] = []
    daemon = Daemon(f"udpin:127.0.0.1:{port}", _cfg(), on_estimate=ests.append)
    worker = threading.Thread(target=daemon.run)
    worker.start()
    forger = Forger(port, forged)
    started = threading.Event()

    def fc_stop() -> bool:  # the forger joins once the flight controller's data flows
        if not started.is_set() and len(ests) > 50:
            started.set()
            forger.thread.start()
        return False

    try:
        wait_for(lambda: daemon.connects > 0, 60.0, "the daemon to listen")
        stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=10.0, stop=fc_stop)
        wait_for(lambda: len(ests) >= len(clean), 60.0, "every heading")
    finally:
        forger.stop.set()
        daemon.stop()
        worker.join(timeout=30)
        if forger.thread.is_alive() or started.is_set():
            forger.thread.join(timeout=10)
    assert started.is_set() and forger.sent > 100
    report = daemon.report().to_json()
    assert report["source_counts"].get("foreign_datagrams", 0) > 0
    assert len(ests) == len(clean)
    assert [_key(e) for e in ests] == [_key(e) for e in clean], "forged data reached the pipeline"
    assert forger.received == 0, "the daemon sent to a host that is not the flight controller"


def _listening_addresses(port: int) -> set[str]:
    """The local addresses (hex, as in /proc/net/tcp) of the TCP sockets listening on ``port``."""
    out = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError), open(table) as f:
            for line in f.readlines()[1:]:
                local, state = line.split()[1], line.split()[3]
                addr, _, hex_port = local.rpartition(":")
                if state == "0A" and int(hex_port, 16) == port:
                    out.add(addr)
    return out


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux's /proc/net/tcp")
@pytest.mark.parametrize(("mode", "expected"), [("serve", {"0100007F"}), ("serve=0.0.0.0", {"00000000"})])
def test_rerun_serve_listens_on_loopback_unless_told_otherwise(mode: str, expected: set[str]) -> None:
    from magcomp.adapters.rerun_viz import free_port, open_viz

    gport = free_port()
    viz = open_viz(mode, live=False, recording_name="trust", grpc_port=gport, web_port=free_port())
    try:
        wait_for(lambda: bool(_listening_addresses(gport)), 30.0, "the recording's server to listen")
        assert _listening_addresses(gport) == expected
        assert viz.url is not None and "127.0.0.1" in viz.url
    finally:
        viz.close()
