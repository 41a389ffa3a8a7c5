"""The pure parts the in-flight stage hands its decisions to (issue 24): late matching, the gyro's yaw frame,
the apply decision and the autopilot's motor-compensation parameters."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magcomp.core.autopilot_params import (
    MOTCT_CURRENT,
    motor_comp_known_off,
    motor_comp_type,
    motor_comp_vector,
    per_motor_comp,
)
from magcomp.core.inflight import GyroYaw, InflightSolution
from magcomp.core.inflight.apply import MAX_APPLY_HEADING_SIGMA_DEG, YawSpan, apply_decision
from magcomp.core.inflight.matching import MAX_PAIR_S, LateMatcher
from magcomp.core.inflight.rows import augmented
from magcomp.core.inflight.yawframe import GyroYawFrame, yaw_turned
from magcomp.core.rotations import dcm_from_euler


def _yaw_of(r: np.ndarray) -> float:
    return math.atan2(float(r[1, 0]), float(r[0, 0]))


def test_a_late_sample_waits_for_both_sources_and_gets_them_interpolated() -> None:
    m: LateMatcher[str] = LateMatcher()
    r0, r1 = dcm_from_euler(0.0, 0.0, 0.0), dcm_from_euler(0.0, 0.0, 0.4)
    # the field at 1.0 s, its attitude and throttle still of 0.5 s: it waits
    assert m.push(1.0, "a", r0, 0.5, 0.2, 0.5) == []
    assert m.waiting
    # the attitude passes 1.0 s, the throttle not yet: still waiting
    assert m.push(1.2, "b", r1, 1.5, 0.2, 0.9) == []
    # both past 1.0 s: "a" matched at its own time, midway on the geodesic, on the throttle line
    out = m.push(1.4, "c", r1, 1.5, 0.6, 1.5)
    assert [o[1] for o in out] == ["a", "b", "c"]
    t, _, r_at, thr_at = out[0]
    assert t == 1.0
    assert _yaw_of(r_at) == pytest.approx(0.2, abs=1e-12)
    assert thr_at == pytest.approx(0.2 + 0.4 * (1.0 - 0.9) / (1.5 - 0.9))  # between the throttles around it
    assert not m.waiting


def test_a_sample_whose_sources_stopped_is_dropped_not_held() -> None:
    m: LateMatcher[int] = LateMatcher()
    r = dcm_from_euler(0.0, 0.0, 0.0)
    assert m.push(1.0, 1, r, 0.9, 0.3, 0.9) == []
    # the sources never come past 1.0 s; a sample MAX_PAIR_S later releases the first one unmatched
    out = m.push(1.0 + MAX_PAIR_S + 0.5, 2, r, 0.9, 0.3, 0.9)
    assert [o[1] for o in out] == []
    m.clear()
    assert not m.waiting


def _turned(r: np.ndarray, turn: tuple[float, float] | None) -> np.ndarray:
    return r if turn is None else yaw_turned(r[None], np.array([turn[0]]), np.array([turn[1]]))[0]


def test_the_gyro_frame_carries_the_gyro_yaw_from_the_autopilot_yaw_at_the_chain_start() -> None:
    f = GyroYawFrame()
    r_ap = dcm_from_euler(0.1, -0.05, 1.0)
    turn, restart = f.turn(r_ap, GyroYaw(3, 5.0))
    assert restart and f.on
    assert _yaw_of(_turned(r_ap, turn)) == pytest.approx(1.0, abs=1e-12)  # offset to the autopilot's yaw
    # the gyro turns by 0.3 rad while the autopilot's yaw (following a compass) turns by 0.5
    r_ap2 = dcm_from_euler(0.1, -0.05, 1.5)
    turn, restart = f.turn(r_ap2, GyroYaw(3, 5.3))
    assert not restart
    r = _turned(r_ap2, turn)
    assert _yaw_of(r) == pytest.approx(1.3, abs=1e-12)
    assert f.ap_yaw_dev == pytest.approx(0.2, abs=1e-12)  # the autopilot's yaw minus the gyro frame's
    # roll and pitch are the autopilot's
    np.testing.assert_allclose(r[2], r_ap2[2], atol=1e-12)
    # a new chain, or no gyro yaw: a new window sequence
    assert f.turn(r_ap, GyroYaw(4, 0.0))[1]
    assert f.turn(r_ap, None) == (None, True)
    assert f.turn(r_ap, None)[1] is False


def test_a_stack_of_yaw_turns_is_each_attitudes_own_product() -> None:
    """``yaw_turned`` on N attitudes gives, bit for bit, each one's own 3 x 3 product ``Rz(a) R``, and the
    yaw span of attitudes held with their turns (read now and then) is that of the turned attitudes."""
    rng = np.random.default_rng(4)
    n = 300
    angles = np.column_stack([rng.uniform(-0.4, 0.4, (n, 2)), rng.uniform(-math.pi, math.pi, n)])
    rs = np.array([dcm_from_euler(*e) for e in angles])
    a = np.cumsum(rng.normal(0.0, 0.3, n))
    c, s = np.cos(a), np.sin(a)
    rz = [np.array([[c[i], -s[i], 0.0], [s[i], c[i], 0.0], [0.0, 0.0, 1.0]]) for i in range(n)]
    each = np.array([rz[i] @ rs[i] for i in range(n)])
    assert np.array_equal(yaw_turned(rs, c, s), each)
    held, turned = YawSpan(), YawSpan()
    spans = []
    for i in range(n):
        held.track(rs[i], (float(c[i]), float(s[i])))
        turned.track(each[i])
        if i % 7 == 0 or i > n - 20:  # read one sample at a time at the end, a block at a time before
            spans.append((held.span_deg, turned.span_deg))
    assert all(h == t for h, t in spans)
    assert turned.span_deg > 90.0  # the attitudes turned through more than a quarter turn


def _solution(d: tuple[float, float, float], sigma_deg: float, split_deg: float = 0.0) -> InflightSolution:
    z3 = np.zeros(3)
    return InflightSolution(np.eye(3), np.asarray(d), z3, np.zeros((0, 3)), z3, sigma_deg, 3.0, 1000,
                            heading_split_deg=split_deg)  # fmt: skip


FIELD = (200.0, 0.0, 400.0)


def test_the_apply_decision_wants_a_real_change_a_turn_and_an_earthly_field() -> None:
    big = _solution((0.0, 100.0, 0.0), 5.0)  # turns the heading by ~27 deg with a 5 deg sigma
    ok, strength = apply_decision(big, "relative", FIELD, (0.0, 0.0, 0.0), 2.0, 120.0, True)
    assert ok and strength == pytest.approx(math.sqrt(200.0**2 + 100.0**2 + 400.0**2))
    assert not apply_decision(big, "relative", FIELD, (0.0, 0.0, 0.0), 2.0, 60.0, True)[0]  # not turned
    assert apply_decision(big, "absolute", FIELD, (0.0, 0.0, 0.0), 2.0, 0.0, True)[0]  # needs no turn
    assert not apply_decision(big, "relative", FIELD, (0.0, 0.0, 0.0), 2.0, 120.0, False)[0]  # unchecked
    small = _solution((0.0, 5.0, 0.0), 5.0)  # a 1.4 deg change cannot justify a 5 deg sigma
    assert not apply_decision(small, "relative", FIELD, (0.0, 0.0, 0.0), 2.0, 120.0, True)[0]
    wide = _solution((0.0, 1000.0, 0.0), MAX_APPLY_HEADING_SIGMA_DEG + 1.0)  # a huge turn, a huge sigma
    assert not apply_decision(wide, "absolute", FIELD, (0.0, 0.0, 0.0), 2.0, 0.0, True)[0]
    stuck = _solution(FIELD, 0.5)  # corrects to ~0 mgauss: a stuck compass
    ok, strength = apply_decision(stuck, "absolute", FIELD, (0.0, 0.0, 0.0), 2.0, 0.0, True)
    assert not ok and strength < 1.0
    # the absolute form leaves the split-half term out of its sigma
    split = _solution((0.0, 5.0, 0.0), 2.5, split_deg=2.0)  # sqrt(2.5^2 - 2^2) = 1.5 < 2
    assert apply_decision(split, "absolute", FIELD, (0.0, 0.0, 0.0), 2.0, 0.0, True)[0]
    assert not apply_decision(split, "relative", FIELD, (0.0, 0.0, 0.0), 2.0, 120.0, True)[0]


def test_the_yaw_span_unwraps_through_north() -> None:
    span = YawSpan()
    for deg in range(170, 400, 10):  # through +-180
        span.track(dcm_from_euler(0.0, 0.0, math.radians(deg)))
    assert span.span_deg == pytest.approx(220.0)


def test_ardupilot_motor_compensation_parameters() -> None:
    assert motor_comp_type({}) == 0 and motor_comp_type({"COMPASS_MOTCT": math.nan}) == 0
    assert motor_comp_type({"COMPASS_MOTCT": 2.0}) == MOTCT_CURRENT
    p = {"COMPASS_MOT2_X": 1.0, "COMPASS_MOT2_Y": 2.0, "COMPASS_MOT2_Z": 3.0, "COMPASS_MOT_X": 9.0}
    assert motor_comp_vector(p, 1) == (1.0, 2.0, 3.0)
    assert motor_comp_vector(p, 0) is None  # Y and Z unknown
    assert per_motor_comp({"COMPASS_PMOT_EN": 1.0}, 0) and not per_motor_comp({"COMPASS_PMOT_EN": 1.0}, 1)
    assert not motor_comp_known_off({}, 0)  # nothing logged: not known
    assert motor_comp_known_off({"COMPASS_MOTCT": 0.0}, 0)
    assert not motor_comp_known_off({"COMPASS_MOTCT": 0.0, "COMPASS_PMOT_EN": 1.0}, 0)
    assert motor_comp_known_off({"COMPASS_MOTCT": 0.0, "COMPASS_PMOT_EN": 1.0}, 1)


def test_the_linearisation_point_of_a_block_is_each_samples() -> None:
    """``InflightEstimator.uncalibrated`` of N samples at once gives each sample's ``y - d - x theta`` (with
    the collective regressor alone and with four motors' too)."""
    from magcomp.core.inflight import InflightEstimator

    rng = np.random.default_rng(7)
    for n_motors in (0, 4):
        est = InflightEstimator("relative", n_motors)
        k = est._k
        est._theta = rng.normal(0.0, 300.0, size=est._theta.shape)
        y = rng.normal(0.0, 500.0, size=(200, 3))
        x = rng.uniform(0.0, 1.0, size=(200, 1 + n_motors))
        th = est._theta[k + 3 :].reshape(-1, 3)
        want = np.array([y[i] - est._theta[k : k + 3] - x[i, : th.shape[0]] @ th for i in range(200)])
        np.testing.assert_allclose(est.uncalibrated(y, x), want, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(est.uncalibrated(y[5], x[5]), want[5], rtol=1e-12, atol=1e-9)


def test_the_open_window_forgets_a_nonzero_h_ee_when_its_sums_clear() -> None:
    """The open window remembers that its nuisance information H_ee is nonzero until its sums clear: a
    window of rows whose nuisance columns are all zero after a cleared one has no nuisance estimate."""
    from magcomp.core.inflight.window import OpenWindow

    rng = np.random.default_rng(3)
    w = OpenWindow(4, prior_sd=1.0)
    p = np.zeros(4)
    w.key = "a"
    for _ in range(5):
        a = augmented(rng.normal(size=(3, 4)), rng.normal(size=3), rng.normal(size=(3, 2)), None)
        w.add_block(a[None], 4)
    assert w.nuisance(1, False, p, 0.0, 10.0) is not None
    w.clear()
    w.n_rows = 0
    w.key = "b"
    for _ in range(5):
        a = augmented(rng.normal(size=(3, 4)), rng.normal(size=3), np.zeros((3, 2)), None)
        w.add_block(a[None], 4)
    assert w.nuisance(2, False, p, 0.0, 10.0) is None
