"""The state of one compass, grouped by the stage that owns each part (:mod:`magcomp.service.pipeline`)."""

from __future__ import annotations

import math
from concurrent.futures import Executor

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import Config
from magcomp.adapters.state_store import CompassState
from magcomp.service.align import CompassClock
from magcomp.service.calibrate import (
    NO_ROTATION,
    CalibrationSummary,
    HandCalibration,
    RotationSource,
)
from magcomp.service.heading import HeadingTrack
from magcomp.service.inflight_stage import InflightStage
from magcomp.service.theta import ThetaTracker

F64 = NDArray[np.float64]


class CompassCorrector:
    """One compass: its clock (align), calibration and in-flight calibration (calibrate), observer
    (theta), heading filters (heading), output and persistence bookkeeping (publish, persist)."""

    def __init__(
        self,
        mag_index: int,
        cfg: Config,
        earth_ned_mgauss: F64,
        stored: CompassState | None,
        fits: Executor,
        stored_from_this_log: bool = False,
    ) -> None:
        """``stored_from_this_log``: ``stored`` was learned from the log now replayed (a two-pass replay's
        per-sample second pass): its in-flight correction starts published (service/heading.py)."""
        self.mag_index = mag_index
        self.clock = CompassClock()
        mode = cfg.calibration.mode
        self.calib = HandCalibration(cfg, earth_ned_mgauss, stored, fits, self._calibration_adopted)
        # an in-flight calibration from an earlier run (or an earlier pass over the same log)
        self.stored_inflight = stored.inflight if (stored is not None and mode != "learn") else None
        theta0 = stored.theta_mgauss if (stored is not None and mode != "learn") else np.zeros(3)
        self.theta = ThetaTracker(cfg, theta0)
        hover = cfg.inflight.enabled and cfg.observer.learn  # theta against the autopilot's calibration
        self.heading = HeadingTrack(cfg.output.heading_tau_s, cfg.output.self_check, hover,
                                    starts_published=stored_from_this_log)  # fmt: skip
        # in-flight calibration jointly with theta (no hand rotation): created at the first sample
        self.inflight: InflightStage | None = None
        self.rel_source: RotationSource = NO_ROTATION
        self.time_s = {"corrected": 0.0, "uncorrected": 0.0}
        self.n_out = 0
        self.out_t = -math.inf
        self.last_saved_t: float | None = None
        self.dirty = False
        #: the state this compass started from came from the store (a vehicle's identity that arrives
        #: later decides whether it may stay: Pipeline._on_identity)
        self.loaded = stored is not None

    def _calibration_adopted(self) -> None:
        """A new calibration: the observer's filters restart once the samples queued before it are through."""
        self.queue_reset()
        self.dirty = True

    def queue_reset(self) -> None:
        """Reset the observer's filters (theta kept) once the samples queued before now are through."""
        self.theta.queue_reset(self.clock.last_t if self.clock.last_t is not None else 0.0)

    # ------------------------------------------------------------------------------ read-only views

    @property
    def calibration(self) -> CalibrationSummary | None:
        return self.calib.summary

    @property
    def last_t(self) -> float | None:
        return self.clock.last_t

    def calibration_cloud(self) -> tuple[F64, F64]:
        """The raw calibration samples and the same after eq. (2) (for the viewer; a
        :class:`~magcomp.service.calibrate.CalibrationCloud`)."""
        return self.calib.cloud()

    def to_state(self, system_id: int, t_s: float, vehicle_uid: str | None = None) -> CompassState:
        """The state to save (every observer steps in this process, so its theta is current)."""
        cal = self.calibration
        keep = cal is not None and cal.source != "identity"
        info = None
        if cal is not None and keep:
            info = {
                "residual_rms_mgauss": cal.residual_rms_mgauss,
                "coverage": cal.coverage,
                "n": float(cal.n),
            }
        inflight = self.inflight.state() if self.inflight is not None else self.stored_inflight
        theta = np.asarray(self.theta.est.theta_mgauss, dtype=float)
        st = self.inflight
        if cal is None and st is not None and st.solution is not None:
            theta = np.asarray(st.solution.theta_mgauss, dtype=float)
        return CompassState(
            system_id=system_id,
            mag_index=self.mag_index,
            calib_l=self.calib.calib_l if keep else None,
            calib_d=self.calib.calib_d if keep else None,
            theta_mgauss=theta,
            t_s=t_s,
            calib_info=info,
            inflight=inflight,
            vehicle_uid=vehicle_uid,
        )
