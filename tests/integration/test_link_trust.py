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
from tests.configs import QUICK_CALIBRATION
from tests.faultgen import rewrite
from tests.waiting import running_daemon, send_paced, wait_for


def _cfg() -> Config:
    return replace(QUICK_CALIBRATION, link=replace(QUICK_CALIBRATION.link, heartbeat_hz=20.0))


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
    forger = Forger(port, forged)
    started = threading.Event()

    def fc_stop() -> bool:  # the forger joins once the flight controller's data flows
        if not started.is_set() and len(ests) > 50:
            started.set()
            forger.thread.start()
        return False

    try:
        with running_daemon(daemon):
            try:
                stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=10.0, stop=fc_stop)
                wait_for(lambda: len(ests) >= len(clean), 60.0, "every heading")
            finally:
                forger.stop.set()
    finally:
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


#: the child that serves: Rerun's servers leave native threads behind in the process that opened them (a
#: later fork, the observers' child process, would copy them mid-lock), so they live in a child process
_SERVE_CHILD = """
import sys
from magcomp.adapters.rerun_viz import open_viz
viz = open_viz(sys.argv[1], live=False, recording_name="trust", grpc_port=int(sys.argv[2]),
               web_port=int(sys.argv[3]))
print(viz.url, flush=True)
sys.stdin.read()
viz.close()
"""


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux's /proc/net/tcp")
@pytest.mark.parametrize(("mode", "expected"), [("serve", {"0100007F"}), ("serve=0.0.0.0", {"00000000"})])
def test_rerun_serve_listens_on_loopback_unless_told_otherwise(mode: str, expected: set[str]) -> None:
    import subprocess
    import sys

    from magcomp.adapters.rerun_viz import free_port

    gport, wport = free_port(), free_port()
    repo = Path(__file__).parents[2]
    proc = subprocess.Popen([sys.executable, "-c", _SERVE_CHILD, mode, str(gport), str(wport)], cwd=repo,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert proc.stdin is not None and proc.stdout is not None
    try:
        url = proc.stdout.readline()
        assert "127.0.0.1" in url, url
        wait_for(lambda: bool(_listening_addresses(gport)), 30.0, "the recording's server to listen")
        assert _listening_addresses(gport) == expected
    finally:
        proc.stdin.close()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()


def _signed(packets: list[bytes], key: bytes) -> list[bytes]:
    """The packets re-packed by pymavlink with MAVLink 2 signing (same sender, sequence and fields)."""
    from magcomp.adapters.dialect import ensure_dialect
    from magcomp.adapters.signing import signing_timestamp

    mod = ensure_dialect()
    parser = mod.MAVLink(None)
    signers: dict[tuple[int, int], object] = {}
    out = []
    for pkt in packets:
        msg = parser.decode(bytearray(pkt))
        key_id = (msg.get_srcSystem(), msg.get_srcComponent())
        signer = signers.get(key_id)
        if signer is None:
            signer = mod.MAVLink(None, srcSystem=key_id[0], srcComponent=key_id[1])
            signer.signing.secret_key, signer.signing.sign_outgoing = key, True  # type: ignore[attr-defined]
            signer.signing.link_id, signer.signing.timestamp = 1, signing_timestamp()  # type: ignore[attr-defined]
            signers[key_id] = signer
        signer.seq = msg.get_seq()  # type: ignore[attr-defined]
        out.append(bytes(msg.pack(signer)))
    return out


@pytest.mark.slow
def test_a_signed_link_interoperates_with_pymavlink_signing_and_refuses_unsigned_frames(
    tmp_path: Path, split_tlog: Callable[[bytes], list[bytes]]
) -> None:
    from magcomp.adapters.dialect import ensure_dialect
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.adapters.signing import read_signing_key, require_signed
    from magcomp.sim import SimConfig, simulate

    key_file = tmp_path / "key"
    key_file.write_text("correct horse battery staple\n")  # a passphrase: its SHA-256 is the key
    key = read_signing_key(key_file)
    path = tmp_path / "flight.tlog"
    write_tlog(simulate(SimConfig(scenario="paper", duration_s=30.0, seed=3, n_compasses=1)), path)
    clean = replay_log(path, _cfg(), keep_estimates=True).estimates
    plain = [r[8:] for r in split_tlog(path.read_bytes())]
    signed = _signed(plain, key)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.05)
    got: list[bytes] = []
    stop = threading.Event()

    def receive() -> None:
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                got.append(rx.recv(65536))

    rx_thread = threading.Thread(target=receive)
    rx_thread.start()
    port = free_udp_port()
    ests: list[HeadingEstimate] = []
    daemon = Daemon(f"udpin:127.0.0.1:{port}", _cfg(), outs=[f"udpout:127.0.0.1:{rx.getsockname()[1]}"],
                    on_estimate=ests.append, signing_key=key)  # fmt: skip
    try:
        with running_daemon(daemon):
            # each frame signed, then the same frame unsigned, from the same socket
            both = [pkt for pair in zip(signed, plain, strict=True) for pkt in pair]
            send_paced(both, port, every=40, pause_s=0.003)
            wait_for(lambda: len(ests) >= len(clean), 60.0, "every heading")
            wait_for(lambda: len(got) > 0, 30.0, "a heading on the --out link")
    finally:
        stop.set()
        rx_thread.join()
        rx.close()
    # the signed frames gave exactly the clean run; every unsigned copy was refused
    assert [_key(e) for e in ests] == [_key(e) for e in clean]
    assert daemon.report().source_counts.get("bad_signature", 0) >= 0.9 * len(plain)
    # what magcomp sent is signed: pymavlink's own check accepts it with the key, refuses it without
    mod = ensure_dialect()
    good, wrong = mod.MAVLink(None), mod.MAVLink(None)
    good.robust_parsing = wrong.robust_parsing = True
    require_signed(good, key)
    require_signed(wrong, bytes(32))
    headings = [m for d in got for m in good.parse_buffer(d) or [] if m.get_type() == "MAGCOMP_HEADING"]
    assert len(headings) > 0 and good.signing.goodsig_count > 0 and good.signing.badsig_count == 0
    refused = [m for d in got for m in wrong.parse_buffer(d) or [] if m.get_type() == "MAGCOMP_HEADING"]
    assert refused == [] and wrong.signing.badsig_count > 0


def test_signing_key_files(tmp_path: Path) -> None:
    import hashlib

    from magcomp.adapters.signing import read_signing_key
    from magcomp.errors import InputError

    raw, hexed, phrase = tmp_path / "raw", tmp_path / "hex", tmp_path / "phrase"
    raw.write_bytes(bytes(range(32)))
    hexed.write_text(bytes(range(32)).hex() + "\n")
    phrase.write_text("my key\n")
    assert read_signing_key(raw) == read_signing_key(hexed) == bytes(range(32))
    assert read_signing_key(phrase) == hashlib.sha256(b"my key").digest()
    with pytest.raises(InputError, match="cannot read"):
        read_signing_key(tmp_path / "missing")
