"""^C during the repair of a DataFlash log with gigabytes of zero tail (issue 25: a 4 GiB zero tail ignored
SIGINT): `magcomp replay` stops within 3 s with one line. The tail is a sparse file (truncate): no disk.

Before the fix, the log's span (the progress bar's total) and the repair each searched the whole mapped
file in one C call (``mmap.find``), which holds off KeyboardInterrupt until it returns: minutes here."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.waiting import wait_for

REPO = Path(__file__).resolve().parents[2]
TAIL_BYTES = 6 << 30


def _maps(pid: int, path: Path) -> bool:
    try:
        return str(path) in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs Linux's /proc/PID/maps")
def test_ctrl_c_stops_replay_of_a_log_with_a_multi_gib_zero_tail_within_3_s(tmp_path: Path) -> None:
    from magcomp.adapters.dataflash_writer import write_sim_dataflash
    from magcomp.sim import SimConfig, simulate

    clean = tmp_path / "clean.bin"
    write_sim_dataflash(simulate(SimConfig(scenario="paper", duration_s=20.0, seed=2)), clean)
    big = tmp_path / "big.bin"
    shutil.copyfile(clean, big)
    os.truncate(big, clean.stat().st_size + TAIL_BYTES)  # a sparse zero tail
    if big.stat().st_blocks * 512 > 2 * clean.stat().st_size + (1 << 20):
        pytest.skip("this file system does not keep sparse files")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    argv = [sys.executable, "-m", "magcomp", "replay", str(big)]
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=REPO, env=env)  # fmt: skip
    try:
        # the log is mapped: replay is reading it (the span estimate, then the repair), 6 GiB to go
        wait_for(lambda: _maps(proc.pid, big) or proc.poll() is not None, 60.0, "replay to map the log")
        assert proc.poll() is None, proc.communicate()
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert took < 3.0, (took, err[-2000:])
    assert proc.returncode == 130, (proc.returncode, err[-2000:])
    assert "Traceback" not in err
    assert err.strip().splitlines() == ["magcomp replay: interrupted"], err[-2000:]


def test_the_dataflash_repair_search_stops_on_the_flag_between_chunks(tmp_path: Path) -> None:
    """The repair's search for the next message header (``dataflash_intact_spans``) through a zero tail reads
    the stop flag between 16 MiB chunks: with the flag set it raises at once instead of scanning 6 GiB."""
    import mmap

    from magcomp.adapters.log_span import interruptible_scans
    from magcomp.adapters.mavlink_source import dataflash_intact_spans

    big = tmp_path / "zeros.bin"
    big.write_bytes(b"\xa3\x95\x80" + bytes(86))  # one FMT message, then damage: zeros
    os.truncate(big, TAIL_BYTES)
    with big.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        asked: list[int] = []

        def stop() -> bool:
            asked.append(1)
            return len(asked) > 2  # the third chunk: a few tens of MiB read, not 6 GiB

        t0 = time.monotonic()
        with pytest.raises(KeyboardInterrupt), interruptible_scans(stop):
            dataflash_intact_spans(data)
        assert time.monotonic() - t0 < 3.0 and len(asked) == 3
        assert dataflash_intact_spans(data[: 1 << 20]).resyncs == 0  # outside the context: no flag read


def test_find_in_chunks_finds_what_find_finds_across_chunk_edges(monkeypatch: pytest.MonkeyPatch) -> None:
    import numpy as np

    from magcomp.adapters import log_span

    monkeypatch.setattr(log_span, "FIND_CHUNK_BYTES", 7)  # headers straddle the chunk edges
    rng = np.random.default_rng(4)
    data = bytes(rng.choice([0, 0xA3, 0x95, 0x80], size=2000).astype(np.uint8))
    for needle in (b"\xa3\x95", b"\xa3\x95\x80", b"\x80"):
        for start in range(0, 2001, 13):
            assert log_span.find_in_chunks(data, needle, start) == data.find(needle, start), (needle, start)
    assert log_span.find_in_chunks(data, b"\x01\x02", 0) == -1
