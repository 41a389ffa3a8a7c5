"""Stage 4, track theta: the observer of eq. (20) on the calibrated field, and the bias of eq. (11).

With a hand-rotation (or stored) calibration, theta comes from the observer (its 5 Hz low-pass of sec.
II-D on the regression, ``y`` and ``Phi`` alike, in the default form). The observer gets the throttle
*interpolated at the sample's own time*: each sample waits in a short per-compass queue until the throttle
after it has arrived (or ``stale_s`` passed). A sample between two throttle messages that straddle a jump
is left out and the observer re-anchors after it (the instant of the step is unknown). The result does
not depend on the order in which a link delivers the messages of one instant; with the latest throttle
instead, theta came out 8-15 % off on simulated flights (docs/benchmarks.md).

A learn-only pass (the first of a two-pass replay, whose theta is read at its end only) does not step the
observer: each tracker logs the samples it would step on, through the same queue and gates
(:class:`ObserverRowLog`), and :meth:`ThetaTracker.finish` solves them at once by the least squares of
eqs. (12)-(15) on the moving vehicle (core/observer_batch.py); the live path and ``--causal`` step the
observer.

With the in-flight calibration, theta and the bias come with its correction (calibrate stage).
The bias ``theta * throttle^2`` (eq. (11)) uses the latest throttle: the published heading adds no latency.
"""

from __future__ import annotations

import struct
from array import array
from collections import deque
from collections.abc import Sequence
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import Config
from magcomp.core import observer_batch
from magcomp.core.observer import ObserverParams
from magcomp.core.types import FLAG_OBSERVER_RESET, FLAG_SATURATED, FLAG_THETA_CONVERGED, FLAG_Z_UNOBSERVABLE
from magcomp.service import estimators as est_core
from magcomp.service.align import Counts, ThrottleTrack
from magcomp.service.record import Float3, MagRecord

F64 = NDArray[np.float64]
_new_tuple = tuple.__new__


class Queued(NamedTuple):
    """An observer input waiting for the throttle at its time; ``field`` None: a marker, of a reset of the
    observer's filters, or with ``skip`` of a skip (samples missing: core.observer.observer_skip)."""

    t_s: float
    gyro: Sequence[float] | None
    field: Float3 | None
    skip: bool = False


#: samples an observer's log holds before they are reduced to their least-squares sums (~22 min at 50 Hz;
#: ~5 MB of samples, ~60 MB while they are reduced)
ROW_LOG_CHUNK = 65536
#: one row of the observer's row log packed as the array's doubles (the values ``array.extend`` would store,
#: in ~60 % of its time)
_ROW = struct.Struct("9d")


class ObserverRowLog:
    """The samples an observer would step on (time, gyro, calibrated field, the throttle at the sample's time)
    and what precedes each (a reset of its filters, samples skipped), for the batch solve of a learn-only
    pass (core/observer_batch.py); reduced to their sums every ``chunk`` samples (bounded memory; a window
    of the solve ends there)."""

    __slots__ = ("buf", "chunk", "params", "pending", "sums")

    def __init__(self, params: ObserverParams, chunk: int = ROW_LOG_CHUNK) -> None:
        self.buf = array("d")
        self.pending = observer_batch.START_CONTINUE
        self.params = params
        self.chunk = chunk
        self.sums = observer_batch.batch_init()

    def mark(self, start: int) -> None:
        """The next sample re-anchors: after a reset (``START_RESET``) or samples skipped (``START_SKIP``)."""
        if start > self.pending:
            self.pending = start

    def add(self, t_s: float, gyro: Sequence[float], field: Float3, throttle_01: float) -> None:
        self.buf.frombytes(_ROW.pack(t_s, *gyro, *field, throttle_01, self.pending))
        self.pending = observer_batch.START_CONTINUE
        if len(self.buf) >= 9 * self.chunk:
            self._reduce()

    def _reduce(self) -> None:
        a = np.frombuffer(self.buf, dtype=np.float64).reshape(-1, 9)
        rows = observer_batch.model_rows(a[:, 0], a[:, 1:4], a[:, 4:7], a[:, 7], a[:, 8], self.params,
                                         excitation_carry=self.sums.excitation_carry)  # fmt: skip
        self.sums = observer_batch.batch_add(self.sums, rows)
        self.buf = array("d")

    def solve(self, theta0_mgauss: F64) -> observer_batch.BatchTheta:
        """theta by least squares over every logged sample, ``theta0_mgauss`` the prior of the axes the log
        does not excite."""
        if self.buf:
            self._reduce()
        return observer_batch.batch_theta(self.sums, self.params, theta0_mgauss)


class ThetaTracker:
    """One compass's observer (:class:`~magcomp.service.estimators.ThetaEstimator`) and its input queue;
    in a learn-only pass, with ``rows``, the log of what the observer would step on instead."""

    def __init__(self, cfg: Config, theta0_mgauss: F64) -> None:
        self.est = est_core.ThetaEstimator(cfg, theta0_mgauss)
        self.queue: deque[Queued] = deque()
        self.last_t: float | None = None
        self.last_info: est_core.ThetaStepInfo | None = None
        self.rows: ObserverRowLog | None = None
        #: the batch solve's result, once :meth:`finish` made it
        self.batch: observer_batch.BatchTheta | None = None

    def finish(self) -> None:
        """The batch solve of the logged samples (a learn-only pass's end): the estimator holds its theta."""
        rows = self.rows
        if rows is None or not (rows.buf or rows.sums.n_samples):
            return
        self.rows = None
        res = self.batch = rows.solve(self.est.theta_mgauss)
        self.est.hold(res.theta_mgauss, all(res.converged))

    def queue_reset(self, t_s: float, skip: bool = False) -> None:
        """Reset the observer's filters (theta kept) once the samples queued before now are through; ``skip``:
        samples are missing, the next step re-anchors but the filters keep their memory."""
        self.queue.append(Queued(t_s, None, None, skip))

    def drain(self, t_now: float, throttle: ThrottleTrack, stale_s: float, counts: Counts) -> bool:
        """Feed the observer every queued sample whose throttle is known now (the throttle stream has
        reached its time), or that has waited longer than ``stale_s`` (then: the latest throttle).
        True when the observer stepped."""
        q = self.queue
        t_thr = throttle.t
        est = self.est
        rows = self.rows
        stepped = False
        while q:
            t, omega, u, skip = q[0]
            if u is None:  # a reset or skip marker
                q.popleft()
                if rows is not None:
                    rows.mark(observer_batch.START_SKIP if skip else observer_batch.START_RESET)
                elif skip:
                    est.skip()
                else:
                    est.reset_filters()
                self.last_t = None
                continue
            if t_thr is None or (t > t_thr and t_now - t <= stale_s):
                break
            q.popleft()
            thr = throttle.at(t)
            if thr is None:
                # the throttle jumped between the two throttle samples around this one: its value at
                # this instant is unknown, so this sample is not used and the observer re-anchors on
                # the next one whose throttle is known
                counts["throttle_jumps"] += 1
                if rows is not None:
                    rows.mark(observer_batch.START_RESET)
                else:
                    est.reset_filters()
                self.last_t = None
                continue
            assert omega is not None
            if rows is not None:  # a learn-only pass: solved at its end (finish)
                rows.add(t, omega, u, thr)
                continue
            last = self.last_t
            self.last_t = t
            self.last_info = est.step(omega, u, thr, 0.0 if last is None else t - last)
            stepped = True
        return stepped


_ZERO3 = (0.0, 0.0, 0.0)


class ThetaHost(Protocol):
    """What the theta stage reads and writes of one compass (``service.compass.CompassCorrector``)."""

    theta: ThetaTracker
    dirty: bool


class ThetaStage:
    """Fills ``rec.theta``, ``rec.bias`` (eq. (11)) and ``rec.field_corrected``."""

    def __init__(self, cfg: Config, throttle: ThrottleTrack, counts: Counts, outputs: bool = True) -> None:
        """``outputs`` False (a learn-only pass: nothing reads them): the observer is fed, but theta, the
        bias and the corrected field are not written into the records (they keep their defaults), nor
        the observer's flags."""
        self.throttle = throttle
        self.counts = counts
        self._stale_s = cfg.input.stale_s
        self._learn = cfg.observer.learn
        self._outputs = outputs

    def drain(self, c: ThetaHost, t_now: float) -> None:
        """Feed compass ``c``'s observer what its queue holds whose throttle is known by ``t_now``."""
        if c.theta.drain(t_now, self.throttle, self._stale_s, self.counts):
            c.dirty = True

    def run(self, rec: MagRecord, c: ThetaHost) -> None:
        out = rec.inflight
        if not self._outputs:  # a learn-only pass: the observer fed, nothing read back
            if out is None and rec.calibrated:
                self._observe(rec, c)
            return
        if out is not None:
            th0, th1, th2 = out.theta_mgauss
        elif rec.calibrated:
            th0, th1, th2 = self._observe(rec, c)
        else:
            th0 = th1 = th2 = 0.0
        # eq. (11): bias = theta throttle^2, removed from the calibrated field
        if out is not None:
            bx, by, bz = out.bias_mgauss  # (+ per-motor terms, from the same fit)
        elif rec.have_throttle:
            d2 = rec.throttle_01 * rec.throttle_01
            bx, by, bz = th0 * d2, th1 * d2, th2 * d2
        else:
            bx = by = bz = 0.0
        ux, uy, uz = rec.field_cal
        rec.theta = (th0, th1, th2)
        rec.bias = (bx, by, bz)
        rec.field_corrected = (ux - bx, uy - by, uz - bz)

    def _observe(self, rec: MagRecord, c: ThetaHost) -> Sequence[float]:
        """Low-pass + observer, eqs. (19)-(20), fed in time order with the throttle interpolated at the
        sample's own time (queued until the throttle after it is known); theta-hat now."""
        tr = c.theta
        if not self._outputs and tr.rows is None and tr.batch is None:  # learn-only: for the batch solve
            tr.rows = ObserverRowLog(tr.est.params)
        if rec.obs_reset:
            tr.queue_reset(rec.t_s, rec.obs_skip)
            self.counts["observer_resets"] += 1
            rec.flags |= FLAG_OBSERVER_RESET
        elif self._learn and rec.have_throttle and rec.gyro_fresh:
            # (tuple.__new__: the named tuple's own constructor without its keyword handling, 0.17 us less)
            tr.queue.append(_new_tuple(Queued, (rec.t_s, rec.gyro, rec.field_cal, False)))
        elif self._learn:  # a sample the observer cannot take: no step across it (observer.samples_missing)
            tr.queue_reset(rec.t_s, skip=True)
        self.drain(c, rec.t_s)
        if not self._outputs:  # a learn-only pass: theta-hat is read at its end
            return _ZERO3
        info = tr.last_info
        rec.info = info
        if info is not None:
            if info.z_unobservable:
                rec.flags |= FLAG_Z_UNOBSERVABLE
            if info.saturated:
                rec.flags |= FLAG_SATURATED
        if tr.est.converged:
            rec.flags |= FLAG_THETA_CONVERGED
        return tr.est.theta_values()
