"""One log -> its fleet rows (one per compass): identity, the two-pass replay's correction, the excitation,
the interference. Never raises for a bad log: a failure is one row with the one-line reason.

Runs in one process, no forks (a Dask worker's task): the replay itself runs in one process.
"""

from __future__ import annotations

import hashlib
import math
import os
import resource
import time
import traceback
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from magcomp import __version__
from magcomp.fleet.diagnosed import FLYING_THROTTLE, LogDiagnosis, diagnose_columns, failed_columns

#: bytes read at a time when hashing a log
HASH_CHUNK = 1 << 20


def content_hash(path: str | Path) -> str:
    """sha256 of the file's bytes (hex): the log's key, whatever its name or folder."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            h.update(chunk)
    return h.hexdigest()


@dataclass
class LogTask:
    """What a worker needs for one log (small, picklable)."""

    path: str
    sha256: str
    size_bytes: int
    config: str | None = None
    #: run ``magcomp diagnose`` too (its findings, theta and parameters in the row)
    diagnose: bool = True


class _Excitation:
    """Throttle and time span of the published estimates, gathered while the replay runs."""

    def __init__(self) -> None:
        self.t_first = math.inf
        self.t_last = -math.inf
        self.thr_min = math.inf
        self.thr_max = -math.inf
        self.n = 0
        self.n_flying = 0
        self.mag0: int | None = None

    def add(self, est: Any) -> None:
        if self.mag0 is None:
            self.mag0 = est.mag_index
        if est.mag_index != self.mag0:  # one compass is enough for the throttle and the time
            return
        t = est.t_s
        thr = est.throttle_01
        self.n += 1
        if t < self.t_first:
            self.t_first = t
        if t > self.t_last:
            self.t_last = t
        if thr == thr:  # not NaN
            if thr < self.thr_min:
                self.thr_min = thr
            if thr > self.thr_max:
                self.thr_max = thr
            if thr > FLYING_THROTTLE:
                self.n_flying += 1

    @property
    def duration_s(self) -> float:
        return self.t_last - self.t_first if self.n >= 2 else math.nan

    @property
    def throttle_min(self) -> float:
        return self.thr_min if self.n and math.isfinite(self.thr_min) else math.nan

    @property
    def throttle_max(self) -> float:
        return self.thr_max if self.n and math.isfinite(self.thr_max) else math.nan

    @property
    def flight_s(self) -> float:
        return self.duration_s * self.n_flying / self.n if self.n >= 2 else math.nan


def analyse_log(task: LogTask) -> list[dict[str, Any]]:
    """The rows of one log. Single-process; any failure becomes one row with ``status = 'failed'``."""
    t_wall = time.perf_counter()
    cpu0 = _cpu_s()
    base: dict[str, Any] = {
        "sha256": task.sha256,
        "path": task.path,
        "file_name": Path(task.path).name,
        "size_bytes": task.size_bytes,
        "magcomp_version": __version__,
        "analysed_at": datetime.now(UTC),
        "host": os.uname().nodename,
    }
    try:
        rows = _analyse(task, base)
    except Exception as exc:  # one bad log must not stop the fleet: the reason becomes its row
        rows = [{**base, "status": "failed", "error": _one_line(exc)}]
    wall, cpu = time.perf_counter() - t_wall, _cpu_s() - cpu0
    for r in rows:
        r["wall_s"], r["cpu_s"] = wall, cpu
        r["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return rows


def _cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _one_line(exc: BaseException) -> str:
    from magcomp.errors import MagcompError

    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    if isinstance(exc, MagcompError):
        return text or type(exc).__name__
    where = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
    at = f" at {Path(where.filename).name}:{where.lineno}" if where is not None else ""
    return f"internal error {type(exc).__name__}{at}: {text}"[:300]


def _analyse(task: LogTask, base: dict[str, Any]) -> list[dict[str, Any]]:
    from magcomp.adapters.config import load_config
    from magcomp.errors import InputError
    from magcomp.fleet.identity import scan_identity
    from magcomp.service import replay as replay_mod

    path = Path(task.path)
    ident = scan_identity(path)
    vehicle, how = ident.vehicle_id(path)
    base.update(
        format=ident.format,
        vehicle_detected=vehicle,
        vehicle=vehicle,
        identity_source=how,
        autopilot=ident.autopilot,
        firmware=ident.firmware,
        board=ident.board,
        board_uid=ident.board_uid,
        date_utc=ident.date_utc,
        date_source=ident.date_source,
    )
    cfg = load_config(task.config)
    diag = _diagnosis(task)
    # the excitation from the diagnosis's read of the log when there is one; else from the estimates
    exc_stats: _Excitation | LogDiagnosis = diag if isinstance(diag, LogDiagnosis) else _Excitation()
    on_estimate = exc_stats.add if isinstance(exc_stats, _Excitation) else None
    cpu0 = _cpu_s()
    rep = replay_mod.replay_log(path, cfg, two_pass=True, on_estimate=on_estimate)
    replay_cpu = _cpu_s() - cpu0  # the two-pass replay's (its worker threads' too), in cpu_s too
    if rep.interrupted:  # ^C: the replay kept a partial result; it must not become this log's row
        raise KeyboardInterrupt
    summary = rep.summary
    if not summary["counts"].get("mag"):
        raise InputError(f"{path.name}: no magnetometer messages in the log, nothing to correct")
    if ident.system_id < 0 and summary.get("system_id") is not None:
        ident.system_id = int(summary["system_id"])
        vehicle, how = ident.vehicle_id(path)
        base.update(vehicle_detected=vehicle, vehicle=vehicle, identity_source=how)
    base["system_id"] = ident.system_id
    earth = summary.get("earth_field") or {}
    ned = earth.get("ned_mgauss") or [math.nan] * 3
    earth_norm = math.sqrt(sum(float(v) ** 2 for v in ned))
    base.update(
        status="ok",
        error=None,
        duration_s=exc_stats.duration_s,
        flight_s=exc_stats.flight_s,
        throttle_min=exc_stats.throttle_min,
        throttle_max=exc_stats.throttle_max,
        earth_field_mgauss=earth_norm,
        earth_field_source=str(earth.get("source", "")),
        warnings=" | ".join(str(w) for w in summary.get("warnings", [])),
        onboard_motor_compensation=bool(summary.get("onboard_motor_compensation")),
        replay_cpu_s=replay_cpu,
    )
    rows = [_compass_row(base, c, earth_norm) for c in summary.get("compasses", [])]
    for r in rows:
        # which sensor the slot holds (a remounted / unplugged compass changes it): the vehicle's history
        # follows sensors, not slots (fleet.vehicles)
        r["compass_sensor"] = ident.compass_sensor(int(r["compass"]))
        if isinstance(diag, LogDiagnosis):
            r.update(diag.columns.get(r["compass"]) or failed_columns("diagnose left this compass out"))
        elif diag is not None:
            r.update(failed_columns(diag))
    return rows or [{**base, "status": "failed", "error": "no compass in the log"}]


def _diagnosis(task: LogTask) -> LogDiagnosis | str | None:
    """The log's diagnosis (fleet/diagnosed.py), its one-line failure, or None when not asked for."""
    if not task.diagnose:
        return None
    cpu0 = _cpu_s()
    try:
        diag = diagnose_columns(task.path, task.config)
    except Exception as exc:  # the replay's row stands without it
        return _one_line(exc)
    for cols in diag.columns.values():
        cols["diagnose_cpu_s"] = _cpu_s() - cpu0  # of the whole diagnosis (every compass), in cpu_s too
    return diag


def _f(value: Any) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return math.nan
    return out


def _compass_row(base: dict[str, Any], c: dict[str, Any], earth_norm: float) -> dict[str, Any]:
    inflight = c.get("inflight") or {}
    theta = [_f(v) for v in (c.get("theta_mgauss") or [math.nan] * 3)]
    sigma = [_f(v) for v in (inflight.get("theta_sigma_mgauss") or [math.nan] * 3)]
    cal = c.get("calibration") or {}
    d = cal.get("d_mgauss") or [math.nan] * 3
    norm = math.sqrt(sum(v * v for v in theta))
    # the delta method: sigma of |theta| from the per-axis sigmas
    norm_sigma = (
        math.sqrt(sum((v / norm * s) ** 2 for v, s in zip(theta, sigma, strict=True)))
        if norm > 0
        else math.nan
    )
    applied = c.get("status") == "corrected"
    check = c.get("self_check") or {}
    why = str(c.get("why") or "")
    if not applied and inflight.get("why_not_applied"):
        why = str(inflight["why_not_applied"])
    thr_max = _f(base.get("throttle_max"))
    # not applied: theta was not determined (the replay reports it as zero), so no interference either
    fraction = (norm / earth_norm if earth_norm > 0 else math.nan) if applied else math.nan
    row = {
        **base,
        "compass": int(c.get("index", -1)),
        "applied": applied,
        "why": why,
        "form": str(inflight.get("form") or ""),
        "theta_x_mgauss": theta[0],
        "theta_y_mgauss": theta[1],
        "theta_z_mgauss": theta[2],
        "theta_sigma_x_mgauss": sigma[0],
        "theta_sigma_y_mgauss": sigma[1],
        "theta_sigma_z_mgauss": sigma[2],
        "theta_norm_mgauss": norm,
        "theta_norm_sigma_mgauss": norm_sigma,
        "theta_converged": bool(c.get("theta_converged")),
        "heading_sigma_deg": _f(inflight.get("heading_sigma_deg")),
        # the self-check against the gyro and the autopilot's yaw (docs/real-flights.md): the autopilot's own
        # heading and the correction, rms deg, and the gain in standard errors
        "selfcheck_autopilot_gyro_deg": _f(check.get("baseline_gyro_deg")),
        "selfcheck_corrected_gyro_deg": _f(check.get("candidate_gyro_deg")),
        "selfcheck_autopilot_att_deg": _f(check.get("baseline_att_deg")),
        "selfcheck_corrected_att_deg": _f(check.get("candidate_att_deg")),
        "selfcheck_gain_sigma": _f(check.get("z")),
        "calibration_source": str(cal.get("source") or ""),
        "calibration_residual_mgauss": _f(cal.get("residual_rms_mgauss")),
        "offset_x_mgauss": _f(d[0]),
        "offset_y_mgauss": _f(d[1]),
        "offset_z_mgauss": _f(d[2]),
        "yaw_span_deg": _f(inflight.get("yaw_span_deg")),
        "throttle2_std": _f(inflight.get("throttle2_std")),
        # ArduPilot's compassmot: |motor bias at full throttle| / |Earth field| * 100 (eq. (11): theta * 1^2)
        "interference_pct": 100.0 * fraction,
        "interference_pct_sigma": 100.0 * fraction * norm_sigma / norm if norm > 0 else math.nan,
        # ... and at the highest throttle this flight reached
        "interference_flown_pct": 100.0 * fraction * thr_max**2 if math.isfinite(thr_max) else math.nan,
    }
    return row
