"""What one sample becomes in the estimators: the absolute form's rows against the reference's attitude, and
the relative form's window-field rows (eqs. (2), (11), (13); ``rows.window_field_rows``) with their
nuisance windows, the tilt model's rows (a second estimator whose theta the published one takes) and the
relinearisation of a slow link's windows. The settings that choose among these are the fields of
:class:`FeedSwitches`. No I/O."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcomp.core.inflight.base import F64, NUISANCE_PRIOR_RAD_S, VIF_BATCH_S
from magcomp.core.inflight.estimator import InflightEstimator
from magcomp.core.inflight.rows import (
    WindowFieldRows,
    absolute_rows,
    reference_yaw_error_rows,
    window_field_rows_block,
    window_nuisance_cols,
    window_nuisance_cols_block,
)
from magcomp.core.inflight.yawframe import GYRO_WINDOW_S, GyroYawFrame, YawErrorLine, YawTurn, yaw_turned
from magcomp.core.linalg3 import Vec3Like

#: the relative form's rotation-source yaw-rate error (InflightEstimator.add) is taken as constant over
#: windows this long (s). The error is the autopilot's compass-driven yaw correction, which varies on the
#: time constant of that correction (2 s for a complementary filter with a 0.5/s yaw gain, longer for an
#: EKF): a window no longer than that. Measured (simulated ordinary flight, 50 Hz, seed 0: heading rms vs
#: an oracle of 0.84 deg): no nuisance 1.61, 2 s 0.97, 5 s 1.36; log171 compass 1 / 2: 1.73 / 2.05 (none),
#: 1.98 / 2.30 (2 s), 1.70 / 2.03 (5 s).
ROTATION_WINDOW_S = 2.0
#: the absolute form's reference yaw (an external compass's, or GPS yaw) has errors of its own that vary as
#: the vehicle turns (an external compass's residual hard iron: ~2 deg per 10 mgauss). One yaw error per
#: ROTATION_WINDOW_S window is a nuisance of the absolute form, with this prior (rad): a calibrated
#: compass's heading accuracy. Measured: simulated external primary (50 Hz, seed 0) 2.21 -> 0.70 deg rms
#: (oracle 0.58); log171 compass 1 / 2 against compass 0: 1.98 / 2.30 -> 2.19 / 2.55 (a prior of 0.02 rad
#: 2.29 / 2.80 with the unscaled ridge; none: the absolute form follows compass 0's yaw exactly).
REFERENCE_YAW_PRIOR_RAD = 0.035
#: prior standard deviation (rad) of the rotation source's tilt error, one per window (window-field rows):
#: the rows compare the field's vertical part across windows, so a tilt error of the autopilot's GPS-aided
#: attitude (a few tenths of a degree; the simulator's 0.49 deg rms) is a model error of |h| x tilt (4 mgauss
#: at 0.5 deg), comparable to theta x delta^2 itself
TILT_PRIOR_RAD = math.radians(0.5)
#: prior standard deviation (rad) of the gyro yaw's error that the line fit of the windows' field directions
#: leaves, one per window (the tilt-from-yaw nuisance): a single window's field direction scatters by 2-7 deg
#: about the gyro frame's true error (noise-free 10 Hz seed 2: it takes up hard-iron errors in windows with
#: little rotation)
AP_YAW_PRIOR_RAD = math.radians(5.0)
#: prior standard deviation (mgauss) of a window's horizontal Earth field in the window-field rows: any
#: Earth field (under 700 mgauss anywhere), i.e. free
WINDOW_FIELD_PRIOR_MGAUSS = 1000.0


@dataclass(frozen=True, slots=True)
class FeedSwitches:
    """Which rows a sample becomes (docs/inflight.md has the measurements behind each default).

    window_rows_motors_only: the window-field rows take samples with the motors running only (a disarmed log
    gives none: said so). gyro_yaw: they take the yaw from the raw gyro (integrated about the vertical of
    the autopilot's GPS-aided tilt, :class:`~magcomp.core.inflight.yawframe.GyroYawFrame`) instead of the
    autopilot's yaw, which follows the disturbed compass, whenever a raw gyro yaw comes with the field
    sample. ap_yaw_att_lead: take the autopilot's yaw minus the gyro's at the ATTITUDE's own time.

    ap_yaw_tilt: the ordinary estimator's rows model the autopilot's tilt error that its compass-driven yaw
    error makes in accelerated flight (:class:`~magcomp.core.inflight.yawframe.YawErrorLine`). Off: it
    removes most of theta's noise-free bias (10 Hz seed 2: 9.9 -> 4.0 %) but the heading gets worse on
    held-out seeds (10 Hz seed 4 two-pass 1.64 -> 2.57 deg): the per-window nuisance lies along the
    specific force, i.e. the compass's misalignment about z in a coordinated turn (docs/inflight.md, fifth
    pass). What is kept instead: tilt_condition, the tilt model in a second estimator of its own (the same
    samples, its rows with the tilt removed and its per-window nuisance) whose theta the published solution
    takes, the other parameters from the ordinary estimator conditioned on that theta (seventh pass;
    seeds 0-5 at 10 / 50 Hz: theta's worst error 14.5 -> 8.6 %, the heading within 0.05 deg). Both need
    ``attitude.TRACK_ACCEL_H``. ap_yaw_nuisance: the tilt model carries the tilt-from-yaw nuisance per
    window (AP_YAW_PRIOR_RAD).

    relinearise_window: the relative form's 2 s windows (the autopilot's yaw) write their rows' yaw-rate
    and tilt columns again about the window's final field estimate when it closes, on slow links only (the
    attitude matched to the field's time: 6.7 Hz and slower, 2-13 samples per window). Measured (sixth
    pass): theta x6 2 / 4 Hz worst theta error 14.5 -> 11.3 % / 13.7 -> 12.0 %."""

    window_rows_motors_only: bool = True
    gyro_yaw: bool = True
    ap_yaw_att_lead: bool = True
    ap_yaw_tilt: bool = False
    tilt_condition: bool = True
    ap_yaw_nuisance: bool = True
    relinearise_window: bool = True

    @property
    def tilt_model(self) -> bool:
        """The tilt model's own estimator is kept (relative form)."""
        return self.tilt_condition and not self.ap_yaw_tilt and self.gyro_yaw


#: nuisance windows per residual batch of the window-field rows, by whether the gyro's yaw frame is on
#: (its windows are GYRO_WINDOW_S long, else ROTATION_WINDOW_S)
_BATCH_WINDOWS = {
    on: max(1, round(VIF_BATCH_S / (GYRO_WINDOW_S if on else ROTATION_WINDOW_S))) for on in (True, False)
}

_PRIOR_SD_CACHE: dict[tuple[float, ...], F64] = {}


def window_prior_sd(ap_yaw: bool) -> F64:
    """The window-field rows' nuisance prior standard deviations: the window's horizontal field, its yaw
    rate, with TILT_PRIOR_RAD its tilt about north and east, with ``ap_yaw`` the tilt-from-yaw nuisance
    (AP_YAW_PRIOR_RAD). One read-only array per set of values (built once, not per row)."""
    sd: tuple[float, ...] = (WINDOW_FIELD_PRIOR_MGAUSS, WINDOW_FIELD_PRIOR_MGAUSS, NUISANCE_PRIOR_RAD_S)
    if TILT_PRIOR_RAD > 0.0:
        sd += (TILT_PRIOR_RAD, TILT_PRIOR_RAD)
    if ap_yaw:
        sd += (AP_YAW_PRIOR_RAD,)
    arr = _PRIOR_SD_CACHE.get(sd)
    if arr is None:
        arr = _PRIOR_SD_CACHE[sd] = np.array(sd)
        arr.flags.writeable = False
    return arr


def add_absolute_row(
    est: InflightEstimator,
    t_s: float,
    epoch: int,
    r_nb: F64,
    field_ref_n_mgauss: F64,
    y: Vec3Like,
    x: F64 | tuple[float, ...],
) -> None:
    """One sample's absolute rows (eqs. (1), (11), (13)) against the trusted attitude ``r_nb`` and the Earth
    field (NED), with the reference's own yaw error (its compass's calibration) as one nuisance value per
    ROTATION_WINDOW_S window of rotation-source ``epoch``."""
    rows, z = absolute_rows(r_nb.T @ field_ref_n_mgauss, y, x)
    cols = reference_yaw_error_rows(r_nb, field_ref_n_mgauss)
    key = (epoch, math.floor(t_s / ROTATION_WINDOW_S))
    est.add(rows, z, float(x[0]), cols, key, prior_sd=REFERENCE_YAW_PRIOR_RAD)


#: a block that opens its nuisance window writes its rows about its own samples' mean field when it has at
#: least this many (else about the previous window's field)
OWN_FIELD_MIN = 5
#: the most samples a block of window-field rows holds before it goes into the estimators (the stage
#: flushes it before every solution: 5 samples at 50 Hz with a solution every 0.1 s, 50 with one a second)
BLOCK_MAX = 128


#: one held sample: time, time from its window's middle, attitude, yaw turn (None: none), field, regressors,
#: the gyro frame's tilt-model inputs (the autopilot's yaw deviation, the horizontal acceleration)
_Held = tuple[
    float, float, F64, "YawTurn | None", Vec3Like, "F64 | tuple[float, ...]", float, tuple[float, float]
]


class _Block:
    """Samples of one nuisance window waiting to become rows (:class:`WindowRowFeed`), one tuple each
    (:data:`_Held`; one append a sample, the columns made once at the flush)."""

    def __init__(self) -> None:
        self.key: tuple[int, int] | None = None
        self.on = False
        self.relin = False
        self.n_r = 0
        self.held: list[_Held] = []

    def __len__(self) -> int:
        return len(self.held)

    def columns(self) -> _Columns:
        """The held samples by column (each a tuple, in the samples' order)."""
        t, tau, r, turns, y, x, ap_dev, accel = zip(*self.held, strict=True)
        return _Columns(t, tau, r, turns, y, x, ap_dev, accel)

    def clear(self) -> None:
        self.held.clear()


class _Columns(NamedTuple):
    """A block's samples by column (:meth:`_Block.columns`)."""

    t: tuple[float, ...]
    tau: tuple[float, ...]
    r: tuple[F64, ...]
    turns: tuple[YawTurn | None, ...]
    y: tuple[Vec3Like, ...]
    x: tuple[F64 | tuple[float, ...], ...]
    ap_dev: tuple[float, ...]
    accel: tuple[tuple[float, float], ...]


class WindowRowFeed:
    """The relative form's window-field rows of one compass: into the ordinary estimator ``est`` and, with a
    raw gyro's yaw, into the tilt model's ``est_tilt`` (its theta the published one).

    Samples are held in a block (at most BLOCK_MAX, one nuisance window) and become rows together
    (:meth:`flush`; the stage flushes before every solution): their nuisance columns written about the
    window's field as estimated before the block, their gate against the last solution and that estimate,
    each a few numpy calls over the block instead of ~35 per row."""

    def __init__(
        self, est: InflightEstimator, est_tilt: InflightEstimator | None, switches: FeedSwitches
    ) -> None:
        self.est = est
        self.est_tilt = est_tilt
        self.sw = switches
        self._line = YawErrorLine()
        # the window field each estimator's yaw-rate column was last written about
        self._field: tuple[float, float, float] | None = None
        self._field_tilt: tuple[float, float, float] | None = None
        # relinearise_window: the open window's key and its used rows (rows, z, field cols, R_nb, tau, common)
        self._rl_key: tuple[int, int] | None = None
        self._rl_rows: list[tuple[F64, F64, F64, F64, float, F64 | None]] = []
        self._block = _Block()

    @property
    def pending(self) -> int:
        """Samples held in the block (not yet rows)."""
        return len(self._block)

    def add(
        self,
        t_s: float,
        epoch: int,
        r_nb: F64,
        y: Vec3Like,
        x: F64 | tuple[float, ...],
        frame: GyroYawFrame,
        slow_link: bool,
        turn: YawTurn | None = None,
    ) -> None:
        """One sample against its window's Earth field (``window_field_rows``), with the window's horizontal
        field and the rotation source's yaw rate as the window's nuisance; with the tilt model the same
        sample into its estimator too (``y``, ``x``: the field (3) and regressors (n_r), floats or arrays).
        ``epoch`` counts rotation-source restarts (a window never spans one); ``frame``: the gyro yaw's
        frame (``on``: ``r_nb`` takes the gyro's yaw by the yaw ``turn``, made when the block becomes rows);
        ``slow_link``: the attitude is matched to the field's time. Held in the block until it is flushed
        (a new window, a full block, :meth:`flush`)."""
        on = frame.on
        w_s = GYRO_WINDOW_S if on else ROTATION_WINDOW_S
        win = math.floor(t_s / w_s)
        tau = t_s - (win + 0.5) * w_s
        key = (epoch, win)
        relin = self.sw.relinearise_window and not on and slow_link
        b = self._block
        held = b.held  # cleared in place by a flush
        n_r = len(x)
        if held and (
            key != b.key or on != b.on or relin != b.relin or n_r != b.n_r or len(held) >= BLOCK_MAX
        ):
            self.flush()
        if relin and key != self._rl_key:
            self._relinearise()
            self._rl_key = key
        if not held:
            b.key, b.on, b.relin, b.n_r = key, on, relin, n_r
        held.append((t_s, tau, r_nb, turn, y, x, frame.ap_yaw_dev, frame.accel_h))

    def flush(self) -> None:
        """The block's samples into the estimators: the ordinary one's rows (gated), and the tilt model's for
        the samples with a raw gyro's yaw that the ordinary one's gate passed (the same glitches). Only
        those: its windows carry one more nuisance column, and a window never mixes the two."""
        b = self._block
        if not b.held or b.key is None:
            return
        cols = b.columns()
        r_nb, y, x = np.array(cols.r), np.array(cols.y, dtype=float), np.array(cols.x, dtype=float)
        turns = [u for u in cols.turns if u is not None]
        if turns:
            if len(turns) != len(cols.r):
                raise AssertionError("a block mixes attitudes with and without the gyro's yaw")
            r_nb = yaw_turned(r_nb, np.array([u[0] for u in turns]), np.array([u[1] for u in turns]))
        tau = np.array(cols.tau)
        est, tilt = self.est, self.est_tilt
        self._field, w, used = self._add(est, self._field, b, cols, r_nb, y, x, tau, self.sw.ap_yaw_tilt)
        if b.on and tilt is not None and used.any():
            sel = None if used.all() else np.flatnonzero(used)
            if sel is not None:
                r_nb, y, x, tau = r_nb[sel], y[sel], x[sel], tau[sel]
                w = WindowFieldRows(w.rows[sel], w.z[sel], w.field_cols[sel], w.common[sel])
            self._field_tilt, _, _ = self._add(tilt, self._field_tilt, b, cols, r_nb, y, x, tau, True, w, sel)
        b.clear()

    def _add(
        self,
        est: InflightEstimator,
        win_field: tuple[float, float, float] | None,
        b: _Block,
        cols: _Columns,
        r_nb: F64,
        y: F64,
        x: F64,
        tau: F64,
        tilt_model: bool,
        like: WindowFieldRows | None = None,
        sel: NDArray[np.intp] | None = None,
    ) -> tuple[tuple[float, float, float] | None, WindowFieldRows, NDArray[np.bool_]]:
        """The block's window-field rows (``sel``: those of its samples) into ``est`` (the tilt model's when
        ``tilt_model``); returns the window field the yaw-rate column was written about (kept for the next
        window's first samples), the rows (``like``: these samples' rows for the other estimator, whose
        columns but the soft-iron ones they share) and which samples were used."""
        key = b.key
        assert key is not None
        v = est.uncalibrated(y, x)
        w = window_field_rows_block(r_nb, y, x, v, like)
        # the yaw-rate column about the window's own field (its horizontal part as estimated before the
        # block: an autopilot yaw following a compass 15 deg off puts it 15 deg from the WMM's); a block
        # of OWN_FIELD_MIN samples or more that opens its window takes the mean of its own samples' fields,
        # R_nb v, in the window's frame (a shorter one: the previous window's, as a row of its own would)
        e_w = est.window_nuisance(key)
        if e_w is not None:
            e0, e1 = e_w[:2].tolist()
            win_field = (e0, e1, float(est.common_estimate))
        elif v.shape[0] >= OWN_FIELD_MIN or win_field is None:
            f0, f1 = np.einsum("nij,nj->i", r_nb[:, 0:2], v).tolist()
            n_s = v.shape[0]
            c = est.common_estimate if est.common_estimate != 0.0 else float(est.field_ned_mgauss[2])
            win_field = (f0 / n_s, f1 / n_s, c)
        h_w: Vec3Like = win_field
        ap_yaw = tilt_model and b.on and self.sw.ap_yaw_nuisance
        z = w.z
        if tilt_model and b.on:
            t_s, ap_dev, accel = np.array(cols.t), np.array(cols.ap_dev), np.array(cols.accel)
            if sel is not None:
                t_s, ap_dev, accel = t_s[sel], ap_dev[sel], accel[sel]
            psi, vh = self._line.tilt(est, t_s, key, h_w, ap_dev, accel)
            # the tilt's column R^T (v x h) last: the window's yaw rate tilts it too (its column takes it
            # times tau); the right-hand side with the tilt removed; with ap_yaw_nuisance the column stays,
            # for what the line fit leaves of the gyro yaw's error, one per window
            nuis = window_nuisance_cols_block(r_nb, h_w, tau, TILT_PRIOR_RAD > 0.0, vh)
            z = z - psi[:, None] * nuis[:, :, -1]
            if not self.sw.ap_yaw_nuisance:
                nuis = nuis[:, :, :-1]
        else:
            nuis = window_nuisance_cols_block(r_nb, h_w, tau, TILT_PRIOR_RAD > 0.0)
        used = est.add_block(
            w.rows,
            z,
            x[:, 0],
            nuis,
            key,
            w.common,
            gate=est is not self.est_tilt,
            prior_sd=window_prior_sd(ap_yaw),
            batch_windows=_BATCH_WINDOWS[b.on],
        )
        if b.relin and est is self.est:
            for i in np.flatnonzero(used).tolist():
                self._rl_rows.append((w.rows[i], z[i], w.field_cols[i], r_nb[i], float(tau[i]), w.common[i]))
        return win_field, w, used

    def _relinearise(self) -> None:
        """The window closing: its rows' yaw-rate and tilt columns written again about the window's final
        field estimate (``relinearise_window``). Each row's column was written about the field as estimated
        when it came, from the window's first samples only (4-8 of them at 2-4 Hz): a direction error there
        gives the rate column a share along the field, which then takes up throttle-driven changes of the
        field's size (docs/inflight.md, sixth pass)."""
        rows, self._rl_rows = self._rl_rows, []
        if not rows or self._rl_key is None:
            return
        e_w = self.est.window_nuisance(self._rl_key)
        if e_w is None:
            return
        h_fin = np.array([e_w[0], e_w[1], self.est.common_estimate])
        self.est.refill_open_window(
            [
                (r, z, window_nuisance_cols(rn, h_fin, tau, TILT_PRIOR_RAD > 0.0), com)
                for r, z, _fc, rn, tau, com in rows
            ]
        )
