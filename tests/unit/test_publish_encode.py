"""MAGCOMP_HEADING packed by magcomp's own frame packer is byte for byte what pymavlink packs."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from magcomp.adapters.dialect import ensure_dialect
from magcomp.core.types import HeadingEstimate
from magcomp.service.publish import Frames, HeadingEncoder, HeadingValues, TlogWriter


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


def test_block_encoder_gives_the_scalar_encoders_bytes_and_decodes() -> None:
    """encode_frames (a block at once, CRC over every row in numpy) == encode_values one by one, and
    pymavlink accepts every frame (CRC valid), with the sequence counting up and wrapping."""
    rng = np.random.default_rng(11)
    n = 700
    zeros = np.arange(n) % 4 == 0  # trailing zero bytes: payloads of several lengths in one block
    v = HeadingValues(
        t_boot_s=rng.uniform(-1.0, 5e6, n),
        heading_deg=rng.uniform(0.0, 360.0, n),
        heading_raw_deg=rng.uniform(0.0, 360.0, n),
        theta=rng.normal(0.0, 200.0, (n, 3)),
        bias=np.where(zeros[:, None], 0.0, rng.normal(0.0, 50.0, (n, 3))),
        throttle_01=np.where(zeros, 0.0, rng.uniform(0.0, 1.0, n)),
        mag_index=np.where(zeros, 0, rng.integers(0, 3, n)),
        flags=np.where(zeros, 0, rng.integers(0, 256, n)),
    )
    one, block = HeadingEncoder(0, 191), HeadingEncoder(0, 191)
    for e in (one, block):
        e.set_system(9)
        e.mav.seq = 200
    expected = [
        one.encode_values(float(v.t_boot_s[i]), float(v.heading_deg[i]), float(v.heading_raw_deg[i]),
                          (float(v.theta[i, 0]), float(v.theta[i, 1]), float(v.theta[i, 2])),
                          (float(v.bias[i, 0]), float(v.bias[i, 1]), float(v.bias[i, 2])),
                          float(v.throttle_01[i]), int(v.mag_index[i]), int(v.flags[i]))
        for i in range(n)
    ]  # fmt: skip
    frames = block.encode_frames(v)
    got = [bytes(frames.data[i, : frames.length[i]]) for i in range(n)]
    assert len(set(frames.length.tolist())) > 1
    assert got == expected
    assert block.mav.seq == one.mav.seq == (200 + n) % 256
    mav = ensure_dialect().MAVLink(None)
    msgs = mav.parse_buffer(b"".join(got))
    assert len(msgs) == n and all(m.get_type() == "MAGCOMP_HEADING" for m in msgs)  # bad CRC -> BAD_DATA
    seqs = [m.get_seq() for m in msgs]
    assert seqs[0] == 200 and all((b - a) % 256 == 1 for a, b in itertools.pairwise(seqs))
    assert 0 in seqs  # wrapped


def test_block_tlog_records_equal_one_by_one(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 50
    t = np.sort(rng.uniform(0.0, 100.0, n))
    frames = [bytes(rng.integers(1, 255, int(k), dtype=np.uint8)) for k in rng.integers(12, 50, n)]
    width = max(len(f) for f in frames)
    data = np.zeros((n, width), dtype=np.uint8)
    for i, f in enumerate(frames):
        data[i, : len(f)] = np.frombuffer(f, dtype=np.uint8)
    a, b = TlogWriter(tmp_path / "a.tlog"), TlogWriter(tmp_path / "b.tlog")
    for ti, f in zip(t.tolist(), frames, strict=True):
        a.write_packet(ti, f)
    b.write_frames(t, Frames(data, np.array([len(f) for f in frames], dtype=np.int64)))
    a.close()
    b.close()
    assert a.packets == b.packets == n
    assert (tmp_path / "a.tlog").read_bytes() == (tmp_path / "b.tlog").read_bytes()
