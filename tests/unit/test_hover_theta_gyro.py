"""Theta against the autopilot's calibration with the yaw from the gyro (core/hover_theta.py GyroYawNormal).

A hover whose compass carries eq. (11)'s bias, flown by an autopilot whose yaw is fused from that compass
(it follows the compass's heading at FOLLOW_PER_S, like a development log's 0.045 /s): fitted against that
yaw, theta comes out short (the yaw has taken part of the bias for attitude); fitted with the gyro's
integrated yaw (its bias drifting), theta is recovered. The same equations solved on the whole log at once
and block by block give the same theta (one model, two solvers)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.hover_theta import (
    GyroYawNormal,
    HoverGroups,
    HoverNormal,
    HoverTheta,
    body_from_nav,
    fit_hover_theta,
    fit_hover_theta_gyro,
    grouped_jackknife,
    with_block_sigma,
)

THETA = np.array([180.0, -120.0, 260.0])  # mgauss per throttle^2
EARTH_NED = np.array([210.0, -30.0, 420.0])  # mgauss
FOLLOW_PER_S = 0.05
DT_S = 0.1


def _hover(seed: int, n: int = 6000, follow_per_s: float = FOLLOW_PER_S) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT_S
    w = 2 * math.pi * t
    yaw = np.radians(50.0) * np.sin(w / 170.0) + np.radians(20.0) * np.sin(w / 47.0)
    roll = np.radians(2.0) * np.sin(2 * math.pi * t / 13.0) + rng.normal(0.0, 0.004, n)
    pitch = np.radians(2.0) * np.cos(2 * math.pi * t / 17.0) + rng.normal(0.0, 0.004, n)
    # the throttle swings over seconds about a hover at 0.5
    thr = 0.5 + 0.12 * np.sin(2 * math.pi * t / 9.0) + 0.06 * np.sin(2 * math.pi * t / 3.7 + 1.0)
    r_bn = body_from_nav(roll, pitch, yaw)
    field = np.einsum("nij,j->ni", r_bn, EARTH_NED) + np.outer(thr**2, THETA) + rng.normal(0.0, 2.0, (n, 3))
    psi = np.radians(heading_from_trig_deg(field[:, 0], field[:, 1], field[:, 2], np.cos(roll), np.sin(roll),
                                           np.cos(pitch), np.sin(pitch)))  # fmt: skip
    decl = math.atan2(EARTH_NED[1], EARTH_NED[0])
    ap = np.empty(n)  # the autopilot's yaw: the gyro's rate, pulled to this compass's heading
    ap[0] = psi[0] + decl
    rate = np.gradient(yaw, DT_S)
    for i in range(1, n):
        err = math.remainder(psi[i - 1] + decl - ap[i - 1], 2 * math.pi)
        ap[i] = ap[i - 1] + (rate[i - 1] + follow_per_s * err) * DT_S
    gyro = yaw + math.radians(0.01) * t + rng.normal(0.0, 0.002, n)  # a bias drift of 0.01 deg/s
    return {"t": t, "field": field, "roll": roll, "pitch": pitch, "ap": ap, "gyro": gyro, "thr": thr}


def test_theta_fitted_with_the_gyros_yaw_where_the_autopilots_follows_the_compass() -> None:
    for seed in (1, 2):
        h = _hover(seed)
        ap_fit = fit_hover_theta(h["field"], h["roll"], h["pitch"], h["ap"], h["thr"])
        gy_fit = fit_hover_theta_gyro(h["field"], h["roll"], h["pitch"], h["gyro"], np.zeros_like(h["t"]),
                                      h["t"], h["thr"])  # fmt: skip
        assert ap_fit is not None and gy_fit is not None
        assert gy_fit.yaw_source == "gyro" and ap_fit.yaw_source == "autopilot"
        err_gy = float(np.linalg.norm(gy_fit.theta_mgauss - THETA))
        err_ap = float(np.linalg.norm(ap_fit.theta_mgauss - THETA))
        # recovered within 10 % of |theta| and within 4 of its stated sigmas
        assert err_gy < 0.1 * float(np.linalg.norm(THETA)), (seed, gy_fit.theta_mgauss)
        sigma = float(np.linalg.norm(gy_fit.theta_sigma_mgauss))
        assert err_gy < 4.0 * sigma, (seed, gy_fit.theta_sigma_mgauss)
        # the autopilot's yaw, following the compass, takes part of the bias for attitude
        assert err_ap > 3.0 * err_gy, (seed, ap_fit.theta_mgauss, gy_fit.theta_mgauss)


def test_block_by_block_and_whole_log_solve_the_same_equations() -> None:
    h = _hover(3)
    epoch = (h["t"] > 400.0).astype(float)  # a restart of the gyro's integral
    cols = (h["field"], h["roll"], h["pitch"], h["gyro"], epoch, h["t"], h["thr"])
    whole = GyroYawNormal()
    whole.add(*cols)
    blocks = GyroYawNormal()
    for lo in range(0, h["t"].size, 137):  # blocks that straddle the pieces
        blocks.add(*(c[lo:lo + 137] for c in cols))
    for sd in (None, 60.0):
        a, b = whole.fit(sd), blocks.fit(sd)
        assert a is not None and b is not None
        np.testing.assert_allclose(a.theta_mgauss, b.theta_mgauss, rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(a.theta_sigma_mgauss, b.theta_sigma_mgauss, rtol=1e-9, atol=1e-6)
    assert whole.pieces == blocks.pieces


def test_a_constant_throttle_gives_no_theta() -> None:
    h = _hover(4)
    thr = np.full_like(h["thr"], 0.5)
    got = fit_hover_theta_gyro(h["field"], h["roll"], h["pitch"], h["gyro"], np.zeros_like(thr), h["t"], thr)
    assert got is None


@pytest.mark.parametrize(
    ("seed", "follow_per_s", "source"), [(7, FOLLOW_PER_S, "gyro"), (8, 0.0, "autopilot")]
)
def test_the_two_pass_hover_candidate_takes_the_yaw_that_does_not_follow_the_compass(
        seed: int, follow_per_s: float, source: str) -> None:  # fmt: skip
    """service/final_pass.py ``hover_candidate`` on the hover's columns (the gyro logged at 10 Hz). Where the
    autopilot's yaw follows the compass, the form published is fitted with the gyro's yaw; where it is the
    true yaw (its measured follow rate below one over the flight's span), with the autopilot's, whose one
    Earth field over the whole log makes the stronger fit. Either passes the held-out check with theta within
    10 %."""
    from magcomp.service.final_pass import hover_candidate

    h = _hover(seed, follow_per_s=follow_per_s)
    n = h["t"].size
    cols = np.column_stack((h["t"], h["field"], h["roll"], h["pitch"], h["ap"], h["thr"], h["gyro"],
                            np.zeros(n), np.full(n, DT_S)))  # fmt: skip
    got = hover_candidate(cols)
    assert got is not None
    fit, chk = got
    assert chk.applies and fit.yaw_source == source, (chk.reason, fit.yaw_source)
    err = float(np.linalg.norm(fit.theta_mgauss - THETA))
    assert err < 0.1 * float(np.linalg.norm(THETA)), fit.theta_mgauss


def test_a_piece_of_zero_field_still_closes() -> None:
    """A piece is closed by its samples, not by its field's energy: a stretch of exactly zero field (a
    sensor that reads nothing) is its own piece, and theta is what the same log gives with a field of
    1e-100."""
    h = _hover(3)
    fits = []
    for tiny in (0.0, 1e-100):
        field = h["field"].copy()
        field[:600] = tiny
        acc = GyroYawNormal()
        acc.add(field, h["roll"], h["pitch"], h["gyro"], np.zeros_like(h["t"]), h["t"], h["thr"])
        fits.append((acc.pieces, acc.fit()))
    (p0, f0), (p1, f1) = fits
    assert f0 is not None and f1 is not None and p0 == p1
    np.testing.assert_allclose(f0.theta_mgauss, f1.theta_mgauss, rtol=1e-9, atol=1e-6)


def _ar1(rng: np.random.Generator, n: int, tau_s: float, sd: float) -> np.ndarray:
    """(n, 3) AR(1) noise of correlation time ``tau_s`` and standard deviation ``sd``, sampled every DT_S."""
    a = math.exp(-DT_S / tau_s)
    e = rng.normal(0.0, sd * math.sqrt(1.0 - a * a), (n, 3))
    out = np.empty((n, 3))
    out[0] = rng.normal(0.0, sd, 3)
    for i in range(1, n):
        out[i] = a * out[i - 1] + e[i]
    return out


def _gyro_fit_on(field: np.ndarray, h: dict[str, np.ndarray]) -> Callable[[np.ndarray], HoverTheta | None]:
    epoch = np.zeros_like(h["t"])

    def fit_on(m: np.ndarray) -> HoverTheta | None:
        return fit_hover_theta_gyro(field[m], h["roll"][m], h["pitch"][m], h["gyro"][m], epoch[m], h["t"][m],
                                    h["thr"][m])  # fmt: skip

    return fit_on


def test_thetas_sigma_from_the_block_jackknife_covers_the_error_under_correlated_residuals() -> None:
    """A field disturbance correlated over seconds (an AR(1) of 6 mgauss and 4 s, as a wandering yaw
    reference or a field that changes along the path leaves it) leaks into theta through the throttle's
    swings of a few seconds. The fit's own covariance takes the residuals as white and states too small a
    sigma; the delete-one-block jackknife over 30-50 s blocks (``with_block_sigma``) covers the realised
    error at about its stated level. Under white noise it states about the fit's own sigma (not a larger
    one)."""
    z_white: list[float] = []
    z_jk: list[float] = []
    ratio_white_noise: list[float] = []
    for seed in range(20):
        h = _hover(100 + seed, n=6000, follow_per_s=0.0)
        for coloured in (True, False):
            field = h["field"] + (_ar1(np.random.default_rng(1000 + seed), h["t"].size, 4.0, 6.0)
                                  if coloured else 0.0)  # fmt: skip
            fit_on = _gyro_fit_on(field, h)
            fit = fit_on(np.ones(h["t"].size, dtype=bool))
            assert fit is not None
            jk = with_block_sigma(fit, h["t"], fit_on)
            assert jk.sigma_blocks == 12 and not jk.sigma_lower_bound  # 600 s: 12 blocks of 50 s
            if coloured:
                err = fit.theta_mgauss - THETA
                z_white.extend(np.abs(err) / fit.theta_sigma_mgauss)
                z_jk.extend(np.abs(err) / jk.theta_sigma_mgauss)
            else:
                ratio_white_noise.extend(jk.theta_sigma_mgauss / fit.theta_sigma_mgauss)
    cover_white = float(np.mean(np.asarray(z_white) < 2.0))
    cover_jk = float(np.mean(np.asarray(z_jk) < 2.0))
    # 60 axis-errors at a 2-sigma (95 %) level: the white sigma covers far fewer, the jackknife's about that
    assert cover_white < 0.75, cover_white
    assert cover_jk >= 0.85, (cover_jk, cover_white)
    # white noise: the larger of the two is about the fit's own (measured median 1.03 with the max taken)
    assert 1.0 <= float(np.median(ratio_white_noise)) < 1.4, np.median(ratio_white_noise)


def test_a_block_left_out_that_holds_the_throttles_change_makes_the_sigma_a_lower_bound() -> None:
    """Where the throttle swings only in the first 50 s, leaving that stretch out leaves nothing to fit
    theta on: the jackknife over the other blocks cannot measure theta's spread, and the sigma says so."""
    h = _hover(5, n=6000, follow_per_s=0.0)
    thr = np.where(h["t"] < 50.0, h["thr"], 0.5)
    field = h["field"] + np.outer(thr**2 - h["thr"] ** 2, THETA)  # eq. (11)'s bias at the new throttle
    h = h | {"thr": thr}
    fit_on = _gyro_fit_on(field, h)
    fit = fit_on(np.ones(h["t"].size, dtype=bool))
    assert fit is not None
    jk = with_block_sigma(fit, h["t"], fit_on)
    assert jk.sigma_lower_bound and jk.sigma_blocks == 11, (jk.sigma_blocks, jk.sigma_lower_bound)


def _live_groups(field: np.ndarray, h: dict[str, np.ndarray]) -> tuple[HoverNormal, HoverGroups]:
    """The normal equations as the live path builds them: blocks of 97 samples, each into the whole and into
    its stretch of time (HoverGroups)."""
    total, groups = HoverNormal(), HoverGroups()
    for lo in range(0, h["t"].size, 97):
        sl = slice(lo, lo + 97)
        part = HoverNormal()
        part.add(field[sl], h["roll"][sl], h["pitch"][sl], h["ap"][sl], h["thr"][sl])
        total.merge(part)
        groups.add(part, float(h["t"][sl][-1]))
    return total, groups


def test_the_live_fits_jackknife_leaves_each_block_out_by_subtraction_and_covers_the_error() -> None:
    """The live hover fit (service/heading.py HoverShadow) keeps its normal equations per stretch of about
    10 s as well (HoverGroups); a stretch left out by subtraction (``HoverNormal.without``) is the fit on the
    other samples, state and all, and the jackknife over those stretches merged into blocks
    (``grouped_jackknife``) covers theta's error under the same correlated disturbance as above, where the
    fit's own sigma does not; under white noise it states about the fit's own."""
    z_white: list[float] = []
    z_jk: list[float] = []
    ratio_white_noise: list[float] = []
    for seed in range(20):
        h = _hover(200 + seed, n=6000, follow_per_s=0.0)  # the autopilot's yaw: the true one
        for coloured in (True, False):
            field = h["field"] + (_ar1(np.random.default_rng(2000 + seed), h["t"].size, 4.0, 6.0)
                                  if coloured else 0.0)  # fmt: skip
            total, groups = _live_groups(field, h)
            fit = total.fit()
            assert fit is not None
            if seed == 0 and coloured:  # one stretch left out by subtraction: the fit on the other samples
                n0 = sum(g.n for g in groups.groups[:13])
                keep = np.ones(h["t"].size, dtype=bool)
                keep[n0:n0 + groups.groups[13].n] = False
                direct = fit_hover_theta(field[keep], h["roll"][keep], h["pitch"][keep], h["ap"][keep],
                                         h["thr"][keep])  # fmt: skip
                left = total.without(groups.groups[13]).fit()
                assert direct is not None and left is not None and left.n == direct.n
                for a, b in ((left.theta_mgauss, direct.theta_mgauss),
                             (left.theta_sigma_mgauss, direct.theta_sigma_mgauss),
                             (left.residual_rms_mgauss, direct.residual_rms_mgauss)):  # fmt: skip
                    np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-5)
            jk = grouped_jackknife(total, groups, fit, None)
            assert jk.sigma_blocks == 12 and not jk.sigma_lower_bound  # 600 s: 12 blocks
            if coloured:
                err = fit.theta_mgauss - THETA
                z_white.extend(np.abs(err) / fit.theta_sigma_mgauss)
                z_jk.extend(np.abs(err) / jk.theta_sigma_mgauss)
            else:
                ratio_white_noise.extend(jk.theta_sigma_mgauss / fit.theta_sigma_mgauss)
    cover_white = float(np.mean(np.asarray(z_white) < 2.0))
    cover_jk = float(np.mean(np.asarray(z_jk) < 2.0))
    assert cover_white < 0.75, cover_white
    assert cover_jk >= 0.85, (cover_jk, cover_white)
    assert 1.0 <= float(np.median(ratio_white_noise)) < 1.4, np.median(ratio_white_noise)


def test_the_live_groups_stay_bounded_on_a_long_flight() -> None:
    """A daemon hovering for hours keeps at most MAX_LIVE_GROUPS stretches (adjacent ones merged), their
    samples and seconds all kept."""
    from magcomp.core.hover_theta import MAX_LIVE_GROUPS

    groups, part = HoverGroups(), HoverNormal()
    part.add(np.ones((5, 3)), np.zeros(5), np.zeros(5), np.zeros(5), np.full(5, 0.5))
    for k in range(2000):
        groups.add(part, 5.0 * k)
    assert len(groups.groups) <= MAX_LIVE_GROUPS
    assert sum(g.n for g in groups.groups) == 2000 * 5
    assert abs(sum(groups.seconds) - 5.0 * 1999) < 1e-6
