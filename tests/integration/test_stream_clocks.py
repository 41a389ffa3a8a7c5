"""Streams on clocks of their own (issue 23, item 4): ArduCopter 3.1/3.2 stamp RAW_IMU and SERVO_OUTPUT_RAW
``time_usec`` 2.57-2.87 s behind ``time_boot_ms``. The offset is measured from messages sent together and
removed, so a replay of such a log gives the headings of its twin on one clock."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.mavlink_source import OFFSET_MIN_S, MavSource, StreamOffsets
from magcomp.service.replay import replay_log
from tests.conftest import split_tlog_records
from tests.faultgen import retime

OFFSET_S = 2.6  # RAW_IMU / SERVO_OUTPUT_RAW behind the time_boot_ms clock, as on the squilter tlogs
SHIFTED = ("RAW_IMU", "SERVO_OUTPUT_RAW")


def _types(records: list[bytes]) -> list[str]:
    from magcomp.adapters.dialect import ensure_dialect

    mav = ensure_dialect().MAVLink(None)
    return [mav.decode(bytearray(r[8:])).get_type() for r in records]


@pytest.fixture(scope="module")
def twins(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A simulated flight (hand rotation, then flying with yaw; two compasses) and the same tlog with
    RAW_IMU and SERVO_OUTPUT_RAW re-encoded OFFSET_S behind the other streams."""
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="paper", duration_s=60.0, seed=4))
    assert float(result.samples.t_s[0]) > OFFSET_S  # the shifted stamps stay positive
    d = tmp_path_factory.mktemp("clocks")
    clean = d / "clean.tlog"
    write_tlog(result, clean)
    recs = split_tlog_records(clean.read_bytes())
    kinds = _types(recs)
    shifted = retime(recs, lambda i, old: old - OFFSET_S if kinds[i] in SHIFTED else old)
    path = d / "offset.tlog"
    path.write_bytes(b"".join(shifted))
    return clean, path


def _offsets(path: Path) -> tuple[dict[str, float], dict[str, int]]:
    src = MavSource(str(path))
    for _ in src.samples():
        pass
    return src.clock_offsets(), dict(src.counts)


def test_offset_found_within_10_ms_and_counted_once(twins: tuple[Path, Path]) -> None:
    clean, shifted = twins
    offsets, counts = _offsets(shifted)
    assert set(offsets) == set(SHIFTED)
    for stream in SHIFTED:
        assert abs(offsets[stream] - OFFSET_S) < 0.010, (stream, offsets[stream])
    assert counts["clock_aligned"] == 2
    # one clock already: nothing applied, nothing said
    offsets, counts = _offsets(clean)
    assert offsets == {} and counts.get("clock_aligned", 0) == 0


def _headings(path: Path) -> tuple[dict[int, tuple[np.ndarray, np.ndarray]], dict[str, Any]]:
    rep = replay_log(path, Config(), keep_estimates=True, two_pass=True)
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for idx in sorted({e.mag_index for e in rep.estimates}):
        es = [e for e in rep.estimates if e.mag_index == idx]
        out[idx] = (np.array([e.t_s for e in es]), np.array([e.heading_deg for e in es]))
    return out, rep.to_json()


def test_replay_headings_match_the_twin_on_one_clock(twins: tuple[Path, Path]) -> None:
    clean, shifted = twins
    (ref, ref_json), (got, got_json) = _headings(clean), _headings(shifted)
    assert "clock_offsets_s" not in ref_json
    assert set(got_json["clock_offsets_s"]) == set(SHIFTED)
    assert got_json["source_counts"]["clock_aligned"] == 2
    assert set(ref) == set(got) == {0, 1}
    for idx in ref:
        t_ref, h_ref = ref[idx]
        t, h = got[idx]
        # from 5 s on (the offset locks after 9 pairs, 0.2 s at 50 Hz), each heading at its twin's time
        keep = t > t_ref[0] + 5.0
        j = np.clip(np.searchsorted(t_ref, t[keep]), 1, len(t_ref) - 1)
        j -= np.abs(t_ref[j - 1] - t[keep]) < np.abs(t_ref[j] - t[keep])
        assert np.max(np.abs(t_ref[j] - t[keep])) < 0.005  # on the twin's clock (stamps of 1 ms, 1 us)
        err = (h[keep] - h_ref[j] + 180.0) % 360.0 - 180.0
        # without the alignment: 88 deg rms on compass 0 (the attitude and throttle of 2.6 s later)
        assert float(np.sqrt(np.mean(err**2))) < 0.5, idx


def _stream(messages: list[tuple[str, float, float]], src: tuple[int, int] = (1, 1)) -> StreamOffsets:
    """Messages observed in turn, the usec streams' from system ``src[0]``, the others' from ``src[1]``."""
    counts: dict[str, Any] = {"clock_aligned": 0}
    so = StreamOffsets(counts)
    for name, raw, rx in messages:
        so.observe(name, raw, rx, src[0] if name in SHIFTED else src[1])
    return so


def test_the_tail_of_the_previous_burst_is_a_lower_bound_not_the_offset() -> None:
    """On a link that runs bursts together, RAW_IMU's predecessor is the previous burst's last message,
    stamped one scheduler slot (20 ms) earlier: as consistent as the true partner, but not sent with it."""
    msgs = []
    for k in range(40):
        t = 100.0 + 0.1 * k  # time_boot_ms clock; RAW_IMU's clock 2.5 s behind
        rx = 1000.0 + 0.1 * k
        msgs += [("ATTITUDE", t - 0.02, rx - 0.006), ("RAW_IMU", t - 2.5, rx),
                 ("SCALED_IMU2", t + 0.0004, rx + 0.006)]  # fmt: skip
    so = _stream(msgs)
    assert abs(so.offset_s["RAW_IMU"] - 2.5) < 0.001


def test_small_or_inconsistent_differences_are_not_applied() -> None:
    rng = np.random.default_rng(1)
    # the same clock, messages 0-20 ms apart: below OFFSET_MIN_S, nothing applied
    same = [m for k in range(40) for m in (("RAW_IMU", 10.0 + 0.1 * k, 5.0 + 0.1 * k),
            ("SCALED_IMU2", 10.0 + 0.1 * k + 0.02 * rng.random(), 5.0 + 0.1 * k + 0.005))]  # fmt: skip
    assert _stream(same).offset_s == {}
    assert OFFSET_MIN_S > 0.02
    # stamps that do not agree (IQR of ~0.5 s): never sent together, nothing applied
    wild = [m for k in range(40) for m in (("RAW_IMU", 10.0 + 0.1 * k, 5.0 + 0.1 * k),
            ("SCALED_IMU2", 12.0 + 0.1 * k + rng.random(), 5.0 + 0.1 * k + 0.005))]  # fmt: skip
    assert _stream(wild).offset_s == {}
    # pairs received far apart are not pairs at all
    apart = [m for k in range(40) for m in (("RAW_IMU", 10.0 + 0.1 * k, 5.0 + 0.1 * k),
             ("SCALED_IMU2", 12.6 + 0.1 * k, 5.0 + 0.1 * k + 0.05))]  # fmt: skip
    assert _stream(apart).offset_s == {}


def test_a_live_link_finds_the_offset_from_arrival_times(twins: tuple[Path, Path]) -> None:
    """Live: the same stream sent over UDP, paced at 10x its own time, the receiver pairing by arrival."""
    import socket
    import threading
    import time

    from tests.faultgen import record_time_s

    _, shifted = twins
    recs = split_tlog_records(shifted.read_bytes())
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    src = MavSource(f"udpin:127.0.0.1:{port}", live_timeout_s=0.1)
    done = threading.Event()

    def send() -> None:  # the flight controller: each record at its own time / 10 (a burst arrives together)
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            t0, wall0 = record_time_s(recs[0]), time.monotonic()
            for rec in recs:
                if done.is_set():
                    return
                ahead = (record_time_s(rec) - t0) / 10.0 - (time.monotonic() - wall0)
                if ahead > 0.0:
                    time.sleep(ahead)  # pacing, not waiting for anything
                out.sendto(rec[8:], ("127.0.0.1", port))
        finally:
            out.close()
            src.close()  # the receiving loop ends at its next timeout

    th = threading.Thread(target=send, daemon=True)
    th.start()
    offsets = src._conv.clock.offsets.offset_s
    try:
        for _ in src.samples():
            if set(SHIFTED) <= set(offsets):
                break
    finally:
        done.set()
        src.close()
        th.join(timeout=10.0)
    assert set(offsets) == set(SHIFTED)
    for stream in SHIFTED:
        assert abs(offsets[stream] - OFFSET_S) < 0.010, (stream, offsets[stream])


def test_only_messages_of_one_sender_pair() -> None:
    """Two vehicles in one tlog: vehicle 1's RAW_IMU right before vehicle 2's SCALED_IMU2 is no pair."""
    msgs = [m for k in range(40) for m in (("RAW_IMU", 10.0 + 0.1 * k, 5.0 + 0.1 * k),
            ("SCALED_IMU2", 12.5 + 0.1 * k, 5.0 + 0.1 * k + 0.005))]  # fmt: skip
    assert abs(_stream(msgs).offset_s["RAW_IMU"] - 2.5) < 1e-9  # one sender: aligned
    assert _stream(msgs, src=(1, 2)).offset_s == {}
