"""Progress only on a terminal; a failed replay leaves no empty --emit file; a live link that loses
messages (sequence-number gaps) is counted and warned about (issue 12, item 10)."""

from __future__ import annotations

import fcntl
import logging
import os
import pty
import struct
import subprocess
import sys
import termios
import threading
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.cli import main
from magcomp.service.daemon import Daemon
from magcomp.service.demo import free_udp_port
from tests.conftest import split_tlog_records
from tests.waiting import finish, running_daemon, send_paced, wait_for

REPO = Path(__file__).parents[2]


@pytest.fixture(scope="module")
def sim_tlog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    path = tmp_path_factory.mktemp("p") / "f.tlog"
    write_tlog(simulate(SimConfig(scenario="paper", duration_s=40.0, seed=2, n_compasses=1)), path)
    return path


def _replay_stderr(log: Path, tty: bool, tmp_path: Path) -> str:
    env = {k: v for k, v in os.environ.items() if k != "CI"} | {"PYTHONPATH": str(REPO), "TERM": "xterm"}
    cmd = [sys.executable, "-m", "magcomp", "replay", str(log), "--json", str(tmp_path / "s.json")]
    if not tty:
        return subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO, timeout=120).stderr
    master, slave = pty.openpty()
    # a terminal of 100 columns (a new pty has none, and tqdm then draws nothing)
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 100, 0, 0))
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=slave, env=env, cwd=REPO)
    os.close(slave)
    chunks: list[bytes] = []

    def read() -> None:
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:
                return
            if not data:
                return
            chunks.append(data)

    t = threading.Thread(target=read, daemon=True)
    t.start()
    finish(proc, 120.0)  # type: ignore[arg-type]
    t.join(timeout=10.0)
    os.close(master)
    return b"".join(chunks).decode(errors="replace")


def test_progress_on_a_terminal_only(sim_tlog: Path, tmp_path: Path) -> None:
    assert "s of log" in _replay_stderr(sim_tlog, True, tmp_path)
    piped = _replay_stderr(sim_tlog, False, tmp_path)
    assert "s of log" not in piped and "\r" not in piped
    assert "s of log" not in (tmp_path / "s.json").read_text()


def test_failed_replay_leaves_no_empty_emit_file(tmp_path: Path) -> None:
    bad = tmp_path / "noise.tlog"
    bad.write_bytes(bytes(np.random.default_rng(3).integers(0, 250, 5000, dtype=np.uint8)))
    out = tmp_path / "out.tlog"
    assert main(["replay", str(bad), "--emit", str(out)]) != 0
    assert not out.exists()


def test_lost_messages_on_a_live_link_are_counted_and_warned(
    sim_tlog: Path, caplog: pytest.LogCaptureFixture
) -> None:
    packets = [r[8:] for r in split_tlog_records(sim_tlog.read_bytes())]
    kept = [p for i, p in enumerate(packets) if i % 5 != 3]  # 20 % lost on the way
    port = free_udp_port()
    daemon = Daemon(f"udpin:127.0.0.1:{port}", Config())
    with caplog.at_level(logging.WARNING, logger="magcomp"), running_daemon(daemon):
        send_paced(kept, port)
        wait_for(lambda: "lost" in caplog.text, 60.0, "the loss warning")
    report = daemon.report().to_json()
    lost = report["source_counts"]["lost_messages"]
    got = report["source_counts"]["link_messages"]
    assert 0.15 < lost / (lost + got) < 0.25
    assert any("lost" in w for w in report["warnings"])
