"""MAGCOMP_HEADING packed by magcomp's own frame packer is byte for byte what pymavlink packs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.dialect import ensure_dialect
from magcomp.core.types import HeadingEstimate
from magcomp.service.publish import FrameQueue, HeadingEncoder, TlogWriter


def _pymavlink_bytes(enc: HeadingEncoder, est: HeadingEstimate) -> bytes:
    mod = ensure_dialect()
    th, b = est.theta_mgauss, est.bias_mgauss
    msg = mod.MAVLink_magcomp_heading_message(
        round(est.t_s * 1000.0) & 0xFFFFFFFF, est.heading_deg, est.heading_raw_deg, list(th), list(b),
        est.throttle_01, est.mag_index & 0xFF, est.flags & 0xFF,
    )  # fmt: skip
    return bytes(msg.pack(enc.mav))


def test_frames_match_pymavlink_and_decode() -> None:
    rng = np.random.default_rng(7)
    enc = HeadingEncoder(0, 191)
    enc.set_system(42)
    mav = ensure_dialect().MAVLink(None)
    for k in range(400):
        zeros = k % 5 == 0  # trailing zero bytes: the MAVLink 2 payload truncation
        est = HeadingEstimate(
            t_s=float(rng.uniform(0.0, 5e6)),
            mag_index=int(rng.integers(0, 3)),
            heading_deg=float(rng.uniform(0.0, 360.0)),
            heading_raw_deg=float(rng.uniform(0.0, 360.0)),
            theta_mgauss=rng.normal(0.0, 200.0, 3),
            bias_mgauss=np.zeros(3) if zeros else rng.normal(0.0, 50.0, 3),
            throttle_01=0.0 if zeros else float(rng.uniform()),
            flags=0 if zeros else int(rng.integers(0, 128)),
            field_raw_mgauss=np.zeros(3),
            field_cal_mgauss=np.zeros(3),
        )
        enc.mav.seq = k % 256
        expected = _pymavlink_bytes(enc, est)  # pymavlink's pack() leaves the counter alone
        got = enc.encode(est)
        assert got == expected
        assert enc.mav.seq == (k + 1) % 256  # and the encoder counts, as a link's send() does
        (msg,) = mav.parse_buffer(got)
        assert msg.get_type() == "MAGCOMP_HEADING"
        assert msg.mag_index == est.mag_index and msg.flags == est.flags
        assert abs(msg.heading - est.heading_deg) < 1e-3


def test_sequence_numbers_count_up_and_wrap() -> None:
    """A ground station counts lost packets by the MAVLink sequence number: consecutive headings carry
    consecutive numbers, wrapping at 256 (they were all 0)."""
    enc = HeadingEncoder(0, 191)
    enc.set_system(1)
    mav = ensure_dialect().MAVLink(None)
    seqs = []
    for k in range(300):
        frame = enc.encode(
            HeadingEstimate(t_s=0.01 * k, mag_index=0, heading_deg=10.0, heading_raw_deg=12.0,
                            theta_mgauss=np.zeros(3), bias_mgauss=np.zeros(3), throttle_01=0.5, flags=0,
                            field_raw_mgauss=np.zeros(3), field_cal_mgauss=np.zeros(3))
        )  # fmt: skip
        (msg,) = mav.parse_buffer(frame)
        seqs.append(msg.get_seq())
    assert seqs == [k % 256 for k in range(300)]


def test_block_writes_the_bytes_of_one_frame_at_a_time(tmp_path: Path) -> None:
    """HeadingEncoder.encode_block + TlogWriter.write_frames (the two-pass replay's writer) give the tlog of
    encode_values + write_packet byte for byte: trailing zero bytes dropped (flags, mag index, throttle and
    bias zero), sequence numbers wrapping, negative times; a time beyond a block's falls back per packet."""
    rng = np.random.default_rng(3)
    for trial in range(12):
        n = int(rng.integers(1, 400))
        t_boot = rng.uniform(-10.0, 5e6, n)
        t_s = rng.uniform(-5.0, 5e6, n)
        if trial == 11:
            t_s[n // 2] = 1e11  # 1e17 us: beyond a block's exact integers
        head, head_raw = rng.uniform(0.0, 360.0, n), rng.uniform(0.0, 360.0, n)
        theta, bias = rng.normal(0.0, 200.0, (n, 3)), rng.normal(0.0, 50.0, (n, 3))
        thr = rng.uniform(0.0, 1.0, n)
        mag, flags = rng.integers(0, 3, n), rng.integers(0, 300, n)
        zero = rng.uniform(size=n) < 0.3
        flags[zero] = 0
        mag[zero & (rng.uniform(size=n) < 0.5)] = 0
        zeros = zero & (rng.uniform(size=n) < 0.5)
        thr[zeros], bias[zeros] = 0.0, 0.0
        one, block = HeadingEncoder(0, 191), HeadingEncoder(0, 191)
        one.set_system(42)
        block.set_system(42)
        one.mav.seq = block.mav.seq = int(rng.integers(0, 256))
        w_one, w_block = TlogWriter(tmp_path / "one.tlog"), TlogWriter(tmp_path / "block.tlog")
        for k in range(n):
            w_one.write_packet(float(t_s[k]), one.encode_values(
                float(t_boot[k]), float(head[k]), float(head_raw[k]), tuple(theta[k].tolist()),
                tuple(bias[k].tolist()), float(thr[k]), int(mag[k]), int(flags[k])))  # fmt: skip
        packed = block.encode_block(t_boot, head, head_raw, theta, bias, thr, mag, flags)
        assert packed is not None
        w_block.write_frames(t_s, *packed)
        w_one.close()
        w_block.close()
        assert block.mav.seq == one.mav.seq and w_block.packets == w_one.packets == n
        assert (tmp_path / "block.tlog").read_bytes() == (tmp_path / "one.tlog").read_bytes()


def test_a_block_with_a_value_beyond_float32_is_left_to_one_frame_at_a_time() -> None:
    """encode_block returns None (counter untouched) where a value would overflow float32: struct refuses it
    a frame at a time (OverflowError), where numpy's cast would write inf into the packet."""
    n = 4
    enc = HeadingEncoder(0, 191)
    seq = enc.mav.seq
    theta = np.zeros((n, 3))
    t, zero, idx = np.arange(n, dtype=float), np.zeros(n), np.zeros(n, dtype=np.int64)

    def block() -> object:
        return enc.encode_block(t, zero, zero, theta, np.zeros((n, 3)), np.full(n, 0.5), idx, idx)

    theta[2, 1] = 1e39
    assert block() is None and enc.mav.seq == seq
    theta[2, 1] = np.inf  # inf packs the same both ways
    assert block() is not None


def test_frame_queue_writes_the_tlog_of_one_frame_at_a_time(tmp_path: Path) -> None:
    """FrameQueue (``replay --causal --emit``'s writer): queued values packed a block at a time, flushed when
    full and at the end, give the tlog of encode_values + write_packet in turn, byte for byte; a block holding
    a time beyond a block's exact integers goes one frame at a time, the sequence numbers still counting."""
    rng = np.random.default_rng(11)
    n = 300
    rows = []
    for k in range(n):
        zero = k % 7 == 0  # trailing zero bytes dropped
        t_s = 1e11 if k == 250 else float(rng.uniform(0.0, 5e4))  # 1e17 us: beyond a block's integers
        rows.append((t_s, float(rng.uniform(-1.0, 5e4)), float(rng.uniform(0.0, 360.0)),
                     float(rng.uniform(0.0, 360.0)), tuple(rng.normal(0.0, 200.0, 3).tolist()),
                     (0.0, 0.0, 0.0) if zero else tuple(rng.normal(0.0, 50.0, 3).tolist()),
                     0.0 if zero else float(rng.uniform()), int(rng.integers(0, 3)),
                     0 if zero else int(rng.integers(0, 300))))  # fmt: skip
    one, queued = HeadingEncoder(0, 191), HeadingEncoder(0, 191)
    one.mav.seq = queued.mav.seq = 200  # wraps within the log
    w_one, w_queue = TlogWriter(tmp_path / "one.tlog"), TlogWriter(tmp_path / "queue.tlog")
    queue = FrameQueue(queued, w_queue, size=64)
    for row in rows:
        w_one.write_packet(row[0], one.encode_values(*row[1:]))
        queue.add(row[0], row[1:])
    assert w_queue.packets == 256  # four full blocks written, the rest queued
    queue.flush()
    w_one.close()
    w_queue.close()
    assert queued.mav.seq == one.mav.seq and w_queue.packets == w_one.packets == n
    assert (tmp_path / "queue.tlog").read_bytes() == (tmp_path / "one.tlog").read_bytes()


def test_frame_queue_keeps_its_frames_when_packing_is_interrupted(tmp_path: Path) -> None:
    """A ^C while a block is packed (``encode_block``) loses none of the frames queued: the next flush (the
    one at close) writes them, and the tlog is byte for byte that of one frame at a time."""
    rng = np.random.default_rng(3)
    rows = [(float(t), float(t) - 1.0, float(rng.uniform(0.0, 360.0)), float(rng.uniform(0.0, 360.0)),
             (1.0, 2.0, 3.0), (0.5, 0.25, 0.125), 0.5, 0, 3) for t in np.sort(rng.uniform(1.0, 50.0, 40))]
    one, queued = HeadingEncoder(0, 191), HeadingEncoder(0, 191)
    w_one, w_queue = TlogWriter(tmp_path / "one.tlog"), TlogWriter(tmp_path / "queue.tlog")
    queue = FrameQueue(queued, w_queue, size=1000)
    for row in rows:
        w_one.write_packet(row[0], one.encode_values(*row[1:]))
        queue.add(row[0], row[1:])
    packed = queued.encode_block

    def interrupted(*args: object) -> None:
        raise KeyboardInterrupt

    queued.encode_block = interrupted  # type: ignore[method-assign,assignment]
    with pytest.raises(KeyboardInterrupt):
        queue.flush()
    queued.encode_block = packed  # type: ignore[method-assign]
    queue.flush()
    w_one.close()
    w_queue.close()
    assert (tmp_path / "queue.tlog").read_bytes() == (tmp_path / "one.tlog").read_bytes()
    assert w_queue.packets == len(rows)
