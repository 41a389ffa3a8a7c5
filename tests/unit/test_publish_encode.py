"""MAGCOMP_HEADING packed by magcomp's own frame packer is byte for byte what pymavlink packs."""

from __future__ import annotations

import numpy as np

from magcomp.adapters.dialect import ensure_dialect
from magcomp.core.types import HeadingEstimate
from magcomp.service.publish import HeadingEncoder


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
