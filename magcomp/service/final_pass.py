"""The second pass of a two-pass replay, without the per-sample loop.

The first pass (:func:`magcomp.service.replay.replay_log`, two passes) runs the pipeline over the whole log
learning only (theta of a hand-rotation or stored calibration solved in batch at its end, not by stepping the
observer: :mod:`magcomp.service.theta`), and records, per magnetometer sample that reaches the heading stage,
what its heading needs (:class:`SampleLog`: time, raw field, throttle, the attitude's roll and pitch, the raw
gyro's yaw rate, the sample's flags).
The second pass then applies the *final* state of every compass (calibration of eq. (2), theta of eq. (11),
the in-flight calibration; :class:`FinalCompass`) to all samples at once: eq. (2), eq. (11) and eq. (24)
on numpy arrays through the same core functions the per-sample path calls with floats. Only the heading
filter, the output decimation and the time accounting step sample by sample (the same stage code as the
live pipeline), and every MAGCOMP_HEADING is packed by the live path's own framer
(:meth:`~magcomp.service.publish.HeadingEncoder.encode_values`).

What changes against the per-sample second pass it replaces: there, the learning went on from the final
state (theta and the in-flight estimate moved again over the log); here the final state is held fixed, so
every heading of the log is corrected with the same calibration and theta (the one a live run would save
at the end of this flight). Observer-step flags (FLAG_Z_UNOBSERVABLE, FLAG_SATURATED from the observer)
are not set: no observer step runs in this pass.

The sample log spills to an anonymous temporary file every CHUNK_ROWS samples, so memory does not grow with
the log's length; the second pass reads it back a chunk at a time.
"""

from __future__ import annotations

import math
import struct
import tempfile
from array import array
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import IO, TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcomp.core import selfcheck
from magcomp.core.correction import Applied, Correction, headings_deg
from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.hover_theta import (
    OFFSET_PRIOR_SD_MGAUSS,
    HoverTheta,
    anchored,
    fit_hover_theta,
    fit_hover_theta_gyro,
    with_block_sigma,
)
from magcomp.core.types import FLAG_OBSERVER_RESET, HeadingEstimate
from magcomp.core.yaw_follow import follows_within
from magcomp.service.heading import filter_rates_block
from magcomp.service.publish import HeadingEncoder, TlogWriter, write_headings
from magcomp.service.record import ZERO3, Float3, MagRecord

if TYPE_CHECKING:
    from magcomp.service.pipeline import Pipeline

F64 = NDArray[np.float64]

#: the sample log's columns (one row per magnetometer sample that reached the heading stage); the heading
#: filters' rates are taken from the gyro columns a block at a time (heading.filter_rates_block)
(T, MAG, RAW_X, RAW_Y, RAW_Z, THR, HAVE_THR, FLAGS, RESET, PREV_T, OBS_RESET, COS_ROLL, SIN_ROLL, COS_PITCH,
 SIN_PITCH, GYRO_FRESH, GRAW_X, GRAW_Y, GRAW_Z, BOOT_OFFSET, REBOOT, AP_YAW, GYRO_YAW, GYRO_EPOCH,
 IMU_DT, ONB_X, ONB_Y, ONB_Z, GYRO_Y, GYRO_Z, SETTLED) = range(31)  # fmt: skip
N_COLS = SETTLED + 1
#: rows held in memory before they go to the temporary file (and rows per block of the second pass):
#: 8192 rows of 31 float64 are 2.0 MB
CHUNK_ROWS = 8192
#: one row packed as the array's doubles (native order; the same values as ``array.extend``, which converts
#: each item as this does, in ~40 % of its time)
_ROW = struct.Struct(f"{N_COLS}d")


class SampleLog:
    """What each magnetometer sample's heading needs, recorded by the first pass (see the module's doc).
    The pipeline calls :meth:`add` once per sample after the attitude stage and :meth:`reboot` when the
    autopilot reboots (the heading filters restart there)."""

    def __init__(self, chunk_rows: int | None = None) -> None:
        self._buf = array("d")
        self._limit = (CHUNK_ROWS if chunk_rows is None else chunk_rows) * N_COLS
        self._file: IO[bytes] | None = None
        self._rebooted: set[int] = set()

    def add(self, rec: MagRecord, boot_offset_s: float, yaws: Float3 = (math.nan, math.nan, math.nan),
            imu_dt_s: float = math.nan) -> None:
        """One sample; ``yaws``: the autopilot's yaw, the raw gyro's integrated yaw and its epoch (rad, rad,
        count) at the sample, ``imu_dt_s`` the IMU's interval: for the self-check (core/selfcheck.py)."""
        reboot = False
        if self._rebooted:
            idx = rec.mag_index
            if idx in self._rebooted:
                self._rebooted.discard(idx)
                reboot = True
        prev = rec.prev_t
        prev = math.nan if prev is None else prev
        vx, vy, vz = rec.raw
        onb = rec.sample.onboard_mgauss or ZERO3
        buf = self._buf
        _, g1, g2 = rec.gyro
        buf.frombytes(_ROW.pack(rec.t_s, rec.mag_index, vx, vy, vz, rec.throttle_01, rec.have_throttle,
                                rec.flags, rec.reset, prev, rec.obs_reset, *rec.tilt, rec.gyro_fresh,
                                *rec.gyro_raw, boot_offset_s, reboot, *yaws, imu_dt_s, *onb, g1, g2,
                                rec.down is not None))  # fmt: skip
        if len(buf) >= self._limit:
            self._spill()

    def reboot(self, compasses: Iterable[int]) -> None:
        """The autopilot rebooted: the next sample of each of ``compasses`` restarts its heading filters."""
        self._rebooted = set(compasses)

    def _spill(self) -> None:
        if self._file is None:
            self._file = tempfile.TemporaryFile()  # noqa: SIM115 - open until close(), across calls
        self._buf.tofile(self._file)
        self._buf = array("d")

    def chunks(self) -> Iterator[F64]:
        """The rows in order, at most ``chunk_rows`` at a time, (n, N_COLS)."""
        if self._file is not None:
            self._file.seek(0)
            while data := self._file.read(self._limit * 8):
                yield np.frombuffer(data, dtype=np.float64).reshape(-1, N_COLS)
        if len(self._buf):
            yield np.array(self._buf, dtype=np.float64).reshape(-1, N_COLS)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        self._buf = array("d")


@dataclass(frozen=True)
class FinalCompass:
    """The state a compass ended the first pass with, as the second pass applies it: its ``correction``
    (core/correction.py, held fixed over the log) and ``accounts``, the in-flight stage's state its samples
    count toward (None: no in-flight stage)."""

    correction: Correction
    accounts: str | None
    #: the coefficients apply to the field as the autopilot had it (its onboard motor compensation kept:
    #: theta against the autopilot's calibration), not to the field as measured
    autopilot_field: bool = False
    #: subtracted from the corrected heading (deg): the constant change of an offsets' change taken out
    heading_offset_deg: float = 0.0


_NONE = Correction()
_CAL_SOURCES = {"learned": "hand rotation", "stored": "stored", "identity": "identity"}


def final_compasses(pipeline: Pipeline) -> dict[int, FinalCompass] | None:
    """Every compass's final state after the first pass (``pipeline`` closed); None when one of them needs
    the per-sample second pass (an in-flight estimate with per-motor terms: its bias follows the motor
    outputs, which the sample log does not record)."""
    cfg = pipeline.cfg
    inflight_on = cfg.observer.learn and cfg.inflight.enabled
    out: dict[int, FinalCompass] = {}
    for idx, c in pipeline.correctors.items():
        k = c.calib.coeffs()
        st = c.inflight
        if k is not None:
            th = c.theta.est.theta_values()
            summary = c.calib.summary
            source = _CAL_SOURCES.get(summary.source, "stored") if summary is not None else "stored"
            cor = Correction(k, (th[0], th[1], th[2]), converged=c.theta.est.converged, source=source)
            out[idx] = FinalCompass(cor, None)
            continue
        if not inflight_on or st is None:
            out[idx] = FinalCompass(_NONE, None)
            continue
        state = st.final_state()
        st.restart_accounts()
        if st.est is not None and st.est.n > 0:  # the second pass starts from the state stored at the end
            st.warm_started = True
            st.first_applied_t = None  # applied from this pass's first sample on (as a warm start says)
        if state != "corrected" or st.est is None:
            out[idx] = FinalCompass(_NONE, state)
            continue
        if st.n_motors > 0:
            return None
        sol = st.solution = st.est.solve()  # the estimate with every row of the log in it
        cor = Correction.from_solution(sol.calib_l, sol.calib_d, sol.theta_mgauss, None,
                                       sol.heading_sigma_deg, st.params.heading_converged_deg)  # fmt: skip
        out[idx] = FinalCompass(cor, state)
    return out


class Corrected(NamedTuple):
    """A chunk's samples with the final state applied (columns (n,), vectors (n, 3))."""

    psi_deg: F64
    psi_raw_deg: F64
    theta: F64
    bias: F64
    field_corrected: F64
    flags: NDArray[np.int64]
    corrected: NDArray[np.bool_]


def _columns(a: F64) -> tuple[F64, F64, F64]:
    return a[:, 0], a[:, 1], a[:, 2]


def correct(rows: F64, finals: dict[int, FinalCompass]) -> Corrected:
    """Each compass's final correction (core/correction.py: eqs. (2), (11)) over a chunk of the sample log,
    and the heading of eq. (24)."""
    n = rows.shape[0]
    mag = rows[:, MAG].astype(np.int64)
    have = rows[:, HAVE_THR] != 0.0
    thr = np.where(have, rows[:, THR], 0.0)  # no throttle known: no bias
    field_cal = rows[:, RAW_X:RAW_Z + 1] + rows[:, ONB_X:ONB_Z + 1]  # uncorrected: as the autopilot had it
    bias = np.zeros((n, 3))
    theta = np.zeros((n, 3))
    offset_deg = np.zeros(n)
    calibrated = np.zeros(n, dtype=bool)
    flags = rows[:, FLAGS].astype(np.int64)
    # sorted(set()) rather than np.unique: that one imports numpy.ma on first use (15 ms of a replay)
    for idx in sorted(set(mag.tolist())):
        f = finals.get(idx)
        if f is None or not f.correction.calibrated:
            continue
        cor = f.correction
        m = mag == idx
        if cor.needs_throttle:
            m &= have
        else:  # the observer's reset marker, as the per-sample path sets it (service/theta.py)
            flags[m & (rows[:, OBS_RESET] != 0.0)] |= FLAG_OBSERVER_RESET
        calibrated |= m
        r = rows[m]
        if f.autopilot_field:  # the field as the autopilot had it, its onboard motor compensation kept
            vx, vy, vz = (r[:, RAW_X + k] + r[:, ONB_X + k] for k in range(3))
        else:
            vx, vy, vz = r[:, RAW_X], r[:, RAW_Y], r[:, RAW_Z]
        got = cor.apply(vx, vy, vz, thr[m])  # eqs. (2), (11)
        field_cal[m] = np.column_stack(got.field_cal)
        bias[m] = np.column_stack(got.bias)
        theta[m] = cor.theta_mgauss
        offset_deg[m] = f.heading_offset_deg
        flags[m] |= cor.flags
    fc = field_cal - bias
    applied = Applied(_columns(field_cal), _columns(bias), _columns(fc))
    psi, psi_raw = headings_deg(applied, rows[:, COS_ROLL], rows[:, SIN_ROLL], rows[:, COS_PITCH],
                                rows[:, SIN_PITCH])  # eq. (24)
    psi = np.where(have, (psi - offset_deg) % 360.0, psi_raw)  # the anchor of an offsets' change (hover)
    return Corrected(psi, psi_raw, theta, bias, fc, flags, calibrated & have)


def _judged(rows: F64) -> NDArray[np.bool_]:
    """The rows the self-check judges: the throttle known, the motors running, the tilt below 60 deg (what
    service/heading.py :func:`~magcomp.service.heading.count_flown` decides per sample)."""
    ok = selfcheck.judged(rows[:, THR], rows[:, COS_ROLL], rows[:, COS_PITCH])
    return np.asarray(ok, dtype=bool) & (rows[:, HAVE_THR] != 0.0)


def throttle2_flown(samples: SampleLog) -> dict[int, tuple[int, float]]:
    """Per compass: the samples the self-check judges and the sum of their throttle^2 (the summary's
    ``throttle2_flown``: theta times their mean is eq. (11)'s bias at the throttle flown), counted from the
    first pass's sample log rather than per sample in a pass that has no heading stage."""
    out: dict[int, tuple[int, float]] = {}
    for rows in samples.chunks():
        r = rows[_judged(rows)]
        for idx in np.unique(r[:, MAG]):
            thr = r[r[:, MAG] == idx, THR]
            n, d2 = out.get(int(idx), (0, 0.0))
            out[int(idx)] = (n + thr.size, d2 + float(thr @ thr))
    return out


def _check_rows(rows: F64, cor: Corrected, idx: int) -> F64:
    """(t, baseline heading, candidate heading, autopilot yaw, gyro yaw, gyro epoch, IMU dt) of compass
    ``idx``'s samples with the motors running and the tilt below 60 deg, from one chunk (rad)."""
    m = (rows[:, MAG] == idx) & _judged(rows)
    r = rows[m]
    trig = (r[:, COS_ROLL], r[:, SIN_ROLL], r[:, COS_PITCH], r[:, SIN_PITCH])
    own = r[:, RAW_X:RAW_Z + 1] + r[:, ONB_X:ONB_Z + 1]  # the field as the autopilot had it
    base = heading_from_trig_deg(own[:, 0], own[:, 1], own[:, 2], *trig)  # eq. (24)
    cand = cor.psi_deg[m]
    return np.column_stack((r[:, T], np.radians(base), np.radians(cand), r[:, AP_YAW], r[:, GYRO_YAW],
                            r[:, GYRO_EPOCH], r[:, IMU_DT]))  # fmt: skip


def _gyro_rows(imu_dt: F64, gyro_yaw: F64) -> NDArray[np.bool_] | None:
    """The samples the gyro's integrated yaw judges where it is the check's reference (the IMU comes at least
    every MAX_GYRO_DT_S on half the samples or more); None: the autopilot's yaw is the reference."""
    fast = np.isfinite(imu_dt) & (imu_dt <= selfcheck.MAX_GYRO_DT_S)
    if fast.size and float(np.mean(fast)) >= 0.5:
        return fast & np.isfinite(gyro_yaw)
    return None


def self_check(cols: F64, circular: bool | None = None) -> selfcheck.SelfCheck:
    """The verdict of :func:`magcomp.core.selfcheck.compare` on :func:`_check_rows`' columns: the gyro's
    integrated yaw is the windowed reference where :func:`_gyro_rows`, else the autopilot's yaw, which is
    then also no second reference where it follows this compass within the check's window
    (:func:`magcomp.core.selfcheck.att_is_circular`, measured on these samples unless ``circular`` is given:
    candidates for the same compass share their baseline, so it is measured once for them)."""
    t, base, cand, ap, gyaw, epoch, imu_dt = cols.T
    has_ap = bool(np.isfinite(ap).any())
    keep = _gyro_rows(imu_dt, gyaw)
    if keep is not None:
        ids = selfcheck.window_ids(t[keep], epoch[keep])
        if circular is None:
            circular = has_ap and selfcheck.att_is_circular(
                selfcheck.autopilot_follows(t[keep], base[keep], ap[keep], gyaw[keep], epoch[keep]))
        return selfcheck.compare(base[keep], cand[keep], gyaw[keep], ids, ap[keep] if has_ap else None,
                                 circular)  # fmt: skip
    return selfcheck.compare(base, cand, ap, selfcheck.window_ids(t), ap if has_ap else None)


def _hover_rows(rows: F64, idx: int) -> F64:
    """(t, field as logged xyz, roll, pitch, autopilot yaw, throttle, and the self-check's gyro yaw, epoch,
    IMU dt) of compass ``idx``'s samples with the motors running and the tilt below 60 deg."""
    r = rows[(rows[:, MAG] == idx) & _judged(rows)]
    roll = np.arctan2(r[:, SIN_ROLL], r[:, COS_ROLL])
    pitch = np.arctan2(r[:, SIN_PITCH], r[:, COS_PITCH])
    own = r[:, RAW_X:RAW_Z + 1] + r[:, ONB_X:ONB_Z + 1]  # the field as the autopilot had it
    cols = (r[:, T], own[:, 0], own[:, 1], own[:, 2], roll, pitch, r[:, AP_YAW], r[:, THR], r[:, GYRO_YAW],
            r[:, GYRO_EPOCH], r[:, IMU_DT])  # fmt: skip
    return np.column_stack(cols)


def hover_candidate(cols: F64) -> tuple[HoverTheta, selfcheck.SelfCheck] | None:
    """Theta against the autopilot's calibration (core/hover_theta.py) on :func:`_hover_rows`' columns and the
    self-check of the heading it gives: the first form that passes, in this order. Where the gyro is the
    check's reference and the autopilot's yaw is not shown to be independent of this compass (its measured
    follow rate, core/yaw_follow.py, within the flight's span), the yaw from the gyro first
    (:class:`~magcomp.core.hover_theta.GyroYawNormal`: a yaw that follows this compass takes part of theta's
    bias for attitude), then the autopilot's; where that yaw is measured not to follow it, the autopilot's
    first (one Earth field over the whole log, where the gyro form leaves the field's horizontal part free per
    piece). Each source: the theta-only form, then with a change of the hard-iron offsets, the constant
    heading change of the offsets' change taken out again (``anchored``). The check judges each sample with
    the fit of the other half of the log (alternate 10 s windows, two folds): a fit judged on its own samples
    against the yaw it was fitted with would pass by construction. None where theta cannot be fitted; where no
    form passes, the last one tried."""
    if cols.shape[0] == 0 or not np.isfinite(cols[:, 6]).any():
        return None
    t, mx, my, mz, roll, pitch, yaw, thr, gyaw, epoch, imu_dt = cols.T
    field = cols[:, 1:4]
    trig = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch))
    base = np.radians(heading_from_trig_deg(mx, my, mz, *trig))
    fold = selfcheck.window_ids(t) % 2 == 1
    fast = _gyro_rows(imu_dt, gyaw)
    yaws: tuple[str, ...] = ("autopilot",)
    circular: bool | None = None
    if fast is not None:  # the gyro is the check's reference: the autopilot's yaw-follow, measured once
        follow = selfcheck.autopilot_follows(t[fast], base[fast], yaw[fast], gyaw[fast], epoch[fast])
        circular = selfcheck.att_is_circular(follow)
        independent = follow is not None and not follows_within(follow, float(t[-1] - t[0]))
        yaws = ("autopilot", "gyro") if independent else ("gyro", "autopilot")

    def fit_on(source: str, m: NDArray[np.bool_], sd: float | None) -> HoverTheta | None:
        if source == "gyro" and fast is not None:
            k = m & fast
            return fit_hover_theta_gyro(field[k], roll[k], pitch[k], gyaw[k], epoch[k], t[k], thr[k], sd)
        return fit_hover_theta(field[m], roll[m], pitch[m], yaw[m], thr[m], sd)

    got: tuple[HoverTheta, selfcheck.SelfCheck] | None = None
    every = np.ones(t.shape, dtype=bool)
    for source in yaws:
        for sd in (None, OFFSET_PRIOR_SD_MGAUSS):
            fit = fit_on(source, every, sd)
            halves = [fit_on(source, m, sd) for m in (~fold, fold)]
            if fit is None or halves[0] is None or halves[1] is None:
                break
            held = np.where(fold[:, None], halves[0].corrected_mgauss(field, thr),
                            halves[1].corrected_mgauss(field, thr))  # fmt: skip
            cand = np.radians(heading_from_trig_deg(held[:, 0], held[:, 1], held[:, 2], *trig))  # (11), (24)
            chk = self_check(np.column_stack((t, base, cand, yaw, gyaw, epoch, imu_dt)), circular)
            got = anchored(fit, field, thr, *trig), chk
            if chk.applies:
                return _stated(got[0], source, sd, fit_on, cols, fast), chk
    return got


def _stated(fit: HoverTheta, source: str, sd: float | None,
            fit_on: Callable[[str, NDArray[np.bool_], float | None], HoverTheta | None], cols: F64,
            fast: NDArray[np.bool_] | None) -> HoverTheta:  # fmt: skip
    """``fit`` with theta's sigma from the jackknife over blocks of time (core/hover_theta.py
    :func:`~magcomp.core.hover_theta.with_block_sigma`), the blocks counted over the rows its form takes
    (the gyro form only the rows :func:`_gyro_rows` gives it; each fit leaves out non-finite rows itself)."""
    t = cols[:, 0]
    use = fast if source == "gyro" and fast is not None else np.ones(t.shape, dtype=bool)

    def on_used(kept: NDArray[np.bool_]) -> HoverTheta | None:
        m = np.zeros(use.shape, dtype=bool)
        m[use] = kept
        return fit_on(source, m, sd)

    return with_block_sigma(fit, t[use], on_used)


def self_check_finals(
    samples: SampleLog, finals: dict[int, FinalCompass], hover_on: bool = True
) -> tuple[dict[int, FinalCompass], dict[int, selfcheck.SelfCheck], dict[int, HoverTheta],
           dict[int, tuple[HoverTheta, selfcheck.SelfCheck]]]:  # fmt: skip
    """The self-check over the whole log (:mod:`magcomp.core.selfcheck`) of every compass corrected in
    flight (a hand rotation's calibration is judged by eq. (3) instead): where the corrected heading is
    not better than the autopilot's own beyond the noise, or worse against the gyro or the autopilot's yaw,
    its final state becomes "uncorrected" and the second pass publishes the autopilot's own field through
    the same heading filter. Every compass left uncorrected then gets theta against the autopilot's own
    calibration (core/hover_theta.py: a hover determines theta, not a calibration), published where that
    passes the same check (``hover_on``: theta may be learned in flight, ``[inflight] enabled``). Returns the
    final states, the checks of what each compass publishes, the hover thetas published and, for those
    tried and not published, the last form tried with its check (the console says why, and with which yaw)."""
    judged = [i for i, f in finals.items() if f.correction.source == "in flight"]
    hover = [i for i, f in finals.items() if hover_on and (not f.correction.calibrated or i in judged)]
    parts: dict[int, list[F64]] = {i: [] for i in judged}
    hparts: dict[int, list[F64]] = {i: [] for i in hover}
    for rows in samples.chunks():
        cor = correct(rows, finals)
        for i in judged:
            parts[i].append(_check_rows(rows, cor, i))
        for i in hover:
            hparts[i].append(_hover_rows(rows, i))
    out = dict(finals)
    checks: dict[int, selfcheck.SelfCheck] = {}
    hovers: dict[int, HoverTheta] = {}
    refused: dict[int, tuple[HoverTheta, selfcheck.SelfCheck]] = {}
    for i in judged:
        cols = np.concatenate(parts[i]) if parts[i] else np.zeros((0, 7))
        chk = checks[i] = self_check(cols)
        if not chk.applies:
            f = finals[i]
            out[i] = FinalCompass(_NONE, None if f.accounts is None else "uncorrected")
    for i in hover:
        if i in checks and checks[i].applies:
            continue
        got = hover_candidate(np.concatenate(hparts[i]) if hparts[i] else np.zeros((0, 11)))
        if got is None or not got[1].applies:
            if got is not None:
                refused[i] = got
            continue
        fit, chk = got
        f = finals[i]
        acc = None if f.accounts is None else "corrected"
        out[i] = FinalCompass(fit.correction(), acc, autopilot_field=True,
                              heading_offset_deg=math.degrees(fit.anchor_rad))  # fmt: skip
        checks[i] = chk
        hovers[i] = fit
    return out, checks, hovers, refused


def filter_and_publish(
    rows: F64, cor: Corrected, pipeline: Pipeline, finals: dict[int, FinalCompass]
) -> tuple[list[int], list[float], list[float]]:
    """The heading filters, the output decimation and the time accounting, sample by sample (the live
    stages' own code). Returns the published rows and their (corrected, uncorrected) headings."""
    due = pipeline.publish.due
    correctors = pipeline.correctors
    stages = {i: correctors[i].inflight for i, f in finals.items() if f.accounts is not None}
    accounts = {i: f.accounts for i, f in finals.items()}
    out: list[int] = []
    head: list[float] = []
    head_raw: list[float] = []
    # the flag columns as bools and the compass as an int once for the chunk (the same truth values as
    # bool() of each float, the same index as int())
    mags = rows[:, MAG].astype(np.int64).tolist()
    flags = [(rows[:, k] != 0.0).tolist() for k in (HAVE_THR, RESET, GYRO_FRESH, REBOOT)]
    # what the heading filters propagate with, as live (heading.filter_rates), for the whole block
    rate, turn, bias = filter_rates_block(
        (rows[:, GRAW_X], rows[:, GRAW_Y], rows[:, GRAW_Z]), (rows[:, GYRO_Y], rows[:, GYRO_Z]),
        (rows[:, COS_ROLL], rows[:, SIN_ROLL], rows[:, COS_PITCH]), rows[:, SETTLED] != 0.0,
        rows[:, HAVE_THR] != 0.0, rows[:, THR],
    )  # fmt: skip
    cols = (rows[:, T], rows[:, PREV_T], rate, cor.psi_deg, cor.psi_raw_deg, cor.corrected,
            rows[:, GYRO_YAW], rows[:, GYRO_EPOCH], rows[:, IMU_DT], turn, bias)
    lists = [mags, *flags, *(c.tolist() for c in cols)]
    # per compass: its state, its in-flight stage whose time is accounted (None: none) and the state counted
    per = {i: (correctors[i], stages.get(i), accounts.get(i) or "uncorrected") for i in set(mags)}
    for i, row in enumerate(zip(*lists, strict=True)):
        (idx, have, reset, fresh, reboot, t, prev, rate, psi, psi_raw, corr, gyaw, gep, imu_dt, turn,
         bias) = row  # fmt: skip
        c, st, acc = per[idx]
        prev_t = None if prev != prev else prev  # NaN: no previous sample
        dt = 0.0 if prev_t is None or reset else t - prev_t
        track = c.heading
        track.step(psi, psi_raw, have, reset or reboot or not fresh, rate, dt, gyaw, gep, imu_dt, turn, bias)
        if have and st is not None:
            st.account(t, acc)
        if due(c, t, prev_t, reset, corr):
            out.append(i)
            head.append(track.corrected_deg)
            head_raw.append(track.raw_deg)
    return out, head, head_raw


@dataclass
class PassProgress:
    """How far a replay pass got (the per-sample loop's and this one's)."""

    n_estimates: int = 0
    interrupted: bool = False
    t_last_s: float = float("nan")


@dataclass(frozen=True)
class PassOutputs:
    """Where the second pass's published headings go: each MAGCOMP_HEADING packed by ``encoder`` into
    ``writer`` (when there is one), each estimate handed to ``on_estimate`` (when there is one)."""

    encoder: HeadingEncoder
    writer: TlogWriter | None
    on_estimate: Callable[[HeadingEstimate], None] | None


def final_pass(
    samples: SampleLog,
    pipeline: Pipeline,
    finals: dict[int, FinalCompass],
    out: PassOutputs,
    should_stop: Callable[[], bool] | None = None,
    on_progress: Callable[[float], None] | None = None,
) -> PassProgress:
    """The second pass over ``samples`` (see the module's doc): headings with ``finals`` applied, the
    published ones to ``out``; counts and times into ``pipeline`` (its summary then describes this pass)."""
    res = PassProgress()
    if pipeline.system_id is not None:
        out.encoder.set_system(pipeline.system_id)
    try:
        for rows in samples.chunks():
            if should_stop is not None and should_stop():
                res.interrupted = True
                break
            if on_progress is not None:
                on_progress(float(rows[-1, T]))
            _block(rows, pipeline, finals, out, res)
    except KeyboardInterrupt:  # as the per-sample loop: what was written stays, the report says where
        res.interrupted = True
    return res


def _block(
    rows: F64, pipeline: Pipeline, finals: dict[int, FinalCompass], out: PassOutputs, res: PassProgress
) -> None:
    """One block of the sample log through :func:`final_pass`."""
    encoder, writer, on_estimate = out.encoder, out.writer, out.on_estimate
    cor = correct(rows, finals)
    idx, head, head_raw = filter_and_publish(rows, cor, pipeline, finals)
    res.n_estimates += len(idx)
    res.t_last_s = float(rows[-1, T])
    if not idx:
        return
    sel = np.asarray(idx, dtype=np.int64)
    pub = rows[sel]
    if writer is not None:  # the live path's framer on the block at once
        write_headings(encoder, writer, pub[:, T], pub[:, T] - pub[:, BOOT_OFFSET], np.asarray(head),
                       np.asarray(head_raw), cor.theta[sel], cor.bias[sel], pub[:, THR],
                       pub[:, MAG].astype(np.int64), cor.flags[sel])  # fmt: skip
    if on_estimate is not None:
        t_s = pub[:, T].tolist()
        t_boot = (pub[:, T] - pub[:, BOOT_OFFSET]).tolist()
        theta = [(a, b, c) for a, b, c in cor.theta[sel].tolist()]
        bias = [(a, b, c) for a, b, c in cor.bias[sel].tolist()]
        thr = pub[:, THR].tolist()
        mag = pub[:, MAG].astype(np.int64).tolist()
        flags = cor.flags[sel].tolist()
        nan = float("nan")
        raw = pub[:, RAW_X:RAW_Z + 1]
        fc = cor.field_corrected[sel]
        for j, t in enumerate(t_s):
            on_estimate(HeadingEstimate(
                t_s=t, mag_index=mag[j], heading_deg=head[j], heading_raw_deg=head_raw[j],
                theta_mgauss=np.array(theta[j], dtype=float), bias_mgauss=np.array(bias[j], dtype=float),
                throttle_01=thr[j], flags=flags[j], field_raw_mgauss=np.array(raw[j], dtype=float),
                field_cal_mgauss=np.array(fc[j], dtype=float), residual_norm_mgauss=nan, excitation=nan,
                t_boot_s=t_boot[j],
            ))  # fmt: skip
