"""Signals: a handler only sets a flag, so a second signal arriving while the first is handled cannot
deadlock; the run still stops, saves its state and writes the --json summary. SIGTERM on `replay`
writes the partial summary like ^C."""

from __future__ import annotations

import json
import signal
import threading
from pathlib import Path

import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.state_store import StateStore
from magcomp.core.identity import SIM_UID
from magcomp.service.daemon import Daemon
from magcomp.service.demo import free_udp_port
from tests.waiting import finish, start_magcomp, wait_for


def test_stop_request_from_a_signal_handler_takes_no_lock() -> None:
    """The deadlock of issue 12: the handler ran stop(), whose Event.set() takes the Event's lock; a
    signal delivered while the main thread held that lock (inside Event.wait/set) waited on itself."""
    daemon = Daemon(f"udpin:127.0.0.1:{free_udp_port()}", Config())
    done = threading.Event()

    def handler_while_lock_held() -> None:
        with daemon._stop._cond:  # type: ignore[attr-defined]  # the main thread interrupted inside the Event's critical section
            daemon.request_stop()  # what the signal handler runs, on the same thread
        done.set()

    t = threading.Thread(target=handler_while_lock_held, daemon=True)
    t.start()
    t.join(timeout=10.0)
    assert done.is_set(), "request_stop blocked on a lock held by the thread it interrupted"
    # the run sees the request: run() returns at once with a report
    report = daemon.run()
    assert report.connects <= 1 and daemon.stopped


@pytest.mark.slow
@pytest.mark.parametrize("signals", [(signal.SIGTERM,), (signal.SIGTERM, signal.SIGINT, signal.SIGTERM)])
def test_run_stopped_by_signals_saves_state_and_summary(
    tmp_path: Path, signals: tuple[signal.Signals, ...]
) -> None:
    """`magcomp run` stops on SIGTERM, and on three signals in quick succession, and still saves the state
    learned on the stream and writes the --json summary."""
    from magcomp.adapters.mavlink_emit import stream_to_link
    from magcomp.sim import SimConfig, simulate

    port = free_udp_port()
    state, summary = tmp_path / "state", tmp_path / "sum.json"
    proc, out, err = start_magcomp("run", "--master", f"udpin:127.0.0.1:{port}", "--state-dir", str(state),
                                   "--json", str(summary))  # fmt: skip
    try:
        wait_for(lambda: err.has("listening on udpin:") or proc.poll() is not None, 60.0, "listening")
        result = simulate(SimConfig(scenario="tumble", duration_s=15.0, seed=2, n_compasses=1))
        stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=20.0)
        # the calibration learned on the stream is saved at once (in the background)
        wait_for(lambda: StateStore(state).load(1, 0, SIM_UID) is not None or proc.poll() is not None, 60.0,
                 "state")
    finally:
        for s in signals:
            proc.send_signal(s)
        code = finish(proc, 60.0)
    assert code == 0, err.join()
    assert "Traceback" not in err.join()
    doc = json.loads(summary.read_text())
    assert doc["counts"]["mag"] > 0 and doc["connects"] == 1
    assert "compass 0:" in out.join()
    assert StateStore(state).load(1, 0, SIM_UID) is not None


@pytest.mark.slow
@pytest.mark.parametrize("signals", [(signal.SIGTERM,), (signal.SIGTERM, signal.SIGINT), (signal.SIGINT,)])
def test_replay_stopped_by_a_signal_writes_the_partial_summary(
    tmp_path: Path, signals: tuple[signal.Signals, ...]
) -> None:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    one = tmp_path / "one.tlog"
    write_tlog(simulate(SimConfig(scenario="paper", duration_s=40.0, seed=7, n_compasses=1)), one)
    long_log = tmp_path / "long.tlog"
    long_log.write_bytes(one.read_bytes() * 200)  # ~2 h of log: minutes to replay, stopped long before
    summary = tmp_path / "sum.json"
    proc, out, err = start_magcomp("replay", str(long_log), "--json", str(summary), "-v")
    try:
        wait_for(lambda: err.has("replaying") or proc.poll() is not None, 60.0, "the replay to start")
    finally:
        for s in signals:
            proc.send_signal(s)
        code = finish(proc, 60.0)
    # two pending signals are handled in signal-number order, not in the order sent
    expected = {143 if s == signal.SIGTERM else 130 for s in signals}
    assert code in expected, err.join()
    assert "Traceback" not in err.join()
    doc = json.loads(summary.read_text())
    assert "interrupted_at_s" in doc
    # stopped in the second pass: how far it got; in the first (which reads the whole log before any
    # heading, the usual case here): that there is nothing to report (was "up to nan s")
    said = out.join()
    assert any(line in said for line in ("interrupted: the summary covers the log up to",
                                         "interrupted before the first heading"))  # fmt: skip
    assert " nan " not in said
