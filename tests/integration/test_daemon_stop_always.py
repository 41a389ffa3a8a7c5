"""Issue 25 (1): a stop request (what ^C and SIGTERM do) ends the run whatever the other threads do: a
housekeeping thread that fails or dies, an open of the link that blocks. The state is saved and the
report returned either way."""

from __future__ import annotations

import logging
import threading
from dataclasses import replace
from typing import Any

import pytest

from magcomp.adapters.config import Config
from magcomp.service.daemon import Daemon, DaemonReport
from magcomp.service.demo import free_udp_port
from tests.waiting import wait_for


def _run_in_thread(daemon: Daemon) -> tuple[threading.Thread, dict[str, Any]]:
    box: dict[str, Any] = {}

    def target() -> None:
        box["report"] = daemon.run()

    t = threading.Thread(target=target, daemon=True)
    t.start()
    return t, box


def _fast_config() -> Config:
    c = Config()
    return replace(c, link=replace(c.link, heartbeat_hz=20.0, reconnect_s=0.1))


def test_a_failing_housekeeping_round_neither_kills_the_thread_nor_blocks_the_stop(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    calls = {"n": 0}

    def broken(self: Daemon, now: float) -> None:
        calls["n"] += 1
        raise AttributeError("'NoneType' object has no attribute 'send'")  # pymavlink mid-reconnect

    monkeypatch.setattr(Daemon, "_check_loss", broken)
    monkeypatch.setattr("magcomp.service.daemon.LOSS_WINDOW_S", 0.05)
    daemon = Daemon(f"udpin:127.0.0.1:{free_udp_port()}", _fast_config())
    with caplog.at_level(logging.INFO, logger="magcomp"):
        t, box = _run_in_thread(daemon)
        wait_for(lambda: calls["n"] >= 3, 30.0, "three failing rounds")
        hk = daemon._hk_thread
        assert hk is not None and hk.is_alive()  # the failures did not end the housekeeping thread
        daemon.request_stop()
        t.join(timeout=30.0)
    assert not t.is_alive(), "the stop request was ignored"
    assert isinstance(box["report"], DaemonReport)
    errors = [r for r in caplog.records if "housekeeping" in r.getMessage()]
    assert len(errors) == 1 and "AttributeError" in errors[0].getMessage()  # one line, not one per round


def test_a_dead_housekeeping_thread_is_seen_and_the_stop_still_works(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    started = {"n": 0}
    real = Daemon._housekeeping

    def ends_first_time(self: Daemon) -> None:
        started["n"] += 1
        if started["n"] == 1:
            return  # the thread ends at once, as if killed by an error nothing caught
        real(self)

    monkeypatch.setattr(Daemon, "_housekeeping", ends_first_time)
    daemon = Daemon(f"udpin:127.0.0.1:{free_udp_port()}", _fast_config())
    with caplog.at_level(logging.INFO, logger="magcomp"):
        t, _ = _run_in_thread(daemon)
        wait_for(lambda: started["n"] >= 2, 30.0, "the housekeeping thread to be started again")
        daemon.request_stop()
        t.join(timeout=30.0)
    assert not t.is_alive(), "the stop request was ignored"
    assert "housekeeping thread ended unexpectedly" in caplog.text


def test_a_stop_request_ends_an_open_that_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    """A TCP connect to a host that does not answer blocks for minutes; the stop must not wait for it."""
    release = threading.Event()
    entered = threading.Event()

    def blocking_open(*args: Any, **kwargs: Any) -> Any:
        entered.set()
        release.wait(120.0)
        raise OSError("released")

    monkeypatch.setattr("magcomp.adapters.mavlink_source.open_source", blocking_open)
    daemon = Daemon("tcp:127.0.0.1:9", _fast_config())
    try:
        t, box = _run_in_thread(daemon)
        wait_for(entered.is_set, 30.0, "the open to start")
        daemon.request_stop()
        t.join(timeout=30.0)
        assert not t.is_alive(), "the run waited for the blocked open"
        assert box["report"].connects == 0
    finally:
        release.set()
