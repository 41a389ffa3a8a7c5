"""diagnose does each piece of work once and skips what cannot change a decision (issue 28: CPU per fleet
log), with the same numbers as doing it every time. Seeded synthetic logs
(tests/unit/test_diagnosis_model.py).

Oracles: the straightforward computation each shortcut replaces (a per-sample loop, a 3x3 product per sample,
a regression per lag), and the selection rule itself (a comparison that fails the BIC test is not significant
whatever its held-out score).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import magcomp.diagnosis.attitude as attitude
from magcomp.core.rotations import down_b_from_quat, quat_step_body_rate
from magcomp.core.types import LogData
from magcomp.diagnosis import engine
from magcomp.diagnosis.gyro_heading import turn_heading
from magcomp.diagnosis.inputs import compass_data, log_attitude, signals_at
from magcomp.diagnosis.model import fit_model
from magcomp.diagnosis.selection import CVScore, SelectionParams, compare, cv_score, folds_for
from magcomp.diagnosis.suspects import relate
from tests.unit.test_diagnosis_model import synth_log


def _two_compasses(log: LogData) -> LogData:
    """``log`` with a second compass: the first one's samples 3 mgauss off."""
    m = log.mag[0]
    return replace(log, mag={0: m, 1: replace(m, values=m.values + 3.0)})


def test_the_gyro_integral_is_built_once_per_log(monkeypatch: pytest.MonkeyPatch) -> None:
    log = _two_compasses(synth_log(11, duration_s=30.0)[0])
    calls: list[int] = []
    real = attitude._propagate  # the integral behind propagate_attitude and attitude_source's passes

    def counting(*args: object, **kw: object) -> tuple[np.ndarray, tuple[float, float, float]]:
        calls.append(1)
        return real(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(attitude, "_propagate", counting)
    d = engine.diagnose(log)
    assert [c.index for c in d.compasses] == [0, 1]
    assert len(calls) == 1  # one integral for both compasses (it was one per compass)
    # and the rotation each compass gets is the one it would get on its own
    shared = log_attitude(log)
    for idx in (0, 1):
        alone = compass_data(log, idx)
        with_shared = compass_data(log, idx, attitude=lambda: shared)
        assert np.array_equal(alone.r_nb, with_shared.r_nb) and alone.attitude_source == "gyro+tilt(attitude)"


def _filter_row_by_row(
    t: np.ndarray, gyro: np.ndarray, ref: np.ndarray, q0: np.ndarray, bias: tuple[float, float, float]
) -> tuple[np.ndarray, tuple[float, float, float]]:
    """One pass of the tilt filter written sample by sample on numpy rows, with core's quaternion step (the
    oracle)."""
    p = attitude.TiltFilterParams()
    w, x, y, z = (float(v) for v in q0)
    bx, by, bz = bias
    dts = np.diff(t, prepend=t[0])
    med = float(np.median(dts[1:]))
    out = np.empty((t.shape[0], 4))
    for k in range(t.shape[0]):
        dt = float(dts[k])
        if not 0.0 < dt < 10.0 * med:
            dt = 0.0 if k == 0 else med
        dx, dy, dz = down_b_from_quat((w, x, y, z))
        rx, ry, rz = (float(v) for v in ref[max(k - 1, 0)])
        ex, ey, ez = dy * rz - dz * ry, dz * rx - dx * rz, dx * ry - dy * rx
        bx, by, bz = bx + p.ki_rad_s2 * ex * dt, by + p.ki_rad_s2 * ey * dt, bz + p.ki_rad_s2 * ez * dt
        gk, gp = gyro[k], gyro[max(k - 1, 0)]
        omega = [0.5 * (float(gk[j]) + float(gp[j])) - b - p.kp_rad_s * e for j, b, e in
                 zip(range(3), (bx, by, bz), (ex, ey, ez), strict=True)]  # fmt: skip
        w, x, y, z = quat_step_body_rate((w, x, y, z), omega, dt)  # eq. (18), core's step
        out[k] = (w, x, y, z)
    return out, (bx, by, bz)


@pytest.mark.parametrize("block", [7, 1 << 16])
def test_the_tilt_filter_on_flat_lists_is_the_row_by_row_filter(
    monkeypatch: pytest.MonkeyPatch, block: int
) -> None:
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.015, 0.025, 400))
    t[150] = t[149]  # a repeated stamp and a gap
    t[250:] += 1.0
    gyro = rng.normal(0.0, 0.6, (400, 3))
    ref = rng.normal(0.0, 0.2, (400, 3)) + np.array([0.0, 0.0, 1.0])
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    q0 = np.array([0.9, 0.1, -0.2, 0.3]) / np.linalg.norm([0.9, 0.1, -0.2, 0.3])
    monkeypatch.setattr(attitude, "_ROW_BLOCK", block)
    got = np.empty((400, 4))
    bias = attitude._tilt_pass(t, gyro, ref, q0, attitude.TiltFilterParams(), (0.01, -0.02, 0.0), got)
    want, want_bias = _filter_row_by_row(t, gyro, ref, q0, (0.01, -0.02, 0.0))
    # the filter's closed form and core's step differ in the last bits only
    np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(bias, want_bias, rtol=0.0, atol=1e-12)


def test_turn_heading_is_the_rotation_product() -> None:
    rng = np.random.default_rng(2)
    q = rng.normal(size=(300, 4))
    r = np.stack([attitude.dcm_from_quat(qi / np.linalg.norm(qi)) for qi in q])
    psi = rng.normal(0.0, 0.3, 300)
    c, s = np.cos(psi), np.sin(psi)
    rz = np.zeros((300, 3, 3))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
    assert np.array_equal(turn_heading(r, psi), np.einsum("nij,njk->nik", rz, r))


def test_relate_is_one_regression_per_signal_and_lag() -> None:
    log, _, _ = synth_log(4, duration_s=30.0, effects={"current_lag": 0.5})
    data = compass_data(log, 0)
    fit = fit_model(data, ())
    sig = signals_at(data, log)
    got = relate(data.t_s, fit.residual_mgauss, sig)
    res = fit.residual_mgauss
    lags = np.arange(-2.0, 2.0 + 1e-9, 0.1)
    for rel in got:
        ts, vs = sig[rel.signal]
        r2s = []
        for lag in lags:  # R^2 of the residual on the lagged signal plus a constant, per lag
            s = np.interp(data.t_s - lag, ts, vs)
            x = np.column_stack([np.ones_like(s), s])
            beta, *_ = np.linalg.lstsq(x, res, rcond=None)
            r2s.append(1.0 - np.sum((res - x @ beta) ** 2) / np.sum((res - res.mean(axis=0)) ** 2))
        best = int(np.argmax(r2s))
        assert rel.r2 == pytest.approx(r2s[best], abs=1e-9)
        assert abs(rel.lag_s - round(float(lags[best]), 3)) <= 0.1 + 1e-9  # near-ties go to the smaller |lag|


def test_a_comparison_that_fails_the_bic_test_runs_no_held_out_fit() -> None:
    p = SelectionParams()

    def never() -> CVScore:
        raise AssertionError("the held-out score was asked for")

    # clean log: a free exponent explains nothing
    log, _, _ = synth_log(6, duration_s=30.0)
    data = compass_data(log, 0)
    base = fit_model(data, ())
    ext = fit_model(data, ("throttle_exponent",), start=base)
    folds = folds_for(data, base, p)
    c = compare(data, base, ext, never, p, folds)
    assert not c.significant and c.delta_bic > -p.min_delta_bic
    assert c.cv_extended is None and math.isnan(c.cv_gain) and math.isnan(c.cv_t)
    # a real exponent: the held-out test runs, asked once, with the same result as given the score itself
    log, _, _ = synth_log(6, duration_s=30.0, effects={"throttle_exponent": 3.0})
    data = compass_data(log, 0)
    base = fit_model(data, ())
    ext = fit_model(data, ("throttle_exponent",), start=base)
    folds = folds_for(data, base, p)
    score = cv_score(data, base, p, folds)
    asked: list[int] = []

    def once() -> CVScore:
        asked.append(1)
        return score

    lazy, eager = compare(data, base, ext, once, p, folds), compare(data, base, ext, score, p, folds)
    assert asked == [1] and lazy.significant and eager.significant
    assert (lazy.cv_gain, lazy.cv_t, lazy.delta_bic) == (eager.cv_gain, eager.cv_t, eager.delta_bic)


def test_a_tlog_gives_no_event_so_it_is_not_read_for_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A tlog's STATUSTEXT has no boot time, and no other event message of a tlog has one to place it by:
    pymavlink's pass over the file found rows and kept none. diagnose no longer makes that pass."""
    import struct

    from pymavlink.dialects.v20 import ardupilotmega as mav

    from magcomp.commands import diagnose as cmd

    link = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    buf = bytearray()
    for i in range(30):
        stamp = struct.pack(">Q", int((1.7e9 + 0.1 * i) * 1e6))
        buf += stamp + mav.MAVLink_attitude_message(100 * i, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(link)
        if i % 10 == 5:
            buf += stamp + mav.MAVLink_statustext_message(6, b"payload on", 0, 0).pack(link)
    path = tmp_path / "events.tlog"
    path.write_bytes(bytes(buf))
    rows: list[tuple[float | None, float, str]] = []
    with cmd._raw_log(str(path)) as m:  # what the pass over the file read
        cmd._read_events(m, rows)
    assert len(rows) == 3 and all(boot is None for boot, _, _ in rows)

    def no_read(_path: str) -> None:
        raise AssertionError("the tlog was opened for its events")

    monkeypatch.setattr(cmd, "_raw_log", no_read)
    assert cmd.log_events(str(path)) == []
