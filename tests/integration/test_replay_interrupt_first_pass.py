"""``magcomp replay LOG`` interrupted with ^C (SIGINT to the process group, as a terminal sends it) while its
first pass runs (one process, service/replay.py): one line, exit 130, no traceback, no child process, and no
empty ``--emit`` file or "up to nan s" when no heading was computed yet."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.sim import SimConfig, simulate
from tests.waiting import LineReader, wait_for

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="ps --ppid: Linux")


def _children(pid: int) -> list[int]:
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    return [int(x) for x in out.split()]


def test_sigint_in_the_first_pass(tmp_path: Path) -> None:
    log = tmp_path / "flight.tlog"
    write_tlog(simulate(SimConfig(scenario="ordinary", duration_s=600.0, seed=2)), log)
    emit, js = tmp_path / "out.tlog", tmp_path / "out.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "magcomp", "replay", str(log), "--emit", str(emit), "--json", str(js)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    assert proc.stdout is not None and proc.stderr is not None
    out_r, err_r = LineReader(proc.stdout), LineReader(proc.stderr)
    try:
        # said by the first pass at the first sample with the throttle known, seconds before its end
        wait_for(lambda: err_r.has("learning calibration and theta in flight") or proc.poll() is not None,
                 120.0, "the first pass to start learning")  # fmt: skip
        assert proc.poll() is None, "the replay ended before its first pass was seen"
        assert _children(proc.pid) == [], "the replay forked"
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    out, err = out_r.join(), err_r.join()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == "magcomp replay: interrupted"
    assert "nan" not in out
    if "interrupted before the first heading" in out:  # stopped in the first pass (the usual case)
        assert not emit.exists(), "an empty --emit file was left"
    else:  # the machine was slow to deliver the signal: stopped in the second pass, headings kept
        assert emit.stat().st_size > 0
    assert js.exists()
