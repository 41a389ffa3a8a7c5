"""A ^C (Python's KeyboardInterrupt) while a block of observer steps goes down the pipe to the observer
process (service/observer_process.py): the block arrives whole, so the child's numbers stay the inline
ones (a pipe write cut short by the signal, then the rest dropped, would shift every later message)."""

from __future__ import annotations

import _thread
import os
import select
import signal
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.errors import MagcompError
from magcomp.service import observer_process
from magcomp.service.estimators import ThetaEstimator
from tests.waiting import wait_for

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the observer process: Linux")


def test_a_sigint_mid_block_leaves_the_observer_stream_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    if threading.active_count() > 1 or threading.current_thread() is not threading.main_thread():
        pytest.skip("threads running: start() would (rightly) not fork")
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("SIGINT is not Python's default handler here")
    cfg = Config()
    proc = observer_process.start(cfg)
    assert proc is not None
    try:
        remote = proc.estimator(0, cfg, None)
        inline = ThetaEstimator(cfg, None)
        real_write = os.write
        cut: list[int] = []

        def write(fd: int, data: memoryview) -> int:
            """The first block's write cut short (a whole number of floats, not of messages), with a
            SIGINT arriving as it returns."""
            if fd == proc._cmd and not cut and len(data) > 8 * 1003:
                cut.append(real_write(fd, data[: 8 * 1003]))
                os.kill(os.getpid(), signal.SIGINT)
                return cut[0]
            return real_write(fd, data)

        monkeypatch.setattr(os, "write", write)
        rng = np.random.default_rng(3)
        interrupts = 0
        for k in range(1200):  # two blocks of 512 messages and a part
            t = k * 0.02
            omega = (0.3 * np.sin(t), 0.2 * np.cos(0.7 * t), 0.5 + 0.1 * rng.standard_normal())
            field = (200.0 + 30.0 * np.sin(t), -50.0 + 20.0 * np.cos(t), 400.0 + rng.standard_normal())
            thr = 0.4 + 0.2 * np.sin(0.3 * t)
            inline.step(omega, field, thr, 0.02)
            try:
                remote.step(tuple(map(float, omega)), tuple(map(float, field)), float(thr), 0.02)
            except KeyboardInterrupt:
                interrupts += 1
        monkeypatch.undo()
        assert cut and interrupts == 1
        # the answer to a query, waited for with a deadline (a shifted stream may never answer)
        proc._buf.extend((observer_process._QUERY, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        proc._flush()
        ready, _, _ = select.select([proc._res], [], [], 60.0)
        assert ready, "no answer from the observer process"
        answer = proc._answer()
        assert answer is not None
        remote.take(answer[0])
        np.testing.assert_array_equal(remote.local.theta_mgauss, inline.theta_mgauss)
        assert remote.local.converged == inline.converged
    finally:
        proc.close()


def test_no_fork_while_a_library_native_thread_runs() -> None:
    """A thread ``threading`` does not see, named as a library names its own (the Rerun SDK's writer of
    ``replay --rerun save=FILE``): the observers step inline."""
    if threading.active_count() > 1 or observer_process._foreign_threads():
        pytest.skip("threads running: start() would (rightly) not fork")
    started, release = _thread.allocate_lock(), _thread.allocate_lock()
    started.acquire()
    release.acquire()

    def native() -> None:
        Path(f"/proc/self/task/{threading.get_native_id()}/comm").write_text("file_writer")
        started.release()
        release.acquire()  # until the test is done

    _thread.start_new_thread(native, ())
    started.acquire()  # the thread has its name
    try:
        assert threading.active_count() == 1  # not Python's: only the name tells
        assert observer_process._foreign_threads() == ["file_writer"]
        assert observer_process.start(Config()) is None
    finally:
        release.release()
        wait_for(lambda: not observer_process._foreign_threads(), 30.0, "the native thread to end")


def test_a_killed_observer_process_is_a_one_line_error() -> None:
    """The child killed (the OOM killer, a kill of its pid): a MagcompError, which the CLI prints as its one
    line ``magcomp replay: error: ...`` with exit 1, not a traceback."""
    if threading.active_count() > 1 or observer_process._foreign_threads():
        pytest.skip("threads running: start() would (rightly) not fork")
    proc = observer_process.start(Config())
    assert proc is not None
    est = proc.estimator(0, Config(), None)
    os.kill(proc._pid, signal.SIGKILL)
    with pytest.raises(MagcompError, match="observer process ended early"):
        for _ in range(100_000):  # fills the block and writes it down the closed pipe
            est.step((0.1, 0.2, 0.3), (200.0, 0.0, 400.0), 0.5, 0.02)
        est.sync()
    proc.close()
