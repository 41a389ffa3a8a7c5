"""Property-based fault injection (issue 12): random byte damage to simulated tlog and DataFlash logs,
clock jumps and reboots. Invariants: no traceback (a bad log is at most a one-line InputError), finite
outputs, output times in order, and the log's time span never stretched."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from magcomp.adapters.config import Config
from magcomp.errors import InputError
from magcomp.service.replay import replay_log
from tests.conftest import split_tlog_records
from tests.faultgen import retime, write_dataflash

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip


class _Logs(dict[str, Any]):
    def __repr__(self) -> str:  # a falsifying example prints the fixture: not the whole logs
        return f"<logs in {self.get('dir')}>"


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    d = tmp_path_factory.mktemp("inject")
    result = simulate(SimConfig(scenario="paper", duration_s=20.0, seed=9, n_compasses=1))
    write_tlog(result, d / "clean.tlog")
    write_dataflash(result, d / "clean.bin")
    tlog = replay_log(d / "clean.tlog", Config(), keep_estimates=True)
    span = tlog.estimates[-1].t_s - tlog.estimates[0].t_s
    return _Logs(dir=d, tlog=(d / "clean.tlog").read_bytes(), bin=(d / "clean.bin").read_bytes(), span=span,
                 records=split_tlog_records((d / "clean.tlog").read_bytes()))  # fmt: skip


def check_invariants(path: Path, span_s: float) -> None:
    try:
        rep = replay_log(path, Config(), keep_estimates=True)
    except InputError as exc:  # a log damaged beyond use: one line, no traceback
        assert "\n" not in str(exc)
        return
    ests = rep.estimates
    for c in rep.summary["compasses"]:
        assert all(math.isfinite(v) for v in c["theta_mgauss"])
    if not ests:
        return
    t = np.array([e.t_s for e in ests])
    assert np.all(np.diff(t) >= 0)
    # reboots are absorbed without a gap, so the span of the output is at most the input's own
    assert t[-1] - t[0] <= span_s + 1.0
    h = np.array([e.heading_deg for e in ests])
    assert np.all(np.isfinite(h) & (h >= 0.0) & (h < 360.0))
    assert all(np.all(np.isfinite(e.theta_mgauss)) and np.all(np.isfinite(e.bias_mgauss)) for e in ests)


damage = st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)), min_size=1, max_size=300)


def apply_damage(data: bytes, hits: list[tuple[float, int]]) -> bytes:
    out = bytearray(data)
    for where, value in hits:
        out[min(len(out) - 1, int(where * len(out)))] = value
    return bytes(out)


@pytest.mark.slow
@SETTINGS
@given(hits=damage)
def test_random_bytes_of_a_tlog(logs: dict[str, Any], hits: list[tuple[float, int]]) -> None:
    path = logs["dir"] / "damaged.tlog"
    path.write_bytes(apply_damage(logs["tlog"], hits))
    check_invariants(path, logs["span"])


@pytest.mark.slow
@SETTINGS
@given(hits=damage)
def test_random_bytes_of_a_dataflash_log(logs: dict[str, Any], hits: list[tuple[float, int]]) -> None:
    path = logs["dir"] / "damaged.bin"
    path.write_bytes(apply_damage(logs["bin"], hits))
    check_invariants(path, logs["span"])


@pytest.mark.slow
@SETTINGS
@given(
    events=st.lists(
        st.tuples(st.floats(0.0, 1.0), st.sampled_from(["reboot", "glitch", "jump"]), st.floats(-1e6, 1e6)),
        min_size=1,
        max_size=4,
    )
)
def test_clock_jumps_glitches_and_reboots(
    logs: dict[str, Any], events: list[tuple[float, str, float]]
) -> None:
    recs = logs["records"]
    n = len(recs)
    shifts: list[tuple[int, str, float]] = [(int(w * (n - 1)), kind, x) for w, kind, x in events]

    def new_time(i: int, old: float) -> float:
        t = old
        for at, kind, x in shifts:
            if kind == "glitch" and i == at:
                t += x
            elif kind == "reboot" and i >= at:  # the clock restarts at 0.3 s
                t = t - old + max(0.0, old - time_at[at]) + 0.3
            elif kind == "jump" and i >= at:
                t += abs(x) % 3600.0
        return max(0.0, t)

    time_at = _message_times(recs)
    path = logs["dir"] / "clock.tlog"
    path.write_bytes(b"".join(retime(recs, new_time)))
    # forward jumps lengthen the input itself: the bound is the input's span, jumps included
    jumps = sum(abs(x) % 3600.0 for _, kind, x in shifts if kind == "jump")
    check_invariants(path, logs["span"] + jumps)


def _message_times(recs: list[bytes]) -> list[float]:
    """Each record's own message time (s), carried forward for messages without one."""
    from magcomp.adapters.dialect import ensure_dialect

    mav = ensure_dialect().MAVLink(None)
    out, last = [], 0.0
    for r in recs:
        m = mav.decode(bytearray(r[8:]))
        if hasattr(m, "time_boot_ms"):
            last = m.time_boot_ms * 1e-3
        elif hasattr(m, "time_usec") and m.get_type() != "SERVO_OUTPUT_RAW":
            last = m.time_usec * 1e-6
        out.append(last)
    return out


def test_a_corrupt_dataflash_instance_byte_makes_no_phantom_compass(tmp_path: Path) -> None:
    """DataFlash has no checksum: a MAG message whose instance byte I was damaged (to 159 or 7) still frames.
    ArduPilot logs at most 3 compasses, so such a message is dropped and counted, not a new compass."""
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="paper", duration_s=20.0, seed=4, n_compasses=2))
    clean = tmp_path / "clean.bin"
    write_dataflash(result, clean)
    data = bytearray(clean.read_bytes())
    mag_len = 3 + 8 + 1 + 12  # header, TimeUS (Q), I (B), MagX..Z (fff): tests/faultgen.py's MAG
    head, nxt = b"\xa3\x95\x82", b"\xa3\x95"
    starts = [i for i in range(len(data) - mag_len - 2) if data[i : i + 3] == head]
    starts = [i for i in starts if data[i + mag_len : i + mag_len + 2] == nxt]
    damaged = starts[100::97]
    for k, i in enumerate(damaged):
        data[i + 11] = 159 if k % 2 else 7
    path = tmp_path / "damaged.bin"
    path.write_bytes(bytes(data))
    rep = replay_log(path, Config())
    assert sorted(c["index"] for c in rep.summary["compasses"]) == [0, 1]
    assert rep.counts["dataflash_bad_instance"] == len(damaged) > 5
