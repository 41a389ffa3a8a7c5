"""Per vehicle: each compass's theta flight after flight (with intervals), the persistent changes
(:mod:`magcomp.core.changes`), and the ranked list of vehicles to inspect.

A compass is a physical sensor, not a slot: the history follows the sensor (the row's ``compass_sensor``,
its device id, :mod:`magcomp.diagnosis.identity`) where the log names it, the slot index where no flight
does. An unplugged GPS compass moves the board's own sensor up to slot 0 (yladzislay's Pixhawk 1, sample-3):
by slot, that flight's theta would be compared with another sensor's and flagged as a change that is none.
A flight that does not name its sensor joins the one sensor the vehicle's other flights have in that slot
(said in the vehicle's notes, :func:`magcomp.diagnosis.identity.group_by_sensor`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np

from magcomp.core.changes import K_INTERVAL, Change, find_changes, level_after
from magcomp.core.pooling import PooledTrack, family_level, pooled_track
from magcomp.diagnosis.identity import group_by_sensor
from magcomp.fleet.discover import VehicleMap

_THETA = ("theta_x_mgauss", "theta_y_mgauss", "theta_z_mgauss")
_SIGMA = ("theta_sigma_x_mgauss", "theta_sigma_y_mgauss", "theta_sigma_z_mgauss")


@dataclass
class Flight:
    sha256: str
    file_name: str
    date_utc: datetime | None
    theta: list[float]
    sigma: list[float]
    heading_sigma_deg: float
    interference_pct: float


@dataclass
class CompassHistory:
    compass: int  # the slot of its latest flight
    flights: list[Flight]  # applied flights, in flight order
    not_applied: int
    changes: list[Change]
    level: list[float] | None  # since the last confirmed change
    level_sigma: list[float] | None
    sensor: str | None = None  # its device id (None: no flight names it; the history follows the slot)
    #: the vehicle's view of theta per flight: partially pooled between changes (:func:`theta_track`)
    track: PooledTrack | None = None

    @property
    def label(self) -> str:
        """``compass 0`` or ``compass 0 (sensor 131594)``."""
        return f"compass {self.compass}" + (f" (sensor {self.sensor})" if self.sensor else "")

    def change_rows(self) -> list[dict[str, Any]]:
        return [
            {
                "at_flight": c.index,
                "file_name": self.flights[c.index].file_name,
                "date_utc": _iso(self.flights[c.index].date_utc),
                "confirmed": c.confirmed,
                "size_mgauss": c.size,
                "z": c.z,
                "before_mgauss": c.before.mean.tolist(),
                "before_sigma_mgauss": c.before.std.tolist(),
                "after_mgauss": c.after.mean.tolist(),
                "after_sigma_mgauss": c.after.std.tolist(),
            }
            for c in self.changes
        ]

    def track_rows(self) -> list[dict[str, Any]]:
        """Per flight: diagnose's (or the replay's) theta and the pooled track's value with its interval."""
        t = self.track
        if t is None:
            return []
        return [
            {
                "file_name": f.file_name,
                "date_utc": _iso(f.date_utc),
                "flight_theta_mgauss": f.theta,
                "flight_sigma_mgauss": f.sigma,
                "theta_mgauss": t.mean[i].tolist(),
                "lower_mgauss": t.lower[i].tolist(),
                "upper_mgauss": t.upper[i].tolist(),
            }
            for i, f in enumerate(self.flights)
        ]


@dataclass
class Vehicle:
    vehicle: str
    identity_source: str
    autopilot: str
    firmware: str
    logs: int
    failed: int
    first_date: datetime | None
    last_date: datetime | None
    compasses: list[CompassHistory] = field(default_factory=list)
    onboard_comp_wrong: int = 0
    score: float = 0.0
    reasons: list[str] = field(default_factory=list)
    #: the compensation parameters to set (:func:`vehicle_params`), None when no flight gave any
    params: dict[str, Any] | None = None
    #: how the compasses were grouped where a reader should know (a slot holding another sensor)
    notes: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {
            "vehicle": self.vehicle,
            "identity_source": self.identity_source,
            "autopilot": self.autopilot,
            "firmware": self.firmware,
            "logs": self.logs,
            "failed": self.failed,
            "first_date": _iso(self.first_date),
            "last_date": _iso(self.last_date),
            "score": self.score,
            "reasons": self.reasons,
            "params": self.params,
            "notes": self.notes,
            "compasses": [
                {
                    "compass": h.compass,
                    "sensor": h.sensor,
                    "flights_applied": len(h.flights),
                    "flights_not_applied": h.not_applied,
                    "theta_mgauss": h.level,
                    "theta_sigma_mgauss": h.level_sigma,
                    "changes": h.change_rows(),
                    "track_family_level": TRACK_FAMILY_LEVEL,
                    "track_level_per_flight_axis": h.track.level if h.track else None,
                    "track_tau_mgauss": h.track.tau.tolist() if h.track else None,
                    "track": h.track_rows(),
                }
                for h in self.compasses
            ],
        }


def _iso(d: datetime | None) -> str | None:
    return d.isoformat() if d is not None else None


def _f(v: Any) -> float:
    return float(v) if v is not None else math.nan


#: 95 % two-sided normal quantile: diagnose's half-widths -> standard deviations
Z95 = 1.959964

#: The vehicle's theta track (:func:`theta_track`) holds the truth on every flight and axis of a compass's
#: history at once with at least this probability: a fleet manager sees a false "outside" on at most 1
#: vehicle in 20, however many flights each has (Bonferroni over the flights and the three axes).
TRACK_FAMILY_LEVEL = 0.95
#: The error that all flights of a segment share, which pooling cannot average away: per axis
#: hypot(TRACK_SYSTEMATIC_REL x |theta|, TRACK_SYSTEMATIC_ABS_MGAUSS). Measured on simulated fleets with
#: the truth known (benchmarks/fleet_changes.py seeds 0 and 1, docs/fleet.md): diagnose's theta carries a
#: bias that follows theta itself (~3 % of |theta| per axis, the same on every flight of a vehicle). Its
#: cause is diagnose's rotation (its tilt follows the autopilot's, which leans with the autopilot's
#: compass-driven yaw error when the vehicle accelerates; docs/diagnosis.md): kept until that is fixed.
TRACK_SYSTEMATIC_REL = 0.03
TRACK_SYSTEMATIC_ABS_MGAUSS = 1.0


def theta_track(x: np.ndarray, s: np.ndarray, changes: list[Change]) -> PooledTrack | None:
    """theta per flight as the vehicle sees it: between its changes (confirmed or pending) the flights share
    theta up to a small flight-to-flight variation, so each flight's value borrows strength from its
    siblings (:mod:`magcomp.core.pooling`: the variation estimated from the flights, its uncertainty kept;
    the shared systematic error added), at the level per flight and axis that makes the whole track hold
    at :data:`TRACK_FAMILY_LEVEL`."""
    if x.shape[0] == 0:
        return None
    return pooled_track(
        x,
        s,
        [c.index for c in changes],
        family_level(TRACK_FAMILY_LEVEL, x.shape[0], x.shape[1]),
        systematic_rel=TRACK_SYSTEMATIC_REL,
        systematic_abs=TRACK_SYSTEMATIC_ABS_MGAUSS,
    )


def summarise(
    rows: list[dict[str, Any]], vmap: VehicleMap | None = None, theta_from: str = "replay"
) -> list[Vehicle]:
    """The vehicles of the dataset's rows, ranked (most worth inspecting first). ``vmap`` re-maps the
    vehicles (a mapping file given after the logs were analysed). ``theta_from``: whose theta per flight the
    history and the changes follow: ``replay`` (the correction's theta and sigma, flights where it was
    applied) or ``diagnose`` (diagnose's theta, sigma = its 95 % half-width / 1.96, flights where it is
    identifiable)."""
    if theta_from not in ("replay", "diagnose"):
        raise ValueError(f"theta_from: replay or diagnose, not {theta_from!r}")
    if vmap is not None:
        for r in rows:
            name = vmap.vehicle(
                str(r.get("path") or ""), str(r.get("sha256") or ""), str(r.get("vehicle_detected") or "")
            )
            if name is not None:
                r["vehicle"], r["identity_source"] = name, "mapping file"
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(str(r.get("vehicle") or r.get("vehicle_detected") or "unknown"), []).append(r)
    out = [_vehicle(name, rs, theta_from) for name, rs in groups.items()]
    for v in out:
        _rank(v)
    out.sort(key=lambda v: (-v.score, v.vehicle))
    return out


def _order_key(r: dict[str, Any]) -> tuple[float, str]:
    d = r.get("date_utc")
    return (d.timestamp() if isinstance(d, datetime) else math.inf, str(r.get("path") or ""))


def _flight_theta(r: dict[str, Any], theta_from: str) -> tuple[list[float], list[float]] | None:
    """(theta, sigma) of a row's compass from ``theta_from`` (:func:`summarise`); None when it has none."""
    if theta_from == "diagnose":
        if not r.get("diagnose_theta_identifiable"):
            return None
        theta = [_f(r.get(f"diagnose_theta_{a}_mgauss")) for a in "xyz"]
        sigma = [_f(r.get(f"diagnose_theta_ci95_{a}_mgauss")) / Z95 for a in "xyz"]
    else:
        if not r.get("applied"):
            return None
        theta = [_f(r.get(k)) for k in _THETA]
        sigma = [_f(r.get(k)) for k in _SIGMA]
    good = all(math.isfinite(t) for t in theta) and all(math.isfinite(s) and s > 0 for s in sigma)
    return (theta, sigma) if good else None


def _vehicle(name: str, rows: list[dict[str, Any]], theta_from: str = "replay") -> Vehicle:
    rows = sorted(rows, key=_order_key)
    logs = {r["sha256"]: r for r in rows}
    failed = sum(1 for r in logs.values() if r.get("status") != "ok")
    dates = [r["date_utc"] for r in rows if isinstance(r.get("date_utc"), datetime)]
    ok = [r for r in rows if r.get("status") == "ok"]
    last = ok[-1] if ok else rows[-1]
    v = Vehicle(
        vehicle=name,
        identity_source=str(last.get("identity_source") or ""),
        autopilot=str(last.get("autopilot") or ""),
        firmware=str(last.get("firmware") or ""),
        logs=len(logs),
        failed=failed,
        first_date=min(dates) if dates else None,
        last_date=max(dates) if dates else None,
    )
    v.params = vehicle_params(ok)
    v.onboard_comp_wrong = len(
        {
            r["sha256"]
            for r in ok
            if "motor compensation" in str(r.get("warnings") or "")
            and "was wrong" in str(r.get("warnings") or "")
        }
    )
    groups, v.notes = sensor_groups(ok)
    for sensor, mine in groups:
        flights = []
        for r in mine:
            ts = _flight_theta(r, theta_from)
            if ts is not None:
                flights.append(
                    Flight(
                        str(r["sha256"]),
                        str(r.get("file_name") or ""),
                        r.get("date_utc"),
                        ts[0],
                        ts[1],
                        _f(r.get("heading_sigma_deg")),
                        _f(r.get("interference_pct")),
                    )
                )
        x = np.array([f.theta for f in flights], dtype=float).reshape(-1, 3)
        s = np.array([f.sigma for f in flights], dtype=float).reshape(-1, 3)
        changes = find_changes(x, s) if len(flights) >= 2 else []
        level = level_after(x, s, changes) if flights else None
        track = theta_track(x, s, changes)
        v.compasses.append(
            CompassHistory(
                int(mine[-1]["compass"]),
                flights,
                len(mine) - len(flights),
                changes,
                level.mean.tolist() if level is not None else None,
                level.std.tolist() if level is not None else None,
                sensor,
                track,
            )
        )
    return v


def _device_id(r: dict[str, Any]) -> int | None:
    s = r.get("compass_sensor")
    try:
        return int(str(s)) if s not in (None, "") else None
    except ValueError:
        return None


def sensor_groups(
    ok_rows: list[dict[str, Any]],
) -> tuple[list[tuple[str | None, list[dict[str, Any]]]], list[str]]:
    """The rows (in flight order) of each physical compass of one vehicle: (its sensor's device id, or None
    where no flight names it and the slot groups them; its rows), ordered by the slot of the latest flight;
    and the notes on the grouping (module docstring)."""
    rows = [r for r in ok_rows if r.get("compass") is not None]
    entries = [(str(r.get("file_name") or r.get("sha256")), int(r["compass"]), _device_id(r)) for r in rows]
    groups, notes = group_by_sensor(entries)
    out: list[tuple[str | None, list[dict[str, Any]]]] = []
    for key, positions in groups.items():
        sensor = key.removeprefix("sensor ") if key.startswith("sensor ") else None
        out.append((sensor, [rows[i] for i in positions]))
    out.sort(key=lambda g: (int(g[1][-1]["compass"]), g[0] or ""))
    return out, notes


def vehicle_params(ok_rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The compensation parameters ``magcomp diagnose`` would write for the vehicle's latest flight (rows in
    flight order) that has any: {"flight", "sha256", "autopilot", "values", "notes"}; the primary compass is
    the lowest index, as diagnose's default. A flight whose theta is not identifiable has none (diagnose
    writes none for it), so an older flight's may be the latest."""
    import json

    from magcomp.adapters.param_files import MAV_AUTOPILOT_PX4, compensation_params

    by_log: dict[str, list[dict[str, Any]]] = {}
    for r in ok_rows:
        by_log.setdefault(str(r["sha256"]), []).append(r)
    for sha in reversed(list(by_log)):  # dicts keep the flight order of ok_rows
        rows = [r for r in by_log[sha] if r.get("compass") is not None]
        sugg = [
            (int(r["compass"]), json.loads(r["diagnose_params_json"]))
            for r in rows
            if r.get("diagnose_params_json")
        ]
        if not sugg:
            continue
        px4 = str(rows[0].get("autopilot") or "") == "PX4"
        primary = min(int(r["compass"]) for r in rows)
        values, notes = compensation_params(sugg, primary, MAV_AUTOPILOT_PX4 if px4 else 3)
        if values:
            return {
                "flight": str(rows[0].get("file_name") or ""),
                "sha256": sha,
                "autopilot": "PX4" if px4 else "ArduPilot",
                "values": values,
                "notes": notes,
            }
    return None


def _rank(v: Vehicle) -> None:
    """A score to sort by (a heuristic, its parts given as reasons): a confirmed change 100, one pending 30,
    a wrong onboard compensation 50, the interference % of the latest theta, twice the worst heading
    uncertainty (deg) of the latest flight, 20 x the share of logs that failed."""
    score = 0.0
    reasons: list[str] = []
    for h in v.compasses:
        for c in h.changes:
            f = h.flights[c.index]
            if c.confirmed:
                score += 100.0
                reasons.append(f"{h.label}: theta changed by {c.size:.0f} mgauss at {f.file_name}")
            else:
                score += 30.0
                reasons.append(f"{h.label}: theta may have changed at {f.file_name} (not yet confirmed)")
        if h.flights:
            last = h.flights[-1]
            if math.isfinite(last.interference_pct):
                score += last.interference_pct
                if last.interference_pct >= 30.0:
                    reasons.append(
                        f"{h.label}: interference {last.interference_pct:.0f} % (ArduPilot wants < 30 %)"
                    )
            if math.isfinite(last.heading_sigma_deg):
                score += 2.0 * last.heading_sigma_deg
    if v.onboard_comp_wrong:
        score += 50.0
        reasons.append(f"the autopilot's own motor compensation was wrong in {v.onboard_comp_wrong} log(s)")
    if v.logs:
        score += 20.0 * v.failed / v.logs
        if v.failed:
            reasons.append(f"{v.failed} of {v.logs} logs failed")
    v.score = score
    v.reasons = reasons


def track_text(h: CompassHistory) -> str:
    """theta now: the track at the latest flight, ``(x, y, z) in [lo, hi] x [lo, hi] x [lo, hi]`` (without a
    track, the level since the last change +- 2 sigma)."""
    t = h.track
    if t is None:
        return interval_text(h.level, h.level_sigma)
    v = ", ".join(f"{a:.0f}" for a in t.mean[-1])
    box = " x ".join(f"[{lo:.0f}, {hi:.0f}]" for lo, hi in zip(t.lower[-1], t.upper[-1], strict=True))
    return f"({v}) in {box}"


def interval_text(theta: list[float] | None, sigma: list[float] | None) -> str:
    if theta is None or sigma is None:
        return "-"
    t = ", ".join(f"{a:.0f}" for a in theta)
    s = ", ".join(f"{K_INTERVAL * b:.0f}" for b in sigma)
    return f"({t}) +- ({s})"


_COMPASS_KEYS = (
    "compass", "compass_sensor", "flights_applied", "flights_not_applied", "theta_x_mgauss", "theta_y_mgauss",
    "theta_z_mgauss",
    "theta_sigma_x_mgauss", "theta_sigma_y_mgauss", "theta_sigma_z_mgauss", "changes_confirmed",
    "last_change_file", "last_change_date", "last_change_confirmed", "last_change_mgauss",
    # the track at the latest flight (the vehicle's theta now) and its band, TRACK_FAMILY_LEVEL over the track
    "track_theta_x_mgauss", "track_theta_y_mgauss", "track_theta_z_mgauss",
    "track_lower_x_mgauss", "track_lower_y_mgauss", "track_lower_z_mgauss",
    "track_upper_x_mgauss", "track_upper_y_mgauss", "track_upper_z_mgauss", "track_family_level",
)  # fmt: skip


def flat_rows(vehicles: list[Vehicle]) -> list[dict[str, Any]]:
    """One row per vehicle and compass (a vehicle without an applied theta: one row, compass None), in the
    inspect order: for ``OUT/vehicles.parquet``."""
    out: list[dict[str, Any]] = []
    for rank, v in enumerate(vehicles, 1):
        base = {
            "rank": rank,
            "vehicle": v.vehicle,
            "identity_source": v.identity_source,
            "autopilot": v.autopilot,
            "firmware": v.firmware,
            "logs": v.logs,
            "failed": v.failed,
            "first_date": v.first_date,
            "last_date": v.last_date,
            "score": v.score,
            "reasons": " | ".join(v.reasons),
            "params_from": v.params["flight"] if v.params else None,
            "params": ", ".join(f"{k}={val:g}" for k, val in v.params["values"].items())
            if v.params
            else None,
        }
        hist: list[CompassHistory | None] = [*v.compasses] or [None]
        for h in hist:
            row = dict(base)
            row.update(dict.fromkeys(_COMPASS_KEYS))
            if h is not None:
                confirmed = [c for c in h.changes if c.confirmed]
                last = h.changes[-1] if h.changes else None
                lvl = h.level or [math.nan] * 3
                sig = h.level_sigma or [math.nan] * 3
                row.update(
                    compass=h.compass,
                    compass_sensor=h.sensor,
                    flights_applied=len(h.flights),
                    flights_not_applied=h.not_applied,
                    theta_x_mgauss=lvl[0],
                    theta_y_mgauss=lvl[1],
                    theta_z_mgauss=lvl[2],
                    theta_sigma_x_mgauss=sig[0],
                    theta_sigma_y_mgauss=sig[1],
                    theta_sigma_z_mgauss=sig[2],
                    changes_confirmed=len(confirmed),
                    last_change_file=h.flights[last.index].file_name if last else None,
                    last_change_date=h.flights[last.index].date_utc if last else None,
                    last_change_confirmed=last.confirmed if last else None,
                    last_change_mgauss=last.size if last else None,
                )
                if h.track is not None:
                    t = h.track
                    for j, a in enumerate("xyz"):
                        row[f"track_theta_{a}_mgauss"] = float(t.mean[-1, j])
                        row[f"track_lower_{a}_mgauss"] = float(t.lower[-1, j])
                        row[f"track_upper_{a}_mgauss"] = float(t.upper[-1, j])
                    row["track_family_level"] = TRACK_FAMILY_LEVEL
            out.append(row)
    return out
