"""Issue 25 (1): a TCP link that drops again and again must never make `magcomp run` unstoppable. A
flight controller that serves one client at a time drops the link several times in quick succession;
every ^C / SIGTERM then stops the run with the state saved and the summary printed, and after each drop
the daemon reads from the new connection again. The same run 50 times: benchmarks/stop_under_drops.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.tcp_drops import SIGNALS, stop_after_drops

#: how long a stopped run may take to exit before the test calls it unstoppable (the issue's bound is
#: 3 s, measured by the benchmark; the test allows for a loaded machine: before the fix the run never
#: exited at all)
STOP_BOUND_S = 20.0


@pytest.mark.slow
@pytest.mark.parametrize("run", range(5))
def test_run_stops_after_quick_tcp_drops_with_state_and_summary(tmp_path: Path, run: int) -> None:
    r = stop_after_drops(tmp_path, SIGNALS[run % 2], STOP_BOUND_S)
    assert r.code == 0, (r.stop_s, r.stderr)
    assert "Traceback" not in r.stderr
    assert r.summary is not None
    # every connection the server saw was one the daemon opened and read: none opened behind its back
    # by a writing thread (pymavlink's in-place reconnect, racing the reader)
    assert r.summary["connects"] == r.served == 5, (r.summary["connects"], r.served)
    assert r.summary["counts"]["mag"] > 0
    assert "compass 0:" in r.stdout
    assert r.state_saved  # compass 0 of system 1, whatever identity the simulated board gave
