"""One pipeline for live links and replays: typed samples in, one :class:`HeadingEstimate` per magnetometer
sample out.

A magnetometer sample becomes one :class:`~magcomp.service.record.MagRecord` and passes seven stages, each
a thin stateful wrapper around pure functions (core, or the scalar helpers beside it):

    align      service/align.py      input gates, message-time checks, gaps, the throttle at the sample
    attitude   service/attitude.py   Mahony down vector (sec. II-A), roll/pitch, the gyro (IMU samples in)
    calibrate  service/calibrate.py  eq. (2), L and d from a hand rotation (eqs. (1)-(3)) or learned in flight
    theta      service/theta.py      observer of eq. (20) on the queued samples; bias of eq. (11)
    heading    service/heading.py    eq. (24), tilt-compensated, through the heading filter
    publish    service/output.py     decimation on message time; the HeadingEstimate, built only when asked
    persist    service/persist.py    calibration and theta saved on message time (writes in the background)

:class:`Pipeline` dispatches the samples and wires the stages; each compass's state lives in a
:class:`~magcomp.service.compass.CompassCorrector`, grouped by the stage that owns it. Every ``dt`` comes
from the messages' own timestamps (never arrival time); live runs and replays call the same
:meth:`Pipeline.process` with the same sample order, so a replay at any speed gives the live answer by
construction. Bad input never stops the pipeline: non-finite or saturated samples, time running
backwards, gaps and clock resets are skipped or absorbed and counted in :attr:`Pipeline.counts`.

``learn_only`` (the first pass of a two-pass replay): the heading and publish stages are left out, and the
theta stage feeds the observers without reading theta back into the records, and the in-flight estimate is
re-solved less often (``inflight_stage.learn_config``: only its final state is published); theta of eq. (11)
with a hand-rotation or stored calibration comes from the batch solve of the samples the observer would have
stepped on (service/theta.py), made when the pipeline closes. With a ``recorder`` it also records what the
second pass needs (:mod:`magcomp.service.final_pass`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from magcomp.adapters.config import Config
from magcomp.core.hover_theta import HoverTheta
from magcomp.core.selfcheck import SelfCheck
from magcomp.core.types import (
    AttitudeSample,
    ClockResetSample,
    HeadingEstimate,
    HeartbeatSample,
    IdentitySample,
    ImuSample,
    MagSample,
    ParamSample,
    PositionSample,
    Sample,
    ThrottleSample,
    TimeSample,
)
from magcomp.geomag import earth_field_ned_mgauss
from magcomp.service import estimators as est_core
from magcomp.service.align import AlignStage
from magcomp.service.attitude import AttitudeStage
from magcomp.service.calibrate import CalibrateStage, CalibrationSummary
from magcomp.service.compass import CompassCorrector
from magcomp.service.console import json_safe
from magcomp.service.heading import heading_stage
from magcomp.service.inflight_stage import learn_config
from magcomp.service.output import PublishStage, estimate
from magcomp.service.persist import PersistStage, StateSink
from magcomp.service.record import Float3, MagRecord
from magcomp.service.summary import Status, compass_summary
from magcomp.service.theta import ThetaStage
from magcomp.service.workers import Workers

__all__ = ["CalibrationSummary", "CompassCorrector", "Pipeline", "json_safe"]

log = logging.getLogger("magcomp.pipeline")

#: a log's date re-takes the Earth field taken at another date only when they are this far apart (years):
#: the field's secular change is at most ~150 nT (1.5 mgauss) a year, so 0.1 year moves it by 0.15 mgauss,
#: far below a compass's noise (1-3 mgauss); nearer dates are not worth restarting the in-flight rows for
RETAKE_YEARS = 0.1

COUNT_KEYS = (
    "samples", "mag", "imu", "estimates", "non_finite", "saturated", "gyro_jumps", "mag_jumps",
    "gyro_gated", "time_backwards", "clock_resets", "reboots", "gaps", "observer_resets",
    "throttle_jumps", "no_throttle", "implausible", "non_finite_params",
)  # fmt: skip


class SampleRecorder(Protocol):
    """Takes each magnetometer record after the attitude stage (a two-pass replay's first pass:
    :class:`magcomp.service.final_pass.SampleLog`)."""

    def add(self, rec: MagRecord, boot_offset_s: float, yaws: Float3, imu_dt_s: float) -> None: ...

    def reboot(self, compasses: Iterable[int]) -> None: ...


def _yaw_words(hov: HoverTheta) -> str:
    """The yaw a theta against the autopilot's calibration was fitted with, in the console's words."""
    return "the gyro's yaw" if hov.yaw_source == "gyro" else "the autopilot's yaw"


def _ignored(sample: object) -> bool:
    """Samples the pipeline does not use (temperature, power)."""
    return False


class Pipeline:
    """Samples in (any order of types, message-time stamped), heading estimates out.

    ``store``: where to load calibration and theta from at the first magnetometer sample of each compass
    and to save them to (on calibration, every ``state.save_interval_s`` of message time and on
    :meth:`close`). ``system_id``: the vehicle; None -> taken from the first HEARTBEAT, else 1.
    ``on_text``: status lines (calibration learned, resets, warnings) with their message time.
    ``workers``: the executors for refined fits and state writes, owned (and shut down) by the caller;
    None: both run inline. ``learn_only``: no headings (see the module's doc). ``recorder``: takes each
    magnetometer record after the attitude stage (the two-pass replay's sample log).
    """

    def __init__(
        self,
        cfg: Config,
        *,
        store: StateSink | None = None,
        system_id: int | None = None,
        on_text: Callable[[float, str], None] | None = None,
        workers: Workers | None = None,
        learn_only: bool = False,
        recorder: SampleRecorder | None = None,
        store_is_this_log: bool = False,
    ) -> None:
        self.cfg = cfg
        self.store = store
        #: the stored states were learned from this very log (the per-sample second pass of a two-pass
        #: replay): their in-flight corrections start published, as the whole-log second pass's do; one
        #: carried over from another flight waits for the live check (service/heading.py)
        self._store_is_this_log = store_is_this_log
        self.system_id = system_id
        #: the vehicle's unique hardware id (IdentitySample), None until (unless) the input names it
        self.vehicle_uid: str | None = None
        self._on_text = on_text
        self._workers = workers if workers is not None else Workers.inline()
        self._learn_only = learn_only
        self._recorder = recorder
        self.counts: dict[str, int] = dict.fromkeys(COUNT_KEYS, 0)
        self.warnings: list[str] = []
        self.correctors: dict[int, CompassCorrector] = {}
        #: the self-check of each corrected compass against the gyro (the two-pass replay's, over the log)
        self.self_checks: dict[int, SelfCheck] = {}
        #: theta fitted against the autopilot's calibration where the flight does not determine one, published
        #: where it passed the self-check (the two-pass replay's; service/final_pass.py)
        self.hover_thetas: dict[int, HoverTheta] = {}
        #: the two-pass replay's checks of theta against the autopilot's calibration, tried and not published
        #: (the last form tried, with its check)
        self.hover_refused: dict[int, tuple[HoverTheta, SelfCheck]] = {}
        self._earth_ned = est_core.earth_field(cfg)
        self._earth_ned.flags.writeable = False  # shared by every stage
        self._params: dict[str, float] = {}  # the autopilot's parameters (in-flight calibration)
        loc = cfg.location
        self._location = (loc.lat_deg, loc.lon_deg, loc.alt_m, loc.decimal_year)
        self._location_source = "config"
        self._gps_year: float | None = None  # the log's date (decimal year), once it has said one
        self._date_source = "config"  # the WMM's date: the configured one, or the log's
        self._boot_offset_s = 0.0  # t_s - the autopilot's own clock (changes at each reboot)
        self.align = AlignStage(cfg, self.counts, self._text)
        self.throttle = self.align.throttle
        self.attitude = AttitudeStage(cfg, self.counts)
        self.persist = PersistStage(store, self._workers.state, cfg.state.save_interval_s, self._vehicle,
                                    self.warnings)  # fmt: skip
        # the first pass of a two-pass replay publishes only its final estimate: re-solved less often
        cal_cfg = replace(cfg, inflight=learn_config(cfg.inflight)) if learn_only else cfg
        self.calibrate = CalibrateStage(cal_cfg, self.attitude, self.throttle, self._params, self._earth_ned,
                                        self.persist.save, self._text, outputs=not learn_only)  # fmt: skip
        self.theta = ThetaStage(cfg, self.throttle, self.counts, outputs=not learn_only)
        self.publish = PublishStage(cfg, self.counts)
        #: sample class -> its handler (:meth:`feed`)
        self._handlers: dict[type, Callable[[Any], bool]] = {}

    # ------------------------------------------------------------------------------------------ helpers

    def _sysid(self) -> int:
        return self.system_id if self.system_id is not None else 1

    def _vehicle(self) -> tuple[int, str | None]:
        """The key of this vehicle's state: (system id, unique id or None)."""
        return self._sysid(), self.vehicle_uid

    def _text(self, t_s: float, msg: str, warning: bool = False) -> None:
        if self._learn_only and self._recorder is None:  # the first of two per-sample passes: the second
            # says the same, on the user's terminal
            if warning:
                self.warnings.append(msg)
            log.debug(msg)
            return
        if warning:
            self.warnings.append(msg)
            log.warning(msg)
        else:
            log.info(msg)
        if self._on_text is not None:
            self._on_text(t_s, msg)

    # --------------------------------------------------------------------------------------- dispatcher

    def process(self, sample: Sample) -> HeadingEstimate | None:
        """Feed one sample; returns the heading estimate for a magnetometer sample, else None."""
        return self.last_estimate() if self.feed(sample) else None

    def feed(self, sample: Sample) -> bool:
        """:meth:`process` without building the estimate: True when one was published; it is then
        :meth:`last_estimate` (for consumers that only count, or need only some estimates)."""
        self.counts["samples"] += 1
        cls = type(sample)
        handler = self._handlers.get(cls)
        if handler is None:  # first sample of its class: its handler found once (a class test chain)
            handler = self._handlers[cls] = self._handler_for(cls)
        return handler(sample)

    def feed_all(self, samples: Iterable[Sample]) -> None:
        """:meth:`feed` of each of ``samples`` in order, for a caller that reads none of the results (a
        learn-only pass): one call for a batch instead of one a sample."""
        handlers = self._handlers
        n = 0
        try:
            for sample in samples:
                n += 1
                cls = type(sample)
                handler = handlers.get(cls)
                if handler is None:
                    handler = handlers[cls] = self._handler_for(cls)
                handler(sample)
        finally:
            self.counts["samples"] += n

    def _handler_for(self, cls: type) -> Callable[[Any], bool]:
        """The handler of a sample class (sources may pass subclasses); temperature and power samples
        are not used here. Looked up by class once, not tested against each kind per sample (0.1-0.5 us
        a sample less: a 10 min log carries ~200k samples)."""
        kinds: tuple[tuple[type, Callable[[Any], bool]], ...] = (
            (MagSample, self._on_mag), (ImuSample, self._on_imu), (ThrottleSample, self._on_throttle),
            (AttitudeSample, self._on_attitude), (ClockResetSample, self._on_reboot),
            (HeartbeatSample, self._on_heartbeat), (ParamSample, self._on_param),
            (IdentitySample, self._on_identity),
            (PositionSample, self._on_fix), (TimeSample, self._on_time),
        )  # fmt: skip
        return next((h for k, h in kinds if issubclass(cls, k)), _ignored)

    def _on_imu(self, sample: ImuSample) -> bool:
        if sample.imu_index == 0 and self.attitude.on_imu(sample.t_s, *sample.floats()):
            self._gyro_gated()  # the attitude comes from the primary IMU
        return False

    def _on_throttle(self, sample: ThrottleSample) -> bool:
        if self.throttle.on_sample(sample):
            for c in self.correctors.values():
                if c.theta.queue:
                    self.theta.drain(c, sample.t_s)
        return False

    def _on_attitude(self, sample: AttitudeSample) -> bool:
        self.attitude.on_attitude(sample)
        return False

    def _on_heartbeat(self, sample: HeartbeatSample) -> bool:
        if self.system_id is None:
            self.system_id = int(sample.system_id)
        return False

    def _on_identity(self, sample: IdentitySample) -> bool:
        """The vehicle names its hardware id: its state is keyed by it from now on. A compass that started
        from a state stored under another key (the system id alone: the identity came after its first
        sample) starts again from this vehicle's own state, or fresh: a state learned on one vehicle is
        never applied to another with the same system id."""
        uid = sample.uid
        if uid == self.vehicle_uid:
            return False
        old, self.vehicle_uid = self.vehicle_uid, uid
        sysid = self._sysid()
        self._text(sample.t_s, f"vehicle {sysid}: unique id {uid}" + (f" (was {old})" if old else ""))
        replaceable = self._recorder is None
        for idx, c in list(self.correctors.items()):
            if not c.loaded:
                continue
            if replaceable:
                del self.correctors[idx]  # made again at the next sample, from this vehicle's state
                self._text(sample.t_s, f"compass {idx}: the state loaded before vehicle {sysid} named its id "
                           "is dropped; starting from this vehicle's own state")  # fmt: skip
            else:
                self._text(sample.t_s, f"compass {idx}: started from the state of vehicle {sysid} without "
                           f"identity before the log named id {uid}", warning=True)  # fmt: skip
        return False

    def _on_param(self, sample: ParamSample) -> bool:
        value = float(sample.value)
        if not math.isfinite(value):  # a damaged record: the stages read parameters as integers and flags
            self.counts["non_finite_params"] += 1
            return False
        if self._params.get(sample.name) != value:
            self._params[sample.name] = value
            self.calibrate.params_version += 1  # the in-flight stages re-decide their reference
        return False

    def _on_fix(self, sample: PositionSample) -> bool:
        self._on_position(sample)
        return False

    def _on_time(self, sample: TimeSample) -> bool:
        self._log_date(float(sample.decimal_year), sample.t_s)
        return False

    def _log_date(self, year: float, t_s: float) -> None:
        """A date the log carries (SYSTEM_TIME, a GPS record's week and time, GPS_RAW_INT's Unix time): the
        WMM's epoch. The first one re-takes a field taken at the configured date (a fix before the date,
        or no fix at all: the configured place at the log's date)."""
        if not (math.isfinite(year) and 2010.0 <= year < 2030.0):
            return
        first = self._gps_year is None
        self._gps_year = year
        lat, lon, alt, used = self._location
        if first and abs(year - used) <= RETAKE_YEARS:
            self._date_source = "log"  # the field in use is the log date's already
        elif first:
            where = "GPS position" if self._location_source == "gps" else "configured location"
            self._take_field(lat, lon, alt, year, t_s, f"Earth field at the log's date, {year:.1f} (was "
                                                       f"{used:.1f}), at the {where}")  # fmt: skip

    def last_estimate(self) -> HeadingEstimate:
        """The estimate of the last magnetometer sample for which :meth:`feed` returned True."""
        rec = self.publish.last
        if rec is None:
            raise ValueError("no estimate published yet")
        return estimate(rec, self._boot_offset_s)

    def last_record(self) -> MagRecord:
        """The record behind :meth:`last_estimate` (the same numbers as plain floats; valid until the next
        magnetometer sample). Its time on the autopilot's clock is ``t_s - boot_offset_s``."""
        rec = self.publish.last
        if rec is None:
            raise ValueError("no estimate published yet")
        return rec

    @property
    def boot_offset_s(self) -> float:
        """``t_s`` minus the autopilot's own clock (changes at each reboot)."""
        return self._boot_offset_s

    # ----------------------------------------------------------------------------------- magnetometer

    def _on_mag(self, s: MagSample) -> bool:
        """One magnetometer sample through the stages; True when its estimate is published."""
        vx, vy, vz = s.floats()
        idx = s.mag_index
        if not self.align.admit(idx, s.t_s, vx, vy, vz):
            return False
        c = self.correctors.get(idx) or self._corrector(idx)
        rec = self.align.begin(s, vx, vy, vz, c.clock)
        if rec is None:
            return False
        self.attitude.stamp(rec)
        if self._recorder is not None:
            a = self.attitude
            ap_yaw = a.yaw if a.att_t is not None else math.nan
            imu_dt = math.nan if a.imu_dt is None else a.imu_dt
            yaws = (ap_yaw, a.heading_yaw_rad, float(a.gyro_yaw_epoch))
            self._recorder.add(rec, self._boot_offset_s, yaws, imu_dt)
        self.calibrate.run(rec, c)
        self.theta.run(rec, c)
        if self._learn_only:
            self.persist.run(c, rec.t_s)
            return False
        heading_stage(rec, c.heading)
        self.persist.run(c, rec.t_s)
        return self.publish.run(rec, c)

    def _corrector(self, idx: int) -> CompassCorrector:
        """The state of compass ``idx``, created (from the store's state, if any) at its first sample."""
        sysid = self._sysid()
        self.system_id = sysid
        store = self.store
        stored = store.load(sysid, idx, self.vehicle_uid) if store is not None else None
        if store is not None:
            for w in store.warnings:
                if w not in self.warnings:
                    self.warnings.append(w)
        c = CompassCorrector(idx, self.cfg, self.calibrate.earth_ned, stored, self._workers.fits,
                             self._store_is_this_log)  # fmt: skip
        self.correctors[idx] = c
        return c

    # -------------------------------------------------------------------------------- other samples

    def _gyro_gated(self) -> None:
        """A bad gyro spell starts: the observers' filters are reset (theta kept)."""
        for c in self.correctors.values():
            c.queue_reset()
        self.counts["observer_resets"] += len(self.correctors)

    def _on_reboot(self, s: ClockResetSample) -> bool:
        """The autopilot rebooted (issue 12): data of two boots never meet in one calibration or one
        filter. A calibration window with a learned calibration ends here (its final fit uses this
        boot's pairs only); one without drops the old boot's pairs and starts again. The observers'
        filters, the heading filters, the attitude and the throttle history restart (theta kept)."""
        self.counts["reboots"] += 1
        self._boot_offset_s = s.offset_s
        self.attitude.on_reboot()
        self.throttle.forget()
        if self._recorder is not None:
            self._recorder.reboot(list(self.correctors))
        for c in self.correctors.values():
            cal = c.calib
            if cal.collecting:
                learned = cal.learned
                if not learned:  # the old boot's pairs on their own, if they determine a calibration
                    learned = cal.fit_now()
                if learned:
                    cal.freeze(c.clock.n_mag)
                else:
                    cal.restart_collection()
            c.queue_reset()
            self.counts["observer_resets"] += 1
            c.heading.reset()
        self._text(s.t_s, "autopilot rebooted (its clock restarted): calibration window closed, filters "
                          "restarted", warning=self.counts["reboots"] == 1)  # fmt: skip
        return False

    def _on_position(self, s: PositionSample) -> None:
        """The first trusted GNSS fix sets the Earth field (WMM at the vehicle, at the log's date). A GPS
        record carries the date even without a fix."""
        self._log_date(s.decimal_year, s.t_s)
        if self._location_source == "gps" or not s.fix_ok:
            return
        lat, lon, alt = s.lat_deg, s.lon_deg, s.alt_m
        finite = math.isfinite(lat) and math.isfinite(lon)
        if not (finite and -90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0):
            self.counts["non_finite"] += 1
            return
        if lat == 0.0 and lon == 0.0:  # "no position" as some autopilots send it
            return
        year = self._gps_year if self._gps_year is not None else self._location[3]
        alt = alt if math.isfinite(alt) and -1000.0 < alt < 20000.0 else 0.0
        self._take_field(lat, lon, alt, year, s.t_s, f"Earth field from the GPS position ({lat:.4f}, "
                                                     f"{lon:.4f}), {year:.1f}", source="gps")  # fmt: skip

    def _take_field(self, lat: float, lon: float, alt: float, year: float, t_s: float, what: str,
                    source: str | None = None) -> None:  # fmt: skip
        """The Earth field from the WMM at this place and date, into every stage (in-flight rows made
        against the old one are dropped); ``source``: where the place came from, when it changes."""
        try:
            field = earth_field_ned_mgauss(lat, lon, alt, year)
        except Exception:  # an out-of-range date or place: keep the field in use
            return
        self._location = (lat, lon, alt, year)
        if source is not None:
            self._location_source = source
        self._date_source = "log" if year == self._gps_year else "config"
        field.flags.writeable = False
        self._earth_ned = self.calibrate.earth_ned = field
        norm = float(np.linalg.norm(field))
        for c in self.correctors.values():
            c.calib.earth_ned = field
            st = c.inflight
            if st is not None:
                st.restart(norm)
        self._text(t_s, f"{what}: {norm:.0f} mgauss, WMM")

    # ------------------------------------------------------------------------------------------ end

    def close(self) -> None:
        """Feed what is still queued, save every compass's state and wait for the writes."""
        for c in self.correctors.values():
            if c.calib.adopt_refined(c.clock.n_mag, force=True) and c.last_t is not None:
                self.calibrate.refined(c, c.last_t)
            if c.theta.queue:
                self.theta.drain(c, math.inf)
            c.theta.finish()  # a learn-only pass: theta by the batch solve of what the observer was given
            if c.last_t is not None:
                self.persist.save(c, c.last_t, final=True)
        self.persist.wait()

    def summary(self) -> dict[str, object]:
        """Plain values for JSON: counts, warnings, where the Earth field came from, and per compass its
        calibration, theta, whether its headings are corrected and, when not, why (strictly valid JSON:
        no NaN)."""
        compasses = [compass_summary(c, self._status(c), self._check(c)[0], self._hover(c, stated=True))
                     for i, c in sorted(self.correctors.items())]
        lat, lon, alt, year = self._location
        return json_safe(
            {
                "system_id": self.system_id,
                "vehicle_uid": self.vehicle_uid,
                "counts": dict(self.counts),
                "warnings": list(self.warnings),
                "earth_field": {
                    "source": self._location_source,
                    "lat_deg": lat,
                    "lon_deg": lon,
                    "alt_m": alt,
                    "decimal_year": year,
                    "date_source": self._date_source,
                    "ned_mgauss": np.asarray(self._earth_ned, dtype=float).tolist(),
                },
                "compasses": compasses,
            }
        )

    def _status(self, c: CompassCorrector) -> Status:
        """(corrected | uncorrected, why) for the summary: one phrase a user can act on, with the verdict of
        the self-check against the gyro where one was made."""
        st = self._learned_status(c)
        chk, on = self._check(c)
        hov = self._hover(c)
        if hov is not None and chk is not None and on:
            what = "theta" if not hov.offset_mgauss.any() else "theta and a change of its offsets"
            yaw = _yaw_words(hov)
            why = (f"{what} against the autopilot's calibration, fitted with {yaw} (none determined by the "
                   f"flight: {st.why})")  # fmt: skip
            return Status("corrected", f"{why}; {chk.describe()}")
        if chk is None or st.status != "corrected":
            if st.status == "uncorrected" and self.cfg.output.self_check and self.throttle.t is not None:
                why = f"{st.why}{self._tried(c)}"
                return Status("uncorrected", f"publishing the autopilot's own heading ({why})")
            return st
        if on:
            return Status("corrected", f"{st.why}; {chk.describe()}")
        reason = chk.reason
        run, sol = c.heading.check, None if c.inflight is None else c.inflight.solution
        if run is not None and run.on and sol is not None:  # the live check's verdict applies; the sigma not
            reason = (f"its heading uncertainty (+-{sol.heading_sigma_deg:.1f} deg) and the bound of its "
                      f"error measured on the check's windows ({run.candidate_bound_deg:.1f} deg) are above "
                      f"the error of the autopilot's own heading there ({run.baseline_deg:.1f} deg), so a "
                      f"gain cannot be shown")  # fmt: skip
        return Status("uncorrected", f"publishing the autopilot's own heading (the correction learned in "
                                     f"flight: {reason}{self._tried(c)})")  # fmt: skip

    def _tried(self, c: CompassCorrector) -> str:
        """What became of theta against the autopilot's calibration where it was tried and not published
        (the two-pass replay's check), as a clause of the uncorrected status; empty where not tried."""
        got = self.hover_refused.get(c.mag_index)
        if got is None:
            return ""
        hov, chk = got
        return f"; theta against the autopilot's calibration, last tried with {_yaw_words(hov)}: {chk.reason}"

    def _hover(self, c: CompassCorrector, stated: bool = False) -> HoverTheta | None:
        """The theta against the autopilot's calibration a compass publishes: the two-pass replay's, else the
        live one's (service/heading.py HoverShadow) where its self-check is on and nothing else applies;
        ``stated``: the live one with the sigma the summary states (its jackknife over blocks of time)."""
        if c.mag_index in self.self_checks or c.mag_index in self.hover_thetas:  # the two-pass replay's
            return self.hover_thetas.get(c.mag_index)
        live, st = c.heading.hover, c.inflight
        if live is None or c.calibration is not None:
            return None
        if st is not None and st.applied:
            return None  # the in-flight correction applies (published or not: service/heading.py)
        return live.stated_fit() if stated else live.fit

    def _check(self, c: CompassCorrector) -> tuple[SelfCheck | None, bool]:
        """A compass's self-check and whether its correction is published: the two-pass replay's over the
        whole log, else the live one's latest verdict (service/heading.py): the in-flight correction's, or
        the live hover theta's where that is published."""
        chk = self.self_checks.get(c.mag_index)
        if chk is not None:
            return chk, chk.applies
        live = c.heading.hover
        if live is not None and live.on_form is not None and self._hover(c) is not None:
            v = live.checks[live.on_form].verdict
            if v is not None:
                return v, True
        run = c.heading.check
        if run is not None and run.verdict is not None:
            sol = None if c.inflight is None else c.inflight.solution
            return run.verdict, run.on if sol is None else run.publishes(sol.heading_sigma_deg)
        return None, False

    def _learned_status(self, c: CompassCorrector) -> Status:
        """What the learning says of a compass (corrected | uncorrected, why), before the self-check."""
        if self.throttle.t is None:
            why = "disabled in the configuration" if not self.throttle.enabled else "none in the input"
            return Status("uncorrected", f"no throttle source ({why})")
        if c.calibration is not None:
            return Status(
                "corrected", f"calibration {c.calibration.source}, theta by the observer of eq. (20)"
            )
        st = c.inflight
        if st is not None and st.applied:
            return Status("corrected", f"calibration and theta learned in flight ({st.mode} form)")
        if st is not None:
            return Status("uncorrected", st.why_not())
        if not self.cfg.observer.learn:
            return Status("uncorrected", "no calibration and learning disabled ([observer] learn = false)")
        if not self.cfg.inflight.enabled:
            return Status("uncorrected", "no hand-rotation calibration and in-flight calibration disabled")
        return Status("uncorrected", "no samples with the throttle known")
