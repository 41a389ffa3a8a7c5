"""The first pass's in-flight calibration run in a process of its own (service/inflight_process.py): the same
numbers as running it inline (a flight log, calibration and theta learned in flight, its state saved as the
pass goes; a GPS fix restarting the Earth field), and the child never outlives the replay."""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.service import inflight_process, observer_process, replay
from magcomp.service.inflight_process import InflightProcess
from magcomp.service.inflight_stage import InflightStage
from magcomp.service.replay import replay_log
from magcomp.sim import SimConfig, simulate

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the in-flight process: Linux")


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An ordinary flight, 150 s, two compasses: no hand rotation, both compasses learned in flight."""
    path = tmp_path_factory.mktemp("ifproc") / "flight.tlog"
    write_tlog(simulate(SimConfig(scenario="ordinary", duration_s=150.0, seed=4)), path)
    return path


def _started(monkeypatch: pytest.MonkeyPatch) -> list[InflightProcess]:
    """Every in-flight process the replays below start."""
    out: list[InflightProcess] = []
    if threading.active_count() > 1 or observer_process._foreign_threads():  # start() would not fork
        pytest.skip(f"threads running: {[t.name for t in threading.enumerate()]}")

    def start() -> InflightProcess | None:
        proc = inflight_process.start(2)
        assert proc is not None
        out.append(proc)
        return proc

    monkeypatch.setattr(replay, "start_inflight", start)
    return out


def test_inflight_process_gives_the_inline_numbers(
    flight: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    started = _started(monkeypatch)
    rep = replay_log(flight, Config(), keep_estimates=True, two_pass=True, emit=tmp_path / "a.tlog")
    assert len(started) == 1 and started[0].closed
    monkeypatch.setattr(replay, "INFLIGHT_PROCESS", False)
    ref = replay_log(flight, Config(), keep_estimates=True, two_pass=True, emit=tmp_path / "b.tlog")
    assert len(started) == 1  # inline this time
    compasses = ref.summary["compasses"]
    assert any(c["inflight"]["applied"] for c in compasses)  # the in-flight estimate was learned and applied
    assert ref.summary["earth_field"]["source"] == "gps"  # the stages restarted on the fix (a restart call)
    assert len(rep.estimates) == len(ref.estimates) > 1000
    theta = np.array([e.theta_mgauss for e in rep.estimates])
    assert np.abs(theta).max() > 1.0
    np.testing.assert_array_equal(theta, [e.theta_mgauss for e in ref.estimates])
    heading = [e.heading_deg for e in rep.estimates]
    np.testing.assert_array_equal(heading, [e.heading_deg for e in ref.estimates])
    assert (tmp_path / "a.tlog").read_bytes() == (tmp_path / "b.tlog").read_bytes()
    a, b = rep.to_json(), ref.to_json()
    a.pop("wall_s"), b.pop("wall_s")
    assert a == b


def test_inflight_process_ends_with_a_stopped_replay(flight: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """should_stop during the first pass: the child is reaped, the replay ends as asked."""
    started = _started(monkeypatch)
    calls = iter(range(1000))
    rep = replay_log(flight, Config(), two_pass=True, should_stop=lambda: next(calls) >= 40)
    assert rep.interrupted
    assert len(started) == 1 and started[0].closed
    assert len(started[0].children) >= 1
    for child in started[0].children:
        with pytest.raises(ChildProcessError):  # reaped: no zombie left
            os.waitpid(child.pid, os.WNOHANG)


def test_no_fork_while_another_thread_runs() -> None:
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        assert inflight_process.start() is None
    finally:
        stop.set()
        t.join()


def test_an_error_in_the_inflight_process_is_reported() -> None:
    """A call the child cannot run (a compass it was never given): its error, not a hang."""
    proc = inflight_process.start(1)
    assert proc is not None
    st = InflightStage(0, Config().inflight, "relative", "test", None, 500.0)
    remote = proc.stage(0, st)
    remote.reset_pairs()
    inflight_process.RemoteInflight(proc.children[0], 3, "relative").output(1.0, (200.0, 0.0, 400.0), 0.5, ())
    with pytest.raises(RuntimeError, match="in-flight process failed: KeyError"):
        proc.query()
    proc.close()
