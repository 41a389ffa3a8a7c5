"""Replay: a whole log through the same :class:`~magcomp.service.pipeline.Pipeline` as a live link, as fast
as the machine goes."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path
from typing import Any

from magcomp.adapters.config import Config
from magcomp.adapters.state_store import CompassState
from magcomp.core.types import HeadingEstimate
from magcomp.errors import InputError
from magcomp.service.attitude_at_mag import AttitudeAtMag
from magcomp.service.final_pass import (
    FinalCompass,
    PassOutputs,
    PassProgress,
    SampleLog,
    final_compasses,
    final_pass,
    self_check_finals,
    throttle2_flown,
)
from magcomp.service.persist import StateSink
from magcomp.service.pipeline import Pipeline, json_safe
from magcomp.service.publish import FrameQueue, HeadingEncoder, TlogWriter
from magcomp.service.workers import Workers

log = logging.getLogger("magcomp.replay")

#: samples decoded per batch of the replay loop
REPLAY_BATCH = 256


@dataclass
class ReplayReport:
    """What a replay did: the pipeline summary, the source's skip counts, timing, the estimates if kept."""

    path: str
    summary: dict[str, Any]
    source_counts: dict[str, int]
    wall_s: float
    n_estimates: int
    emitted: int = 0
    estimates: list[HeadingEstimate] = field(default_factory=list)
    #: per compass, the calibration samples before and after eq. (2) (only with ``keep_estimates``)
    clouds: dict[int, tuple[Any, Any]] = field(default_factory=dict)
    #: ^C stopped the replay early; everything above covers the log up to ``t_last_s``
    interrupted: bool = False
    t_last_s: float = float("nan")

    @property
    def counts(self) -> dict[str, int]:
        """The source's and the pipeline's counters, summed where both count the same thing."""
        out = dict(self.source_counts)
        for k, v in self.summary["counts"].items():
            out[k] = out.get(k, 0) + int(v)
        return out

    def to_json(self) -> dict[str, Any]:
        out = dict(self.summary)
        out["log"] = self.path
        out["source_counts"] = dict(sorted(self.source_counts.items()))
        out["wall_s"] = self.wall_s
        out["estimates"] = self.n_estimates
        out["emitted"] = self.emitted
        if self.interrupted:
            out["interrupted_at_s"] = self.t_last_s
        return out


class MemoryStore:
    """A state store in memory (the first pass of a two-pass replay hands its states to the second)."""

    def __init__(self) -> None:
        self.states: dict[tuple[int, str | None, int], CompassState] = {}
        self.warnings: list[str] = []
        #: the pipeline's summary at the end of the pass (set by :func:`learn_pass`)
        self.summary: dict[str, Any] | None = None

    def save(self, state: CompassState) -> None:
        self.states[(state.system_id, state.vehicle_uid, state.mag_index)] = state

    def load(self, system_id: int, mag_index: int, uid: str | None = None) -> CompassState | None:
        return self.states.get((system_id, uid, mag_index))


def learn_pass(
    path: str | Path,
    cfg: Config,
    should_stop: Callable[[], bool] | None = None,
    workers: Workers | None = None,
    on_progress: Callable[[float], None] | None = None,
) -> MemoryStore | None:
    """First pass of a two-pass replay: the whole log through the pipeline without its heading and publish
    stages (``learn_only``), the final state of every compass kept (what a live run would save at the end
    of this flight). None when ``should_stop`` asked to stop."""
    store = MemoryStore()
    pipeline = Pipeline(cfg, store=store, workers=workers, learn_only=True)
    if _learn(path, cfg, pipeline, should_stop, on_progress) is None:
        return None
    store.summary = pipeline.summary()
    return store


@dataclass
class _FirstPass:
    """The first pass of a two-pass replay: its pipeline (closed), the states it saved, the sample log the
    second pass reads, what the source counted and found."""

    pipeline: Pipeline
    store: MemoryStore
    samples: SampleLog
    source: _SourceFacts


@dataclass
class _SourceFacts:
    counts: dict[str, int]
    onboard: dict[Any, Any]
    clock_offsets: dict[str, float]


def _clock_offsets(source: Any) -> dict[str, float]:
    """The streams a MAVLink source moved onto the time_boot_ms clock, and by how much (s)."""
    return source.clock_offsets() if hasattr(source, "clock_offsets") else {}


def _learn(
    path: str | Path,
    cfg: Config,
    pipeline: Pipeline,
    should_stop: Callable[[], bool] | None,
    on_progress: Callable[[float], None] | None,
) -> _SourceFacts | None:
    """Every sample of ``path`` through ``pipeline`` (then closed); None when ``should_stop`` asked to
    stop."""
    from magcomp.adapters.mavlink_source import open_source

    source = open_source(path, throttle_source=source_throttle(cfg), pipeline_only=True)
    feed_all = pipeline.feed_all
    at_mag = AttitudeAtMag()  # the attitude at each field sample's time (service/attitude_at_mag.py)
    samples = at_mag.stream(source.samples())
    try:
        while batch := list(islice(samples, REPLAY_BATCH)):
            if should_stop is not None and should_stop():
                return None
            feed_all(batch)
            if on_progress is not None:
                on_progress(batch[-1].t_s)
    finally:
        # what the pipeline_only source left out counts as fed (the pipeline ignores those samples); the
        # interpolated ATTITUDEs are not the log's
        pipeline.counts["samples"] += source.skipped_samples - at_mag.inserted
        source.close()
        pipeline.close()
    onboard = source.onboard_motor_comp() if hasattr(source, "onboard_motor_comp") else {}
    return _SourceFacts(dict(source.counts), onboard, _clock_offsets(source))


def _first_pass(
    path: str | Path,
    cfg: Config,
    should_stop: Callable[[], bool] | None,
    workers: Workers,
    on_progress: Callable[[float], None] | None,
    on_text: Callable[[float, str], None] | None,
) -> _FirstPass | None:
    """:func:`learn_pass` that also records the sample log (service/final_pass.py). One process: a fork
    would buy wall time on an idle machine and cost CPU (the pipes, the copies), which is what a fleet of
    logs pays (benchmarks/replay_speed.py)."""
    store = MemoryStore()
    samples = SampleLog()
    pipeline = Pipeline(cfg, store=store, workers=workers, learn_only=True, recorder=samples, on_text=on_text)
    try:
        facts = _learn(path, cfg, pipeline, should_stop, on_progress)
    except BaseException:
        samples.close()
        raise
    if facts is None:
        samples.close()
        return None
    store.summary = pipeline.summary()
    return _FirstPass(pipeline, store, samples, facts)


def source_throttle(cfg: Config) -> str:
    """The throttle option for the source (``none`` is handled by the pipeline, which ignores throttle)."""
    return "auto" if cfg.input.throttle_source == "none" else cfg.input.throttle_source


class _Outputs:
    """Where a replay's estimates go: kept, a callback, an ``--emit`` tlog. The estimate object is built
    only when one of them wants it (same numbers: Pipeline.process = feed + last_estimate)."""

    def __init__(
        self,
        cfg: Config,
        emit: str | Path | None,
        keep: bool,
        on_estimate: Callable[[HeadingEstimate], None] | None,
    ) -> None:
        self.writer = TlogWriter(emit) if emit is not None else None
        self.encoder = HeadingEncoder(cfg.output.source_system, cfg.output.source_component)
        self.kept: list[HeadingEstimate] = []
        self._keep = keep
        self._on_estimate = on_estimate
        self.wanted = keep or on_estimate is not None or self.writer is not None
        self._sysid_set = False
        #: --emit alone: the frames packed from the records a block at a time, no estimate object built
        self._queue = None if self.writer is None or keep or on_estimate is not None else (
            FrameQueue(self.encoder, self.writer))  # fmt: skip

    def take(self, pipeline: Pipeline) -> None:
        writer = self.writer
        queue = self._queue
        if writer is not None and not self._sysid_set and pipeline.system_id is not None:
            if queue is not None:
                queue.flush()  # the frames queued so far carry the system id they were made under
            self.encoder.set_system(pipeline.system_id)
            self._sysid_set = True
        if queue is not None:
            r = pipeline.last_record()
            t_boot = r.t_s - pipeline.boot_offset_s
            queue.add(r.t_s, (t_boot, r.heading_deg, r.heading_raw_deg, r.theta, r.bias, r.throttle_01,
                              r.mag_index, r.flags))  # fmt: skip
            return
        est = pipeline.last_estimate()
        if self._keep:
            self.kept.append(est)
        if self._on_estimate is not None:
            self._on_estimate(est)
        if writer is not None:
            writer.write_packet(est.t_s, self.encoder.encode(est))

    def flush(self) -> None:
        """Write the frames queued (``--emit``)."""
        if self._queue is not None:
            self._queue.flush()

    def close(self, failed: bool = False) -> None:
        """Close the tlog (idempotent). A tlog with no heading in it is not written (the ``--emit`` path
        is left as it was: nothing magcomp did not create is ever removed); after a failure, what was
        written so far is kept."""
        writer = self.writer
        if writer is None:
            return
        try:
            if self._queue is not None:
                self._queue.flush()
        except InputError:
            if not failed:  # (after a failure, that failure is the one reported)
                raise
        finally:
            writer.close()

    @property
    def emitted(self) -> int:
        return self.writer.packets if self.writer is not None else 0


def _replay_loop(
    source: Any,
    pipeline: Pipeline,
    outputs: _Outputs,
    should_stop: Callable[[], bool] | None,
    on_progress: Callable[[float], None] | None,
) -> PassProgress:
    """Every sample of ``source`` through ``pipeline``; published estimates to ``outputs``. Samples are
    decoded a batch at a time, then fed one by one in the same order: the same numbers as feeding each
    sample as it is decoded (the source never depends on the pipeline), 3-4 % less wall time (each half
    of the loop runs on warm caches)."""
    prog = PassProgress()
    feed = pipeline.feed
    wanted = outputs.wanted
    samples = source.samples()
    n = 0
    sample: Any = None
    try:
        while batch := list(islice(samples, REPLAY_BATCH)):
            if should_stop is not None and should_stop():
                prog.interrupted = True
                break
            if on_progress is not None:
                on_progress(batch[-1].t_s)
            for sample in batch:
                if feed(sample):
                    n += 1
                    if wanted:
                        outputs.take(pipeline)
    except KeyboardInterrupt:
        prog.interrupted = True
    prog.n_estimates = n
    prog.t_last_s = float(sample.t_s) if sample is not None else float("nan")
    return prog


def replay_log(
    path: str | Path,
    cfg: Config,
    *,
    store: StateSink | None = None,
    emit: str | Path | None = None,
    keep_estimates: bool = False,
    on_estimate: Callable[[HeadingEstimate], None] | None = None,
    on_text: Callable[[float, str], None] | None = None,
    two_pass: bool = False,
    should_stop: Callable[[], bool] | None = None,
    on_progress: Callable[[float], None] | None = None,
    keep_clouds: bool = False,
) -> ReplayReport:
    """Run ``path`` (tlog, raw MAVLink, DataFlash .bin/.log) through the pipeline.

    ``emit``: write every published MAGCOMP_HEADING into this tlog. ``keep_estimates``: return them
    (for tests and the batch viewer). Raises :class:`~magcomp.errors.InputError` for unreadable, empty
    or non-MAVLink files; damaged parts of a readable log are skipped and counted. A ^C
    (KeyboardInterrupt) ends the replay early but keeps what was done: the state is saved, the ``emit``
    file closed, and the report (``interrupted=True``) covers the log up to the last sample. So does
    ``should_stop`` returning True (checked once per batch of samples; e.g. a flag a signal handler sets).
    ``keep_clouds``: return the calibration clouds (also with ``keep_estimates``).
    ``on_progress``: called once per batch with the message time reached (s), in each pass (the time starts
    again with the second). When the replay fails
    (an unreadable log) before any heading was written, the ``emit`` file is removed, not left empty.
    The refined calibration fits and the state writes run on worker threads owned by this call.
    """
    t_wall = time.perf_counter()
    asked = _Asked(emit, keep_estimates, on_estimate, should_stop, on_progress)
    log.debug("replaying %s (%s)", path, "two passes" if two_pass and store is None else "one pass")
    with Workers.threads() as workers:
        first: _FirstPass | None = None
        finals: dict[int, FinalCompass] | None = None
        if two_pass and store is None:
            # the log is known whole: learn from all of it first, then replay with the state it ends with
            # (as a live run would start from yesterday's saved state); a ^C here leaves a one-pass replay
            try:
                first = _first_pass(path, cfg, should_stop, workers, on_progress, on_text)
            except KeyboardInterrupt:
                first = None
            finals = final_compasses(first.pipeline) if first is not None else None
            if first is not None and finals is not None and cfg.output.self_check:  # never worse than its own
                hover_on = cfg.inflight.enabled and cfg.observer.learn  # theta is learned in flight
                finals, checks, hovers, refused = self_check_finals(first.samples, finals, hover_on)
                for idx, (n, d2) in throttle2_flown(first.samples).items():
                    if idx in first.pipeline.correctors:
                        first.pipeline.correctors[idx].heading.add_flown(n, d2)
                first.pipeline.self_checks.update(checks)
                first.pipeline.hover_thetas.update(hovers)
                first.pipeline.hover_refused.update(refused)
        if first is not None and finals is not None:
            pipeline = first.pipeline
            report = _second_pass(path, cfg, first, finals, asked)
        else:  # one pass; or two, the second per sample from the stored states (per-motor terms)
            mem = store
            if first is not None:
                first.samples.close()
                mem = first.store
            pipeline = Pipeline(cfg, store=mem, on_text=on_text, workers=workers,
                                store_is_this_log=first is not None)  # fmt: skip
            report = _replay(path, cfg, pipeline, asked)
    report.wall_s = time.perf_counter() - t_wall
    report.summary["passes"] = 2 if first is not None else 1
    if keep_estimates or keep_clouds:
        report.clouds = {i: c.calibration_cloud() for i, c in pipeline.correctors.items()}
    return report


@dataclass(frozen=True)
class _Asked:
    """What the caller of :func:`replay_log` asked of the pass that publishes (see its doc)."""

    emit: str | Path | None
    keep_estimates: bool
    on_estimate: Callable[[HeadingEstimate], None] | None
    should_stop: Callable[[], bool] | None
    on_progress: Callable[[float], None] | None

    def outputs(self, cfg: Config) -> _Outputs:
        return _Outputs(cfg, self.emit, self.keep_estimates, self.on_estimate)


def _second_pass(
    path: str | Path, cfg: Config, first: _FirstPass, finals: dict[int, FinalCompass], asked: _Asked
) -> ReplayReport:
    """The second pass of a two-pass replay over the first pass's sample log (service/final_pass.py)."""
    outputs = asked.outputs(cfg)
    sink: Callable[[HeadingEstimate], None] | None = None
    keep, on_estimate = asked.keep_estimates, asked.on_estimate
    if keep or on_estimate is not None:

        def sink(est: HeadingEstimate) -> None:
            if keep:
                outputs.kept.append(est)
            if on_estimate is not None:
                on_estimate(est)

    try:
        to = PassOutputs(outputs.encoder, outputs.writer, sink)
        res = final_pass(first.samples, first.pipeline, finals, to, asked.should_stop, asked.on_progress)
    except BaseException:
        outputs.close(failed=True)
        raise
    finally:
        outputs.close()
        first.samples.close()
    summary = _with_onboard(first.pipeline.summary(), first.source.onboard, first.source.clock_offsets)
    return _report(path, summary, first.source.counts, outputs, res)


def _report(
    path: str | Path,
    summary: dict[str, Any],
    source_counts: dict[str, int],
    outputs: _Outputs,
    prog: PassProgress,
) -> ReplayReport:
    """The report of the pass that published (``wall_s`` is set by :func:`replay_log`)."""
    return ReplayReport(
        path=str(path),
        summary=summary,
        source_counts=source_counts,
        wall_s=0.0,
        n_estimates=prog.n_estimates,
        emitted=outputs.emitted,
        estimates=outputs.kept,
        interrupted=prog.interrupted,
        t_last_s=prog.t_last_s,
    )


def _with_onboard(
    summary: dict[str, Any], onboard: dict[Any, Any], clock_offsets: dict[str, float]
) -> dict[str, Any]:
    """The summary with the check of ArduPilot's own motor compensation, when the source undid one, and
    the streams' clock offsets (s), when it aligned any."""
    if clock_offsets:
        summary["clock_offsets_s"] = dict(sorted(clock_offsets.items()))
    if onboard:  # ArduPilot's own motor compensation was undone: was it right? (issue 9, item 7)
        from magcomp.adapters.ardupilot_motcomp import onboard_comp_warnings

        warnings = summary["warnings"]
        assert isinstance(warnings, list)
        summary["warnings"] = [*warnings, *onboard_comp_warnings(onboard, summary)]
        summary["onboard_motor_compensation"] = json_safe({str(k): v for k, v in onboard.items()})
    return summary


def _replay(path: str | Path, cfg: Config, pipeline: Pipeline, asked: _Asked) -> ReplayReport:
    """One pass of :func:`replay_log` with ``pipeline``."""
    from magcomp.adapters.mavlink_source import open_source

    source = open_source(path, throttle_source=source_throttle(cfg), pipeline_only=True)
    try:
        outputs = asked.outputs(cfg)
    except BaseException:
        source.close()
        raise
    try:
        prog = _replay_loop(source, pipeline, outputs, asked.should_stop, asked.on_progress)
        outputs.flush()  # a write that fails here is a failure of the run: the state is still saved below
    except BaseException:
        outputs.close(failed=True)
        raise
    finally:
        pipeline.counts["samples"] += source.skipped_samples  # as in _learn
        source.close()
        try:
            outputs.close()
        finally:
            pipeline.close()
    onboard = source.onboard_motor_comp() if hasattr(source, "onboard_motor_comp") else {}
    summary = _with_onboard(pipeline.summary(), onboard, _clock_offsets(source))
    return _report(path, summary, dict(source.counts), outputs, prog)
