"""``magcomp replay LOG`` interrupted with ^C (SIGINT to the process group, as a terminal sends it) while its
first pass runs, the observers stepping in their forked process (service/observer_process.py): one line,
exit 130, no traceback, no observer process left, and no empty ``--emit`` file or "up to nan s" when no
heading was computed yet."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.sim import SimConfig, simulate
from tests.waiting import wait_for

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the observer process: Linux")


def _children(pid: int) -> list[int]:
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    return [int(x) for x in out.split()]


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_sigint_in_the_first_pass(tmp_path: Path) -> None:
    log = tmp_path / "flight.tlog"
    write_tlog(simulate(SimConfig(scenario="ordinary", duration_s=600.0, seed=2)), log)
    emit, js = tmp_path / "out.tlog", tmp_path / "out.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "magcomp", "replay", str(log), "--emit", str(emit), "--json", str(js)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    kids: list[int] = []

    def forked() -> bool:
        kids[:] = _children(proc.pid)
        return bool(kids) or proc.poll() is not None

    try:
        wait_for(forked, 120.0, "the observer process")
        assert kids, "the replay ended before its observer process was seen"
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == "magcomp replay: interrupted"
    wait_for(lambda: not any(_alive(k) for k in kids), 30.0, "the observer process to end")
    assert "nan" not in out
    if "interrupted before the first heading" in out:  # stopped in the first pass (the usual case)
        assert not emit.exists(), "an empty --emit file was left"
    else:  # the machine was slow to deliver the signal: stopped in the second pass, headings kept
        assert emit.stat().st_size > 0
    assert js.exists()
