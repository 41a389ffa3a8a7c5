"""The demo: the simulator as a fake flight controller on loopback UDP, the daemon attached to it.

The simulated vehicle flies the paper's whole experiment (``paper`` scenario: hand rotation with the
motor off, spin at full throttle, pan, ramp, step; sec. III) and streams it, paced at ``speed`` x real
time, to the daemon's ``udpin:`` master, receiving the MAGCOMP_HEADING messages sent back. The report
compares the published headings with the simulated truth, per segment, with and without correction.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from magcomp.adapters.config import Config
from magcomp.adapters.state_store import CompassState, StateStore
from magcomp.core.types import HeadingEstimate
from magcomp.service.daemon import Daemon, DaemonReport

if TYPE_CHECKING:
    from magcomp.service.replay import ReplayReport

log = logging.getLogger("magcomp.demo")

SEGMENTS = ("pan", "ramp", "step")


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class SegmentError:
    name: str
    n: int
    max_corrected_deg: float
    max_raw_deg: float
    rms_corrected_deg: float
    rms_raw_deg: float


@dataclass
class DemoReport:
    duration_s: float
    speed: float
    wall_s: float
    sent: int
    received_back: dict[str, int]
    estimates: int
    theta_mgauss: dict[int, list[float]]
    theta_truth_mgauss: dict[int, list[float]]
    segments: list[SegmentError]
    daemon: DaemonReport
    warnings: list[str] = field(default_factory=list)
    clouds: dict[int, tuple[Any, Any]] = field(default_factory=dict)

    def lines(self) -> list[str]:
        out = [
            f"simulated {self.duration_s:.0f} s at {self.speed:g}x in {self.wall_s:.1f} s wall: "
            f"{self.sent} packets sent, {self.estimates} headings published, "
            f"{self.received_back.get('MAGCOMP_HEADING', 0)} MAGCOMP_HEADING received back by the flight "
            "controller",
        ]
        for idx in sorted(self.theta_mgauss):
            th, tr = self.theta_mgauss[idx], self.theta_truth_mgauss.get(idx, [float("nan")] * 3)
            err = float(np.linalg.norm(np.subtract(th, tr)))
            out.append(
                f"compass {idx}: theta = ({th[0]:.1f}, {th[1]:.1f}, {th[2]:.1f}) mgauss, truth "
                f"({tr[0]:.1f}, {tr[1]:.1f}, {tr[2]:.1f}), |error| {err:.1f} mgauss"
            )
        out.append(
            "heading error, compass 0 (deg)  max corrected / uncorrected   rms corrected / uncorrected"
        )
        for s in self.segments:
            out.append(
                f"  {s.name:<5} ({s.n:4d} samples)          {s.max_corrected_deg:6.2f} / {s.max_raw_deg:6.2f}"
                f"          {s.rms_corrected_deg:6.2f} / {s.rms_raw_deg:6.2f}"
            )
        lat = self.daemon.latency_ms
        if lat:
            out.append(f"latency sample -> MAGCOMP_HEADING: p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms")
        return out


def _wrap(a: Any) -> Any:
    return (np.asarray(a, dtype=float) + 180.0) % 360.0 - 180.0


class TruthAt(NamedTuple):
    """The simulated truth at estimate times."""

    sample_index: np.ndarray  # the simulated sample nearest each time
    matched: np.ndarray  # bool: that sample lies within 1 ms
    truth_index: np.ndarray  # index into the truth arrays
    heading_deg: np.ndarray  # true magnetic heading


def truth_at(result: Any, t_s: np.ndarray) -> TruthAt:
    """The simulated truth at estimate times (see :class:`TruthAt`)."""
    s = result.samples
    k = np.clip(np.searchsorted(s.t_s, t_s - 1e-4), 0, len(s.t_s) - 1)
    matched = np.abs(s.t_s[k] - t_s) < 1e-3
    idx = s.truth_index[k]
    truth = (np.degrees(result.euler_rad[idx, 2]) - result.declination_deg) % 360.0
    return TruthAt(k, matched, idx, truth)


def heading_errors(result: Any, estimates: list[HeadingEstimate], mag_index: int = 0) -> list[SegmentError]:
    """Max and rms heading error per paper segment (pan, ramp, step) against the simulated truth."""
    ests = [e for e in estimates if e.mag_index == mag_index]
    if not ests:
        return []
    _, matched, idx, truth = truth_at(result, np.array([e.t_s for e in ests]))
    seg = result.motion.segment[idx]
    names = result.motion.segment_names
    h = np.array([e.heading_deg for e in ests])
    hr = np.array([e.heading_raw_deg for e in ests])
    out = []
    for name in SEGMENTS:
        ids = [i for i, nm in enumerate(names) if nm == name]
        m = np.isin(seg, ids) & matched
        if not m.any():
            continue
        ec, er = _wrap(h[m] - truth[m]), _wrap(hr[m] - truth[m])
        out.append(SegmentError(name, int(m.sum()), float(np.max(np.abs(ec))), float(np.max(np.abs(er))),
                                float(np.sqrt(np.mean(ec**2))), float(np.sqrt(np.mean(er**2)))))  # fmt: skip
    return out


def save_true_states(result: Any, store: StateStore) -> None:
    """Store every simulated compass's true calibration (L = K^-1, d = K^-1 b) and theta: the oracle's
    starting state (replayed with learning off and ``[calibration] mode = "stored"``)."""
    for c in result.compasses:
        j = int(c.index)
        l_true, d_true = result.true_calibration(j)
        theta = np.asarray(c.theta_mgauss, dtype=float)
        store.save(CompassState(1, j, np.asarray(l_true, float), np.asarray(d_true, float), theta, 0.0,
                                vehicle_uid=result.config.uid))  # fmt: skip


def oracle_replay(result: Any, path: Any, store_dir: Any, cfg: Config | None = None) -> ReplayReport:
    """The oracle of the benchmarks and tests: the same replay of ``path`` with the simulator's true
    calibration and theta stored in ``store_dir`` (:func:`save_true_states`) and nothing learned."""
    from pathlib import Path

    from magcomp.service.replay import replay_log

    cfg = cfg or Config()
    store = StateStore(Path(store_dir))
    save_true_states(result, store)
    oracle_cfg = replace(cfg, observer=replace(cfg.observer, learn=False),
                         calibration=replace(cfg.calibration, mode="stored"))  # fmt: skip
    return replay_log(path, oracle_cfg, store=store, keep_estimates=True)


def errors_after_learning(
    result: Any, estimates: list[HeadingEstimate], mag_index: int = 0, learn_s: float = 60.0
) -> tuple[np.ndarray, np.ndarray]:
    """(corrected, uncorrected) heading errors (deg, wrapped) against the simulated truth over the flying
    samples (throttle above 0.2) from ``learn_s`` after the first one: issue 9's "after the first 60 s of
    flight"."""
    ests = [e for e in estimates if e.mag_index == mag_index]
    t = np.array([e.t_s for e in ests])
    k, _, _, truth = truth_at(result, t)
    flying = np.asarray(result.samples.throttle_01)[k] > 0.2
    t_fly = t[flying][0] if flying.any() else np.inf
    m = flying & (t >= t_fly + learn_s)
    corrected = _wrap(np.array([e.heading_deg for e in ests])[m] - truth[m])
    raw = _wrap(np.array([e.heading_raw_deg for e in ests])[m] - truth[m])
    return corrected, raw


def rms_after_learning(
    result: Any, estimates: list[HeadingEstimate], mag_index: int = 0, learn_s: float = 60.0
) -> tuple[float, float]:
    """(corrected, uncorrected) rms of :func:`errors_after_learning`, deg."""
    corrected, raw = errors_after_learning(result, estimates, mag_index, learn_s)
    return float(np.sqrt(np.mean(corrected**2))), float(np.sqrt(np.mean(raw**2)))


def offset_split(errors_deg: np.ndarray) -> tuple[float, float]:
    """(constant part, rms of the rest) of a heading error series, deg. The constant part is what a compass
    mounted a little rotated about the body's z axis gives: for a compass that is also the yaw reference
    (the relative form) it is not observable, a rotation of the Earth's field in the horizontal (a
    declination error) looking the same (docs/inflight.md, tenth pass)."""
    mean = float(np.mean(errors_deg))
    return mean, float(np.sqrt(np.mean((errors_deg - mean) ** 2)))


def run_demo(
    *,
    duration_s: float = 90.0,
    speed: float = 10.0,
    seed: int = 0,
    cfg: Config | None = None,
    store: StateStore | None = None,
    on_estimate: Callable[[HeadingEstimate], None] | None = None,
    on_text: Callable[[float, str], None] | None = None,
    on_sim: Callable[[Any], None] | None = None,
    port: int | None = None,
) -> tuple[DemoReport, Any, list[HeadingEstimate]]:
    """Simulate, serve the stream on loopback UDP, run the daemon on it, compare with the truth.

    Returns (report, the SimResult, every published estimate).
    """
    from magcomp.adapters.mavlink_emit import stream_to_link
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="paper", duration_s=duration_s, seed=seed))
    if on_sim is not None:
        on_sim(result)
    loc = result.config.location
    base = cfg if cfg is not None else Config()
    cfg = replace(base, location=replace(base.location, lat_deg=loc.lat_deg, lon_deg=loc.lon_deg,
                                         alt_m=loc.alt_m, decimal_year=loc.decimal_year))  # fmt: skip
    port = port if port is not None else free_udp_port()
    estimates: list[HeadingEstimate] = []

    def collect(est: HeadingEstimate) -> None:
        estimates.append(est)
        if on_estimate is not None:
            on_estimate(est)

    daemon = Daemon(f"udpin:127.0.0.1:{port}", cfg, store=store, on_estimate=collect, on_text=on_text)
    box: dict[str, DaemonReport] = {}
    worker = threading.Thread(target=lambda: box.setdefault("r", daemon.run()), name="magcomp-daemon")
    wall0 = time.monotonic()
    worker.start()
    t_wait = time.monotonic()
    while daemon.connects == 0 and time.monotonic() - t_wait < 10.0 and worker.is_alive():
        time.sleep(0.02)
    try:
        link = stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=speed)
        # let the daemon finish what is queued: stop when no estimate arrived for 0.5 s
        expected = int(result.samples.t_s.shape[0]) * int(result.samples.mag_mgauss.shape[0])
        last_n, last_change = -1, time.monotonic()
        while len(estimates) < expected and time.monotonic() - last_change < 0.5:
            if len(estimates) != last_n:
                last_n, last_change = len(estimates), time.monotonic()
            time.sleep(0.02)
    finally:
        daemon.stop()
        worker.join(timeout=10.0)
    wall = time.monotonic() - wall0
    rep = box.get("r") or daemon.report()
    clouds = {i: c.calibration_cloud() for i, c in daemon.pipeline.correctors.items()}
    theta = {c["index"]: list(c["theta_mgauss"]) for c in rep.summary["compasses"]}
    truth = {int(c.index): [float(x) for x in c.theta_mgauss] for c in result.compasses}
    report = DemoReport(
        duration_s=float(result.samples.t_s[-1] - result.samples.t_s[0]),
        speed=speed,
        wall_s=wall,
        sent=link.sent,
        received_back=dict(link.received),
        estimates=len(estimates),
        theta_mgauss=theta,
        theta_truth_mgauss=truth,
        segments=heading_errors(result, estimates),
        daemon=rep,
        warnings=list(rep.summary.get("warnings", [])),
        clouds=clouds,
    )
    return report, result, estimates
