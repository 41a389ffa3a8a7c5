"""The first pass's observers stepped in a process of their own (service/observer_process.py): the same
numbers as stepping them inline (hand rotation, a reboot, an in-flight calibration whose state the first pass
saves as it goes), and the child never outlives the replay."""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.service import observer_process, replay
from magcomp.service.observer_process import ObserverProcess
from magcomp.service.replay import replay_log
from magcomp.sim import SimConfig, simulate
from tests.faultgen import paper_and_rebooted

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the observer process: Linux")


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The paper's scenario (hand rotation, then flight), 120 s, two compasses; and the same log with the
    autopilot rebooting 80 s in (the observers' filters reset: reset messages down the pipe)."""
    d = tmp_path_factory.mktemp("obsproc")
    logs = paper_and_rebooted(d, 120.0, 7, 80.0)
    # calibration and theta learned in flight: its state is saved every 10 s of the first pass too
    write_tlog(simulate(SimConfig(scenario="ordinary", duration_s=120.0, seed=3)), d / "flight.tlog")
    return {**logs, "flight": d / "flight.tlog"}


def _started(monkeypatch: pytest.MonkeyPatch) -> list[ObserverProcess]:
    """Every observer process the replays below start."""
    out: list[ObserverProcess] = []
    if threading.active_count() > 1:  # left by another test: start() would (rightly) not fork
        pytest.skip(f"threads running: {[t.name for t in threading.enumerate()]}")
    if observer_process._foreign_threads():  # a library's native threads (e.g. the Rerun SDK's): as above
        pytest.skip(f"native threads running: {observer_process._foreign_threads()}")

    def start(cfg: Config) -> ObserverProcess | None:
        proc = observer_process.start(cfg)
        assert proc is not None
        out.append(proc)
        return proc

    monkeypatch.setattr(replay, "start_observers", start)
    return out


@pytest.mark.parametrize("name", ["paper", "reboot", "flight"])
def test_observer_process_gives_the_inline_numbers(
    logs: dict[str, Path], name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    started = _started(monkeypatch)
    rep = replay_log(logs[name], Config(), keep_estimates=True, two_pass=True, emit=tmp_path / "a.tlog")
    assert len(started) == 1 and started[0]._closed
    monkeypatch.setattr(replay, "OBSERVER_PROCESS", False)
    ref = replay_log(logs[name], Config(), keep_estimates=True, two_pass=True, emit=tmp_path / "b.tlog")
    assert len(started) == 1  # inline this time
    assert rep.summary["counts"]["reboots"] == (name == "reboot")
    assert len(rep.estimates) == len(ref.estimates) > 1000
    # theta learned in the first pass and held by the second: bit for bit what the inline observer gives
    theta = np.array([e.theta_mgauss for e in rep.estimates])
    assert np.abs(theta).max() > 1.0  # the observers (or the in-flight estimate) did learn something
    np.testing.assert_array_equal(theta, [e.theta_mgauss for e in ref.estimates])
    heading = [e.heading_deg for e in rep.estimates]
    np.testing.assert_array_equal(heading, [e.heading_deg for e in ref.estimates])
    np.testing.assert_array_equal([e.flags for e in rep.estimates], [e.flags for e in ref.estimates])
    assert (tmp_path / "a.tlog").read_bytes() == (tmp_path / "b.tlog").read_bytes()
    a, b = rep.to_json(), ref.to_json()
    a.pop("wall_s"), b.pop("wall_s")
    assert a == b


def test_observer_process_ends_with_a_stopped_replay(
    logs: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    """should_stop during the first pass: the child is reaped, the replay ends as asked."""
    started = _started(monkeypatch)
    calls = iter(range(1000))
    rep = replay_log(logs["paper"], Config(), two_pass=True, should_stop=lambda: next(calls) >= 20)
    assert rep.interrupted
    assert len(started) == 1 and started[0]._closed
    with pytest.raises(ChildProcessError):  # reaped: no zombie left
        os.waitpid(started[0]._pid, os.WNOHANG)


def test_no_fork_while_another_thread_runs() -> None:
    """A caller's own thread (a viewer, a test runner's watchdog): the observers step inline."""
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        assert observer_process.start(Config()) is None
    finally:
        stop.set()
        t.join()


def test_an_error_in_the_observer_process_is_reported() -> None:
    """A step the child cannot run (a compass it was never told of): its error, not a hang."""
    proc = observer_process.start(Config())
    assert proc is not None
    proc.estimator(0, Config(), None)
    proc.step(5, (0.1, 0.2, 0.3), (200.0, 0.0, 400.0), 0.5, 0.02)
    with pytest.raises(RuntimeError, match="observer process failed: KeyError"):
        proc.query()
    proc.close()
